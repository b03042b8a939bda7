"""Other participants' latency while one participant floods: ``ldm bench flood``.

    users process: N participants at HZ --+
                                          +--> user broker <- user core -> backbone broker
    flooder process: 1 participant,       |     (shipped       (this          ^
      RATE valid-looking inputs/s --------+      ACL)         process)        |
                                            service process: service core ----+
                                              + echo provider -> service broker

The three brokers are Mosquitto processes; the user broker runs the shipped ACL
(`ldm.local.brokers.mosquitto_acl`), unless ``--no-acl``. The user core runs in this
process, the service core with the echo provider in another (as in a deployment, where
each is a process or a container of its own), the users and the flooder in processes
of their own. One run has two phases of equal length: a baseline (the users alone),
then the flood (the flooder sends valid input of its own session, sealed and tagged
by the library, on its own input topic, at QoS 0, at ``--rate``). Latency is measured
per user request from just before ``Session.submit`` to the reply's arrival, and a
request counts in the phase it was sent in. The figure of merit is p99(flood) / p99(baseline);
the target of issue 11 is at most 2. Other load on the machine shows in the figures:
on a small shared machine, run it when the machine is otherwise idle, and more than
once.

Kept out of the test suite (it takes ``2 * phase`` seconds plus set-up);
``tests/ldm/test_intake.py`` checks the same property structurally and loosely.
"""

from __future__ import annotations

import math
import multiprocessing as mp
import os
import time
from concurrent.futures import Future, wait
from dataclasses import asdict, dataclass
from functools import partial
from multiprocessing.queues import Queue
from typing import Any

from ldm.client.participant import Participant
from ldm.config import BrokerSettings
from ldm.core.core import Core
from ldm.local.brokers import MosquittoBroker, mosquitto_acl, wait_for
from ldm.provider.provider import Provider, Request
from ldm.wire.messages import Envelope, ServiceSpec

__all__ = ["FloodReport", "PhaseFigures", "format_report", "run_flood_bench"]

_CORE_USER = "ldm-core"
_PROVIDER_USER = "svc-echo"
_ECHO = ServiceSpec(name="echo", version="1", description="Replies with what it was sent.")
_SETTLE = 3.0  # s after the flood phase for the last replies, at most
_FLOODER = "flooder"


@dataclass(frozen=True)
class PhaseFigures:
    """Latency of the users' requests sent in one phase (milliseconds)."""

    sent: int
    answered: int
    p50_ms: float
    p99_ms: float
    max_ms: float


@dataclass(frozen=True)
class FloodReport:
    baseline: PhaseFigures
    flood: PhaseFigures
    ratio: float
    """p99(flood) / p99(baseline)."""
    flood_sent: int
    flood_rate: float
    """Messages per second the flooder achieved."""
    flood_span: float
    """Seconds from the flood phase's start to when ``core`` was read: the longest the
    core's rate can have been admitting the flooder's messages (the broker may deliver
    them after the flooder stopped, on a busy machine)."""
    flooder_waiting: int
    """The most of the flooder's messages waiting in the user core's intake at once
    (sampled every 10 ms): the flood is refused before it queues."""
    queued: int
    """The most messages waiting in the user core's intake at once, anyone's."""
    load: tuple[float, float]
    """The machine's 1-minute load average at the start and the end of the phases:
    other work on the machine shows in the latencies."""
    core: dict[str, int]
    """The user core's counters at the end."""
    settings: dict[str, Any]


def _figures(samples: list[tuple[float, float | None]]) -> PhaseFigures:
    done = sorted(1000.0 * lat for _, lat in samples if lat is not None)
    if not done:
        return PhaseFigures(len(samples), 0, math.nan, math.nan, math.nan)

    def pct(q: float) -> float:
        return done[min(len(done) - 1, max(0, math.ceil(q * len(done)) - 1))]

    return PhaseFigures(len(samples), len(done), pct(0.5), pct(0.99), done[-1])


def _echo(request: Request) -> dict[str, Any]:
    return {"echo": request.payload}


# --- child processes ----------------------------------------------------------------


def _stamp(into: list[float], future: Future[Any]) -> None:
    """A done callback: the arrival time of a reply (nothing for a failed request)."""
    if future.exception() is None:
        into.append(time.perf_counter())


