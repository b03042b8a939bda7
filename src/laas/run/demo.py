"""`laas demo`: the paper's scenario through the paper's deployment, end to end.

Starts three brokers, two LDM cores and the LaaS worker on this machine, runs the
simulated road users of the Hamburg scenario as real participants (sped up), and ends
with the accuracy of what they received over MQTT beside the offline engine on the same
fixes, and the pictures of the paper's Fig. 3 and Fig. 4. While the road users run, the
worker's live map is served (`laas.worker.dashboard`) and its URL printed at the start.
"""

from __future__ import annotations

import sys
from pathlib import Path

from laas.config import EngineConfig
from laas.errors import ConfigError
from laas.evaluation.plots import plot_lanes_over_time, plot_traces
from laas.evaluation.score import RunResult, answer_trace, score
from laas.map.geojson import read_geojson_file
from laas.progress import progress_printer
from laas.run.deployment import BrokerChoice, LocalDeployment
from laas.run.participants import run_participants
from laas.sim.scenario import hamburg_scenario, simulate_with
from laas.worker.dashboard import DashboardServer

__all__ = ["run_demo"]


def _row(name: str, r: RunResult) -> str:
    return (
        f"{name:<34}{r.answered:>9}{r.rmse_x:>8.2f}{r.rmse_y:>8.2f}{r.aed:>8.2f}"
        f"{r.accuracy:>8.2f}{r.cross:>8.2f}{r.along:>8.2f}"
    )


def run_demo(
    out: Path,
    *,
    seed: int = 0,
    sigma_pos: float = 1.0,
    sigma_vel: float = 0.25,
    speedup: float = 10.0,
    brokers: BrokerChoice = "auto",
    http_port: int = 0,
    http_host: str = "127.0.0.1",
    metrics_port: int | None = None,
    metrics_host: str = "127.0.0.1",
) -> int:
    """Run the demo; print the table; write the pictures to `out`. The live map is served
    on `http_host`:`http_port` (0: a free port) while the road users run, and with
    `metrics_port` the cores' and the worker's metrics (/metrics, /healthz, /readyz)."""
    scenario = hamburg_scenario()
    hdmap = read_geojson_file(scenario.map)
    trace = simulate_with(hdmap, scenario, seed, sigma_pos=sigma_pos, sigma_vel=sigma_vel)
    errors = trace.errors
    config = EngineConfig(sigma_pos=sigma_pos, sigma_vel=sigma_vel, sigma_heading=0.05)
    print(
        f"LaaS demo: {len(scenario.users)} road users on {scenario.name}, {len(trace.fixes)} "
        f"fixes, common GNSS error ({errors.bias_east:+.0f} m E, {errors.bias_north:+.0f} m N), "
        f"sigma_pos {sigma_pos} m"
    )
    with LocalDeployment(
        hdmap, config, brokers=brokers, metrics_port=metrics_port, metrics_host=metrics_host
    ) as deployment:
        print(
            f"started 3 {deployment.kind} brokers (user {deployment.user_url}, inter-cluster, "
            "service), 2 LDM cores and the laas worker; participants pin the worker's "
            "identity and the user core's key"
        )
        if deployment.service is None:
            raise ConfigError("the demo's worker runs in this process; it has not started")
        live_map = DashboardServer(
            deployment.service, deployment.provider, host=http_host, port=http_port
        )
        try:
            print(f"live map: {live_map.url} (while the road users run)", flush=True)
            if deployment.metrics_url is not None:
                print(f"metrics: {deployment.metrics_url} (and /healthz, /readyz)", flush=True)
            print(f"running the road users as LDM participants at {speedup:g}x real time:")
            live = run_participants(
                deployment.user_url,
                trace,
                speedup=speedup,
                progress=progress_printer("  sent", "fixes"),
                hdmap=hdmap,
                **deployment.trust,
            )
        finally:
            live_map.stop()
    for error in live.errors[:5]:
        print(f"  {error}", file=sys.stderr)
    if not live.answered:
        print("laas demo: no fix was answered over MQTT", file=sys.stderr)
        return 1
    rows = [_row("received over MQTT (default mode)", score(hdmap, trace, live.answers))]
    offline = {}
    for mode in ("default", "paper"):
        offline[mode] = answer_trace(hdmap, trace, config.model_copy(update={"mode": mode}))
        rows.append(_row(f"offline replay, {mode} mode", score(hdmap, trace, offline[mode])))
    raw = score(hdmap, trace, offline["default"])  # its raw_aed column: the fixes as sent
    lat = sorted(live.latencies)
    print()
    head = f"{'':<34}{'answered':>9}" + "".join(
        f"{c:>8}" for c in ("RMSE_x", "RMSE_y", "AED", "Acc.", "cross", "along")
    )
    print(head)
    print("-" * len(head))
    print("\n".join(rows))
    print(f"{'raw GNSS fixes':<34}{len(trace.fixes):>9}{'':>16}{raw.raw_aed:>8.2f}")
    p50, p99 = lat[len(lat) // 2], lat[min(len(lat) - 1, int(0.99 * len(lat)))]
    print(
        f"\nround trip participant -> cores -> worker -> participant: p50 {1000 * p50:.1f} ms, "
        f"p99 {1000 * p99:.1f} ms over {len(lat)} replies"
    )
    out.mkdir(parents=True, exist_ok=True)
    for path in (
        plot_traces(hdmap, trace, out / "demo-traces.png"),
        plot_lanes_over_time(trace, live.answers, out / "demo-lanes-live.png"),
        plot_lanes_over_time(trace, offline["paper"], out / "demo-lanes-paper.png"),
    ):
        print(f"wrote {path}")
    return 0
