"""`laas bench --profile`: py-spy's raw profiles summed up per process, and a short bench
that records them. Functional only: never how fast anything was."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from laas.run.bench import BenchConfig, format_report, run_bench
from laas.run.profile import find_py_spy, format_profiles, profiles, read_profile, summarise

RAW = """\
<module> (/x/laas/cli.py);main (/x/laas/cli.py);work (/x/laas/engine/engine.py) 6
<module> (/x/laas/cli.py);main (/x/laas/cli.py) 2
Thread.run (/usr/lib/python3.11/threading.py);loop (/v/site-packages/paho/mqtt/client.py) 2
"""


def test_summarise_shares_own_and_total_time(tmp_path: Path) -> None:
    (tmp_path / "worker-7.txt").write_text(RAW)
    (tmp_path / "cores-3.txt").write_text(RAW)
    stacks = read_profile(tmp_path / "worker-7.txt")
    assert sum(stacks.values()) == 10
    p = summarise(stacks, "worker-7", top=3)
    assert [e.function for e in p.entries] == [  # ties by name
        "work (laas/engine/engine.py)",
        "loop (paho/mqtt/client.py)",
        "main (laas/cli.py)",
    ]
    assert p.entries[0].own == pytest.approx(0.6) and p.entries[0].total == pytest.approx(0.6)
    assert p.entries[2].own == pytest.approx(0.2) and p.entries[2].total == pytest.approx(0.8)
    found = profiles(tmp_path)
    assert [f.label for f in found] == ["cores-3", "worker-7"]
    text = format_profiles(found, tmp_path)
    assert "worker-7: 10 samples" in text and "loop (paho/mqtt/client.py)" in text
    assert [e.function for e in found[1].inclusive] == [
        "<module> (laas/cli.py)",
        "main (laas/cli.py)",
        "work (laas/engine/engine.py)",
    ]


def _can_profile() -> bool:
    try:
        exe = find_py_spy()
    except Exception:
        return False
    child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(3)"])
    try:
        import time

        time.sleep(0.5)
        done = subprocess.run(
            [exe, "dump", "--pid", str(child.pid)], capture_output=True, timeout=20
        )
        return done.returncode == 0
    finally:
        child.kill()
        child.wait()


@pytest.mark.slow
@pytest.mark.timeout(180)
def test_a_short_bench_profiles_each_process(tmp_path: Path) -> None:
    if shutil.which("py-spy") is None and not (Path(sys.executable).parent / "py-spy").exists():
        pytest.skip("py-spy is not installed")
    if not _can_profile():
        pytest.skip("py-spy may not trace processes here (ptrace)")
    folder = tmp_path / "profile"
    config = BenchConfig(
        participants=4,
        rate=2.0,
        duration=3.0,
        brokers="embedded",
        processes=2,
        privacy=False,
        profile=str(folder),
    )
    report = run_bench(config)
    assert report.answered == report.sent > 0
    kinds = {p.label.split("-")[0] for p in report.profiles}
    assert kinds == {"cores", "worker", "participants"}  # the brokers are not profiled
    assert len([p for p in report.profiles if p.label.startswith("participants")]) == 2
    assert all((folder / f"{p.label}.txt").exists() for p in report.profiles)
    assert any(p.samples > 0 and p.entries for p in report.profiles)
    assert "profiles (py-spy" in format_report(report)
