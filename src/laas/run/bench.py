"""`laas bench`: latency, throughput and the cost of privacy through the full topology.

    participant processes --> user broker <- user core -> backbone broker <- service core
      (N LDM participants,        ^                                service broker <- worker
       R Hz each, T seconds)      |
                                  +-- echo process (the bare MQTT floor)

The brokers are Mosquitto processes (or the embedded broker, each in a child process),
the two cores share this process, the laas worker has a process of its own (a
`laas.run.deployment.LocalDeployment` with `worker_process`), and the participants run
in worker processes, each participant a real `ldm.Participant` with its own connection.
They drive simulated road users along the Hamburg road (`laas.sim.scenario`), with the
fixes' timestamps shifted to the wall clock. By default every user's fixes fall on the
whole second, as GNSS receivers emit them (so the load comes in a burst each second);
`spread` gives each user a random phase within the period instead.

Each participant process holds its participants on one shared client loop
(`laas.run.loadgen.paced_sessions`, `ldm.transport.ClientLoop`): no network thread per
connection, and connections opened at `connect_rate` per second in all. Before, each
participant had paho's threaded loop, whose ``select()`` fails for descriptors of 1024
and more; with three descriptors per client a process held at most about 340, and at
800 participants in two processes the 340th connection of each timed out.

Latency is measured where it is felt: from just before `Session.submit` (JSON,
encryption and publish included) to the moment the decrypted reply reaches the
participant, on one clock in one process.

The floor, in the same run on the same user broker: each participant process has one
plain MQTT client (`ldm.transport.Transport`) that publishes a ping beside every fourth
fix; the echo process takes it off its queue on a dispatch thread (the hand-off every LDM
component makes) and publishes it back. The LDM overhead is p50(LDM) / p50(bare).

The cost of privacy: the Hamburg scenario (`laas.sim.scenario.hamburg_scenario`) runs
through fresh deployments twice, with pseudonyms rotating every `rotation_period`
seconds of scenario time and with rotation off, and both are scored against the truth.
"""

from __future__ import annotations

import math
import multiprocessing as mp
import os
import queue
import secrets
import threading
import time
from collections.abc import Callable, Sequence
from contextlib import ExitStack
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Literal

import numpy as np

from laas.errors import ConfigError
from laas.evaluation.score import score
from laas.map.geojson import read_geojson_file
from laas.map.hdmap import HdMap
from laas.run.deployment import BrokerChoice, LocalDeployment
from laas.run.loadgen import paced_sessions
from laas.run.participants import (
    Request,
    collect_replies,
    run_participants,
    submit_on_time,
)
from laas.run.profile import Profile, Recorder, format_profiles, profiles
from laas.sim.scenario import (
    EPOCH_MS,
    ErrorModel,
    Scenario,
    Trace,
    UserPlan,
    hamburg_scenario,
    simulate,
)
from ldm import BrokerSettings, RoutedSession, Session
from ldm.local.brokers import find_mosquitto
from ldm.transport import Event, Message, Transport
from ldm.transport.hops import Hops

__all__ = [
    "STAGES",
    "BenchConfig",
    "BenchReport",
    "Latency",
    "PrivacyRun",
    "bench_scenario",
    "format_loads",
    "format_report",
    "run_bench",
    "run_loads",
]

ROTATION_OFF = 1e9  # s: longer than any run
_PING_EVERY = 4  # one bare ping beside every fourth fix
_PING = "bench/bare/{shard}/ping"
_PONG = "bench/bare/{shard}/pong"

Progress = Callable[[str], None]


@dataclass(frozen=True)
class BenchConfig:
    """What to run: N participants at R Hz for T seconds on a kind of broker."""

    participants: int = 200
    rate: float = 1.0
    duration: float = 30.0
    brokers: BrokerChoice = "auto"
    rotation_period: float = 120.0
    processes: int | None = None  # participant processes; default: 2 to 4 by cores
    seed: int = 0
    privacy_speedup: float = 20.0  # the Hamburg runs, faster than real time by
    reply_timeout: float = 5.0
    connect_rate: float = 200.0  # new connections per second, over all processes
    spread: bool = False  # fixes spread over the second, not all on the whole second
    privacy: bool = True  # the two Hamburg runs after the load (the cost of privacy)
    workers: int = 1  # worker processes, each serving a region of the map (laas.worker.regions)
    profile: str | None = None  # a folder: py-spy profiles of each process over the load

    def __post_init__(self) -> None:
        if self.participants < 1:
            raise ConfigError("--participants must be at least 1")
        if not (0.0 < self.rate <= 50.0):
            raise ConfigError("--rate must be in (0, 50] Hz")
        if self.duration <= 0.0:
            raise ConfigError("--duration must be positive")
        if self.rotation_period <= 0.0:
            raise ConfigError("--rotation-period must be positive")
        if self.processes is not None and self.processes < 1:
            raise ConfigError("--processes must be at least 1")
        if not self.connect_rate > 0.0:
            raise ConfigError("--connect-rate must be positive")
        if self.workers < 1:
            raise ConfigError("--workers must be at least 1")


