"""A bridge in front of regional workers: each device's fixes go to the worker of their
region (`laas.discovery`, `ldm.RoutedSession`), across the border and back."""

from __future__ import annotations

import json
import time
from collections.abc import Callable

import pytest

from laas.bridges.owntracks import OwnTracksBridge
from laas.bridges.pool import DevicePool, PoolConfig
from laas.map.hdmap import HdMap
from laas.run.deployment import LocalDeployment
from laas.sim.scenario import ErrorModel, hamburg_scenario, simulate
from ldm import BrokerSettings, Participant
from tests.ldm.deployment import has_service

from .test_live import client, now_shifted
from .test_owntracks_acl import owntracks_location


def _wait(done: Callable[[], bool], timeout: float) -> bool:
    deadline = time.monotonic() + timeout
    while not done():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.05)
    return True


@pytest.mark.timeout(120)
def test_owntracks_phones_are_answered_by_two_regional_workers(hamburg_map: HdMap) -> None:
    """Three phones (the Hamburg road users, who all cross the border between the two
    regions) through `laas owntracks`: every fix is answered, and both workers answer."""
    trace = simulate(hamburg_map, hamburg_scenario(), ErrorModel(), 0)
    users = sorted({f.user for f in trace.fixes})
    fixes = {u: now_shifted([f.measurement for f in trace.fixes if f.user == u]) for u in users}
    with LocalDeployment(hamburg_map, brokers="embedded", regions=2) as deployment:
        assert [p.name for p, _ in deployment.workers] == ["laas-1of2", "laas-2of2"]
        # the phones start once the user cluster lists both regions (a session opened
        # before would find no provider for a position in the region not yet listed)
        with Participant.create(
            BrokerSettings(url=deployment.user_url), **deployment.trust
        ) as probe:
            assert _wait(
                lambda: all(has_service(probe, n)() for n in ("laas-1of2", "laas-2of2")), 15
            )
        pool = DevicePool(
            PoolConfig(cluster=BrokerSettings(url=deployment.user_url), **deployment.trust)
        )
        phones, inbox = client(deployment.user_url, "regional-phones", "owntracks/+/+")
        with OwnTracksBridge(BrokerSettings(url=deployment.user_url), pool):
            for i in range(len(fixes[users[0]])):
                for u in users:
                    location = owntracks_location(fixes[u][i], fixes[u][i].timestamp // 1000)
                    phones.publish(f"owntracks/{u}/phone", json.dumps(location).encode(), 1, False)
                time.sleep(0.1)  # ten times live: the test is of routing, not of load
            total = sum(len(f) for f in fixes.values())
            assert _wait(
                lambda: pool.stats.answered + pool.stats.lost + pool.stats.refused >= total, 30
            )

            def answers() -> int:
                return sum(m.topic.endswith("-lane") for m in inbox)

            assert _wait(lambda: answers() >= pool.stats.answered, 10), (answers(), pool.stats)
            shares = [service.stats.answered for _, service in deployment.workers]
            stats = pool.stats
        phones.stop()
    # Nothing is lost and nothing refused: the fixes that came while a phone's session
    # opened go on before the later ones (`laas.bridges.pool`), so none is stale.
    assert stats.lost == 0 and stats.refused == 0 and stats.answered == total, stats
    assert sum(shares) == stats.answered and min(shares) > 0, shares