def _users(
    url: str, n: int, hz: float, phase: float, go: Any, start: Any, out: Queue[Any]
) -> None:  # pragma: no cover - runs in a child process
    """N participants submit at HZ each for two phases from the wall-clock time `start`
    holds once `go` is set; report [(sent wall time, latency or None)]."""
    parts = [Participant.create(url, client_id=f"user-{i}").start(timeout=10) for i in range(n)]
    try:
        assert wait_for(lambda: all(p.services(0.05) for p in parts), 10), "no service list"
        sessions = [p.open("echo", timeout=10) for p in parts]
        out.put(("users-ready", None))
        go.wait()
        records: list[tuple[float, float, list[float]]] = []
        futures: list[Future[Any]] = []
        period, end = 1.0 / hz, start.value + 2 * phase
        time.sleep(max(0.0, start.value - time.time()))
        base = time.perf_counter()
        k = 0
        while time.time() < end:
            delay = base + k * period / n - time.perf_counter()
            if delay > 0:
                time.sleep(delay)
            stamp: list[float] = []
            sent_wall, sent = time.time(), time.perf_counter()
            future = sessions[k % n].submit({"i": k})
            future.add_done_callback(partial(_stamp, stamp))
            records.append((sent_wall, sent, stamp))
            futures.append(future)
            k += 1
        wait(futures, timeout=_SETTLE)
        time.sleep(0.05)  # the last done callbacks
        out.put(("users", [(w, (s[0] - sent) if s else None) for w, sent, s in records]))
    finally:
        for p in parts:
            p.stop()


def _flooder(
    url: str, rate: float, phase: float, go: Any, start: Any, out: Queue[Any]
) -> None:  # pragma: no cover - runs in a child process
    """One participant with a real session floods its own input topic in the second
    phase with valid input: envelopes made by the library as any input is (sealed and
    tagged), 200 fresh ones every 0.2 s, each published again and again (the core's
    intake sees valid input; only the service would notice the replays). Making each
    anew would spend this machine's CPU on the attacker's side."""
    p = Participant.create(url, client_id=_FLOODER).start(timeout=10)
    try:
        assert wait_for(lambda: p.services(0.05), 10), "no service list"
        session = p.open("echo", timeout=10)
        pool: list[bytes] = []

        def keep(_session: Any, env: Envelope) -> bool:
            pool.append(env.encode())
            return True

        p.publish_input = keep  # type: ignore[method-assign,assignment]
        topic = session.grant.input_topic
        out.put(("flooder-ready", None))
        go.wait()
        time.sleep(max(0.0, start.value + phase - time.time()))
        end = start.value + 2 * phase
        sent, fresh = 0, 0.0
        began = time.perf_counter()
        while time.time() < end:
            if time.perf_counter() >= fresh:
                pool.clear()
                for i in range(200):
                    session.send({"flood": i})
                fresh = time.perf_counter() + 0.2
            delay = began + sent / rate - time.perf_counter()
            if delay > 0.002:
                time.sleep(delay)
            for _ in range(20):
                p.transport.publish(topic, pool[sent % len(pool)], 0)
                sent += 1
        elapsed = time.perf_counter() - began
        out.put(("flooder", (sent, sent / elapsed if elapsed > 0 else 0.0)))
    finally:
        p.stop()


def _service_side(
    service_url: str, backbone_url: str, done: Any, out: Queue[Any]
) -> None:  # pragma: no cover - runs in a child process
    """The service core and the echo provider, until `done` is set."""
    core = Core.create("service", service_url, backbone_url).start(timeout=10)
    provider = Provider.create(
        BrokerSettings(url=service_url, username=_PROVIDER_USER), _ECHO, _echo
    ).start(timeout=10)
    out.put(("service", None))
    try:
        done.wait()
    finally:
        provider.stop()
        core.stop()


# --- the run ------------------------------------------------------------------------


