"""Road map for hybrid IAMP: the project's only lanelet2 wrapper (METHOD.md §5).

`load_map` reads a Lanelet2 OSM file robustly (problems are returned, never
raised) in the metric frame of a recording: x east and y north in metres from
the recording's origin. `RoadMap` then holds, for the lanelets a car may drive,
the vehicle routing graph, smoothed centrelines with arc length, heading and
curvature, point-in-lanelet queries, the precomputed conflicts between lanelets,
the intersections and a right-of-way rule. Nothing here knows about the bus.

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

Conflicts (`Conflict`)
    Candidate pairs come from the routing graph's `conflicting` relation, plus
    the pairs with a common successor or a common predecessor or the same end
    point. Each candidate is refined with the smoothed centrelines, all segment
    pairs at once:
    - MERGE (common successor, or the same end point): placed at the merge
      start, the first arc length from which the two centrelines stay closer
      than the mean of the two lane widths, which is where the lanelets begin to
      overlap; x, y is the mean of the two merge-start points.
    - DIVERGE (common predecessor, or the same start point): kept for the
      following relation, but not a conflict; it marks where the lanelets stop
      overlapping.
    - CROSSING: centrelines that intersect away from a merge or divergence zone
      and from shared end points. Crossing wins over MERGE and DIVERGE.
    - A `conflicting` pair whose centrelines neither cross, merge nor diverge
      (polygons that only graze each other) is dropped.
    An intersection is a connected cluster of lanelets joined by CROSSING or
    MERGE conflicts. A member's entry and exit arc lengths are the first and last
    conflict points on it; for a merge, the exit is the lanelet's end.

Right of way (`RoadMap.priority`), in this order
    1. Regulatory elements on the lanelet or its direct predecessors (approach
       lanelets): RightOfWay (right_of_way lanelets over yield lanelets), a
       TrafficSign stop or give-way sign (de205, de206, or a type naming stop or
       yield) against a lanelet without one, AllWayStop (equal).
    2. Geometry, from the approach heading (at s = 0) and the turn of each
       lanelet (heading change above 30 degrees):
       - oncoming lanelets (more than 135 degrees apart): a left turn yields to
         a lanelet that does not turn left, otherwise equal;
       - crossing lanelets (45 to 135 degrees): the major road first when both
         carry OSM tags that differ (priority_road=designated, then the highway
         class motorway > trunk > primary > secondary > tertiary > the rest),
         else right before left;
       - the same approach direction: the lanelet that turns less, by more than
         15 degrees, goes first; otherwise equal (0).
    Road tags are only compared between crossing roads because k733's tags come
    from OSM ways and differ between the two halves of one road. The TAF-BW
    maps have no regulatory elements, and both intersections are signalised,
    so this rule describes who yields under the same green phase.

Projection, measured on TAF-BW (share of all car rows inside a car lanelet)
    | recording         | LOCAL_CARTESIAN | SCALED_MERCATOR | UTM    |
    | k729, 25 seq.     | 0.9882          | 0.9891          | 0.9944 |
    | k733, 1 seq.      | 0.8333          | 0.8360          | 0.8203 |
    SCALED_MERCATOR is lanelet2's MercatorProjector (spherical Mercator on
    R = 6378137 m scaled by cos(origin latitude)) minus the origin's own x, y.
    In k733 the projection is not the cause: the moving cars fit the lane
    centrelines with 0.82 to 0.88 m rms and a residual offset of about 0.6 m
    under each of the three, and 91 % of the misses (1818 of 1981 rows) lie in a 3 m wide
    unmapped lane between lanelets -103632 and -103634, the missing fourth lane
    of Ostring's south-west approach, where two cars wait for about 75 s each.
    Counting that strip, the share is 0.986. `projection_for_location` picks
    UTM for K729 and SCALED_MERCATOR for K733 (the best measured, and the
    method the dataset names); `Projection.AUTO` tries all three against given
    car positions and keeps the best aligned. `offset_m` shifts the map: the
    least-squares offsets of the map towards the tracks are about
    (-0.4, -0.55) m for k729 and (+0.6, -0.1) m for k733; they raise the shares
    to 0.998 and 0.846 but are fitted on the same data, so none is applied.
"""

from __future__ import annotations

import enum
import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
from lanelet2 import core as ll_core
from lanelet2 import io as ll_io
from lanelet2 import projection as ll_projection
from lanelet2 import routing as ll_routing
from lanelet2 import traffic_rules as ll_traffic_rules

DEFAULT_SPEED_LIMIT_MPS = 50.0 / 3.6
CAR_SUBTYPES = frozenset({"road", "highway", "play_street", "emergency_lane"})
TURN_THRESHOLD_RAD = math.radians(30.0)
_HIGHWAY_RANK = {"motorway": 6, "trunk": 5, "primary": 4, "secondary": 3, "tertiary": 2}
_STOP_OR_YIELD_SIGNS = ("de205", "de206", "stop", "yield", "give_way")
_MIN_LANELET_LENGTH_M = 0.05


class Projection(enum.Enum):
    """How the map's latitude and longitude become metres from the origin."""

    UNKNOWN = 0
    LOCAL_CARTESIAN = 1
    SCALED_MERCATOR = 2
    UTM = 3
    AUTO = 4


PROJECTION_BY_LOCATION = {"k729": Projection.UTM, "k733": Projection.SCALED_MERCATOR}
_AUTO_CANDIDATES = (Projection.LOCAL_CARTESIAN, Projection.SCALED_MERCATOR, Projection.UTM)


def projection_for_location(location_id: str) -> Projection:
    """Measured best projection for a TAF-BW location id; LOCAL_CARTESIAN if unknown."""
    return PROJECTION_BY_LOCATION.get(location_id.strip().lower(), Projection.LOCAL_CARTESIAN)


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


class ConflictKind(enum.Enum):
    UNKNOWN = 0
    CROSSING = 1
    MERGE = 2
    DIVERGE = 3


class Turn(enum.Enum):
    UNKNOWN = 0
    STRAIGHT = 1
    LEFT = 2
    RIGHT = 3


class PriorityRule(enum.Enum):
    """Which rule decided `RoadMap.priority_with_rule`."""

    UNKNOWN = 0
    REGULATORY = 1
    ROAD_CLASS = 2
    ONCOMING_TURN = 3
    RIGHT_BEFORE_LEFT = 4
    LESS_TURNING = 5
    EQUAL = 6


