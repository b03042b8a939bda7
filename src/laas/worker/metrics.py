"""The LaaS worker's metrics, on top of the LDM's (`ldm.ops.metrics`).

`watch_worker` adds to a `Metrics` registry the provider under the worker (inputs,
replies, queue, stage timings) and a collector that reads, when Prometheus scrapes,
the worker's and its engine's counters and state:

- ``laas_fixes_total{outcome}``: answered, or refused as invalid, clock, outside,
  stale or internal (the `ErrorReply` kinds);
- live pseudonyms and tracks, road elements with users in them (segment groups), the
  common-error areas and, per area, its estimate and its 1-sigma across and along the
  road;
- ``ldm_stage_seconds{component="service", stage="engine"}``: time in the engine per
  worker step.

No label carries a pseudonym: areas are numbered in the order the engine made them.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric
from prometheus_client.registry import Collector

from laas.engine.engine import Engine
from laas.worker.service import LaasService
from ldm import Provider
from ldm.ops.metrics import Metrics

__all__ = ["ENGINE_COUNTERS", "FIX_OUTCOMES", "WorkerCollector", "watch_worker"]

FIX_OUTCOMES: dict[str, str] = {
    "answered": "answered",
    "invalid": "invalid",
    "clock": "clock",
    "outside": "outside",
    "refused": "stale",
    "failed": "internal",
}
"""`WorkerStats` field -> outcome of ``laas_fixes_total`` (the error reply's kind)."""

ENGINE_COUNTERS: dict[str, tuple[str, str]] = {
    "started": ("laas_tracks_started", "Tracks started (a pseudonym's first fix)."),
    "restarted": ("laas_tracks_restarted", "Tracks restarted after a gap or a jump."),
    "off_map": ("laas_answers_off_map", "Fixes answered off every road element."),
}
"""`EngineStats` field -> (counter name, help)."""


def watch_worker(metrics: Metrics, provider: Provider, service: LaasService) -> None:
    """Expose a running worker: its provider, its service and its engine."""
    service.timer = metrics.timer("service", provider.name)
    metrics.watch_provider(provider)
    metrics.add(WorkerCollector(service))


class WorkerCollector(Collector):
    """Reads a `LaasService` and its engine at scrape time (from the HTTP thread: only
    counters, lengths and arrays the worker replaces whole)."""

    def __init__(self, service: LaasService) -> None:
        self._service = service

    def collect(self) -> Iterable[Metric]:
        service = self._service
        engine = service.engine
        stats = service.stats
        fixes = CounterMetricFamily(
            "laas_fixes",
            "Fixes the worker handled, by outcome: answered, or the kind of its error reply.",
            labels=["outcome"],
        )
        for field, outcome in FIX_OUTCOMES.items():
            fixes.add_metric([outcome], getattr(stats, field))
        yield fixes
        forgotten = CounterMetricFamily(
            "laas_pseudonyms_forgotten",
            "Pseudonyms whose state was dropped: expired (track_timeout of silence) or "
            "evicted (max_pseudonyms held).",
            labels=["reason"],
        )
        forgotten.add_metric(["expired"], stats.expired)
        forgotten.add_metric(["evicted"], stats.evicted)
        yield forgotten
        handovers = CounterMetricFamily(
            "laas_handovers",
            "Regional hand-overs: answers that carried a user's state out, states taken in, "
            "refused (could not be opened or read), skipped (too large to hand over).",
            labels=["way"],
        )
        for way in ("out", "in", "refused", "skipped"):
            field = {"out": "handed_out", "in": "handed_in"}.get(way, f"handover_{way}")
            handovers.add_metric([way], getattr(stats, field))
        yield handovers
        yield CounterMetricFamily(
            "laas_engine_seconds",
            "Time spent in the engine, all fixes together.",
            value=stats.engine_seconds,
        )
        for field, (name, text) in ENGINE_COUNTERS.items():
            yield CounterMetricFamily(name, text, value=getattr(engine.stats, field))
        yield GaugeMetricFamily(
            "laas_pseudonyms", "Live pseudonyms the worker holds state for.", value=service.sessions
        )
        yield GaugeMetricFamily("laas_tracks", "Live Kalman tracks.", value=engine.users)
        yield GaugeMetricFamily(
            "laas_segment_groups",
            "Road elements with users in the lane filter (one group each).",
            value=engine.segment_groups(),
        )
        yield from _common_errors(engine)


def _common_errors(engine: Engine) -> Iterable[Metric]:
    areas = engine.common_errors()
    yield GaugeMetricFamily(
        "laas_common_error_areas",
        "Areas with a common-error estimate of their own (default mode).",
        value=len(areas),
    )
    sigma = GaugeMetricFamily(
        "laas_common_error_sigma_metres",
        "1-sigma of an area's common-error estimate: across = its best-known direction "
        "(across the roads driven there), along = its worst-known (along them).",
        labels=["area", "axis"],
    )
    estimate = GaugeMetricFamily(
        "laas_common_error_metres",
        "An area's common GNSS error estimate, east and north (UTM grid).",
        labels=["area", "axis"],
    )
    for i, area in enumerate(areas):
        b, cov = area.b, area.P  # replaced whole by the worker, never changed in place
        # cov = V diag(l) V^T: the smaller eigenvalue is the variance across the road
        low, high = np.sqrt(np.clip(np.linalg.eigvalsh(cov), 0.0, None))
        sigma.add_metric([str(i), "across"], float(low))
        sigma.add_metric([str(i), "along"], float(high))
        estimate.add_metric([str(i), "east"], float(b[0]))
        estimate.add_metric([str(i), "north"], float(b[1]))
    yield sigma
    yield estimate
