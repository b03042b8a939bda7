"""A phone whose clock jumps ahead once, through the OwnTracks bridge and a real broker:
the live worker refuses that fix, and the phone's later fixes are answered as before."""

from __future__ import annotations

import json
import logging
import threading

import pytest

from laas.bridges.owntracks import OwnTracksBridge
from laas.map.hdmap import HdMap
from laas.models import GpsMeasurement
from laas.run.deployment import LocalDeployment
from laas.worker import WorkerConfig
from ldm import BrokerSettings
from ldm.transport import Event, Message, Transport

from .test_live import now_shifted, pool_for

AHEAD_MS = 5 * 60 * 1000  # a phone clock 5 minutes fast, for one fix


def location(fix: GpsMeasurement, timestamp_ms: int) -> bytes:
    return json.dumps(
        {
            "_type": "location",
            "tst": timestamp_ms // 1000,
            "lat": round(fix.latitude, 7),
            "lon": round(fix.longitude, 7),
            "vel": round(fix.speed * 3.6),
            "cog": round(fix.heading) % 360,
            "acc": 3,
        }
    ).encode()


@pytest.mark.timeout(90)
def test_one_fix_dated_ahead_does_not_lock_the_phone_out_in_the_bridge(
    hamburg_map: HdMap, car: list[GpsMeasurement], caplog: pytest.LogCaptureFixture
) -> None:
    # A live worker (max_speedup 1): it refuses a fix dated 5 minutes ahead.
    with LocalDeployment(hamburg_map, limits=WorkerConfig()) as deployment:
        pool = pool_for(deployment)
        bridge = OwnTracksBridge(BrokerSettings(url=deployment.user_url), pool)
        answers: list[dict[str, int]] = []
        enough = threading.Event()
        wanted = 12  # 4 fixes before the one dated ahead, 8 after it

        def sink(e: Event) -> None:
            if isinstance(e, Message) and e.topic == "owntracks/alice/phone-lane":
                answers.append(json.loads(e.payload))
                if len(answers) >= wanted:
                    enough.set()

        phone = Transport(
            BrokerSettings(url=deployment.user_url), client_id="alice", sink=sink, name="alice"
        )
        phone.subscribe("owntracks/alice/+", 1)
        fixes = now_shifted(car[:12], lead_s=20.0)
        try:
            bridge.start()
            phone.start(timeout=5)
            with caplog.at_level(logging.WARNING, logger="laas.bridges.pool"):
                for fix in fixes[:4]:
                    phone.publish("owntracks/alice/phone", location(fix, fix.timestamp), 1)
                ahead = fixes[3].timestamp + 1000 + AHEAD_MS
                phone.publish("owntracks/alice/phone", location(fixes[4], ahead), 1)
                for fix in fixes[4:]:
                    phone.publish("owntracks/alice/phone", location(fix, fix.timestamp), 1)
                answered = enough.wait(30)
                assert pool.drain(10), pool.stats
        finally:
            phone.stop()
            bridge.stop()
    assert answered, (len(answers), pool.stats)
    # every fix but the one dated ahead answered, in the phone's own time
    assert sorted(a["tst"] for a in answers) == [f.timestamp // 1000 for f in fixes]
    assert pool.stats.refused == 1 and pool.stats.stale == 0, pool.stats
    refusals = [r.getMessage() for r in caplog.records if "refused (clock)" in r.getMessage()]
    assert len(refusals) == 1 and "ahead" in refusals[0], refusals
