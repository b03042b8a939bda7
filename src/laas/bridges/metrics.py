"""A bridge's metrics: its devices and what became of their messages.

`watch_bridge` adds to a `Metrics` registry a collector that reads the bridge's
`PoolStats` when Prometheus scrapes, and its health checks (the bridge's thread runs;
ready while it is connected to the user-cluster broker):

- ``laas_bridge_devices``: devices held now, each an LDM participant of its own;
- ``laas_bridge_sessions_total{event}``: device sessions opened, devices forgotten
  after ``track_timeout`` of silence;
- ``laas_bridge_messages_total{outcome}``: fixes sent on, answered, refused by the
  service, lost (no reply), device messages that were not a fix (malformed), and fixes
  not newer than their device's last, dropped by the bridge (stale).

No label names a device: they are counted, never listed.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable

from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric
from prometheus_client.registry import Collector

from laas.bridges.pool import DevicePool
from ldm.ops.metrics import Check, Metrics

__all__ = ["BridgeCollector", "watch_bridge"]

_OUTCOMES = ("fixes", "answered", "refused", "lost", "malformed", "stale")


class BridgeCollector(Collector):
    """Reads a bridge's device pool at scrape time."""

    def __init__(self, pool: DevicePool) -> None:
        self._pool = pool

    def collect(self) -> Iterable[Metric]:
        s = self._pool.stats
        yield GaugeMetricFamily(
            "laas_bridge_devices", "Devices the bridge holds a participant for.", value=s.devices
        )
        devices = CounterMetricFamily(
            "laas_bridge_sessions",
            "Device sessions opened, and devices forgotten after track_timeout of silence.",
            labels=["event"],
        )
        devices.add_metric(["opened"], s.opened)
        devices.add_metric(["forgotten"], s.forgotten)
        yield devices
        messages = CounterMetricFamily(
            "laas_bridge_messages",
            "Device messages by outcome: fixes sent on, answered, refused by the service, "
            "lost without a reply, malformed (not a fix), and stale (not newer than the "
            "device's last fix, dropped by the bridge).",
            labels=["outcome"],
        )
        for outcome in _OUTCOMES:
            messages.add_metric([outcome], getattr(s, outcome))
        yield messages


def watch_bridge(
    metrics: Metrics,
    name: str,
    pool: DevicePool,
    *,
    alive: Callable[[], bool],
    connected: Callable[[], bool],
) -> None:
    """Expose a bridge: its pool's counters; healthy while `alive`, ready while
    `connected` (to the broker its devices speak to)."""
    metrics.add(BridgeCollector(pool))
    metrics.live.append(Check(f"{name}: running", alive))
    metrics.ready.append(Check(f"{name}: connected", connected))
