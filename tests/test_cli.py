"""The command line end to end, on a map and a trace that are not Hamburg's."""

from __future__ import annotations

import json
import queue
import subprocess
import sys
import threading
from pathlib import Path
from typing import IO

import pytest

from laas.cli import main
from laas.sim.trace import format_measurement

from .helpers import T0, fix_on, small_map, small_map_data


@pytest.fixture()
def files(tmp_path: Path) -> tuple[Path, Path]:
    """The small Sydney map on disk, and a trace on it with three bad lines."""
    map_path = tmp_path / "sydney.geojson"
    map_path.write_text(json.dumps(small_map_data()))
    hdmap = small_map()
    seg = hdmap.segments["r-0"]
    lines = []
    for k in range(5):
        for user, lane in (("car", 2), ("bike", 3)):
            m = fix_on(hdmap, seg, 20.0 + 5 * k, lane, T0 + 1000 * k, bias=(0.5, 0.5))
            lines.append(format_measurement(user, m))
    lines.insert(3, '{"user": "car", "timestamp": "soon"}')
    lines.insert(5, "not json at all")
    lines.insert(7, lines[6])  # a duplicate fix
    trace_path = tmp_path / "trace.jsonl"
    trace_path.write_text("\n".join(lines) + "\n")
    return map_path, trace_path


def test_replay_answers_good_lines_and_names_bad_ones(
    files: tuple[Path, Path], capsys: pytest.CaptureFixture[str]
) -> None:
    map_path, trace_path = files
    assert main(["replay", "--map", str(map_path), str(trace_path)]) == 0
    out, err = capsys.readouterr()
    answers = [json.loads(line) for line in out.splitlines()]
    assert len(answers) == 10
    assert {a["user"] for a in answers} == {"car", "bike"}
    assert [a["lane"] for a in answers if a["user"] == "bike"][-1] == 3
    assert all(a["segment"] == "r-0" for a in answers)
    assert "trace.jsonl:4: timestamp: Input should be a valid integer" in err
    assert "trace.jsonl:6: not JSON" in err
    assert "is not newer than the user's last fix" in err
    assert "10 answered, 3 lines skipped" in err


def test_replay_takes_the_folder_laas_scenario_writes_and_names_one_without_a_trace(
    files: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    map_path, trace_path = files
    assert main(["replay", "--map", str(map_path), str(trace_path.parent)]) == 0
    assert "10 answered, 3 lines skipped" in capsys.readouterr().err
    empty = tmp_path / "empty"
    empty.mkdir()
    assert main(["replay", "--map", str(map_path), str(empty)]) == 2
    assert "is a folder without a trace.jsonl" in capsys.readouterr().err


def test_replay_reads_stdin_in_a_real_process(files: tuple[Path, Path]) -> None:
    map_path, trace_path = files
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "laas.cli",
            "replay",
            "--map",
            str(map_path),
            "-",
            "--mode",
            "paper",
        ],
        input=trace_path.read_text(),
        capture_output=True,
        text=True,
        timeout=120,
        check=True,
    )
    assert len(done.stdout.splitlines()) == 10


def test_replay_on_a_pipe_answers_each_epoch_before_the_next_is_written(
    files: tuple[Path, Path],
) -> None:
    """From a live pipe, a batch is answered once no further line is ready: the answers
    to one epoch come before the next epoch's lines are written, and they are the
    answers of the same trace read from a file."""
    map_path, trace_path = files
    lines = [
        line
        for line in trace_path.read_text().splitlines()
        if line.startswith("{") and '"soon"' not in line
    ]
    lines = list(dict.fromkeys(lines))  # the good lines once: two users, five epochs
    epochs = [lines[i : i + 2] for i in range(0, len(lines), 2)]
    offline = tmp = trace_path.with_name("good.jsonl")
    tmp.write_text("\n".join(lines) + "\n")
    command = [sys.executable, "-m", "laas.cli", "replay", "--map", str(map_path)]
    expected = subprocess.run(
        [*command, str(offline)], capture_output=True, text=True, timeout=120, check=True
    ).stdout.splitlines()
    child = subprocess.Popen(
        [*command, "-"], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
    )
    assert child.stdin is not None and child.stdout is not None
    answers: queue.Queue[str] = queue.Queue()

    def read(stream: IO[str]) -> None:
        for line in stream:
            answers.put(line)

    reader = threading.Thread(target=read, args=(child.stdout,), daemon=True)
    reader.start()
    got: list[str] = []
    try:
        for epoch in epochs:
            child.stdin.write("\n".join(epoch) + "\n")
            child.stdin.flush()
            for _ in epoch:  # the map loads before the first answer: allow for it
                got.append(answers.get(timeout=60).rstrip("\n"))
        child.stdin.close()
        assert child.wait(timeout=60) == 0
    finally:
        child.kill()
        child.wait()
    reader.join(5)
    assert answers.empty()
    assert got == expected and len(got) == 10


