"""A simulated run as files: its fixes (``trace.jsonl``) and their truth (``truth.jsonl``).

``trace.jsonl`` holds one fix per line as `laas replay` reads it
(`laas.sim.trace.format_measurement`). ``truth.jsonl`` holds, line for line, where
each fix really was:

    {"user", "kind", "timestamp" (ms), "easting", "northing" (m, UTM), "epsg" (of the
     UTM zone), "segment", "lane"}

`laas scenario` writes both (`write_run`).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from laas.sim.scenario import SimulatedFix, Trace
from laas.sim.trace import format_measurement

__all__ = ["TRACE_FILE", "TRUTH_FILE", "format_truth", "truth_row", "write_run"]

TRACE_FILE = "trace.jsonl"
TRUTH_FILE = "truth.jsonl"


def truth_row(fix: SimulatedFix, epsg: int) -> dict[str, Any]:
    """Where one simulated fix really was (the module docstring's fields)."""
    return {
        "user": fix.user,
        "kind": fix.kind,
        "timestamp": fix.measurement.timestamp,
        "easting": fix.true_e,
        "northing": fix.true_n,
        "epsg": epsg,
        "segment": fix.segment,
        "lane": fix.lane,
    }


def format_truth(fix: SimulatedFix, epsg: int) -> str:
    """One line of ``truth.jsonl``."""
    return json.dumps(truth_row(fix, epsg))


def write_run(trace: Trace, epsg: int, out: Path) -> tuple[Path, Path]:
    """Write `trace`'s fixes and truth into folder `out` (made if missing); both paths."""
    out.mkdir(parents=True, exist_ok=True)
    fixes, truth = out / TRACE_FILE, out / TRUTH_FILE
    with open(fixes, "w", encoding="utf-8") as f:
        for fix in trace.fixes:
            f.write(format_measurement(fix.user, fix.measurement) + "\n")
    with open(truth, "w", encoding="utf-8") as f:
        for fix in trace.fixes:
            f.write(format_truth(fix, epsg) + "\n")
    return fixes, truth
