"""Scenario families: random roads, road users and GNSS errors from written-down distributions.

``build_case(family, seed)`` draws one scenario of a family: a road (its map, built in
memory), the road users' plans and the GNSS error model. The same (family, seed) gives the
same case, byte for byte, on every run and in every process: every draw comes from one
generator seeded by (crc32(family), seed), in a fixed order. U(a, b) is uniform, logU(a, b)
log-uniform, "p" a probability; where a family differs it is named, else the draw is common.

Road (one road, its cross-section constant along it, cut into road elements = segments):
  place       lon U(-177, 177), lat U(-56, 70) (any UTM zone, both hemispheres, no polar
              caps, no antimeridian); bearing of the first straight U(0, 360)
  geometry    a lead straight (urban U(30, 150) m, arterial U(250, 600), shared U(20, 100)),
              then n features (urban 2-4, arterial 1-3, shared 2-4), each followed by a
              straight U(20, 150) m:
                straight   U(30, 200) m more
                gentle     a curve of radius U(150, 600) m turning U(5, 25) degrees
                sharp      radius U(max(25, W/2 + 6), 80) m, U(30, 75) degrees
                corner     radius U(W/2 + 4, W/2 + 15) m, 90 degrees (a junction: its own
                           road element; curves keep every vertex turn far below 60 degrees)
                s-bend     two opposite curves of radius U(max(30, W/2 + 6), 120) m,
                           U(20, 50) degrees, up to 30 m apart
              weights (straight, gentle, sharp, corner, s-bend): urban (1, 1, 2, 3, 1),
              arterial (2, 4, 1, 0.5, 1), shared (1, 1, 2, 3, 1); turns go left or right at
              random, but the road's headings stay within a 170-degree span (so it never
              crosses itself; if neither way fits, a straight instead). W is the road's width.
  elements    cut 1 m outside both ends of each corner, and elsewhere every U(60, 250) m
              (shared U(40, 150)) moved to the nearest straight (no element ends in a
              curve; cuts closer than 10 m merge); each element's successor is the next
  traffic     two-way with p urban 0.7, arterial 0.8, shared 0.9; left-hand traffic with p 0.25
  lanes       per direction of a two-way road, driving lanes: urban 1-2, arterial 2-3,
              shared 1; a shared two-way street has one driving lane for both directions with
              p 0.5; a one-way road has 1-3 (shared 1-2). Each kerb side has a sidewalk
              (p urban 0.8, arterial 0.5, shared 0.95), a bicycle lane (0.45, 0.3, 0.5) and a
              parking lane (0.4, 0.2, 0.5), in the order driving | bicycle | parking |
              sidewalk or driving | parking | bicycle | sidewalk (p 0.5 each). Parking and
              bicycle lanes are dropped at random until the road has at most 8 lanes (urban
              8, arterial 8, shared 6); at least 2.
              Widths, m: driving U(2.75, 3.75) (one per road), bicycle U(1.5, 2.2), parking
              U(2.0, 2.6), sidewalk U(1.5, 4.0), rounded to 0.05. Directions: driving,
              parking and bicycle lanes that of their half (a one-way road's are forward; one
              of its bicycle lanes runs against it, contraflow, with p 0.2), sidewalks both.

Road users (their number logU(1, 40) rounded, shared: logU(2, 40)):
  kind        car, cyclist, pedestrian with weights urban (0.55, 0.25, 0.2), arterial (0.85,
              0.1, 0.05), shared (0.25, 0.4, 0.35); no sidewalk: pedestrians become cars. A
              car is parked (on a parking lane, speed 0 the whole time) with p 0.15 if the
              road has a parking lane.
  lanes       cars: a driving lane; cyclists: either way on a two-way road (or one with a
              contraflow bicycle lane), on a bicycle lane of their direction (p 0.8, if
              there is one) else the kerb-side driving lane; pedestrians: a sidewalk. The
              direction of travel is the lane's (both: either way); travellers against the
              reference direction drive the route backwards.
  motion      along their own lane at their own speed, slowed in curves to
              v <= sqrt(2.5 m/s^2 * radius) and changing speed by at most 1.5 m/s^2 toward
              and after them (scenario.UserPlan.along_lane)
  speed       cars urban U(5, 14), arterial U(10, 17), shared U(5, 10) m/s; cyclists U(3, 8);
              pedestrians U(0.8, 2.0)
  time        duration U(60, 120) s; a user enters late with p 0.4 (at U(0, D - 20) s) and
              leaves early with p 0.4 (at U(enter + 20, D) s); one who reaches the end of
              the road leaves there.
  stops       a moving user stops once (at a light, say) with p urban 0.35, arterial 0.2,
              shared 0.3, for U(5, 30) s if that fits in its time, braking and starting at
              peak 2.0 m/s^2 (cars), 1.5 (cyclists), 1.0 (pedestrians)
  lane changes  a Poisson process per user at rate U(1/60, 1/20) per s for cars (one change
              per 20-60 s) and U(1/120, 1/40) for cyclists, to an adjacent lane that allows
              their type and direction (cyclists: bicycle <-> driving); 40 % of them are
              overtakes (out, then back after U(4, 12) s). With p 0.15 another car changes
              lane at the same moment. Changes take U(2.5, 5) s (cars) or U(1.5, 3) s,
              never while braking or stopped. Pedestrians keep their sidewalk.

GNSS errors:
  common      magnitude U(0, 15) m in a direction U(0, 360); random-walk drift U(0, 0.2)
              m/sqrt(s)
  receiver    a constant bias of magnitude U(0, 1) m, any direction; noise_scale U(0.7, 1.4)
              times sigma_pos
  noise       sigma_pos U(0.5, 4) m per axis (a suite overrides it), sigma_vel U(0.1, 0.5)
              m/s; heading sigma_h = U(0.2, 2) deg + U(3, 20) deg m/s / max(v, 0.1), <= 180
              (course over ground from a Doppler velocity of sigma 0.05-0.35 m/s)
  outliers    share U(0, 0.03) of fixes: U(3, 8) m times Student-t (3 degrees of freedom)
  multipath   U(0, 1/30) jumps per s per receiver (urban U(0, 1/20), arterial U(0, 1/60)),
              U(2, 6) m max size, U(2, 6) s mean length
  dropouts    share U(0, 0.05) lost one by one; gaps at U(0, 1/60) per s of U(2, 8) s mean
  course      with p 1/2 a receiver reports the road's direction as its course (a
              smoothed or map-matched course, a phone's fused bearing: a lane change does not
              show in it), else that of its true motion; drawn from a stream of its own,
              seeded by (crc32(family), seed, 1)
  rates       per receiver, Hz: cars 1, 2, 5, 10 with p 0.5, 0.15, 0.15, 0.2; cyclists and
              pedestrians (phones) with p 0.75, 0.1, 0.1, 0.05; a random phase in the period
  accuracy    half of the receivers report one (GpsMeasurement.accuracy, the horizontal
              radius sqrt(2) sigma): logU(0.5, 2) times their own true radius (a steady
              misjudgement), times a log-normal jitter of 0.25 per fix, rounded to 0.1 m

The edge family draws as the others, with its own ranges: a lead straight U(300, 700) m,
  1-2 features with weights (4, 2, 0.5, 0, 0.5), elements every U(25, 60) m (a long road
  cut into many short elements, as importers cut real roads); two-way with p 0.3, 1-2
  driving lanes per direction or 2-3 one way; a bicycle lane on each kerb side always, no
  parking lane, a sidewalk with p 0.5; 3 or 4 users (logU(3, 4) rounded), cars and
  cyclists with weights (0.35, 0.65, 0), cars U(5, 14) m/s; stops p 0.2; multipath
  U(0, 1/30) per s. Its cases are the ones a common error can lock in: a small group
  whose every member could sit one lane over.

Map families: the same road users and errors on a real map (`MAP_FAMILIES`, imported
with `laas map import` and shipped in ``maps/``). ``build_case(name, seed)`` of a map
family draws, from one generator seeded by (crc32(name), seed):
  errors      which drawn family's error distributions apply, p 1/3 each (urban,
              arterial, shared), then the errors as above
  users       their number from that family's range as above; their kinds, lanes, paths,
              speeds and times from `laas.sim.roam.roam_scenario` (seeded by the next draw):
              users roam the map, following successors through junctions
  time        duration U(60, 120) s
  course      as above, from the stream seeded by (crc32(name), seed, 1)
The map is the map: nothing about it is drawn.
"""