@dataclass(frozen=True)
class Latency:
    """Percentiles of round trips, in milliseconds."""

    n: int
    p50: float
    p95: float
    p99: float
    mean: float
    max: float

    @classmethod
    def of(cls, seconds: Sequence[float]) -> Latency:
        if not seconds:
            return cls(0, math.nan, math.nan, math.nan, math.nan, math.nan)
        ms = 1000.0 * np.asarray(seconds, dtype=float)
        p50, p95, p99 = np.percentile(ms, [50, 95, 99])
        return cls(len(ms), float(p50), float(p95), float(p99), float(ms.mean()), float(ms.max()))


@dataclass(frozen=True)
class PrivacyRun:
    """The Hamburg scenario through the deployment at one rotation period."""

    rotation_period: float  # s of scenario time; ROTATION_OFF for none
    rotations: int  # pseudonym changes the user core made
    answered: int
    fixes: int
    accuracy: float
    aed: float


@dataclass
class BenchReport:
    """Everything `laas bench` measured."""

    participants: int
    rate: float
    duration: float
    brokers: str
    processes: int
    sent: int
    answered: int
    error_replies: int
    lost: int
    elapsed: float  # s from the first send to the last
    ldm: Latency
    bare: Latency
    bare_lost: int
    dropped_stale: int  # by the cores, over max_age
    worker_answered: int
    workers: int = 1  # worker processes, each serving a region
    spread: bool = False  # fixes spread over the second (else all on the whole second)
    ramp: float = math.nan  # s from the first connection to the last session open
    cpu_participants: float = math.nan  # CPU s per s of sending, all participant processes
    cpu_cores: float = math.nan  # CPU s per s of sending, the process of the two cores
    stages: dict[str, Latency] = field(default_factory=dict)  # each stage, by `STAGES` name
    cpu_worker: float = math.nan  # CPU s of the worker process while it served
    cpu: dict[str, float] = field(default_factory=dict)
    """CPU s of each kind of process over the load (from /proc), brokers included:
    ``participants``, ``cores`` (this process: the two cores, and the bench's own
    loop), ``worker``, ``brokers`` (all three); empty without /proc."""
    privacy: list[PrivacyRun] = field(default_factory=list)
    errors: list[str] = field(default_factory=list)
    profiles: list[Profile] = field(default_factory=list)
    """With `BenchConfig.profile`: each process's top entries over the load
    (`laas.run.profile`), brokers excluded."""

    @property
    def share_answered(self) -> float:
        return self.answered / self.sent if self.sent else 0.0

    @property
    def throughput(self) -> float:
        """Corrected positions received per second."""
        return self.answered / self.elapsed if self.elapsed > 0 else 0.0

    @property
    def overhead(self) -> float:
        """p50 of the LDM round trip over p50 of the bare MQTT echo."""
        return self.ldm.p50 / self.bare.p50 if self.bare.p50 > 0 else math.nan

    def cpu_per_1000(self) -> dict[str, float]:
        """CPU seconds per 1,000 fixes sent, by kind of process: from the operating
        system's counters, brokers included (`cpu`), or, without /proc, from the
        processes' own clocks (brokers not counted)."""
        k = 1000.0 / self.sent if self.sent else math.nan
        if self.cpu:
            return {name: seconds * k for name, seconds in self.cpu.items()}
        return {
            "participants": self.cpu_participants * self.duration * k,
            "cores": self.cpu_cores * self.duration * k,
            "worker": self.cpu_worker * k,
        }

    def as_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d.update(
            share_answered=self.share_answered,
            throughput=self.throughput,
            overhead=self.overhead,
            cpu_per_1000=self.cpu_per_1000(),
        )
        return d


