"""The OpenDRIVE importer (laas.map.importers.opendrive) on the esmini samples and on small
hand-made inputs, one per geometry type and lane case.

Every geometry check compares the imported lane centres, read back from the written
GeoJSON with ``read_geojson_file``, against an evaluation of the reference line made here
independently of the importer: closed forms for line and arc, numerical integration of
the heading (``scipy.integrate.quad``) for spirals, and root finding on the integrated
arc length for poly3 and paramPoly3. The parameters are copied from the .xodr files.
"""

from __future__ import annotations

import functools
import math
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pyproj
import pytest
import shapely
from scipy.integrate import quad  # type: ignore[import-untyped]
from scipy.optimize import brentq  # type: ignore[import-untyped]
from shapely import LineString

from laas.errors import MapError
from laas.map.geojson import read_geojson_file
from laas.map.hdmap import HdMap
from laas.map.importers import import_map
from laas.map.importers.opendrive import MIN_WIDTH, WIDTH_RANGE, import_opendrive

ROOT = Path(__file__).resolve().parent.parent
SAMPLES = ROOT / "maps" / "samples" / "opendrive"
DATA = Path(__file__).resolve().parent / "data" / "opendrive"
ORIGIN = (48.137, 11.575)  # (lat, lon) for the files without a geoReference
TOL = 0.1  # m: the bar for imported lane centres
BORDER = "lane of type 'border' (not a lane for road users; its width is kept)"
HEAD_ON = "road link where the reference lines meet head-on (no successor written)"

Ref = Callable[[float], tuple[float, float, float]]  # s -> x, y, heading


# ----------------------------------------------------------------------------------------------
# Independent reference lines
# ----------------------------------------------------------------------------------------------


def line_ref(x0: float, y0: float, h0: float) -> Ref:
    return lambda s: (x0 + s * math.cos(h0), y0 + s * math.sin(h0), h0)


def arc_ref(x0: float, y0: float, h0: float, k: float) -> Ref:
    def ref(s: float) -> tuple[float, float, float]:
        h = h0 + k * s
        return x0 + (math.sin(h) - math.sin(h0)) / k, y0 - (math.cos(h) - math.cos(h0)) / k, h

    return ref


def integrated_ref(x0: float, y0: float, theta: Callable[[float], float]) -> Ref:
    """Position by integrating the heading: x = x0 + int cos(theta), y = y0 + int sin(theta)."""

    @functools.cache
    def ref(s: float) -> tuple[float, float, float]:
        opts = {"limit": 200, "epsabs": 1e-11, "epsrel": 1e-11}
        dx = quad(lambda u: math.cos(theta(u)), 0.0, s, **opts)[0]
        dy = quad(lambda u: math.sin(theta(u)), 0.0, s, **opts)[0]
        return x0 + dx, y0 + dy, theta(s)

    return ref


def curvature_theta(
    h0: float, pieces: list[tuple[float, float, float]]
) -> Callable[[float], float]:
    """Heading of a chain of (length, k_start, k_end) pieces with linear curvature."""

    def theta(s: float) -> float:
        out, s0 = h0, 0.0
        for length, k0, k1 in pieces:
            ds = min(max(s - s0, 0.0), length)
            out += k0 * ds + 0.5 * (k1 - k0) / length * ds * ds
            s0 += length
        return out

    return theta


def curve_ref(
    x0: float,
    y0: float,
    h0: float,
    point: Callable[[float], tuple[float, float]],
    deriv: Callable[[float], tuple[float, float]],
    q_end: float,
    length: float,
) -> Ref:
    """A parametric curve (u(q), v(q)) in the frame of (x0, y0, h0), q found from s by its
    arc length (scaled to `length` at q_end), solved with brentq."""

    def arc(q: float) -> float:
        return float(quad(lambda r: math.hypot(*deriv(r)), 0.0, q, epsabs=1e-12)[0])

    scale = length / arc(q_end)

    def ref(s: float) -> tuple[float, float, float]:
        q = q_end if s >= length else brentq(lambda r: arc(r) * scale - s, 0.0, q_end, xtol=1e-12)
        u, v = point(q)
        du, dv = deriv(q)
        c, si = math.cos(h0), math.sin(h0)
        return x0 + c * u - si * v, y0 + si * u + c * v, h0 + math.atan2(dv, du)

    return ref


