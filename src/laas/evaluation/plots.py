"""Pictures: the paper's Fig. 3 (true traces on the lanes) and Fig. 4 (lanes over time),
and a lane map on its own (`laas map show`).

A map is drawn lane by lane: each centre line as wide as the lane (to the picture's
scale), coloured by type; arrows along a one-way lane show its direction of travel (a
lane for both directions has none); segment ids may be written at their middle.
Coordinates are UTM metres of the map's projection, relative to its south-west corner.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.axes import Axes
from matplotlib.lines import Line2D

from laas.errors import ConfigError
from laas.map.hdmap import HdMap
from laas.models import CorrectedPosition
from laas.sim.scenario import EPOCH_MS, Scenario, Trace

__all__ = [
    "LANE_COLOURS",
    "draw_lanes",
    "plot_lanes_over_time",
    "plot_traces",
    "render_map",
    "scenario_plots",
]

LANE_COLOURS = {
    "driving": "#9aa0a6",
    "parking": "#c7b38a",
    "bicycle": "#d98c8c",
    "sidewalk": "#b5c99a",
}
"""Lane colour by type: grey driving, tan parking, red bicycle, green sidewalk."""

_ARROW_EVERY = 40.0  # m of centre line between direction arrows


def draw_lanes(ax: Axes, hdmap: HdMap, scale: float = 2.2, alpha: float = 0.6) -> None:
    """Draw every lane of `hdmap` on `ax`, relative to the map's south-west corner;
    `scale` points of line width per metre of lane width."""
    e0, n0 = hdmap.bounds[0], hdmap.bounds[1]
    for segment in hdmap.segments.values():
        for lane in segment.lanes:
            xs, ys = lane.centerline.xy
            ax.plot(
                np.asarray(xs) - e0,
                np.asarray(ys) - n0,
                color=LANE_COLOURS.get(lane.type, "grey"),
                linewidth=max(0.3, lane.width * scale),
                alpha=alpha,
                solid_capstyle="butt",
            )


def _arrows(hdmap: HdMap, e0: float, n0: float, size: float) -> np.ndarray:
    """Arrows along every one-way lane in its direction of travel, one every
    `_ARROW_EVERY` m: rows of (x, y, dx, dy), relative to (e0, n0)."""
    rows: list[tuple[float, float, float, float]] = []
    for segment in hdmap.segments.values():
        for lane in segment.lanes:
            if lane.direction == "both":
                continue
            sign = 1.0 if lane.direction == "forward" else -1.0
            line = lane.centerline
            length = line.length
            count = max(1, int(length // _ARROW_EVERY))
            for k in range(count):
                s = (k + 0.5) * length / count
                p = line.interpolate(s)
                q = line.interpolate(min(length, s + 0.1))
                dx, dy = q.x - p.x, q.y - p.y
                norm = float(np.hypot(dx, dy)) or 1.0
                rows.append((p.x - e0, p.y - n0, sign * dx / norm * size, sign * dy / norm * size))
    return np.array(rows).reshape(-1, 4)


def render_map(hdmap: HdMap, path: str | Path, ids: bool = False, title: str | None = None) -> Path:
    """Write a PNG of `hdmap`: lanes coloured by type, travel arrows, and with `ids` the
    segment ids. The figure grows with the map (at most 16 inches a side)."""
    x0, y0, x1, y1 = hdmap.bounds
    width, height = max(x1 - x0, 1.0), max(y1 - y0, 1.0)
    side = float(np.clip(max(width, height) / 60.0, 6.0, 16.0))
    fig, ax = plt.subplots(
        figsize=(side * min(1.0, width / height) + 1.5, side * min(1.0, height / width) + 1.0)
    )
    # line widths in points at this figure's scale: 72 points per inch
    points_per_m = 72.0 * side / max(width, height)
    draw_lanes(ax, hdmap, scale=points_per_m, alpha=0.75)
    arrow = float(np.clip(max(width, height) / 150.0, 1.0, 6.0))
    arrows = _arrows(hdmap, x0, y0, arrow)
    if len(arrows):
        ax.quiver(*arrows.T, angles="xy", scale_units="xy", scale=1.0, width=0.0015, color="black")
    if ids:
        for segment in hdmap.segments.values():
            mid = segment.reference.interpolate(0.5, normalized=True)
            ax.text(mid.x - x0, mid.y - y0, segment.id, fontsize=5, ha="center", va="center")
    handles = [
        Line2D([], [], color=colour, linewidth=4, label=kind)
        for kind, colour in LANE_COLOURS.items()
    ]
    ax.legend(handles=handles, fontsize=7, loc="best")
    ax.set_aspect("equal")
    ax.set_xlabel(f"easting - {x0:.0f} m (UTM zone {hdmap.projection.zone})")
    ax.set_ylabel(f"northing - {y0:.0f} m")
    ax.set_title(title or f"{hdmap.source}: {len(hdmap.segments)} road elements", fontsize=9)
    fig.tight_layout()
    out = Path(path)
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(out, dpi=110)
    except (OSError, ValueError) as exc:  # an unwritable place, a format matplotlib lacks
        raise ConfigError(f"{out}: cannot write the picture: {exc}") from exc
    finally:
        plt.close(fig)
    return out


def plot_traces(hdmap: HdMap, trace: Trace, path: Path, measured: bool = True) -> Path:
    """Fig. 3: the lanes of the map and every user's true trace (and raw fixes)."""
    fig, ax = plt.subplots(figsize=(7, 7))
    e0, n0 = hdmap.bounds[0], hdmap.bounds[1]
    draw_lanes(ax, hdmap)
    users = sorted({f.user for f in trace.fixes})
    for user in users:
        fixes = [f for f in trace.fixes if f.user == user]
        (line,) = ax.plot(
            [f.true_e - e0 for f in fixes], [f.true_n - n0 for f in fixes], label=f"{user} (truth)"
        )
        if measured:
            pts = [
                hdmap.projection.to_utm(f.measurement.longitude, f.measurement.latitude)
                for f in fixes
            ]
            ax.scatter(
                [p[0] - e0 for p in pts],
                [p[1] - n0 for p in pts],
                s=4,
                color=line.get_color(),
                alpha=0.5,
                label=f"{user} (GPS)",
            )
    ax.set_aspect("equal")
    ax.set_xlabel(f"easting - {e0:.0f} m")
    ax.set_ylabel(f"northing - {n0:.0f} m")
    ax.set_title(
        f"{trace.scenario.name}: true traces on the lanes\n"
        "(lanes: grey driving, tan parking, red bicycle, green sidewalk)",
        fontsize=10,
    )
    ax.legend(fontsize=7, loc="best")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def plot_lanes_over_time(
    trace: Trace, answers: Sequence[CorrectedPosition | None], path: Path
) -> Path:
    """Fig. 4: per user, the assigned lane over time against the true lane."""
    users = sorted({f.user for f in trace.fixes})
    fig, axes = plt.subplots(
        len(users), 1, figsize=(8, 2.2 * len(users)), sharex=True, squeeze=False
    )
    for ax, user in zip(axes[:, 0], users, strict=True):
        idx = [i for i, f in enumerate(trace.fixes) if f.user == user]
        t = [(trace.fixes[i].measurement.timestamp - EPOCH_MS) / 1000.0 for i in idx]
        truth = [trace.fixes[i].lane for i in idx]
        got = [a.lane if (a := answers[i]) is not None and a.lane is not None else -1 for i in idx]
        ax.step(t, truth, where="post", color="black", linewidth=2.5, alpha=0.4, label="true lane")
        ax.plot(t, got, ".", color="tab:blue", markersize=4, label="assigned lane")
        ax.set_ylabel(user)
        ax.invert_yaxis()
        ax.set_yticks(sorted(set(truth) | {g for g in got if g >= 0}))
        ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=7, loc="upper right")
    axes[-1, 0].set_xlabel("time, s")
    fig.suptitle(f"{trace.scenario.name}: assigned lane over time (lane 0 = leftmost)")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def scenario_plots(
    scenario: Scenario,
    hdmap: HdMap,
    out: Path,
    seed: int = 0,
    sigma_pos: float = 1.0,
    sigma_vel: float = 0.25,
) -> list[Path]:
    """Simulate one run of `scenario` and draw it into folder `out`: the traces, and the
    lanes over time as each mode (paper, default) answers them; the paths written."""
    from laas.config import EngineConfig
    from laas.evaluation.score import answer_trace
    from laas.sim.scenario import simulate_with

    name = scenario.name
    trace = simulate_with(hdmap, scenario, seed, sigma_pos=sigma_pos, sigma_vel=sigma_vel)
    out.mkdir(parents=True, exist_ok=True)
    paths = [plot_traces(hdmap, trace, out / f"{name}-traces.png")]
    for mode in ("paper", "default"):
        config = EngineConfig(mode=mode, sigma_pos=sigma_pos, sigma_vel=sigma_vel)
        answers = answer_trace(hdmap, trace, config)
        paths.append(plot_lanes_over_time(trace, answers, out / f"{name}-lanes-{mode}.png"))
    return paths