STAGES = (
    ("participant -> user core", "sent", "user_core"),
    ("user core -> service core", "user_core", "service_core"),
    ("service core -> worker", "service_core", "arrived"),
    ("queue wait in the worker", "arrived", "taken"),
    ("worker: open, engine, checks", "taken", "answered"),
    ("worker -> user core (reply)", "answered", "delivered"),
)
"""The stages `laas bench` times: (name, from point, to point) of `ldm.transport.hops`."""


def stage_latencies(hops: Hops) -> dict[str, Latency]:
    """Each stage's latency over the messages that passed both its points."""
    return {name: Latency.of(hops.stage(a, b)) for name, a, b in STAGES}


# --- the participants' drive --------------------------------------------------------


def bench_scenario(
    participants: int, rate: float, duration: float, seed: int = 0, *, spread: bool = True
) -> Scenario:
    """N road users on the Hamburg road: cars on the driving lanes, cyclists on the bike
    lane, random starts and speeds, all staying on the route for `duration` seconds.

    With `spread` each user has a random phase within the period; without, every fix
    falls on a multiple of the period (the whole second at 1 Hz)."""
    base = hamburg_scenario()
    hdmap = read_geojson_file(base.map)
    length = sum(hdmap.segments[s].length for s in base.route) - 1.0
    rng = np.random.default_rng(seed)
    users = []
    for i in range(participants):
        car = rng.random() < 0.6
        speed = float(rng.uniform(4.0, 9.0) if car else rng.uniform(3.0, 6.0))
        speed = min(speed, 0.8 * length / duration)
        start = float(rng.uniform(0.0, length - speed * duration))
        lane = int(rng.integers(0, 2)) if car else 3
        phase = float(rng.uniform(0.0, min(0.999, 1.0 / rate)))  # drawn either way: same users
        users.append(
            UserPlan(
                user=f"u{i:04d}",
                kind="car" if car else "bicycle",
                speed=speed,
                start=start,
                lanes=((0.0, lane),),
                phase=phase if spread else 0.0,
            )
        )
    return base.model_copy(
        update={"name": "bench", "users": tuple(users), "duration": duration, "rate": rate}
    )


# --- participant processes ----------------------------------------------------------


@dataclass(frozen=True)
class _Shard:
    index: int
    url: str
    tag: str
    # (user, measurement as a dict), in time order; its time zero is EPOCH_MS
    sends: list[tuple[str, dict[str, Any]]]
    reply_timeout: float
    trust: dict[str, Any]  # the participants' pinned keys (LocalDeployment.trust)
    connect_rate: float  # this process's share of BenchConfig.connect_rate
    regional: bool = False  # route each user to the worker of its region (RoutedSession)


def _participant_process(shard: _Shard, results: Any, go: Any, start_at: Any, abort: Any) -> None:
    """Run one shard of the participants; report to `results` (a multiprocessing queue)."""
    settings = BrokerSettings.of(shard.url)
    logins = {u: (settings, f"bench-{shard.tag}-{u}") for u in sorted({u for u, _ in shard.sends})}
    pongs: dict[int, float] = {}

    pong_topic = _PONG.format(shard=shard.index)

    def on_pong(event: Event) -> None:  # paho's thread: record the time, nothing more
        # Only this shard's pongs count; anything else the broker delivers (a retained
        # message, another client's traffic) is ignored, never parsed.
        if isinstance(event, Message) and event.topic == pong_topic:
            payload = event.payload.decode("ascii", "replace")
            if payload.isdigit():
                pongs[int(payload)] = time.perf_counter()

    bare = Transport(settings, client_id=f"bench-bare-{shard.tag}-{shard.index}", sink=on_pong)
    bare.subscribe(pong_topic, 0)
    try:  # "failed" before "ready": could not start; after it: failed while sending
        with ExitStack() as stack:
            stack.callback(bare.stop)  # last: after the participants
            bare.start(10.0)
            t0 = time.monotonic()
            sessions = stack.enter_context(
                paced_sessions(
                    logins,
                    connect_rate=shard.connect_rate,
                    where=_first_positions(shard.sends) if shard.regional else None,
                    progress=lambda stage, done, total: results.put(
                        ("ramp", shard.index, (stage, done, total))
                    ),
                    **shard.trust,
                )
            )
            results.put(("ready", shard.index, (len(sessions), time.monotonic() - t0)))
            go.wait()
            if not abort.is_set():
                report = _drive(shard, sessions, bare, pongs, results, start_at.value)
                results.put(("done", shard.index, report))
    except Exception as exc:
        results.put(("failed", shard.index, f"{type(exc).__name__}: {exc}"))


