"""The bridges against the paper's deployment: CAM stations, OwnTracks devices that send
garbage or fall silent, and a receiver behind Debian's gpsd fed by gpsfake."""

from __future__ import annotations

import contextlib
import json
import logging
import os
import shutil
import signal
import socket
import subprocess
import time
from pathlib import Path
from typing import Any

import pytest

from laas.bridges.cam import CamBridge
from laas.bridges.gpsd import gpsd_fixes, run_receiver
from laas.bridges.nmea import nmea_sentences
from laas.bridges.owntracks import OwnTracksBridge
from laas.bridges.pool import Answer, DevicePool, PoolConfig
from laas.cli import main
from laas.map.hdmap import HdMap
from laas.models import CorrectedPosition, GpsMeasurement
from laas.run.deployment import LocalDeployment
from ldm import BrokerSettings
from ldm.local.brokers import free_port, wait_for
from ldm.transport import Event, Message, Transport


def pool_for(d: LocalDeployment, **settings: Any) -> DevicePool:
    return DevicePool(PoolConfig(cluster=BrokerSettings(url=d.user_url), **d.trust, **settings))


def client(url: str, name: str, *subscriptions: str) -> tuple[Transport, list[Message]]:
    inbox: list[Message] = []

    def sink(e: Event) -> None:
        if isinstance(e, Message):
            inbox.append(e)

    t = Transport(BrokerSettings(url=url), client_id=name, sink=sink, name=name)
    for s in subscriptions:
        t.subscribe(s, 1)
    t.start(timeout=5)
    return t, inbox


def cam_message(fix: GpsMeasurement, i: int, uuid: str, station_id: int) -> dict[str, Any]:
    """Fix `i` of a passenger car as its-client publishes a CAM (ETSI units)."""
    return {
        "message_type": "cam",
        "source_uuid": uuid,
        "timestamp": fix.timestamp,
        "version": "2.1.0-dev",
        "message": {
            "protocol_version": 1,
            "station_id": station_id,
            "generation_delta_time": i,
            "basic_container": {
                "station_type": 5,
                "reference_position": {
                    "latitude": round(fix.latitude * 1e7),
                    "longitude": round(fix.longitude * 1e7),
                    "altitude": {"value": round(fix.altitude * 100)},
                },
            },
            "high_frequency_container": {
                "heading": round(fix.heading * 10) % 3600,
                "speed": round(fix.speed * 100),
            },
        },
    }


def now_shifted(fixes: list[GpsMeasurement], lead_s: float = 15.0) -> list[GpsMeasurement]:
    """The fixes moved in time so that the first is `lead_s` s ago (spacing kept)."""
    shift = int((time.time() - lead_s) * 1000) - fixes[0].timestamp
    return [f.model_copy(update={"timestamp": f.timestamp + shift}) for f in fixes]


def test_cam_stations_get_their_cam_back_with_the_lane(
    deployment: LocalDeployment, hamburg_map: HdMap, car: list[GpsMeasurement]
) -> None:
    bridge = CamBridge(BrokerSettings(url=deployment.user_url), pool_for(deployment), hamburg_map)
    station, inbox = client(deployment.user_url, "cam-station", "laas/cam/#")
    try:
        bridge.start()
        for i, fix in enumerate(now_shifted(car[:8])):
            cam = cam_message(fix, i, "car_1", 7)
            station.publish("v2x/cam/car_1", json.dumps(cam).encode(), 1)
            time.sleep(0.05)
        assert wait_for(lambda: len(inbox) >= 8, 15), (len(inbox), bridge.pool.stats)
        answers = [json.loads(m.payload) for m in inbox]
        assert {m.topic for m in inbox} == {"laas/cam/car_1"}
        lanes = [a["message"]["high_frequency_container"].get("lane_position") for a in answers]
        assert all(isinstance(lane, int) and 1 <= lane <= 13 for lane in lanes), lanes
        assert bridge.station_types == {"cam.car_1.7": "passengerCar"}
        assert bridge.pool.stats.opened == 1 and bridge.pool.stats.answered == 8
    finally:
        station.stop()
        bridge.stop()


