"""`laas map info` and `laas map show`, and what every importer relies on: the loader's
lenient mode (a faulty road element left out and named, never written) and the atomic,
strictly checked write."""

from __future__ import annotations

import copy
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from laas.cli import main
from laas.errors import MapError
from laas.map.bundled import bundled_map
from laas.map.geojson import read_geojson
from laas.map.hdmap import HdMap
from laas.map.importers.common import ImportReport, LaneDraft, finish, write_map
from laas.map.summary import summarise


def _hamburg() -> dict[str, Any]:
    data: dict[str, Any] = json.loads(bundled_map("messe-hamburg").read_text())
    return data


def test_info_counts_what_the_map_holds(capsys: pytest.CaptureFixture[str]) -> None:
    path = bundled_map("messe-hamburg")
    assert main(["map", "info", str(path), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    hdmap = HdMap.load(path)
    assert info["segments"] == len(hdmap.segments) == 5
    assert sum(info["lanes"].values()) == sum(len(s.lanes) for s in hdmap.segments.values())
    lengths = sum(lane.centerline.length for seg in hdmap.segments.values() for lane in seg.lanes)
    assert sum(info["length_m"].values()) == pytest.approx(lengths, abs=1.0)
    assert info["utm"] == "zone 32N (EPSG:32632)"
    w, s, e, n = info["bounds_lonlat"]
    assert 9.97 < w < e < 9.99 and 53.55 < s < n < 53.57
    assert info["load_s"] > 0


def test_show_writes_a_picture(tmp_path: Path) -> None:
    out = tmp_path / "map.png"
    assert (
        main(["map", "show", str(bundled_map("melbourne-corner")), "--out", str(out), "--ids"]) == 0
    )
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and out.stat().st_size > 10_000


def test_lenient_load_leaves_out_a_broken_element_and_its_references() -> None:
    data = _hamburg()
    for feature in data["features"]:
        if feature["properties"]["segment"] == "messe-4" and feature["properties"]["lane"] == 1:
            feature["properties"]["lane"] = 7  # a gap in messe-4's lane indices
    with pytest.raises(MapError, match="messe-4"):
        read_geojson(copy.deepcopy(data))
    rejected: list[tuple[str, str]] = []
    hdmap = read_geojson(data, reject=lambda seg, msg: rejected.append((seg, msg)))
    assert [seg for seg, _ in rejected] == ["messe-4"] and "contiguous" in rejected[0][1]
    assert "messe-4" not in hdmap.segments and len(hdmap.segments) == 4
    assert hdmap.segments["messe-3"].successors == ()  # its successor was messe-4
    assert hdmap.segments["messe-2"].successors == ("messe-3",)


def _drafts(hdmap: HdMap) -> list[LaneDraft]:
    proj = hdmap.projection
    out = []
    for seg in hdmap.segments.values():
        for lane in seg.lanes:
            xy = np.asarray(lane.centerline.coords)
            out.append(
                LaneDraft(
                    segment=seg.id,
                    index=lane.index,
                    type=lane.type,
                    width=lane.width,
                    direction=lane.direction,
                    lonlat=proj.to_wgs84_array(xy[:, 0], xy[:, 1]),
                    origin=f"element {seg.id}",
                    successors=seg.successors,
                )
            )
    return out


def test_finish_reports_a_refused_element_by_its_source_and_writes_only_the_rest(
    tmp_path: Path,
) -> None:
    hdmap = HdMap.load(bundled_map("messe-hamburg"))
    drafts = _drafts(hdmap)
    for draft in drafts:  # messe-2's lane 1 drawn 20 m east: not beside lane 0
        if draft.segment == "messe-2" and draft.index == 1:
            draft.lonlat = draft.lonlat + np.array([0.0003, 0.0])
    report = ImportReport("test")
    result = finish(drafts, report)
    assert set(result.hdmap.segments) == {"messe-0", "messe-1", "messe-3", "messe-4"}
    assert report.skipped == {"road element rejected by the loader": 1}
    (example,) = report.examples["road element rejected by the loader"]
    assert example.startswith("element messe-2: ") and "(segment 'messe-2', lane 1)" in example
    out = tmp_path / "map.geojson"
    result.write(out)
    again = HdMap.load(out)
    assert set(again.segments) == set(result.hdmap.segments)
    assert again.segments["messe-1"].successors == ()
    assert report.lanes == sum(len(s.lanes) for s in again.segments.values())
    summary = summarise(again)
    assert summary.segments == 4


def test_a_map_the_loader_refuses_is_never_written_and_the_old_file_stays(
    tmp_path: Path,
) -> None:
    out = tmp_path / "map.geojson"
    out.write_text("old")
    broken = _hamburg()
    broken["features"][0]["properties"]["width"] = -1
    with pytest.raises(MapError, match="width"):
        write_map(broken, out)
    assert out.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["map.geojson"]  # no temporary file left
    write_map(_hamburg(), out)
    assert len(HdMap.load(out).segments) == 5


def test_import_options_are_checked_before_any_work(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["map", "import", "osm", "x.osm", "--out", "y", "--origin", "1,2"]) == 2
    assert "--origin applies to lanelet2 and opendrive" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["map", "import", "osm", "x.osm", "--out", "y", "--bbox", "3,1,2,4"])
    assert "empty box" in capsys.readouterr().err


def test_users_roaming_a_map_are_written_and_replayed(tmp_path: Path) -> None:
    lane_map = str(bundled_map("melbourne-corner"))
    out = tmp_path / "run"
    args = ["--map", lane_map, "--users", "4", "--duration", "30", "--seed", "3"]
    assert main(["scenario", *args, "--out", str(out)]) == 0
    fixes = (out / "trace.jsonl").read_text().splitlines()
    truth = [json.loads(line) for line in (out / "truth.jsonl").read_text().splitlines()]
    assert len(fixes) == len(truth) > 30
    assert {row["segment"] for row in truth} <= set(HdMap.load(lane_map).segments)
    answers = tmp_path / "answers.jsonl"
    trace = str(out / "trace.jsonl")
    assert main(["replay", "--map", lane_map, trace, "--out", str(answers)]) == 0
    rows = [json.loads(line) for line in answers.read_text().splitlines()]
    assert len(rows) == len(fixes)
    right = sum(
        r.get("segment") == t["segment"] and r.get("lane") == t["lane"]
        for r, t in zip(rows, truth, strict=True)
    )
    assert right / len(rows) > 0.5  # 8 lanes: chance is well below


def test_unwritable_outputs_are_clear_errors(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(MapError, match="cannot write the map"):
        write_map(_hamburg(), tmp_path)  # a folder, not a file
    lane_map = str(bundled_map("messe-hamburg"))
    assert main(["map", "show", lane_map, "--out", str(tmp_path / "map.txt")]) == 2
    assert "cannot write the picture" in capsys.readouterr().err
