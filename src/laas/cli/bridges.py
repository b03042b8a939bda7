"""The bridges' commands: `laas owntracks`, `laas gpsd` and `laas cam` (`laas.bridges`),
and the per-device account flags `laas simulate` shares with them."""

from __future__ import annotations

import argparse
import logging
import os
import socket
import sys
import time
from collections.abc import Iterable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from laas.bridges.metrics import watch_bridge
from laas.bridges.pool import Answer, DevicePool, Malformed, PoolConfig
from laas.cli.common import Subcommands, connection_args, pinned_key_args
from laas.errors import ConfigError
from laas.models import CorrectedPosition, GpsMeasurement
from ldm import BrokerSettings
from ldm.config import build
from ldm.ops.logs import configure
from ldm.ops.process import broker_settings, operations_args, start_metrics, wait_for_signal

if TYPE_CHECKING:
    from laas.map.hdmap import HdMap

__all__ = ["add_bridges", "device_account_args"]


def _logging(a: argparse.Namespace) -> None:
    configure(
        getattr(a, "log_format", None),  # laas gpsd, a run that ends: LDM_LOG_FORMAT only
        component=f"laas-{a.command}",
        level=getattr(logging, a.log_level.upper()),
        text_format="ts=%(asctime)s level=%(levelname)s logger=%(name)s msg=%(message)s",
    )


def _own_broker(a: argparse.Namespace) -> BrokerSettings:
    if not a.cluster:
        raise ConfigError(
            "give the user-cluster broker: --cluster mqtt://HOST:PORT (or LAAS_CLUSTER)"
        )
    return broker_settings(a.cluster, a.ca_file, a.username, a.password_env)


def _pool(a: argparse.Namespace, own: BrokerSettings, hdmap: HdMap | None = None) -> DevicePool:
    devices = own
    if a.device_accounts:
        devices = broker_settings(a.cluster, a.ca_file, "device", a.device_password_env)
    config = build(
        PoolConfig,
        cluster=devices,
        device_accounts=a.device_accounts,
        service_keys={"laas": a.service_key} if a.service_key else {},
        core_key=a.core_key,
        track_timeout=a.track_timeout,
    )
    return DevicePool(config, hdmap=hdmap)


def device_account_args(p: argparse.ArgumentParser, devices: str = "device") -> None:
    """--device-accounts and --device-password-env: the one spelling of per-device
    accounts in `laas simulate`, `gpsd`, `owntracks` and `cam`."""
    p.add_argument(
        "--device-accounts",
        action="store_true",
        help=f"log each {devices} in as its own broker account, named as its client id "
        "(PREFIX + names), with the password in --device-password-env",
    )
    p.add_argument(
        "--device-password-env",
        default="LAAS_DEVICE_PASSWORD",
        help="environment variable holding the device accounts' password",
    )


def _pool_args(p: argparse.ArgumentParser) -> None:
    device_account_args(p)
    pinned_key_args(p)
    p.add_argument(
        "--track-timeout",
        type=float,
        default=60.0,
        help="forget a device silent for this long, s (default 60)",
    )
    p.add_argument(
        "--log-level",
        default=os.environ.get("LAAS_LOG_LEVEL", "warning"),
        choices=["debug", "info", "warning", "error"],
        help="log lines of this level and above, on stderr (env LAAS_LOG_LEVEL)",
    )


def _serve(bridge: Any, what: str, a: argparse.Namespace) -> int:
    served = start_metrics(a, f"laas {what}")  # /readyz: 503 until the bridge is connected
    if served is not None:
        watch_bridge(
            served[0],
            f"laas {what}",
            bridge.pool,
            alive=lambda: bridge.alive,
            connected=lambda: bridge.transport.connected,
        )
    bridge.start()
    print(f"laas {what}: serving on {bridge.transport.settings.url}", file=sys.stderr, flush=True)
    try:
        wait_for_signal()
    finally:
        if served is not None:
            served[1].stop()
        bridge.stop()
        s = bridge.pool.stats
        print(
            f"laas {what}: stopped; {s.opened} devices opened, {s.answered} answered, "
            f"{s.refused} refused, {s.lost} lost, {s.malformed} malformed, "
            f"{s.stale} not newer than their device's last (dropped)",
            file=sys.stderr,
            flush=True,
        )
    return 0


def _cmd_owntracks(a: argparse.Namespace) -> int:
    from laas.bridges.owntracks import OwnTracksBridge, OwnTracksConfig, read_secrets

    _logging(a)
    own = _own_broker(a)
    secrets = read_secrets(a.secrets) if a.secrets else {}
    config = build(OwnTracksConfig, prefix=a.prefix, secrets=secrets, card_name=a.card_name)
    return _serve(OwnTracksBridge(own, _pool(a, own), config), "owntracks", a)


