"""OwnTracks end to end on Mosquitto with the shipped user-cluster ACL and passwords:
each phone is an account of its own, the bridge another, each device's participant a
third (``--device-accounts``). A phone gets its lane position back as a friend, and
never sees another user's; an encrypting phone's answers come back sealed."""

from __future__ import annotations

import json
import logging
import subprocess
import time
from typing import Any

import pytest

from laas.bridges.owntracks import OwnTracksBridge, OwnTracksConfig, read_location, secret_key
from laas.bridges.pool import DevicePool, PoolConfig
from laas.map.hdmap import HdMap
from laas.models import GpsMeasurement
from laas.worker.service import start_worker
from ldm import Core
from ldm.config import BrokerSettings
from ldm.local.brokers import MosquittoBroker, wait_for
from ldm.local.pytest_plugin import need_mosquitto
from ldm.transport import Connected, Event, Message, Transport

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


def _documented_device_block() -> str:
    """The block the shipped ACL shows, commented, for a user's further device."""
    text = (SECURITY / "acl-user-cluster").read_text()
    lines = [ln[4:] for ln in text.splitlines() if ln.startswith(("#   user ", "#   topic "))]
    assert lines == ["user alice-tablet", "topic readwrite owntracks/alice/#"], lines
    return "\n".join(lines) + "\n"


@pytest.mark.mosquitto
@pytest.mark.timeout(90)
def test_two_devices_of_one_user_each_with_its_account_stay_connected(
    hamburg_map: HdMap, car: list[GpsMeasurement]
) -> None:
    """Alice's phone (account alice) and tablet (account alice-tablet, with the block the
    shipped ACL documents) both get their lanes and are never thrown off; two devices
    sharing the account alice throw each other off (the broker makes every client id
    its account name), which is why each device needs its own."""
    need_mosquitto()
    acl = (SECURITY / "acl-user-cluster").read_text() + _documented_device_block()
    acl += (SECURITY / "acl-service-cluster").read_text()
    broker = MosquittoBroker(allow_anonymous=False, acl=acl)
    users = ("ldm-core-user", "laas-worker", "laas-owntracks", "alice", "alice-tablet")
    passwd, passwords = password_file(broker.directory, *users)
    device_password = "device-pw-8"
    subprocess.run(
        ["bash", str(SECURITY / "make-passwd.sh"), str(passwd),
         f"ot.alice.phone={device_password}", f"ot.alice.tablet={device_password}"],
        check=True, capture_output=True, env={"PATH": "/usr/bin:/bin", "MODE": "0644"},
    )  # fmt: skip
    broker.config_file.write_text(
        broker.config_file.read_text() + f"password_file {passwd}\nuse_username_as_clientid true\n"
    )

    def account(user: str) -> BrokerSettings:
        return BrokerSettings(url=broker.url, username=user, password=passwords[user])

    events: dict[str, list[Event]] = {}

    def device(user: str, client_id: str) -> Transport:
        inbox = events.setdefault(client_id, [])
        t = Transport(account(user), client_id=client_id, sink=inbox.append, name=client_id)
        t.subscribe("owntracks/+/+", 1)
        return t

    def connects(name: str) -> int:
        return sum(isinstance(e, Connected) for e in events[name])

    def answers(name: str, device_name: str) -> int:
        topic = f"owntracks/alice/{device_name}-lane"
        return sum(isinstance(e, Message) and e.topic == topic for e in events[name])

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
        bridge = OwnTracksBridge(account("laas-owntracks"), pool)
        phone, tablet = device("alice", "alice"), device("alice-tablet", "alice-tablet")
        try:
            bridge.start(timeout=5)
            phone.start(timeout=5)
            tablet.start(timeout=5)
            t0 = int(time.time()) - 10
            for i, fix in enumerate(car[:6]):
                plain = json.dumps(owntracks_location(fix, t0 + i)).encode()
                phone.publish("owntracks/alice/phone", plain, 1)
                tablet.publish("owntracks/alice/tablet", plain, 1)
                time.sleep(0.1)
            assert wait_for(
                lambda: answers("alice", "phone") >= 6 and answers("alice-tablet", "tablet") >= 6,
                20,
            ), pool.stats
            time.sleep(1.0)  # a device thrown off would have reconnected by now
            assert connects("alice") == connects("alice-tablet") == 1
            assert sorted(pool.names()) == ["ot.alice.phone", "ot.alice.tablet"]
        finally:
            for t in (phone, tablet):
                t.stop()
        # the old advice: both devices on the user's account
        first, second = device("alice", "shared-1"), device("alice", "shared-2")
        try:
            first.start(timeout=5)
            second.start(timeout=5)
            assert wait_for(lambda: connects("shared-1") + connects("shared-2") > 2, 10)
        finally:
            for t in (first, second):
                t.stop()
            bridge.stop()
            worker.stop()
            core.stop()


@pytest.mark.mosquitto
@pytest.mark.timeout(60)
def test_a_bridge_that_hears_nothing_says_what_to_check(
    hamburg_map: HdMap, caplog: pytest.LogCaptureFixture
) -> None:
    """A CAM bridge on an account the ACL does not let read the CAMs: Mosquitto grants
    its subscription and delivers nothing, so the bridge itself says what to check."""
    from laas.bridges.cam import CamBridge

    need_mosquitto()
    broker = MosquittoBroker(allow_anonymous=False, acl=(SECURITY / "acl-user-cluster").read_text())
    passwd, passwords = password_file(broker.directory, "laas-nobody", "its-car-1")
    broker.config_file.write_text(
        broker.config_file.read_text() + f"password_file {passwd}\nuse_username_as_clientid true\n"
    )
    with broker:
        nobody = BrokerSettings(
            url=broker.url, username="laas-nobody", password=passwords["laas-nobody"]
        )
        pool = DevicePool(PoolConfig(cluster=nobody))
        bridge = CamBridge(nobody, pool, hamburg_map)
        bridge.quiet_after = 1.0
        station = Transport(
            BrokerSettings(url=broker.url, username="its-car-1", password=passwords["its-car-1"]),
            client_id="its-car-1",
            sink=lambda _e: None,
        )
        try:
            with caplog.at_level(logging.WARNING, logger="laas.bridges.mqtt"):
                bridge.start(timeout=5)
                station.start(timeout=5)
                station.publish("v2x/cam/its-car-1/cam", b'{"message_type": "cam"}', 1)
                assert wait_for(lambda: "no message on v2x/cam/#" in caplog.text, 5), caplog.text
        finally:
            station.stop()
            bridge.stop()
    assert bridge.received == 0
    assert "account laas-nobody" in caplog.text and "acl-user-cluster" in caplog.text
