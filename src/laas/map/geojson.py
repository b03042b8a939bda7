"""The GeoJSON lane-map reader: parsing and validation, into an :class:`HdMap`.

The format is described in ``maps/README.md``: a FeatureCollection whose features are
lanes (LineString centre lines, lon/lat) of road elements called segments. Every refusal
is a :class:`MapError` that names the feature and the problem.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType
from typing import Any, cast

import numpy as np
import numpy.typing as npt
import shapely
from shapely import LineString

from laas.errors import MapError
from laas.map.frame import sharpest_turn
from laas.map.geo import UtmProjection
from laas.map.hdmap import DIRECTIONS, LANE_TYPES, Direction, HdMap, Lane, LaneType, Segment

__all__ = [
    "MAX_TURN_DEG",
    "Reject",
    "cover_tolerance",
    "gap_stations",
    "gap_tolerance",
    "read_geojson",
    "read_geojson_file",
]

FloatArray = npt.NDArray[np.float64]

_KNOWN_PROPERTIES = frozenset({"segment", "lane", "type", "width", "direction", "successors"})

# The loader's tolerances for a road element. They are public so that the importers, which
# shape their road elements to pass these checks, use the loader's own figures.
MAX_TURN_DEG = 60.0
"""Sharpest turn, in degrees, allowed at one vertex of a segment's reference (lane 0)."""
_COVER_MIN = 5.0  # m: the least station tolerance of `cover_tolerance`
_COVER_SHARE = 0.1  # the station tolerance as a share of lane 0's length
_GAP_MIN = 0.75  # m: the least lateral tolerance of `gap_tolerance`
_GAP_SHARE = 0.35  # the lateral tolerance as a share of the expected spacing
_GAP_STEP = 10.0  # m: spacing of the stations at which the lane spacing is checked
_GAP_COUNT = 5  # the least number of such stations


def cover_tolerance(length: float) -> float:
    """How far (m) a lane's station range may lie beyond lane 0's ``0..length`` at either
    end: ``max(5 m, 10 % of length)``."""
    return max(_COVER_MIN, _COVER_SHARE * length)


def gap_tolerance(expected: float) -> float:
    """How far (m) the lateral distance of two neighbouring lane centres may be off
    `expected`, the mean of their widths ``(w_k + w_k+1) / 2``: ``max(35 %, 0.75 m)``."""
    return max(_GAP_SHARE * expected, _GAP_MIN)


def gap_stations(length: float) -> FloatArray:
    """The stations of lane 0 at which the lane spacing is checked: ``n = max(5, ceil(L /
    10 m))`` equally spaced inside ``0..L``, both ends left out."""
    count = max(_GAP_COUNT, math.ceil(length / _GAP_STEP))
    return np.linspace(0.0, length, count + 2)[1:-1]


def read_geojson_file(path: str | Path) -> HdMap:
    """Load and validate a GeoJSON map file; raises :class:`MapError` naming the problem."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise MapError(f"{p}: cannot read the map file: {exc.strerror or exc}") from exc
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise MapError(
            f"{p}: invalid JSON at line {exc.lineno} column {exc.colno}: {exc.msg}"
        ) from exc
    return read_geojson(data, source=str(p))


Reject = Callable[[str, str], None]
"""Called with (segment id, the loader's message) for each road element left out."""


def read_geojson(
    data: Mapping[str, Any], source: str = "<memory>", reject: Reject | None = None
) -> HdMap:
    """Build a map from a parsed GeoJSON FeatureCollection.

    Without `reject` any fault raises :class:`MapError`. With it (the importers'
    mode), a road element with a fault is left out and passed to `reject` with the
    message, and references to it are dropped from its neighbours' successors; the
    FeatureCollection itself must still be one, with at least one usable element.
    The map's UTM zone is then the one of the elements kept, so that those elements
    alone, with the references to left-out or unknown ones dropped, load without
    `reject` to the same map (what ``laas.map.importers.common`` relies on).
    """
    return _build(data, source, reject)


@dataclass
class _RawLane:
    feature: int
    segment: str
    index: int
    type: LaneType
    width: float
    direction: Direction
    lonlat: FloatArray
    successors: tuple[str, ...]
    extra: dict[str, Any]


def _where(source: str, i: int, segment: str | None = None, lane: int | None = None) -> str:
    where = f"{source}: feature {i}"
    if segment is not None and lane is not None:
        where += f" (segment {segment!r}, lane {lane})"
    elif segment is not None:
        where += f" (segment {segment!r})"
    return where


def _is_number(v: object) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool)


