"""Rotation strategies on a real broker (`ldm.wire.rotation`): epochs on the shared clock,
silence after a change, a change the participant decides; and the pure rules."""

from __future__ import annotations

import functools
import itertools
import math
import random
import time
from collections.abc import Callable, Iterator
from concurrent.futures import Future
from typing import Any

import pytest

from ldm import ConfigError, Core, CoreConfig, Participant, Provider, SessionSilent
from ldm.client.rotation import CITS_FIRST, CITS_GAP, CITS_MIN_DISTANCE, STOP_TIME, Rotator
from ldm.core.rotation import next_rotation
from ldm.local.brokers import RunningBroker, wait_for
from ldm.wire.rotation import RotationPolicy

from .deployment import EchoService, echo_provider, has_service

Edge = tuple[Core, Provider, EchoService, str]


def _edge(factory: Callable[[], RunningBroker], **core: Any) -> Iterator[Edge]:
    """One broker with a core and an echo provider in its cluster."""
    broker = factory()
    c = Core.create("edge", broker.url, grace=0.5, idle_timeout=10.0, **core).start(timeout=5)
    echo = EchoService()
    provider = echo_provider(broker.url, echo)
    try:
        yield c, provider, echo, broker.url
    finally:
        provider.stop()
        c.stop()


def _participant(url: str, name: str) -> Participant:
    p = Participant.create(url, client_id=name).start(timeout=5)
    assert wait_for(has_service(p, "echo"), 5), "echo never listed"
    return p


def _all_done(futures: list[Future[dict[str, Any]]]) -> bool:
    return all(f.done() for f in futures)


def _first_seen(echo: EchoService, who: str) -> list[float]:
    """When each of `who`'s pseudonyms sent its first input (the service's view)."""
    with echo.lock:
        firsts: dict[str, float] = {}
        for r in echo.requests:
            if r.payload.get("who") == who:
                firsts.setdefault(r.pseudonym, r.sent_at)
    return sorted(firsts.values())


def test_epoch_rotation_changes_every_session_at_the_same_moment(
    broker_factory: Callable[[], RunningBroker],
) -> None:
    period = 2.0  # rekey_interval 1 s: a session may skip its first epoch, never another
    for core, _, echo, url in _edge(
        broker_factory, rotation_period=period, rotation={"strategy": "epoch"}
    ):
        ps = [_participant(url, "ann")]
        time.sleep(0.7)  # the second opens its session later: periodic would keep it apart
        ps.append(_participant(url, "bob"))
        sessions = [p.open("echo") for p in ps]
        assert sessions[0].grant.rotation == RotationPolicy(strategy="epoch")
        end = time.time() + 3 * period + 0.5
        scheduled: dict[str, set[float]] = {"ann": set(), "bob": set()}
        while time.time() < end:
            for who, s in zip(("ann", "bob"), sessions, strict=True):
                s.submit({"who": who})
            for state in core.sessions:  # the core's schedule: when it tells each to change
                if state.next_rotate:  # 0: not granted yet
                    scheduled[state.client].add(state.next_rotate)
            time.sleep(0.05)
        time.sleep(0.3)
        for p in ps:
            p.stop()
        # The core schedules every change at a multiple of the period on the Unix clock,
        # the same moments for both (periodic would keep bob 0.7 s behind ann).
        for who, times in scheduled.items():
            assert all(t / period == round(t / period) for t in times), (who, times)
        assert scheduled["ann"] >= scheduled["bob"] and len(scheduled["bob"]) >= 2, scheduled
        # What the service saw: each new pseudonym starts after a multiple of the period
        # (no change within an epoch), in the same epochs for both. How long after the
        # boundary (the core's tick, the notice's trip, the next input) depends on the
        # machine's load, and is printed, not bounded.
        changes = {who: _first_seen(echo, who)[1:] for who in ("ann", "bob")}
        assert all(len(c) >= 2 for c in changes.values()), changes
        epochs = {who: [math.floor(t / period) for t in times] for who, times in changes.items()}
        for who, e in epochs.items():
            assert e == sorted(set(e)), (who, e)  # one change per epoch at most
        assert set(epochs["ann"][-2:]) == set(epochs["bob"][-2:]), epochs
        late = {who: [round(t % period, 3) for t in times] for who, times in changes.items()}
        print(f"first input under each new pseudonym, s after its epoch: {late}")
        assert core.stats.rejected_rekey == 0


def test_a_silent_session_sends_nothing_after_its_change(
    broker_factory: Callable[[], RunningBroker],
) -> None:
    silence = 0.6
    for core, _, echo, url in _edge(
        broker_factory, rotation_period=2.0, rotation={"strategy": "periodic", "silence": silence}
    ):
        p = _participant(url, "cat")
        session = p.open("echo")
        futures: list[Future[dict[str, Any]]] = []
        end = time.time() + 5.8  # two rotations: at 2 s, and 2 s after the silence
        while time.time() < end:
            futures.append(session.submit({"who": "cat", "i": len(futures)}))
            time.sleep(0.05)
        assert wait_for(functools.partial(_all_done, futures), 5)
        silent = [f for f in futures if isinstance(f.exception(), SessionSilent)]
        answered = [f for f in futures if f.exception() is None]
        assert len(silent) + len(answered) == len(futures)
        assert session.rotations >= 2 and len(silent) >= 2 * int(silence / 0.05) - 2
        with echo.lock:  # the service saw exactly the answered inputs, with gaps between
            seen = sorted((r.sent_at, r.pseudonym) for r in echo.requests)
        assert len(seen) == len(answered)
        gaps = [b[0] - a[0] for a, b in itertools.pairwise(seen) if a[1] != b[1]]
        assert len(gaps) >= 2 and all(g >= silence for g in gaps), gaps
        assert core.stats.rejected_rekey == 0
        p.stop()


