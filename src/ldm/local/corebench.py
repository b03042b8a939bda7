"""The LDM's own cost: two cores between participants and an echo provider.

    ldm bench core --participants 100 --rate 3 --duration 10

Three Mosquitto brokers (user, backbone, service), the user core and the service core
in this process, an echo provider in a child process (its reply is ``{"ok": 1}``:
no service work), and the participants in another child, every one sending on the
same tick (as GNSS receivers do). It prints how many inputs were answered, the round
trip, and the CPU seconds per 1,000 inputs of the process of both cores, of the
brokers and of the provider, read from the operating system's counters (/proc), so
the LDM's part of `laas bench` can be measured without the positioning engine.
"""

from __future__ import annotations

import math
import multiprocessing as mp
import os
import statistics
import time
from collections.abc import Callable
from concurrent.futures import Future, wait
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ldm.core import Core
from ldm.local.brokers import MosquittoBroker

__all__ = ["CoreBenchReport", "format_report", "run_core_bench"]

_TICKS = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100


def _cpu(pid: int) -> float:
    """User plus system CPU seconds of process `pid` so far (0 if it is gone)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return 0.0
    return (int(fields[11]) + int(fields[12])) / _TICKS


def _provider(url: str, ready: Any, stop: Any) -> None:
    from ldm import Provider, ServiceSpec

    provider = Provider.create(url, ServiceSpec(name="echo"), lambda _r: {"ok": 1})
    provider.start(timeout=10)
    ready.set()
    stop.wait()
    provider.stop()


def _participants(url: str, n: int, rate: float, seconds: float, out: Any, go: Any) -> None:
    from ldm import Participant

    clients = [Participant.create(url, client_id=f"bench-{i}").start(timeout=10) for i in range(n)]
    # The service core announces `echo` over the backbone after the provider is up;
    # a participant that asks before its list names it is refused (ServiceNotFound).
    deadline = time.time() + 30
    for p in clients:
        while not any(s.name == "echo" for s in p.services(10)):
            if time.time() > deadline:
                raise SystemExit("corebench: the user cluster never listed 'echo' within 30 s")
            time.sleep(0.05)
    sessions = [p.open("echo", timeout=10) for p in clients]
    out.put(("ready", 0))
    go.wait()
    sent: list[Future[Any]] = []
    trips: list[float] = []  # appended on the participants' threads as replies come

    def timed(at: float) -> Callable[[Future[Any]], None]:
        return lambda f: None if f.exception() else trips.append(time.time() - at)

    start = time.time()
    k = 0
    while time.time() - start < seconds:
        for s in sessions:
            future = s.submit({"k": k})
            future.add_done_callback(timed(time.time()))
            sent.append(future)
        k += 1
        time.sleep(max(0.0, start + k / rate - time.time()))
    wait(sent, timeout=10)
    out.put(("done", (len(sent), list(trips))))
    for p in clients:
        p.stop()


@dataclass(frozen=True)
class CoreBenchReport:
    """What one run of the core bench measured."""

    participants: int
    rate: float
    duration: float
    sent: int
    answered: int
    p50_ms: float
    """Round trip of the answered inputs, milliseconds."""
    p99_ms: float
    cpu_per_1000: dict[str, float]
    """CPU seconds per 1,000 inputs sent: ``cores`` (this process), ``brokers``,
    ``provider``."""
    batched: int
    """Envelopes the two cores forwarded in batches."""

    def as_dict(self) -> dict[str, Any]:
        return {
            "participants": self.participants,
            "rate": self.rate,
            "duration": self.duration,
            "sent": self.sent,
            "answered": self.answered,
            "p50_ms": self.p50_ms,
            "p99_ms": self.p99_ms,
            "cpu_per_1000": dict(self.cpu_per_1000),
            "batched": self.batched,
        }


def run_core_bench(participants: int, rate: float, duration: float) -> CoreBenchReport:
    """Run the load (see the module docstring); `ConnectError` without Mosquitto."""
    brokers = [MosquittoBroker().start() for _ in range(3)]
    user, backbone, service = (b.url for b in brokers)
    ctx = mp.get_context("spawn")
    ready, stop, go, out = ctx.Event(), ctx.Event(), ctx.Event(), ctx.Queue()
    provider = ctx.Process(target=_provider, args=(service, ready, stop))
    provider.start()
    ready.wait(30)
    cores = [
        Core.create("user", user, backbone).start(),
        Core.create("svc", service, backbone).start(),
    ]
    load = ctx.Process(target=_participants, args=(user, participants, rate, duration, out, go))
    load.start()
    try:
        out.get(timeout=120)  # sessions open
        pids = {
            "cores": [os.getpid()],
            "brokers": [b.pid or 0 for b in brokers],
            "provider": [provider.pid or 0],
        }
        before = {k: sum(_cpu(p) for p in v) for k, v in pids.items()}
        go.set()
        _, (sent, trips) = out.get(timeout=duration + 120)
        used = {k: sum(_cpu(p) for p in v) - before[k] for k, v in pids.items()}
        batched = sum(c.stats.batched for c in cores)
    finally:
        for core in cores:
            core.stop()
        stop.set()
        for process in (provider, load):
            process.join(10)
        for broker in brokers:
            broker.stop()
    ms = sorted(1000 * t for t in trips)
    k = 1000.0 / sent if sent else math.nan
    return CoreBenchReport(
        participants=participants,
        rate=rate,
        duration=duration,
        sent=sent,
        answered=len(trips),
        p50_ms=statistics.median(ms) if ms else math.nan,
        p99_ms=ms[int(0.99 * (len(ms) - 1))] if ms else math.nan,
        cpu_per_1000={name: seconds * k for name, seconds in used.items()},
        batched=batched,
    )


def format_report(report: CoreBenchReport) -> str:
    """The report as text, four lines."""
    r = report
    return "\n".join(
        [
            f"corebench: {r.participants} participants at {r.rate:g} Hz for {r.duration:g} s, "
            "all on the same tick, through 3 Mosquitto brokers, 2 cores and an echo provider",
            f"answered {r.answered}/{r.sent}; round trip p50 {r.p50_ms:.2f} ms, "
            f"p99 {r.p99_ms:.2f} ms",
            "CPU s per 1,000 inputs: "
            + ", ".join(f"{name} {seconds:.3f}" for name, seconds in r.cpu_per_1000.items()),
            f"envelopes forwarded in batches by the cores: {r.batched}",
        ]
    )