def _parse_feature(source: str, i: int, feature: object) -> _RawLane:
    if not isinstance(feature, Mapping):
        raise MapError(f"{_where(source, i)}: not a JSON object")
    if feature.get("type") != "Feature":
        raise MapError(
            f"{_where(source, i)}: 'type' must be 'Feature', got {feature.get('type')!r}"
        )
    props = feature.get("properties")
    if not isinstance(props, Mapping):
        raise MapError(f"{_where(source, i)}: 'properties' must be an object")

    seg = props.get("segment")
    if not isinstance(seg, str) or not seg:
        raise MapError(
            f"{_where(source, i)}: property 'segment' must be a non-empty string, got {seg!r}"
        )
    lane = props.get("lane")
    if not isinstance(lane, int) or isinstance(lane, bool):
        raise MapError(
            f"{_where(source, i, seg)}: property 'lane' must be an integer, got {lane!r}"
        )
    at = _where(source, i, seg, lane)
    if lane < 0:
        raise MapError(f"{at}: property 'lane' must be >= 0, got {lane}")

    ltype = props.get("type")
    if not isinstance(ltype, str):
        raise MapError(f"{at}: property 'type' must be a string, got {ltype!r}")
    if ltype not in LANE_TYPES:
        raise MapError(
            f"{at}: unknown lane type {ltype!r} (expected one of {', '.join(sorted(LANE_TYPES))})"
        )
    width = props.get("width")
    if not _is_number(width):
        raise MapError(f"{at}: property 'width' must be a number, got {width!r}")
    width_f = float(cast(float, width))
    if not math.isfinite(width_f) or width_f <= 0.0:
        raise MapError(f"{at}: property 'width' must be > 0 metres, got {width!r}")
    direction = props.get("direction")
    if not isinstance(direction, str):
        raise MapError(f"{at}: property 'direction' must be a string, got {direction!r}")
    if direction not in DIRECTIONS:
        raise MapError(
            f"{at}: unknown direction {direction!r} (expected one of "
            f"{', '.join(sorted(DIRECTIONS))})"
        )
    succ = props.get("successors", [])
    if succ is None:
        succ = []
    if not isinstance(succ, list) or not all(isinstance(s, str) and s for s in succ):
        raise MapError(f"{at}: property 'successors' must be a list of segment ids, got {succ!r}")

    geom = feature.get("geometry")
    if not isinstance(geom, Mapping):
        raise MapError(f"{at}: 'geometry' must be an object, got {geom!r}")
    if geom.get("type") != "LineString":
        raise MapError(f"{at}: geometry must be a LineString, got {geom.get('type')!r}")
    coords = geom.get("coordinates")
    if not isinstance(coords, list):
        raise MapError(f"{at}: LineString 'coordinates' must be a list")
    if len(coords) < 2:
        raise MapError(f"{at}: LineString needs at least 2 points, got {len(coords)}")
    lonlat = np.empty((len(coords), 2))
    for k, pos in enumerate(coords):
        if (
            not isinstance(pos, list)
            or not 2 <= len(pos) <= 3
            or not all(_is_number(c) for c in pos)
        ):
            raise MapError(f"{at}: coordinate {k} must be [lon, lat] numbers, got {pos!r}")
        lon, lat = float(pos[0]), float(pos[1])
        if not (
            math.isfinite(lon)
            and -180.0 <= lon <= 180.0
            and math.isfinite(lat)
            and -90.0 <= lat <= 90.0
        ):
            raise MapError(
                f"{at}: coordinate {k} [{pos[0]}, {pos[1]}] is out of lon/lat range "
                "(GeoJSON order is [longitude, latitude])"
            )
        lonlat[k] = lon, lat
    if not np.any(lonlat[1:] != lonlat[0]):
        raise MapError(f"{at}: LineString has fewer than 2 distinct points")
    line = LineString(lonlat)
    if line.is_closed:
        raise MapError(f"{at}: LineString is closed (first point equals last)")
    if not shapely.is_simple(line):
        raise MapError(f"{at}: LineString intersects itself")

    extra = {k: v for k, v in props.items() if k not in _KNOWN_PROPERTIES}
    return _RawLane(
        i,
        seg,
        lane,
        cast(LaneType, ltype),
        width_f,
        cast(Direction, direction),
        lonlat,
        tuple(succ),
        extra,
    )


