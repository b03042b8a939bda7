"""The `laas` command line: thin faces over the library (no logic lives only here)."""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from laas.config import EngineConfig, Mode
from laas.errors import ConfigError, LaasError, TraceError
from laas.map.bundled import maps_dir
from laas.map.geojson import read_geojson_file
from laas.map.hdmap import HdMap
from laas.progress import progress_printer
from ldm import BrokerSettings, LdmError
from ldm.ops.help import Parser, add_version
from ldm.ops.logs import configure
from ldm.ops.process import broker_settings, operations_args, start_metrics, wait_for_signal

if TYPE_CHECKING:
    from laas.sim.scenario import Scenario
    from ldm.ops.metrics import Metrics

__all__ = ["main"]


def _engine_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--mode", choices=["default", "paper"], default="default", help="lane filter")
    p.add_argument("--no-kalman", action="store_true", help="use the raw fixes, unsmoothed")
    p.add_argument("--sigma-pos", type=float, default=1.0, help="receiver position noise, m")
    p.add_argument("--sigma-vel", type=float, default=0.25, help="receiver speed noise, m/s")
    p.add_argument("--sigma-heading", type=float, default=0.5, help="heading noise, degrees")


def _engine_config(a: argparse.Namespace) -> EngineConfig:
    return EngineConfig(
        mode=a.mode,
        kalman=not a.no_kalman,
        sigma_pos=a.sigma_pos,
        sigma_vel=a.sigma_vel,
        sigma_heading=a.sigma_heading,
    )


def _cmd_replay(a: argparse.Namespace) -> int:
    from laas.sim.replay import replay
    from laas.sim.trace import format_answer, is_live, live_lines, read_trace

    hdmap = read_geojson_file(a.map)
    errors = 0

    def on_error(error: TraceError) -> None:
        nonlocal errors
        errors += 1
        print(f"laas replay: {error}", file=sys.stderr)

    source = sys.stdin if a.trace == "-" else open(a.trace, encoding="utf-8")  # noqa: SIM115
    out = sys.stdout if a.out is None else open(a.out, "w", encoding="utf-8")  # noqa: SIM115
    live = source is sys.stdin and is_live(source.fileno())  # a pipe: answer what is ready
    answered = 0
    try:
        name = "<stdin>" if a.trace == "-" else a.trace
        lines = read_trace(live_lines(source.fileno()) if live else source, name)
        for result in replay(hdmap, lines, _engine_config(a), on_error):
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


def _scenario(a: argparse.Namespace) -> tuple[Scenario, HdMap]:
    """The built-in scenario `--scenario`, or with `--map` users roaming that map."""
    from laas.sim.scenario import get_scenario

    if a.map is not None:
        from laas.sim.roam import roam_scenario

        hdmap = read_geojson_file(a.map)
        return roam_scenario(hdmap, a.seed, users=a.users, duration=a.duration), hdmap
    scenario = get_scenario(a.scenario)
    return scenario, read_geojson_file(scenario.map)


def _cmd_scenario(a: argparse.Namespace) -> int:
    from laas.sim.scenario import simulate_with
    from laas.sim.truth import write_run

    scenario, hdmap = _scenario(a)
    trace = simulate_with(hdmap, scenario, a.seed, sigma_pos=a.sigma_pos, sigma_vel=a.sigma_vel)
    fixes, truth = write_run(trace, hdmap.projection.epsg, Path(a.out))
    print(f"wrote {len(trace.fixes)} fixes to {fixes} and the truth to {truth}")
    return 0


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
        _plots(scenario, hdmap, Path(a.plot), seed=0, sigma_pos=1.0, sigma_vel=0.25)
    return 0