def poly3_ref(
    x0: float, y0: float, h0: float, a: float, b: float, c: float, d: float, length: float
) -> Ref:
    def arc(u: float) -> float:
        return float(quad(lambda r: math.hypot(1.0, b + 2 * c * r + 3 * d * r * r), 0, u)[0])

    u_end = brentq(lambda u: arc(u) - length, 0.0, length, xtol=1e-12)
    return curve_ref(
        x0,
        y0,
        h0,
        lambda u: (u, a + b * u + c * u * u + d * u**3),
        lambda u: (1.0, b + 2 * c * u + 3 * d * u * u),
        u_end,
        length,
    )


def param_poly3_ref(
    x0: float,
    y0: float,
    h0: float,
    cu: tuple[float, float, float, float],
    cv: tuple[float, float, float, float],
    p_end: float,
    length: float,
) -> Ref:
    def cubic(k: tuple[float, float, float, float], p: float) -> float:
        return k[0] + k[1] * p + k[2] * p * p + k[3] * p**3

    def slope(k: tuple[float, float, float, float], p: float) -> float:
        return k[1] + 2 * k[2] * p + 3 * k[3] * p * p

    return curve_ref(
        x0,
        y0,
        h0,
        lambda p: (cubic(cu, p), cubic(cv, p)),
        lambda p: (slope(cu, p), slope(cv, p)),
        p_end,
        length,
    )


def expected_centre(ref: Ref, t: Callable[[float], float], s0: float, s1: float) -> LineString:
    """The curve at lateral coordinate t(s) (left positive) from the reference, every 0.5 m."""
    pts = []
    for s in np.linspace(s0, s1, max(3, math.ceil((s1 - s0) / 0.5) + 1)):
        x, y, h = ref(float(s))
        ts = t(float(s))
        pts.append((x - ts * math.sin(h), y + ts * math.cos(h)))
    return LineString(pts)


# ----------------------------------------------------------------------------------------------
# Reading the imported map back
# ----------------------------------------------------------------------------------------------


def import_and_load(tmp_path: Path, name: str, origin: tuple[float, float] | None = ORIGIN):
    result = import_opendrive(DATA / name, origin=origin)
    out = tmp_path / (Path(name).stem + ".geojson")
    result.write(out)
    return result, read_geojson_file(out)  # strict


def local_lines(hdmap: HdMap, road: str, lane: int) -> list[LineString]:
    """The lane's centre lines (one per segment it is written in), in the local metres of
    ORIGIN's transverse Mercator, the importer's inertial frame."""
    to_local = pyproj.Transformer.from_crs(
        "EPSG:4326",
        f"+proj=tmerc +lat_0={ORIGIN[0]} +lon_0={ORIGIN[1]} +k=1 +x_0=0 +y_0=0 +ellps=WGS84",
        always_xy=True,
    )
    out = []
    for seg in hdmap.segments.values():
        for ln in seg.lanes:
            if ln.properties["opendrive_road"] == road and ln.properties["opendrive_lane"] == lane:
                xy = np.asarray(ln.centerline.coords)
                lonlat = hdmap.projection.to_wgs84_array(xy[:, 0], xy[:, 1])
                x, y = to_local.transform(lonlat[:, 0], lonlat[:, 1])
                out.append(LineString(np.column_stack([x, y])))
    return out


def deviation(hdmap: HdMap, road: str, lane: int, expected: LineString) -> float:
    """Hausdorff distance between the imported centre line and the expected one."""
    lines = local_lines(hdmap, road, lane)
    assert len(lines) == 1, f"road {road} lane {lane}: {len(lines)} centre lines"
    return float(shapely.hausdorff_distance(lines[0], expected, densify=0.05))


def constant(v: float) -> Callable[[float], float]:
    return lambda s: v


