"""Traces offline: `laas replay` corrects a recorded one (`laas.sim.replay`), `laas
scenario` writes a simulated one with its truth, `laas plot` draws the paper's figures."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from laas.cli.common import (
    Subcommands,
    chosen_scenario,
    engine_args,
    engine_config,
    scenario_args,
    write_plots,
)
from laas.errors import TraceError
from laas.map.geojson import read_geojson_file

__all__ = ["add_plot", "add_replay", "add_scenario"]


def _cmd_replay(a: argparse.Namespace) -> int:
    from laas.sim.replay import replay
    from laas.sim.trace import format_answer, is_live, live_lines, read_trace

    hdmap = read_geojson_file(a.map)
    errors = 0

    def on_error(error: TraceError) -> None:
        nonlocal errors
        errors += 1
        print(f"laas replay: {error}", file=sys.stderr)

    if a.trace != "-" and Path(a.trace).is_dir():  # the folder `laas scenario` writes
        inside = Path(a.trace) / "trace.jsonl"
        if not inside.is_file():
            raise TraceError(
                f"{a.trace} is a folder without a trace.jsonl: give the trace file itself"
            )
        a.trace = str(inside)
    source = sys.stdin if a.trace == "-" else open(a.trace, encoding="utf-8")  # noqa: SIM115
    out = sys.stdout if a.out is None else open(a.out, "w", encoding="utf-8")  # noqa: SIM115
    live = source is sys.stdin and is_live(source.fileno())  # a pipe: answer what is ready
    answered = 0
    try:
        name = "<stdin>" if a.trace == "-" else a.trace
        lines = read_trace(live_lines(source.fileno()) if live else source, name)
        for result in replay(hdmap, lines, engine_config(a), on_error):
            out.write(format_answer(result.user, result.answer) + "\n")
            if live:
                out.flush()
            answered += 1
    finally:
        if source is not sys.stdin:
            source.close()
        if out is not sys.stdout:
            out.close()
    print(f"laas replay: {answered} answered, {errors} lines skipped", file=sys.stderr)
    return 0 if answered or not errors else 1


def _cmd_scenario(a: argparse.Namespace) -> int:
    from laas.sim.scenario import simulate_with
    from laas.sim.truth import write_run

    scenario, hdmap = chosen_scenario(a)
    trace = simulate_with(hdmap, scenario, a.seed, sigma_pos=a.sigma_pos, sigma_vel=a.sigma_vel)
    fixes, truth = write_run(trace, hdmap.projection.epsg, Path(a.out))
    print(f"wrote {len(trace.fixes)} fixes to {fixes} and the truth to {truth}")
    return 0


def _cmd_plot(a: argparse.Namespace) -> int:
    scenario, hdmap = chosen_scenario(a)
    write_plots(scenario, hdmap, Path(a.out), a.seed, a.sigma_pos, a.sigma_vel)
    return 0


def add_replay(sub: Subcommands) -> None:
    """`laas replay`."""
    p = sub.add_parser("replay", help="correct a recorded trace (JSON Lines) offline")
    p.add_argument("--map", required=True, help="GeoJSON lane map")
    p.add_argument(
        "trace",
        help="trace file, JSON Lines with a `user` field (or the folder `laas scenario` wrote); "
        "- for stdin",
    )
    p.add_argument("--out", help="output file (default: stdout)")
    engine_args(p)
    p.set_defaults(func=_cmd_replay)


def add_scenario(sub: Subcommands) -> None:
    """`laas scenario`."""
    p = sub.add_parser("scenario", help="write a simulated trace and its ground truth")
    scenario_args(p)
    p.add_argument("--out", required=True, help="folder for trace.jsonl and truth.jsonl")
    p.set_defaults(func=_cmd_scenario)


def add_plot(sub: Subcommands) -> None:
    """`laas plot`."""
    p = sub.add_parser("plot", help="pictures like the paper's Fig. 3 and Fig. 4")
    scenario_args(p)
    p.add_argument("--out", required=True, help="folder for the PNG files")
    p.set_defaults(func=_cmd_plot)
