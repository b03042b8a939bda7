"""The worker as a library: a worker process's whole life (`laas.worker.serve_worker`),
and the package that names its parts."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

import pytest

import laas.worker
from laas.map.bundled import bundled_map
from laas.map.hdmap import HdMap
from laas.run.deployment import LocalDeployment
from laas.run.participants import run_participants
from laas.sim.scenario import ErrorModel, hamburg_scenario, simulate
from laas.worker import ServeOptions, WorkerConfig, regions, serve_worker, service
from ldm import BrokerSettings, KeyPair, Participant
from ldm.local.brokers import start_broker, wait_for
from ldm.security.crypto import aad
from ldm.transport.mqtt import Event, Message, Transport
from ldm.wire.messages import Announcement, Envelope


def test_serve_worker_serves_a_region_and_says_what_it_did(
    hamburg_map: HdMap, tmp_path: Path
) -> None:
    """In place of a LocalDeployment's first regional worker, under its identity: the
    road users are answered by both regions, and the stop line counts them."""
    full = simulate(hamburg_map, hamburg_scenario(), ErrorModel(), 0)
    car = [f for f in full.fixes if f.user == "car"][:30]
    trace = type(full)(full.scenario, full.errors, full.seed, tuple(car))
    said: list[str] = []
    stop = threading.Event()
    with LocalDeployment(hamburg_map, brokers="embedded", regions=2) as d:
        watcher = Participant.create(d.user_url, **d.trust).start()

        def listed() -> bool:
            return any(s.name == "laas-1of2" for s in watcher.services(timeout=0.5))

        def until(done: Callable[[], bool]) -> None:
            deadline = time.monotonic() + 20
            while not done() and time.monotonic() < deadline:
                time.sleep(0.05)

        first, _ = d.workers.pop(0)
        first.stop()  # laas-1of2 withdraws; serve_worker takes its place
        until(lambda: not listed())
        key = tmp_path / "worker.key"
        d.identity.save(key)
        options = ServeOptions(
            cluster=BrokerSettings(url=d.brokers["service"].url),
            map=Path(bundled_map("messe-hamburg")),
            limits=WorkerConfig(max_speedup=100.0),
            region="1/2",
            identity=key,
        )
        result: list[laas.worker.WorkerStats] = []
        thread = threading.Thread(
            target=lambda: result.append(serve_worker(options, wait=stop.wait, say=said.append))
        )
        thread.start()
        until(listed)  # until the user cluster lists it, fixes in its region find no worker
        watcher.stop()
        live = run_participants(d.user_url, trace, speedup=20.0, **d.trust)
        stop.set()
        thread.join(10)
        other = d.workers[0][1].stats.answered
    assert live.answered == len(car), live.errors
    (stats,) = result
    assert stats.answered > 0 and stats.answered + other == len(car)
    assert said[0].startswith("laas worker: serving")
    assert d.identity.public in said[0]
    assert said[-1] == f"laas worker: stopped; {stats.answered} answered, 0 refused"


def test_the_worker_package_names_its_parts() -> None:
    assert laas.worker.LaasService is service.LaasService
    assert laas.worker.split is regions.split


def _delayed_input_answered(url: str, delay: float) -> bool:
    """Send the laas worker at `url` one input stamped `delay` s ago, sealed for its key,
    as a clustered broker delivers input after a node failure; True if it replied."""
    replies: list[Message] = []
    announced: list[Message] = []

    def sink(event: Event) -> None:
        if isinstance(event, Message):
            (announced if event.topic.endswith("/announce") else replies).append(event)

    spy = Transport(BrokerSettings(url=url), client_id="late-input", sink=sink)
    for flt in ("ldm/svc/laas/announce", "ldm/svc/laas/out", "ldm/svc/laas/out/+"):
        spy.subscribe(flt, 1)
    spy.start(5)
    try:
        deadline = time.monotonic() + 30
        while not any(m.payload for m in announced) and time.monotonic() < deadline:
            time.sleep(0.05)
        ann = Announcement.model_validate_json(next(m for m in announced if m.payload).payload)
        mine = KeyPair()
        cipher = mine.cipher(ann.service.public_key, initiator=True)

        def send(c: str, t: float) -> None:
            fix = {"timestamp": int(t * 1000), "latitude": 53.56, "longitude": 9.97}
            sealed = cipher.seal(json.dumps(fix).encode(), aad(c, t))
            env = Envelope(c=c, t=t, k=mine.public, d=sealed)
            spy.publish("ldm/svc/laas/in/pseudo-late", env.encode(), qos=1)

        def replied(c: str) -> bool:
            return any(c.encode() in m.payload for m in list(replies))

        # The late input, then a fresh one (the positive control): the worker takes one
        # pseudonym's input in order, so once the fresh one is answered, the late one
        # has been answered or dropped (no fixed wait).
        send("late-1", time.time() - delay)
        send("fresh-1", time.time())
        assert wait_for(lambda: replied("fresh-1"), 30), "the fresh input was not answered"
        return replied("late-1")
    finally:
        spy.stop()


@pytest.mark.parametrize(("max_age", "answered"), [(None, False), (10.0, True)])
def test_laas_worker_max_age_takes_input_delayed_by_a_failover(
    max_age: float | None, answered: bool
) -> None:
    """`laas worker --max-age 10` (a process) answers an input that arrives 5 s after it
    was sent, as inputs do while a NATS cluster elects new leaders; by default (2 s) the
    worker drops it as stale (issue 25: the worker had no --max-age)."""
    broker = start_broker("embedded")
    argv = [sys.executable, "-m", "laas.cli", "worker", "--cluster", broker.url]
    if max_age is not None:
        argv += ["--max-age", str(max_age)]
    node = subprocess.Popen(argv, stdout=subprocess.DEVNULL)
    try:
        assert _delayed_input_answered(broker.url, delay=5.0) is answered
    finally:
        node.send_signal(signal.SIGTERM)
        try:
            node.wait(30)
        except subprocess.TimeoutExpired:
            node.kill()
        broker.stop()