def _evaluate_suite(a: argparse.Namespace) -> int:
    import time

    from laas.evaluation.suite import (
        format_report,
        get_suite,
        run_suite,
        suite_plots,
        summarize,
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
        report = {
            "suite": suite.name,
            "seconds": seconds,
            "summaries": [s.as_dict() for s in summarize(rows)],
            "runs": [r.as_dict() for r in rows],
        }
        print(json.dumps(report, indent=1))
    else:
        print(format_report(suite, rows, seconds))
    if a.plot:
        for p in suite_plots(worst_run(rows), Path(a.plot)):
            print(f"wrote {p}", file=sys.stderr if a.json else sys.stdout)
    failed = any(m.error is not None for r in rows for m in r.methods.values())
    return 1 if failed else 0


def _plots(
    scenario: Scenario,
    hdmap: HdMap,
    out: Path,
    seed: int,
    sigma_pos: float,
    sigma_vel: float,
) -> list[Path]:
    from laas.evaluation.plots import scenario_plots

    paths = scenario_plots(scenario, hdmap, out, seed, sigma_pos, sigma_vel)
    for p in paths:
        print(f"wrote {p}")
    return paths


def _cmd_regions(a: argparse.Namespace) -> int:
    from laas.evaluation.regional import compare_regions
    from laas.sim.scenario import simulate_with

    if a.workers < 2 or a.after < 1:
        raise ConfigError("--workers must be >= 2 and --after >= 1")
    scenario, hdmap = _scenario(a)
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


def _cmd_plot(a: argparse.Namespace) -> int:
    scenario, hdmap = _scenario(a)
    _plots(scenario, hdmap, Path(a.out), a.seed, a.sigma_pos, a.sigma_vel)
    return 0


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


def _broker(a: argparse.Namespace) -> BrokerSettings:
    if not a.cluster:
        raise ConfigError("give the cluster broker: --cluster mqtt://HOST:PORT (or LAAS_CLUSTER)")
    return broker_settings(a.cluster, a.ca_file, a.username, a.password_env)


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
        cluster=_broker(a),
        map=Path(a.map),
        engine=_engine_config(a),
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


def _cmd_simulate(a: argparse.Namespace) -> int:
    from laas.evaluation.score import score
    from laas.run.participants import accounts, run_participants
    from laas.sim.scenario import simulate_with
    from laas.sim.trace import format_answer

    scenario, hdmap = _scenario(a)
    trace = simulate_with(hdmap, scenario, a.seed, sigma_pos=a.sigma_pos, sigma_vel=a.sigma_vel)
    if a.list_accounts:
        print("\n".join(accounts(trace, a.prefix).values()))
        return 0
    cluster = _broker(a)
    if a.device_accounts:  # one account per road user, one password for all
        cluster = broker_settings(cluster.url, a.ca_file, "device", a.device_password_env)
    print(
        f"laas simulate: {len(trace.fixes)} fixes of {len(scenario.users)} road users "
        f"at {a.speedup:g}x real time",
        file=sys.stderr,
    )
    live = run_participants(
        cluster,
        trace,
        account_prefix=a.prefix if a.device_accounts else None,
        speedup=a.speedup,
        reply_timeout=max(5.0, 2 * a.max_age + 1.0),  # the participant's own limit, and more
        max_age=a.max_age,
        progress=progress_printer("  sent", "fixes"),
        hdmap=hdmap,  # a silent user's own answer goes on the map's lanes
        service_keys={"laas": a.service_key} if a.service_key else {},
        anchors=a.trust_anchor,
        core_key=a.core_key,
    )
    out = sys.stdout if a.out is None else open(a.out, "w", encoding="utf-8")  # noqa: SIM115
    try:
        for fix, answer in zip(trace.fixes, live.answers, strict=True):
            if answer is not None:
                out.write(format_answer(fix.user, answer) + "\n")
    finally:
        if out is not sys.stdout:
            out.close()
    for error in live.errors[:10]:
        print(f"laas simulate: {error}", file=sys.stderr)
    if not live.answered:
        print("laas simulate: no fix was answered", file=sys.stderr)
        return 1
    r = score(hdmap, trace, live.answers)
    print(
        f"laas simulate: {live.answered}/{len(trace.fixes)} answered; lane accuracy "
        f"{r.accuracy:.3f}, AED {r.aed:.2f} m (raw fixes {r.raw_aed:.2f} m)",
        file=sys.stderr,
    )
    return 0


def _max_age_arg(p: argparse.ArgumentParser, what: str) -> None:
    """`--max-age`: every hop drops what is older than its max_age (docs/brokers.md)."""
    p.add_argument(
        "--max-age",
        type=float,
        default=float(os.environ.get("LAAS_MAX_AGE", "2")),
        metavar="SECONDS",
        help=f"{what} (env LAAS_MAX_AGE; default 2 s). Give every hop the same: the "
        "cores' `ldm core --max-age`; on a NATS cluster about 10 s, the time it takes "
        "to elect new leaders after a node fails (docs/brokers.md)",
    )


def _connection_args(p: argparse.ArgumentParser, env_prefix: str) -> None:
    p.add_argument(
        "--cluster",
        default=os.environ.get(f"{env_prefix}_CLUSTER"),
        help=f"cluster broker, mqtt[s]://HOST:PORT (env {env_prefix}_CLUSTER)",
    )
    p.add_argument(
        "--username",
        default=os.environ.get(f"{env_prefix}_USERNAME"),
        help=f"user name on the broker (env {env_prefix}_USERNAME)",
    )
    p.add_argument(
        "--password-env",
        default=f"{env_prefix}_PASSWORD",
        help=f"environment variable holding the password (default {env_prefix}_PASSWORD)",
    )
    p.add_argument(
        "--ca-file",
        type=Path,
        default=os.environ.get(f"{env_prefix}_CA_FILE"),
        help=f"CA certificates for an mqtts:// broker (env {env_prefix}_CA_FILE)",
    )


def _http_args(p: argparse.ArgumentParser, default: int | None) -> None:
    """--http and --http-host: the live map (`laas.worker.dashboard`)."""
    p.add_argument(
        "--http",
        type=int,
        metavar="PORT",
        default=os.environ.get("LAAS_HTTP_PORT", default),  # argparse converts a string
        help="serve the live map on this port; 0 picks a free one (env LAAS_HTTP_PORT; "
        + ("default: no live map)" if default is None else f"default {default})"),
    )
    p.add_argument(
        "--http-host",
        metavar="HOST",
        default=os.environ.get("LAAS_HTTP_HOST", "127.0.0.1"),
        help="address of the live map (env LAAS_HTTP_HOST; default 127.0.0.1)",
    )


def _cmd_bench_filter(a: argparse.Namespace) -> int:
    from laas.run.filterbench import bench_filter, format_filter_table

    counts = [n for n in (1, 2, 3, 4, 6, 8, 10, 20, 50, 100, 200) if n <= a.max_users]
    rows = bench_filter(
        counts,
        steps=a.steps,
        progress=None if a.json else lambda n: print(f"  {n} users", file=sys.stderr),
    )
    if a.json:
        print(json.dumps([r.as_dict() for r in rows], indent=1))
    else:
        print(format_filter_table(rows))
    return 0


def _origin(text: str) -> tuple[float, float]:
    """``LAT,LON`` in degrees."""
    try:
        lat, lon = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected LAT,LON in degrees, got {text!r}") from None
    if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0):
        raise argparse.ArgumentTypeError(f"LAT,LON out of range: {text!r}")
    return lat, lon