# ----------------------------------------------------------------------------------------------
# The esmini samples
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("name", "origin", "segments", "lanes", "skipped"),
    [
        ("fabriksgatan", (57.7, 11.97), 16, 32, {BORDER: 12, HEAD_ON: 12}),
        (
            "straight_500m",
            None,
            1,
            2,
            {
                BORDER: 2,
                "lane of type 'shoulder' (not a lane for road users; its width is kept)": 2,
            },
        ),
        ("curves", (57.7, 11.97), 3, 6, {BORDER: 4}),
    ],
)
def test_samples_import(tmp_path, name, origin, segments, lanes, skipped):
    t0 = time.perf_counter()
    result = import_opendrive(SAMPLES / f"{name}.xodr", origin=origin)
    # how long it took is printed (docs/maps/opendrive.md quotes it: 0.13 s for curves),
    # not bounded: a loaded machine's clock is no property of the importer
    print(f"\n{name}: imported in {time.perf_counter() - t0:.2f} s")
    assert result.report.segments == segments
    assert result.report.lanes == lanes
    assert dict(result.report.skipped) == skipped
    out = tmp_path / f"{name}.geojson"
    result.write(out)
    hdmap = read_geojson_file(out)
    assert len(hdmap.segments) == segments
    assert sum(len(s.lanes) for s in hdmap.segments.values()) == lanes


def test_fabriksgatan_junction():
    result = import_map("opendrive", SAMPLES / "fabriksgatan.xodr", origin=(57.7, 11.97))
    segs = result.hdmap.segments
    # road 2 ends at junction 4, whose connecting roads 14, 15, 16 start there
    assert set(segs["road2-s0"].successors) == {"road14-s0", "road15-s0", "road16-s0"}
    assert set(segs["road3-s0"].successors) == {"road11-s0", "road12-s0", "road13-s0"}
    assert segs["road14-s0"].successors == ("road0-s0",)
    assert segs["road8-s0"].successors == ("road1-s0",)
    # road 13 ends where road 2 ends: head-on, no successor
    assert segs["road13-s0"].successors == ()
    lanes = segs["road16-s0"].lanes
    assert [ln.properties["opendrive_lane"] for ln in lanes] == [-1, -3]
    assert [ln.type for ln in lanes] == ["driving", "sidewalk"]
    assert lanes[0].properties["opendrive_junction"] == "4"
    main = segs["road2-s0"].lanes
    assert [ln.properties["opendrive_lane"] for ln in main] == [3, 1, -1, -3]
    assert [ln.direction for ln in main] == ["both", "backward", "forward", "both"]
    # the border lane (0.3 m) between driving lane and sidewalk keeps its width
    assert segs["road2-s0"].lane_offsets(100.0)[1:] == pytest.approx([3.05, 6.55, 9.6], abs=0.02)


def test_curves_sample_spirals_are_exact():
    """The sample's geometry chain is written with the joint coordinates of the designer's
    tool; the importer's spiral and arc ends must reach the next joint."""
    result = import_opendrive(SAMPLES / "curves.xodr", origin=ORIGIN)
    hdmap = result.hdmap
    lines = local_lines(hdmap, "1", -1)
    assert len(lines) == 3  # 442 degrees of turning: cut in three
    joined = shapely.line_merge(shapely.union_all(lines))
    # joints of the file (x, y at s), lane -1 is 3.07 / 2 m right of the reference
    for s_x_y_h in [
        (324.39947525641378, 215.64971938253680, 168.45810429685304, 1.7457963267961383),
        (654.39947525641378, 374.12433096630843, 315.89227473333710, -0.87420367320634473),
        (904.39947525641378, 521.14515184258346, 120.97026385011969, -0.74920367320634473),
    ]:
        _, x, y, h = s_x_y_h
        p = shapely.Point(x + 1.535 * math.sin(h), y - 1.535 * math.cos(h))
        assert float(joined.distance(p)) < 0.01


def test_georeferenced_sample_follows_its_proj_string():
    """straight_500m's geoReference is +proj=utm +zone=32 (its lat_0/lon_0 are ignored by
    PROJ for utm); the importer follows PROJ, dropping the missing vertical grid."""
    result = import_opendrive(SAMPLES / "straight_500m.xodr")
    seg = result.hdmap.segments["road1-s0"]
    lon, lat = result.hdmap.projection.to_wgs84(*seg.reference.coords[0])
    utm32 = pyproj.Transformer.from_crs("EPSG:32632", "EPSG:4326", always_xy=True)
    exp_lon, exp_lat = utm32.transform(0.0, 3.07 / 2)  # utm forces x_0 = 500 km: x = 0 is far west
    assert lon == pytest.approx(exp_lon, abs=1e-6)
    assert lat == pytest.approx(exp_lat, abs=1e-6)
    end = result.hdmap.projection.to_wgs84(*seg.reference.coords[-1])
    assert end == pytest.approx(utm32.transform(500.0, 3.07 / 2), abs=1e-7)


