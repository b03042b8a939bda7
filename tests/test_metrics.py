"""Metrics and health endpoints of `ldm core` and `laas worker`, as child processes.

A core is live at once and ready only while connected; a three-broker deployment (two
cores, the worker) counts a participant's fixes, their refusals and a rejected message,
times each stage, and shows the engine's state, with no pseudonym or client id as a label.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import pytest
import yaml  # type: ignore[import-untyped]

from laas.engine.engine import EngineStats
from laas.map.hdmap import HdMap
from laas.worker.metrics import ENGINE_COUNTERS, FIX_OUTCOMES
from laas.worker.service import WorkerStats
from ldm import BrokerSettings, CoreStats, Participant, ProviderStats
from ldm.local.brokers import free_port
from ldm.local.embedded import EmbeddedBroker
from ldm.ops.metrics import CORE_COUNTERS, CORE_OUTCOMES, PROVIDER_COUNTERS, PROVIDER_INPUTS
from ldm.transport import Transport

from .operations import (
    LAAS,
    LDM,
    Child,
    Scrape,
    brokers,
    checks,
    get,
    hamburg_fixes,
    ready,
    wait_until,
)

FIXES = 12


def test_every_counter_of_the_components_is_exposed_once() -> None:
    """A new field in a stats class must be given a metric (or this fails)."""
    core = set(CORE_OUTCOMES) | set(CORE_COUNTERS)
    assert {f.name for f in dataclasses.fields(CoreStats)} == core
    assert not set(CORE_OUTCOMES) & set(CORE_COUNTERS)
    provider = set(PROVIDER_INPUTS) | set(PROVIDER_COUNTERS)
    assert {f.name for f in dataclasses.fields(ProviderStats)} == provider
    worker = set(FIX_OUTCOMES) | {"expired", "evicted", "engine_seconds"}
    worker |= {"handed_out", "handed_in", "handover_refused", "handover_skipped"}
    assert {f.name for f in dataclasses.fields(WorkerStats)} == worker
    assert set(ENGINE_COUNTERS) <= {f.name for f in dataclasses.fields(EngineStats)}


@pytest.mark.timeout(60)
def test_a_core_is_live_at_once_and_ready_only_while_connected(tmp_path: Path) -> None:
    port = free_port()
    core = Child(
        [
            *LDM,
            "core",
            "--name",
            "late",
            "--cluster",
            f"mqtt://127.0.0.1:{port}",
            "--metrics-port",
            "0",
        ],
        tmp_path / "core.log",
    )
    broker = EmbeddedBroker(port=port)
    try:
        base = core.metrics_base()  # served before the core connects
        # live as soon as its dispatch thread runs, a moment after the server is up (in
        # that moment, with nothing watched yet, it answers 200 {"started": true}: waiting
        # for any 200 raced the core's check being added, and failed on a loaded machine)
        live = (200, {"status": "ok", "checks": {"core late: dispatch thread": True}})
        wait_until(lambda: checks(base, "/healthz") == live, timeout=10.0)
        assert checks(base, "/readyz") == (
            503,
            {"status": "failing", "checks": {"core late: cluster broker connected": False}},
        )
        assert get(base + "/nothing")[0] == 404
        broker.start()
        wait_until(lambda: ready(base))
        before = Scrape(base)
        assert before.value("ldm_broker_connected", name="late", broker="cluster") == 1.0
        assert before.value("ldm_broker_reconnects_total", name="late") == 0.0
        broker.stop()  # the core loses its broker: not ready, and a reconnect is counted
        wait_until(lambda: not ready(base))
        assert checks(base, "/healthz")[0] == 200  # alive all the same
        lost = Scrape(base)
        assert lost.value("ldm_broker_reconnects_total", name="late", broker="cluster") == 1.0
        assert lost.value("ldm_broker_connected", name="late") == 0.0
        broker.start()  # the same port again
        wait_until(lambda: ready(base), timeout=20.0)
    finally:
        assert core.stop() == 0, core.log()
        broker.stop()


@pytest.mark.timeout(90)
def test_a_deployment_counts_fixes_refusals_and_stages(tmp_path: Path, hamburg_map: HdMap) -> None:
    with brokers(3) as (user, backbone, service):
        cores = {
            name: Child(
                [
                    *(*LDM, "core", "--name", name, "--cluster", broker.url),
                    *("--backbone", backbone.url, "--metrics-port", "0"),
                ],
                tmp_path / f"core-{name}.log",
            )
            for name, broker in (("user", user), ("service", service))
        }
        worker = Child(
            [*LAAS, "worker", "--cluster", service.url, "--metrics-port", "0"],
            tmp_path / "worker.log",
        )
        children = [*cores.values(), worker]
        try:
            bases = {name: child.metrics_base() for name, child in cores.items()}
            bases["worker"] = worker.metrics_base()
            for base in bases.values():
                wait_until(lambda base=base: ready(base), timeout=40.0)
            answers, refusals = _drive(user.url, hamburg_map)
            assert answers == FIXES and refusals == {"invalid": 1, "outside": 1}
            _reject_oversized(user.url)
            wait_until(
                lambda: (
                    Scrape(bases["user"]).value(
                        "ldm_core_messages_total", outcome="rejected", reason="too_large"
                    )
                    == 1.0
                )
            )
            _check_worker(Scrape(bases["worker"]))
            _check_cores(Scrape(bases["user"]), Scrape(bases["service"]))
            for base in bases.values():
                text = Scrape(base).text
                assert "metrics-car" not in text and "metrics-raw" not in text
        finally:
            for child in children:
                assert child.stop() == 0, child.log()


def _drive(user_url: str, hdmap: HdMap) -> tuple[int, dict[str, int]]:
    """A participant sends FIXES good fixes, one invalid and one outside the map."""
    answered = 0
    refusals: dict[str, int] = {}
    with Participant.create(user_url, client_id="metrics-car") as participant:
        wait_until(lambda: any(s.name == "laas" for s in participant.services(timeout=0.1)))
        session = participant.open("laas")
        fixes = [f.model_dump() for f in hamburg_fixes(hdmap, FIXES)]
        bad = [{"timestamp": "soon"}, {**fixes[-1], "latitude": 0.0, "longitude": 0.0}]
        for payload in [*fixes, *bad]:
            reply = session.request(payload, timeout=10.0)
            if "error" in reply:
                kind = reply["error"]["kind"]
                refusals[kind] = refusals.get(kind, 0) + 1
            else:
                answered += 1
    return answered, refusals


def _reject_oversized(user_url: str) -> None:
    """A client sends more than the core's max_payload (64 KiB) as input."""
    raw = Transport(BrokerSettings(url=user_url), client_id="metrics-raw", sink=lambda _e: None)
    raw.start(timeout=5)
    try:
        raw.publish_and_wait("ldm/p/metrics-raw/up/data/laas", b"x" * 70_000, qos=1)
    finally:
        raw.stop()


