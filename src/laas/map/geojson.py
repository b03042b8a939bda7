"""The GeoJSON lane-map reader: parsing and validation, into an :class:`HdMap`.

The format is described in ``maps/README.md``: a FeatureCollection whose features are
lanes (LineString centre lines, lon/lat) of road elements called segments. Every refusal
is a :class:`MapError` that names the feature and the problem.
"""

from __future__ import annotations

import gc
import itertools
import json
import math
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType
from typing import Any, cast

import numpy as np
import numpy.typing as npt
import shapely

from laas.errors import MapError
from laas.map.frame import FrameStack
from laas.map.geo import UtmProjection
from laas.map.hdmap import (
    DIRECTIONS,
    LANE_TYPES,
    Direction,
    HdMap,
    Lane,
    LaneType,
    Segment,
    prepare,
)

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
    with _gc_paused():
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
    with _gc_paused():
        return _build(data, source, reject)


@contextmanager
def _gc_paused() -> Iterator[None]:
    """Python's cycle collector off while a map is built: a load makes tens of thousands
    of objects and no cycles, and the collections it would trigger walk every object the
    process holds (a quarter of Helsinki's load time). Back on afterwards if it was on."""
    was = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if was:
            gc.enable()


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
    # plain numbers are taken as they are, their range checked with the other lanes' (in
    # `_tail_faults`); anything else is checked here, one position at a time
    lonlat = _lonlat_fast(coords)
    if lonlat is None:
        lonlat = _lonlat_checked(at, coords)
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


def _lonlat_fast(coords: list[Any]) -> FloatArray | None:
    """The [lon, lat] of each position when every one is a list of 2 or 3 plain floats or
    ints (their range not yet checked); otherwise None."""
    plain = (float, int)
    if not all(
        type(pos) is list and 2 <= len(pos) <= 3 and all(type(c) in plain for c in pos)
        for pos in coords
    ):
        return None
    try:
        return np.array([pos[:2] for pos in coords], dtype=np.float64)
    except (OverflowError, ValueError):
        return None


def _lonlat_checked(at: str, coords: list[Any]) -> FloatArray:
    """The [lon, lat] of each position, checked one by one; MapError names the first fault."""
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
    return lonlat


def _tail_faults(
    source: str, raws: Sequence[_RawLane], features: Sequence[Any]
) -> list[MapError | None]:
    """The last checks of each lane's coordinates, for all lanes at once, in the order
    :func:`_parse_feature` would make them: lon/lat in range (where out of range, that
    function's check names the position), at least 2 distinct points, a LineString (in
    lon/lat, as written) that is not closed and does not cross itself."""
    if not raws:
        return []
    counts = np.array([len(raw.lonlat) for raw in raws])
    starts = np.cumsum(counts) - counts
    owner = np.repeat(np.arange(len(raws)), counts)
    ll = np.concatenate([raw.lonlat for raw in raws])
    bad = ~(np.isfinite(ll).all(axis=1) & (np.abs(ll[:, 0]) <= 180.0) & (np.abs(ll[:, 1]) <= 90.0))
    out_of_range = np.logical_or.reduceat(bad, starts)
    distinct = np.logical_or.reduceat(np.any(ll != ll[starts][owner], axis=1), starts)
    lines = shapely.linestrings(np.where(bad[:, None], 0.0, ll), indices=owner)
    closed, simple = shapely.is_closed(lines), shapely.is_simple(lines)
    out: list[MapError | None] = []
    for k, raw in enumerate(raws):
        if distinct[k] and not out_of_range[k] and simple[k] and not closed[k]:
            out.append(None)
            continue
        at = _where(source, raw.feature, raw.segment, raw.index)
        if out_of_range[k]:
            try:
                _lonlat_checked(at, features[raw.feature]["geometry"]["coordinates"])
            except MapError as exc:
                out.append(exc)
                continue
        if not distinct[k]:
            out.append(MapError(f"{at}: LineString has fewer than 2 distinct points"))
        elif closed[k] or not simple[k]:
            problem = "is closed (first point equals last)" if closed[k] else "intersects itself"
            out.append(MapError(f"{at}: LineString {problem}"))
        else:
            out.append(None)
    return out


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

    parsed: list[_RawLane | MapError] = []
    for i, f in enumerate(features):
        try:
            parsed.append(_parse_feature(source, i, f))
        except MapError as exc:
            parsed.append(exc)
    shapes = iter(_tail_faults(source, [p for p in parsed if isinstance(p, _RawLane)], features))
    for i, (f, p) in enumerate(zip(features, parsed, strict=True)):
        problem = p if isinstance(p, MapError) else next(shapes)
        if problem is None:
            raws.append(cast(_RawLane, p))
            continue
        props = f.get("properties") if isinstance(f, Mapping) else None
        seg = props.get("segment") if isinstance(props, Mapping) else None
        fault(seg if isinstance(seg, str) and seg else f"feature {i}", problem)
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
        groups = [
            (seg_id, [lanes[k] for k in range(len(lanes))])
            for seg_id, lanes in by_seg.items()
            if seg_id not in bad
        ]
        segments = _make_segments(source, projection, groups, fault)
        if reject is None:
            break
        kept_raws = [r for r in usable if r.segment not in bad]
        if len(kept_raws) == len(usable) or (kept_raws and _projection(kept_raws) == projection):
            break
        usable = kept_raws
    if reject is not None:
        kept = {seg.id for seg in segments}
        segments = [
            seg._relinked([s for s in seg.successors if s in kept])
            if any(s not in kept for s in seg.successors)
            else seg
            for seg in segments
        ]
    return HdMap(segments, projection, source)


