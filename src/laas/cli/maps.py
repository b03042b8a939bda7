"""`laas map import`, `laas map info` and `laas map show`: real HD maps into lane maps
(`laas.map.importers`), and a lane map's figures and picture."""

from __future__ import annotations

import argparse
import json
import sys

from laas.cli.common import Subcommands
from laas.errors import ConfigError
from laas.map.geojson import read_geojson_file

__all__ = ["add_map"]


def _origin(text: str) -> tuple[float, float]:
    """``LAT,LON`` in degrees."""
    try:
        lat, lon = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected LAT,LON in degrees, got {text!r}") from None
    if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0):
        raise argparse.ArgumentTypeError(f"LAT,LON out of range: {text!r}")
    return lat, lon


def _bbox(text: str) -> tuple[float, float, float, float]:
    """``MIN_LON,MIN_LAT,MAX_LON,MAX_LAT`` in degrees."""
    try:
        w, s, e, n = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected MIN_LON,MIN_LAT,MAX_LON,MAX_LAT in degrees, got {text!r}"
        ) from None
    if not (w < e and s < n):
        raise argparse.ArgumentTypeError(f"an empty box: {text!r} (west < east, south < north)")
    return w, s, e, n


def _cmd_map_import(a: argparse.Namespace) -> int:
    import time

    from laas.map.importers import import_map

    options: dict[str, object] = {}
    if a.origin is not None:
        if a.format == "osm":
            raise ConfigError("--origin applies to lanelet2 and opendrive maps, not osm")
        options["origin"] = a.origin
    if a.bbox is not None:
        if a.format != "osm":
            raise ConfigError("--bbox applies to osm maps only")
        options["bbox"] = a.bbox
    start = time.perf_counter()
    print(f"laas map import: reading {a.input} as {a.format}", file=sys.stderr)
    result = import_map(a.format, a.input, **options)
    result.write(a.out)
    took = time.perf_counter() - start
    for line in result.report.lines():
        print(line)
    print(f"wrote {a.out} in {took:.1f} s")
    return 0


def _cmd_map_info(a: argparse.Namespace) -> int:
    from laas.map.summary import load_timed, summarise

    hdmap, took = load_timed(a.map)
    summary = summarise(hdmap, took)
    if a.json:
        print(json.dumps(summary.as_dict(), indent=2))
    else:
        print("\n".join(summary.lines()))
    return 0


def _cmd_map_show(a: argparse.Namespace) -> int:
    from laas.evaluation.plots import render_map

    print(f"laas map show: wrote {render_map(read_geojson_file(a.map), a.out, ids=a.ids)}")
    return 0


def add_map(sub: Subcommands) -> None:
    """`laas map import|info|show`."""
    p = sub.add_parser("map", help="import real HD maps, and look at lane maps")
    maps = p.add_subparsers(dest="map_command", required=True)
    q = maps.add_parser(
        "import", help="convert a Lanelet2, OpenDRIVE or OpenStreetMap file to a lane map"
    )
    q.add_argument("format", choices=["lanelet2", "opendrive", "osm"], help="source format")
    q.add_argument("input", help="the source file (.osm, .xodr, .osm.pbf)")
    q.add_argument("--out", required=True, help="the lane map to write (GeoJSON)")
    q.add_argument(
        "--origin",
        type=_origin,
        help="LAT,LON: OpenDRIVE without a geoReference: its local origin; Lanelet2: the "
        "projection origin (default: the mean of its nodes)",
    )
    q.add_argument(
        "--bbox", type=_bbox, help="MIN_LON,MIN_LAT,MAX_LON,MAX_LAT: cut an extract (osm)"
    )
    q.set_defaults(func=_cmd_map_import)
    q = maps.add_parser("info", help="segments, lanes by type, length, bounds, load time")
    q.add_argument("map", help="lane map (GeoJSON)")
    q.add_argument("--json", action="store_true", help="machine-readable output")
    q.set_defaults(func=_cmd_map_info)
    q = maps.add_parser("show", help="a picture of the lanes, coloured by type")
    q.add_argument("map", help="lane map (GeoJSON)")
    q.add_argument("--out", required=True, help="the PNG to write")
    q.add_argument("--ids", action="store_true", help="write the segment ids")
    q.set_defaults(func=_cmd_map_show)