def _bbox(text: str) -> tuple[float, float, float, float]:
    """``MIN_LON,MIN_LAT,MAX_LON,MAX_LAT`` in degrees."""
    try:
        w, s, e, n = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected MIN_LON,MIN_LAT,MAX_LON,MAX_LAT in degrees, got {text!r}"
        ) from None
    if not (w < e and s < n):
        raise argparse.ArgumentTypeError(f"an empty box: {text!r} (west < east, south < north)")
    return w, s, e, n


def _cmd_map_import(a: argparse.Namespace) -> int:
    import time

    from laas.map.importers import import_map

    options: dict[str, object] = {}
    if a.origin is not None:
        if a.format == "osm":
            raise ConfigError("--origin applies to lanelet2 and opendrive maps, not osm")
        options["origin"] = a.origin
    if a.bbox is not None:
        if a.format != "osm":
            raise ConfigError("--bbox applies to osm maps only")
        options["bbox"] = a.bbox
    start = time.perf_counter()
    print(f"laas map import: reading {a.input} as {a.format}", file=sys.stderr)
    result = import_map(a.format, a.input, **options)
    result.write(a.out)
    took = time.perf_counter() - start
    for line in result.report.lines():
        print(line)
    print(f"wrote {a.out} in {took:.1f} s")
    return 0