def run_flood_bench(
    *,
    participants: int = 4,
    hz: float = 5.0,
    rate: float = 6700.0,
    phase: float = 10.0,
    acl: bool = True,
    core_settings: dict[str, float] | None = None,
) -> FloodReport:
    """One run, baseline then flood; see the module docstring."""
    settings = dict(core_settings or {})
    ctx = mp.get_context("spawn")
    out: Queue[Any] = ctx.Queue()
    text = mosquitto_acl(_CORE_USER, {_PROVIDER_USER: "echo"}) if acl else None
    with (
        MosquittoBroker(acl=text) as user,
        MosquittoBroker() as backbone,
        MosquittoBroker() as service,
    ):
        as_core = BrokerSettings(url=user.url, username=_CORE_USER)
        user_core = Core.create("user", as_core, backbone.url, **settings).start(timeout=10)
        done = ctx.Event()
        side = ctx.Process(
            target=_service_side, args=(service.url, backbone.url, done, out), daemon=True
        )
        go, start = ctx.Event(), ctx.Value("d", 0.0)
        users = ctx.Process(
            target=_users, args=(user.url, participants, hz, phase, go, start, out), daemon=True
        )
        flooder = ctx.Process(
            target=_flooder, args=(user.url, rate, phase, go, start, out), daemon=True
        )
        children = (side, users, flooder)
        try:
            for child in children:
                child.start()
            results: dict[str, Any] = {}
            ready = {"service", "users-ready", "flooder-ready"}
            while not ready <= results.keys():
                kind, value = out.get(timeout=60)  # queue.Empty: a child failed to start
                results[kind] = value
            start.value = time.time() + 0.2
            flood_start, end = start.value + phase, start.value + 2 * phase
            go.set()
            waiting = queued = 0
            load = os.getloadavg()[0]
            while time.time() < end:  # the most waiting at once: the flooder's, all
                waiting = max(waiting, user_core._intake.waiting(_FLOODER))
                queued = max(queued, user_core._intake.qsize())
                time.sleep(0.01)
            while "users" not in results or "flooder" not in results:
                kind, value = out.get(timeout=_SETTLE + 30)
                results[kind] = value
            samples: list[tuple[float, float | None]] = results["users"]
            baseline = _figures([s for s in samples if s[0] < flood_start])
            flood = _figures([s for s in samples if s[0] >= flood_start])
            sent, achieved = results.get("flooder", (0, 0.0))
            core = asdict(user_core.stats)
            span = time.time() - flood_start
            return FloodReport(
                baseline=baseline,
                flood=flood,
                ratio=flood.p99_ms / baseline.p99_ms if baseline.p99_ms > 0 else math.nan,
                flood_sent=sent,
                flood_rate=achieved,
                flood_span=span,
                flooder_waiting=waiting,
                queued=queued,
                load=(load, os.getloadavg()[0]),
                core=core,
                settings={
                    "participants": participants,
                    "hz": hz,
                    "rate": rate,
                    "phase": phase,
                    "acl": acl,
                    "core_rate": user_core.config.rate,
                    "core_burst": user_core.config.burst,
                },
            )
        finally:
            done.set()
            for child in children:
                child.join(10)
                if child.is_alive():
                    child.terminate()
            user_core.stop()


def format_report(report: FloodReport) -> str:
    b, f, s = report.baseline, report.flood, report.settings
    lines = [
        f"flood bench: {s['participants']} users at {s['hz']:g} Hz, one flooder at "
        f"{report.flood_rate:,.0f} msg/s ({report.flood_sent:,} sent), Mosquitto "
        f"{'with' if s['acl'] else 'without'} the shipped ACL, core rate "
        f"{s['core_rate']:g}/s burst {s['core_burst']:g}, phases of {s['phase']:g} s",
        f"{'phase':<10}{'sent':>7}{'answered':>10}{'p50 ms':>9}{'p99 ms':>9}{'max ms':>9}",
    ]
    for name, x in (("baseline", b), ("flood", f)):
        lines.append(
            f"{name:<10}{x.sent:>7}{x.answered:>10}{x.p50_ms:>9.1f}{x.p99_ms:>9.1f}{x.max_ms:>9.1f}"
        )
    lines.append(f"p99 flood / baseline: {report.ratio:.2f} (target <= 2)")
    lines.append(
        f"waiting in the user core's intake at once: {report.flooder_waiting} of the "
        f"flooder's, {report.queued} in all; load average {report.load[0]:.1f} -> "
        f"{report.load[1]:.1f} on {os.cpu_count()} CPUs"
    )
    c = report.core
    keys = ("forwarded_in", "rejected_rate", "notices_suppressed", "dropped_overload")
    lines.append("user core: " + ", ".join(f"{k} {c.get(k, 0):,}" for k in keys))
    return "\n".join(lines)