from __future__ import annotations

import functools
import itertools
import math
import zlib
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict

from laas.errors import ConfigError
from laas.map.bundled import bundled_map
from laas.map.geo import UtmProjection
from laas.map.geojson import read_geojson, read_geojson_file
from laas.map.hdmap import Direction, HdMap, LaneType
from laas.map.mapgen import Curve, LaneSpec, Straight, road_features_utm, track
from laas.sim.scenario import ErrorModel, Scenario, UserPlan, distance_driven

__all__ = [
    "FAMILIES",
    "MAP_FAMILIES",
    "FamilyCase",
    "FamilySpec",
    "Road",
    "build_case",
    "get_family",
]

Range = tuple[float, float]
Kind = Literal["car", "bicycle", "pedestrian"]
Feature = Literal["straight", "gentle", "sharp", "corner", "s-bend"]

_FEATURES: tuple[Feature, ...] = ("straight", "gentle", "sharp", "corner", "s-bend")
_KINDS: tuple[Kind, ...] = ("car", "bicycle", "pedestrian")
_MARGIN = 3.0  # m kept between a user and either end of the road


class FamilySpec(BaseModel):
    """The distributions of one family (see the module docstring for the common ones)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    name: str
    description: str
    lead_straight: Range
    features: tuple[int, int]
    feature_weights: tuple[float, float, float, float, float]  # in _FEATURES order
    element_length: Range
    two_way: float
    driving_two_way: tuple[int, int]  # driving lanes per direction
    driving_one_way: tuple[int, int]
    single_lane: float  # a two-way road with one driving lane for both directions
    sidewalk: float
    bicycle: float
    parking: float
    max_lanes: int
    users: tuple[int, int]
    kinds: tuple[float, float, float]  # in _KINDS order
    car_speed: Range
    stop: float
    multipath_rate: Range


FAMILIES: dict[str, FamilySpec] = {
    "urban": FamilySpec(
        name="urban",
        description="city streets: 2-8 lanes of all types, corners and sharp curves",
        lead_straight=(30.0, 150.0),
        features=(2, 4),
        feature_weights=(1.0, 1.0, 2.0, 3.0, 1.0),
        element_length=(60.0, 250.0),
        two_way=0.7,
        driving_two_way=(1, 2),
        driving_one_way=(1, 3),
        single_lane=0.0,
        sidewalk=0.8,
        bicycle=0.45,
        parking=0.4,
        max_lanes=8,
        users=(1, 40),
        kinds=(0.55, 0.25, 0.2),
        car_speed=(5.0, 14.0),
        stop=0.35,
        multipath_rate=(0.0, 1.0 / 20.0),
    ),
    "arterial": FamilySpec(
        name="arterial",
        description="long straights and gentle curves, several driving lanes, fast cars",
        lead_straight=(250.0, 600.0),
        features=(1, 3),
        feature_weights=(2.0, 4.0, 1.0, 0.5, 1.0),
        element_length=(60.0, 250.0),
        two_way=0.8,
        driving_two_way=(2, 3),
        driving_one_way=(1, 3),
        single_lane=0.0,
        sidewalk=0.5,
        bicycle=0.3,
        parking=0.2,
        max_lanes=8,
        users=(1, 40),
        kinds=(0.85, 0.1, 0.05),
        car_speed=(10.0, 17.0),
        stop=0.2,
        multipath_rate=(0.0, 1.0 / 60.0),
    ),
    "shared": FamilySpec(
        name="shared",
        description="narrow two-way streets, many cyclists and pedestrians",
        lead_straight=(20.0, 100.0),
        features=(2, 4),
        feature_weights=(1.0, 1.0, 2.0, 3.0, 1.0),
        element_length=(40.0, 150.0),
        two_way=0.9,
        driving_two_way=(1, 1),
        driving_one_way=(1, 2),
        single_lane=0.5,
        sidewalk=0.95,
        bicycle=0.5,
        parking=0.5,
        max_lanes=6,
        users=(2, 40),
        kinds=(0.25, 0.4, 0.35),
        car_speed=(5.0, 10.0),
        stop=0.3,
        multipath_rate=(0.0, 1.0 / 30.0),
    ),
    "edge": FamilySpec(
        name="edge",
        description=(
            "a bicycle lane at the kerb with small groups of cyclists and cars on it; long "
            "straights cut into short elements"
        ),
        lead_straight=(300.0, 700.0),
        features=(1, 2),
        feature_weights=(4.0, 2.0, 0.5, 0.0, 0.5),
        element_length=(25.0, 60.0),
        two_way=0.3,
        driving_two_way=(1, 2),
        driving_one_way=(2, 3),
        single_lane=0.0,
        sidewalk=0.5,
        bicycle=1.0,
        parking=0.0,
        max_lanes=8,
        users=(3, 4),
        kinds=(0.35, 0.65, 0.0),
        car_speed=(5.0, 14.0),
        stop=0.2,
        multipath_rate=(0.0, 1.0 / 30.0),
    ),
}
"""The families by name."""


def get_family(name: str) -> FamilySpec:
    """A family by name; the error lists the names there are."""
    try:
        return FAMILIES[name]
    except KeyError:
        raise ConfigError(
            f"unknown scenario family {name!r}; choose one of {', '.join(sorted(FAMILIES))}"
        ) from None


@dataclass(frozen=True)
class Road:
    """The drawn road: where, its shape (local metres from the origin), lanes and elements."""

    origin: tuple[float, float]  # lon, lat
    bearing: float  # degrees, of the lead straight
    pieces: tuple[Straight | Curve, ...]
    reference: tuple[tuple[float, float], ...]  # the centre line, local metres (east, north)
    lanes: tuple[LaneSpec, ...]  # left to right, looking along the reference
    split_at: tuple[float, ...]  # stations of the element boundaries on the centre line
    two_way: bool
    keep_left: bool


@dataclass(frozen=True)
class FamilyCase:
    """One drawn scenario: the road (None on a map family's real map), its map (GeoJSON,
    empty for a map family, and loaded), and the scenario."""

    family: str
    seed: int
    road: Road | None
    geojson: dict[str, Any]
    hdmap: HdMap
    scenario: Scenario

    @property
    def lanes(self) -> int:
        """The most lanes side by side on the case's map."""
        return max(len(segment.lanes) for segment in self.hdmap.segments.values())