# ----------------------------------------------------------------------------------------------
# Geometry types against the independent evaluation
# ----------------------------------------------------------------------------------------------

SPIRAL_PIECES = [(20.0, 0.0, 0.0), (60.0, -0.01, 0.02), (40.0, 0.02, 0.005), (30.0, 0.005, 0.005)]
POLY3_LENGTH = 60.29652807393801
PP3_NORMALIZED_LENGTH = 39.01142971304388

GEOMETRY_CASES = {
    "line": (
        "line.xodr",
        {"1": (line_ref(10.0, -5.0, 0.3), 80.0)},
        {1: 1.75, -1: -1.625, -2: -4.0, -3: -5.75},
    ),
    "arc": (
        "arc.xodr",
        {"1": (arc_ref(20.0, 30.0, 1.0, 0.02), 100.0)},
        {1: 1.5, -1: -1.5, -2: -4.25},
    ),
    "spiral": (
        "spiral.xodr",
        {"1": (integrated_ref(0.0, 0.0, curvature_theta(0.5, SPIRAL_PIECES)), 150.0)},
        {1: 1.75, -1: -1.75, -2: -4.5},
    ),
    "poly3": (
        "poly3.xodr",
        {"1": (poly3_ref(5.0, 5.0, -0.4, 0.0, 0.05, 0.002, -2e-5, POLY3_LENGTH), POLY3_LENGTH)},
        {1: 1.75, -1: -1.75},
    ),
    "paramPoly3": (
        "parampoly3.xodr",
        {
            "1": (
                param_poly3_ref(
                    0.0, 0.0, 0.1, (0.0, 1.0, -0.001, -1e-5), (0.0, 0.0, 0.008, -5e-5), 50.0, 50.0
                ),
                50.0,
            ),
            "2": (
                param_poly3_ref(
                    0.0,
                    100.0,
                    -0.2,
                    (0.0, 40.0, -2.0, 0.0),
                    (0.0, 0.0, 12.0, -4.0),
                    1.0,
                    PP3_NORMALIZED_LENGTH,
                ),
                PP3_NORMALIZED_LENGTH,
            ),
        },
        {1: 1.75, -1: -1.75},
    ),
}


@pytest.mark.parametrize("case", sorted(GEOMETRY_CASES))
def test_geometry_lane_centres(tmp_path, case):
    name, roads, offsets = GEOMETRY_CASES[case]
    _, hdmap = import_and_load(tmp_path, name)
    worst = 0.0
    for road, (ref, length) in roads.items():
        for lane, t in offsets.items():
            expected = expected_centre(ref, constant(t), 0.0, length)
            worst = max(worst, deviation(hdmap, road, lane, expected))
    assert worst < TOL
    assert worst < 0.01  # in fact: chord error at 1 m steps and 1e-8 degree rounding


def test_reference_check_is_sensitive(tmp_path):
    """The comparison sees an error: a reference with the wrong curvature is far off."""
    _, hdmap = import_and_load(tmp_path, "arc.xodr")
    wrong = expected_centre(arc_ref(20.0, 30.0, 1.0, 0.021), constant(-1.5), 0.0, 100.0)
    assert deviation(hdmap, "1", -1, wrong) > 1.0


def test_lane_offset_and_cubic_widths(tmp_path):
    _, hdmap = import_and_load(tmp_path, "lane_offset.xodr")

    def offset(s: float) -> float:
        if s < 60.0:
            return 0.5 + 0.01 * s - 2e-4 * s * s + 1e-6 * s**3
        return 0.596 - 0.005 * (s - 60.0)

    def w_m1(s: float) -> float:
        return 3.0 + 0.004 * s if s < 50.0 else 3.2 + 2e-4 * (s - 50) ** 2 - 2.5e-6 * (s - 50) ** 3

    def w_m2(s: float) -> float:
        return 1.8 + 0.002 * s

    def w_2(s: float) -> float:
        return 2.0 + 3e-5 * s * s - 2e-7 * s**3

    t = {
        2: lambda s: offset(s) + 3.25 + w_2(s) / 2,
        1: lambda s: offset(s) + 3.25 / 2,
        -1: lambda s: offset(s) - w_m1(s) / 2,
        -2: lambda s: offset(s) - w_m1(s) - w_m2(s) / 2,
    }
    ref = line_ref(0.0, 0.0, 0.2)
    for lane, tf in t.items():
        assert deviation(hdmap, "1", lane, expected_centre(ref, tf, 0.0, 100.0)) < TOL
    seg = hdmap.segments["road1-s0"]
    widths = {ln.properties["opendrive_lane"]: ln.width for ln in seg.lanes}
    for lane, wf in ((2, w_2), (1, constant(3.25)), (-1, w_m1), (-2, w_m2)):
        mean = quad(wf, 0.0, 100.0, points=[50.0])[0] / 100.0
        assert widths[lane] == pytest.approx(mean, abs=0.002)
    assert seg.lanes[2].properties["opendrive_width_range"] == pytest.approx([3.0, 3.388], abs=1e-3)


