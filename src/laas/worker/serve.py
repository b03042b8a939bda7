"""Serving the worker: its whole life as one process of `laas worker`.

`serve_worker` loads the map, takes its region (``--region K/N``), waits as a standby
until the service or region is vacant, starts the worker (`start_worker`), shows it to
a metrics registry and serves its live map, waits until told to stop, stops, and
returns what it did. `laas worker` parses its arguments into a `ServeOptions`, starts
the metrics server and calls it; tests and other programs can call it as well.

It says what it does on `say` (`print` by default): the service it serves, its
identity (participants pin it), the live map's address, and at the end what it
answered and refused, by kind.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from laas.config import EngineConfig
from laas.errors import ConfigError
from laas.map.geojson import read_geojson_file
from laas.worker.service import SERVICE_NAME, WorkerConfig, WorkerStats, start_worker
from ldm import BrokerSettings
from ldm.ops.metrics import Metrics

__all__ = ["ServeOptions", "serve_worker"]


@dataclass(frozen=True)
class ServeOptions:
    """What one worker process serves, and how (the options of `laas worker`)."""

    cluster: BrokerSettings
    """The service-cluster broker."""
    map: Path
    engine: EngineConfig | None = None
    limits: WorkerConfig | None = None
    region: str | None = None
    """``K/N``: strip K of the map cut into N (`laas.worker.regions`); None, all of it."""
    overlap: float = 150.0
    standby: bool = False
    """Wait until the service (or region) is vacant, then serve under the same identity."""
    identity: Path | None = None
    endorsement: str | None = None
    data_qos: int | None = None
    max_age: float = 2.0
    """Input older than this (s) when its turn comes is dropped (`ProviderConfig.max_age`)."""
    http_port: int | None = None
    """Serve the live map on this port (0: a free one); None: no live map."""
    http_host: str = "127.0.0.1"


def _say(line: str) -> None:
    print(line, flush=True)


def serve_worker(
    options: ServeOptions,
    *,
    wait: Callable[[], object],
    metrics: Metrics | None = None,
    say: Callable[[str], None] = _say,
) -> WorkerStats:
    """Serve until `wait` returns (`ldm.ops.process.wait_for_signal` for a process); the
    worker's counters. `metrics`: a registry to show the worker to (its /metrics)."""
    from laas.worker.regions import parse_region, split

    hdmap = read_geojson_file(options.map)
    region = None
    if options.region is not None:
        k, count = parse_region(options.region)
        region = split(hdmap, count, overlap=options.overlap)[k]
    if options.standby:
        from ldm.provider.standby import wait_until_vacant

        if options.identity is None:
            raise ConfigError(
                "a standby serves under the active worker's identity: give --identity "
                "with the same key file"
            )
        name = SERVICE_NAME if region is None else region.name
        say(f"laas worker: standby for {name!r}, waiting until it is vacant")
        wait_until_vacant(options.cluster, name)
    provider, service = start_worker(
        options.cluster,
        hdmap,
        options.engine,
        options.limits,
        region=region,
        data_qos=options.data_qos,
        max_age=options.max_age,
        identity_file=options.identity,
        endorsement=options.endorsement,
    )
    if metrics is not None:
        from laas.worker.metrics import watch_worker

        watch_worker(metrics, provider, service)
    mode = "default" if options.engine is None else options.engine.mode
    say(
        f"laas worker: serving {len(hdmap.segments)} road elements of {options.map} "
        f"on {options.cluster.url} ({mode} mode); identity (participants pin it): "
        f"{provider.identity.public}"
    )
    live_map = None
    try:
        if options.http_port is not None:
            from laas.worker.dashboard import DashboardServer

            live_map = DashboardServer(
                service, provider, host=options.http_host, port=options.http_port
            )
            say(f"laas worker: live map on {live_map.url}")
        wait()
    finally:
        if live_map is not None:
            live_map.stop()
        provider.stop()
        say(f"laas worker: stopped; {service.stats.summary()}")
    return service.stats