MAP_FAMILIES: dict[str, str] = {
    "karlsruhe": "karlsruhe",
    "fabriksgatan": "fabriksgatan",
    "helsinki": "helsinki",
}
"""Map families: name -> bundled map (``maps/<name>.geojson``), imported from real HD maps."""


@functools.lru_cache(maxsize=8)
def _real_map(name: str) -> HdMap:
    return read_geojson_file(bundled_map(MAP_FAMILIES[name]))


def _map_case(name: str, seed: int) -> FamilyCase:
    """A map family's case (see the module docstring)."""
    from laas.sim.roam import roam_scenario  # roam builds on scenario, as this module does

    rng = np.random.default_rng([zlib.crc32(name.encode()), seed])
    spec = get_family(tuple(FAMILIES)[_pick(rng, (1.0, 1.0, 1.0))])
    errors = _draw_errors(spec, rng)
    count = round(math.exp(_u(rng, (math.log(spec.users[0]), math.log(spec.users[1])))))
    duration = float(round(rng.uniform(60.0, 120.0)))
    hdmap = _real_map(name)
    scenario = roam_scenario(
        hdmap,
        int(rng.integers(0, 2**31)),
        users=count,
        duration=duration,
        name=f"{name}-{seed}",
        errors=errors,
    )
    scenario = scenario.model_copy(update={"users": _courses(scenario.users, name, seed)})
    return FamilyCase(name, seed, None, {}, hdmap, scenario)