def _cmd_map_info(a: argparse.Namespace) -> int:
    from laas.map.summary import load_timed, summarise

    hdmap, took = load_timed(a.map)
    summary = summarise(hdmap, took)
    if a.json:
        print(json.dumps(summary.as_dict(), indent=2))
    else:
        print("\n".join(summary.lines()))
    return 0


def _cmd_map_show(a: argparse.Namespace) -> int:
    from laas.evaluation.plots import render_map

    print(f"laas map show: wrote {render_map(read_geojson_file(a.map), a.out, ids=a.ids)}")
    return 0


def _cmd_asyncapi(a: argparse.Namespace) -> int:
    from laas.worker.asyncapi import laas_document_text, write_document

    if a.out is None:
        sys.stdout.write(laas_document_text())
    else:
        print(f"laas asyncapi: wrote {write_document(Path(a.out))}", file=sys.stderr)
    return 0


def _scenario_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scenario", default="messe-hamburg", help="built-in scenario")
    p.add_argument(
        "--map",
        help="instead: road users roaming this lane map (GeoJSON, e.g. from laas map import)",
    )
    p.add_argument("--users", type=int, default=10, help="with --map: road users (default 10)")
    p.add_argument(
        "--duration", type=float, default=120.0, help="with --map: seconds (default 120)"
    )
    p.add_argument(
        "--seed", type=int, default=0, help="seed of the GNSS errors (and of --map's users)"
    )
    p.add_argument("--sigma-pos", type=float, default=1.0, help="receiver position noise, m")
    p.add_argument("--sigma-vel", type=float, default=0.25, help="receiver speed noise, m/s")


def _add_demo_and_bench(sub: Any) -> None:
    """`laas demo` and `laas bench`."""
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
    _http_args(p, default=0)
    p.add_argument(
        "--metrics-port",
        type=int,
        default=None,
        help="serve the cores' and the worker's /metrics, /healthz, /readyz on this port "
        "(0: a free one; default: none)",
    )
    p.add_argument("--metrics-host", default="127.0.0.1", help="address of the metrics server")
    p.set_defaults(func=_cmd_demo)

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


def _add_worker(sub: Any) -> None:
    """`laas worker`."""
    p = sub.add_parser("worker", help="serve the laas service on an LDM service cluster")
    _connection_args(p, "LAAS")
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
    _max_age_arg(p, "drop input older than this when its turn comes")
    p.add_argument(
        "--max-speedup",
        type=float,
        default=float(os.environ.get("LAAS_MAX_SPEEDUP", "1")),
        help="let a session's timestamps run this much faster than real time (env "
        "LAAS_MAX_SPEEDUP; default 1, live devices): set it to a simulator's --speedup",
    )
    _engine_args(p)
    operations_args(p, "LAAS")
    _http_args(p, default=None)
    p.set_defaults(func=_cmd_worker)


def _add_simulate(sub: Any) -> None:
    """`laas simulate`."""
    p = sub.add_parser("simulate", help="run a scenario's road users as live LDM participants")
    _connection_args(p, "LAAS")
    _scenario_args(p)
    p.add_argument("--speedup", type=float, default=1.0, help="faster than real time by")
    _max_age_arg(p, "drop replies older than this, and fail a request after 2x this + 1 s")
    p.add_argument("--out", help="write the answers (JSON Lines) here; default stdout")
    from laas.bridges.commands import device_account_args

    device_account_args(p, "road user")
    p.add_argument(
        "--prefix",
        default="sim-",
        help="the road users' client ids (and accounts) with --device-accounts: PREFIX + user",
    )
    p.add_argument(
        "--list-accounts",
        action="store_true",
        help="print the accounts the users need with --device-accounts, and exit",
    )
    p.add_argument(
        "--service-key",
        default=os.environ.get("LAAS_SERVICE_KEY"),
        help="pin the laas worker's identity (its public key; env LAAS_SERVICE_KEY)",
    )
    p.add_argument(
        "--trust-anchor",
        action="append",
        default=[],
        metavar="KEY",
        help="trust a laas identity this anchor endorsed (repeatable)",
    )
    p.add_argument(
        "--core-key",
        default=os.environ.get("LAAS_CORE_KEY"),
        help="pin the user core's key: act only on notices it signed (env LAAS_CORE_KEY)",
    )
    p.set_defaults(func=_cmd_simulate)


