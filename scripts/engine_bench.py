"""The engine alone, without the worker around it: wall time per fix of
`Engine.process_many` over users roaming a bundled map, one at a time or in batches.

    .venv/bin/python scripts/engine_bench.py                 # one at a time, on the second
    .venv/bin/python scripts/engine_bench.py --batch 64 --spread
    .venv/bin/python scripts/engine_bench.py --profile OUT   # cProfile's table, raw into OUT

Every user's fixes come on the whole second (as GNSS receivers emit them) unless
`--spread`, which keeps each user's own phase. A throw-away engine takes the first fixes
first, so the compiled arithmetic (`laas.engine.jit`) is built before the clock starts.
`laas bench --worker-only` times the worker's own stages too; this is the engine's share
of it, and its cProfile table names the entries (docs/performance.md).
"""

from __future__ import annotations

import argparse
import cProfile
import pstats
import time

from laas.engine import Engine
from laas.map.bundled import bundled_map
from laas.map.geojson import read_geojson_file
from laas.sim.roam import roam_scenario
from laas.sim.scenario import simulate_with


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--map", default="messe-hamburg", help="bundled map (default messe-hamburg)")
    p.add_argument("--users", type=int, default=200, help="roaming users (default 200)")
    p.add_argument("--duration", type=float, default=50.0, help="simulated seconds (default 50)")
    p.add_argument("--batch", type=int, default=1, help="fixes per call (default 1)")
    p.add_argument("--spread", action="store_true", help="each user at its own phase")
    p.add_argument("--seed", type=int, default=0, help="seed of the scenario (default 0)")
    p.add_argument("--profile", metavar="OUT", help="run under cProfile, its raw stats to OUT")
    a = p.parse_args()
    if a.batch < 1:
        p.error(f"--batch must be at least 1, not {a.batch}")
    hdmap = read_geojson_file(bundled_map(a.map))
    scenario = roam_scenario(hdmap, a.seed, a.users, a.duration)
    if not a.spread:
        users = tuple(u.model_copy(update={"phase": 0.0}) for u in scenario.users)
        scenario = scenario.model_copy(update={"users": users})
    trace = simulate_with(hdmap, scenario, a.seed, sigma_pos=1.0, sigma_vel=0.25)
    fixes = [(f.user, f.measurement) for f in trace.fixes]
    warm = Engine(hdmap)
    for k in range(0, min(400, len(fixes)), a.batch):
        warm.process_many(fixes[k : k + a.batch])
    engine = Engine(hdmap)

    def run() -> None:
        for k in range(0, len(fixes), a.batch):
            engine.process_many(fixes[k : k + a.batch])

    if a.profile:
        cProfile.runctx("run()", globals(), {"run": run}, a.profile)
        pstats.Stats(a.profile).sort_stats("tottime").print_stats(30)
        return
    started = time.perf_counter()
    run()
    spent = time.perf_counter() - started
    how = f"in batches of {a.batch}" if a.batch > 1 else "one at a time"
    when = "spread over the second" if a.spread else "on the whole second"
    print(
        f"{spent / len(fixes) * 1e6:.1f} us a fix: {len(fixes)} fixes of {a.users} users on "
        f"{a.map}, {how}, {when}"
    )


if __name__ == "__main__":
    main()
