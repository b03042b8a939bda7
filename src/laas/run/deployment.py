"""The paper's deployment (its Fig. 1) on one machine, for the demo, tests and the bench.

    participants -> user broker <- user core -> inter-cluster broker <- service core
                                                                  service broker <- laas worker

Three brokers (Mosquitto processes when `mosquitto` is installed, else the embedded
broker), two LDM cores and the worker, each with its own MQTT connections. The cores
run in this process; the worker too, or in a process of its own (`worker_process`).

Its workers serve simulations, so they let a session's timestamps run up to 1000 times
faster than real time (`WorkerConfig.max_speedup`; a `laas worker` allows only real
time unless told). The worker gets a fresh identity key; both cores and every
participant started with `trust` pin it, and participants pin the user core's key, so
no broker and no core can read a fix or answer in the worker's name (docs/security.md).
"""

from __future__ import annotations

import math
import multiprocessing as mp
import queue
import time
from pathlib import Path
from types import TracebackType
from typing import Any, Literal

from laas.config import EngineConfig
from laas.errors import ConfigError
from laas.map.geojson import read_geojson_file
from laas.map.hdmap import HdMap
from laas.worker.regions import Region, split
from laas.worker.service import LaasService, WorkerConfig, start_worker
from ldm import Core, Provider
from ldm.local.brokers import BrokerKind, RunningBroker, find_mosquitto, start_broker
from ldm.ops.metrics import Metrics, MetricsServer
from ldm.security.identity import SigningKey
from ldm.transport.hops import Hops
from ldm.wire.rotation import RotationPolicy

__all__ = ["SIMULATION_LIMITS", "BrokerChoice", "LocalDeployment"]

SIMULATION_LIMITS = WorkerConfig(max_speedup=1000.0)
"""The workers' limits by default: simulators sped up to 1000 times real time."""

BrokerChoice = Literal["auto", "embedded", "embedded-process", "mosquitto"]

WORKER_START_TIMEOUT = 60.0  # s for a worker process to load its map and connect


class LocalDeployment:
    """Start with `with LocalDeployment(hdmap) as d:`; participants connect to `d.user_url`.

    With `worker_process=True` the worker runs in a spawned process of its own, as in
    the field: its engine holds the GIL for milliseconds per fix, which would otherwise
    delay every core hop in this process (what `laas bench` measures). That process
    loads the map from `hdmap.source`, so the map must come from a file.
    """

    def __init__(
        self,
        hdmap: HdMap,
        config: EngineConfig | None = None,
        *,
        brokers: BrokerChoice = "auto",
        rotation_period: float = 120.0,
        rotation: RotationPolicy | None = None,
        data_qos: int = 0,
        worker_process: bool = False,
        hops: Hops | None = None,
        regions: int = 1,
        limits: WorkerConfig = SIMULATION_LIMITS,
        metrics_port: int | None = None,
        metrics_host: str = "127.0.0.1",
    ) -> None:
        if worker_process and not Path(hdmap.source).is_file():
            raise ConfigError(
                f"a worker process loads its map from a file; {hdmap.source!r} is not one"
            )
        self.hdmap = hdmap
        self.config = config
        self.limits = limits
        """The workers' limits on their input (`laas.worker.WorkerConfig`)."""
        self.metrics_port = metrics_port
        self.metrics_host = metrics_host
        self.metrics: Metrics | None = None
        """With `metrics_port`: one registry of both cores and the workers in this
        process, served at `metrics_url` (/metrics, /healthz, /readyz) while it runs."""
        self._metrics_server: MetricsServer | None = None
        self.kind: BrokerKind = (
            ("mosquitto" if find_mosquitto() else "embedded") if brokers == "auto" else brokers
        )
        self.rotation_period = rotation_period
        self.rotation = rotation or RotationPolicy()
        """The user core's rotation strategy (`ldm.wire.rotation`); the LDM's default if None."""
        self.data_qos = data_qos
        self.worker_process = worker_process
        self.brokers: dict[str, RunningBroker] = {}
        self.cores: dict[str, Core] = {}
        self.regions = split(hdmap, regions) if regions > 1 else [None]
        """The workers' regions (`laas.worker.regions`): one worker each; [None], one for all."""
        self.workers: list[tuple[Provider, LaasService]] = []  # in this process
        self.provider: Provider | None = None  # the first worker's, in this process
        self.service: LaasService | None = None
        self.identity = SigningKey.generate()
        """The laas worker's identity, pinned by the cores and by `trust`'s participants."""
        self.hops = hops
        """Where the cores and the worker note each input's passage (`ldm.transport.hops`)."""
        self._processes: list[_WorkerProcess] = []
        self._worker_answered = -1
        self.worker_cpu = math.nan
        """CPU seconds of the worker process while it served, known once it has stopped."""

    @property
    def user_url(self) -> str:
        return self.brokers["user"].url

    @property
    def trust(self) -> dict[str, Any]:
        """`ldm.ParticipantConfig` settings that pin the worker's and the user core's keys."""
        return {
            "service_keys": {"laas": self.identity.public},
            "core_key": self.cores["user"].public_key,
        }

    @property
    def worker_answered(self) -> int:
        """Fixes the worker answered; of a worker process, known once it has stopped (-1
        until then)."""
        if self.workers:
            return sum(service.stats.answered for _, service in self.workers)
        return self._worker_answered

    def start(self) -> LocalDeployment:
        try:
            for name in ("user", "backbone", "service"):
                self.brokers[name] = start_broker(self.kind)
            backbone = self.brokers["backbone"].url
            for name in ("user", "service"):
                self.cores[name] = Core.create(
                    name,
                    self.brokers[name].url,
                    backbone,
                    rotation_period=self.rotation_period,
                    rotation=self.rotation,
                    data_qos=self.data_qos,
                    service_keys={"laas": self.identity.public},
                )
                self.cores[name].hops = self.hops
                self.cores[name].start()
            url = self.brokers["service"].url
            for region in self.regions:
                if self.worker_process:
                    self._processes.append(
                        _WorkerProcess(
                            url,
                            self.hdmap,
                            self.config,
                            self.limits,
                            self.identity,
                            self.hops is not None,
                            region,
                        )
                    )
                else:
                    provider, service = start_worker(
                        url,
                        self.hdmap,
                        self.config,
                        self.limits,
                        identity=self.identity,
                        region=region,
                    )
                    provider.hops = self.hops
                    self.workers.append((provider, service))
            if self.workers:
                self.provider, self.service = self.workers[0]
                self._wait_listed([p.name for p, _ in self.workers])
            if self.metrics_port is not None:
                self._serve_metrics(self.metrics_port)
        except BaseException:
            self.stop()
            raise
        return self

    @property
    def metrics_url(self) -> str | None:
        """Where /metrics is served (`metrics_port`), while the deployment runs."""
        return None if self._metrics_server is None else self._metrics_server.url

    def _serve_metrics(self, port: int) -> None:
        """Both cores and the workers of this process in one registry, served on `port`
        (a worker process serves none: `laas worker --metrics-port` does)."""
        from laas.worker.metrics import watch_worker

        metrics = Metrics()
        for core in self.cores.values():
            metrics.watch_core(core)
        for provider, service in self.workers:
            watch_worker(metrics, provider, service)
        self.metrics = metrics
        self._metrics_server = metrics.serve(self.metrics_host, port)

    def stop(self) -> None:
        if self._metrics_server is not None:
            self._metrics_server.stop()
            self._metrics_server = None
        for provider, _ in self.workers:
            provider.stop()
        self.workers.clear()
        self.provider = None
        if self._processes:
            self._worker_answered, self.worker_cpu = 0, 0.0
        for process in self._processes:
            answered, cpu, marks = process.stop()
            self._worker_answered += answered
            self.worker_cpu += cpu
            if self.hops is not None and marks:
                self.hops.merge(marks)
        self._processes.clear()
        for core in self.cores.values():
            core.stop()
        self.cores.clear()
        for broker in self.brokers.values():
            broker.stop()
        self.brokers.clear()

    def _wait_listed(self, names: list[str], timeout: float = 10.0) -> None:
        """Wait until the user core lists every worker, so that a participant started
        now finds the worker of each region (not only the first announced)."""
        deadline = time.monotonic() + timeout
        while {s.name for s in self.cores["user"].services} < set(names):
            if time.monotonic() > deadline:
                raise TimeoutError(
                    f"the user core did not list the workers {names} within {timeout:g} s; "
                    "are the backbone and the service core running?"
                )
            time.sleep(0.02)

    def __enter__(self) -> LocalDeployment:
        return self.start()

    def __exit__(
        self,
        _type: type[BaseException] | None,
        _value: BaseException | None,
        _tb: TracebackType | None,
    ) -> None:
        self.stop()


