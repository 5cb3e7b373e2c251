"""Road map for hybrid IAMP: the project's only lanelet2 wrapper (docs/method.md §5).

A Lanelet2 OSM map in the metric frame of a recording (x east, y north in
metres from its origin), for the lanelets a car may drive. Nothing here knows
about the bus except the scene-map cache, which reads a ``SceneInfo``'s fields.
Split along Lanelet2's own seams; import the names from here:

- `projection`: `Projection`, the lanelet2 projector, the measured choice per location;
- `io`: reading the OSM file with lanelet2, `MapProblem`, the car-lanelet rule, `lanelet_bounds`;
- `geometry`: angles, Frenet projection, `Centreline`, segment intersections, polygons;
- `kernels`: numba kernels of the corridors and relations hot paths (projections, route sampling, lanelet
  measurement), the numpy code's values bit for bit, with `warm_up`;
- `road_map`: `RoadMap` (routing, point queries, relations, right of way) and `load_map`;
- `conflicts`: crossings, merges, divergences and intersections between car lanelets;
- `priority`: `Turn`, `PriorityRule`, the right-of-way rule;
- `scene`: the scene-map cache (`SceneMaps`) and the checked local map file.
"""

from stages.lib.maps.conflicts import Conflict, ConflictKind, ConflictPoint, Intersection, IntersectionMember
from stages.lib.maps.geometry import (
    Centreline,
    FrenetPoints,
    concatenate_centrelines,
    project_in_window,
    project_to_polyline,
    segment_intersections,
    wrap_angle_rad,
)
from stages.lib.maps.io import CAR_SUBTYPES, LaneletBounds, MapProblem, MapProblemKind, is_car_lanelet, lanelet_bounds, read_osm
from stages.lib.maps.priority import TURN_THRESHOLD_RAD, PriorityRule, RightOfWay, Turn
from stages.lib.maps.projection import PROJECTION_BY_LOCATION, Projection, parse_projection, projection_for_location, projector
from stages.lib.maps.road_map import DEFAULT_SPEED_LIMIT_MPS, LaneletInfo, Neighbours, RoadMap, load_map
from stages.lib.maps.scene import (
    MAP_MAX_BYTES,
    SceneMap,
    SceneMaps,
    data_folder,
    local_map_file,
    resolve_projection,
    shown_map_name,
)

__all__ = [
    "CAR_SUBTYPES",
    "DEFAULT_SPEED_LIMIT_MPS",
    "MAP_MAX_BYTES",
    "PROJECTION_BY_LOCATION",
    "TURN_THRESHOLD_RAD",
    "Centreline",
    "Conflict",
    "ConflictKind",
    "ConflictPoint",
    "FrenetPoints",
    "Intersection",
    "IntersectionMember",
    "LaneletBounds",
    "LaneletInfo",
    "MapProblem",
    "MapProblemKind",
    "Neighbours",
    "PriorityRule",
    "Projection",
    "RightOfWay",
    "RoadMap",
    "SceneMap",
    "SceneMaps",
    "Turn",
    "concatenate_centrelines",
    "data_folder",
    "is_car_lanelet",
    "lanelet_bounds",
    "load_map",
    "local_map_file",
    "parse_projection",
    "project_in_window",
    "project_to_polyline",
    "projection_for_location",
    "projector",
    "read_osm",
    "resolve_projection",
    "segment_intersections",
    "shown_map_name",
]
