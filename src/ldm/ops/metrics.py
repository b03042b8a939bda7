"""Metrics and health checks for long-running LDM processes: /metrics, /healthz, /readyz.

    metrics = Metrics()                    # a registry of its own, with process metrics
    server = metrics.serve("0.0.0.0", 9464)  # before connecting: /readyz says 503
    metrics.watch_core(core)               # or watch_provider(provider)
    ...
    server.stop()

Nothing is counted twice: a collector reads the components' own counters (`CoreStats`,
`ProviderStats`, transports' lost connections) and gauges (queue depth, sessions,
pseudonyms) when Prometheus scrapes. Only latencies are observed as they happen, into
one histogram, ``ldm_stage_seconds{component, name, stage}``:

- a core: ``admit`` (a participant message at intake, paho's thread) and ``route``
  (one event on the core's dispatch thread);
- a provider: ``open`` (one input: envelope, decryption, JSON), ``seal`` (one reply)
  and ``step`` (one turn of its dispatch thread: an input, or a batch, open to publish).

Labels name a component (a core's or a service's name), a broker (``cluster`` or
``backbone``), an outcome, a reason or a stage: never a pseudonym, a participant id
or anything a participant sent.

/healthz answers 200 while every component's dispatch thread runs (else 503), /readyz
200 once every component is connected to each of its brokers (503 before anything is
watched); both with a JSON body naming each check.
"""

from __future__ import annotations

import json
import threading
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any

from prometheus_client import CollectorRegistry, Histogram
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric
from prometheus_client.exposition import choose_encoder
from prometheus_client.gc_collector import GCCollector
from prometheus_client.platform_collector import PlatformCollector
from prometheus_client.process_collector import ProcessCollector
from prometheus_client.registry import Collector

from ldm.core.core import Core
from ldm.errors import ConfigError
from ldm.provider.provider import Provider
from ldm.transport.mqtt import Transport

__all__ = [
    "CORE_COUNTERS",
    "CORE_OUTCOMES",
    "PROVIDER_COUNTERS",
    "PROVIDER_INPUTS",
    "STAGE_BUCKETS",
    "Check",
    "Metrics",
    "MetricsServer",
    "StageTimer",
]

StageTimer = Callable[[str, float], None]
"""Told (stage, seconds) each time a stage of a component ends."""

STAGE_BUCKETS = (
    0.00005,
    0.0001,
    0.00025,
    0.0005,
    0.001,
    0.0025,
    0.005,
    0.01,
    0.025,
    0.05,
    0.1,
    0.25,
    0.5,
    1.0,
    2.5,
)
"""Seconds: a core's hop takes tens of microseconds, an engine step milliseconds."""

CORE_OUTCOMES: dict[str, tuple[str, str]] = {
    "forwarded_in": ("forwarded", "in"),
    "forwarded_out": ("forwarded", "out"),
    "granted": ("granted", ""),
    "control": ("control", ""),
    "answered_nosession": ("answered", "nosession"),
    "answered_refused": ("answered", "refused"),
    "rejected_rate": ("rejected", "rate_limited"),
    "rejected_size": ("rejected", "too_large"),
    "rejected_clock": ("rejected", "clock"),
    "rejected_rekey": ("rejected", "rekey"),
    "rejected_unavailable": ("rejected", "unavailable"),
    "dropped_stale": ("dropped", "stale"),
    "dropped_unroutable": ("dropped", "unroutable"),
    "dropped_invalid": ("dropped", "invalid"),
    "dropped_overload": ("dropped", "overload"),
    "dropped_untrusted": ("dropped", "untrusted"),
    "dropped_elsewhere": ("dropped", "elsewhere"),
    "dropped_unauthentic": ("dropped", "unauthentic"),
    "dropped_retained": ("dropped", "retained"),
}
"""`CoreStats` field -> (outcome, reason) of ``ldm_core_messages_total``: every message
a core takes ends in exactly one of them."""