def build_case(family: str, seed: int) -> FamilyCase:
    """Draw scenario `seed` of `family` (reproducible; see the module docstring)."""
    if seed < 0:
        raise ConfigError(f"seed must be >= 0, got {seed}")
    if family in MAP_FAMILIES:
        return _map_case(family, seed)
    spec = get_family(family)
    rng = np.random.default_rng([zlib.crc32(spec.name.encode()), seed])
    road = _draw_road(spec, rng)
    projection = UtmProjection.for_location(*road.origin)
    ox, oy = projection.to_utm(*road.origin)
    geojson = road_features_utm(
        "road",
        [(x + ox, y + oy) for x, y in road.reference],
        projection,
        road.lanes,
        road.split_at,
        reference_is="center",
    )
    name = f"{spec.name}-{seed}"
    hdmap = read_geojson(geojson, source=f"family:{name}")
    route = tuple(f"road-{k}" for k in range(len(road.split_at) + 1))
    duration = float(round(rng.uniform(60.0, 120.0)))
    errors = _draw_errors(spec, rng)
    length = sum(hdmap.segments[s].length for s in route)
    users = _courses(_draw_users(spec, rng, road, length, duration), spec.name, seed)
    scenario = Scenario(
        name=name,
        map=f"family:{name}",
        route=route,
        users=users,
        duration=duration,
        rate=1.0,
        errors=errors,
    )
    return FamilyCase(spec.name, seed, road, geojson, hdmap, scenario)


def _courses(users: tuple[UserPlan, ...], name: str, seed: int) -> tuple[UserPlan, ...]:
    """Each receiver's course from the road with p 1/2 (`UserPlan.course_from_road`),
    drawn from a stream of its own so that every other draw of the case stays as it was."""
    rng = np.random.default_rng([zlib.crc32(name.encode()), seed, 1])
    return tuple(u.model_copy(update={"course_from_road": bool(rng.random() < 0.5)}) for u in users)


# --- the road ---------------------------------------------------------------------------


def _u(rng: np.random.Generator, r: Range) -> float:
    return float(rng.uniform(r[0], r[1]))


def _pick(rng: np.random.Generator, weights: Sequence[float]) -> int:
    w = np.asarray(weights, dtype=float)
    return int(rng.choice(len(w), p=w / w.sum()))


def _width(rng: np.random.Generator, lane: LaneType) -> float:
    lo, hi = {
        "driving": (2.75, 3.75),
        "bicycle": (1.5, 2.2),
        "parking": (2.0, 2.6),
        "sidewalk": (1.5, 4.0),
    }[lane]
    return round(float(rng.uniform(lo, hi)) * 20.0) / 20.0


