"""OwnTracks end to end on Mosquitto with the shipped user-cluster ACL and passwords:
each phone is an account of its own, the bridge another, each device's participant a
third (``--device-accounts``). A phone gets its lane position back as a friend, and
never sees another user's; an encrypting phone's answers come back sealed."""

from __future__ import annotations

import json
import subprocess
import time
from typing import Any

import pytest

from laas.bridges.owntracks import OwnTracksBridge, OwnTracksConfig, read_location, secret_key
from laas.bridges.pool import DevicePool, PoolConfig
from laas.map.hdmap import HdMap
from laas.models import GpsMeasurement
from laas.service import start_worker
from ldm import Core
from ldm.brokers import MosquittoBroker, wait_for
from ldm.config import BrokerSettings
from ldm.pytest_plugin import need_mosquitto
from ldm.transport import Event, Message, Transport

from ..test_hardening import CORE, SECURITY, password_file

SECRET = "mysecreTpass01"  # the booklet's example secret (features/encrypt.md)


def owntracks_location(fix: GpsMeasurement, tst: int) -> dict[str, Any]:
    """What the app publishes (booklet tech/json: acc, vel in km/h, cog)."""
    return {
        "_type": "location",
        "tid": "ph",
        "tst": tst,
        "lat": round(fix.latitude, 7),
        "lon": round(fix.longitude, 7),
        "acc": 3,
        "vel": round(fix.speed * 3.6),
        "cog": round(fix.heading) % 360,
        "conn": "m",
    }


@pytest.mark.mosquitto
@pytest.mark.timeout(90)
def test_a_phone_gets_its_lane_as_a_friend_and_nobody_elses(
    hamburg_map: HdMap, car: list[GpsMeasurement]
) -> None:
    need_mosquitto()
    acl = (SECURITY / "acl-user-cluster").read_text() + (
        SECURITY / "acl-service-cluster"
    ).read_text()
    broker = MosquittoBroker(allow_anonymous=False, acl=acl)
    passwd, passwords = password_file(
        broker.directory, "ldm-core-user", "laas-worker", "laas-owntracks", "alice", "bob"
    )
    device_password = "device-pw-7"  # the devices' accounts share one password
    subprocess.run(
        ["bash", str(SECURITY / "make-passwd.sh"), str(passwd),
         f"ot.alice.phone={device_password}", f"ot.bob.phone={device_password}"],
        check=True, capture_output=True, env={"PATH": "/usr/bin:/bin", "MODE": "0644"},
    )  # fmt: skip
    broker.config_file.write_text(
        broker.config_file.read_text() + f"password_file {passwd}\nuse_username_as_clientid true\n"
    )

    def account(user: str) -> BrokerSettings:
        return BrokerSettings(url=broker.url, username=user, password=passwords[user])

    inboxes: dict[str, list[Message]] = {"alice": [], "bob": []}

    def phone(user: str) -> Transport:
        def sink(e: Event) -> None:
            if isinstance(e, Message):
                inboxes[user].append(e)

        t = Transport(account(user), client_id=user, sink=sink, name=user)
        for flt in ("owntracks/+/+", "owntracks/+/+/info", "owntracks/#"):  # as the app, and more
            t.subscribe(flt, 1)
        return t

    with broker:
        core = Core.create("single", account("ldm-core-user"), None, **CORE).start(timeout=5)
        worker, _service = start_worker(account("laas-worker"), hamburg_map)
        pool = DevicePool(
            PoolConfig(
                cluster=BrokerSettings(url=broker.url, username="x", password=device_password),
                device_accounts=True,
                service_keys={"laas": worker.identity.public},
                core_key=core.public_key,
            )
        )
        bridge = OwnTracksBridge(
            account("laas-owntracks"), pool, OwnTracksConfig(secrets={"bob-phone": SECRET})
        )
        phones = {user: phone(user) for user in inboxes}
        try:
            bridge.start(timeout=5)
            for t in phones.values():
                t.start(timeout=5)
            t0 = int(time.time()) - 10
            key = secret_key(SECRET)
            for i, fix in enumerate(car[:6]):
                plain = json.dumps(owntracks_location(fix, t0 + i)).encode()
                phones["alice"].publish("owntracks/alice/phone", plain, 1)
                sealed = {"_type": "encrypted", "data": _seal(plain, key)}
                phones["bob"].publish("owntracks/bob/phone", json.dumps(sealed).encode(), 1)
                time.sleep(0.1)

            def answers(user: str) -> list[Message]:
                return [m for m in list(inboxes[user]) if m.topic == f"owntracks/{user}/phone-lane"]

            assert wait_for(lambda: len(answers("alice")) >= 6 and len(answers("bob")) >= 6, 20), (
                pool.stats
            )
            time.sleep(0.3)  # anything that would leak has had time to arrive
            # each phone reads its own topics only: never the other's fixes or answers
            assert all(m.topic.startswith("owntracks/alice/") for m in inboxes["alice"])
            assert all(m.topic.startswith("owntracks/bob/") for m in inboxes["bob"])
            cards = [m for m in inboxes["alice"] if m.topic == "owntracks/alice/phone-lane/info"]
            assert [json.loads(c.payload)["name"] for c in cards] == ["my lane position"]
            lanes = [json.loads(m.payload) for m in answers("alice")]
            assert all(a["_type"] == "location" and a["tid"] == "LP" for a in lanes)
            assert all(a["laas"]["segment"] is not None for a in lanes), lanes
            assert {a["tst"] for a in lanes} == {t0 + i for i in range(6)}
            # bob encrypts: his answers come back sealed with his secret
            for m in answers("bob"):
                assert json.loads(m.payload)["_type"] == "encrypted"
                location = read_location(m.payload, key)
                assert location is not None and location.tid == "LP"
            # each device was its own participant, logged in as its own account
            assert sorted(pool.names()) == ["ot.alice.phone", "ot.bob.phone"]
            assert pool.stats.opened == 2 and pool.stats.malformed == 0
            assert core.session_count == 2
        finally:
            for t in phones.values():
                t.stop()
            bridge.stop()
            worker.stop()
            core.stop()


def _seal(plain: bytes, key: bytes) -> str:
    from laas.bridges.owntracks import encrypt

    return str(json.loads(encrypt(plain, key))["data"])
