"""The HD map: lanes and road elements in UTM, their frames, and the readers that build them.

geo        UTM projections (pyproj), picked from the map's location
frame      the exact curvilinear (s, d) frame of a polyline
hdmap      Lane, Segment, HdMap: the queries the engine needs
geojson    the GeoJSON lane-map reader and its validation
mapgen     builds lane maps from a road description
bundled    where the maps that ship with LaaS are
summary    a map in figures (`laas map info`)
importers  Lanelet2, OpenDRIVE and OpenStreetMap maps into the lane-map format
"""

from laas.map.geo import UtmProjection
from laas.map.hdmap import HdMap, Lane, LaneType, Segment

__all__ = ["HdMap", "Lane", "LaneType", "Segment", "UtmProjection"]