CORE_COUNTERS: dict[str, tuple[str, str]] = {
    "notices_suppressed": (
        "ldm_core_notices_suppressed",
        "Refusals not answered: the client's notice budget (10/s) was spent.",
    ),
    "rotations": ("ldm_core_rotations", "Pseudonyms replaced by a new one (rotation)."),
    "sessions_expired": ("ldm_core_sessions_expired", "Sessions dropped after idle_timeout."),
    "repaired_list": (
        "ldm_core_service_list_repairs",
        "Service lists on the cluster that were not this core's, replaced by its own.",
    ),
    "batches_sent": (
        "ldm_core_batches_sent",
        "Messages that carried more than one envelope to a provider or another core.",
    ),
    "batched": ("ldm_core_batched_envelopes", "Envelopes forwarded in those batches."),
}
"""The other `CoreStats` fields: field -> (counter name, help)."""

PROVIDER_INPUTS: dict[str, str] = {
    "requests": "accepted",
    "dropped_stale": "stale",
    "dropped_invalid": "invalid",
    "dropped_oversize": "oversize",
    "dropped_overload": "overload",
    "dropped_replay": "replay",
    "answered_again": "again",
}
"""`ProviderStats` field -> outcome of ``ldm_provider_inputs_total``."""

PROVIDER_COUNTERS: dict[str, tuple[str, str]] = {
    "replies": ("ldm_provider_replies", "Replies sealed and published."),
    "handler_errors": (
        "ldm_provider_handler_errors",
        "Inputs left without a reply: the handler raised, or its reply could not be sent.",
    ),
    "reply_batches": (
        "ldm_provider_reply_batches",
        "Messages that carried more than one reply.",
    ),
    "notes_sent": ("ldm_provider_notes_sent", "Family notes sent (Provider.note)."),
    "notes_taken": ("ldm_provider_notes_taken", "Family notes of the others taken."),
    "dropped_notes": (
        "ldm_provider_notes_dropped",
        "Family notes dropped: malformed, unauthentic, stale or replayed.",
    ),
}
"""The other `ProviderStats` fields: field -> (counter name, help)."""


@dataclass(frozen=True, slots=True)
class Check:
    """One health or readiness check: its name and a callable that says if it passes."""

    name: str
    passes: Callable[[], bool]


class Metrics:
    """A Prometheus registry of the components of one process, and their health checks.

    It holds the process collectors (CPU, memory, open files, GC), one collector
    that reads every watched core and provider at scrape time, any collector given
    to `add`, and the stage histogram.
    """

    def __init__(self) -> None:
        self.registry = CollectorRegistry()
        ProcessCollector(registry=self.registry)  # process_cpu_seconds_total, memory, fds
        PlatformCollector(registry=self.registry)  # python_info
        GCCollector(registry=self.registry)  # python_gc_*
        self.stages = Histogram(
            "ldm_stage_seconds",
            "Time spent in one stage of a component (see docs/operations.md).",
            ["component", "name", "stage"],
            registry=self.registry,
            buckets=STAGE_BUCKETS,
        )
        self.cores: list[Core] = []
        self.providers: list[Provider] = []
        self.live: list[Check] = []
        self.ready: list[Check] = []
        self._lock = threading.Lock()
        self.registry.register(_LdmCollector(self))

    def add(self, collector: Collector) -> None:
        """Register a further collector (a service's own metrics)."""
        self.registry.register(collector)

    def timer(self, component: str, name: str) -> StageTimer:
        """A `StageTimer` that observes into ``ldm_stage_seconds`` (thread-safe)."""
        children: dict[str, Any] = {}
        lock = threading.Lock()

        def observe(stage: str, seconds: float) -> None:
            child = children.get(stage)
            if child is None:
                with lock:
                    child = children.setdefault(
                        stage, self.stages.labels(component=component, name=name, stage=stage)
                    )
            child.observe(seconds)

        return observe

    def watch_core(self, core: Core) -> None:
        """Expose a core's counters and gauges, time its stages, check its brokers."""
        with self._lock:
            self.cores.append(core)
        core.timer = self.timer("core", core.name)
        self.live.append(Check(f"core {core.name}: dispatch thread", lambda: core.alive))
        for transport in (core.cluster, core.backbone):
            if transport is not None:
                self.ready.append(_connected(f"core {core.name}", transport.name, transport))

    def watch_provider(self, provider: Provider) -> None:
        """Expose a provider's counters and gauges, time its stages, check its broker."""
        with self._lock:
            self.providers.append(provider)
        provider.timer = self.timer("provider", provider.name)
        self.live.append(
            Check(f"provider {provider.name}: dispatch thread", lambda: provider.alive)
        )
        self.ready.append(_connected(f"provider {provider.name}", "cluster", provider.transport))

    def health(self) -> tuple[bool, dict[str, bool]]:
        """(every liveness check passes, each check's result)."""
        return _run(self.live, when_empty=True)

    def readiness(self) -> tuple[bool, dict[str, bool]]:
        """(every readiness check passes and there is one, each check's result)."""
        return _run(self.ready, when_empty=False)

    def serve(self, host: str = "127.0.0.1", port: int = 0) -> MetricsServer:
        """Serve /metrics, /healthz and /readyz on a thread; port 0 picks a free one."""
        return MetricsServer(self, host, port)


