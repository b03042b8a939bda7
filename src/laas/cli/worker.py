"""`laas worker` (`laas.worker.serve`; `--processes`: `laas.worker.processes`) and
`laas asyncapi`, the document of the topics and messages a worker speaks."""

from __future__ import annotations

import argparse
import logging
import os
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from laas.cli.common import (
    Subcommands,
    cluster_broker,
    connection_args,
    engine_args,
    engine_config,
    http_args,
    max_age_arg,
)
from laas.errors import ConfigError
from laas.map.bundled import maps_dir
from ldm.ops.logs import configure
from ldm.ops.process import operations_args, start_metrics, wait_for_signal

if TYPE_CHECKING:
    from ldm.ops.metrics import Metrics

__all__ = ["add_asyncapi", "add_worker"]


def _cmd_worker(a: argparse.Namespace) -> int:
    if a.processes < 1:
        raise ConfigError(f"--processes {a.processes}: give at least 1")
    if a.processes > 1:
        if a.region is not None or a.standby:
            raise ConfigError("--processes serves every region itself: drop --region/--standby")
        from laas.worker.processes import serve_processes

        return serve_processes(a.argv, a.processes, a.identity)
    configure(
        a.log_format,
        component="laas-worker",
        level=getattr(logging, a.log_level.upper()),
        text_format="ts=%(asctime)s level=%(levelname)s logger=%(name)s msg=%(message)s",
    )
    served = start_metrics(a, "laas worker")  # /readyz: 503 until the worker is connected
    try:
        return _serve_worker(a, None if served is None else served[0])
    finally:
        if served is not None:
            served[1].stop()


def _serve_worker(a: argparse.Namespace, metrics: Metrics | None) -> int:
    from laas.worker.serve import ServeOptions, serve_worker
    from laas.worker.service import WorkerConfig

    options = ServeOptions(
        cluster=cluster_broker(a),
        map=Path(a.map),
        engine=engine_config(a),
        limits=WorkerConfig(max_speedup=a.max_speedup),
        region=a.region,
        overlap=a.overlap,
        standby=a.standby,
        identity=a.identity,
        endorsement=a.endorsement,
        data_qos=a.data_qos,
        max_age=a.max_age,
        http_port=a.http,
        http_host=a.http_host,
    )
    serve_worker(options, wait=wait_for_signal, metrics=metrics)
    return 0


def _cmd_asyncapi(a: argparse.Namespace) -> int:
    from laas.worker.asyncapi import laas_document_text, write_document

    if a.out is None:
        sys.stdout.write(laas_document_text())
    else:
        print(f"laas asyncapi: wrote {write_document(Path(a.out))}", file=sys.stderr)
    return 0


def add_worker(sub: Subcommands) -> None:
    """`laas worker`."""
    p = sub.add_parser("worker", help="serve the laas service on an LDM service cluster")
    connection_args(p, "LAAS")
    p.add_argument(
        "--map",
        default=os.environ.get("LAAS_MAP", str(maps_dir() / "messe-hamburg.geojson")),
        help="GeoJSON lane map (env LAAS_MAP; default: the Hamburg test road of the "
        "bundled maps, in the folder LAAS_MAPS names if set)",
    )
    p.add_argument(
        "--data-qos",
        type=int,
        choices=(0, 1, 2),
        default=None,
        help="QoS of the input subscription and replies (default: follow the core's)",
    )
    p.add_argument(
        "--log-level",
        default=os.environ.get("LAAS_LOG_LEVEL", "warning"),
        choices=["debug", "info", "warning", "error"],
        help="log lines of this level and above, on stderr (env LAAS_LOG_LEVEL)",
    )
    p.add_argument(
        "--identity",
        type=Path,
        default=os.environ.get("LAAS_IDENTITY"),
        help="the worker's Ed25519 identity key file, made if missing (env LAAS_IDENTITY); "
        "participants pin its public key. Default: a new identity each start",
    )
    p.add_argument(
        "--endorsement",
        default=os.environ.get("LAAS_ENDORSEMENT"),
        help="a trust anchor's endorsement of the identity (`ldm keys endorse`; env "
        "LAAS_ENDORSEMENT)",
    )
    p.add_argument(
        "--region",
        default=os.environ.get("LAAS_REGION"),
        metavar="K/N",
        help="serve strip K of the map cut into N (env LAAS_REGION; laas.worker.regions): "
        "participants route their fixes here by position",
    )
    p.add_argument(
        "--overlap",
        type=float,
        default=150.0,
        help="with --region: metres each strip reaches into its neighbours (default 150)",
    )
    p.add_argument(
        "--processes",
        type=int,
        default=int(os.environ.get("LAAS_PROCESSES", "1")),
        help="serve the map as this many regions, one worker process each (env "
        "LAAS_PROCESSES; default 1)",
    )
    p.add_argument(
        "--standby",
        action="store_true",
        help="wait until the worker of this service (or --region) is gone, then take "
        "over under the same --identity",
    )
    max_age_arg(p, "drop input older than this when its turn comes")
    p.add_argument(
        "--max-speedup",
        type=float,
        default=float(os.environ.get("LAAS_MAX_SPEEDUP", "1")),
        help="let a session's timestamps run this much faster than real time (env "
        "LAAS_MAX_SPEEDUP; default 1, live devices): set it to a simulator's --speedup",
    )
    engine_args(p)
    operations_args(p, "LAAS")
    http_args(p, default=None)
    p.set_defaults(func=_cmd_worker)


def add_asyncapi(sub: Subcommands) -> None:
    """`laas asyncapi`."""
    p = sub.add_parser(
        "asyncapi", help="write the AsyncAPI 3.0 document of the LDM topics and laas messages"
    )
    p.add_argument("--out", help="the file to write (JSON; default: stdout)")
    p.set_defaults(func=_cmd_asyncapi)