def _frozen(array: np.ndarray) -> np.ndarray:
    out = np.array(array, dtype=np.float64, copy=True)
    out.flags.writeable = False
    return out


def wrap_angle_rad(angle_rad):
    """Wrap angles to [-pi, pi)."""
    return (np.asarray(angle_rad) + np.pi) % (2.0 * np.pi) - np.pi


@dataclass(frozen=True, slots=True, eq=False)
class FrenetPoints:
    """Projections of n points onto a polyline, arrays of shape (n,) float64.

    `d_m` is the signed lateral offset, positive to the left of the direction of
    travel; `heading_rad` is the polyline's heading at `s_m`. Points beyond
    either end project onto the straight extension of the end segment, so `s_m`
    can be negative or exceed the length.
    """

    s_m: np.ndarray
    d_m: np.ndarray
    heading_rad: np.ndarray


def project_to_polyline(
    points_m,
    polyline_m,
    s_m=None,
    heading_rad=None,
    *,
    s_hint_m=None,
    window_m: float | None = None,
) -> FrenetPoints:
    """Project points (n, 2) onto a polyline (m, 2), vectorised over points and segments.

    `s_m` (m,) is the polyline's arc length (computed if absent) and
    `heading_rad` (m,) its heading, interpolated at the foot point when given
    (else the segment's direction). With `s_hint_m` (scalar or (n,)) and
    `window_m`, only segments within `window_m` of the hint are candidates,
    which keeps projections continuous at joins and on tight curves; a point
    with no candidate falls back to all segments.
    """
    points = np.atleast_2d(np.asarray(points_m, dtype=np.float64))
    line = np.asarray(polyline_m, dtype=np.float64)
    if line.ndim != 2 or line.shape[0] < 2 or line.shape[1] != 2:
        raise ValueError("polyline_m must have shape (m >= 2, 2)")
    seg = np.diff(line, axis=0)
    seg_len = np.hypot(seg[:, 0], seg[:, 1])
    arc = np.concatenate([[0.0], np.cumsum(seg_len)]) if s_m is None else np.asarray(s_m, np.float64)
    seg_len2 = np.maximum(seg_len**2, 1e-18)
    n_seg = len(seg)
    lower = np.zeros(n_seg)
    upper = np.ones(n_seg)
    lower[0] = -np.inf
    upper[-1] = np.inf
    hints = None
    if s_hint_m is not None and window_m is not None:
        hints = np.broadcast_to(np.asarray(s_hint_m, np.float64), (len(points),))
    n_pts = len(points)
    out_s = np.empty(n_pts)
    out_d = np.empty(n_pts)
    out_seg = np.empty(n_pts, dtype=np.int64)
    chunk = max(1, 2_000_000 // max(n_seg, 1))
    for start in range(0, n_pts, chunk):
        p = points[start : start + chunk]
        rel = p[:, None, :] - line[None, :-1, :]
        t = np.clip((rel * seg[None]).sum(axis=2) / seg_len2[None], lower[None], upper[None])
        foot = line[None, :-1, :] + t[..., None] * seg[None]
        dist2 = ((p[:, None, :] - foot) ** 2).sum(axis=2)
        if hints is not None:
            h = hints[start : start + chunk, None]
            outside = (arc[None, 1:] < h - window_m) | (arc[None, :-1] > h + window_m)
            masked = np.where(outside, np.inf, dist2)
            usable = np.isfinite(masked).any(axis=1)
            dist2 = np.where(usable[:, None], masked, dist2)
        j = dist2.argmin(axis=1)
        rows = np.arange(len(p))
        tj = t[rows, j]
        out_s[start : start + chunk] = arc[j] + tj * seg_len[j]
        ux, uy = seg[j, 0] / np.sqrt(seg_len2[j]), seg[j, 1] / np.sqrt(seg_len2[j])
        rx, ry = rel[rows, j, 0], rel[rows, j, 1]
        out_d[start : start + chunk] = ux * ry - uy * rx
        out_seg[start : start + chunk] = j
    if heading_rad is None:
        heading = np.arctan2(seg[out_seg, 1], seg[out_seg, 0])
    else:
        unwrapped = np.unwrap(np.asarray(heading_rad, np.float64))
        heading = wrap_angle_rad(np.interp(out_s, arc, unwrapped))
    return FrenetPoints(s_m=out_s, d_m=out_d, heading_rad=heading)


@dataclass(frozen=True, slots=True, eq=False)
class Centreline:
    """A resampled, lightly smoothed centreline; arrays (n,) float64, read-only.

    `s_m` is the cumulative arc length from 0, `heading_rad` the direction of
    travel and `curvature_1pm` its derivative along s (positive to the left).
    """

    x_m: np.ndarray
    y_m: np.ndarray
    s_m: np.ndarray
    heading_rad: np.ndarray
    curvature_1pm: np.ndarray

    @classmethod
    def from_points(cls, points_m, step_m: float = 0.5, smoothing_m: float = 1.0) -> Centreline:
        """Resample a polyline (m >= 2, 2) to about `step_m` and smooth it.

        The smoothing is a Gaussian of standard deviation `smoothing_m` over a
        point-reflected extension, so both end points stay where they are and
        consecutive lanelets still meet.
        """
        raw = np.asarray(points_m, dtype=np.float64)[:, :2]
        keep = np.concatenate([[True], np.hypot(*np.diff(raw, axis=0).T) > 1e-9])
        raw = raw[keep]
        if len(raw) < 2:
            raise ValueError("a centreline needs two distinct points")
        raw_s = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(raw, axis=0).T))])
        n = max(2, int(math.ceil(raw_s[-1] / step_m)) + 1)
        s = np.linspace(0.0, raw_s[-1], n)
        pts = np.column_stack([np.interp(s, raw_s, raw[:, 0]), np.interp(s, raw_s, raw[:, 1])])
        sigma = smoothing_m / (raw_s[-1] / (n - 1))
        radius = min(int(math.ceil(3.0 * sigma)), n - 1)
        if sigma > 0.0 and radius >= 1:
            kernel = np.exp(-0.5 * (np.arange(-radius, radius + 1) / sigma) ** 2)
            kernel /= kernel.sum()
            head = 2.0 * pts[0] - pts[radius:0:-1]
            tail = 2.0 * pts[-1] - pts[-2 : -radius - 2 : -1]
            padded = np.concatenate([head, pts, tail])
            pts = np.column_stack([np.convolve(padded[:, k], kernel, mode="valid") for k in range(2)])
        return cls.from_resampled(pts)

    @classmethod
    def from_resampled(cls, points_m) -> Centreline:
        """Build from points that are already dense and smooth (no resampling)."""
        pts = np.asarray(points_m, dtype=np.float64)
        s = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(pts, axis=0).T))])
        dx = np.gradient(pts[:, 0], s) if len(s) > 2 else np.full(len(s), pts[-1, 0] - pts[0, 0])
        dy = np.gradient(pts[:, 1], s) if len(s) > 2 else np.full(len(s), pts[-1, 1] - pts[0, 1])
        heading = np.unwrap(np.arctan2(dy, dx))
        curvature = np.gradient(heading, s) if len(s) > 2 else np.zeros(len(s))
        return cls(
            x_m=_frozen(pts[:, 0]),
            y_m=_frozen(pts[:, 1]),
            s_m=_frozen(s),
            heading_rad=_frozen(wrap_angle_rad(heading)),
            curvature_1pm=_frozen(curvature),
        )

    @property
    def length_m(self) -> float:
        return float(self.s_m[-1])

    @property
    def points_m(self) -> np.ndarray:
        """(n, 2) float64 copy of the points."""
        return np.column_stack([self.x_m, self.y_m])

    def heading_at(self, s_m) -> np.ndarray:
        return wrap_angle_rad(np.interp(s_m, self.s_m, np.unwrap(self.heading_rad)))

    def to_xy(self, s_m, d_m=0.0) -> np.ndarray:
        """Points (n, 2) at arc lengths `s_m` and left offsets `d_m`; straight beyond the ends."""
        s = np.atleast_1d(np.asarray(s_m, dtype=np.float64))
        d = np.broadcast_to(np.asarray(d_m, dtype=np.float64), s.shape)
        heading = self.heading_at(s)
        x = np.interp(s, self.s_m, self.x_m)
        y = np.interp(s, self.s_m, self.y_m)
        for beyond, s_end, idx in ((s < 0.0, 0.0, 0), (s > self.length_m, self.length_m, -1)):
            h = self.heading_rad[idx]
            x = np.where(beyond, self.x_m[idx] + (s - s_end) * math.cos(h), x)
            y = np.where(beyond, self.y_m[idx] + (s - s_end) * math.sin(h), y)
        return np.column_stack([x - d * np.sin(heading), y + d * np.cos(heading)])

    def project(self, points_m, *, s_hint_m=None, window_m: float | None = None) -> FrenetPoints:
        """Frenet coordinates of points (n, 2); see `project_to_polyline`."""
        return project_to_polyline(
            points_m, self.points_m, self.s_m, self.heading_rad, s_hint_m=s_hint_m, window_m=window_m
        )