def _draw_lanes(spec: FamilySpec, rng: np.random.Generator) -> tuple[list[LaneSpec], bool, bool]:
    """The cross-section, left to right: (lanes, two-way, keep left)."""
    two_way = bool(rng.random() < spec.two_way)
    keep_left = bool(rng.random() < 0.25)
    driving_width = _width(rng, "driving")
    # each half from the centre line outwards: (type, direction)
    halves: list[list[tuple[LaneType, Direction]]] = []
    if two_way and rng.random() < spec.single_lane:
        centre: list[tuple[LaneType, Direction]] = [("driving", "both")]
        directions: tuple[Direction, Direction] = ("backward", "forward")
        halves = [[], []]
    elif two_way:
        n = int(rng.integers(spec.driving_two_way[0], spec.driving_two_way[1] + 1))
        centre = []
        directions = ("backward", "forward")
        halves = [[("driving", "backward")] * n, [("driving", "forward")] * n]
    else:
        n = int(rng.integers(spec.driving_one_way[0], spec.driving_one_way[1] + 1))
        centre = [("driving", "forward")] * n
        directions = ("forward", "forward")
        halves = [[], []]
    contraflow = int(rng.integers(0, 2)) if not two_way and rng.random() < 0.2 else -1
    for side in (0, 1):
        direction = directions[side]
        has_bicycle = rng.random() < spec.bicycle
        has_parking = rng.random() < spec.parking
        has_sidewalk = rng.random() < spec.sidewalk
        bike_first = rng.random() < 0.5
        bike: Direction = "backward" if side == contraflow else direction
        kerb: list[tuple[LaneType, Direction]] = []
        for lane in ("bicycle", "parking") if bike_first else ("parking", "bicycle"):
            if lane == "bicycle" and has_bicycle:
                kerb.append(("bicycle", bike))
            if lane == "parking" and has_parking:
                kerb.append(("parking", direction))
        if has_sidewalk:
            kerb.append(("sidewalk", "both"))
        halves[side] = halves[side] + kerb
    # too many lanes: drop parking, then bicycle lanes, at random sides
    while len(centre) + len(halves[0]) + len(halves[1]) > spec.max_lanes:
        for drop in ("parking", "bicycle", "sidewalk"):
            sides = [s for s in (0, 1) if any(t == drop for t, _ in halves[s])]
            if sides:
                side = sides[int(rng.integers(0, len(sides)))]
                k = next(i for i, (t, _) in enumerate(halves[side]) if t == drop)
                del halves[side][k]
                break
    if len(centre) + len(halves[0]) + len(halves[1]) < 2:
        halves[1].append(("sidewalk", "both"))
    # right-hand traffic: the backward half on the left; left-hand traffic mirrors the road
    left, right = halves
    if two_way and keep_left:
        left, right = right, left
    order = [*reversed(left), *centre, *right]
    lanes = [LaneSpec(t, driving_width if t == "driving" else _width(rng, t), d) for t, d in order]
    return lanes, two_way, keep_left


def _draw_road(spec: FamilySpec, rng: np.random.Generator) -> Road:
    lon = _u(rng, (-177.0, 177.0))
    lat = _u(rng, (-56.0, 70.0))
    bearing = _u(rng, (0.0, 360.0))
    lanes, two_way, keep_left = _draw_lanes(spec, rng)
    half = sum(lane.width for lane in lanes) / 2.0  # W / 2
    lead = Straight(_u(rng, spec.lead_straight))
    pieces: list[Straight | Curve] = [lead]
    heading, lo, hi = 0.0, 0.0, 0.0
    corners: list[tuple[int, int]] = []  # (first, last) piece of each corner
    count = int(rng.integers(spec.features[0], spec.features[1] + 1))
    for _ in range(count):
        feature = _FEATURES[_pick(rng, spec.feature_weights)]
        side = 1.0 if rng.random() < 0.5 else -1.0
        new: list[Straight | Curve] = []
        if feature == "straight":
            new = [Straight(_u(rng, (30.0, 200.0)))]
        elif feature == "gentle":
            new = [Curve(_u(rng, (150.0, 600.0)), side * _u(rng, (5.0, 25.0)))]
        elif feature == "sharp":
            new = [Curve(_u(rng, (max(25.0, half + 6.0), 80.0)), side * _u(rng, (30.0, 75.0)))]
        elif feature == "corner":
            new = [Curve(_u(rng, (half + 4.0, half + 15.0)), side * 90.0)]
        else:
            radius = _u(rng, (max(30.0, half + 6.0), 120.0))
            angle = side * _u(rng, (20.0, 50.0))
            gap = _u(rng, (0.0, 30.0))
            new = [
                Curve(radius, angle),
                *([Straight(gap)] if gap > 1.0 else []),
                Curve(radius, -angle),
            ]
        # keep every heading of the road within a 170-degree span: try the other way round
        turns = [p.angle for p in new if isinstance(p, Curve)]
        if not _fits(heading, lo, hi, turns):
            new = [Curve(p.radius, -p.angle) if isinstance(p, Curve) else p for p in new]
            turns = [-a for a in turns]
        if not _fits(heading, lo, hi, turns):
            new = [Straight(_u(rng, (30.0, 200.0)))]
            turns = []
        for a in turns:
            heading += a
            lo, hi = min(lo, heading), max(hi, heading)
        for piece in [*new, Straight(_u(rng, (20.0, 150.0)))]:
            last = pieces[-1]
            if isinstance(piece, Straight) and isinstance(last, Straight):  # no collinear
                pieces[-1] = Straight(last.length + piece.length)  # vertices (GEOS offsets)
            else:
                pieces.append(piece)
            if feature == "corner" and turns and isinstance(piece, Curve):
                corners.append((len(pieces) - 1, len(pieces) - 1))
    # the reference, piece by piece, so each piece's ends are known vertices
    reference: list[tuple[float, float]] = [(0.0, 0.0)]
    ends: list[float] = []  # station of each piece's end
    station, bearing_k = 0.0, bearing
    for piece in pieces:
        pts = track(reference[-1], bearing_k, [piece])[1:]
        for p in pts:
            station += math.dist(p, reference[-1])
            reference.append(p)
        ends.append(station)
        if isinstance(piece, Curve):
            bearing_k = (bearing_k + piece.angle) % 360.0
    junctions = [(ends[first - 1], ends[last]) for first, last in corners]
    vertices = np.concatenate(
        [[0.0], np.cumsum(np.hypot(*np.diff(np.asarray(reference), axis=0).T))]
    )
    return Road(
        origin=(lon, lat),
        bearing=bearing,
        pieces=tuple(pieces),
        reference=tuple(reference),
        lanes=tuple(lanes),
        split_at=tuple(_cuts(rng, spec, vertices, junctions)),
        two_way=two_way,
        keep_left=keep_left,
    )


