"""`laas bench --worker-only`: the worker's capacity on one core, without brokers.

Fixes of simulated road users are encrypted beforehand as their participants would send
them (a session key each, the envelope as it arrives from the core), then fed to the
worker's own code in this process, one after another, and each stage is timed:

- open: the provider's `Provider.open` (envelope, decryption, JSON);
- engine: `Engine.process`, inside the service's handler;
- service: the rest of the handler (validation into `GpsMeasurement`, the clock and
  area checks, the answer's `model_dump`);
- seal: `Provider.seal` (JSON, encryption, envelope).

No broker, no paho thread and no queue is involved, so the figure is the worker's CPU
ceiling: fixes per second on one core = 1e6 / (total us per fix).

Two workers take the same fixes in the same run, chunk by chunk in turn: one is handed
them one at a time (`LaasService.handle`, as a worker with an empty queue), the other
in batches of `batch` in arrival order (`LaasService.handle_many`, as the provider hands
over what waited together under load). A batch is one step of the engine for all its
fixes (`Engine.process_many`), whose answers stay within the bounds that
`tests/test_same_answers.py` holds them to; the figures say what the batch saves.

The reference is one Kalman step as filterpy does it (`KalmanFilter.predict` with
`Q_discrete_white_noise`, then `update`, on the track's 4-state model), timed in the same
run: the fixes go through the worker in chunks, and a chunk of filterpy steps of the same
size runs after each, so both see the same machine. The engine's cost is reported as a
ratio to it.
"""

from __future__ import annotations

import secrets
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass

import numpy as np

from laas.engine.warm import warm_up
from laas.map.bundled import bundled_map
from laas.map.geojson import read_geojson_file
from laas.map.hdmap import HdMap
from laas.sim.roam import roam_scenario
from laas.sim.scenario import simulate_with
from laas.worker.service import LaasService, WorkerConfig, service_spec
from ldm import KeyPair, Provider
from ldm.security.crypto import aad
from ldm.wire import topics
from ldm.wire.batch import Entry
from ldm.wire.messages import Envelope

__all__ = ["WorkerBenchReport", "bench_worker", "format_worker_report"]

_CHUNK = 250  # fixes per timed chunk, then as many filterpy steps


@dataclass(frozen=True)
class StageTimes:
    """Microseconds per fix for each stage of one way of feeding the worker."""

    open_us: float
    service_us: float
    engine_us: float
    seal_us: float

    @property
    def total_us(self) -> float:
        return self.open_us + self.service_us + self.engine_us + self.seal_us

    @property
    def fixes_per_second(self) -> float:
        return 1e6 / self.total_us


@dataclass(frozen=True)
class WorkerBenchReport:
    """Stage times one fix at a time and in batches, and one filterpy step, per fix."""

    map: str
    users: int
    fixes: int
    answered: int
    batch: int
    single: StageTimes
    batched: StageTimes
    filterpy_us: float
    seconds: float

    @property
    def engine_per_filterpy(self) -> float:
        """The batched engine's cost per fix in filterpy Kalman steps."""
        return self.batched.engine_us / self.filterpy_us

    def as_dict(self) -> dict[str, object]:
        out: dict[str, object] = asdict(self)
        for name in ("single", "batched"):
            times: StageTimes = getattr(self, name)
            out[name] = {
                **asdict(times),
                "total_us": times.total_us,
                "fixes_per_second": times.fixes_per_second,
            }
        out["engine_per_filterpy"] = self.engine_per_filterpy
        return out


class _Lane:
    """One worker (provider code and service) fed the fixes one way, timing each stage."""

    def __init__(self, hdmap: HdMap, provider: Provider | None) -> None:
        self.service = LaasService(hdmap, worker=WorkerConfig(max_past=1e9, max_speedup=1e9))
        # Never started: no connection is made; `open` and `seal` are its worker
        # thread's code.
        self.provider = Provider.create(
            "mqtt://127.0.0.1:1",
            service_spec(),
            self.service.handle,
            key=None if provider is None else provider.key,
            max_age=1e9,
        )
        self.t_open = self.t_handle = self.t_seal = 0.0
        self.answered = 0

    def feed(self, messages: list[Entry], batch: int) -> None:
        for k in range(0, len(messages), batch):
            t0 = time.perf_counter()
            opened = [o for o in map(self.provider.open, messages[k : k + batch]) if o]
            t1 = time.perf_counter()
            requests = [request for request, _ in opened]
            if batch == 1:
                answers = [self.service.handle(r) for r in requests]
            else:
                answers = self.service.handle_many(requests)
            t2 = time.perf_counter()
            for (request, route), answer in zip(opened, answers, strict=True):
                self.provider.seal(route, request.correlation_id, answer)
                self.answered += "error" not in answer
            t3 = time.perf_counter()
            self.t_open += t1 - t0
            self.t_handle += t2 - t1
            self.t_seal += t3 - t2

    def times(self, n: int) -> StageTimes:
        engine = self.service.stats.engine_seconds
        return StageTimes(
            open_us=self.t_open / n * 1e6,
            service_us=(self.t_handle - engine) / n * 1e6,
            engine_us=engine / n * 1e6,
            seal_us=self.t_seal / n * 1e6,
        )