def test_bad_owntracks_input_is_counted_logged_once_and_touches_no_one_else(
    deployment: LocalDeployment, car: list[GpsMeasurement], caplog: pytest.LogCaptureFixture
) -> None:
    pool = pool_for(deployment, track_timeout=1.5)
    bridge = OwnTracksBridge(BrokerSettings(url=deployment.user_url), pool)
    phone, inbox = client(deployment.user_url, "phones", "owntracks/+/+")
    try:
        bridge.start()
        with caplog.at_level(logging.WARNING, logger="laas.bridges.pool"):
            for i, fix in enumerate(now_shifted(car[:6])):
                location = {
                    "_type": "location",
                    "tst": fix.timestamp // 1000,
                    "lat": fix.latitude,
                    "lon": fix.longitude,
                    "vel": round(fix.speed * 3.6),
                    "cog": round(fix.heading) % 360,
                    "acc": 3,
                }
                phone.publish("owntracks/alice/phone", json.dumps(location).encode(), 1)
                garbage = [b"{", b'{"_type":"location","lat":"x"}', b"[1]"][i % 3]
                phone.publish("owntracks/mallory/junk", garbage, 1)
                time.sleep(0.1)

            def answered() -> list[Message]:
                return [m for m in list(inbox) if m.topic == "owntracks/alice/phone-lane"]

            assert wait_for(lambda: len(answered()) >= 6, 15), pool.stats
        lane = [json.loads(m.payload)["laas"] for m in answered()]
        assert all(x["segment"] is not None for x in lane)
        assert pool.stats.malformed == 6
        assert pool.stats.malformed_by_device == {"ot.mallory.junk": 6}
        junk = [r for r in caplog.records if "ot.mallory.junk" in r.getMessage()]
        assert len(junk) == 1, [r.getMessage() for r in junk]  # once per device per minute
        assert "ot.mallory.junk" not in pool.names()  # garbage opens no participant
        participant = pool.participant("ot.alice.phone")
        assert participant is not None and participant.transport.connected
        # silent for track_timeout: forgotten, its participant closed
        # (the device leaves the pool's table first, then its participant closes)
        assert wait_for(lambda: not participant.transport.connected, 10)
        assert pool.names() == [] and pool.stats.forgotten == 1
    finally:
        phone.stop()
        bridge.stop()


def gpsfake() -> str:
    found = shutil.which("gpsfake")
    if found is None or (shutil.which("gpsd") or shutil.which("gpsd", path="/usr/sbin")) is None:
        if os.environ.get("LAAS_REQUIRE_GPSD") == "1":  # CI installs gpsd
            pytest.fail("LAAS_REQUIRE_GPSD=1 but gpsd or gpsfake is not installed")
        pytest.skip(
            "gpsd and gpsfake are not installed: `apt-get install -y gpsd gpsd-clients` "
            "(Debian; gpsfake is in gpsd-clients) to run this test"
        )
    return found


def stop_group(process: subprocess.Popen[bytes]) -> None:
    """Stop `process` and every process of its group (gpsfake and its gpsd): SIGTERM,
    which gpsfake answers by stopping its gpsd, then SIGKILL for what is left after 10 s."""
    with contextlib.suppress(ProcessLookupError):
        os.killpg(process.pid, signal.SIGTERM)
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline:
        process.poll()  # reap gpsfake, so the group can empty
        try:
            os.killpg(process.pid, 0)
        except ProcessLookupError:
            break  # no process of the group is left
        time.sleep(0.1)
    else:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(process.pid, signal.SIGKILL)
    process.wait(5)


def _listening(port: int) -> bool:
    with socket.socket() as s:
        return s.connect_ex(("127.0.0.1", port)) == 0