def _fits(heading: float, lo: float, hi: float, turns: Sequence[float]) -> bool:
    for a in turns:
        heading += a
        lo, hi = min(lo, heading), max(hi, heading)
    return hi - lo < 170.0


def _cuts(
    rng: np.random.Generator,
    spec: FamilySpec,
    vertices: np.ndarray,
    junctions: Sequence[Range],
) -> list[float]:
    """Element boundaries: 1 m outside each end of each corner, and every U(element_length)
    between, each moved to the nearest straight (there the lanes' offset curves of the two
    elements meet exactly)."""
    length = float(vertices[-1])
    fixed = [0.0, *[s + d for j in junctions for s, d in zip(j, (-1.0, 1.0), strict=True)]]
    fixed.append(length)
    cuts: list[float] = []
    short, long = spec.element_length
    for a, b in itertools.pairwise(fixed):
        at = a
        while b - at > long:
            at += min(_u(rng, (short, long)), b - at - short)
            cuts.append(at)
        if b < length:
            cuts.append(b)
    out: list[float] = []
    for c in sorted(_on_a_straight(c, vertices) for c in cuts):  # no sliver elements
        if c - (out[-1] if out else 0.0) >= 10.0 and length - c >= 10.0:
            out.append(c)
    return out


def _on_a_straight(c: float, vertices: np.ndarray) -> float:
    """The station nearest c on a straight piece (>= 2 m long), >= 1 m from its ends: no
    element ends in a curve (GEOS's offsets of such ends can split or leave a gap)."""
    lo, hi = vertices[:-1] + 1.0, vertices[1:] - 1.0
    straight = np.diff(vertices) >= 2.0
    near = np.clip(c, lo[straight], hi[straight])
    return float(near[np.argmin(np.abs(near - c))])


# --- the errors -------------------------------------------------------------------------


def _draw_errors(spec: FamilySpec, rng: np.random.Generator) -> ErrorModel:
    size, angle = _u(rng, (0.0, 15.0)), math.radians(_u(rng, (0.0, 360.0)))
    return ErrorModel(
        bias_east=size * math.sin(angle),
        bias_north=size * math.cos(angle),
        bias_drift=_u(rng, (0.0, 0.2)),
        sigma_pos=_u(rng, (0.5, 4.0)),
        sigma_vel=_u(rng, (0.1, 0.5)),
        sigma_heading=_u(rng, (0.2, 2.0)),
        heading_per_speed=_u(rng, (3.0, 20.0)),
        outlier_rate=_u(rng, (0.0, 0.03)),
        outlier_scale=_u(rng, (3.0, 8.0)),
        outlier_dof=3.0,
        multipath_rate=_u(rng, spec.multipath_rate),
        multipath_offset=_u(rng, (2.0, 6.0)),
        multipath_duration=_u(rng, (2.0, 6.0)),
        dropout_rate=_u(rng, (0.0, 0.05)),
        gap_rate=_u(rng, (0.0, 1.0 / 60.0)),
        gap_duration=_u(rng, (2.0, 8.0)),
        accuracy_jitter=0.25,
    )