def _build(data: Mapping[str, Any], source: str, reject: Reject | None = None) -> HdMap:
    if not isinstance(data, Mapping) or data.get("type") != "FeatureCollection":
        got = data.get("type") if isinstance(data, Mapping) else type(data).__name__
        raise MapError(f"{source}: not a GeoJSON FeatureCollection (type is {got!r})")
    features = data.get("features")
    if not isinstance(features, list):
        raise MapError(f"{source}: FeatureCollection has no 'features' list")
    if not features:
        raise MapError(f"{source}: FeatureCollection has no features")

    raws: list[_RawLane] = []
    bad: set[str] = set()  # segments left out (with `reject` only)

    def fault(seg_id: str, exc: MapError) -> None:
        if reject is None:
            raise exc
        if seg_id not in bad:
            bad.add(seg_id)
            reject(seg_id, str(exc))

    for i, f in enumerate(features):
        try:
            raws.append(_parse_feature(source, i, f))
        except MapError as exc:
            props = f.get("properties") if isinstance(f, Mapping) else None
            seg = props.get("segment") if isinstance(props, Mapping) else None
            fault(seg if isinstance(seg, str) and seg else f"feature {i}", exc)
    by_seg: dict[str, dict[int, _RawLane]] = {}
    for raw in raws:
        lanes = by_seg.setdefault(raw.segment, {})
        if raw.index in lanes:
            first = lanes[raw.index].feature
            fault(
                raw.segment,
                MapError(
                    f"{_where(source, raw.feature, raw.segment, raw.index)}: duplicate "
                    f"lane (segment {raw.segment!r}, lane {raw.index}) also in feature "
                    f"{first}"
                ),
            )
        lanes[raw.index] = raw
    for seg_id, lanes in by_seg.items():
        expected = list(range(len(lanes)))
        got = sorted(lanes)
        if got != expected:
            missing = sorted(set(expected) - set(got))
            wrong = min(i for i in got if i not in expected)
            fault(
                seg_id,
                MapError(
                    f"{_where(source, lanes[wrong].feature, seg_id, wrong)}: lane indices of "
                    f"segment {seg_id!r} must be contiguous from 0, got {got} "
                    f"(missing {missing})"
                ),
            )
    if reject is None:
        for raw in raws:
            for succ in raw.successors:
                if succ not in by_seg:
                    raise MapError(
                        f"{_where(source, raw.feature, raw.segment, raw.index)}: unknown "
                        f"successor segment {succ!r}"
                    )
    usable = [r for r in raws if r.segment not in bad]
    # The map's projection is the UTM zone of the mean of its points. In the lenient mode it
    # must be the zone of what is kept, so that a strict load of the kept elements alone (what
    # an importer writes) builds the very same elements: where rejected elements moved the
    # mean into another zone (a map on a zone boundary), the kept ones are built again in
    # their own zone. Each round can only leave out more, so this ends.
    while True:
        if not usable:
            raise MapError(f"{source}: no usable road element (every one was left out)")
        projection = _projection(usable)
        segments: list[Segment] = []
        for seg_id, lanes in by_seg.items():
            if seg_id in bad:
                continue
            ordered = [lanes[k] for k in range(len(lanes))]
            try:
                segments.append(_make_segment(source, projection, seg_id, ordered))
            except MapError as exc:
                fault(seg_id, exc)
        if reject is None:
            break
        kept_raws = [r for r in usable if r.segment not in bad]
        if len(kept_raws) == len(usable) or (kept_raws and _projection(kept_raws) == projection):
            break
        usable = kept_raws
    if reject is not None:
        kept = {seg.id for seg in segments}
        segments = [
            Segment(seg.id, seg.lanes, [s for s in seg.successors if s in kept])
            if any(s not in kept for s in seg.successors)
            else seg
            for seg in segments
        ]
    return HdMap(segments, projection, source)


