"""A long-running process of the LDM or LaaS (a core, a worker, a bridge), as its
operators start and stop it; the `ldm` and `laas` command lines both use it.

    operations_args(parser, "LAAS")          # --metrics-port, --metrics-host, --log-format
    served = start_metrics(args, "laas worker")
    cluster = broker_settings(args.cluster, args.ca_file, args.username, "LAAS_PASSWORD")
    wait_for_signal()                         # until SIGINT or SIGTERM

A password never comes from the command line: `broker_settings` is given the name of the
environment variable that holds it.
"""

from __future__ import annotations

import argparse
import os
import signal
import threading
from pathlib import Path
from typing import Any

from ldm.config import BrokerSettings, build
from ldm.ops.logs import LOG_FORMATS
from ldm.ops.metrics import Metrics, MetricsServer

__all__ = ["broker_settings", "operations_args", "start_metrics", "wait_for_signal"]


def broker_settings(
    url: str, ca_file: Path | None, username: str | None, env: str
) -> BrokerSettings:
    """Broker settings from command-line values; the password is read from `env`."""
    values: dict[str, Any] = {"url": url, "ca_file": ca_file, "username": username}
    if username is not None:
        values["password_env"] = env
    return build(BrokerSettings, **values)


def wait_for_signal() -> None:
    """Block until SIGINT or SIGTERM (a service's main loop)."""
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    stop.wait()


def operations_args(p: argparse.ArgumentParser, env_prefix: str) -> None:
    """The options of a long-running command for its operators: metrics and log format."""
    p.add_argument(
        "--metrics-port",
        type=int,
        metavar="PORT",
        default=os.environ.get(f"{env_prefix}_METRICS_PORT"),
        help="serve /metrics, /healthz and /readyz on this port; 0 picks a free one "
        f"(env {env_prefix}_METRICS_PORT; default: no metrics server)",
    )
    p.add_argument(
        "--metrics-host",
        metavar="HOST",
        default=os.environ.get(f"{env_prefix}_METRICS_HOST", "127.0.0.1"),
        help=f"address of the metrics server (env {env_prefix}_METRICS_HOST; default "
        "127.0.0.1; 0.0.0.0 in a container)",
    )
    p.add_argument(
        "--log-format",
        choices=LOG_FORMATS,
        default=None,
        help="text, or json: one JSON object per line with component and event "
        "(default: env LDM_LOG_FORMAT, else text)",
    )


def start_metrics(args: argparse.Namespace, who: str) -> tuple[Metrics, MetricsServer] | None:
    """The metrics server `operations_args` asked for (None: none), serving at once:
    /readyz says 503 until the components it is given are connected."""
    if args.metrics_port is None:
        return None
    metrics = Metrics()
    server = metrics.serve(args.metrics_host, args.metrics_port)
    print(f"{who}: metrics on {server.url} (and /healthz, /readyz)", flush=True)
    return metrics, server