def _add_offline(sub: Any) -> None:
    """The offline commands: replay, evaluate, privacy, liar, regions, bench-filter, map,
    asyncapi, scenario, plot."""
    p = sub.add_parser("replay", help="correct a recorded trace (JSON Lines) offline")
    p.add_argument("--map", required=True, help="GeoJSON lane map")
    p.add_argument("trace", help="trace file, JSON Lines with a `user` field; - for stdin")
    p.add_argument("--out", help="output file (default: stdout)")
    _engine_args(p)
    p.set_defaults(func=_cmd_replay)

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

    p = sub.add_parser(
        "regions",
        help="one worker against regional workers on the same road users (offline): lane "
        "accuracy, mean error, lane accuracy after each hand-over; each worker alone and "
        "with hand-over",
    )
    _scenario_args(p)
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

    p = sub.add_parser(
        "bench-filter", help="lane filter time per update against users in a segment"
    )
    p.add_argument("--max-users", type=int, default=100, help="largest group (default 100)")
    p.add_argument("--steps", type=int, default=10, help="timed steps per group size")
    p.add_argument("--json", action="store_true", help="machine-readable output")
    p.set_defaults(func=_cmd_bench_filter)

    p = sub.add_parser("map", help="import real HD maps, and look at lane maps")
    maps = p.add_subparsers(dest="map_command", required=True)
    q = maps.add_parser(
        "import", help="convert a Lanelet2, OpenDRIVE or OpenStreetMap file to a lane map"
    )
    q.add_argument("format", choices=["lanelet2", "opendrive", "osm"], help="source format")
    q.add_argument("input", help="the source file (.osm, .xodr, .osm.pbf)")
    q.add_argument("--out", required=True, help="the lane map to write (GeoJSON)")
    q.add_argument(
        "--origin",
        type=_origin,
        help="LAT,LON: OpenDRIVE without a geoReference: its local origin; Lanelet2: the "
        "projection origin (default: the mean of its nodes)",
    )
    q.add_argument(
        "--bbox", type=_bbox, help="MIN_LON,MIN_LAT,MAX_LON,MAX_LAT: cut an extract (osm)"
    )
    q.set_defaults(func=_cmd_map_import)
    q = maps.add_parser("info", help="segments, lanes by type, length, bounds, load time")
    q.add_argument("map", help="lane map (GeoJSON)")
    q.add_argument("--json", action="store_true", help="machine-readable output")
    q.set_defaults(func=_cmd_map_info)
    q = maps.add_parser("show", help="a picture of the lanes, coloured by type")
    q.add_argument("map", help="lane map (GeoJSON)")
    q.add_argument("--out", required=True, help="the PNG to write")
    q.add_argument("--ids", action="store_true", help="write the segment ids")
    q.set_defaults(func=_cmd_map_show)

    p = sub.add_parser(
        "asyncapi", help="write the AsyncAPI 3.0 document of the LDM topics and laas messages"
    )
    p.add_argument("--out", help="the file to write (JSON; default: stdout)")
    p.set_defaults(func=_cmd_asyncapi)

    p = sub.add_parser("scenario", help="write a simulated trace and its ground truth")
    _scenario_args(p)
    p.add_argument("--out", required=True, help="folder for trace.jsonl and truth.jsonl")
    p.set_defaults(func=_cmd_scenario)

    p = sub.add_parser("plot", help="pictures like the paper's Fig. 3 and Fig. 4")
    _scenario_args(p)
    p.add_argument("--out", required=True, help="folder for the PNG files")
    p.set_defaults(func=_cmd_plot)


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of every subcommand."""
    parser = Parser(
        prog="laas", description="Location as a Service: lane-level positioning at the edge."
    )
    add_version(parser, "laas")
    sub = parser.add_subparsers(dest="command", required=True)

    _add_demo_and_bench(sub)
    _add_worker(sub)
    _add_simulate(sub)
    _add_offline(sub)

    from laas.bridges.commands import add_bridge_commands  # owntracks, gpsd, cam

    add_bridge_commands(sub, _connection_args)
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


if __name__ == "__main__":
    sys.exit(main())