def _check_worker(m: Scrape) -> None:
    assert m.value("laas_fixes_total", outcome="answered") == FIXES
    assert m.value("laas_fixes_total", outcome="invalid") == 1
    assert m.value("laas_fixes_total", outcome="outside") == 1
    assert m.value("laas_fixes_total", outcome="stale") == 0
    assert m.value("ldm_provider_inputs_total", service="laas", outcome="accepted") == FIXES + 2
    assert m.value("ldm_provider_replies_total", service="laas") == FIXES + 2
    assert m.value("laas_pseudonyms") == 1 and m.value("laas_tracks") == 1
    assert m.value("laas_segment_groups") == 1
    assert m.value("laas_common_error_areas") >= 1
    across = m.value("laas_common_error_sigma_metres", area="0", axis="across")
    along = m.value("laas_common_error_sigma_metres", area="0", axis="along")
    assert 0 < across < along  # one straight road: b is learnt across it, not along
    assert m.value("laas_engine_seconds_total") > 0
    stage = "ldm_stage_seconds_count"
    for name in ("open", "seal", "step"):
        assert m.value(stage, component="provider", name="laas", stage=name) >= FIXES + 2
    engine_steps = m.value(stage, component="service", name="laas", stage="engine")
    assert 1 <= engine_steps <= FIXES
    assert m.value("ldm_broker_reconnects_total", name="laas") == 0
    assert m.value("ldm_provider_queue_depth", service="laas") == 0
    assert m.value("process_resident_memory_bytes") > 0


