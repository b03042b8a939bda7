"""`laas.Client` against a real deployment: brokers, both LDM cores and the workers.

A fix in, a `CorrectedPosition` out; every refusal an exception that says what to do;
regional workers reached by the fix's position; the session's silences after a change of
pseudonym answered by the client itself; settings from the commands' environment.
"""

from __future__ import annotations

import asyncio
import time
import tomllib
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

import laas
from laas import (
    AsyncClient,
    Client,
    ConfigError,
    CorrectedPosition,
    FixRefused,
    GpsMeasurement,
    HdMap,
    KeepingQuiet,
    MapError,
    NoAnswer,
    ServiceUnavailable,
    UntrustedService,
)
from laas.evaluation.regional import route_fixes
from laas.run.deployment import LocalDeployment
from laas.sim.scenario import hamburg_scenario, simulate
from laas.worker.regions import split
from ldm import RotationPolicy, SigningKey
from ldm.local.brokers import free_port


def car_fixes(hdmap: HdMap, seed: int = 4) -> list[GpsMeasurement]:
    """The Hamburg car's fixes, moved so that its last is dated now (spacing kept)."""
    scenario = hamburg_scenario()
    trace = simulate(hdmap, scenario, scenario.errors, seed=seed)
    fixes = [f.measurement for f in trace.fixes if f.user == "car"]
    shift = int(time.time() * 1000) - fixes[-1].timestamp
    return [f.model_copy(update={"timestamp": f.timestamp + shift}) for f in fixes]


def pins(deployment: LocalDeployment) -> dict[str, Any]:
    """The Client settings that pin the deployment's worker and user core."""
    return {
        "service_key": deployment.trust["service_keys"]["laas"],
        "core_key": deployment.trust["core_key"],
    }


def connect(deployment: LocalDeployment, **settings: Any) -> Client:
    """A client of the deployment's user cluster that pins its worker and user core."""
    return Client(deployment.user_url, **pins(deployment), **settings)


@pytest.fixture
def deployment(hamburg_map: HdMap) -> Iterator[LocalDeployment]:
    with LocalDeployment(hamburg_map) as running:
        yield running


def test_a_fix_in_a_corrected_position_out_and_refusals_raise(
    deployment: LocalDeployment, hamburg_map: HdMap
) -> None:
    car = car_fixes(hamburg_map)[-15:]
    with connect(deployment) as client:
        answers = [client.locate(fix) for fix in car]
        assert client.worker == "laas"
        last = car[-1]
        # dated a day ahead: the deployment's workers take simulations at up to 1000x
        # real time (SIMULATION_LIMITS), so 5 minutes ahead was refused only while the
        # session was younger than 0.3 s, and not on a loaded machine
        with pytest.raises(FixRefused) as ahead:
            client.locate(last.model_copy(update={"timestamp": last.timestamp + 86_400_000}))
        with pytest.raises(FixRefused) as again:  # not newer than the last fix taken
            client.locate(last)
        with pytest.raises(FixRefused) as off:  # 1 degree north: far off the map
            later = last.timestamp + 100
            client.locate(last.model_copy(update={"timestamp": later, "latitude": 54.56}))
        with pytest.raises(TypeError, match=r"give a laas\.GpsMeasurement"):
            client.locate(last.model_dump())  # type: ignore[arg-type]
    assert all(isinstance(a, CorrectedPosition) for a in answers)
    assert [a.timestamp for a in answers] == [f.timestamp for f in car]
    lanes = {(a.segment, a.lane, a.lane_type) for a in answers}
    assert all(segment is not None and kind == "driving" for segment, _, kind in lanes), lanes
    assert all(a.handover is None for a in answers)
    assert ahead.value.kind == "clock" and "NTP" in str(ahead.value)
    assert [f.field for f in ahead.value.fields] == ["timestamp"]
    assert again.value.kind == "stale" and "later timestamp" in str(again.value)
    assert off.value.kind == "outside" and "map" in str(off.value)
    assert isinstance(off.value, laas.LaasError)


