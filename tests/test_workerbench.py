"""`laas bench --worker-only`: the worker's own code, fed encrypted fixes in process."""

from __future__ import annotations

import json
import subprocess
import sys

from laas.run.workerbench import bench_worker, format_worker_report


def test_the_worker_alone_answers_every_fix_and_times_each_stage() -> None:
    lines: list[str] = []
    r = bench_worker(users=12, duration=20.0, seed=3, progress=lines.append)
    assert r.fixes > 150
    assert r.answered == r.fixes  # every sealed fix opened, answered and sealed back
    for us in (r.open_us, r.service_us, r.engine_us, r.seal_us, r.filterpy_us):
        assert 0.0 < us < 1e5
    assert abs(r.total_us - (r.open_us + r.service_us + r.engine_us + r.seal_us)) < 1e-9
    assert r.fixes_per_second == 1e6 / r.total_us
    assert lines and lines[0].startswith("sealing")
    table = format_worker_report(r)
    assert "engine / filterpy" in table and f"{r.answered} answered" in table


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