def _connected(who: str, broker: str, transport: Transport) -> Check:
    return Check(f"{who}: {broker} broker connected", lambda: transport.connected)


def _run(checks: list[Check], when_empty: bool) -> tuple[bool, dict[str, bool]]:
    results = {check.name: bool(check.passes()) for check in list(checks)}
    if not results:
        return when_empty, {"started": when_empty}
    return all(results.values()), results


class _LdmCollector(Collector):
    """Reads every watched core and provider when Prometheus scrapes."""

    def __init__(self, metrics: Metrics) -> None:
        self._metrics = metrics

    def collect(self) -> Iterable[Metric]:
        with self._metrics._lock:
            cores = list(self._metrics.cores)
            providers = list(self._metrics.providers)
        reconnects = CounterMetricFamily(
            "ldm_broker_reconnects",
            "Connections to a broker lost; each is followed by reconnecting with back-off.",
            labels=["component", "name", "broker"],
        )
        connected = GaugeMetricFamily(
            "ldm_broker_connected",
            "1 while the connection to the broker is up (acknowledged), else 0.",
            labels=["component", "name", "broker"],
        )
        for core in cores:
            for t in (core.cluster, core.backbone):
                if t is not None:
                    reconnects.add_metric(["core", core.name, t.name], t.disconnects)
                    connected.add_metric(["core", core.name, t.name], float(t.connected))
        for provider in providers:
            t = provider.transport
            reconnects.add_metric(["provider", provider.name, "cluster"], t.disconnects)
            connected.add_metric(["provider", provider.name, "cluster"], float(t.connected))
        yield reconnects
        yield connected
        yield from _core_metrics(cores)
        yield from _provider_metrics(providers)


def _core_metrics(cores: list[Core]) -> Iterator[Metric]:
    messages = CounterMetricFamily(
        "ldm_core_messages",
        "Messages a core took, by what became of them (outcome, and its reason or "
        "direction); rejected: a participant's message refused with a notice.",
        labels=["core", "outcome", "reason"],
    )
    counters = {
        field: CounterMetricFamily(name, text, labels=["core"])
        for field, (name, text) in CORE_COUNTERS.items()
    }
    gauges = {
        "sessions": GaugeMetricFamily(
            "ldm_core_sessions", "Participant sessions held.", labels=["core"]
        ),
        "pseudonyms": GaugeMetricFamily(
            "ldm_core_pseudonyms",
            "Live pseudonyms of this cluster's participants (current and in their grace).",
            labels=["core"],
        ),
        "routes": GaugeMetricFamily(
            "ldm_core_routes",
            "Pseudonyms of other clusters' participants whose replies this core routes.",
            labels=["core"],
        ),
        "services": GaugeMetricFamily(
            "ldm_core_services", "Services in this core's list.", labels=["core"]
        ),
        "queue": GaugeMetricFamily(
            "ldm_core_queue_depth",
            "Events waiting for the core's dispatch thread.",
            labels=["core"],
        ),
    }
    for core in cores:
        stats = core.stats
        for field, (outcome, reason) in CORE_OUTCOMES.items():
            messages.add_metric([core.name, outcome, reason], getattr(stats, field))
        for field, family in counters.items():
            family.add_metric([core.name], getattr(stats, field))
        gauges["sessions"].add_metric([core.name], core.session_count)
        gauges["pseudonyms"].add_metric([core.name], core.pseudonym_count)
        gauges["routes"].add_metric([core.name], core.route_count)
        gauges["services"].add_metric([core.name], len(core.services))
        gauges["queue"].add_metric([core.name], core.queued)
    yield messages
    yield from counters.values()
    yield from gauges.values()


