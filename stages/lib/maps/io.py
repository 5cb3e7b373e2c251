"""Reading a Lanelet2 OSM file with lanelet2, robustly, and the car-lanelet rule.

`read_osm` parses the file with lanelet2 in a recording's metric frame (x east,
y north in metres from its origin; `projection.projector`), returning parser
messages as `MapProblem`s instead of raising. `lanelet_bounds` gives every
lanelet's bounds as plain arrays (for drawing the lanelets `RoadMap` leaves
out), and `is_car_lanelet` decides which lanelets a car may drive.

Car lanelets
    A lanelet is a car lanelet when its `subtype` is absent or one of road,
    highway, play_street, emergency_lane, unless a `participant:vehicle` (or
    `participant:vehicle:car`) tag says no; a `participant:vehicle=yes` tag
    admits any subtype. Everything else is not: walkway, crosswalk, bicycle_lane
    and the TAF-BW spelling `bikelane`, stairs, exit, bus_lane, rail. The TAF-BW
    maps have lanelets with no subtype (roads; k733 carries OSM tags such as
    highway=primary instead), walkway, crosswalk and bikelane. Germany's vehicle
    traffic rules accept lanelets with no subtype; a car lanelet that the rules
    reject anyway gets `participant:vehicle=yes` on the in-memory map, so that
    routing works, and a ROUTING_OVERRIDE problem. The routing graph is built
    from a submap of the car lanelets only.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from lanelet2 import core as ll_core
from lanelet2 import io as ll_io

from stages.lib.maps.projection import Projection, projector

CAR_SUBTYPES = frozenset({"road", "highway", "play_street", "emergency_lane"})


class MapProblemKind(enum.Enum):
    UNKNOWN = 0
    FILE_NOT_FOUND = 1
    UNREADABLE = 2
    PARSE_ERROR = 3
    BAD_ARGUMENT = 4
    ROUTING_OVERRIDE = 5
    DEGENERATE_LANELET = 6
    NO_CAR_LANELETS = 7


@dataclass(frozen=True, slots=True)
class MapProblem:
    kind: MapProblemKind
    detail: str
    element_id: int | None = None



def is_car_lanelet(attributes) -> bool:
    """The car-lanelet rule of the module docstring, on a lanelet's tag mapping."""
    tags = {str(k): str(v) for k, v in dict(attributes).items()}
    for key in ("participant:vehicle:car", "participant:vehicle"):
        if key in tags:
            return tags[key].strip().lower() in ("yes", "true", "1")
    subtype = tags.get("subtype", "").strip().lower()
    return subtype == "" or subtype in CAR_SUBTYPES



def read_osm(
    osm_path: str | Path,
    origin_lat_deg: float,
    origin_lon_deg: float,
    projection: Projection,
    *,
    offset_m: tuple[float, float] = (0.0, 0.0),
):
    """Parse a Lanelet2 OSM file into the recording's frame: ``(lanelet_map, problems)``.

    `projection` must be a concrete one (not UNKNOWN or AUTO). The map is
    projected at the origin and shifted so that the origin is (0, 0), then by
    `offset_m`. The lanelet2 `LaneletMap` is None when the file is missing or
    lanelet2 cannot read it; its parser messages come back as PARSE_ERROR
    problems. The origin is not checked here (`load_map` does).
    """
    problems: list[MapProblem] = []
    path = Path(osm_path)
    if not path.is_file():
        problems.append(MapProblem(MapProblemKind.FILE_NOT_FOUND, f"no map file at {path}"))
        return None, problems
    chosen = projector(projection, origin_lat_deg, origin_lon_deg)
    try:
        lanelet_map, errors = ll_io.loadRobust(str(path), chosen)
    except RuntimeError as error:
        problems.append(MapProblem(MapProblemKind.UNREADABLE, f"lanelet2 could not read {path}: {error}"))
        return None, problems
    problems.extend(
        MapProblem(MapProblemKind.PARSE_ERROR, message.strip().removeprefix("- "))
        for message in errors
        if not message.startswith("Errors ocurred while parsing")
    )
    origin_xy = chosen.forward(ll_core.GPSPoint(origin_lat_deg, origin_lon_deg, 0.0))
    shift_x = float(offset_m[0]) - origin_xy.x
    shift_y = float(offset_m[1]) - origin_xy.y
    if shift_x or shift_y:
        _shift_map(lanelet_map, shift_x, shift_y)
    return lanelet_map, problems


def _shift_map(lanelet_map, shift_x_m: float, shift_y_m: float) -> None:
    """Move every point of a freshly loaded map; `RoadMap` builds new spatial indices."""
    for point in lanelet_map.pointLayer:
        point.x = point.x + shift_x_m
        point.y = point.y + shift_y_m
    for lanelet in lanelet_map.laneletLayer:
        lanelet.resetCache()



@dataclass(frozen=True, slots=True, eq=False)
class LaneletBounds:
    """One lanelet of the file: its bounds (k, 2) float64 in the recording's frame, and whether a car may drive it."""

    lanelet_id: int
    is_car: bool
    left_bound_m: np.ndarray
    right_bound_m: np.ndarray


def lanelet_bounds(
    osm_path: str | Path,
    origin_lat_deg: float,
    origin_lon_deg: float,
    projection: Projection,
    *,
    offset_m: tuple[float, float] = (0.0, 0.0),
) -> tuple[list[LaneletBounds] | None, list[MapProblem]]:
    """Every lanelet of an OSM file (car or not), projected and shifted exactly as `load_map` does.

    `RoadMap` keeps the car lanelets only; this is for drawing the others
    (walkways, crosswalks, bike lanes). Lanelets in lanelet2's layer order;
    ``(None, problems)`` when the file cannot be read (`read_osm`), a ValueError
    for a projection that is not a concrete one.
    """
    lanelet_map, problems = read_osm(osm_path, origin_lat_deg, origin_lon_deg, projection, offset_m=offset_m)
    if lanelet_map is None:
        return None, problems
    out = []
    for lanelet in lanelet_map.laneletLayer:
        left = np.array([(p.x, p.y) for p in lanelet.leftBound], dtype=np.float64).reshape(-1, 2)
        right = np.array([(p.x, p.y) for p in lanelet.rightBound], dtype=np.float64).reshape(-1, 2)
        out.append(LaneletBounds(int(lanelet.id), is_car_lanelet(lanelet.attributes), left, right))
    return out, problems