def concatenate_centrelines(centrelines: Sequence[Centreline]) -> Centreline:
    """Join the centrelines of a lanelet sequence into one, dropping repeated join points."""
    parts = [centrelines[0].points_m]
    for line in centrelines[1:]:
        pts = line.points_m
        if np.hypot(*(pts[0] - parts[-1][-1])) < 1e-6:
            pts = pts[1:]
        if len(pts):
            parts.append(pts)
    return Centreline.from_resampled(np.concatenate(parts))


@dataclass(frozen=True, slots=True, eq=False)
class LaneletInfo:
    """Geometry and rules of one car lanelet; bound arrays are (k, 2) float64.

    `width_m` is the polygon's area over the centreline's length. The speed
    limit comes from the lanelet's `speed_limit` (lanelet2) or `maxspeed` (OSM)
    tag, in km/h unless a unit is given, else from a SpeedLimit regulatory
    element, else the map's default. `turn` classifies `turn_angle_rad`, the
    heading change from start to end, at 30 degrees.
    """

    lanelet_id: int
    centreline: Centreline
    left_bound_m: np.ndarray
    right_bound_m: np.ndarray
    width_m: float
    length_m: float
    speed_limit_mps: float
    subtype: str
    turn: Turn
    turn_angle_rad: float


@dataclass(frozen=True, slots=True)
class Neighbours:
    """Same-direction neighbours from the routing graph; ids or None."""

    left_id: int | None
    right_id: int | None
    can_change_left: bool
    can_change_right: bool


@dataclass(frozen=True, slots=True)
class ConflictPoint:
    """Where lanelets a and b meet: arc lengths on each; angle = heading b - heading a."""

    x_m: float
    y_m: float
    s_a_m: float
    s_b_m: float
    angle_rad: float

    def swapped(self) -> ConflictPoint:
        return ConflictPoint(self.x_m, self.y_m, self.s_b_m, self.s_a_m, -self.angle_rad)


@dataclass(frozen=True, slots=True)
class Conflict:
    """A relation between two car lanelets; `points` is ordered along lanelet a.

    A positive angle means lanelet b comes from the right of lanelet a.
    """

    lanelet_a_id: int
    lanelet_b_id: int
    kind: ConflictKind
    points: tuple[ConflictPoint, ...]

    @property
    def first(self) -> ConflictPoint:
        return self.points[0]

    @property
    def is_conflict(self) -> bool:
        return self.kind in (ConflictKind.CROSSING, ConflictKind.MERGE)

    def swapped(self) -> Conflict:
        pts = sorted((p.swapped() for p in self.points), key=lambda p: p.s_a_m)
        return Conflict(self.lanelet_b_id, self.lanelet_a_id, self.kind, tuple(pts))


@dataclass(frozen=True, slots=True)
class IntersectionMember:
    lanelet_id: int
    entry_s_m: float
    exit_s_m: float


@dataclass(frozen=True, slots=True)
class Intersection:
    intersection_id: int
    members: tuple[IntersectionMember, ...]

    @property
    def lanelet_ids(self) -> tuple[int, ...]:
        return tuple(m.lanelet_id for m in self.members)

    def member(self, lanelet_id: int) -> IntersectionMember | None:
        return next((m for m in self.members if m.lanelet_id == lanelet_id), None)


def is_car_lanelet(attributes) -> bool:
    """The car-lanelet rule of the module docstring, on a lanelet's tag mapping."""
    tags = {str(k): str(v) for k, v in dict(attributes).items()}
    for key in ("participant:vehicle:car", "participant:vehicle"):
        if key in tags:
            return tags[key].strip().lower() in ("yes", "true", "1")
    subtype = tags.get("subtype", "").strip().lower()
    return subtype == "" or subtype in CAR_SUBTYPES


