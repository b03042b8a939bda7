"""Pictures like the paper's: Fig. 3 (true traces on the lanes) and Fig. 4 (lanes over time)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from laas.map.hdmap import HdMap
from laas.map.render import draw_lanes
from laas.models import CorrectedPosition
from laas.sim.scenario import EPOCH_MS, Trace

__all__ = ["plot_lanes_over_time", "plot_traces"]


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