# --- the road users ---------------------------------------------------------------------


def _allows(direction: Direction, reverse: bool) -> bool:
    return direction == "both" or direction == ("backward" if reverse else "forward")


@dataclass
class _Draft:
    """A user's plan while it is drawn."""

    user: str
    kind: Kind
    speed: float
    reverse: bool
    lanes: list[tuple[float, int]]
    change_time: float
    enter: float
    end: float
    stops: list[tuple[float, float]]
    brake: float

    def busy(self, t: float, span: float) -> bool:
        """Whether [t, t + span] meets a stop (with its ramps) or another lane change."""
        ramp = math.pi * self.speed / (2.0 * self.brake)
        for at, held in self.stops:
            if t < at + held + ramp and t + span > at - ramp:
                return True
        return any(abs(t - since) < span + self.change_time + 1.0 for since, _ in self.lanes[1:])

    def lane_at(self, t: float) -> int:
        lane = self.lanes[0][1]
        for since, k in self.lanes:
            if since <= t:
                lane = k
        return lane


def _neighbours(road: Road, draft: _Draft, lane: int) -> list[int]:
    """Adjacent lanes this user may change to."""
    out = []
    for k in (lane - 1, lane + 1):
        if not 0 <= k < len(road.lanes):
            continue
        spec = road.lanes[k]
        if not _allows(spec.direction, draft.reverse):
            continue
        here = road.lanes[lane].type
        pair = {here, spec.type}
        if (draft.kind == "car" and spec.type == "driving") or (
            draft.kind == "bicycle" and pair == {"bicycle", "driving"}
        ):
            out.append(k)
    return out


def _change(rng: np.random.Generator, road: Road, draft: _Draft, t: float, overtake: bool) -> bool:
    """Add a lane change (or an overtake: out and back) at t if it fits; whether it did."""
    back = _u(rng, (4.0, 12.0)) if overtake else 0.0
    span = draft.change_time + back + (draft.change_time if overtake else 0.0)
    if t < draft.enter + 1.0 or t + span > draft.end - 1.0 or draft.busy(t, span):
        return False
    here = draft.lane_at(t)
    options = _neighbours(road, draft, here)
    if not options:
        return False
    target = options[int(rng.integers(0, len(options)))]
    draft.lanes.append((round(t, 3), target))
    if overtake:
        draft.lanes.append((round(t + draft.change_time + back, 3), here))
    draft.lanes.sort()
    return True


def _start_lane(
    rng: np.random.Generator, road: Road, kind: Kind, parked: bool
) -> tuple[int, bool] | None:
    """(lane, reverse) of a new user of this kind, or None if the road has no lane for it."""
    lanes = road.lanes
    if kind == "car":
        if parked:
            options = [k for k, lane in enumerate(lanes) if lane.type == "parking"]
        else:
            options = [k for k, lane in enumerate(lanes) if lane.type == "driving"]
    elif kind == "pedestrian":
        options = [k for k, lane in enumerate(lanes) if lane.type == "sidewalk"]
    else:
        contraflow = any(lane.type == "bicycle" and lane.direction == "backward" for lane in lanes)
        reverse = bool((road.two_way or contraflow) and rng.random() < 0.5)
        bikes = [
            k
            for k, lane in enumerate(lanes)
            if lane.type == "bicycle" and _allows(lane.direction, reverse)
        ]
        driving = [
            k
            for k, lane in enumerate(lanes)
            if lane.type == "driving" and _allows(lane.direction, reverse)
        ]
        if bikes and (rng.random() < 0.8 or not driving):
            options = bikes
        else:  # the kerb-side driving lane of its direction
            right = not reverse if not road.keep_left else reverse
            options = [driving[-1] if right else driving[0]]
        return options[int(rng.integers(0, len(options)))], reverse
    if not options:
        return None
    lane = options[int(rng.integers(0, len(options)))]
    direction = lanes[lane].direction
    reverse = direction == "backward" or (direction == "both" and bool(rng.random() < 0.5))
    return lane, reverse