def _projection(raws: Sequence[_RawLane]) -> UtmProjection:
    """The UTM zone of the mean longitude and latitude of the lanes' points."""
    all_ll = np.concatenate([r.lonlat for r in raws])
    return UtmProjection.for_location(float(np.mean(all_ll[:, 0])), float(np.mean(all_ll[:, 1])))


def _make_segments(
    source: str,
    proj: UtmProjection,
    groups: Sequence[tuple[str, Sequence[_RawLane]]],
    fault: Callable[[str, MapError], None],
) -> list[Segment]:
    """Build and check the road elements, each lane's raw lane list in index order.

    The work is done for all of them at once (one projection of every point, one frame
    stack, :func:`~laas.map.hdmap.prepare`); the checks are those of one element at a
    time, and each element's first fault is passed to `fault` in the elements' order.
    """
    raws = [raw for _, lanes in groups for raw in lanes]
    if not raws:
        return []
    lonlat = np.concatenate([raw.lonlat for raw in raws])
    xy = proj.to_utm_array(lonlat[:, 0], lonlat[:, 1])
    counts = np.array([len(raw.lonlat) for raw in raws])
    lines = shapely.linestrings(xy, indices=np.repeat(np.arange(len(raws)), counts))
    first = np.cumsum([len(lanes) for _, lanes in groups]) - [len(lanes) for _, lanes in groups]
    start = np.cumsum(counts) - counts
    refs = [xy[start[k] : start[k] + counts[k]] for k in first]  # each lane 0
    stack = FrameStack(refs)
    turns, vertices = stack.sharpest_turns()
    errors: dict[int, MapError] = {}
    built: list[tuple[int, Segment]] = []
    for g, (seg_id, lanes) in enumerate(groups):
        ref = lanes[0]
        turn = math.degrees(float(turns[g]))
        if turn > MAX_TURN_DEG:
            errors[g] = MapError(
                f"{_where(source, ref.feature, seg_id, 0)}: the reference centre line turns "
                f"by {turn:.0f} degrees at vertex {int(vertices[g])} (at most "
                f"{MAX_TURN_DEG:.0f} allowed; add vertices along the curve)"
            )
            continue
        made = [
            Lane(
                seg_id,
                raw.index,
                raw.type,
                raw.width,
                raw.direction,
                lines[first[g] + k],
                MappingProxyType(dict(raw.extra)),
            )
            for k, raw in enumerate(lanes)
        ]
        successors = [s for raw in lanes for s in raw.successors]
        try:
            built.append((g, Segment(seg_id, made, successors)))
        except MapError as exc:
            errors[g] = MapError(f"{_where(source, ref.feature, seg_id)}: {exc}")
    done: dict[int, Segment] = {}
    whole = stack if len(built) == len(groups) else None  # every element built: its frames
    for (g, seg), prep in zip(built, prepare([s for _, s in built], stack=whole), strict=True):
        seg_id, lanes = groups[g]
        try:
            _check_side_by_side(source, seg, lanes, prep.samples)
        except MapError as exc:
            errors[g] = exc
            continue
        try:
            seg.settle_area(prep.surface)
        except MapError as exc:
            errors[g] = MapError(f"{_where(source, lanes[0].feature, seg_id)}: {exc}")
            continue
        done[g] = seg
    for g, (seg_id, _) in enumerate(groups):
        if g in errors:
            fault(seg_id, errors[g])
    return [done[g] for g in range(len(groups)) if g in done]


def _check_side_by_side(
    source: str, seg: Segment, raws: Sequence[_RawLane], samples: Sequence[FloatArray]
) -> None:
    """Lanes must follow the reference direction, cover it, and lie next to each other in order.

    `samples`: (s, d) of each lane's densified centre line but lane 0's (:func:`prepare`).
    """
    if len(raws) < 2:
        return
    length = seg.length
    tol_s = cover_tolerance(length)
    for raw, sd in zip(raws[1:], samples, strict=True):
        s = sd[:, 0]
        lo, hi = float(s.min()), float(s.max())
        backward = s[-1] <= s[0]
        if backward or lo > tol_s or lo < -tol_s or hi < length - tol_s or hi > length + tol_s:
            at = _where(source, raw.feature, seg.id, raw.index)
            if backward:
                raise MapError(
                    f"{at}: the centre line runs against the segment's reference direction "
                    "(coordinates must follow lane 0's order; use direction 'backward' for "
                    "travel against it)"
                )
            raise MapError(
                f"{at}: the lane covers stations {lo:.1f}..{hi:.1f} m of the segment, "
                f"but lane 0 runs 0..{length:.1f} m (tolerance {tol_s:.1f} m)"
            )
    stations = gap_stations(length)
    table = seg.lane_offsets_many(stations).tolist()  # d of every lane at every station
    pairs = [
        (k, a, b, (a.width + b.width) / 2.0) for k, (a, b) in enumerate(itertools.pairwise(raws))
    ]
    for s, offsets in zip(stations.tolist(), table, strict=True):
        for k, a, b, expected in pairs:
            gap = offsets[k + 1] - offsets[k]
            tol = gap_tolerance(expected)
            if gap <= 0.0:
                raise MapError(
                    f"{_where(source, b.feature, seg.id, b.index)}: at station {s:.1f} m the "
                    f"lane is not to the right of lane {a.index} (lateral offset "
                    f"{offsets[k + 1]:.2f} m vs {offsets[k]:.2f} m); lanes are numbered from "
                    "the left"
                )
            if abs(gap - expected) > tol:
                raise MapError(
                    f"{_where(source, b.feature, seg.id, b.index)}: at station {s:.1f} m the "
                    f"lane is {gap:.2f} m from lane {a.index}, expected {expected:.2f} ± "
                    f"{tol:.2f} m from the widths; the lanes do not run side by side"
                )
