"""`laas demo`: the paper's scenario end to end on this machine (`laas.run.demo`)."""

from __future__ import annotations

import argparse
from pathlib import Path

from laas.cli.common import Subcommands, http_args

__all__ = ["add_demo"]


def _cmd_demo(a: argparse.Namespace) -> int:
    from laas.run.demo import run_demo

    return run_demo(
        Path(a.out),
        seed=a.seed,
        sigma_pos=a.sigma_pos,
        speedup=a.speedup,
        brokers=a.brokers,
        http_port=a.http,
        http_host=a.http_host,
        metrics_port=a.metrics_port,
        metrics_host=a.metrics_host,
    )


def add_demo(sub: Subcommands) -> None:
    """`laas demo`."""
    p = sub.add_parser("demo", help="run the paper's scenario end to end and show the results")
    p.add_argument("--out", default="out", help="folder for the pictures (default: out)")
    p.add_argument("--seed", type=int, default=0, help="seed of the simulated GNSS errors")
    p.add_argument("--sigma-pos", type=float, default=1.0, help="receiver position noise, m")
    p.add_argument("--speedup", type=float, default=10.0, help="faster than real time by")
    p.add_argument(
        "--brokers",
        choices=["auto", "embedded", "embedded-process", "mosquitto"],
        default="auto",
        help="broker kind (auto: Mosquitto if installed, else the embedded broker)",
    )
    http_args(p, default=0)
    p.add_argument(
        "--metrics-port",
        type=int,
        default=None,
        help="serve the cores' and the worker's /metrics, /healthz, /readyz on this port "
        "(0: a free one; default: none)",
    )
    p.add_argument("--metrics-host", default="127.0.0.1", help="address of the metrics server")
    p.set_defaults(func=_cmd_demo)
