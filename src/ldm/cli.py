"""The `ldm` command line: run a core or an embedded broker until interrupted.

    ldm broker --port 1883
    ldm core --name user --cluster mqtt://localhost:1883 --backbone mqtt://hub:1883

Passwords come from environment variables (``--password-env``, default LDM_PASSWORD;
``--backbone-password-env``, default LDM_BACKBONE_PASSWORD), never from the command line.
"""

from __future__ import annotations

import argparse
import logging
import signal
import threading
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from ldm.broker import EmbeddedBroker
from ldm.config import BrokerSettings, CoreConfig, build
from ldm.core import Core
from ldm.errors import LdmError

__all__ = ["broker_settings", "core_config", "main", "wait_for_signal"]


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="ldm", description=__doc__.splitlines()[0])
    parser.add_argument("-v", "--verbose", action="store_true", help="log at INFO level")
    sub = parser.add_subparsers(dest="command", required=True)

    broker = sub.add_parser("broker", help="run the embedded MQTT 3.1.1 broker (amqtt)")
    broker.add_argument("--host", default="127.0.0.1", help="address to listen on")
    broker.add_argument("--port", type=int, default=1883, help="port (0 picks a free one)")

    core = sub.add_parser("core", help="run an LDM core for one cluster")
    core.add_argument("--name", required=True, help="core name, unique in the deployment")
    core.add_argument("--cluster", required=True, help="cluster broker, mqtt[s]://HOST:PORT")
    core.add_argument("--backbone", help="inter-cluster broker, mqtt[s]://HOST:PORT")
    core.add_argument("--ca-file", type=Path, help="CA certificates for mqtts:// brokers")
    core.add_argument("--username", help="user name on the cluster broker")
    core.add_argument("--password-env", default="LDM_PASSWORD", help="env var with its password")
    core.add_argument("--backbone-username", help="user name on the backbone broker")
    core.add_argument(
        "--backbone-password-env",
        default="LDM_BACKBONE_PASSWORD",
        help="env var with the backbone password",
    )
    for option, field in [
        ("--rotation-period", "rotation_period"),
        ("--grace", "grace"),
        ("--idle-timeout", "idle_timeout"),
        ("--service-ttl", "service_ttl"),
        ("--max-age", "max_age"),
        ("--rate", "rate"),
        ("--burst", "burst"),
        ("--max-clock-skew", "max_clock_skew"),
    ]:
        default = CoreConfig.model_fields[field].default
        unit = "messages/s" if field == "rate" else "messages" if field == "burst" else "seconds"
        core.add_argument(option, type=float, default=default, help=f"{unit} (default {default})")
    core.add_argument(
        "--max-payload",
        type=int,
        default=CoreConfig.model_fields["max_payload"].default,
        help="largest participant message, bytes",
    )
    core.add_argument("--data-qos", type=int, default=0, choices=(0, 1, 2), help="QoS of data")
    return parser


def broker_settings(
    url: str, ca_file: Path | None, username: str | None, env: str
) -> BrokerSettings:
    """Broker settings from command-line values; the password is read from `env`."""
    values: dict[str, Any] = {"url": url, "ca_file": ca_file, "username": username}
    if username is not None:
        values["password_env"] = env
    return build(BrokerSettings, **values)


def core_config(args: argparse.Namespace) -> CoreConfig:
    """The CoreConfig the `ldm core` arguments describe."""
    cluster = broker_settings(args.cluster, args.ca_file, args.username, args.password_env)
    backbone = None
    if args.backbone:
        backbone = broker_settings(
            args.backbone, args.ca_file, args.backbone_username, args.backbone_password_env
        )
    return build(
        CoreConfig,
        name=args.name,
        cluster=cluster,
        backbone=backbone,
        rotation_period=args.rotation_period,
        grace=args.grace,
        idle_timeout=args.idle_timeout,
        service_ttl=args.service_ttl,
        max_age=args.max_age,
        data_qos=args.data_qos,
        rate=args.rate,
        burst=args.burst,
        max_clock_skew=args.max_clock_skew,
        max_payload=args.max_payload,
    )


def wait_for_signal() -> None:
    """Block until SIGINT or SIGTERM (a service's main loop)."""
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    stop.wait()


def main(argv: Sequence[str] | None = None) -> int:
    """Run the `ldm` command line and return its exit status."""
    args = _parser().parse_args(argv)
    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.WARNING,
        format="%(asctime)s %(name)s %(levelname)s %(message)s",
    )
    try:
        if args.command == "broker":
            broker = EmbeddedBroker(args.host, args.port).start()
            print(f"ldm broker listening on {broker.url}", flush=True)
            wait_for_signal()
            broker.stop()
        else:
            core = Core(core_config(args)).start(timeout=30)
            backbone = f" and {args.backbone}" if args.backbone else ""
            print(f"ldm core {args.name} running on {args.cluster}{backbone}", flush=True)
            wait_for_signal()
            core.stop()
    except LdmError as exc:
        print(f"ldm: {exc}", flush=True)
        return 2
    return 0
