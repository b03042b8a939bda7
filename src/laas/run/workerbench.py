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

from laas.map.bundled import bundled_map
from laas.map.hdmap import HdMap
from laas.service import LaasService, WorkerConfig, service_spec
from laas.sim.roam import roam_scenario
from laas.sim.scenario import simulate_with
from ldm import KeyPair, Provider, topics
from ldm.crypto import aad
from ldm.messages import Envelope
from ldm.transport import Message

__all__ = ["WorkerBenchReport", "bench_worker", "format_worker_report"]

_CHUNK = 250  # fixes per timed chunk, then as many filterpy steps


@dataclass(frozen=True)
class WorkerBenchReport:
    """Microseconds per fix for each stage, and what they add up to."""

    map: str
    users: int
    fixes: int
    answered: int
    open_us: float
    service_us: float
    engine_us: float
    seal_us: float
    filterpy_us: float
    seconds: float

    @property
    def total_us(self) -> float:
        return self.open_us + self.service_us + self.engine_us + self.seal_us

    @property
    def fixes_per_second(self) -> float:
        return 1e6 / self.total_us

    @property
    def engine_per_filterpy(self) -> float:
        return self.engine_us / self.filterpy_us

    def as_dict(self) -> dict[str, object]:
        out: dict[str, object] = asdict(self)
        out.update(
            total_us=self.total_us,
            fixes_per_second=self.fixes_per_second,
            engine_per_filterpy=self.engine_per_filterpy,
        )
        return out


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
    progress: Callable[[str], None] | None = None,
) -> WorkerBenchReport:
    """Feed a roaming scenario's fixes, encrypted, through the worker's code (module doc)."""
    say = progress or (lambda _line: None)
    hdmap = HdMap.load(bundled_map(map_name))
    trace = simulate_with(
        hdmap, roam_scenario(hdmap, seed, users, duration), seed, sigma_pos=1.0, sigma_vel=0.25
    )
    service = LaasService(hdmap, worker=WorkerConfig(max_past=1e9, max_speedup=1e9))
    # Never started: no connection is made; `open` and `seal` are its worker thread's code.
    provider = Provider.create("mqtt://127.0.0.1:1", service_spec(), service.handle, max_age=1e9)
    say(f"sealing {len(trace.fixes)} fixes of {users} users on {map_name}")
    shift = time.time() * 1000.0 - trace.fixes[0].measurement.timestamp
    sessions: dict[str, tuple[str, str]] = {}  # user -> (pseudonym, ephemeral public key)
    ciphers = {}
    messages: list[Message] = []
    for fix in trace.fixes:
        if fix.user not in sessions:
            pair = KeyPair()
            sessions[fix.user] = (secrets.token_hex(8), pair.public)
            ciphers[fix.user] = pair.cipher(provider.key.public, initiator=True)
        pseudonym, public = sessions[fix.user]
        m = fix.measurement.model_copy(update={"timestamp": int(fix.measurement.timestamp + shift)})
        c, t = secrets.token_hex(8), time.time()
        sealed = ciphers[fix.user].seal(m.model_dump_json().encode(), aad(c, t))
        env = Envelope(c=c, t=t, k=public, d=sealed)
        topic = topics.provider_input(service_spec().name, pseudonym)
        messages.append(Message(topic, env.encode(), 1, False, "bench"))

    rng = np.random.default_rng(seed)
    t_open = t_handle = t_seal = t_filterpy = 0.0
    engine_before = service.stats.engine_seconds
    answered = 0
    start = time.perf_counter()
    for k in range(0, len(messages), _CHUNK):
        for msg in messages[k : k + _CHUNK]:
            t0 = time.perf_counter()
            opened = provider.open(msg)
            t1 = time.perf_counter()
            if opened is None:
                continue
            request, route = opened
            answer = service.handle(request)
            t2 = time.perf_counter()
            provider.seal(route, request.correlation_id, answer)
            t3 = time.perf_counter()
            t_open += t1 - t0
            t_handle += t2 - t1
            t_seal += t3 - t2
            answered += "error" not in answer
        t_filterpy += _filterpy_steps(min(_CHUNK, len(messages) - k), rng)
        if (k // _CHUNK) % 8 == 7:
            say(f"{k + _CHUNK} of {len(messages)} fixes")
    seconds = time.perf_counter() - start
    n = len(messages)
    engine = service.stats.engine_seconds - engine_before
    return WorkerBenchReport(
        map=map_name,
        users=users,
        fixes=n,
        answered=answered,
        open_us=t_open / n * 1e6,
        service_us=(t_handle - engine) / n * 1e6,
        engine_us=engine / n * 1e6,
        seal_us=t_seal / n * 1e6,
        filterpy_us=t_filterpy / n * 1e6,
        seconds=seconds,
    )


def format_worker_report(r: WorkerBenchReport) -> str:
    """The report as a table."""
    rows = [
        ("open (envelope, decryption, JSON)", r.open_us),
        ("service (validation, checks, answer)", r.service_us),
        ("engine", r.engine_us),
        ("seal (JSON, encryption, envelope)", r.seal_us),
        ("total", r.total_us),
    ]
    lines = [
        f"worker alone, one core: {r.fixes} fixes of {r.users} users on {r.map}, "
        f"{r.answered} answered",
        f"{'stage':40s} {'us/fix':>8s}",
        *(f"{name:40s} {us:8.1f}" for name, us in rows),
        f"fixes/s on one core: {r.fixes_per_second:,.0f}",
        f"filterpy predict + update, same run: {r.filterpy_us:.1f} us; "
        f"engine / filterpy = {r.engine_per_filterpy:.2f}",
    ]
    return "\n".join(lines)
