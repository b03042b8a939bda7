"""Judging the answers (`laas.evaluation`): `laas evaluate` (the paper's Table I, or a
suite of drawn scenarios), `laas privacy`, `laas liar` and `laas regions`."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from laas.cli.common import Subcommands, chosen_scenario, scenario_args, write_plots
from laas.config import Mode
from laas.errors import ConfigError
from laas.map.geojson import read_geojson_file
from laas.progress import progress_printer

__all__ = ["add_evaluate", "add_liar", "add_privacy", "add_regions"]


def _cmd_evaluate(a: argparse.Namespace) -> int:
    from laas.evaluation.evaluate import evaluate, format_table
    from laas.sim.scenario import get_scenario

    if a.suite is not None:
        return _evaluate_suite(a)
    cut = [f"--{n}" for n in ("families", "seeds", "sigma_pos") if getattr(a, n) is not None]
    if cut or a.uncalibrated:
        flags = ", ".join(cut + (["--uncalibrated"] if a.uncalibrated else [])).replace("_", "-")
        raise ConfigError(f"{flags}: these cut a suite down; give --suite too (dev, for example)")
    scenario = get_scenario(a.scenario)
    modes: tuple[Mode, ...] = ("paper", "default") if a.mode == "both" else (a.mode,)
    rows = evaluate(
        scenario,
        modes=modes,
        runs=a.runs,
        workers=a.workers,
        progress=None if a.json else progress_printer("evaluate", "runs"),
    )
    if a.json:
        print(json.dumps([r.as_dict() for r in rows], indent=1))
    else:
        print(f"scenario {scenario.name}: {a.runs} seeded runs per row (seeds 0..{a.runs - 1})")
        print(format_table(rows))
    if a.plot:
        hdmap = read_geojson_file(scenario.map)
        write_plots(scenario, hdmap, Path(a.plot), seed=0, sigma_pos=1.0, sigma_vel=0.25)
    return 0


def _evaluate_suite(a: argparse.Namespace) -> int:
    import time

    from laas.evaluation.suite import (
        format_report,
        get_suite,
        run_suite,
        suite_plots,
        suite_report,
        worst_run,
    )
    from laas.sim.foreign import default_foreign_dir

    if a.foreign is not None and a.suite != "foreign":
        raise ConfigError("--foreign names the set of --suite foreign; give --suite foreign too")
    foreign = Path(a.foreign) if a.foreign is not None else default_foreign_dir()
    if a.suite == "foreign" and a.plot:
        raise ConfigError("--plot draws simulated runs; the foreign suite's roads are recorded")
    suite = get_suite(a.suite, foreign).subset(
        families=None if a.families is None else [f.strip() for f in a.families.split(",")],
        seeds=a.seeds,
        sigmas=a.sigma_pos,
        calibrated=False if a.uncalibrated else None,
    )
    t0 = time.perf_counter()
    rows = run_suite(suite, workers=a.workers, progress=progress_printer("evaluate", "runs"))
    seconds = time.perf_counter() - t0
    if a.json:
        print(json.dumps(suite_report(suite, rows, seconds), indent=1))
    else:
        print(format_report(suite, rows, seconds))
    if a.plot:
        for p in suite_plots(worst_run(rows), Path(a.plot)):
            print(f"wrote {p}", file=sys.stderr if a.json else sys.stdout)
    return 1 if any(r.failed for r in rows) else 0


def _cmd_privacy(a: argparse.Namespace) -> int:
    import time

    from laas.evaluation.privacy import STRATEGIES, format_privacy, privacy_rows, target_check

    def numbers(text: str) -> list[int]:
        return [int(x) for x in text.split(",") if x]

    strategies = a.strategies.split(",") if a.strategies else list(STRATEGIES)
    t0 = time.perf_counter()
    rows = []
    for row in privacy_rows(
        a.places.split(","),
        numbers(a.users),
        a.duration,
        range(a.runs),
        strategies,
        a.accuracy_users or None,
    ):
        rows.append(row)
        print(f"privacy: {row.place} {row.users} users, {row.strategy}", file=sys.stderr)
    if a.json:
        print(json.dumps([r.as_dict() for r in rows], indent=1))
    else:
        print(format_privacy(rows))
        print(f"\n{target_check(rows)}")
        print(f"({time.perf_counter() - t0:.0f} s)")
    return 0


def _cmd_liar(a: argparse.Namespace) -> int:
    from laas.evaluation.liar import liar_report
    from laas.evaluation.suite import get_suite

    def numbers(text: str | None) -> list[float]:
        return [float(x) for x in text.split(",") if x] if text else []

    rows, report = liar_report(
        get_suite(a.suite),
        sweep=numbers(a.sweep),
        caps=numbers(a.k),
        workers=a.workers,
        progress=progress_printer("liar", "runs"),
    )
    if a.json:
        with open(a.json, "w") as fh:
            json.dump([r.as_dict() for r in rows], fh)
    print(report)
    return 0


def _cmd_regions(a: argparse.Namespace) -> int:
    from laas.evaluation.regional import compare_regions
    from laas.sim.scenario import simulate_with

    if a.workers < 2 or a.after < 1:
        raise ConfigError("--workers must be >= 2 and --after >= 1")
    scenario, hdmap = chosen_scenario(a)
    trace = simulate_with(hdmap, scenario, a.seed, sigma_pos=a.sigma_pos, sigma_vel=a.sigma_vel)
    print(
        f"laas regions: {len(trace.fixes)} fixes of {len(scenario.users)} road users on "
        f"{hdmap.source}, seed {a.seed}"
    )
    if a.live:
        from laas.run.regional import compare_live

        print("live: one worker, then regional workers, on a local deployment", flush=True)
        live = compare_live(
            hdmap, trace, workers=a.workers, speedup=a.speedup, brokers=a.brokers, after=a.after
        )
        print(live.format())
        return 0
    for handover in (False, True):
        r = compare_regions(
            hdmap, trace, workers=a.workers, handover=handover, overlap=a.overlap, after=a.after
        )
        print(r.format())
    return 0


def add_evaluate(sub: Subcommands) -> None:
    """`laas evaluate`."""
    p = sub.add_parser(
        "evaluate", help="the paper's Table I, both modes, seeded runs; or a scenario suite"
    )
    p.add_argument("--scenario", default="messe-hamburg", help="built-in scenario")
    p.add_argument(
        "--suite",
        help="run a suite of drawn scenarios instead: dev, heldout, maps-dev, maps-heldout, "
        "ci or smoke; or foreign, the recorded roads of --foreign DIR (docs/evaluation.md; "
        "--scenario, --runs and --mode do not apply)",
    )
    p.add_argument(
        "--foreign",
        metavar="DIR",
        help="with --suite foreign: the set's folder, sigma<S>/<road>/ with map.geojson, "
        "trace.jsonl and truth.jsonl (default: ../shared/foreign-roads where present)",
    )
    p.add_argument(
        "--families", metavar="A,B", help="with --suite: only these families (comma-separated)"
    )
    p.add_argument(
        "--seeds", type=int, metavar="N", help="with --suite: only the first N seeds of each"
    )
    p.add_argument(
        "--sigma-pos",
        type=float,
        action="append",
        metavar="S",
        help="with --suite: only this sigma_pos (repeat for more)",
    )
    p.add_argument(
        "--uncalibrated",
        action="store_true",
        help="with --suite: report default mode's posterior without the calibration map",
    )
    p.add_argument("--runs", type=int, default=20, help="seeded runs per configuration")
    p.add_argument(
        "--mode",
        choices=["both", "default", "paper"],
        default="both",
        help="lane filter to evaluate (both: each, side by side)",
    )
    p.add_argument("--workers", type=int, default=None, help="processes (default: cores)")
    p.add_argument("--json", action="store_true", help="machine-readable output")
    p.add_argument("--plot", metavar="DIR", help="also write the pictures to DIR")
    p.set_defaults(func=_cmd_evaluate)


def add_privacy(sub: Subcommands) -> None:
    """`laas privacy`."""
    p = sub.add_parser(
        "privacy",
        help="how many pseudonym changes a tracker on the service side undoes, per rotation "
        "strategy, and what each costs in accuracy",
    )
    p.add_argument(
        "--places",
        default="ring,helsinki,urban",
        help="maps the users roam: ring (a closed ring road), a bundled map, or a road family",
    )
    p.add_argument("--users", default="5,10,50,200", help="road users per run, comma-separated")
    p.add_argument("--duration", type=float, default=600.0, help="seconds per run")
    p.add_argument("--runs", type=int, default=1, help="seeded runs per place and user count")
    p.add_argument("--strategies", help="comma-separated (default: all of laas.evaluation.privacy)")
    p.add_argument(
        "--accuracy-users",
        type=int,
        default=20,
        help="also run this many users with the engine's accuracy scored (0: never)",
    )
    p.add_argument("--json", action="store_true", help="machine-readable output")
    p.set_defaults(func=_cmd_privacy)


def add_liar(sub: Subcommands) -> None:
    """`laas liar`."""
    p = sub.add_parser(
        "liar",
        help="a suite's scenarios with one participant lying, scored against their honest "
        "twins: the common error and the neighbours' lanes (docs/security.md)",
    )
    p.add_argument("--suite", default="ci", help="dev, heldout, ci or smoke")
    p.add_argument(
        "--workers", type=int, default=None, help="processes (default: the cores, at most 4)"
    )
    p.add_argument(
        "--sweep",
        metavar="M,M",
        help="comma-separated across offsets (m): the drawn liar lies by each instead",
    )
    p.add_argument("--json", metavar="FILE", help="write every row to this file")
    p.add_argument(
        "--k",
        metavar="K,K",
        help="comma-separated values of K (max_user_evidence) to score beside the variants",
    )
    p.set_defaults(func=_cmd_liar)


def add_regions(sub: Subcommands) -> None:
    """`laas regions`."""
    p = sub.add_parser(
        "regions",
        help="one worker against regional workers on the same road users (offline): lane "
        "accuracy, mean error, lane accuracy after each hand-over; each worker alone and "
        "with hand-over",
    )
    scenario_args(p)
    p.add_argument("--workers", type=int, default=2, help="regional workers (default 2)")
    p.add_argument(
        "--overlap", type=float, default=150.0, help="metres each region reaches into the next"
    )
    p.add_argument(
        "--after", type=int, default=10, help="fixes counted after each hand-over (default 10)"
    )
    p.add_argument(
        "--live",
        action="store_true",
        help="instead: the users as live participants on a local deployment, through one "
        "worker and then through regional workers (--overlap: the default 150 m)",
    )
    p.add_argument("--speedup", type=float, default=20.0, help="with --live: faster by")
    p.add_argument(
        "--brokers",
        choices=["auto", "embedded", "mosquitto"],
        default="auto",
        help="with --live: broker kind (auto: Mosquitto if installed)",
    )
    p.set_defaults(func=_cmd_regions)