class _WorkerProcess:
    """`laas worker` in a spawned child process, serving until `stop`."""

    def __init__(
        self,
        url: str,
        hdmap: HdMap,
        config: EngineConfig | None,
        limits: WorkerConfig,
        identity: SigningKey,
        hops: bool = False,
        region: Region | None = None,
    ) -> None:
        ctx = mp.get_context("spawn")
        self._ready, self._stop = ctx.Event(), ctx.Event()
        self._results: Any = ctx.Queue()
        pem = identity.to_pem()  # through the process pipe, never a file or a log
        self._process = ctx.Process(
            target=_serve,
            args=(
                url,
                hdmap.source,
                config,
                limits,
                pem,
                self._ready,
                self._stop,
                self._results,
                hops,
                region,
            ),
            name="laas-worker",
        )
        self._process.start()
        waited = 0.0
        while not self._ready.wait(0.5):
            waited += 0.5
            if not self._process.is_alive() or waited >= WORKER_START_TIMEOUT:
                self.stop()
                raise ConfigError(
                    f"the laas worker process did not start within {WORKER_START_TIMEOUT:.0f} s"
                    if waited >= WORKER_START_TIMEOUT
                    else f"the laas worker process exited (code {self._process.exitcode})"
                )

    def stop(self) -> tuple[int, float, dict[str, dict[str, float]]]:
        """Stop the worker: the fixes it answered (-1 if it did not say), its CPU seconds
        and its hop marks."""
        self._stop.set()
        try:
            answered, cpu, marks = self._results.get(timeout=15.0)
        except queue.Empty:
            answered, cpu, marks = -1, math.nan, {}
        self._process.join(15.0)
        if self._process.is_alive():
            self._process.kill()
            self._process.join(5.0)
        return int(answered), float(cpu), marks


def _serve(
    url: str,
    map_path: str,
    config: EngineConfig | None,
    limits: WorkerConfig,
    pem: bytes,
    ready: Any,
    stop: Any,
    results: Any,
    hops: bool,
    region: Region | None,
) -> None:
    """The worker process: serve until `stop` is set, then leave what it did."""
    identity = SigningKey.from_pem(pem)
    provider, service = start_worker(
        url, read_geojson_file(map_path), config, limits, identity=identity, region=region
    )
    if hops:
        provider.hops = Hops()
    cpu0 = time.process_time()
    ready.set()
    stop.wait()
    provider.stop()
    marks = provider.hops.marks if provider.hops is not None else {}
    results.put((service.stats.answered, time.process_time() - cpu0, marks))