def _filterpy_steps(count: int, rng: np.random.Generator) -> float:
    """Seconds for `count` filterpy predict + update steps of the track's model."""
    from filterpy.common import Q_discrete_white_noise
    from filterpy.kalman import KalmanFilter

    kf = KalmanFilter(dim_x=4, dim_z=4)
    kf.H = np.eye(4)
    kf.x = np.zeros((4, 1))
    kf.P = np.eye(4)
    r = np.diag([1.0, 1.0, 0.07, 0.07])
    zs = rng.normal(0.0, 1.0, (count, 4))
    t0 = time.perf_counter()
    for z in zs:
        f = np.eye(4)
        f[0, 2] = f[1, 3] = 1.0
        q = Q_discrete_white_noise(dim=2, dt=1.0, var=0.49, block_size=2, order_by_dim=False)
        kf.predict(F=f, Q=q)
        kf.update(z, R=r)
    return time.perf_counter() - t0


def bench_worker(
    *,
    map_name: str = "messe-hamburg",
    users: int = 200,
    duration: float = 50.0,
    seed: int = 0,
    batch: int = 64,
    spread: bool = False,
    progress: Callable[[str], None] | None = None,
) -> WorkerBenchReport:
    """Feed a roaming scenario's fixes, encrypted, through the worker's code (module doc):
    every user's fixes on the whole second, as GNSS receivers emit them, or with `spread`
    at a random phase each (the roaming scenario's own)."""
    if batch < 1:
        raise ValueError(f"batch must be at least 1, not {batch}")
    say = progress or (lambda _line: None)
    hdmap = read_geojson_file(bundled_map(map_name))
    warm_up(hdmap)  # compiled before the clock runs, as a worker does before its first fix
    scenario = roam_scenario(hdmap, seed, users, duration)
    if not spread:
        on_the_second = tuple(u.model_copy(update={"phase": 0.0}) for u in scenario.users)
        scenario = scenario.model_copy(update={"users": on_the_second})
    trace = simulate_with(hdmap, scenario, seed, sigma_pos=1.0, sigma_vel=0.25)
    single = _Lane(hdmap, None)
    batched = _Lane(hdmap, single.provider)  # the same key: both open the same messages
    say(f"sealing {len(trace.fixes)} fixes of {users} users on {map_name}")
    shift = time.time() * 1000.0 - trace.fixes[0].measurement.timestamp
    sessions: dict[str, tuple[str, str]] = {}  # user -> (pseudonym, ephemeral public key)
    ciphers = {}
    messages: list[Entry] = []  # as the provider queues them: each topic parsed on arrival
    name = service_spec().name
    for fix in trace.fixes:
        if fix.user not in sessions:
            pair = KeyPair()
            sessions[fix.user] = (secrets.token_hex(8), pair.public)
            ciphers[fix.user] = pair.cipher(single.provider.key.public, initiator=True)
        pseudonym, public = sessions[fix.user]
        m = fix.measurement.model_copy(update={"timestamp": int(fix.measurement.timestamp + shift)})
        c, t = secrets.token_hex(8), time.time()
        sealed = ciphers[fix.user].seal(m.model_dump_json().encode(), aad(c, t))
        env = Envelope(c=c, t=t, k=public, d=sealed)
        topic = topics.parse(topics.provider_input(name, pseudonym))
        messages.append(Entry(topic, pseudonym, env.encode(), 1, "bench"))

    rng = np.random.default_rng(seed)
    t_filterpy = 0.0
    chunk = max(_CHUNK // batch, 1) * batch  # whole batches per chunk
    start = time.perf_counter()
    for k in range(0, len(messages), chunk):
        part = messages[k : k + chunk]
        batched.feed(part, batch)
        single.feed(part, 1)
        t_filterpy += _filterpy_steps(len(part), rng)
        if (k // chunk) % 8 == 7:
            say(f"{k + len(part)} of {len(messages)} fixes")
    seconds = time.perf_counter() - start
    n = len(messages)
    return WorkerBenchReport(
        map=map_name,
        users=users,
        fixes=n,
        answered=min(single.answered, batched.answered),
        batch=batch,
        single=single.times(n),
        batched=batched.times(n),
        filterpy_us=t_filterpy / n * 1e6,
        seconds=seconds,
    )


def format_worker_report(r: WorkerBenchReport) -> str:
    """The report as a table."""
    rows = [
        ("open (envelope, decryption, JSON)", "open_us"),
        ("service (validation, checks, answer)", "service_us"),
        ("engine", "engine_us"),
        ("seal (JSON, encryption, envelope)", "seal_us"),
        ("total", "total_us"),
    ]
    one, many = r.single, r.batched
    lines = [
        f"worker alone, one core: {r.fixes} fixes of {r.users} users on {r.map}, "
        f"{r.answered} answered both ways",
        f"{'us/fix':40s} {'one at a time':>14s} {f'batches of {r.batch}':>14s}",
        *(f"{name:40s} {getattr(one, key):14.1f} {getattr(many, key):14.1f}" for name, key in rows),
        f"{'fixes/s on one core':40s} {one.fixes_per_second:14,.0f} {many.fixes_per_second:14,.0f}",
        f"filterpy predict + update, same run: {r.filterpy_us:.1f} us; "
        f"engine / filterpy = {one.engine_us / r.filterpy_us:.2f} one at a time, "
        f"{r.engine_per_filterpy:.2f} in batches",
    ]
    return "\n".join(lines)