def _parse_speed_mps(text: str) -> float | None:
    match = re.fullmatch(r"\s*([0-9]+(?:\.[0-9]*)?)\s*(km/h|kmh|kph|mph|m/s|mps)?\s*", text.lower())
    if not match:
        return None
    value = float(match.group(1))
    unit = match.group(2) or "km/h"
    factor = {"mph": 0.44704, "m/s": 1.0, "mps": 1.0}.get(unit, 1.0 / 3.6)
    return value * factor if value > 0.0 else None


def _speed_limit_element_mps(element) -> float | None:
    """The limit of a SpeedLimit element: its speed_limit tag, or a German sign type such as de274-30."""
    tags = {str(k): str(v) for k, v in dict(element.attributes).items()}
    if "speed_limit" in tags:
        return _parse_speed_mps(tags["speed_limit"])
    match = re.search(r"de274-([0-9]+)", str(element.type()).lower())
    return float(match.group(1)) / 3.6 if match else None


def _polygon_area_m2(polygon: np.ndarray) -> float:
    x, y = polygon[:, 0], polygon[:, 1]
    return 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))


def _distance_to_polyline_m(points: np.ndarray, line: np.ndarray) -> np.ndarray:
    seg = np.diff(line, axis=0)
    len2 = np.maximum((seg**2).sum(axis=1), 1e-18)
    rel = points[:, None, :] - line[None, :-1, :]
    t = np.clip((rel * seg[None]).sum(axis=2) / len2[None], 0.0, 1.0)
    diff = rel - t[..., None] * seg[None]
    return np.sqrt((diff**2).sum(axis=2).min(axis=1))