@pytest.mark.timeout(60)
def test_a_receiver_behind_gpsd_is_answered(
    deployment: LocalDeployment, car: list[GpsMeasurement], tmp_path: Path
) -> None:
    program = gpsfake()
    fixes = now_shifted(car[:8], lead_s=30.0)
    log = tmp_path / "car.nmea"
    log.write_text("".join(s + "\r\n" for f in fixes for s in nmea_sentences(f)))
    port = free_port()
    fake = subprocess.Popen(
        [program, "-1", "-q", "-c", "0.2", "-P", str(port), str(log)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        start_new_session=True,  # gpsfake and the gpsd it starts: one process group
    )
    answers: list[Answer] = []
    try:
        deadline = time.monotonic() + 10
        while True:  # gpsfake starts gpsd, which then listens on the port
            try:
                source = gpsd_fixes("127.0.0.1", port, timeout=3)
                first = next(source)
                break
            except (OSError, StopIteration):
                if time.monotonic() > deadline or fake.poll() is not None:
                    raise AssertionError(f"gpsd did not serve: {fake.stderr}") from None
                time.sleep(0.2)
        with pool_for(deployment) as pool:

            def chain() -> Any:
                yield first
                yield from source

            sent = run_receiver(chain(), pool, "gpsd.test", answers.append)
            assert wait_for(lambda: len(answers) >= sent, 10)
    finally:
        stop_group(fake)
    # gpsd is gone with gpsfake (before, SIGKILL to gpsfake alone left gpsd running)
    assert not _listening(port), f"gpsd still listens on port {port} after the test"
    assert sent >= 6  # gpsd reports a TPV per RMC; it may miss the first cycle
    corrected = [a for a in answers if isinstance(a, CorrectedPosition)]
    assert len(corrected) == sent, answers
    # NMEA carries hundredths of a second: each answer is for one of the logged fixes
    assert all(min(abs(a.timestamp - f.timestamp) for f in fixes) < 10 for a in corrected)
    assert all(a.segment is not None for a in corrected)


def test_laas_gpsd_reads_an_nmea_file_and_prints_the_answers(
    deployment: LocalDeployment,
    car: list[GpsMeasurement],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    fixes = now_shifted(car[:5])
    log = tmp_path / "receiver.nmea"
    lines = [s for f in fixes for s in nmea_sentences(f)]
    lines.insert(3, "$GPRMC,123519,A,4807.038,N,01131.000,E,022.4,084.4,230394,003.1,W*00")
    log.write_text("\r\n".join(lines) + "\r\n")
    trust = ["--service-key", deployment.trust["service_keys"]["laas"]]
    trust += ["--core-key", deployment.trust["core_key"]]
    args = ["gpsd", "--nmea", str(log), "--cluster", deployment.user_url, "--speedup", "10"]
    started = time.monotonic()
    code = main([*args, *trust])
    out, err = capsys.readouterr()
    assert code == 0, err
    assert time.monotonic() - started >= 0.4  # paced: 4 s of the log at 10x
    assert f"replaying {log} at 10x the pace of its own timestamps, moved to now" in err
    answers = [CorrectedPosition.model_validate_json(line) for line in out.splitlines()]
    assert len(answers) == 5 and all(a.segment is not None for a in answers)
    assert "5 fixes sent, 5 answered, 0 refused, 0 lost, 1 malformed" in err
    assert main(["gpsd", "--cluster", deployment.user_url]) == 2
    assert "give one source" in capsys.readouterr().err


def test_laas_cam_serves_its_metrics_and_logs_json(
    deployment: LocalDeployment, hamburg_map: HdMap, car: list[GpsMeasurement], tmp_path: Path
) -> None:
    """`laas cam --metrics-port 0 --log-format json`, a real process: ready once
    connected; after five CAMs of one station and a malformed one, /metrics counts one
    device, five fixes answered and one malformed message, with no device in a label;
    its log lines are JSON objects with the bridge as component."""
    from tests.operations import LAAS, Child, Scrape, checks

    bridge = Child(
        [
            *LAAS,
            "cam",
            "--cluster",
            deployment.user_url,
            "--map",
            str(hamburg_map.source),
            "--metrics-port",
            "0",
            "--log-format",
            "json",
            "--log-level",
            "info",
        ],
        tmp_path / "cam.log",
        env={"LAAS_SERVICE_KEY": deployment.trust["service_keys"]["laas"]},
    )
    station, inbox = client(deployment.user_url, "cam-metrics-station", "laas/cam/#")
    try:
        base = bridge.metrics_base()
        assert wait_for(lambda: checks(base, "/readyz")[0] == 200, 15)
        assert checks(base, "/healthz")[0] == 200
        for i, fix in enumerate(now_shifted(car[:5])):
            cam = cam_message(fix, i, "car_9", 9)
            station.publish("v2x/cam/car_9", json.dumps(cam).encode(), 1)
            time.sleep(0.05)
        station.publish("v2x/cam/car_9", b"{not json", 1)
        assert wait_for(lambda: len(inbox) >= 5, 15), len(inbox)
        scrape = Scrape(base)
        assert wait_for(
            lambda: Scrape(base).value("laas_bridge_messages_total", outcome="malformed") == 1, 5
        )
        scrape = Scrape(base)
        assert scrape.value("laas_bridge_devices") == 1
        assert scrape.value("laas_bridge_sessions_total", event="opened") == 1
        assert scrape.value("laas_bridge_messages_total", outcome="fixes") == 5
        assert scrape.value("laas_bridge_messages_total", outcome="answered") == 5
        assert "car_9" not in scrape.text
    finally:
        station.stop()
        code = bridge.stop()
    assert code == 0, bridge.log()
    records = [line for line in bridge.log().splitlines() if line.startswith("{")]
    assert records, bridge.log()
    assert all(json.loads(line)["component"] == "laas-cam" for line in records)


def test_a_receiver_restarted_under_its_name_is_answered_and_told_why_if_again(
    deployment: LocalDeployment, car: list[GpsMeasurement], caplog: pytest.LogCaptureFixture
) -> None:
    """A bridge restarted under its name is answered: the user core's fresh grant lets its
    new ephemeral key in. Restarted again at once, the session's budget of key changes is
    spent, the core refuses the new key within its rekey interval, and the bridge says so,
    and what to do."""
    fixes = now_shifted(car[:6], lead_s=10.0)
    with pool_for(deployment) as first:
        run_receiver(fixes[:2], first, "gpsd.restarted", lambda _a: None)
        assert first.drain(10) and first.stats.answered == 2
    with pool_for(deployment) as again:
        run_receiver(fixes[2:4], again, "gpsd.restarted", lambda _a: None)
        assert again.drain(10)
    assert again.stats.answered == 2, again.stats
    with caplog.at_level(logging.WARNING), pool_for(deployment) as third:
        run_receiver(fixes[4:], third, "gpsd.restarted", lambda _a: None)
        assert third.drain(10)
    assert third.stats.answered == 0 and third.stats.lost == 2, third.stats
    assert "still holds the session of an earlier participant of this name" in caplog.text
    assert "restart under another name" in caplog.text


def test_a_device_s_fixes_reach_the_service_in_order_and_once(
    deployment: LocalDeployment, car: list[GpsMeasurement]
) -> None:
    """Fixes that arrive while a device's session opens, and after, go on in the order
    they came; a fix not newer than its device's last (a QoS 1 redelivery, a phone's
    second fix in the same second of ``tst``) is dropped by the bridge, not refused by
    the service as stale."""
    devices, count, gap = 4, 50, 0.03
    start = int((time.time() - 10.0) * 1000)
    fixes = [f.model_copy(update={"timestamp": start + 100 * i}) for i, f in enumerate(car[:count])]
    pool = pool_for(deployment)
    with pool:
        for i, fix in enumerate(fixes):
            for d in range(devices):
                pool.submit(f"order.{d}", fix, lambda _a: None)
                if i == count // 2:  # the same fix again
                    pool.submit(f"order.{d}", fix, lambda _a: None)
            time.sleep(gap)
        assert pool.drain(30.0), pool.stats
        stats = pool.stats
    assert stats.stale == devices, stats
    assert stats.refused == 0, stats
    # lost: only what the user core refused for its rate, the fixes that waited for the
    # session going on at once (a burst of at most 20 per client)
    assert stats.answered + stats.lost == devices * count, stats
    assert stats.answered >= 0.9 * devices * count, stats
