"""What every map importer shares: lane drafts, the report of what was left out, and
writing a GeoJSON lane map that the loader accepts.

An importer turns its source (Lanelet2, OpenDRIVE, OpenStreetMap) into `LaneDraft`s,
lane centre lines in lon/lat grouped into road elements (segments) as
``maps/README.md`` describes them, and counts in an `ImportReport` what it could not
use, by kind. `finish` then loads the drafts with the GeoJSON reader in its lenient mode:
a road element the loader refuses is left out and reported with the loader's message
(and the source element it came from), never written.

An import never writes a map that the loader rejects, and it loads the map only once.
What the lenient load keeps loads strictly, as it stands, to the same map: the loader
judges each road element on its own lanes, in the map's UTM zone, which the lenient
mode takes from the kept elements alone; and `finish` drops every successor that names
an element left out (or none at all). So `finish` serialises the kept features once,
and `ImportResult.write` writes that text without loading it again
(``tests/test_map_tools.py`` loads what `finish` keeps strictly, for every kind of
fault). `write_map`, for any other FeatureCollection, loads it strictly first. Either
way the output file is replaced atomically: a failed write leaves the old file as it
was.
"""

from __future__ import annotations

import json
import os
import tempfile
from collections import Counter
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from laas.errors import MapError
from laas.map.geojson import read_geojson
from laas.map.hdmap import Direction, HdMap, LaneType

__all__ = [
    "ImportReport",
    "ImportResult",
    "LaneDraft",
    "feature_collection",
    "finish",
    "no_lanes",
    "write_map",
]

FloatArray = npt.NDArray[np.float64]

_EXAMPLES = 3  # source elements named per kind in the report
_DIGITS = 8  # decimal places of lon/lat written: 1e-8 degrees is about 1 mm


@dataclass
class LaneDraft:
    """One lane of one road element, as an importer found it.

    `lonlat` is the lane's centre line, (n, 2) longitude and latitude, ordered along the
    segment's reference direction; `index` counts from the left edge looking along it;
    `origin` names the source element ("lanelet 1234", "road 5 laneSection s=12.0",
    "way 123") for messages; `properties` are kept in the map (``Lane.properties``).
    """

    segment: str
    index: int
    type: LaneType
    width: float
    direction: Direction
    lonlat: FloatArray
    origin: str
    successors: tuple[str, ...] = ()
    properties: dict[str, Any] = field(default_factory=dict)

    def feature(self) -> dict[str, Any]:
        """The lane as a GeoJSON Feature of the lane-map format."""
        props: dict[str, Any] = {
            "segment": self.segment,
            "lane": self.index,
            "type": self.type,
            "width": round(float(self.width), 3),
            "direction": self.direction,
            "successors": list(self.successors),
            "origin": self.origin,
        }
        props.update(self.properties)
        coords = np.round(np.asarray(self.lonlat, dtype=np.float64), _DIGITS)
        return {
            "type": "Feature",
            "properties": props,
            "geometry": {"type": "LineString", "coordinates": coords.tolist()},
        }


class ImportReport:
    """What an import could not use, counted by kind, with the first source elements of
    each kind named; and what it produced."""

    def __init__(self, source: str) -> None:
        self.source = source
        self.skipped: Counter[str] = Counter()
        self.examples: dict[str, list[str]] = {}
        self.segments = 0
        self.lanes = 0

    def skip(self, kind: str, where: str, count: int = 1) -> None:
        """Count `count` things of `kind` left out, the first of them at `where`."""
        self.skipped[kind] += count
        names = self.examples.setdefault(kind, [])
        if len(names) < _EXAMPLES:
            names.append(where)

    def lines(self) -> list[str]:
        """The report as lines of text, most frequent kind first."""
        out = [f"{self.source}: {self.segments} road elements, {self.lanes} lanes written"]
        if not self.skipped:
            out.append("nothing left out")
        for kind, n in self.skipped.most_common():
            named = "; ".join(self.examples.get(kind, []))
            out.append(f"left out: {n} x {kind} (e.g. {named})")
        return out