def segment_intersections(line_a: np.ndarray, line_b: np.ndarray):
    """All intersections of two polylines, every segment pair at once.

    Returns (i, j, t, u): segment indices on a and b and the fractions along
    those segments, arrays of equal length.
    """
    a0, r = line_a[:-1], np.diff(line_a, axis=0)
    b0, q = line_b[:-1], np.diff(line_b, axis=0)
    denom = r[:, None, 0] * q[None, :, 1] - r[:, None, 1] * q[None, :, 0]
    diff = b0[None, :, :] - a0[:, None, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (diff[..., 0] * q[None, :, 1] - diff[..., 1] * q[None, :, 0]) / denom
        u = (diff[..., 0] * r[:, None, 1] - diff[..., 1] * r[:, None, 0]) / denom
    hit = (np.abs(denom) > 1e-12) & (t >= 0.0) & (t <= 1.0) & (u >= 0.0) & (u <= 1.0)
    i, j = np.nonzero(hit)
    return i, j, t[i, j], u[i, j]


class RoadMap:
    """Car lanelets of a lanelet2 map in the recording's frame, with routing and relations.

    Build it with `load_map`, or directly from a lanelet2 `LaneletMap` whose
    points are already in the recording's frame. Problems found while building
    are in `build_problems`.
    """

    def __init__(
        self,
        lanelet_map,
        *,
        projection: Projection = Projection.UNKNOWN,
        default_speed_limit_mps: float = DEFAULT_SPEED_LIMIT_MPS,
        resample_step_m: float = 0.5,
        smoothing_m: float = 1.0,
    ) -> None:
        self.projection = projection
        self.projection_shares: tuple[tuple[Projection, float], ...] = ()
        problems: list[MapProblem] = []
        rules = ll_traffic_rules.create(ll_traffic_rules.Locations.Germany, ll_traffic_rules.Participants.Vehicle)
        car_lanelets = []
        infos: dict[int, LaneletInfo] = {}
        for lanelet in sorted(lanelet_map.laneletLayer, key=lambda item: item.id):
            if not is_car_lanelet(lanelet.attributes):
                continue
            info = self._lanelet_info(lanelet, default_speed_limit_mps, resample_step_m, smoothing_m)
            if info is None:
                problems.append(
                    MapProblem(MapProblemKind.DEGENERATE_LANELET, "centreline shorter than 5 cm", lanelet.id)
                )
                continue
            if not rules.canPass(lanelet):
                lanelet.attributes["participant:vehicle"] = "yes"
                problems.append(
                    MapProblem(
                        MapProblemKind.ROUTING_OVERRIDE,
                        "vehicle rules rejected a car lanelet; set participant:vehicle=yes",
                        lanelet.id,
                    )
                )
            car_lanelets.append(lanelet)
            infos[lanelet.id] = info
        if not car_lanelets:
            problems.append(MapProblem(MapProblemKind.NO_CAR_LANELETS, "the map has no lanelet a car may drive"))
        self.build_problems: tuple[MapProblem, ...] = tuple(problems)
        self._infos = infos
        self.lanelet_ids: tuple[int, ...] = tuple(infos)
        self._index = {lanelet_id: k for k, lanelet_id in enumerate(self.lanelet_ids)}
        self._lanelets = {lanelet.id: lanelet for lanelet in car_lanelets}
        self.lanelet2_map = ll_core.createMapFromLanelets(car_lanelets)
        self.routing_graph = ll_routing.RoutingGraph(self.lanelet2_map, rules) if car_lanelets else None
        self._read_routing()
        self._build_polygon_edges()
        self._relations = self._compute_relations()
        self._conflict_keys: dict[int, list[tuple[int, int]]] = {x: [] for x in self.lanelet_ids}
        for key, relation in self._relations.items():
            if relation.is_conflict:
                self._conflict_keys[key[0]].append(key)
                self._conflict_keys[key[1]].append(key)
        self._intersections = self._compute_intersections()
        self._read_regulatory_elements()

    # ----- construction helpers -------------------------------------------

    @staticmethod
    def _lanelet_info(lanelet, default_speed_limit_mps, step_m, smoothing_m) -> LaneletInfo | None:
        raw = np.array([(p.x, p.y) for p in lanelet.centerline], dtype=np.float64)
        if len(raw) < 2 or np.hypot(*np.diff(raw, axis=0).T).sum() < _MIN_LANELET_LENGTH_M:
            return None
        centreline = Centreline.from_points(raw, step_m, smoothing_m)
        left = np.array([(p.x, p.y) for p in lanelet.leftBound], dtype=np.float64)
        right = np.array([(p.x, p.y) for p in lanelet.rightBound], dtype=np.float64)
        width_m = _polygon_area_m2(np.concatenate([left, right[::-1]])) / centreline.length_m
        tags = {str(k): str(v) for k, v in dict(lanelet.attributes).items()}
        speed = None
        for key in ("speed_limit", "maxspeed"):
            if key in tags and speed is None:
                speed = _parse_speed_mps(tags[key])
        for element in lanelet.regulatoryElements:
            if speed is None and isinstance(element, ll_core.SpeedLimit):
                speed = _speed_limit_element_mps(element)
        turn_angle = float(wrap_angle_rad(centreline.heading_rad[-1] - centreline.heading_rad[0]))
        if turn_angle > TURN_THRESHOLD_RAD:
            turn = Turn.LEFT
        elif turn_angle < -TURN_THRESHOLD_RAD:
            turn = Turn.RIGHT
        else:
            turn = Turn.STRAIGHT
        return LaneletInfo(
            lanelet_id=lanelet.id,
            centreline=centreline,
            left_bound_m=_frozen(left),
            right_bound_m=_frozen(right),
            width_m=float(width_m),
            length_m=centreline.length_m,
            speed_limit_mps=float(speed if speed is not None else default_speed_limit_mps),
            subtype=tags.get("subtype", ""),
            turn=turn,
            turn_angle_rad=turn_angle,
        )

    def _read_routing(self) -> None:
        graph = self.routing_graph
        self._successors: dict[int, tuple[int, ...]] = {}
        self._predecessors: dict[int, tuple[int, ...]] = {}
        self._neighbours: dict[int, Neighbours] = {}
        self._lanelet2_conflicts: dict[int, tuple[int, ...]] = {}
        known = self._infos
        for lanelet_id, lanelet in self._lanelets.items():
            self._successors[lanelet_id] = tuple(sorted(x.id for x in graph.following(lanelet) if x.id in known))
            self._predecessors[lanelet_id] = tuple(sorted(x.id for x in graph.previous(lanelet) if x.id in known))
            left, right = graph.left(lanelet), graph.right(lanelet)
            adjacent_left = left if left is not None else graph.adjacentLeft(lanelet)
            adjacent_right = right if right is not None else graph.adjacentRight(lanelet)
            self._neighbours[lanelet_id] = Neighbours(
                left_id=adjacent_left.id if adjacent_left is not None else None,
                right_id=adjacent_right.id if adjacent_right is not None else None,
                can_change_left=left is not None,
                can_change_right=right is not None,
            )
            conflicting = []
            for other in graph.conflicting(lanelet):
                other_id = getattr(other, "id", None)
                if other_id in known and other_id != lanelet_id:
                    conflicting.append(other_id)
            self._lanelet2_conflicts[lanelet_id] = tuple(sorted(conflicting))

    def _build_polygon_edges(self) -> None:
        starts, edges = [], []
        for lanelet_id in self.lanelet_ids:
            info = self._infos[lanelet_id]
            polygon = np.concatenate([info.left_bound_m, info.right_bound_m[::-1]])
            starts.append(sum(len(e) for e in edges))
            edges.append(np.concatenate([polygon, np.roll(polygon, -1, axis=0)], axis=1))
        self._edges = np.concatenate(edges) if edges else np.zeros((0, 4))
        self._edge_starts = np.asarray(starts, dtype=np.int64)

    def _compute_relations(self) -> dict[tuple[int, int], Conflict]:
        candidates: set[tuple[int, int]] = set()
        for a, others in self._lanelet2_conflicts.items():
            candidates.update((min(a, b), max(a, b)) for b in others)
        for groups in (self._successors, self._predecessors):
            for members in groups.values():
                candidates.update((a, b) for a in members for b in members if a < b)
        ids = np.asarray(self.lanelet_ids)
        for end in (0, -1):
            ends = np.array([self._infos[x].centreline.points_m[end] for x in self.lanelet_ids]).reshape(-1, 2)
            close = np.hypot(*(ends[:, None, :] - ends[None, :, :]).transpose(2, 0, 1)) < 0.5
            i, j = np.nonzero(np.triu(close, k=1))
            candidates.update((int(min(ids[p], ids[q])), int(max(ids[p], ids[q]))) for p, q in zip(i, j))
        relations = {}
        for a, b in sorted(candidates):
            relation = self._relate(a, b)
            if relation is not None:
                relations[(a, b)] = relation
        return relations

    def _relate(self, a: int, b: int) -> Conflict | None:
        info_a, info_b = self._infos[a], self._infos[b]
        line_a, line_b = info_a.centreline, info_b.centreline
        pts_a, pts_b = line_a.points_m, line_b.points_m
        overlap_m = 0.5 * (info_a.width_m + info_b.width_m)
        touch_m = 0.5
        merge = bool(set(self._successors[a]) & set(self._successors[b])) or (
            np.hypot(*(pts_a[-1] - pts_b[-1])) < touch_m
        )
        diverge = not merge and (
            bool(set(self._predecessors[a]) & set(self._predecessors[b])) or np.hypot(*(pts_a[0] - pts_b[0])) < touch_m
        )
        zone_a = zone_b = None
        if merge or diverge:
            dist_a = _distance_to_polyline_m(pts_a, pts_b)
            dist_b = _distance_to_polyline_m(pts_b, pts_a)
            if merge:
                zone_a = _merge_start_m(line_a.s_m, dist_a, overlap_m)
                zone_b = _merge_start_m(line_b.s_m, dist_b, overlap_m)
            else:
                zone_a = _divergence_end_m(line_a.s_m, dist_a, overlap_m)
                zone_b = _divergence_end_m(line_b.s_m, dist_b, overlap_m)
        i, j, t, u = segment_intersections(pts_a, pts_b)
        s_a = line_a.s_m[i] + t * np.diff(line_a.s_m)[i]
        s_b = line_b.s_m[j] + u * np.diff(line_b.s_m)[j]
        keep = np.ones(len(s_a), dtype=bool)
        end_margin_m = 0.5
        at_end_a = (s_a < end_margin_m) | (s_a > line_a.length_m - end_margin_m)
        at_end_b = (s_b < end_margin_m) | (s_b > line_b.length_m - end_margin_m)
        keep &= ~(at_end_a & at_end_b)
        if merge:
            keep &= (s_a < zone_a - end_margin_m) & (s_b < zone_b - end_margin_m)
        if diverge:
            keep &= (s_a > zone_a + end_margin_m) & (s_b > zone_b + end_margin_m)
        order = np.argsort(s_a[keep])
        s_a, s_b = s_a[keep][order], s_b[keep][order]
        points = []
        for sa, sb in zip(s_a, s_b):
            if points and sa - points[-1].s_a_m < 1.0:
                continue
            xy = line_a.to_xy(sa)[0]
            angle = float(wrap_angle_rad(line_b.heading_at(sb) - line_a.heading_at(sa)))
            points.append(ConflictPoint(float(xy[0]), float(xy[1]), float(sa), float(sb), angle))
        if points:
            return Conflict(a, b, ConflictKind.CROSSING, tuple(points))
        if merge or diverge:
            xy = 0.5 * (line_a.to_xy(zone_a)[0] + line_b.to_xy(zone_b)[0])
            angle = float(wrap_angle_rad(line_b.heading_at(zone_b) - line_a.heading_at(zone_a)))
            point = ConflictPoint(float(xy[0]), float(xy[1]), float(zone_a), float(zone_b), angle)
            return Conflict(a, b, ConflictKind.MERGE if merge else ConflictKind.DIVERGE, (point,))
        return None

    def _compute_intersections(self) -> tuple[Intersection, ...]:
        parent = {lanelet_id: lanelet_id for lanelet_id in self.lanelet_ids}

        def root(x: int) -> int:
            while parent[x] != x:
                parent[x] = parent[parent[x]]
                x = parent[x]
            return x

        spans: dict[int, list[float]] = {}
        for (a, b), relation in self._relations.items():
            if not relation.is_conflict:
                continue
            parent[root(a)] = root(b)
            for lanelet_id, values in (
                (a, [p.s_a_m for p in relation.points]),
                (b, [p.s_b_m for p in relation.points]),
            ):
                if relation.kind is ConflictKind.MERGE:
                    values = values + [self._infos[lanelet_id].length_m]
                spans.setdefault(lanelet_id, []).extend(values)
        clusters: dict[int, list[int]] = {}
        for lanelet_id in self.lanelet_ids:
            if lanelet_id in spans:
                clusters.setdefault(root(lanelet_id), []).append(lanelet_id)
        ordered = sorted(clusters.values(), key=lambda ids: min(self._index[x] for x in ids))
        result = []
        for number, ids in enumerate(ordered):
            members = tuple(
                IntersectionMember(
                    lanelet_id,
                    float(max(0.0, min(spans[lanelet_id]))),
                    float(min(self._infos[lanelet_id].length_m, max(spans[lanelet_id]))),
                )
                for lanelet_id in sorted(ids, key=self._index.get)
            )
            result.append(Intersection(number, members))
        self._intersection_of = {m.lanelet_id: x for x in result for m in x.members}
        return tuple(result)

    def _read_regulatory_elements(self) -> None:
        self._right_of_way: dict[int, set[int]] = {x: set() for x in self.lanelet_ids}
        self._yields_in: dict[int, set[int]] = {x: set() for x in self.lanelet_ids}
        self._all_way_stops: dict[int, set[int]] = {x: set() for x in self.lanelet_ids}
        self._has_stop_sign: dict[int, bool] = {x: False for x in self.lanelet_ids}
        self._has_regulation: dict[int, bool] = {x: False for x in self.lanelet_ids}
        for lanelet_id, lanelet in self._lanelets.items():
            for element in lanelet.regulatoryElements:
                if isinstance(element, ll_core.RightOfWay):
                    self._has_regulation[lanelet_id] = True
                    if any(x.id == lanelet_id for x in element.rightOfWayLanelets()):
                        self._right_of_way[lanelet_id].add(element.id)
                    if any(x.id == lanelet_id for x in element.yieldLanelets()):
                        self._yields_in[lanelet_id].add(element.id)
                elif isinstance(element, ll_core.AllWayStop):
                    self._has_regulation[lanelet_id] = True
                    self._all_way_stops[lanelet_id].add(element.id)
                elif isinstance(element, ll_core.TrafficSign):
                    sign_type = str(element.type()).lower()
                    if any(key in sign_type for key in _STOP_OR_YIELD_SIGNS):
                        self._has_regulation[lanelet_id] = True
                        self._has_stop_sign[lanelet_id] = True

    # ----- lanelets and routing -------------------------------------------

    def lanelet(self, lanelet_id: int) -> LaneletInfo:
        """Geometry of a car lanelet; KeyError if it is not one."""
        return self._infos[lanelet_id]

    def has_lanelet(self, lanelet_id: int) -> bool:
        return lanelet_id in self._infos

    def successors(self, lanelet_id: int) -> tuple[int, ...]:
        return self._successors[lanelet_id]

    def predecessors(self, lanelet_id: int) -> tuple[int, ...]:
        return self._predecessors[lanelet_id]

    def neighbours(self, lanelet_id: int) -> Neighbours:
        return self._neighbours[lanelet_id]

    def possible_paths(
        self, start_id: int, min_length_m: float, *, start_s_m: float = 0.0, max_paths: int = 256
    ) -> list[tuple[int, ...]]:
        """Lanelet sequences from `start_id` without lane changes, like lanelet2's possiblePaths.

        A path ends as soon as it reaches `min_length_m` beyond `start_s_m` on
        the start lanelet, or at a dead end (then it is shorter). No lanelet is
        visited twice. At most `max_paths` paths, depth first in id order.
        """
        paths: list[tuple[int, ...]] = []
        stack = [((start_id,), self._infos[start_id].length_m - start_s_m)]
        while stack and len(paths) < max_paths:
            path, length_m = stack.pop()
            following = [x for x in self._successors[path[-1]] if x not in path]
            if length_m >= min_length_m or not following:
                paths.append(path)
                continue
            for succ in reversed(following):
                stack.append((path + (succ,), length_m + self._infos[succ].length_m))
        return paths

    def path_centreline(self, path: Sequence[int]) -> Centreline:
        """One centreline along a lanelet sequence."""
        return concatenate_centrelines([self._infos[x].centreline for x in path])

    # ----- point queries --------------------------------------------------

    def inside_matrix(self, points_m) -> np.ndarray:
        """(n, n_lanelets) bool: point k lies inside lanelet `lanelet_ids[j]` (even-odd rule)."""
        points = np.atleast_2d(np.asarray(points_m, dtype=np.float64))
        result = np.zeros((len(points), len(self.lanelet_ids)), dtype=bool)
        if not len(self.lanelet_ids) or not len(points):
            return result
        x0, y0, x1, y1 = (self._edges[:, k][None, :] for k in range(4))
        dy = y1 - y0
        chunk = max(1, 4_000_000 // len(self._edges))
        for start in range(0, len(points), chunk):
            px = points[start : start + chunk, 0:1]
            py = points[start : start + chunk, 1:2]
            straddles = (y0 > py) != (y1 > py)
            with np.errstate(divide="ignore", invalid="ignore"):
                x_cross = x0 + (x1 - x0) * (py - y0) / dy
            crossings = (straddles & (px < x_cross)).astype(np.int32)
            counts = np.add.reduceat(crossings, self._edge_starts, axis=1)
            result[start : start + chunk] = (counts % 2) == 1
        return result

    def lanelets_containing(self, points_m) -> list[tuple[int, ...]]:
        """For each point (n, 2), the ids of the car lanelets that contain it."""
        ids = np.asarray(self.lanelet_ids, dtype=np.int64)
        return [tuple(int(x) for x in ids[row]) for row in self.inside_matrix(points_m)]

    def share_inside(self, points_m) -> float:
        """Share of points (n, 2) inside any car lanelet; the alignment measure."""
        inside = self.inside_matrix(points_m)
        return float(inside.any(axis=1).mean()) if len(inside) else 0.0

    # ----- relations ------------------------------------------------------

    def relation(self, lanelet_a_id: int, lanelet_b_id: int) -> Conflict | None:
        """The crossing, merge or divergence between two lanelets, oriented a to b."""
        key = (min(lanelet_a_id, lanelet_b_id), max(lanelet_a_id, lanelet_b_id))
        found = self._relations.get(key)
        if found is None or found.lanelet_a_id == lanelet_a_id:
            return found
        return found.swapped()

    def conflict(self, lanelet_a_id: int, lanelet_b_id: int) -> Conflict | None:
        """Like `relation`, but only CROSSING and MERGE."""
        found = self.relation(lanelet_a_id, lanelet_b_id)
        return found if found is not None and found.is_conflict else None

    def conflicts(self, *, include_divergences: bool = False) -> tuple[Conflict, ...]:
        """All pair relations, each once with a < b."""
        return tuple(r for r in self._relations.values() if include_divergences or r.is_conflict)

    def conflicts_of(self, lanelet_id: int) -> tuple[Conflict, ...]:
        """The CROSSING and MERGE conflicts of a lanelet, oriented with it as a."""
        return tuple(
            self.relation(lanelet_id, b if a == lanelet_id else a) for a, b in self._conflict_keys[lanelet_id]
        )

    def intersections(self) -> tuple[Intersection, ...]:
        return self._intersections

    def intersection_of(self, lanelet_id: int) -> Intersection | None:
        return self._intersection_of.get(lanelet_id)

    # ----- right of way ---------------------------------------------------

    def priority(self, lanelet_a_id: int, lanelet_b_id: int) -> int:
        """+1 if lanelet a has right of way over b, -1 if b over a, 0 if equal or unknown."""
        return self.priority_with_rule(lanelet_a_id, lanelet_b_id)[0]

    def priority_with_rule(self, lanelet_a_id: int, lanelet_b_id: int) -> tuple[int, PriorityRule]:
        """`priority` and the rule (module docstring) that decided it."""
        a, b = lanelet_a_id, lanelet_b_id
        if a == b:
            return 0, PriorityRule.EQUAL
        regulatory = self._regulatory_priority(a, b)
        if regulatory is not None:
            return regulatory, PriorityRule.REGULATORY
        info_a, info_b = self._infos[a], self._infos[b]
        approach = float(wrap_angle_rad(info_b.centreline.heading_rad[0] - info_a.centreline.heading_rad[0]))
        if abs(approach) >= math.radians(135.0):
            left_a, left_b = info_a.turn is Turn.LEFT, info_b.turn is Turn.LEFT
            if left_a != left_b:
                return (-1 if left_a else 1), PriorityRule.ONCOMING_TURN
            return 0, PriorityRule.EQUAL
        if abs(approach) > math.radians(45.0):
            rank_a, rank_b = self._road_rank(a), self._road_rank(b)
            if rank_a is not None and rank_b is not None and rank_a != rank_b:
                return (1 if rank_a > rank_b else -1), PriorityRule.ROAD_CLASS
            return (-1 if approach > 0.0 else 1), PriorityRule.RIGHT_BEFORE_LEFT
        turn_a, turn_b = abs(info_a.turn_angle_rad), abs(info_b.turn_angle_rad)
        if abs(turn_a - turn_b) > math.radians(15.0):
            return (1 if turn_a < turn_b else -1), PriorityRule.LESS_TURNING
        return 0, PriorityRule.EQUAL

    def _with_approaches(self, lanelet_id: int) -> tuple[int, ...]:
        return (lanelet_id,) + self._predecessors[lanelet_id]

    def _regulatory_priority(self, a: int, b: int) -> int | None:
        group_a, group_b = self._with_approaches(a), self._with_approaches(b)
        if not any(self._has_regulation[x] for x in group_a + group_b):
            return None
        row_a = set().union(*(self._right_of_way[x] for x in group_a))
        row_b = set().union(*(self._right_of_way[x] for x in group_b))
        yield_a = set().union(*(self._yields_in[x] for x in group_a))
        yield_b = set().union(*(self._yields_in[x] for x in group_b))
        if row_a & yield_b:
            return 1
        if row_b & yield_a:
            return -1
        stops_a = set().union(*(self._all_way_stops[x] for x in group_a))
        stops_b = set().union(*(self._all_way_stops[x] for x in group_b))
        if stops_a & stops_b:
            return 0
        sign_a = any(self._has_stop_sign[x] for x in group_a)
        sign_b = any(self._has_stop_sign[x] for x in group_b)
        if sign_a != sign_b:
            return -1 if sign_a else 1
        return None

    def _road_rank(self, lanelet_id: int) -> tuple[int, int] | None:
        tags = {str(k): str(v) for k, v in dict(self._lanelets[lanelet_id].attributes).items()}
        if "highway" not in tags and "priority_road" not in tags:
            return None
        highway = tags.get("highway", "").removesuffix("_link")
        designated = tags.get("priority_road", "").lower() in ("designated", "yes")
        return (int(designated), _HIGHWAY_RANK.get(highway, 1))


def _merge_start_m(s_m: np.ndarray, distance_m: np.ndarray, overlap_m: float) -> float:
    """First arc length from which `distance_m` stays below `overlap_m` to the end."""
    apart = np.nonzero(distance_m >= overlap_m)[0]
    if not len(apart):
        return 0.0
    k = apart[-1]
    if k == len(s_m) - 1:
        return float(s_m[-1])
    d0, d1 = distance_m[k], distance_m[k + 1]
    frac = (d0 - overlap_m) / max(d0 - d1, 1e-12)
    return float(s_m[k] + frac * (s_m[k + 1] - s_m[k]))


def _divergence_end_m(s_m: np.ndarray, distance_m: np.ndarray, overlap_m: float) -> float:
    """Last arc length up to which `distance_m` stays below `overlap_m` from the start."""
    reversed_s = s_m[-1] - s_m[::-1]
    return float(s_m[-1] - _merge_start_m(reversed_s, distance_m[::-1], overlap_m))


def _projector(projection: Projection, origin_lat_deg: float, origin_lon_deg: float):
    origin = ll_io.Origin(origin_lat_deg, origin_lon_deg)
    if projection is Projection.LOCAL_CARTESIAN:
        return ll_projection.LocalCartesianProjector(origin)
    if projection is Projection.SCALED_MERCATOR:
        return ll_projection.MercatorProjector(origin)
    if projection is Projection.UTM:
        return ll_projection.UtmProjector(origin)
    raise ValueError(f"no projector for {projection}")


def parse_projection(value: Projection | str) -> Projection:
    """A Projection from itself or its name, case-insensitive; UNKNOWN if unrecognised."""
    if isinstance(value, Projection):
        return value
    return Projection.__members__.get(str(value).strip().upper(), Projection.UNKNOWN)


def load_map(
    osm_path: str | Path,
    origin_lat_deg: float,
    origin_lon_deg: float,
    projection: Projection | str = Projection.LOCAL_CARTESIAN,
    *,
    probe_positions_m=None,
    offset_m: tuple[float, float] = (0.0, 0.0),
    default_speed_limit_mps: float = DEFAULT_SPEED_LIMIT_MPS,
    resample_step_m: float = 0.5,
    smoothing_m: float = 1.0,
) -> tuple[RoadMap | None, list[MapProblem]]:
    """Load a Lanelet2 OSM file into the metric frame of a recording, robustly.

    The map is projected with `projection` at the origin and shifted so that
    the origin is (0, 0), then by `offset_m`. `Projection.AUTO` loads it with
    each candidate projection and keeps the one that puts most of
    `probe_positions_m` ((n, 2) car positions in the recording's frame) inside
    a car lanelet; the shares are in `RoadMap.projection_shares`. The map is
    None only when nothing could be read; parser messages and build problems
    come back as `MapProblem`s.
    """
    chosen = parse_projection(projection)
    problems: list[MapProblem] = []
    if not (
        math.isfinite(origin_lat_deg)
        and math.isfinite(origin_lon_deg)
        and -90.0 < origin_lat_deg < 90.0
        and -180.0 <= origin_lon_deg <= 180.0
    ):
        problems.append(
            MapProblem(MapProblemKind.BAD_ARGUMENT, f"origin {origin_lat_deg}, {origin_lon_deg} is not a position")
        )
        return None, problems
    if chosen is Projection.UNKNOWN:
        problems.append(MapProblem(MapProblemKind.BAD_ARGUMENT, f"unknown projection {projection!r}"))
        return None, problems
    if chosen is Projection.AUTO:
        probes = None if probe_positions_m is None else np.asarray(probe_positions_m, dtype=np.float64)
        if probes is None or probes.ndim != 2 or probes.shape[1] != 2 or not len(probes):
            problems.append(
                MapProblem(MapProblemKind.BAD_ARGUMENT, "projection AUTO needs probe_positions_m of shape (n, 2)")
            )
            return None, problems
        best: tuple[RoadMap | None, list[MapProblem]] = (None, problems)
        shares = []
        for candidate in _AUTO_CANDIDATES:
            road_map, found = load_map(
                osm_path,
                origin_lat_deg,
                origin_lon_deg,
                candidate,
                offset_m=offset_m,
                default_speed_limit_mps=default_speed_limit_mps,
                resample_step_m=resample_step_m,
                smoothing_m=smoothing_m,
            )
            if road_map is None:
                return None, found
            shares.append((candidate, road_map.share_inside(probes)))
            if best[0] is None or shares[-1][1] > max(s for _, s in shares[:-1]):
                best = (road_map, found)
        best[0].projection_shares = tuple(shares)
        return best
    path = Path(osm_path)
    if not path.is_file():
        problems.append(MapProblem(MapProblemKind.FILE_NOT_FOUND, f"no map file at {path}"))
        return None, problems
    projector = _projector(chosen, origin_lat_deg, origin_lon_deg)
    try:
        lanelet_map, errors = ll_io.loadRobust(str(path), projector)
    except RuntimeError as error:
        problems.append(MapProblem(MapProblemKind.UNREADABLE, f"lanelet2 could not read {path}: {error}"))
        return None, problems
    problems.extend(
        MapProblem(MapProblemKind.PARSE_ERROR, message.strip().removeprefix("- "))
        for message in errors
        if not message.startswith("Errors ocurred while parsing")
    )
    origin_xy = projector.forward(ll_core.GPSPoint(origin_lat_deg, origin_lon_deg, 0.0))
    shift_x = float(offset_m[0]) - origin_xy.x
    shift_y = float(offset_m[1]) - origin_xy.y
    if shift_x or shift_y:
        _shift_map(lanelet_map, shift_x, shift_y)
    road_map = RoadMap(
        lanelet_map,
        projection=chosen,
        default_speed_limit_mps=default_speed_limit_mps,
        resample_step_m=resample_step_m,
        smoothing_m=smoothing_m,
    )
    return road_map, problems + list(road_map.build_problems)


def _shift_map(lanelet_map, shift_x_m: float, shift_y_m: float) -> None:
    """Move every point of a freshly loaded map; `RoadMap` builds new spatial indices."""
    for point in lanelet_map.pointLayer:
        point.x = point.x + shift_x_m
        point.y = point.y + shift_y_m
    for lanelet in lanelet_map.laneletLayer:
        lanelet.resetCache()