def test_the_participant_changes_its_key_where_it_stops(
    broker_factory: Callable[[], RunningBroker],
) -> None:
    # rotation_period 8 s: the core's backstop does not fire within this test; rekey 2 s.
    for core, _, echo, url in _edge(
        broker_factory, rotation_period=8.0, rotation={"strategy": "stop"}
    ):
        p = _participant(url, "dan")
        session = p.open("echo")
        start = time.time()
        session.request({"who": "dan"}, timeout=5)
        changed = False
        while time.time() - start < session.grant.rekey_interval + STOP_TIME + 1.5:
            # standing still from the start: the change waits for rekey_interval
            changed = session.moved(0.0, 0.0) or changed
            session.request({"who": "dan"}, timeout=5)
            time.sleep(0.1)
        assert changed and session.rotations == 1
        assert len(echo.pseudonyms_of("dan")) == 2
        assert core.stats.rejected_rekey == 0 and core.stats.rotations == 1
        p.stop()


def test_silence_longer_than_the_period_less_rekey_interval_is_refused() -> None:
    with pytest.raises(ConfigError, match=r"rotation\.silence"):
        from ldm.config import build

        build(
            CoreConfig,
            name="c",
            cluster="mqtt://localhost:1",
            rotation_period=10.0,  # rekey_interval 2.5 s: at most 7.5 s
            rotation={"strategy": "epoch", "silence": 7.6},
        )


def test_a_longest_silence_over_the_limit_or_below_the_shortest_is_refused() -> None:
    from ldm.config import build

    with pytest.raises(ConfigError, match=r"rotation\.silence"):
        build(
            CoreConfig,
            name="c",
            cluster="mqtt://localhost:1",
            rotation_period=120.0,
            rotation={"strategy": "epoch", "silence": 30.0, "silence_max": 91.0},
            idle_timeout=120.0,
        )
    with pytest.raises(ConfigError, match=r"silence_max 20 s is below silence 30 s"):
        build(
            CoreConfig,
            name="c",
            cluster="mqtt://localhost:1",
            rotation={"strategy": "epoch", "silence": 30.0, "silence_max": 20.0},
        )


def test_silences_are_drawn_from_the_policys_range() -> None:
    policy = RotationPolicy(strategy="epoch", silence=30.0, silence_max=90.0)
    r = Rotator(policy, 30.0, 0.0, random.Random(3))
    lengths = []
    for k in range(200):
        t = 1000.0 * (k + 1)
        r.changed(t)
        lengths.append(r.silent_until - t)
        assert r.silent(t + 29.9) and not r.silent(t + 90.0)
    assert min(lengths) >= 30.0 and max(lengths) <= 90.0
    assert max(lengths) - min(lengths) > 50.0  # drawn, not fixed
    fixed = Rotator(RotationPolicy(strategy="epoch", silence=15.0), 30.0, 0.0)
    fixed.changed(10.0)
    assert fixed.silent_until == 25.0


def test_epochs_fall_on_multiples_of_the_period() -> None:
    assert next_rotation("epoch", 60.0, 1_000_000.5) == 1_000_020.0
    assert next_rotation("epoch", 60.0, 1_000_020.0) == 1_000_080.0
    assert next_rotation("periodic", 60.0, 1_000_000.5) == 1_000_060.5


def test_the_cits_profile_changes_after_its_distances_and_times() -> None:
    rng = random.Random(7)
    r = Rotator(RotationPolicy(strategy="distance"), 30.0, 0.0, rng)
    t, travelled, changes = 0.0, 0.0, []
    r.used(0.0)
    while t < 2000.0:  # 10 m/s for 2,000 s
        t += 1.0
        travelled += 10.0
        if r.moved(10.0, 10.0, t):
            changes.append((t, travelled))
            r.changed(t)
            r.used(t)
    _, first_d = changes[0]
    assert CITS_FIRST[0] <= first_d <= CITS_FIRST[1] + 10.0
    for (t0, d0), (t1, d1) in itertools.pairwise(changes):
        assert d1 - d0 >= CITS_MIN_DISTANCE and CITS_GAP[0] <= t1 - t0 <= CITS_GAP[1] + 1.0
    assert len(changes) >= 2000.0 / CITS_GAP[1]


def test_a_participant_never_asks_for_a_key_the_core_would_refuse() -> None:
    r = Rotator(RotationPolicy(strategy="stop", silence=5.0), 15.0, 0.0, random.Random(1))
    r.used(0.0)
    assert not r.moved(0.0, 0.0, 10.0) and not r.moved(0.0, 0.0, 15.5)
    assert r.moved(0.0, 0.0, 16.5)  # 2 s standing, and rekey_interval + 1 s since its first use
    r.changed(16.5)
    assert r.silent(20.0) and not r.silent(21.5)
    r.used(21.5)  # the new key's first input: the core counts from here
    assert not r.may_change(21.5 + 14.9) and r.may_change(21.5 + 15.0)