def _projection(raws: Sequence[_RawLane]) -> UtmProjection:
    """The UTM zone of the mean longitude and latitude of the lanes' points."""
    all_ll = np.concatenate([r.lonlat for r in raws])
    return UtmProjection.for_location(float(np.mean(all_ll[:, 0])), float(np.mean(all_ll[:, 1])))


def _make_segment(
    source: str, proj: UtmProjection, seg_id: str, raws: Sequence[_RawLane]
) -> Segment:
    lanes = []
    for raw in raws:
        xy = proj.to_utm_array(raw.lonlat[:, 0], raw.lonlat[:, 1])
        lanes.append(
            Lane(
                seg_id,
                raw.index,
                raw.type,
                raw.width,
                raw.direction,
                LineString(xy),
                MappingProxyType(dict(raw.extra)),
            )
        )
    ref = raws[0]
    turn, vertex = sharpest_turn(np.asarray(lanes[0].centerline.coords))
    if turn > MAX_TURN_DEG:
        raise MapError(
            f"{_where(source, ref.feature, seg_id, 0)}: the reference centre line turns "
            f"by {turn:.0f} degrees at vertex {vertex} (at most {MAX_TURN_DEG:.0f} "
            "allowed; add vertices along the curve)"
        )
    successors = [s for raw in raws for s in raw.successors]
    try:
        seg = Segment(seg_id, lanes, successors)
    except MapError as exc:
        raise MapError(f"{_where(source, ref.feature, seg_id)}: {exc}") from exc
    _check_side_by_side(source, seg, raws)
    try:
        _ = seg.area
    except MapError as exc:
        raise MapError(f"{_where(source, ref.feature, seg_id)}: {exc}") from exc
    return seg


def _check_side_by_side(source: str, seg: Segment, raws: Sequence[_RawLane]) -> None:
    """Lanes must follow the reference direction, cover it, and lie next to each other in order."""
    length = seg.length
    tol_s = cover_tolerance(length)
    samples = seg._lane_samples
    for raw, sd in zip(raws, samples, strict=True):
        at = _where(source, raw.feature, seg.id, raw.index)
        if raw.index == 0:
            continue
        if sd[-1, 0] <= sd[0, 0]:
            raise MapError(
                f"{at}: the centre line runs against the segment's reference direction "
                "(coordinates must follow lane 0's order; use direction 'backward' for "
                "travel against it)"
            )
        lo, hi = float(sd[:, 0].min()), float(sd[:, 0].max())
        if lo > tol_s or lo < -tol_s or hi < length - tol_s or hi > length + tol_s:
            raise MapError(
                f"{at}: the lane covers stations {lo:.1f}..{hi:.1f} m of the segment, "
                f"but lane 0 runs 0..{length:.1f} m (tolerance {tol_s:.1f} m)"
            )
    for s in gap_stations(length):
        offsets = seg.lane_offsets(float(s))
        for k in range(len(raws) - 1):
            a, b = raws[k], raws[k + 1]
            at = _where(source, b.feature, seg.id, b.index)
            gap = float(offsets[k + 1] - offsets[k])
            expected = (a.width + b.width) / 2.0
            tol = gap_tolerance(expected)
            if gap <= 0.0:
                raise MapError(
                    f"{at}: at station {s:.1f} m the lane is not to the right of lane "
                    f"{a.index} (lateral offset {offsets[k + 1]:.2f} m vs "
                    f"{offsets[k]:.2f} m); lanes are numbered from the left"
                )
            if abs(gap - expected) > tol:
                raise MapError(
                    f"{at}: at station {s:.1f} m the lane is {gap:.2f} m from lane "
                    f"{a.index}, expected {expected:.2f} ± {tol:.2f} m from the widths; "
                    "the lanes do not run side by side"
                )
