"""A participant's own answer while its session keeps quiet after a change of pseudonym.

The LDM's rotation policy may ask a participant to send nothing for a while after each
change (`ldm.wire.rotation`, ``silence``). A positioning client then answers itself: the
correction of its last answer (the answer minus the fix it answered: mostly the common
error, which drifts slowly) applied to its current fix,

    p_own = p_now + (p_answer - p_answered)

on the same lane. A client that holds the lane map too (it is the service's map, a public
file: `laas.map.bundled`, ``laas map import``) places that point on it itself, as
`own_lane` says, so that its answer follows the user through turns and junctions; without
a map the lane stays the last one answered, which is wrong once the user turns.
"""

from __future__ import annotations

import math

from laas.map.hdmap import HdMap, Segment
from laas.models import CorrectedPosition, GpsMeasurement

__all__ = ["MATCH_RADIUS", "MOVING", "dead_reckon", "own_lane"]

MATCH_RADIUS = 8.0  # m: lanes searched round the corrected point (a lane's width and the
#                     few metres a corrected fix is off)
MOVING = 1.0  # m/s: above this the fix's heading says which way the user travels


def dead_reckon(
    answer: CorrectedPosition,
    answered: GpsMeasurement,
    now: GpsMeasurement,
    hdmap: HdMap | None = None,
) -> CorrectedPosition:
    """The answer to fix `now` from the last answer `answer` to fix `answered` (module
    docstring); on `hdmap`'s lane for the corrected point when a map is given."""
    lat = now.latitude + (answer.latitude - answered.latitude)
    lon = now.longitude + (answer.longitude - answered.longitude)
    update: dict[str, object] = {"timestamp": now.timestamp, "latitude": lat, "longitude": lon}
    if hdmap is not None and answer.segment is not None and answer.lane is not None:
        x, y = hdmap.projection.to_utm(lon, lat)
        heading = now.heading if now.speed > MOVING else None
        update["segment"], update["lane"] = own_lane(
            hdmap, (answer.segment, answer.lane), answer.lane_type, x, y, heading
        )
    return answer.model_copy(update=update)


def own_lane(
    hdmap: HdMap,
    last: tuple[str, int],
    lane_type: str | None,
    x: float,
    y: float,
    heading: float | None,
) -> tuple[str, int]:
    """The lane of the UTM point (x, y) for a user last answered on lane `last`: that lane
    while it holds the point; else, of the lanes of the same type within ``MATCH_RADIUS``
    that may be driven the way the user travels (`heading`, degrees; None: either way),
    the one whose centre line is nearest; else `last`."""
    segment = hdmap.segments.get(last[0])
    if segment is not None and _holds(segment, last[1], x, y):
        return last
    best: tuple[float, str, int] | None = None
    for seg in hdmap.segments_near(x, y, MATCH_RADIUS):
        s, d = seg.frame(x, y)
        if not -1.0 <= s <= seg.length + 1.0:
            continue
        offsets = seg.lane_offsets(s)
        forward = None
        if heading is not None:
            delta = math.radians(heading - seg.heading(min(max(s, 0.0), seg.length)))
            forward = math.cos(delta) >= 0.0
        for lane in seg.lanes:
            if lane_type is not None and lane.type != lane_type:
                continue
            one_way = forward is not None and lane.direction != "both"
            if one_way and (lane.direction == "forward") != forward:
                continue
            gap = abs(d - float(offsets[lane.index]))
            if best is None or gap < best[0]:
                best = (gap, seg.id, lane.index)
    return last if best is None else (best[1], best[2])


def _holds(segment: Segment, lane: int, x: float, y: float) -> bool:
    """The point lies on lane `lane` of `segment` (within its length and its width)."""
    if not 0 <= lane < len(segment.lanes):
        return False
    s, d = segment.frame(x, y)
    if not 0.0 <= s <= segment.length:
        return False
    return abs(d - float(segment.lane_offsets(s)[lane])) <= segment.lanes[lane].width / 2
