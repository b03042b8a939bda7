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
from laas.map.geo import UtmProjection
from laas.map.geojson import read_geojson, read_geojson_file
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
    hdmap = read_geojson_file(path)
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
    hdmap = read_geojson_file(bundled_map("messe-hamburg"))
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
    again = read_geojson_file(out)
    assert set(again.segments) == set(result.hdmap.segments)
    assert again.segments["messe-1"].successors == ()
    assert report.lanes == sum(len(s.lanes) for s in again.segments.values())
    summary = summarise(again)
    assert summary.segments == 4


def _utm(draft: LaneDraft, proj: UtmProjection) -> np.ndarray:
    return proj.to_utm_array(draft.lonlat[:, 0], draft.lonlat[:, 1])


def _set_xy(draft: LaneDraft, proj: UtmProjection, xy: np.ndarray) -> None:
    draft.lonlat = proj.to_wgs84_array(xy[:, 0], xy[:, 1])


def _bent(xy: np.ndarray, across: float) -> np.ndarray:
    """A straight lane's start, end and, between them, a vertex `across` m to its left."""
    a, b = xy[0], xy[-1]
    t = (b - a) / np.hypot(*(b - a))
    return np.array([a, b, 0.5 * (a + b) + across * np.array([-t[1], t[0]])])


def _shift(draft: LaneDraft, proj: UtmProjection, along: float, left: float) -> np.ndarray:
    """A move of a straight lane by `along` m along it and `left` m to its left."""
    xy = _utm(draft, proj)
    t = (xy[-1] - xy[0]) / np.hypot(*(xy[-1] - xy[0]))
    return np.asarray(along * t + left * np.array([-t[1], t[0]]))


def _shortened(xy: np.ndarray) -> np.ndarray:
    """The first 30 % of a straight lane."""
    return np.array([xy[0], xy[0] + 0.3 * (xy[-1] - xy[0])])


# Every kind of fault for which the lenient load leaves a road element out, each done to
# messe-3 (straight, 110 m, four lanes) of its own copy of the Hamburg map: the lanes'
# checks (parsing), the element's lane indices, and its geometry.
FAULTS: dict[str, Any] = {
    "width": lambda lanes, p: setattr(lanes[1], "width", 0.0),
    "type": lambda lanes, p: setattr(lanes[1], "type", "tram"),
    "direction": lambda lanes, p: setattr(lanes[1], "direction", "sideways"),
    "lon/lat range": lambda lanes, p: setattr(
        lanes[1], "lonlat", lanes[1].lonlat + np.array([0.0, 90.0])
    ),
    "closed": lambda lanes, p: _set_xy(lanes[1], p, _bent(_utm(lanes[1], p), 5.0)[[0, 2, 1, 0]]),
    "self-crossing": lambda lanes, p: _set_xy(
        lanes[1], p, np.vstack([_bent(_utm(lanes[1], p), 5.0), _bent(_utm(lanes[1], p), -5.0)[2]])
    ),
    "duplicate lane": lambda lanes, p: setattr(lanes[2], "index", 1),
    "index gap": lambda lanes, p: setattr(lanes[3], "index", 7),
    "sharp turn": lambda lanes, p: _set_xy(lanes[0], p, _bent(_utm(lanes[0], p), 60.0)[[0, 2, 1]]),
    "against": lambda lanes, p: setattr(lanes[1], "lonlat", lanes[1].lonlat[::-1]),
    "short": lambda lanes, p: _set_xy(lanes[1], p, _shortened(_utm(lanes[1], p))),
    "along": lambda lanes, p: _set_xy(
        lanes[2], p, _utm(lanes[2], p) + _shift(lanes[2], p, 30.0, 0.0)
    ),
    "apart": lambda lanes, p: _set_xy(
        lanes[2], p, _utm(lanes[2], p) + _shift(lanes[2], p, 0.0, -5.0)
    ),
}


def _same_map(a: HdMap, b: HdMap) -> None:
    """The two maps hold the same road elements, lane for lane, in the same projection."""
    assert a.projection == b.projection
    assert list(a.segments) == list(b.segments)
    for seg_id, seg in a.segments.items():
        other = b.segments[seg_id]
        assert seg.successors == other.successors
        for lane, twin in zip(seg.lanes, other.lanes, strict=True):
            assert (lane.index, lane.type, lane.width, lane.direction) == (
                twin.index,
                twin.type,
                twin.width,
                twin.direction,
            )
            assert dict(lane.properties) == dict(twin.properties)
            assert np.array_equal(np.asarray(lane.centerline.coords), twin.centerline.coords)