def test_border_lanes(tmp_path):
    """Border records are t of the outer border from the reference line (not moved by the
    laneOffset); a lane with width records beyond them is measured from that border; a
    lane with both uses its widths."""
    result, hdmap = import_and_load(tmp_path, "border.xodr")
    ref = line_ref(0.0, 0.0, 0.0)
    t = {
        2: lambda s: (3.8 + 0.001 * s + 5.8 + 0.001 * s) / 2,
        1: lambda s: (0.3 + 3.8 + 0.001 * s) / 2,
        -1: lambda s: (0.3 - 3.2 - 0.002 * s) / 2,
        -2: lambda s: -3.2 - 0.002 * s - 0.75,
        -3: lambda s: -3.2 - 0.002 * s - 1.5 - 1.0,
    }
    for lane, tf in t.items():
        assert deviation(hdmap, "1", lane, expected_centre(ref, tf, 0.0, 60.0)) < TOL
    widths = [ln.width for ln in hdmap.segments["road1-s0"].lanes]
    assert widths == pytest.approx([2.0, 3.53, 3.56, 1.5, 2.0], abs=1e-3)
    assert not result.report.skipped


# ----------------------------------------------------------------------------------------------
# Lanes left out, split sections
# ----------------------------------------------------------------------------------------------


def test_median_splits_the_section_side_by_side(tmp_path):
    result, hdmap = import_and_load(tmp_path, "median.xodr")
    assert sorted(hdmap.segments) == ["road1-s0a", "road1-s0b"]
    left, right = hdmap.segments["road1-s0a"], hdmap.segments["road1-s0b"]
    assert [ln.properties["opendrive_lane"] for ln in left.lanes] == [2]
    assert [ln.properties["opendrive_lane"] for ln in right.lanes] == [-1, -3]
    # the 0.3 m shoulder stays inside the right-hand element: its width is kept
    assert right.lane_offsets(40.0)[1] == pytest.approx(1.75 + 0.3 + 1.0, abs=0.01)
    assert left.lanes[0].direction == "backward"
    assert dict(result.report.skipped) == {
        "lane of type 'median' (not a lane for road users; its width is kept)": 1,
        "lane of type 'shoulder' (not a lane for road users; its width is kept)": 1,
    }
    ref = line_ref(0.0, 0.0, 0.0)
    for lane, t in ((2, 5.75), (-1, -1.75), (-3, -4.8)):
        assert deviation(hdmap, "1", lane, expected_centre(ref, constant(t), 0.0, 80.0)) < TOL


def test_taper_is_cut_into_pieces(tmp_path):
    result, hdmap = import_and_load(tmp_path, "taper.xodr")

    def width(s: float) -> float:
        return 3.5 * (3 * (s / 40) ** 2 - 2 * (s / 40) ** 3) if s < 40 else 3.5

    pieces = sorted(
        (seg for seg in hdmap.segments.values() if seg.id.startswith("road1-s0.")),
        key=lambda seg: int(seg.id.rsplit(".", 1)[1]),
    )
    assert len(pieces) >= 4
    covered = 0.0
    for k, seg in enumerate(pieces):
        nxt = pieces[k + 1].id if k + 1 < len(pieces) else "road1-s1"
        assert seg.successors == (nxt,)
        s0 = covered  # lane 0 (lane 1, 1.75 m left of a straight reference) runs along s
        covered += seg.length
        taper = [ln for ln in seg.lanes if ln.properties["opendrive_lane"] == -2]
        true = [width(s) for s in np.linspace(s0, covered, 201)]
        mean = float(np.mean(true))
        if mean < MIN_WIDTH:
            assert not taper
            continue
        assert taper, f"{seg.id}: the opening lane is missing"
        assert max(true) - min(true) <= WIDTH_RANGE + 1e-9
        assert taper[0].width == pytest.approx(mean, abs=0.02)
    assert covered == pytest.approx(40.0, abs=0.01)
    assert result.report.skipped == {
        f"lane narrower than {MIN_WIDTH} m over part of its laneSection (left out there)": 1
    }
    expected = expected_centre(line_ref(0.0, 0.0, 0.0), lambda s: -3.5 - width(s) / 2, 0.0, 100.0)
    lines = local_lines(hdmap, "1", -2)
    assert len(lines) == len(pieces)  # every piece but the first, and section 1
    for line in lines:
        assert max(expected.distance(shapely.Point(p)) for p in line.coords) < TOL