def _check_cores(user: Scrape, service: Scrape) -> None:
    sent = FIXES + 2
    for m, name in ((user, "user"), (service, "service")):
        assert (
            m.value("ldm_core_messages_total", core=name, outcome="forwarded", reason="in") >= sent
        )
        assert (
            m.value("ldm_core_messages_total", core=name, outcome="forwarded", reason="out") >= sent
        )
        assert m.value("ldm_stage_seconds_count", name=name, stage="route") >= sent
        assert m.value("ldm_broker_connected", name=name) == 2.0  # cluster and backbone
    assert user.value("ldm_core_messages_total", core="user", outcome="granted") >= 1
    assert user.value("ldm_stage_seconds_count", name="user", stage="admit") >= sent + 1
    assert user.value("ldm_core_sessions", core="user") == 1
    assert user.value("ldm_core_pseudonyms", core="user") == 1
    assert service.value("ldm_core_routes", core="service") == 1
    assert service.value("ldm_core_services", core="service") == 1
    # labels name cores, outcomes and stages: never a client id or a pseudonym
    allowed = {"core", "outcome", "reason", "component", "name", "broker", "stage", "le"}
    for m in (user, service):
        names = {k for k, _ in m.labels()}
        assert (
            names - {"generation", "implementation", "major", "minor", "patchlevel", "version"}
            <= allowed
        )


def test_the_scrape_config_covers_every_compose_service_with_metrics() -> None:
    root = Path(__file__).resolve().parents[1]
    services: dict[str, dict[str, Any]] = {}  # docker-compose.yml and its NATS override
    for file in ("docker-compose.yml", "docker-compose.cluster.yml"):
        for name, service in yaml.safe_load((root / file).read_text())["services"].items():
            services[name] = {**services.get(name, {}), **service}
    serving = {}
    for name, service in services.items():
        env = service.get("environment", {})
        port = env.get("LDM_METRICS_PORT") or env.get("LAAS_METRICS_PORT")
        if port is not None:
            assert str(port) in [str(p) for p in service.get("expose", [])], name
            serving[name] = f"{name}:{port}"
    cluster = {  # docker-compose.cluster.yml
        "core-service-cluster",
        "worker-1of2",
        "worker-2of2",
        "worker-1of2-standby",
        "worker-2of2-standby",
    }
    bridges = {"owntracks", "cam"}  # profile `bridges`
    assert set(serving) == {"core-user", "core-service", "worker", *cluster, *bridges}
    scrape = yaml.safe_load((root / "deploy" / "prometheus.yml").read_text())
    targets = {
        target
        for job in scrape["scrape_configs"]
        for group in job["static_configs"]
        for target in group["targets"]
    }
    assert targets == set(serving.values())


def test_a_local_deployment_serves_its_cores_and_workers_metrics(hamburg_map: HdMap) -> None:
    """`LocalDeployment(metrics_port=0)` (and so `laas demo --metrics-port`): one server
    for both cores and every worker of the process, ready while they are connected."""
    from laas.run.deployment import LocalDeployment
    from laas.run.participants import run_participants
    from laas.sim.scenario import ErrorModel, hamburg_scenario, simulate

    full = simulate(hamburg_map, hamburg_scenario(), ErrorModel(), 0)
    trace = dataclasses.replace(full, fixes=tuple(f for f in full.fixes if f.user == "car")[:10])
    with LocalDeployment(hamburg_map, brokers="embedded", regions=2, metrics_port=0) as d:
        base = d.metrics_url
        assert base is not None and base.startswith("http://127.0.0.1:")
        base = base.removesuffix("/metrics")
        assert ready(base)
        live = run_participants(d.user_url, trace, speedup=20.0, **d.trust)
        m = Scrape(base)
        assert live.answered == 10
        assert m.value("laas_fixes_total", outcome="answered") == 10
        assert {name for _, name in m.labels() if name.startswith("laas-")} >= {
            "laas-1of2",
            "laas-2of2",
        }
        assert m.value("ldm_core_messages_total") > 0
    assert d.metrics_url is None
    from laas.cli import build_parser

    demo = build_parser().parse_args(["demo", "--metrics-port", "0"])
    assert (demo.metrics_port, demo.metrics_host) == (0, "127.0.0.1")
