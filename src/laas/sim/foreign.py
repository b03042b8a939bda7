"""Roads from another generator: a folder of recorded runs with their truth, read as traces.

A foreign set holds one folder per road under one folder per receiver noise,

    DIR/sigma<S>/<road>/map.geojson    the lane map (the project's GeoJSON lane format)
                        trace.jsonl    what the receivers sent (`laas replay`'s input)
                        truth.jsonl    per fix: the true position (latitude and
                                       longitude, or easting and northing as
                                       `laas scenario` writes them), segment and lane
                        meta.json      what was drawn (optional)

and is scored as the project's own runs are (`laas.evaluation.score`), by (segment, lane) id as
well as by geometry. Such a set says nothing of the common error it drew beyond its size,
so the oracle's common error at a fix is estimated from the truth: the mean of every
fix's error, fix less truth, within `ORACLE_WINDOW` seconds of it,

    b^(t) = mean { p_j - x_j : |t_j - t| <= W },

which averages the receivers' own errors (noise sigma_pos, a bias of a few decimetres
each) over the users and seconds of the window: with 3-12 users at 1 Hz, some 30-120
fixes, a few decimetres' error at most, against a common error of metres.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from laas.errors import TraceError
from laas.map.geojson import read_geojson_file
from laas.map.hdmap import HdMap
from laas.sim.plan import SimulatedFix
from laas.sim.trace import TraceLine, read_trace

__all__ = [
    "FOREIGN_FAMILY",
    "ORACLE_WINDOW",
    "ForeignRoad",
    "ForeignTrace",
    "default_foreign_dir",
    "find_roads",
    "load_road",
]

FOREIGN_FAMILY = "foreign"
"""The family name under which a foreign set's runs are reported."""

ORACLE_WINDOW = 5.0
"""s either side of a fix over which the oracle averages the fixes' errors."""


@dataclass(frozen=True, slots=True)
class ForeignRoad:
    """One road of a foreign set: its number, its receiver noise and its folder."""

    road: int
    sigma_pos: float
    path: Path


@dataclass(frozen=True)
class ForeignTrace:
    """A foreign road's fixes with their truth, in the order the receivers sent them, and
    what its generator says it drew."""

    fixes: tuple[SimulatedFix, ...]
    meta: dict[str, object]


def default_foreign_dir() -> Path | None:
    """`../shared/foreign-roads` beside the working directory or beside this checkout,
    where present."""
    here = Path(__file__).resolve()
    for base in (Path.cwd(), *here.parents):
        candidate = base.parent / "shared" / "foreign-roads"
        if candidate.is_dir():
            return candidate
    return None


def find_roads(root: Path) -> list[ForeignRoad]:
    """Every road of the set under `root` (`sigma<S>/<road>/`), by road number."""
    if not root.is_dir():
        raise TraceError(f"{root}: no such folder; give the foreign set's folder (--foreign DIR)")
    roads = []
    for noise in sorted(root.glob("sigma*")):
        try:
            sigma = float(noise.name.removeprefix("sigma"))
        except ValueError:
            continue
        for folder in noise.iterdir():
            if folder.is_dir() and folder.name.isdigit() and (folder / "trace.jsonl").is_file():
                roads.append(ForeignRoad(int(folder.name), sigma, folder))
    if not roads:
        raise TraceError(
            f"{root}: no roads found; expected sigma<S>/<road>/ folders holding map.geojson, "
            "trace.jsonl and truth.jsonl"
        )
    return sorted(roads, key=lambda r: r.road)


def load_road(road: ForeignRoad) -> tuple[HdMap, ForeignTrace]:
    """The map and the fixes of one road, each with its truth and the oracle's estimate of
    the common error (module docstring)."""
    hdmap = read_geojson_file(road.path / "map.geojson")
    meta_file = road.path / "meta.json"
    meta = json.loads(meta_file.read_text()) if meta_file.is_file() else {}
    trace = road.path / "trace.jsonl"
    lines: list[TraceLine] = []
    with trace.open() as f:
        for item in read_trace(f, str(trace)):
            if isinstance(item, TraceError):
                raise item
            if isinstance(item, TraceLine):
                lines.append(item)
    truths: dict[tuple[str, int], dict[str, object]] = {}
    with (road.path / "truth.jsonl").open() as f:
        for text in f:
            if text.strip():
                row = json.loads(text)
                truths[(str(row["user"]), int(row["timestamp"]))] = row
    proj = hdmap.projection
    n = len(lines)
    fix_xy = np.empty((n, 2))
    true_xy = np.empty((n, 2))
    t = np.empty(n)
    for i, line in enumerate(lines):
        m = line.measurement
        row = truths.get((line.user, m.timestamp))
        if row is None:
            raise TraceError(
                f"{trace}:{line.line}: no truth for user {line.user!r} at {m.timestamp}"
            )
        fix_xy[i] = proj.to_utm(m.longitude, m.latitude)
        true_xy[i] = _true_position(row, proj.to_utm)
        t[i] = m.timestamp / 1000.0
    error = fix_xy - true_xy
    order = np.argsort(t)
    ts, cum = t[order], np.cumsum(np.vstack([[0.0, 0.0], error[order]]), axis=0)
    lo = np.searchsorted(ts, t - ORACLE_WINDOW, side="left")
    hi = np.searchsorted(ts, t + ORACLE_WINDOW, side="right")
    common = (cum[hi] - cum[lo]) / (hi - lo)[:, None]
    heading = _true_headings([line.user for line in lines], true_xy, t)
    fixes = []
    for i, line in enumerate(lines):
        row = truths[(line.user, line.measurement.timestamp)]
        fixes.append(
            SimulatedFix(
                user=line.user,
                kind=line.user.split("-")[0],
                measurement=line.measurement,
                true_e=float(true_xy[i, 0]),
                true_n=float(true_xy[i, 1]),
                true_heading=float(heading[i]),
                segment=str(row["segment"]),
                lane=int(row["lane"]),  # type: ignore[call-overload]
                common_e=float(common[i, 0]),
                common_n=float(common[i, 1]),
            )
        )
    return hdmap, ForeignTrace(tuple(fixes), meta)


def _true_position(
    row: dict[str, object], to_utm: Callable[[float, float], tuple[float, float]]
) -> tuple[float, float]:
    """A truth row's position in the map's frame: its WGS84 `latitude` and `longitude`,
    or the `easting` and `northing` that `laas scenario` writes (`laas.sim.truth`)."""
    if "easting" in row:
        return float(row["easting"]), float(row["northing"])  # type: ignore[arg-type]
    return to_utm(float(row["longitude"]), float(row["latitude"]))  # type: ignore[arg-type]


def _true_headings(users: list[str], xy: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Each fix's true heading (degrees from north): towards the user's next true position,
    or from its previous one at its last fix; a user that has not moved keeps the last."""
    out = np.zeros(len(users))
    by_user: dict[str, list[int]] = {}
    for i, user in enumerate(users):
        by_user.setdefault(user, []).append(i)
    for ks in by_user.values():
        ks.sort(key=lambda k: t[k])
        last = 0.0
        for j, k in enumerate(ks):
            a, b = (k, ks[j + 1]) if j + 1 < len(ks) else (ks[j - 1], k) if j else (k, k)
            de, dn = xy[b] - xy[a]
            if math.hypot(de, dn) > 0.05:
                last = math.degrees(math.atan2(de, dn)) % 360.0
            out[k] = last
    return out