def _drive(
    shard: _Shard,
    sessions: dict[str, Session] | dict[str, RoutedSession],
    bare: Transport,
    pongs: dict[int, float],
    results: Any,
    start: float,
) -> dict[str, Any]:
    """Send the shard's fixes on time (a bare ping beside every fourth), then collect
    the replies and the pongs."""
    pings: dict[int, float] = {}
    next_report = time.perf_counter() + 1.0
    waiting: list[Request] = []  # not yet answered at the last report
    counted = 0  # requests looked at by the reports so far

    def beside(i: int, requests: Sequence[Request]) -> None:
        nonlocal next_report, waiting, counted
        if i % _PING_EVERY == 0:
            pings[i] = time.perf_counter()
            bare.publish(_PING.format(shard=shard.index), str(i).encode(), 0)
        now = time.perf_counter()
        if now >= next_report:  # once a second, looking only at what was open or is new
            waiting = [r for r in (*waiting, *requests[counted:]) if not r.future.done()]
            counted = len(requests)
            results.put(("progress", shard.index, (i + 1, counted - len(waiting))))
            next_report = now + 1.0

    cpu0 = time.process_time()
    sent = submit_on_time(sessions, shard.sends, t0_ms=EPOCH_MS, start=start, on_submit=beside)
    cpu = time.process_time() - cpu0

    latencies: list[float] = []
    errors: list[str] = []
    error_replies = lost = 0
    for reply in collect_replies(sent, shard.reply_timeout):
        if reply.latency is not None:
            latencies.append(reply.latency)
            continue
        if reply.lost:
            lost += 1
        else:  # an error reply, or one that is not a corrected position
            error_replies += 1
        if len(errors) < 5 and reply.error:
            errors.append(reply.error)
    time.sleep(min(1.0, shard.reply_timeout))  # the last pongs
    bare_latencies = [pongs[i] - t for i, t in pings.items() if i in pongs]
    return {
        "sent": len(sent.requests),
        "latencies": latencies,
        "error_replies": error_replies,
        "lost": lost,
        "bare": bare_latencies,
        "bare_lost": len(pings) - len(bare_latencies),
        "elapsed": sent.end - sent.start,
        "cpu": cpu,
        "errors": errors,
    }


def _is_ping(topic: str) -> bool:
    """True for a bare ping topic, bench/bare/{shard}/ping."""
    parts = topic.split("/")
    return len(parts) == 4 and parts[:2] == ["bench", "bare"] and parts[3] == "ping"


def _echo_process(url: str, tag: str, ready: Any, stop: Any) -> None:
    """Echo every ping on the user broker back as a pong, via a dispatch thread."""
    inbox: queue.SimpleQueue[Event] = queue.SimpleQueue()
    transport = Transport(BrokerSettings.of(url), client_id=f"bench-echo-{tag}", sink=inbox.put)
    transport.subscribe(_PING.format(shard="+"), 0)

    def work() -> None:
        while True:
            event = inbox.get()
            # Echo only pings (bench/bare/{shard}/ping) back to their shard's pong topic.
            if isinstance(event, Message) and _is_ping(event.topic):
                transport.publish(event.topic[: -len("ping")] + "pong", event.payload, 0)
            elif event is None:
                return

    worker = threading.Thread(target=work, name="bench-echo", daemon=True)
    worker.start()
    transport.start(10.0)
    ready.set()
    stop.wait()
    transport.stop()


# --- the run ------------------------------------------------------------------------


_CLOCK_TICKS = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100