@dataclass(frozen=True)
class ImportResult:
    """A finished import: the map as loaded, its GeoJSON, and the report.

    `text` is `geojson` serialised when it was loaded (by `finish`); `write` writes that
    text, so what is written is what was loaded, even if `geojson` is changed later. A
    result without `text` is loaded strictly before it is written."""

    hdmap: HdMap
    geojson: dict[str, Any]
    report: ImportReport
    text: str | None = field(default=None, repr=False)

    def write(self, out: str | Path) -> None:
        """Write the map to `out`, atomically (a temporary file renamed over `out`)."""
        if self.text is None:
            write_map(self.geojson, out)
        else:
            _replace(Path(out), self.text)


def feature_collection(lanes: Iterable[LaneDraft]) -> dict[str, Any]:
    """The drafts as a GeoJSON FeatureCollection of the lane-map format."""
    return {"type": "FeatureCollection", "features": [lane.feature() for lane in lanes]}


def finish(drafts: Iterable[LaneDraft], report: ImportReport) -> ImportResult:
    """Load the drafts leniently: every road element the loader refuses is left out and
    reported (kind "rejected by the loader", named by its source element), references to
    it are dropped from its neighbours. Raises `MapError` if nothing is left."""
    lanes = list(drafts)
    origins: dict[str, str] = {}
    for lane in lanes:
        origins.setdefault(lane.segment, lane.origin)
    rejected: dict[str, str] = {}

    def reject(segment: str, message: str) -> None:
        rejected[segment] = message
        where = origins.get(segment, segment)
        report.skip("road element rejected by the loader", f"{where}: {message}")

    data = feature_collection(lanes)
    hdmap = read_geojson(data, source=report.source, reject=reject)
    kept = hdmap.segments
    features = []
    for lane, feature in zip(lanes, data["features"], strict=True):
        if lane.segment not in kept:
            continue
        props = feature["properties"]
        props["successors"] = [s for s in props["successors"] if s in kept]
        features.append(feature)
    geojson = {"type": "FeatureCollection", "features": features}
    report.segments = len(kept)
    report.lanes = len(features)
    # What is kept loads strictly as it stands (see the module docstring), so the text is
    # written later without a second load; JSON gives every float back exactly.
    return ImportResult(hdmap, geojson, report, _serialise(geojson))


def _serialise(geojson: dict[str, Any]) -> str:
    return json.dumps(geojson, separators=(",", ":")) + "\n"


def write_map(geojson: dict[str, Any], out: str | Path) -> None:
    """Write a lane map to `out` after loading it strictly; the old file stays until the
    new one is complete."""
    path = Path(out)
    read_geojson(geojson, source=str(path))  # raises MapError: nothing written
    _replace(path, _serialise(geojson))


def _replace(path: Path, text: str) -> None:
    """Write `text` to a temporary file beside `path`, then rename it over `path`."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    except OSError as exc:
        raise MapError(f"{path}: cannot write the map: {exc.strerror or exc}") from exc
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            mask = os.umask(0)
            os.umask(mask)
            os.fchmod(fh.fileno(), 0o666 & ~mask)  # as open() would make it, not 0600
            fh.write(text)
        os.replace(tmp, path)
    except BaseException as exc:
        Path(tmp).unlink(missing_ok=True)
        if isinstance(exc, OSError):
            raise MapError(f"{path}: cannot write the map: {exc.strerror or exc}") from exc
        raise


def no_lanes(source: str, report: ImportReport | None = None) -> MapError:
    """The error of an import that found nothing to write, with what was left out."""
    left = "; ".join(report.lines()[1:]) if report is not None else ""
    return MapError(f"{source}: no lanes found that LaaS can use" + (f" ({left})" if left else ""))
