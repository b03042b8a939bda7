"""The `ldm` command line: run a core or an embedded broker, or write a password file.

    ldm broker --port 1883
    ldm nats-cluster --nodes 3 --account user --account backbone   # needs nats-server
    ldm core --name user --cluster mqtt://localhost:1883 --backbone mqtt://hub:1883
    ldm passwd deploy/security/passwd car-17 bike-42=PASSWORD
    ldm keys new laas.key            # an Ed25519 identity; prints its public key
    ldm keys endorse anchor.key laas PUBLIC_KEY
    ldm bench flood --phase 10       # others' latency while one participant floods
    ldm bench core --participants 100 --rate 3   # the LDM's own cost, without a service

A core's passwords come from environment variables (``--password-env``, default
LDM_PASSWORD; ``--backbone-password-env``, default LDM_BACKBONE_PASSWORD), never from the
command line. ``ldm passwd`` reads USER=PASSWORD entries from its arguments or, for the
entry ``-``, from standard input (out of the process list).
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from collections.abc import Sequence
from dataclasses import asdict
from pathlib import Path
from typing import get_args

from ldm.config import CoreConfig, build
from ldm.core.core import Core
from ldm.errors import ConfigError, LdmError, PasswordFileError
from ldm.local.embedded import EmbeddedBroker
from ldm.ops.help import Parser, add_version
from ldm.ops.logs import configure
from ldm.ops.passwd import random_password, set_passwords
from ldm.ops.process import broker_settings, operations_args, start_metrics, wait_for_signal
from ldm.security.identity import SigningKey, endorse
from ldm.wire.rotation import MAX_SILENCE, RotationPolicy, Strategy

__all__ = ["core_config", "main", "password_entries", "pins"]


def _parser() -> argparse.ArgumentParser:
    parser = Parser(prog="ldm", description=__doc__.splitlines()[0])
    add_version(parser, "ldm")
    parser.add_argument("-v", "--verbose", action="store_true", help="log at INFO level")
    sub = parser.add_subparsers(dest="command", required=True)

    broker = sub.add_parser("broker", help="run the embedded MQTT 3.1.1 broker (amqtt)")
    broker.add_argument("--host", default="127.0.0.1", help="address to listen on")
    broker.add_argument("--port", type=int, default=1883, help="port (0 picks a free one)")

    nats = sub.add_parser(
        "nats-cluster",
        help="run a local cluster of NATS servers with MQTT and JetStream (docs/brokers.md)",
        description="Start NODES nats-server processes on free ports of 127.0.0.1, "
        "clustered, with JetStream and MQTT; print the cluster URL (give it to --cluster "
        "or --backbone) and, per --account, the password of its user, once.",
    )
    nats.add_argument("--nodes", type=int, default=3, help="servers in the cluster (default 3)")
    nats.add_argument(
        "--account",
        action="append",
        default=[],
        metavar="NAME",
        help="an isolated topic space with one user NAME (repeatable: one per LDM broker)",
    )

    core = sub.add_parser("core", help="run an LDM core for one cluster")
    core.add_argument("--name", required=True, help="core name, unique in the deployment")
    core.add_argument(
        "--cluster",
        required=True,
        help="cluster broker, mqtt[s]://HOST:PORT (a clustered one: HOST:PORT,HOST:PORT,...)",
    )
    core.add_argument(
        "--backbone", help="inter-cluster broker, mqtt[s]://HOST:PORT[,HOST:PORT,...]"
    )
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
        ("--retain-sweep", "retain_sweep"),
    ]:
        default = CoreConfig.model_fields[field].default
        unit = "messages/s" if field == "rate" else "messages" if field == "burst" else "seconds"
        core.add_argument(option, type=float, default=default, help=f"{unit} (default {default})")
    core.add_argument(
        "--rotation",
        choices=get_args(Strategy),
        default=RotationPolicy().strategy,
        help="who decides when pseudonyms change (docs/ldm.md, ldm.wire.rotation; default "
        f"{RotationPolicy().strategy})",
    )
    core.add_argument(
        "--silence",
        type=float,
        default=RotationPolicy().silence,
        help=f"seconds a participant sends nothing after each change (default "
        f"{RotationPolicy().silence:g}, at most {MAX_SILENCE:g}); with --silence-max the "
        "shortest",
    )
    core.add_argument(
        "--silence-max",
        type=float,
        default=None,
        help="the longest silence: each participant draws each of its silences uniformly "
        "between --silence and this (default: always --silence)",
    )
    core.add_argument(
        "--max-payload",
        type=int,
        default=CoreConfig.model_fields["max_payload"].default,
        help="largest participant message, bytes",
    )
    core.add_argument("--data-qos", type=int, default=0, choices=(0, 1, 2), help="QoS of data")
    core.add_argument(
        "--identity",
        type=Path,
        help="the core's Ed25519 key file (made if missing); participants pin its public key",
    )
    core.add_argument(
        "--trust-service",
        action="append",
        default=[],
        metavar="SERVICE=KEY",
        help="take announcements of SERVICE only if signed by identity KEY (repeatable)",
    )
    core.add_argument(
        "--trust-anchor",
        action="append",
        default=[],
        metavar="KEY",
        help="take services whose identity this anchor endorsed (repeatable)",
    )
    operations_args(core, "LDM")

    keys = sub.add_parser("keys", help="make and show Ed25519 identity keys")
    keys_sub = keys.add_subparsers(dest="keys_command", required=True)
    new = keys_sub.add_parser(
        "new", help="write a new private key (mode 0600), print its public key"
    )
    new.add_argument("file", type=Path, metavar="FILE", help="the key file to write")
    show = keys_sub.add_parser("show", help="print the public key of a private key file")
    show.add_argument("file", type=Path, metavar="FILE", help="a private key file")
    endorse_ = keys_sub.add_parser(
        "endorse", help="print an anchor's endorsement of a service identity"
    )
    endorse_.add_argument(
        "anchor", type=Path, metavar="ANCHOR_FILE", help="the trust anchor's private key file"
    )
    endorse_.add_argument("service", metavar="SERVICE", help="the service name, e.g. laas")
    endorse_.add_argument(
        "identity", metavar="IDENTITY_PUBLIC_KEY", help="the service's public identity key"
    )

    passwd = sub.add_parser(
        "passwd",
        help="create or extend a Mosquitto password file",
        description="Create or extend a Mosquitto password file (PBKDF2-SHA512, as "
        "mosquitto_passwd writes it). Other accounts in FILE are kept, and so is the "
        "password of an account FILE already holds, unless --replace is given; a USER "
        "without =PASSWORD gets a random password, printed once as USER=PASSWORD.",
    )
    passwd.add_argument("file", type=Path, metavar="FILE", help="the password file")
    passwd.add_argument(
        "entries",
        nargs="+",
        metavar="USER[=PASSWORD]",
        help="an account; '-' reads such entries from standard input, one per line",
    )
    passwd.add_argument(
        "--mode", type=_octal, default=0o640, help="file mode, octal (default 0640)"
    )
    passwd.add_argument(
        "--replace",
        action="store_true",
        help="give accounts FILE already holds the new password (default: keep theirs)",
    )
    _add_bench(sub)
    return parser


def _add_bench(sub: argparse._SubParsersAction[Parser]) -> None:
    """`ldm bench flood` and `ldm bench core`: both start Mosquitto brokers of their own."""
    bench = sub.add_parser(
        "bench", help="benchmarks of the LDM alone, on Mosquitto brokers of their own"
    )
    kinds = bench.add_subparsers(dest="bench_command", required=True)
    flood = kinds.add_parser(
        "flood",
        help="other participants' p99 latency before and during one participant's flood "
        "(ldm.local.floodbench)",
    )
    flood.add_argument("--participants", type=int, default=4, help="calm users (default 4)")
    flood.add_argument("--hz", type=float, default=5.0, help="requests/s per user (default 5)")
    flood.add_argument("--rate", type=float, default=6700.0, help="flood msg/s (default 6700)")
    flood.add_argument("--phase", type=float, default=10.0, help="seconds per phase (10)")
    flood.add_argument("--no-acl", action="store_true", help="user broker without the ACL")
    flood.add_argument("--core-rate", type=float, help="the user core's rate (default: its own)")
    flood.add_argument("--core-burst", type=float, help="the user core's burst")
    flood.add_argument("--json", action="store_true", help="machine-readable output")
    core = kinds.add_parser(
        "core",
        help="the LDM's own cost: two cores between participants and an echo provider, "
        "CPU per 1,000 inputs (ldm.local.corebench)",
    )
    core.add_argument("--participants", type=int, default=100, help="participants")
    core.add_argument("--rate", type=float, default=3.0, help="inputs per participant per s")
    core.add_argument("--duration", type=float, default=10.0, help="seconds of load")
    core.add_argument("--json", action="store_true", help="machine-readable output")


def _octal(text: str) -> int:
    try:
        mode = int(text, 8)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not an octal file mode: {text!r}") from None
    if not 0 <= mode <= 0o7777:
        raise argparse.ArgumentTypeError(f"not a file mode: {text!r}")
    return mode


def password_entries(entries: Sequence[str]) -> tuple[dict[str, str], list[str]]:
    """USER[=PASSWORD] entries -> (passwords by user, users that got a random password).

    The entry ``-`` stands for the non-empty lines of standard input.
    """
    lines: list[str] = []
    for entry in entries:
        if entry == "-":
            lines += [line for line in sys.stdin.read().splitlines() if line]
        else:
            lines.append(entry)
    passwords: dict[str, str] = {}
    generated: list[str] = []
    for line in lines:
        user, sep, password = line.partition("=")
        if user in passwords:
            raise PasswordFileError(f"user {user!r} is given twice")
        if not sep:
            password = random_password()
            generated.append(user)
        passwords[user] = password
    return passwords, generated


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
        rotation={
            "strategy": args.rotation,
            "silence": args.silence,
            "silence_max": args.silence_max,
        },
        grace=args.grace,
        idle_timeout=args.idle_timeout,
        service_ttl=args.service_ttl,
        max_age=args.max_age,
        data_qos=args.data_qos,
        rate=args.rate,
        burst=args.burst,
        max_clock_skew=args.max_clock_skew,
        retain_sweep=args.retain_sweep,
        max_payload=args.max_payload,
        identity_file=args.identity,
        service_keys=pins(args.trust_service),
        anchors=args.trust_anchor,
    )


def pins(entries: Sequence[str]) -> dict[str, str]:
    """SERVICE=KEY entries -> {service: key}; ConfigError names a malformed one."""
    result: dict[str, str] = {}
    for entry in entries:
        service, sep, key = entry.partition("=")
        if not sep or not service or not key:
            raise ConfigError(f"--trust-service {entry!r}: use SERVICE=KEY")
        result[service] = key
    return result


def _keys(args: argparse.Namespace) -> int:
    """`ldm keys`: stdout carries only public keys and endorsements, never a private key."""
    try:
        if args.keys_command == "new":
            if args.file.exists():
                print(f"ldm keys: {args.file} exists; not overwriting a key", file=sys.stderr)
                return 2
            key = SigningKey.generate()
            key.save(args.file)
        else:
            key = SigningKey.load(args.anchor if args.keys_command == "endorse" else args.file)
    except OSError as exc:
        print(f"ldm keys: cannot write {args.file}: {exc.strerror or exc}", file=sys.stderr)
        return 1
    if args.keys_command == "endorse":
        print(endorse(key, args.service, args.identity))
    else:
        print(key.public)
    return 0


def _core(args: argparse.Namespace) -> None:
    """`ldm core`: serve until SIGINT or SIGTERM (metrics from before it connects)."""
    core = Core(core_config(args))
    served = start_metrics(args, f"ldm core {args.name}")
    try:
        if served is not None:
            served[0].watch_core(core)
        core.start(timeout=30)
        backbone = f" and {args.backbone}" if args.backbone else ""
        print(
            f"ldm core {args.name} running on {args.cluster}{backbone}; "
            f"its key (participants pin it): {core.public_key}",
            flush=True,
        )
        wait_for_signal()
        core.stop()
    finally:
        if served is not None:
            served[1].stop()


def _passwd(args: argparse.Namespace) -> int:
    """`ldm passwd`: errors go to stderr, stdout carries only the generated passwords."""
    try:
        passwords, generated = password_entries(args.entries)
        kept = set_passwords(args.file, passwords, mode=args.mode, replace=args.replace)
    except PasswordFileError as exc:
        print(f"ldm passwd: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"ldm passwd: cannot write {args.file}: {exc.strerror or exc}", file=sys.stderr)
        return 1
    for user in kept:
        print(
            f"ldm passwd: {user} is already in {args.file}: its password was kept "
            "(--replace gives it a new one)",
            file=sys.stderr,
        )
    for user in generated:
        if user not in kept:
            print(f"{user}={passwords[user]}", flush=True)
    return 0


def _nats_cluster(args: argparse.Namespace) -> int:
    """`ldm nats-cluster`: stdout carries the URL and the generated passwords."""
    from ldm.local.nats import NatsCluster  # only this command needs it

    if args.nodes < 1:
        raise ConfigError("--nodes must be at least 1")
    cluster = NatsCluster(args.nodes, accounts=args.account).start()
    try:
        print(f"ldm nats-cluster: {args.nodes} nodes, MQTT at {cluster.url}", flush=True)
        print(f"ldm nats-cluster: logs and stores in {cluster.directory}", flush=True)
        for line in cluster.describe():
            print(f"ldm nats-cluster: {line}", flush=True)
        for account, password in cluster.passwords.items():
            print(f"{account}={password}", flush=True)
        wait_for_signal()
    finally:
        cluster.stop()
    return 0


def _bench(args: argparse.Namespace) -> int:
    """`ldm bench flood|core`: the report on stdout; 1 if no request was answered."""
    if args.bench_command == "flood":
        from ldm.local import floodbench  # only this command needs it

        settings: dict[str, float] = {}
        if args.core_rate is not None:
            settings["rate"] = args.core_rate
        if args.core_burst is not None:
            settings["burst"] = args.core_burst
        flood = floodbench.run_flood_bench(
            participants=args.participants,
            hz=args.hz,
            rate=args.rate,
            phase=args.phase,
            acl=not args.no_acl,
            core_settings=settings,
        )
        text = json.dumps(asdict(flood), indent=1) if args.json else floodbench.format_report(flood)
        print(text)
        return 0 if flood.flood.answered else 1
    from ldm.local import corebench

    core = corebench.run_core_bench(args.participants, args.rate, args.duration)
    print(json.dumps(core.as_dict(), indent=1) if args.json else corebench.format_report(core))
    return 0 if core.answered else 1


def main(argv: Sequence[str] | None = None) -> int:
    """Run the `ldm` command line and return its exit status."""
    args = _parser().parse_args(argv)
    try:
        component = f"ldm-core-{args.name}" if args.command == "core" else f"ldm-{args.command}"
        configure(
            getattr(args, "log_format", None),
            component=component,
            level=logging.INFO if args.verbose else logging.WARNING,
        )
        if args.command == "passwd":
            return _passwd(args)
        if args.command == "keys":
            return _keys(args)
        if args.command == "nats-cluster":
            return _nats_cluster(args)
        if args.command == "bench":
            return _bench(args)
        if args.command == "broker":
            broker = EmbeddedBroker(args.host, args.port).start()
            print(f"ldm broker listening on {broker.url}", flush=True)
            wait_for_signal()
            broker.stop()
        else:
            _core(args)
    except LdmError as exc:
        print(f"ldm {args.command}: {exc}", file=sys.stderr, flush=True)
        return 2
    return 0
