"""`laas bench` (the full topology, `laas.run.bench`; `--worker-only`:
`laas.run.workerbench`) and `laas bench-filter` (`laas.run.filterbench`)."""

from __future__ import annotations

import argparse
import json
import sys

from laas.cli.common import Subcommands
from laas.errors import ConfigError

__all__ = ["add_bench", "add_bench_filter"]


def _cmd_bench(a: argparse.Namespace) -> int:
    from laas.run.bench import BenchConfig, format_loads, format_report, run_bench, run_loads

    if a.worker_only:
        return _bench_worker_only(a)
    config = BenchConfig(
        participants=a.participants,
        rate=a.rate,
        duration=a.duration,
        brokers=a.brokers,
        rotation_period=a.rotation_period,
        processes=a.processes,
        seed=a.seed,
        connect_rate=a.connect_rate,
        spread=a.spread,
        privacy=not a.no_privacy,
        workers=a.workers,
        profile=a.profile,
    )

    def progress(line: str) -> None:
        print(line, file=sys.stderr, flush=True)

    if a.both:
        reports = run_loads(config, progress)
        loads = {"loads": [r.as_dict() for r in reports]}
        print(json.dumps(loads, indent=1) if a.json else format_loads(reports))
        return 0 if all(r.answered for r in reports) else 1
    report = run_bench(config, progress)
    print(json.dumps(report.as_dict(), indent=1) if a.json else format_report(report))
    return 0 if report.answered else 1


def _bench_worker_only(a: argparse.Namespace) -> int:
    from laas.run.workerbench import bench_worker, format_worker_report

    if a.participants < 1 or not a.duration > 0 or a.batch < 1:
        raise ConfigError("--participants and --batch must be >= 1 and --duration > 0")
    report = bench_worker(
        map_name=a.map,
        users=a.participants,
        duration=a.duration,
        seed=a.seed,
        batch=a.batch,
        spread=a.spread,
        progress=lambda line: print(line, file=sys.stderr, flush=True),
    )
    print(json.dumps(report.as_dict(), indent=1) if a.json else format_worker_report(report))
    return 0 if report.answered == report.fixes else 1


def _cmd_bench_filter(a: argparse.Namespace) -> int:
    from laas.run.filterbench import bench_filter, format_filter_table, group_sizes

    rows = bench_filter(
        group_sizes(a.max_users),
        steps=a.steps,
        progress=None if a.json else lambda n: print(f"  {n} users", file=sys.stderr),
    )
    if a.json:
        print(json.dumps([r.as_dict() for r in rows], indent=1))
    else:
        print(format_filter_table(rows))
    return 0


def add_bench(sub: Subcommands) -> None:
    """`laas bench`."""
    p = sub.add_parser("bench", help="latency and throughput through the full LDM topology")
    p.add_argument("--participants", type=int, default=200, help="simulated participants")
    p.add_argument("--rate", type=float, default=1.0, help="fixes per participant per second")
    p.add_argument("--duration", type=float, default=30.0, help="seconds of load")
    p.add_argument(
        "--brokers",
        choices=["auto", "embedded", "mosquitto"],
        default="auto",
        help="broker kind (auto: Mosquitto if installed, else the embedded broker)",
    )
    p.add_argument(
        "--rotation-period", type=float, default=120.0, help="pseudonym rotation, s (LDM default)"
    )
    p.add_argument("--processes", type=int, help="participant processes (default: 2 to 4)")
    p.add_argument("--seed", type=int, default=0, help="seed of the simulated GNSS errors")
    p.add_argument("--json", action="store_true", help="machine-readable output")
    p.add_argument(
        "--connect-rate",
        type=float,
        default=200.0,
        help="new participant connections per second, over all participant processes",
    )
    p.add_argument(
        "--spread",
        action="store_true",
        help=(
            "spread each participant's fixes over the second (default: all on the whole "
            "second, as GNSS receivers emit them)"
        ),
    )
    p.add_argument(
        "--both",
        action="store_true",
        help=(
            "run the load on the whole second, then spread over it, each on a deployment "
            "of its own, and report the two together (--spread is then ignored)"
        ),
    )
    p.add_argument(
        "--no-privacy",
        action="store_true",
        help="skip the two Hamburg rotation runs after the load",
    )
    p.add_argument(
        "--worker-only",
        action="store_true",
        help=(
            "the worker's own code on one core, no brokers: us per fix for each stage, "
            "against one filterpy Kalman step (--participants users roaming --map for "
            "--duration simulated seconds)"
        ),
    )
    p.add_argument(
        "--workers",
        type=int,
        default=1,
        help="worker processes, each serving a region of the map (default 1)",
    )
    p.add_argument(
        "--profile",
        metavar="DIR",
        help=(
            "record where each process (cores, worker, participants; not the brokers) "
            "spends its CPU over the load with py-spy: raw profiles into DIR, the top "
            "entries per process printed after the report"
        ),
    )
    p.add_argument("--map", default="messe-hamburg", help="with --worker-only: bundled map to roam")
    p.add_argument(
        "--batch",
        type=int,
        default=64,
        help="with --worker-only: fixes per batch, timed beside one at a time (default 64)",
    )
    p.set_defaults(func=_cmd_bench)


def add_bench_filter(sub: Subcommands) -> None:
    """`laas bench-filter`."""
    p = sub.add_parser(
        "bench-filter", help="lane filter time per update against users in a segment"
    )
    p.add_argument("--max-users", type=int, default=100, help="largest group (default 100)")
    p.add_argument("--steps", type=int, default=10, help="timed steps per group size")
    p.add_argument("--json", action="store_true", help="machine-readable output")
    p.set_defaults(func=_cmd_bench_filter)