def _cpu_seconds(pid: int) -> float:
    """User plus system CPU seconds of process `pid` so far (/proc/PID/stat), 0 if gone."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return 0.0
    fields = stat.rsplit(")", 1)[1].split()  # after "pid (comm)": state, ppid, ...
    return (int(fields[11]) + int(fields[12])) / _CLOCK_TICKS  # utime, stime


def _children(pid: int) -> list[int]:
    """The child processes of `pid` (/proc/PID/task/*/children)."""
    found: list[int] = []
    for task in Path(f"/proc/{pid}/task").glob("*"):
        try:
            found += [int(c) for c in (task / "children").read_text().split()]
        except OSError:
            continue
    return found


def _processes(echo: int | None, participants: Sequence[int] = ()) -> dict[int, str]:
    """The processes of the system under test that outlive the load, by pid -> kind:
    this one (``cores``), the brokers (Mosquitto, or the embedded broker in a process)
    and the worker processes (any other child but the bare echo, which is the floor's,
    not the LDM's, and multiprocessing's resource tracker). The participant processes,
    which exit once done, count their own CPU time: they are not counted here (they are
    this process's children too, and were once counted as the worker's)."""
    kinds = {os.getpid(): "cores"}
    for pid in _children(os.getpid()):
        if pid in kinds or pid == echo or pid in participants:
            continue
        try:
            command = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        if any(b"resource_tracker" in part for part in command):
            continue
        broker = Path(command[0].decode(errors="replace")).name == "mosquitto" or (
            b"ldm" in command and b"broker" in command
        )
        kinds[pid] = "brokers" if broker else "worker"
    return kinds


def _cpu_by_kind(kinds: dict[int, str]) -> dict[str, float]:
    """CPU seconds so far, summed by kind of process."""
    total = dict.fromkeys(("cores", "worker", "brokers"), 0.0)
    for pid, kind in kinds.items():
        total[kind] += _cpu_seconds(pid)
    return total


def _kind(brokers: BrokerChoice) -> Literal["mosquitto", "embedded-process"]:
    if brokers == "mosquitto" or (brokers == "auto" and find_mosquitto()):
        if not find_mosquitto():
            raise ConfigError("--brokers mosquitto, but mosquitto is not installed")
        return "mosquitto"
    return "embedded-process"


def _deployment(
    kind: Literal["mosquitto", "embedded-process"],
    hdmap: HdMap,
    rotation_period: float,
    hops: Hops | None = None,
    workers: int = 1,
) -> LocalDeployment:
    """The three brokers, the two cores in this process and the workers, each in its
    own process (with several, each serving a region of the map)."""
    return LocalDeployment(
        hdmap,
        brokers=kind,
        rotation_period=rotation_period,
        worker_process=True,
        hops=hops,
        regions=workers,
    )


def _shards(
    trace: Trace, processes: int, url: str, config: BenchConfig, trust: dict[str, Any]
) -> list[_Shard]:
    users = sorted({f.user for f in trace.fixes})
    owner = {u: k % processes for k, u in enumerate(users)}
    sends: list[list[tuple[str, dict[str, Any]]]] = [[] for _ in range(processes)]
    for fix in trace.fixes:
        sends[owner[fix.user]].append((fix.user, fix.measurement.model_dump(exclude_none=True)))
    tag = secrets.token_hex(3)
    rate = config.connect_rate / processes
    regional = config.workers > 1
    return [
        _Shard(k, url, tag, s, config.reply_timeout, trust, rate, regional)
        for k, s in enumerate(sends)
        if s
    ]


def _first_positions(sends: Sequence[tuple[str, dict[str, Any]]]) -> dict[str, tuple[float, float]]:
    """Each user's first (longitude, latitude): where its session is routed first."""
    first: dict[str, tuple[float, float]] = {}
    for user, m in sends:
        first.setdefault(user, (m["longitude"], m["latitude"]))
    return first


def _load(
    config: BenchConfig, deployment: LocalDeployment, trace: Trace, say: Progress
) -> BenchReport:
    cores = mp.cpu_count() or 2
    processes = config.processes or max(2, min(4, cores))
    processes = min(processes, config.participants)
    ctx = mp.get_context("spawn")
    results = ctx.Queue()
    go, abort, echo_ready, echo_stop = ctx.Event(), ctx.Event(), ctx.Event(), ctx.Event()
    start_at = ctx.Value("d", 0.0)
    shards = _shards(trace, processes, deployment.user_url, config, deployment.trust)
    recorder: Recorder | None = None
    echo = ctx.Process(
        target=_echo_process,
        args=(deployment.user_url, shards[0].tag, echo_ready, echo_stop),
        name="bench-echo",
    )
    workers = [
        ctx.Process(
            target=_participant_process,
            args=(shard, results, go, start_at, abort),
            name=f"bench-participants-{shard.index}",
        )
        for shard in shards
    ]
    try:
        echo.start()
        for w in workers:
            w.start()
        if not echo_ready.wait(30.0):
            raise ConfigError("the echo process did not connect within 30 s")
        ready = 0
        ramp = 0.0
        stages: dict[int, tuple[str, int, int]] = {}
        next_line = time.monotonic()  # the first ramp line at once, then one a second
        wait = 90.0 + config.participants / config.connect_rate
        while ready < len(shards):
            kind, index, value = results.get(timeout=wait)
            if kind == "failed":
                raise ConfigError(f"participant process {index} could not start: {value}")
            if kind == "ramp":
                stages[index] = value
                if time.monotonic() >= next_line:
                    next_line = time.monotonic() + 1.0
                    say("  " + _ramp_line(stages, config.participants))
                continue
            ready += 1
            opened, seconds = value
            ramp = max(ramp, seconds)
            say(f"  participant process {index}: {opened} sessions open after {seconds:.1f} s")
        start_at.value = time.time() + 0.5
        go.set()
        say(f"  sending for {config.duration:g} s ...")
        cpu0 = time.process_time()
        kinds = _processes(echo.pid, [w.pid for w in workers if w.pid is not None])
        if config.profile is not None:
            recorder = Recorder(Path(config.profile), config.duration)
            recorder.start({**kinds, **{w.pid: "participants" for w in workers if w.pid}})
        by_kind0 = _cpu_by_kind(kinds) if kinds and Path("/proc/self/stat").exists() else {}
        sent = {s.index: 0 for s in shards}
        answered = dict(sent)
        done: dict[int, dict[str, Any]] = {}
        next_line = time.monotonic() + 5.0
        t_start = time.monotonic()
        limit = config.duration + config.reply_timeout + 60.0
        while len(done) < len(shards):
            try:
                kind, index, value = results.get(timeout=1.0)
            except queue.Empty:
                if time.monotonic() - t_start > limit:
                    raise TimeoutError("participant processes did not finish") from None
                continue
            if kind == "failed":
                raise ConfigError(f"participant process {index} failed: {value}")
            if kind == "progress":
                sent[index], answered[index] = value
            elif kind == "done":
                done[index] = value
                sent[index] = answered[index] = value["sent"]
            if time.monotonic() >= next_line:
                next_line += 5.0
                say(
                    f"  t={time.monotonic() - t_start:4.0f} s: {sum(sent.values())} fixes sent, "
                    f"{sum(answered.values())} replies"
                )
        cpu_cores = (time.process_time() - cpu0) / config.duration
        by_kind = {}
        if by_kind0:
            # Once each participant process reported done, before any of them exits.
            by_kind = {k: v - by_kind0[k] for k, v in _cpu_by_kind(kinds).items()}
            by_kind["participants"] = -1.0  # their own clocks, below
        if recorder is not None:
            for label in recorder.stop():
                say(f"  profile of {label} missing: see {config.profile}/{label}.log")
    finally:
        abort.set()
        go.set()
        echo_stop.set()
        for process in (*workers, echo):
            process.join(10.0)
            if process.is_alive():
                process.kill()
                process.join(5.0)
    parts = list(done.values())
    return BenchReport(
        participants=config.participants,
        rate=config.rate,
        duration=config.duration,
        brokers=deployment.kind,
        processes=len(shards),
        sent=sum(p["sent"] for p in parts),
        answered=sum(len(p["latencies"]) for p in parts),
        error_replies=sum(p["error_replies"] for p in parts),
        lost=sum(p["lost"] for p in parts),
        elapsed=max(p["elapsed"] for p in parts),
        ldm=Latency.of([x for p in parts for x in p["latencies"]]),
        bare=Latency.of([x for p in parts for x in p["bare"]]),
        bare_lost=sum(p["bare_lost"] for p in parts),
        dropped_stale=sum(c.stats.dropped_stale for c in deployment.cores.values()),
        worker_answered=-1,  # known when the deployment stops
        workers=config.workers,
        spread=config.spread,
        ramp=ramp,
        cpu_participants=sum(p["cpu"] for p in parts) / config.duration,
        cpu_cores=cpu_cores,
        cpu={k: sum(p["cpu"] for p in parts) if v < 0 else v for k, v in by_kind.items()},
        errors=[e for p in parts for e in p["errors"]][:10],
    )


def _ramp_line(stages: dict[int, tuple[str, int, int]], participants: int) -> str:
    """One progress line of the ramp over all participant processes."""
    connected = sum(done if stage == "connect" else total for stage, done, total in stages.values())
    opened = sum(done for stage, done, _ in stages.values() if stage == "session")
    return f"ramp: {connected}/{participants} connected, {opened}/{participants} sessions open"


def _privacy(
    kind: Literal["mosquitto", "embedded-process"], period: float, speedup: float
) -> PrivacyRun:
    """The Hamburg scenario at `speedup`, pseudonyms rotating every `period` s of its time."""
    scenario = hamburg_scenario()
    hdmap = read_geojson_file(scenario.map)
    trace = simulate(hdmap, scenario, ErrorModel(), seed=0)
    with _deployment(kind, hdmap, period / speedup) as deployment:
        live = run_participants(
            deployment.user_url, trace, speedup=speedup, hdmap=hdmap, **deployment.trust
        )
        rotations = deployment.cores["user"].stats.rotations
    result = score(hdmap, trace, live.answers) if live.answered else None
    return PrivacyRun(
        rotation_period=period,
        rotations=rotations,
        answered=live.answered,
        fixes=len(trace.fixes),
        accuracy=result.accuracy if result else math.nan,
        aed=result.aed if result else math.nan,
    )


def run_bench(config: BenchConfig, progress: Progress | None = None) -> BenchReport:
    """Run the load, then the two privacy runs; `progress` gets a line now and then."""
    say = progress or (lambda _line: None)
    kind = _kind(config.brokers)
    scenario = bench_scenario(
        config.participants, config.rate, config.duration, config.seed, spread=config.spread
    )
    hdmap = read_geojson_file(scenario.map)
    trace = simulate(hdmap, scenario, ErrorModel(), config.seed)
    say(
        f"laas bench: {config.participants} participants at {config.rate:g} Hz for "
        f"{config.duration:g} s ({len(trace.fixes)} fixes, "
        f"{'spread over' if config.spread else 'on'} the period) on {kind} brokers; "
        f"connecting {config.connect_rate:g}/s"
    )
    hops = Hops()
    deployment = _deployment(kind, hdmap, config.rotation_period, hops, config.workers)
    with deployment:
        report = _load(config, deployment, trace, say)
    report.worker_answered = deployment.worker_answered
    report.cpu_worker = deployment.worker_cpu
    report.stages = stage_latencies(hops)
    if config.profile is not None:
        report.profiles = profiles(Path(config.profile))
    for period in (config.rotation_period, ROTATION_OFF) if config.privacy else ():
        label = "off" if period == ROTATION_OFF else f"every {period:g} s"
        say(f"  privacy: Hamburg scenario, rotation {label}, {config.privacy_speedup:g}x ...")
        report.privacy.append(_privacy(kind, period, config.privacy_speedup))
    return report


def format_report(r: BenchReport) -> str:
    """The table `laas bench` prints."""
    lines = [
        f"laas bench: {r.participants} participants at {r.rate:g} Hz for {r.duration:g} s "
        f"through 3 {r.brokers} brokers, 2 LDM cores and "
        + ("the laas worker" if r.workers == 1 else f"{r.workers} regional laas workers"),
        f"(participants in {r.processes} processes, ramp {r.ramp:.1f} s; fixes "
        f"{'spread over the period' if r.spread else 'aligned to the period'}; "
        "floor: MQTT echo over the user broker)",
        "",
        f"{'round trip, ms':<34}{'n':>7}{'p50':>9}{'p95':>9}{'p99':>9}{'mean':>9}{'max':>9}",
    ]
    for name, lat in (
        ("LDM: fix -> corrected position", r.ldm),
        ("bare MQTT echo (floor)", r.bare),
    ):
        lines.append(
            f"{name:<34}{lat.n:>7}{lat.p50:>9.2f}{lat.p95:>9.2f}{lat.p99:>9.2f}"
            f"{lat.mean:>9.2f}{lat.max:>9.2f}"
        )
    lines += [
        f"{'LDM overhead (p50 / bare p50)':<34}{r.overhead:>16.1f}x",
        "",
        f"answered     {r.answered}/{r.sent} ({100 * r.share_answered:.1f} %); "
        f"{r.error_replies} error replies, {r.lost} without reply; "
        f"{r.dropped_stale} dropped as stale by the cores",
        f"throughput   {r.throughput:.1f} corrected positions/s "
        f"({r.sent / r.elapsed if r.elapsed else 0:.1f} fixes/s sent)",
    ]
    if r.stages:
        lines += [
            "",
            f"{'each stage, ms':<34}{'n':>7}{'p50':>9}{'p95':>9}{'p99':>9}{'mean':>9}{'max':>9}",
        ]
        for name, lat in r.stages.items():
            lines.append(
                f"{name:<34}{lat.n:>7}{lat.p50:>9.2f}{lat.p95:>9.2f}{lat.p99:>9.2f}"
                f"{lat.mean:>9.2f}{lat.max:>9.2f}"
            )
        lines.append("(the participant's receipt of the reply is in the round trip above)")
    cpu = r.cpu_per_1000()
    if r.cpu:
        lines += [
            "",
            "CPU s per 1,000 fixes (from /proc), each kind of process:",
            "  " + "  ".join(f"{name} {seconds:.3f}" for name, seconds in cpu.items()),
            f"  total {sum(cpu.values()):.3f} (cores: the process of both cores)",
        ]
    else:
        lines += [
            "",
            f"CPU s per 1,000 fixes: participants {cpu['participants']:.2f}, "
            f"cores {cpu['cores']:.2f}, worker {cpu['worker']:.2f} (brokers not counted)",
        ]
    lines += _privacy_lines(r)
    for error in r.errors[:5]:
        lines.append(f"  e.g. {error}")
    if r.profiles:
        lines += ["", format_profiles(r.profiles)]
    return "\n".join(lines)


def run_loads(config: BenchConfig, progress: Progress | None = None) -> list[BenchReport]:
    """The load on the whole second, then spread over it (`BenchConfig.spread` is
    ignored), each on a deployment of its own; the privacy runs (if any) after the
    second only."""
    folder = config.profile
    aligned = replace(config, spread=False, privacy=False)
    spread = replace(config, spread=True)
    if folder is not None:  # each load's profiles in a folder of its own
        aligned = replace(aligned, profile=str(Path(folder) / "aligned"))
        spread = replace(spread, profile=str(Path(folder) / "spread"))
    return [run_bench(aligned, progress), run_bench(spread, progress)]


def format_loads(reports: Sequence[BenchReport]) -> str:
    """The loads of `run_loads` side by side: answers, round trips and CPU per 1,000
    fixes by kind of process, one row each; then the privacy runs of the last."""
    first = reports[0]
    served = "the laas worker" if first.workers == 1 else f"{first.workers} regional laas workers"
    lines = [
        f"laas bench: {first.participants} participants at {first.rate:g} Hz for "
        f"{first.duration:g} s through 3 {first.brokers} brokers, 2 LDM cores and {served}, "
        "each load on a deployment of its own (floor: MQTT echo over the user broker)",
        "",
        f"{'load':<24}{'answered':>10}{'LDM p50':>9}{'p95':>9}{'p99':>9}{'bare p50':>10}"
        f"{'p99':>9}{'LDM/bare':>10}",
    ]
    for r in reports:
        lines.append(
            f"{_load_name(r):<24}{100 * r.share_answered:>8.1f} %{r.ldm.p50:>9.2f}"
            f"{r.ldm.p95:>9.2f}{r.ldm.p99:>9.2f}{r.bare.p50:>10.2f}{r.bare.p99:>9.2f}"
            f"{r.overhead:>9.1f}x"
        )
    kinds = list(dict.fromkeys(k for r in reports for k in r.cpu_per_1000()))
    lines += ["", f"{'CPU s per 1,000 fixes':<24}" + "".join(f"{k:>14}" for k in kinds)]
    lines[-1] += f"{'total':>9}"
    for r in reports:
        cpu = r.cpu_per_1000()
        row = "".join(f"{cpu.get(k, math.nan):>14.3f}" for k in kinds)
        lines.append(f"{_load_name(r):<24}{row}{sum(cpu.values()):>9.3f}")
    lines.append("(round trips in ms; cores: the process of both cores; brokers from /proc)")
    for r in reports:
        lost = r.sent - r.answered
        if lost or r.dropped_stale:
            lines.append(
                f"{_load_name(r)}: {r.error_replies} error replies, {r.lost} without reply, "
                f"{r.dropped_stale} dropped as stale by the cores"
            )
        for error in r.errors[:3]:
            lines.append(f"  e.g. {error}")
    lines += _privacy_lines(reports[-1])
    return "\n".join(lines)


def _privacy_lines(r: BenchReport) -> list[str]:
    """The cost of privacy, from the two Hamburg runs (none: no lines)."""
    if not r.privacy:
        return []
    lines = ["", "cost of privacy (Hamburg scenario, lane accuracy against the truth):"]
    for p in r.privacy:
        label = (
            "rotation off"
            if p.rotation_period == ROTATION_OFF
            else (f"rotation every {p.rotation_period:g} s")
        )
        lines.append(
            f"  {label:<26} accuracy {p.accuracy:.3f}, AED {p.aed:.2f} m, "
            f"{p.answered}/{p.fixes} answered, {p.rotations} rotations"
        )
    if r.privacy[0].rotations == 0:
        lines.append("  (the scenario lasts 100 s: shorter than this period, so no rotation)")
    return lines


def _load_name(r: BenchReport) -> str:
    return "spread over the second" if r.spread else "on the whole second"
