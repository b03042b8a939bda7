"""The LDM's own cost: two cores between participants and an echo provider.

    python -m ldm.local.corebench --participants 100 --rate 3 --duration 10

Three Mosquitto brokers (user, backbone, service), the user core and the service core
in this process, an echo provider in a child process (its reply is ``{"ok": 1}``:
no service work), and the participants in another child, every one sending on the
same tick (as GNSS receivers do). It prints how many inputs were answered, the round
trip, and the CPU seconds per 1,000 inputs of the process of both cores, of the
brokers and of the provider, read from the operating system's counters (/proc), so
the LDM's part of `laas bench` can be measured without the positioning engine.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import statistics
import time
from collections.abc import Callable
from concurrent.futures import Future, wait
from pathlib import Path
from typing import Any

from ldm.core import Core
from ldm.local.brokers import MosquittoBroker, find_mosquitto

__all__ = ["main", "run"]

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


def run(participants: int, rate: float, duration: float) -> str:
    """Run the load; the report as text."""
    if find_mosquitto() is None:
        raise SystemExit("corebench: mosquitto is not installed (apt-get install mosquitto)")
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
    p99 = ms[int(0.99 * (len(ms) - 1))] if ms else float("nan")
    k = 1000.0 / sent if sent else float("nan")
    return "\n".join(
        [
            f"corebench: {participants} participants at {rate:g} Hz for {duration:g} s, all on "
            "the same tick, through 3 Mosquitto brokers, 2 cores and an echo provider",
            f"answered {len(trips)}/{sent}; round trip p50 "
            f"{statistics.median(ms) if ms else float('nan'):.2f} ms, p99 {p99:.2f} ms",
            "CPU s per 1,000 inputs: "
            + ", ".join(f"{name} {seconds * k:.3f}" for name, seconds in used.items()),
            f"envelopes forwarded in batches by the cores: {batched}",
        ]
    )


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m ldm.local.corebench", description=__doc__)
    parser.add_argument("--participants", type=int, default=100)
    parser.add_argument("--rate", type=float, default=3.0, help="inputs per participant per s")
    parser.add_argument("--duration", type=float, default=10.0, help="seconds of load")
    a = parser.parse_args(argv)
    print(run(a.participants, a.rate, a.duration))


if __name__ == "__main__":
    main()
