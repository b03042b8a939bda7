"""Regional workers: one map split among workers, each fix routed by the participant."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from laas.config import EngineConfig
from laas.errors import ConfigError
from laas.evaluation.score import answer_trace, score
from laas.map.hdmap import HdMap
from laas.run.deployment import LocalDeployment
from laas.run.participants import run_participants
from laas.sim.scenario import hamburg_scenario, simulate
from laas.worker.regions import parse_region, split
from laas.worker.service import service_spec
from ldm import BrokerSettings
from ldm.client.routing import covers, depth
from ldm.local.brokers import BrokerKind
from ldm.local.pytest_plugin import broker_kind
from ldm.wire.messages import ServiceDescription

__all__ = ["broker_kind"]

CONFIG = EngineConfig(sigma_pos=1.0, sigma_vel=0.25, sigma_heading=0.05)


def _described(hamburg_map: HdMap, count: int) -> list[ServiceDescription]:
    return [
        ServiceDescription(**service_spec(r).model_dump(), public_key="A" * 43 + "=")
        for r in split(hamburg_map, count, overlap=50.0)
    ]


def test_the_regions_cover_the_map_once_and_overlap_at_their_borders(hamburg_map: HdMap) -> None:
    """Every point of the map lies in one region's coverage, or two within the overlap of
    a border; names and family are those of the laas family."""
    regions = _described(hamburg_map, 3)
    assert [d.name for d in regions] == ["laas-1of3", "laas-2of3", "laas-3of3"]
    assert {d.family for d in regions} == {"laas"}
    x0, y0, x1, y1 = hamburg_map.bounds
    rng = np.random.default_rng(1)
    width = (x1 - x0) / 3 if x1 - x0 >= y1 - y0 else (y1 - y0) / 3
    for x, y in zip(rng.uniform(x0, x1, 300), rng.uniform(y0, y1, 300), strict=True):
        where = hamburg_map.projection.to_wgs84(float(x), float(y))
        holders = [d.name for d in regions if covers(d, where)]
        assert 1 <= len(holders) <= 2, (x, y, holders)
        along = x - x0 if x1 - x0 >= y1 - y0 else y - y0
        near_border = min(abs(along - width), abs(along - 2 * width)) < 50.0
        assert len(holders) == 1 or near_border
    # the deepest coverage of a point is the region it lies in
    centre = hamburg_map.projection.to_wgs84((x0 + x1) / 2, (y0 + y1) / 2)
    assert max(regions, key=lambda d: depth(d, centre)).name == "laas-2of3"
    with pytest.raises(ConfigError, match="K/N"):
        parse_region("4/3")
    assert parse_region("2/3") == (1, 3)


def test_two_workers_split_hamburg_and_answer_users_across_the_border(hamburg_map: HdMap) -> None:
    """The Hamburg scenario through two regional workers: every fix is answered, each
    worker answers its share, the users who cross the border keep being answered, and
    lane accuracy is within 0.02 of one worker's (the offline replay, which a single
    live worker equals: tests/test_live.py)."""
    scenario = hamburg_scenario()
    trace = simulate(hamburg_map, scenario, scenario.errors, seed=4)
    offline = score(hamburg_map, trace, answer_trace(hamburg_map, trace, CONFIG))
    with LocalDeployment(hamburg_map, CONFIG, brokers="embedded", regions=2) as deployment:
        assert [p.name for p, _ in deployment.workers] == ["laas-1of2", "laas-2of2"]
        live = run_participants(deployment.user_url, trace, speedup=20.0, **deployment.trust)
        shares = [service.stats.answered for _, service in deployment.workers]
    assert live.errors == []
    assert live.answered == len(trace.fixes) == sum(shares)
    assert min(shares) > 0, shares
    # some road user's fixes lie on both sides: it was handed over and answered all along
    regions = split(hamburg_map, 2)
    along_x = regions[0].box[2] < regions[1].box[2]  # cut across x (else across y)
    k = 0 if along_x else 1
    border = (regions[0].box[2 + k] + regions[1].box[k]) / 2
    sides: dict[str, set[bool]] = {}
    for fix in trace.fixes:
        x, y = hamburg_map.projection.to_utm(fix.measurement.longitude, fix.measurement.latitude)
        sides.setdefault(fix.user, set()).add((x if along_x else y) > border)
    assert any(len(s) == 2 for s in sides.values()), "no user crosses the border"
    online = score(hamburg_map, trace, live.answers)
    print(
        f"\nregions: lane accuracy {online.accuracy:.3f} with two workers (answered "
        f"{shares[0]} + {shares[1]}), {offline.accuracy:.3f} with one"
    )
    assert abs(online.accuracy - offline.accuracy) <= 0.02, (online.accuracy, offline.accuracy)


def test_a_standby_takes_over_when_the_worker_dies(
    hamburg_map: HdMap, broker_kind: BrokerKind
) -> None:
    """A standby waits while the worker serves; the worker dies without a goodbye (its
    last will withdraws it), the standby starts under the same identity, and a road
    user sending a fix every 0.2 s is answered again, with no wrong answer; the fixes
    sent in between fail with an error that says why, none by a timeout."""
    import threading
    import time

    from laas.worker.service import start_worker
    from ldm import LdmError, Participant, RequestTimeout, RoutedSession
    from ldm.provider.standby import wait_until_vacant

    scenario = hamburg_scenario()
    trace = simulate(hamburg_map, scenario, scenario.errors, seed=4)
    car = [f.measurement for f in trace.fixes if f.user == trace.fixes[0].user]
    with LocalDeployment(hamburg_map, CONFIG, brokers=broker_kind) as deployment:
        url = deployment.brokers["service"].url
        took_over: list[object] = []

        def standby() -> None:
            if wait_until_vacant(url, "laas", quiet=60.0, stop=stopping):
                took_over.append(
                    start_worker(url, hamburg_map, CONFIG, identity=deployment.identity)
                )

        stopping = threading.Event()
        thread = threading.Thread(target=standby, daemon=True)
        thread.start()
        participant = Participant.create(deployment.user_url, **deployment.trust).start()
        routed = RoutedSession(participant, "laas")
        shift = int(time.time() * 1000) - car[0].timestamp
        answered: list[tuple[float, int]] = []  # (wall clock, fix index)
        failed: list[tuple[int, LdmError]] = []  # (fix index, why)
        killed_at = None
        try:
            for i, m in enumerate(car[:80]):
                fix = m.model_copy(update={"timestamp": m.timestamp + shift})
                try:
                    reply = routed.request(
                        fix.model_dump(exclude_none=True), (m.longitude, m.latitude), 10.0
                    )
                except LdmError as exc:  # anything else fails the test
                    failed.append((i, exc))
                    reply = {}
                if "segment" in reply:
                    assert reply["timestamp"] == fix.timestamp
                    answered.append((time.monotonic(), i))
                if i == 10:
                    assert not took_over, "the standby must wait while the worker serves"
                    provider, _ = deployment.workers.pop()
                    provider.kill()  # no goodbye: the broker publishes its last will
                    killed_at = time.monotonic()
                time.sleep(0.2)
                if took_over and len([a for a in answered if a[1] > 10]) >= 10:
                    break
        finally:
            stopping.set()
            participant.stop()
            for provider, _ in took_over:  # type: ignore[misc]
                provider.stop()
    assert killed_at is not None and took_over, "the standby never took over"
    after = [t for t, i in answered if i > 10]
    assert after, "no answer after the worker died"
    gap = after[0] - killed_at
    kinds = sorted({type(e).__name__ for _, e in failed})
    print(f"\nstandby: answers resumed {gap:.2f} s after the worker died; failed {kinds}")
    # The fixes sent between the kill and the standby's first answer fail with an error
    # that says why (the service is gone), none silently (a RequestTimeout), and none
    # after it: how soon answers resume is the printed figure (the README quotes it),
    # not a bound on a busy machine's clock.
    first = min(i for _, i in answered if i > 10)
    assert all(10 < i < first for i, _ in failed), failed
    assert not any(isinstance(e, RequestTimeout) for _, e in failed), failed


def test_child_processes_get_their_region_identity_and_ports() -> None:
    from laas.worker.processes import child_argv

    argv = ["--cluster", "mqtt://h:1", "--processes", "3", "--metrics-port=9000", "--http", "0"]
    child = child_argv(argv, 1, 3, Path("/k.pem"))
    assert child == [
        "--cluster",
        "mqtt://h:1",
        "--region",
        "2/3",
        "--identity",
        "/k.pem",
        "--metrics-port",
        "9001",
        "--http",
        "0",
    ]


def test_a_worker_node_serves_the_map_as_regions_in_processes(tmp_path: Path) -> None:
    """`laas worker --processes 2`: two child workers announce laas-1of2 and laas-2of2
    in the laas family under one identity, with coverages; on SIGTERM both withdraw."""
    import json
    import signal
    import subprocess
    import sys
    import time

    from ldm import EmbeddedBroker
    from ldm.local.brokers import wait_for
    from ldm.transport import Event, Message, Transport
    from ldm.wire.messages import Announcement

    broker = EmbeddedBroker(port=0).start()
    seen: dict[str, bytes] = {}

    def sink(event: Event) -> None:
        if isinstance(event, Message):
            seen[event.topic] = event.payload

    watcher = Transport(BrokerSettings.of(broker.url), client_id="watch", sink=sink)
    watcher.subscribe("ldm/svc/+/announce", 1)
    watcher.start(5)
    node = subprocess.Popen(
        [sys.executable, "-m", "laas.cli", "worker", "--cluster", broker.url, "--processes", "2"],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        names = ("laas-1of2", "laas-2of2")
        topics_ = [f"ldm/svc/{n}/announce" for n in names]
        assert wait_for(lambda: all(seen.get(t) for t in topics_), 60), seen.keys()
        anns = [Announcement.model_validate_json(seen[t]) for t in topics_]
        assert [a.service.name for a in anns] == list(names)
        assert {a.service.family for a in anns} == {"laas"}
        assert anns[0].service.identity == anns[1].service.identity is not None
        assert all(a.service.coverage for a in anns)
        node.send_signal(signal.SIGTERM)
        assert node.wait(30) == 0
        time.sleep(0.5)
        for t in topics_:  # withdrawn: the signed goodbye replaces the announcement
            assert "withdrawn" in json.loads(seen[t])
    finally:
        if node.poll() is None:
            node.kill()
        watcher.stop()
        broker.stop()


def test_a_missing_regional_worker_fails_only_the_fixes_of_its_region(
    hamburg_map: HdMap, tmp_path: Path
) -> None:
    """With the worker of region 2 gone, the simulator goes on: the fixes in region 1
    are answered, those in region 2 only are reported, and `laas simulate --out` writes
    the answers it got."""
    from laas.cli import main

    scenario = hamburg_scenario()
    trace = simulate(hamburg_map, scenario, scenario.errors, seed=4)
    with LocalDeployment(hamburg_map, CONFIG, brokers="embedded", regions=2) as deployment:
        deployment.workers[1][0].stop()  # laas-2of2 withdraws its announcement
        live = run_participants(deployment.user_url, trace, speedup=20.0, **deployment.trust)
        out = tmp_path / "answers.jsonl"
        trust = ["--service-key", deployment.trust["service_keys"]["laas"]]
        trust += ["--core-key", deployment.trust["core_key"]]
        args = ["simulate", "--cluster", deployment.user_url, "--speedup", "20"]
        code = main([*args, "--out", str(out), *trust])
    first = deployment.regions[0]
    assert first is not None
    inside = [
        covers(
            ServiceDescription(**service_spec(first).model_dump(), public_key="A" * 43 + "="),
            (f.measurement.longitude, f.measurement.latitude),
        )
        for f in trace.fixes
    ]
    assert 0 < live.answered < len(trace.fixes)
    assert all(inside[i] for i, a in enumerate(live.answers) if a is not None)
    assert len(live.errors) == len(trace.fixes) - live.answered
    assert any("no provider of 'laas' covers" in e for e in live.errors)
    assert code == 0
    assert 0 < len(out.read_text().splitlines()) < len(trace.fixes)


def test_a_user_crossing_the_border_keeps_its_track(hamburg_map: HdMap) -> None:
    """A car drives from region 1 into region 2 of two live regional workers. Past the
    border worker 1's answers carry its state sealed for the workers; the participant's
    RoutedSession hands the latest to worker 2 with its first fix there, and worker 2's
    first answer is what one worker gives (offline: `Engine`): the same lane, accuracy
    and probability (without the hand-over its lane probability is 0.12 lower). No broker
    message holds the hand-over in the clear or even its sealed text (the sessions
    encrypt it again), and a key other than the workers' cannot open it."""
    import time

    from laas.engine import Engine
    from laas.evaluation.regional import route_fixes
    from ldm import CryptoError, Participant, RoutedSession
    from ldm.security.crypto import region_cipher
    from ldm.security.identity import SigningKey
    from ldm.transport.mqtt import Event, Message, Transport

    scenario = hamburg_scenario()
    trace = simulate(hamburg_map, scenario, scenario.errors, seed=4)
    route = route_fixes(hamburg_map, trace, split(hamburg_map, 2))
    mine = [i for i, f in enumerate(trace.fixes) if f.user == "car"]
    cross = next(k for k in range(1, len(mine)) if route[mine[k]] != route[mine[k - 1]])
    car = [trace.fixes[i].measurement for i in mine[: cross + 1]]  # its first fix in 2
    one = Engine(hamburg_map, CONFIG)
    reference = [one.process("car", m) for m in car][-1]
    assert reference is not None
    seen: list[bytes] = []

    def sink(event: Event) -> None:
        if isinstance(event, Message):
            seen.append(event.payload)

    with LocalDeployment(hamburg_map, CONFIG, brokers="embedded", regions=2) as deployment:
        spies = []
        for name, broker in deployment.brokers.items():
            spy = Transport(BrokerSettings(url=broker.url), client_id=f"spy-{name}", sink=sink)
            spy.subscribe("#", 0)
            spy.start(timeout=5)
            spies.append(spy)
        participant = Participant.create(deployment.user_url, **deployment.trust).start()
        try:
            deadline = time.monotonic() + 10
            while len({s.name for s in participant.services()}) < 2:
                assert time.monotonic() < deadline, "the user cluster never listed both workers"
                time.sleep(0.05)
            routed = RoutedSession(participant, "laas")
            shift = int(time.time() * 1000) - car[0].timestamp
            replies = []
            for m in car:
                fix = m.model_copy(update={"timestamp": m.timestamp + shift})
                replies.append(
                    routed.request(fix.model_dump(exclude_none=True), (m.longitude, m.latitude), 5)
                )
            time.sleep(0.3)  # the spies' last messages
        finally:
            participant.stop()
            for spy in spies:
                spy.stop()
        stats = [service.stats for _, service in deployment.workers]
    assert routed.handovers == 1 and routed.current == "laas-2of2"
    first = replies[-1]  # worker 2's first answer
    assert "segment" in first, first
    assert (first["segment"], first["lane"]) == (reference.segment, reference.lane)
    assert first["accuracy"] == pytest.approx(reference.accuracy, rel=0.15)
    assert first["probability"] == pytest.approx(reference.probability, abs=0.05)
    assert stats[0].handed_out > 0 and stats[1].handed_in == 1, stats
    assert stats[1].handover_refused == 0
    tokens = [r["handover"] for r in replies if "handover" in r]
    assert tokens
    for payload in seen:
        assert b'"alpha"' not in payload and b'"lanes"' not in payload
        assert not any(t[:64].encode() in payload for t in tokens)
    with pytest.raises(CryptoError):
        region_cipher(SigningKey.generate(), "laas").open(tokens[-1], "laas-handover/1")
    print(
        f"\nhand-over: worker 2's first answer lane {first['lane']}, accuracy "
        f"{first['accuracy']:.2f} m (one worker {reference.accuracy:.2f} m), "
        f"{len(tokens)} sealed hand-overs of {len(tokens[-1])} characters"
    )
