"""The `laas` command line: thin faces over the library (no logic lives only here).

One module per group of commands, each of which parses its flags, calls the library
and prints what it returns:

    demo       laas demo
    bench      laas bench, laas bench-filter
    worker     laas worker, laas asyncapi
    simulate   laas simulate
    traces     laas replay, laas scenario, laas plot
    evaluate   laas evaluate, laas privacy, laas liar, laas regions
    maps       laas map import, laas map info, laas map show
    bridges    laas owntracks, laas gpsd, laas cam
    common     the flags several commands share
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from laas.cli import bench, bridges, demo, evaluate, maps, simulate, traces, worker
from laas.errors import LaasError
from ldm import LdmError
from ldm.ops.help import Parser, add_version

__all__ = ["build_parser", "main"]


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of every subcommand."""
    parser = Parser(
        prog="laas", description="Location as a Service: lane-level positioning at the edge."
    )
    add_version(parser, "laas")
    sub = parser.add_subparsers(dest="command", required=True)

    # in the order `laas --help` lists them
    demo.add_demo(sub)
    bench.add_bench(sub)
    worker.add_worker(sub)
    simulate.add_simulate(sub)
    traces.add_replay(sub)
    evaluate.add_evaluate(sub)
    evaluate.add_privacy(sub)
    evaluate.add_liar(sub)
    evaluate.add_regions(sub)
    bench.add_bench_filter(sub)
    maps.add_map(sub)
    worker.add_asyncapi(sub)
    traces.add_scenario(sub)
    traces.add_plot(sub)
    bridges.add_bridges(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the `laas` command line and return its exit status."""
    args = build_parser().parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)[1:]  # after the command
    try:
        code: int = args.func(args)
    except (LaasError, LdmError, TimeoutError) as exc:
        print(f"laas {args.command}: {exc}", file=sys.stderr)
        return 2
    except FileNotFoundError as exc:
        print(f"laas {args.command}: {exc.filename}: no such file", file=sys.stderr)
        return 2
    return code