def test_a_burst_over_the_cores_rate_is_refused_with_what_to_do(
    deployment: LocalDeployment, hamburg_map: HdMap
) -> None:
    """60 fixes at once against the user core's burst of 20: the first are answered, the
    rest raise ServiceUnavailable saying to send fewer, or NoAnswer where the core's notices
    ran out of their own budget."""
    last = car_fixes(hamburg_map)[-1]
    burst = [
        last.model_copy(update={"timestamp": last.timestamp - 600 + 10 * i}) for i in range(60)
    ]
    with connect(deployment) as client:
        client.locate(burst[0])  # the session is open: every later fix leaves at once
        futures = [client.submit(fix) for fix in burst[1:]]
        outcomes = [f.exception(timeout=10) or f.result() for f in futures]
    answered = [o for o in outcomes if isinstance(o, CorrectedPosition)]
    refused = [o for o in outcomes if isinstance(o, ServiceUnavailable)]
    unanswered = [o for o in outcomes if isinstance(o, NoAnswer)]
    assert len(answered) + len(refused) + len(unanswered) == len(outcomes), outcomes
    assert answered and refused, outcomes
    assert all("send fewer fixes a second" in str(r) for r in refused), refused[0]


def test_the_asyncio_client_gets_the_same_answers(
    deployment: LocalDeployment, hamburg_map: HdMap
) -> None:
    car = car_fixes(hamburg_map)[-5:]

    async def run() -> list[CorrectedPosition]:
        async with AsyncClient(deployment.user_url, **pins(deployment)) as client:
            return [await client.locate(fix) for fix in car]

    answers = asyncio.run(run())
    assert [a.timestamp for a in answers] == [f.timestamp for f in car]
    assert all(a.segment is not None for a in answers)


def test_a_client_crossing_a_border_is_handed_to_the_next_regional_worker(
    hamburg_map: HdMap,
) -> None:
    scenario = hamburg_scenario()
    trace = simulate(hamburg_map, scenario, scenario.errors, seed=4)
    route = route_fixes(hamburg_map, trace, split(hamburg_map, 2))
    regions = [route[i] for i, f in enumerate(trace.fixes) if f.user == "car"]
    assert len(set(regions)) == 2, "the car stays in one region"
    car = car_fixes(hamburg_map)
    workers = []
    with (
        LocalDeployment(hamburg_map, regions=2) as deployment,
        connect(deployment) as client,
    ):
        for fix in car:
            answer = client.locate(fix)
            assert answer.timestamp == fix.timestamp
            workers.append(client.worker)
        shares = [service.stats.answered for _, service in deployment.workers]
    assert set(workers) == {"laas-1of2", "laas-2of2"}
    assert shares[0] > 0 and shares[1] > 0 and sum(shares) == len(car)


def test_the_client_answers_itself_while_its_session_keeps_quiet(hamburg_map: HdMap) -> None:
    """Epochs of 2 s with silences of 0.3-0.8 s: every fix answered, some by the client,
    on the map's lanes (it holds the map), nearly all on the car's kind of lane."""
    policy = RotationPolicy(strategy="epoch", silence=0.3, silence_max=0.8)
    car = car_fixes(hamburg_map)[-60:]
    speedup = 10.0  # the deployment's workers allow simulators up to 1000 x
    with (
        LocalDeployment(hamburg_map, rotation_period=2.0, rotation=policy) as deployment,
        connect(deployment, hdmap=hamburg_map) as client,
    ):
        start, t0 = time.monotonic(), car[0].timestamp
        answers = []
        for fix in car:  # paced as the receiver gives them, sped up
            time.sleep(max(0.0, start + (fix.timestamp - t0) / 1000 / speedup - time.monotonic()))
            answers.append(client.locate(fix))
        rotations = deployment.cores["user"].stats.rotations
    assert rotations >= 1 and 0 < client.silent < len(car)
    assert [a.timestamp for a in answers] == [f.timestamp for f in car]
    assert all(a.segment is not None for a in answers)
    # a new pseudonym is a new track to the worker: its first answers may doubt the lane
    driving = sum(a.lane_type == "driving" for a in answers)
    assert driving >= 0.9 * len(answers), [a.lane_type for a in answers]


