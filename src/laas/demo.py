"""`laas demo`: the paper's scenario run through LaaS, with its table and pictures."""

from __future__ import annotations

from pathlib import Path

from laas.evaluate import TABLE_I_CONFIGS, evaluate, format_table, print_progress
from laas.scenario import hamburg_scenario

__all__ = ["run_demo"]


def run_demo(out: Path, runs: int = 5) -> int:
    """Evaluate both modes on the Hamburg scenario, print the table, write the pictures."""
    from laas.cli import _plots

    scenario = hamburg_scenario()
    print(f"LaaS demo: scenario {scenario.name}, {len(scenario.users)} road users, {runs} seeds")
    rows = evaluate(
        scenario,
        runs=runs,
        configs=[c for c in TABLE_I_CONFIGS if c[0]],
        progress=print_progress,
    )
    print(format_table(rows))
    _plots(scenario.name, out, seed=0, sigma_pos=1.0, sigma_vel=0.25)
    return 0