def test_bend_after_a_long_straight_is_cut_where_the_loader_needs_it(tmp_path):
    """300 m of straight, then 120 degrees of bend: as one element the loader's frame would
    put the straight's outer lanes beyond the bend's end; the importer cuts it (and only
    where needed) so that every piece loads, and the centre lines stay exact."""
    result, hdmap = import_and_load(tmp_path, "bend.xodr")
    assert not result.report.skipped
    assert len(hdmap.segments) == 2
    first, second = hdmap.segments["road1-s0.0"], hdmap.segments["road1-s0.1"]
    assert first.successors == ("road1-s0.1",)
    # lane 0 is lane 1, 1.75 m inside the left bend
    inner = 300.0 + (30.0 - 1.75) * math.radians(120.0)
    assert first.length + second.length == pytest.approx(inner, abs=0.05)

    def ref(s: float) -> tuple[float, float, float]:
        if s <= 300.0:
            return s, 0.0, 0.0
        return arc_ref(300.0, 0.0, 0.0, 1 / 30.0)(s - 300.0)

    end = 300.0 + 30.0 * math.radians(120.0)
    for lane, t in ((1, 1.75), (-1, -1.75), (-2, -4.5)):
        lines = local_lines(hdmap, "1", lane)
        assert len(lines) == 2
        expected = expected_centre(ref, constant(t), 0.0, end)
        merged = shapely.line_merge(shapely.union_all(lines))
        assert float(shapely.hausdorff_distance(merged, expected, densify=0.05)) < TOL


def test_zero_width_lane_is_counted(tmp_path):
    text = (DATA / "line.xodr").read_text()
    text = text.replace('<width sOffset="0.0" a="1.5"', '<width sOffset="0.0" a="0.0"')
    path = tmp_path / "zero.xodr"
    path.write_text(text)
    result = import_opendrive(path, origin=ORIGIN)
    assert result.report.skipped == {"lane of zero width": 1}
    seg = result.hdmap.segments["road1-s0"]
    assert [ln.properties["opendrive_lane"] for ln in seg.lanes] == [1, -1, -3]


# ----------------------------------------------------------------------------------------------
# Direction, links
# ----------------------------------------------------------------------------------------------


def test_traffic_rule_and_lane_direction(tmp_path):
    _, hdmap = import_and_load(tmp_path, "rule.xodr")
    lht = [ln.direction for ln in hdmap.segments["road1-s0"].lanes]
    rht = [ln.direction for ln in hdmap.segments["road2-s0"].lanes]
    # lanes 2 (direction="both"), 1, -1, -2 (direction="reversed"), -3 sidewalk
    assert lht == ["both", "forward", "backward", "forward", "both"]
    assert rht == ["both", "backward", "forward", "backward", "both"]


def test_road_links(tmp_path):
    result, hdmap = import_and_load(tmp_path, "links.xodr")
    succ = {sid: set(seg.successors) for sid, seg in hdmap.segments.items()}
    assert succ == {
        "road1-s0": {"road2-s0"},  # road 1 successor road 2, contactPoint start
        "road2-s0": {"road2-s1"},  # next laneSection
        "road2-s1": set(),  # road 2's end meets road 3's end: head-on
        "road3-s0": set(),
        "road4-s0": {"road5-s0"},  # only road 5's predecessor link (contactPoint end) says so
        "road5-s0": set(),  # its successor road 99 does not exist
    }
    assert result.report.skipped == {
        HEAD_ON: 2,
        "road link to a missing road or junction": 1,
    }
    assert result.report.examples[HEAD_ON] == [
        "road 2 end - road 3 end",
        "road 3 start - road 4 start",
    ]


