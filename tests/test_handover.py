"""Hand-over between regional engines (`laas.engine.handover`), without brokers: a
user's state moves to another engine, and areas pool their evidence across engines."""

from __future__ import annotations

import zlib

import numpy as np
import pytest

from laas.config import EngineConfig
from laas.engine import Engine
from laas.engine.common_error import CommonError
from laas.engine.handover import (
    AreaState,
    HandoverError,
    areas_from_bytes,
    areas_to_bytes,
    user_from_bytes,
    user_to_bytes,
)
from laas.map.hdmap import HdMap
from laas.sim.scenario import hamburg_scenario, simulate

CONFIG = EngineConfig(sigma_pos=1.0, sigma_vel=0.25, sigma_heading=0.05)


@pytest.mark.parametrize("memory", [None, 2.0])
def test_two_areas_that_share_their_evidence_hold_the_pooled_posterior(
    memory: float | None,
) -> None:
    """Two areas, each fed half of the fixes, that pass each other their own evidence
    every round hold what one area fed all of them holds (no evidence counted twice),
    also when evidence fades (a memory of 2 s: each round's evidence counts e^-0.5 of
    the round before's)."""
    rng = np.random.default_rng(0)
    a, b, pooled = (CommonError(np.zeros(2), 10.0, 0.1, 0.3, None, memory) for _ in range(3))
    a.record()
    b.record()
    truth = np.array([1.5, -0.7])
    for step in range(8):
        for mine in (a, b):
            for _ in range(4):
                angle = rng.uniform(0.0, np.pi)
                normal = np.array([np.cos(angle), np.sin(angle)])
                z = normal @ truth + rng.normal(0.0, 0.5)
                for area in (mine, pooled):
                    area.predict(float(step))
                    area.update(normal, -0.5 * (area.u.values - z) ** 2 / 0.25)
        from_a, from_b = a.shared(), b.shared()
        assert from_a is not None and from_b is not None
        a.take_shared(*from_b)
        b.take_shared(*from_a)
        for area in (a, b):
            assert np.allclose(area.b, pooled.b, atol=0.02), (step, area.b, pooled.b)
            assert np.allclose(area.P, pooled.P, rtol=0.1, atol=1e-3)
    assert a.shared() is None  # nothing new since the last round


def test_a_user_handed_to_another_engine_is_answered_as_by_one(hamburg_map: HdMap) -> None:
    """Engine A answers a car up to a border; its state (through bytes) and A's area
    evidence go to a fresh engine B, whose answer to the next fix is A's own; without
    them B answers as to a new track, far less sure."""
    scenario = hamburg_scenario()
    trace = simulate(hamburg_map, scenario, scenario.errors, seed=4)
    car = [f.measurement for f in trace.fixes if f.user == "car"][:80]
    a = Engine(hamburg_map, CONFIG)
    a.record_areas()
    for m in car[:-1]:
        a.process("car", m)
    state = a.export_user("car")
    assert state is not None and state.lanes is not None
    b = Engine(hamburg_map, CONFIG)
    everywhere = (-1e9, -1e9, 1e9, 1e9)
    assert b.import_areas("a", a.export_areas(everywhere)) == 1
    assert b.import_user("p2", user_from_bytes(user_to_bytes(state)))
    one, handed = a.process("car", car[-1]), b.process("p2", car[-1])
    fresh = Engine(hamburg_map, CONFIG).process("p3", car[-1])
    assert one is not None and handed is not None and fresh is not None
    assert (handed.segment, handed.lane) == (one.segment, one.lane)
    assert handed.accuracy == pytest.approx(one.accuracy, rel=0.1)  # b: evidence unblurred
    assert handed.probability == pytest.approx(one.probability, abs=0.02)
    assert abs(handed.latitude - one.latitude) < 3e-6  # ~0.3 m
    assert abs(handed.longitude - one.longitude) < 5e-6
    # what the hand-over saves: 10.5 m against 5.6 m (one car's along-road error is
    # known only from its turns, and that knowledge fades over evidence_memory)
    assert fresh.accuracy > 1.5 * one.accuracy
    with pytest.raises(HandoverError, match="version"):
        user_from_bytes(zlib.compress(b'{"v": 0}'))
    with pytest.raises(HandoverError, match=r"malformed|array"):
        user_from_bytes(zlib.compress(b'{"v": 1, "x": {"shape": [4], "data": "!!"}}'))
    with pytest.raises(HandoverError, match="compressed JSON"):
        user_from_bytes(b"{}")


def test_a_worker_refuses_a_hand_over_it_cannot_open_and_answers_the_fix(
    hamburg_map: HdMap,
) -> None:
    """A hand-over sealed under another identity, or no sealed text at all, is counted
    refused; the fix itself is answered, as a new track's."""
    import time

    from laas.worker.regions import split
    from laas.worker.service import LaasService, service_spec
    from ldm import Provider, Request
    from ldm.security.identity import SigningKey

    regions = split(hamburg_map, 2)

    def provider(k: int) -> Provider:  # never started: only its keys are used
        spec = service_spec(regions[k])
        return Provider.create(
            "mqtt://127.0.0.1:1", spec, lambda r: {}, identity=SigningKey.generate()
        )

    service = LaasService(hamburg_map, CONFIG, region=regions[1], shared=provider(1))
    other = provider(0)  # a regional worker under another identity
    scenario = hamburg_scenario()
    fix = simulate(hamburg_map, scenario, scenario.errors, seed=4).fixes[0].measurement
    now = int(time.time() * 1000)
    tokens = [other.seal_shared(b"x", "laas-handover/1"), "not sealed"]
    replies = service.handle_many(
        [
            Request(
                f"p{k}", f"c{k}", {**fix.model_dump(), "timestamp": now, "handover": t}, 0, True
            )
            for k, t in enumerate(tokens)
        ]
    )
    assert all("segment" in r for r in replies), replies
    assert service.stats.handover_refused == 2 and service.stats.handed_in == 0


def test_shared_areas_keep_the_time_their_evidence_is_faded_to() -> None:
    log = np.arange(6.0).reshape(2, 3)
    states = [
        AreaState((1.0, 2.0), 99, (4, 6, 7, 10), log, 12.5),
        AreaState((3.0, 4.0), 99, (0, 2, 0, 3), log, None),
    ]
    back = areas_from_bytes(areas_to_bytes(states))
    assert [(a.centre, a.window, a.t) for a in back] == [
        ((1.0, 2.0), (4, 6, 7, 10), 12.5),
        ((3.0, 4.0), (0, 2, 0, 3), None),
    ]
    assert np.array_equal(back[0].log, log)
    text = zlib.decompress(areas_to_bytes(states[:1]))
    with pytest.raises(HandoverError, match="malformed"):
        areas_from_bytes(zlib.compress(text.replace(b'"t":12.5', b'"t":"soon"')))
    with pytest.raises(HandoverError, match="finite"):
        areas_from_bytes(zlib.compress(text.replace(b'"t":12.5', b'"t":NaN')))