def test_a_quiet_session_with_nothing_to_go_on_says_when_to_send_again(
    hamburg_map: HdMap,
) -> None:
    """Fixes off the map are refused, so the client has no answer to dead-reckon from:
    once its session keeps quiet after a change of pseudonym, `locate` says so."""
    policy = RotationPolicy(strategy="epoch", silence=0.3, silence_max=0.8)
    off = car_fixes(hamburg_map)[-1].model_copy(update={"latitude": 54.56})
    with (
        LocalDeployment(hamburg_map, rotation_period=2.0, rotation=policy) as deployment,
        connect(deployment) as client,
    ):
        deadline = time.monotonic() + 10.0  # an epoch is 2 s
        while True:
            assert time.monotonic() < deadline, "the session never kept quiet"
            try:
                client.locate(off.model_copy(update={"timestamp": int(time.time() * 1000)}))
            except FixRefused as refused:
                assert refused.kind == "outside"
            except KeepingQuiet as quiet:
                assert "keeps quiet" in str(quiet) and "send again" in str(quiet)
                break
            time.sleep(0.05)  # a 20 Hz receiver
    assert client.silent == 0


def test_settings_come_from_the_commands_environment(
    monkeypatch: pytest.MonkeyPatch, deployment: LocalDeployment
) -> None:
    for name in ("CLUSTER", "USERNAME", "PASSWORD", "CA_FILE", "SERVICE_KEY", "CORE_KEY"):
        monkeypatch.delenv(f"LAAS_{name}", raising=False)
    with pytest.raises(ConfigError, match="set LAAS_CLUSTER"):
        Client.from_env()
    monkeypatch.setenv("LAAS_CLUSTER", deployment.user_url)
    monkeypatch.setenv("LAAS_USERNAME", "bike-42")
    with pytest.raises(ConfigError, match="LAAS_PASSWORD is not set"):
        Client.from_env()
    monkeypatch.delenv("LAAS_USERNAME")
    monkeypatch.setenv("LAAS_SERVICE_KEY", "not-a-key")
    with pytest.raises(ConfigError, match="not an Ed25519 public key"):
        Client.from_env()
    for name, value in pins(deployment).items():
        monkeypatch.setenv(f"LAAS_{name.upper()}", value)
    with Client.from_env() as client:
        assert client.locate(car_fixes(deployment.hdmap)[-1]).segment is not None
    # keys the worker and the core do not hold: the client refuses the service
    for name in ("LAAS_SERVICE_KEY", "LAAS_CORE_KEY"):
        monkeypatch.setenv(name, SigningKey.generate().public)
        with pytest.raises(UntrustedService, match=name):
            Client.from_env(timeout=1.0).start()
        monkeypatch.setenv(name, pins(deployment)[name[5:].lower()])
    # nothing listens on the port: the message says what to check
    monkeypatch.setenv("LAAS_CLUSTER", f"mqtt://127.0.0.1:{free_port()}")
    with pytest.raises(ServiceUnavailable, match="is the broker running"):
        Client.from_env(timeout=1.0).start()


def test_a_map_loads_by_name_or_file_and_the_version_is_the_projects(tmp_path: Path) -> None:
    hamburg = laas.load_map("messe-hamburg")
    assert "messe-0" in hamburg.segments
    assert set(laas.load_map(Path(hamburg.source)).segments) == set(hamburg.segments)
    with pytest.raises(MapError, match="not found"):
        laas.load_map("atlantis")
    with pytest.raises(MapError, match="no map file"):
        laas.load_map(tmp_path / "nothing.geojson")
    pyproject = tomllib.loads((Path(__file__).parents[1] / "pyproject.toml").read_text())
    assert laas.__version__ == pyproject["project"]["version"]