# ----------------------------------------------------------------------------------------------
# Georeference
# ----------------------------------------------------------------------------------------------


def test_geo_reference_with_header_offset(tmp_path):
    _, hdmap = import_and_load(tmp_path, "geo.xodr", origin=None)
    proj = pyproj.Transformer.from_crs(
        "+proj=tmerc +lat_0=53.55 +lon_0=9.99 +k=1 +x_0=0 +y_0=0 +ellps=WGS84 +units=m",
        "EPSG:4326",
        always_xy=True,
    )
    seg = hdmap.segments["road1-s0"]
    for s in (0.0, 60.0):
        lx, ly = s, -1.75  # lane -1 of the line along x
        wx = 100.0 + math.cos(0.1) * lx - math.sin(0.1) * ly
        wy = -50.0 + math.sin(0.1) * lx + math.cos(0.1) * ly
        lon, lat = proj.transform(wx, wy)
        x, y = hdmap.projection.to_utm(lon, lat)
        assert shapely.Point(x, y).distance(seg.lanes[1].centerline) < 0.01
    # an origin overrides the geoReference (and its offset)
    moved = import_opendrive(DATA / "geo.xodr", origin=ORIGIN)
    lon, lat = moved.hdmap.projection.to_wgs84(
        *moved.hdmap.segments["road1-s0"].reference.coords[0]
    )
    assert (lat, lon) == pytest.approx((ORIGIN[0] + 1.75 / 111_200, ORIGIN[1]), abs=2e-6)


def test_missing_geo_reference_asks_for_origin():
    with pytest.raises(MapError, match=r"no <geoReference>.*--origin LAT,LON"):
        import_opendrive(SAMPLES / "fabriksgatan.xodr")


# ----------------------------------------------------------------------------------------------
# Bad input
# ----------------------------------------------------------------------------------------------


def test_broken_xml_names_the_line():
    with pytest.raises(MapError, match=r"broken\.xodr: not valid XML at line \d+"):
        import_opendrive(DATA / "broken.xodr", origin=ORIGIN)


def test_road_without_plan_view_is_named():
    with pytest.raises(MapError, match=r"road 7: has no <planView>"):
        import_opendrive(DATA / "no_planview.xodr", origin=ORIGIN)


@pytest.mark.parametrize(
    ("old", "new", "message"),
    [
        ('<arc curvature="0.02"/>', "<clothoid/>", r"road 1 geometry s=0\.0: unknown geometry"),
        ('curvature="0.02"', 'curvature="abc"', r"road 1 geometry s=0\.0: .*'abc' is not a finite"),
        ('junction="-1"', 'junction="-1" rule="XHT"', r"road 1: rule='XHT'"),
        ('<width sOffset="0.0" a="2.5"', '<width sOffset="x" a="2.5"', r"laneSection s=0 lane -2"),
    ],
)
def test_bad_road_content_is_named(tmp_path, old, new, message):
    text = (DATA / "arc.xodr").read_text()
    assert old in text
    path = tmp_path / "bad.xodr"
    path.write_text(text.replace(old, new))
    with pytest.raises(MapError, match=message):
        import_opendrive(path, origin=ORIGIN)


def test_missing_file_and_bad_step(tmp_path):
    with pytest.raises(MapError, match="cannot read"):
        import_opendrive(tmp_path / "nothing.xodr", origin=ORIGIN)
    with pytest.raises(ValueError, match="step"):
        import_opendrive(DATA / "line.xodr", origin=ORIGIN, step=0.0)


def test_lane_folding_inside_a_tight_curve_is_left_out(tmp_path):
    """On a 4 m radius right turn the parking lane's centre (4.25 m right of the reference)
    would fold back on itself: it is left out and counted, the rest is kept."""
    text = (DATA / "arc.xodr").read_text()
    text = text.replace('curvature="0.02"', 'curvature="-0.25"').replace(
        'length="100.0"', 'length="8.0"'
    )
    path = tmp_path / "tight.xodr"
    path.write_text(text)
    result = import_opendrive(path, origin=ORIGIN)
    assert result.report.skipped == {
        "lane inside a curve tighter than its distance from the reference": 1
    }
    seg = result.hdmap.segments["road1-s0"]
    assert [ln.properties["opendrive_lane"] for ln in seg.lanes] == [1, -1]