def _draw_users(
    spec: FamilySpec, rng: np.random.Generator, road: Road, length: float, duration: float
) -> tuple[UserPlan, ...]:
    count = round(math.exp(_u(rng, (math.log(spec.users[0]), math.log(spec.users[1])))))
    drafts: list[_Draft] = []
    rates: list[float] = []
    for i in range(count):
        kind = _KINDS[_pick(rng, spec.kinds)]
        parked = kind == "car" and bool(rng.random() < 0.15)
        start = _start_lane(rng, road, kind, parked)
        if start is None:  # no sidewalk for a pedestrian: a car instead
            kind, parked = "car", False
            start = _start_lane(rng, road, kind, parked)
        if start is None:
            raise ConfigError(f"road of {spec.name} has no driving lane")
        lane, reverse = start
        speed = {
            "car": _u(rng, spec.car_speed),
            "bicycle": _u(rng, (3.0, 8.0)),
            "pedestrian": _u(rng, (0.8, 2.0)),
        }[kind]
        enter = _u(rng, (0.0, duration - 20.0)) if rng.random() < 0.4 else 0.0
        end = _u(rng, (enter + 20.0, duration)) if rng.random() < 0.4 else duration
        phone = kind != "car"
        rate = float(
            [1.0, 2.0, 5.0, 10.0][
                _pick(rng, (0.75, 0.1, 0.1, 0.05) if phone else (0.5, 0.15, 0.15, 0.2))
            ]
        )
        rates.append(rate)
        draft = _Draft(
            user=f"{kind}-{i}",
            kind=kind,
            speed=0.0 if parked else speed,
            reverse=reverse,
            lanes=[(0.0, lane)],
            change_time=_u(rng, (2.5, 5.0) if kind == "car" else (1.5, 3.0)),
            enter=round(enter, 3),
            end=round(end, 3),
            stops=[],
            brake={"car": 2.0, "bicycle": 1.5, "pedestrian": 1.0}[kind],
        )
        if not parked and rng.random() < spec.stop:
            ramp = math.pi * draft.speed / (2.0 * draft.brake)
            held = _u(rng, (5.0, 30.0))
            lo, hi = draft.enter + ramp + 1.0, draft.end - held - ramp - 1.0
            if hi > lo:
                draft.stops.append((round(_u(rng, (lo, hi)), 3), round(held, 3)))
        drafts.append(draft)
    # lane changes, one Poisson process per user; some pair with another car's
    for draft in drafts:
        if draft.speed == 0.0 or draft.kind == "pedestrian":
            continue
        rate = _u(
            rng, (1.0 / 60.0, 1.0 / 20.0) if draft.kind == "car" else (1.0 / 120.0, 1.0 / 40.0)
        )
        t = draft.enter
        while True:
            t += float(rng.exponential(1.0 / rate))
            if t >= draft.end:
                break
            if _change(rng, road, draft, t, overtake=bool(rng.random() < 0.4)) and (
                draft.kind == "car" and rng.random() < 0.15
            ):
                others = [d for d in drafts if d is not draft and d.kind == "car" and d.speed > 0]
                if others:
                    other = others[int(rng.integers(0, len(others)))]
                    _change(rng, road, other, t, overtake=False)
    # in a curve an inner lane's station runs ahead of the distance driven: by at most the
    # road's width times the angle turned
    width = sum(lane.width for lane in road.lanes)
    slack = width * sum(math.radians(abs(p.angle)) for p in road.pieces if isinstance(p, Curve))
    return tuple(
        _place(rng, draft, rate, length, slack) for draft, rate in zip(drafts, rates, strict=True)
    )


def _place(
    rng: np.random.Generator, draft: _Draft, rate: float, length: float, slack: float
) -> UserPlan:
    """The user's plan with a start station that keeps it on the road (`slack` m to spare),
    leaving where it would pass the end."""
    size, angle = _u(rng, (0.0, 1.0)), math.radians(_u(rng, (0.0, 360.0)))
    scale = math.exp(_u(rng, (math.log(0.5), math.log(2.0))))
    reports = bool(rng.random() < 0.5)
    plan = UserPlan(
        user=draft.user,
        kind=draft.kind,
        speed=draft.speed,
        start=0.0,
        lanes=tuple(draft.lanes),
        change_time=draft.change_time,
        phase=math.floor(_u(rng, (0.0, 1.0 / rate)) * 999.0) / 1000.0,
        reverse=draft.reverse,
        along_lane=True,
        enter=draft.enter,
        leave=draft.end,
        stops=tuple(draft.stops),
        brake=draft.brake,
        rate=rate,
        bias=(size * math.sin(angle), size * math.cos(angle)),
        noise_scale=_u(rng, (0.7, 1.4)),
        accuracy_scale=scale if reports else None,
    )
    room = length - 2.0 * _MARGIN - slack
    need = distance_driven(plan, draft.end + 0.2)
    offset = _u(rng, (0.0, max(room - need, 0.0)))
    leave = draft.end
    if need > room:  # it reaches the end of the road and leaves there
        offset = _u(rng, (0.0, 0.25 * room))
        lo, hi = draft.enter, draft.end
        for _ in range(60):
            mid = (lo + hi) / 2.0
            lo, hi = (mid, hi) if distance_driven(plan, mid + 0.2) <= room - offset else (lo, mid)
        leave = round(lo, 3) if lo > draft.enter + 1.0 else draft.enter + 1.0
    start = _MARGIN + offset
    if draft.reverse:
        start = length - start
    return UserPlan.model_validate({**plan.model_dump(), "start": start, "leave": leave})