def test_what_the_lenient_load_keeps_loads_strictly_as_it_stands(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The claim `finish` rests on (so an import loads its map once, and writes it without
    a second load): for every kind of fault, the elements the lenient load keeps, with the
    successors that name left-out elements dropped, load strictly to the same map."""
    hdmap = read_geojson_file(bundled_map("messe-hamburg"))
    proj = hdmap.projection
    drafts: list[LaneDraft] = []
    for name, fault in FAULTS.items():
        copy_of = _drafts(hdmap)
        for draft in copy_of:
            draft.segment = f"{draft.segment}/{name}"
            draft.successors = tuple(f"{s}/{name}" for s in draft.successors)
        fault([d for d in copy_of if d.segment.startswith("messe-3/")], proj)
        drafts += copy_of
    drafts[0].successors += ("nowhere",)  # an unknown successor is dropped too
    report = ImportReport("test")
    loads: list[str] = []

    def read_geojson_counted(*args: Any, **kwargs: Any) -> HdMap:
        loads.append(kwargs.get("source", ""))
        return read_geojson(*args, **kwargs)

    monkeypatch.setattr("laas.map.importers.common.read_geojson", read_geojson_counted)
    result = finish(drafts, report)
    out = tmp_path / "map.geojson"
    result.write(out)
    assert loads == ["test"]  # loaded once, leniently; written without a second load

    assert report.skipped["road element rejected by the loader"] == len(FAULTS)
    assert set(result.hdmap.segments) == {
        f"messe-{k}/{name}" for k in (0, 1, 2, 4) for name in FAULTS
    }
    assert all(
        result.hdmap.segments[f"messe-2/{name}"].successors == () for name in FAULTS
    )  # messe-3 is left out
    assert result.hdmap.segments[drafts[0].segment].successors == (drafts[0].successors[0],)
    strict = read_geojson(json.loads(result.text or ""), source="strict")
    _same_map(strict, result.hdmap)
    _same_map(read_geojson_file(out), result.hdmap)
    assert out.read_text() == result.text


def test_a_rejected_element_does_not_choose_the_projection() -> None:
    """A map whose rejected element drew the mean of its points into the next UTM zone:
    what is kept is built in its own zone, as a strict load of it alone would do."""
    west = UtmProjection.for_location(5.9, 50.0)  # zone 31; 6 E is the boundary
    east = UtmProjection.for_location(6.6, 50.0)  # zone 32
    x, y = west.to_utm(5.9, 50.0)
    keep = west.to_wgs84_array(np.array([x, x + 100.0]), np.array([y, y]))
    x, y = east.to_utm(6.6, 50.0)
    vee = np.array([[x, y], [x + 100.0, y], [x, y + 20.0], [x + 100.0, y + 40.0]])
    sharp = east.to_wgs84_array(vee[:, 0], vee[:, 1])  # turns by more than 60 degrees
    drafts = [
        LaneDraft("keep", 0, "driving", 3.0, "forward", keep, "keep", ("sharp",)),
        LaneDraft("sharp", 0, "driving", 3.0, "forward", sharp, "sharp"),
    ]
    mean = np.concatenate([keep, sharp]).mean(axis=0)
    assert UtmProjection.for_location(*mean) == east  # the rejected element's pull
    report = ImportReport("test")
    result = finish(drafts, report)
    assert report.skipped == {"road element rejected by the loader": 1}
    assert "turns by" in report.examples["road element rejected by the loader"][0]
    assert result.hdmap.projection == west
    assert result.hdmap.segments["keep"].successors == ()
    _same_map(read_geojson(json.loads(result.text or "")), result.hdmap)


def test_a_changed_import_result_is_not_what_is_written(tmp_path: Path) -> None:
    """`write` writes what was loaded; a FeatureCollection changed afterwards goes through
    `write_map`, which loads it strictly."""
    result = finish(_drafts(read_geojson_file(bundled_map("messe-hamburg"))), ImportReport("test"))
    result.geojson["features"][0]["properties"]["width"] = -1
    out = tmp_path / "map.geojson"
    result.write(out)
    assert len(read_geojson_file(out).segments) == 5
    with pytest.raises(MapError, match="width"):
        write_map(result.geojson, out)


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
    assert len(read_geojson_file(out).segments) == 5


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
    assert {row["segment"] for row in truth} <= set(read_geojson_file(lane_map).segments)
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
