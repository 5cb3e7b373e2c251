"""The road map: the car lanelets of a Lanelet2 map with routing, geometry and relations.

`RoadMap` holds, for the lanelets a car may drive (`io.is_car_lanelet`), the
lanelet2 vehicle routing graph, smoothed centrelines with arc length, heading
and curvature, point-in-lanelet queries, the precomputed conflicts and
intersections (`conflicts`) and the right of way (`priority`). `load_map`
reads a file (`io.read_osm`) and builds one, robustly: problems are returned,
never raised. Germany's vehicle traffic rules accept lanelets with no subtype;
a car lanelet that the rules reject anyway gets `participant:vehicle=yes` on
the in-memory map, so that routing works, and a ROUTING_OVERRIDE problem. The
routing graph is built from a submap of the car lanelets only.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
from lanelet2 import core as ll_core
from lanelet2 import routing as ll_routing
from lanelet2 import traffic_rules as ll_traffic_rules

from stages.lib.maps.conflicts import Conflict, Intersection, find_intersections, find_relations
from stages.lib.maps.geometry import Centreline, _frozen, _polygon_area_m2, concatenate_centrelines, wrap_angle_rad
from stages.lib.maps.io import MapProblem, MapProblemKind, is_car_lanelet, read_osm
from stages.lib.maps.priority import PriorityRule, RightOfWay, Turn, turn_of
from stages.lib.maps.projection import _AUTO_CANDIDATES, Projection, parse_projection

DEFAULT_SPEED_LIMIT_MPS = 50.0 / 3.6
_MIN_LANELET_LENGTH_M = 0.05


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
        self._relations = find_relations(
            self.lanelet_ids, self._infos, self._successors, self._predecessors, self._lanelet2_conflicts
        )
        self._conflict_keys: dict[int, list[tuple[int, int]]] = {x: [] for x in self.lanelet_ids}
        for key, relation in self._relations.items():
            if relation.is_conflict:
                self._conflict_keys[key[0]].append(key)
                self._conflict_keys[key[1]].append(key)
        self._intersections, self._intersection_of = find_intersections(self.lanelet_ids, self._infos, self._relations)
        self._right_of_way = RightOfWay(self._lanelets, self._predecessors, self._infos)

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
        turn = turn_of(turn_angle)
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
        """`priority` and the rule (`stages.lib.maps.priority`) that decided it."""
        return self._right_of_way.priority_with_rule(lanelet_a_id, lanelet_b_id)


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
    lanelet_map, read_problems = read_osm(osm_path, origin_lat_deg, origin_lon_deg, chosen, offset_m=offset_m)
    problems.extend(read_problems)
    if lanelet_map is None:
        return None, problems
    road_map = RoadMap(
        lanelet_map,
        projection=chosen,
        default_speed_limit_mps=default_speed_limit_mps,
        resample_step_m=resample_step_m,
        smoothing_m=smoothing_m,
    )
    return road_map, problems + list(road_map.build_problems)