def _cmd_cam(a: argparse.Namespace) -> int:
    from laas.bridges.cam import CamBridge, CamConfig
    from laas.map.geojson import read_geojson_file

    _logging(a)
    own = _own_broker(a)
    config = build(CamConfig, topic_filter=a.topic, answer_topic=a.answer_topic, prefix=a.prefix)
    hdmap = read_geojson_file(a.map)  # lane numbers, and the devices' own answers while silent
    return _serve(CamBridge(own, _pool(a, own, hdmap), hdmap, config), "cam", a)


def _print_answer(answer: Answer) -> None:
    if isinstance(answer, CorrectedPosition):
        print(answer.model_dump_json(), flush=True)


def _cmd_gpsd(a: argparse.Namespace) -> int:
    from laas.bridges.gpsd import gpsd_fixes, paced, parse_address, run_receiver
    from laas.bridges.nmea import read_nmea_file

    _logging(a)
    if (a.gpsd is None) == (a.nmea is None):
        raise ConfigError("give one source: --gpsd HOST:PORT or --nmea FILE_OR_DEVICE")
    if a.speedup <= 0:
        raise ConfigError(f"--speedup {a.speedup:g}: give a factor above 0")
    own = _own_broker(a)
    fixes: Iterable[GpsMeasurement | Malformed]
    if a.gpsd is not None:
        try:
            host, port = parse_address(a.gpsd)
        except ValueError as exc:
            raise ConfigError(str(exc)) from None
        fixes = gpsd_fixes(host, port)
    elif a.nmea.is_file():  # a recorded log: at its own pace, its times moved to now
        fixes = paced(read_nmea_file(a.nmea, now=time.time()), speedup=a.speedup)
        print(
            f"laas gpsd: replaying {a.nmea} at {a.speedup:g}x the pace of its own "
            "timestamps, moved to now",
            file=sys.stderr,
            flush=True,
        )
    else:  # a serial device: live, dated against this machine's clock (week rollover)
        fixes = read_nmea_file(a.nmea, now=time.time())
    with _pool(a, own) as pool:
        try:
            sent = run_receiver(fixes, pool, a.name, _print_answer)
        except OSError as exc:
            raise ConfigError(f"cannot read the receiver: {exc}") from None
        pool.drain(a.reply_timeout)
        s = pool.stats
        print(
            f"laas gpsd: {sent} fixes sent, {s.answered} answered, {s.refused} refused, "
            f"{s.lost} lost, {s.malformed} malformed, {s.stale} not newer than the last "
            "(dropped)",
            file=sys.stderr,
        )
        if sent == 0:
            print(
                "laas gpsd: the receiver gave no fix: no valid RMC (status A) nor GGA "
                "with a fix quality above 0 (or, from gpsd, no TPV of mode 2 or 3); is "
                "the antenna outside, and is it NMEA 0183?",
                file=sys.stderr,
            )
    return 0


def add_bridges(sub: Subcommands) -> None:
    """`laas owntracks`, `laas gpsd` and `laas cam`."""
    p = sub.add_parser("owntracks", help="OwnTracks phones as participants; answers as friends")
    connection_args(p, "LAAS")
    p.add_argument("--prefix", default="ot.", help="device client ids: PREFIX + user.device")
    p.add_argument(
        "--secrets",
        type=Path,
        help="OwnTracks payload secrets, `user-device secret` per line (keep it 0600)",
    )
    p.add_argument("--card-name", default="my lane position", help="the answers' name in the app")
    _pool_args(p)
    operations_args(p, "LAAS")
    p.set_defaults(func=_cmd_owntracks)

    p = sub.add_parser("gpsd", help="a receiver (gpsd or NMEA) as one participant")
    connection_args(p, "LAAS")
    p.add_argument("--gpsd", help="gpsd daemon, HOST:PORT (e.g. localhost:2947)")
    p.add_argument(
        "--nmea",
        type=Path,
        help="NMEA 0183 serial device, or a recorded log replayed at its own pace (RMC, GGA, "
        "GST, VTG)",
    )
    p.add_argument(
        "--name",
        default=f"gpsd.{socket.gethostname().split('.')[0]}",
        help="the receiver's client id (default gpsd.HOSTNAME)",
    )
    p.add_argument(
        "--reply-timeout", type=float, default=10.0, help="wait this long for the last answers, s"
    )
    p.add_argument(
        "--speedup",
        type=float,
        default=1.0,
        help="--nmea FILE (a recorded log): replay this much faster than its own timestamps "
        "(default 1; above 1 the worker must allow it: laas worker --max-speedup)",
    )
    _pool_args(p)
    p.set_defaults(func=_cmd_gpsd)

    p = sub.add_parser("cam", help="ETSI CAM stations (its-client JSON) as participants")
    connection_args(p, "LAAS")
    p.add_argument("--map", required=True, help="the lane map the worker serves (lane numbers)")
    p.add_argument("--topic", default="v2x/cam/#", help="topic filter of the CAMs")
    p.add_argument(
        "--answer-topic", default="laas/cam/{source_uuid}", help="topic template of the answers"
    )
    p.add_argument("--prefix", default="cam.", help="device client ids: PREFIX + uuid.station")
    _pool_args(p)
    operations_args(p, "LAAS")
    p.set_defaults(func=_cmd_cam)
