"""One user's timeline on a road of a foreign set, and how far the set's courses are off.

    .venv/bin/python scripts/foreign_timeline.py 111 car-6 20 50   # road, user, t0, t1 (s)
    .venv/bin/python scripts/foreign_timeline.py --courses         # course errors

The timeline answers the road as `laas evaluate --suite foreign` does (default mode,
batches as live) and prints per fix of the user: the time from the road's first fix, the
true (segment, lane), the answer's and its probability, the filtered position's lateral
offset d (the common error not removed) and the true one td, the track's lateral
velocity and the lane-change threshold (2 sigma of it), and the lanes' marginal
posterior. `--courses` prints the robust sigma of the reported course against the true
direction of motion, for movers above 3 m/s, per kind and sigma_pos.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np

from laas.engine import Engine
from laas.evaluation.suite import engine_config
from laas.sim.batches import in_batches
from laas.sim.foreign import default_foreign_dir, find_roads, load_road


def timeline(root: Path, road: int, user: str, t0: float, t1: float) -> None:
    (found,) = [r for r in find_roads(root) if r.road == road]
    hdmap, trace = load_road(found)
    engine = Engine(hdmap, engine_config("default", found.sigma_pos))
    start = trace.fixes[0].measurement.timestamp
    fixes = [(f.user, f.measurement, f) for f in trace.fixes]
    for batch in in_batches(fixes, lambda x: x[1].timestamp):
        answers = engine.process_many([(u, m) for u, m, _ in batch])
        for (who, m, fix), a in zip(batch, answers, strict=True):
            t = (m.timestamp - start) / 1000.0
            if who != user or not t0 <= t <= t1 or a is None or a.segment is None:
                continue
            track = engine._tracks[who]
            seg = hdmap.segments[a.segment]
            s, d = seg.frame(*track.position)
            tangent = seg.tangent(s)
            normal = np.array([tangent[1], -tangent[0]])
            v_lat = float(track.velocity @ normal)
            noise = 2.0 * math.sqrt(max(float(normal @ track.velocity_cov @ normal), 0.0))
            _, td = seg.frame(fix.true_e, fix.true_n)
            kept = engine._lanes._lanes.get(who)  # type: ignore[attr-defined]
            marginal = ""
            if kept is not None:
                mass = kept.area.u_moments(kept.normal)[:, 0]
                p = (mass[:, None] * kept.alpha).sum(axis=0)
                marginal = " ".join(f"{x:.2f}" for x in p / p.sum())
            print(
                f"{t:6.1f} true {fix.segment}:{fix.lane} answer {a.segment}:{a.lane} "
                f"p {a.probability:.2f}  d {d:6.2f} td {td:6.2f} vlat {v_lat:5.2f} "
                f"threshold {noise:4.2f} [{marginal}]"
            )


def courses(root: Path) -> None:
    errors: dict[tuple[str, float], list[float]] = {}
    for found in find_roads(root):
        _, trace = load_road(found)
        for f in trace.fixes:
            if f.measurement.speed > 3.0:
                off = (f.measurement.heading - f.true_heading + 180.0) % 360.0 - 180.0
                errors.setdefault((f.kind, found.sigma_pos), []).append(off)
    for (kind, sigma), values in sorted(errors.items()):
        v = np.array(values)
        robust = 1.4826 * float(np.median(np.abs(v - np.median(v))))
        print(
            f"{kind:<11} sigma_pos {sigma:g}: {v.size} fixes, course error robust sigma "
            f"{robust:.2f} deg, 99th percentile {np.percentile(np.abs(v), 99):.1f} deg"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("road", nargs="?", type=int)
    parser.add_argument("user", nargs="?")
    parser.add_argument("t0", nargs="?", type=float, default=0.0)
    parser.add_argument("t1", nargs="?", type=float, default=math.inf)
    parser.add_argument("--foreign", type=Path, default=default_foreign_dir())
    parser.add_argument("--courses", action="store_true")
    a = parser.parse_args()
    if a.foreign is None:
        parser.error("no foreign set found: give --foreign DIR")
    if a.courses:
        courses(a.foreign)
    elif a.road is None or a.user is None:
        parser.error("give ROAD and USER, or --courses")
    else:
        timeline(a.foreign, a.road, a.user, a.t0, a.t1)


if __name__ == "__main__":
    main()