def test_a_broken_map_is_a_clear_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "bad.geojson"
    bad.write_text('{"type": "FeatureCollection", "features": [{"type": "Feature"}]}')
    trace = tmp_path / "t.jsonl"
    trace.write_text("")
    assert main(["replay", "--map", str(bad), str(trace)]) == 2
    assert "feature 0" in capsys.readouterr().err


def test_evaluate_json_reports_both_modes_on_the_same_seeds(
    capsys: pytest.CaptureFixture[str],
) -> None:
    assert main(["evaluate", "--runs", "1", "--json", "--workers", "1"]) == 0
    rows = json.loads(capsys.readouterr().out)
    assert len(rows) == 16
    assert {r["mode"] for r in rows} == {"paper", "default"}
    for r in rows:
        assert r["aed"] > 0.0
        assert r["aed"] < r["raw_aed"]
    # default mode's mean error is below paper mode's in every row (the same sigma and
    # filter, in the same order): what the common error is for (the README's evaluate table)
    paper = [r for r in rows if r["mode"] == "paper"]
    default = [r for r in rows if r["mode"] == "default"]
    for p, d in zip(paper, default, strict=True):
        assert (p["sigma_pos"], p["kalman"]) == (d["sigma_pos"], d["kalman"])
        assert d["aed"] < p["aed"], (p, d)


def test_scenario_and_plot_write_their_files(tmp_path: Path) -> None:
    assert main(["scenario", "--out", str(tmp_path), "--seed", "3"]) == 0
    lines = (tmp_path / "trace.jsonl").read_text().splitlines()
    truth = (tmp_path / "truth.jsonl").read_text().splitlines()
    assert len(lines) == len(truth) == 303
    assert main(["plot", "--out", str(tmp_path)]) == 0
    pngs = sorted(p.name for p in tmp_path.glob("*.png"))
    assert pngs == [
        "messe-hamburg-lanes-default.png",
        "messe-hamburg-lanes-paper.png",
        "messe-hamburg-traces.png",
    ]
    assert all((tmp_path / p).stat().st_size > 10_000 for p in pngs)


def test_bench_filter_reports_both_modes(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["bench-filter", "--max-users", "10", "--steps", "2", "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)
    assert [r["users"] for r in rows] == [1, 2, 3, 4, 6, 8, 10]
    assert all(r["default_ms"] > 0 for r in rows)
    assert all(r["paper_ms"] > 0 for r in rows[:-1])
    assert rows[-1]["paper_ms"] is None  # 4^10 hypotheses: past the enumeration limit


def test_regions_compares_one_worker_with_two(capsys: pytest.CaptureFixture[str]) -> None:
    """`laas regions` prints both comparisons: each worker alone, and with hand-over."""
    from laas.map.bundled import bundled_map

    argv = ["regions", "--map", str(bundled_map("messe-hamburg")), "--users", "6"]
    assert main([*argv, "--duration", "40"]) == 0
    out = capsys.readouterr().out
    assert "without hand-over" in out and "with hand-over" in out
    assert out.count("lane accuracy in the 10 fixes after each of") == 2
    assert main(["regions", "--workers", "1"]) == 2
    assert "--workers must be >= 2" in capsys.readouterr().err
