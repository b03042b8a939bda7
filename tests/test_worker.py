"""The worker as a library: a worker process's whole life (`laas.worker.serve_worker`),
and the old module names that still name its parts."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from pathlib import Path

import laas.asyncapi
import laas.metrics
import laas.regions
import laas.run.workers
import laas.service
import laas.worker
from laas.map.bundled import bundled_map
from laas.map.hdmap import HdMap
from laas.run.deployment import LocalDeployment
from laas.run.participants import run_participants
from laas.sim.scenario import ErrorModel, hamburg_scenario, simulate
from laas.worker import (
    ServeOptions,
    WorkerConfig,
    asyncapi,
    metrics,
    processes,
    regions,
    serve_worker,
    service,
)
from ldm import BrokerSettings, Participant


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


def test_the_old_module_names_name_the_workers_parts() -> None:
    for old, new in (
        (laas.service, service),
        (laas.metrics, metrics),
        (laas.regions, regions),
        (laas.asyncapi, asyncapi),
        (laas.run.workers, processes),
    ):
        assert old.__all__ == new.__all__
        assert all(getattr(old, name) is getattr(new, name) for name in new.__all__)
    assert laas.worker.LaasService is service.LaasService