def _provider_metrics(providers: list[Provider]) -> Iterator[Metric]:
    inputs = CounterMetricFamily(
        "ldm_provider_inputs",
        "Inputs a provider took, by outcome: accepted (handed to the service) or why "
        "it was dropped.",
        labels=["service", "outcome"],
    )
    counters = {
        field: CounterMetricFamily(name, text, labels=["service"])
        for field, (name, text) in PROVIDER_COUNTERS.items()
    }
    queue = GaugeMetricFamily(
        "ldm_provider_queue_depth",
        "Inputs waiting for the provider's dispatch thread.",
        labels=["service"],
    )
    ciphers = GaugeMetricFamily(
        "ldm_provider_session_ciphers",
        "Derived session ciphers cached (about one per live participant key).",
        labels=["service"],
    )
    for provider in providers:
        stats = provider.stats
        for field, outcome in PROVIDER_INPUTS.items():
            inputs.add_metric([provider.name, outcome], getattr(stats, field))
        for field, family in counters.items():
            family.add_metric([provider.name], getattr(stats, field))
        queue.add_metric([provider.name], provider.queued)
        ciphers.add_metric([provider.name], provider.cached_ciphers)
    yield inputs
    yield from counters.values()
    yield queue
    yield ciphers


class MetricsServer:
    """/metrics, /healthz and /readyz over HTTP on a daemon thread (`Metrics.serve`)."""

    def __init__(self, metrics: Metrics, host: str, port: int) -> None:
        try:
            self._server = _Server((host, port), _Handler)
        except (OSError, OverflowError) as exc:
            reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else exc
            raise ConfigError(
                f"cannot serve metrics on {host}:{port}: {reason}; choose "
                "another --metrics-port (0 picks a free one)"
            ) from None
        self._server.metrics = metrics
        self.host = host
        self.port: int = self._server.server_address[1]
        self._thread = threading.Thread(
            target=self._server.serve_forever, name="ldm-metrics", daemon=True
        )
        self._thread.start()

    @property
    def url(self) -> str:
        """Where /metrics is served (an address of 0.0.0.0 shown as 127.0.0.1)."""
        host = "127.0.0.1" if self.host in ("", "0.0.0.0") else self.host
        return f"http://{host}:{self.port}/metrics"

    def stop(self) -> None:
        self._server.shutdown()
        self._server.server_close()
        self._thread.join(5.0)


class _Server(ThreadingHTTPServer):
    daemon_threads = True
    metrics: Metrics


class _Handler(BaseHTTPRequestHandler):
    server: _Server

    def do_GET(self) -> None:
        path = self.path.split("?", 1)[0]
        metrics = self.server.metrics
        if path == "/metrics":
            encoder, content_type = choose_encoder(self.headers.get("Accept", ""))
            self._send(200, content_type, encoder(metrics.registry))
        elif path in ("/healthz", "/readyz"):
            ok, checks = metrics.health() if path == "/healthz" else metrics.readiness()
            body = json.dumps({"status": "ok" if ok else "failing", "checks": checks})
            self._send(200 if ok else 503, "application/json", body.encode() + b"\n")
        else:
            text = b"not found; try /metrics, /healthz or /readyz\n"
            self._send(404, "text/plain; charset=utf-8", text)

    def _send(self, code: int, content_type: str, body: bytes) -> None:
        self.send_response(code)
        self.send_header("Content-Type", content_type)
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, format: str, *args: Any) -> None:
        """No access log: Prometheus and health probes call every few seconds."""
