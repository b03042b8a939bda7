"""`laas bench --worker-only`: the worker's own code, fed encrypted fixes in process."""

from __future__ import annotations

import json
import subprocess
import sys

from laas.run.workerbench import bench_worker, format_worker_report


def test_the_worker_alone_answers_every_fix_and_times_each_stage() -> None:
    lines: list[str] = []
    r = bench_worker(users=12, duration=20.0, seed=3, batch=8, progress=lines.append)
    assert r.fixes > 150
    # every sealed fix opened, answered and sealed back, one at a time and in batches
    assert r.answered == r.fixes
    for times in (r.single, r.batched):  # every stage timed (no figure left at 0)
        for us in (times.open_us, times.service_us, times.engine_us, times.seal_us):
            assert us > 0.0
    assert r.filterpy_us > 0.0
    assert lines and lines[0].startswith("sealing")
    # The report prints the figures measured (not recomputed here: the properties'
    # formulas are the code's own).
    table = format_worker_report(r)
    assert "engine / filterpy" in table and f"{r.answered} answered" in table
    assert "batches of 8" in table
    assert (
        f"{r.batched.fixes_per_second:,.0f}" in table
        or f"{r.batched.fixes_per_second:.0f}" in table
    ), table


def test_the_cli_prints_the_worker_alone_figures_as_json() -> None:
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "laas.cli",
            "bench",
            "--worker-only",
            "--participants",
            "5",
            "--duration",
            "10",
            "--json",
        ],
        capture_output=True,
        text=True,
        timeout=120,
        check=True,
    )
    report = json.loads(out.stdout)
    assert report["answered"] == report["fixes"] > 0
    assert report["engine_per_filterpy"] > 0
