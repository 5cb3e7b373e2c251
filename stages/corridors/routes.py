"""Routes and corridor geometry for the corridors stage (docs/method.md §5, §5.5).

A *route* is a lanelet sequence from a start lanelet without lane changes,
run to a dead end or to at least `route_length_m` (`RoadMap.possible_paths`),
optionally with one predecessor in front. The map is static, so `RouteCache`
builds each route's joined centreline once. `cut_corridor` samples a route
between `behind_m` behind and `ahead_m` ahead of the vehicle on a uniform
grid, extending the centreline straight before its start and past its end.
"""

from __future__ import annotations

import bisect
import hashlib
import math
from dataclasses import dataclass, field

import numpy as np

from bus_schemas import Corridor
from stages.lib.maps import Centreline, RoadMap, kernels, project_in_window, wrap_angle_rad


@dataclass(frozen=True, slots=True, eq=False)
class RouteGeometry:
    """A route's joined centreline; arrays (m,) float64 except where noted.

    `lanelet_start_s_m` (k,) is where each lanelet begins along the route and
    `lanelet_end_s_m` (k,) where it ends; `heading_unwrapped_rad` is
    continuous so it can be interpolated.
    """

    lanelet_ids: tuple[int, ...]
    lanelet_start_s_m: np.ndarray
    lanelet_end_s_m: np.ndarray
    widths_m: np.ndarray
    speed_limits_mps: np.ndarray
    points_m: np.ndarray
    s_m: np.ndarray
    heading_unwrapped_rad: np.ndarray
    curvature_1pm: np.ndarray
    samples_table: np.ndarray = field(init=False, repr=False)  # (4, m) x, y, heading, curvature: `cut_corridor`'s kernel
    end_directions: tuple[float, float, float, float] = field(init=False, repr=False)  # cos, sin of the first and last heading
    lanelet_id_array: np.ndarray = field(init=False, repr=False)  # `lanelet_ids` (k,) int64
    # the per-lanelet arrays as tuples of floats, for the per-frame code that reads a few of them (no numpy call per read)
    lanelet_starts: tuple[float, ...] = field(init=False, repr=False)
    lanelet_ends: tuple[float, ...] = field(init=False, repr=False)
    speed_limits: tuple[float, ...] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        table = np.ascontiguousarray(np.stack([self.points_m[:, 0], self.points_m[:, 1], self.heading_unwrapped_rad, self.curvature_1pm]))
        first, last = float(self.heading_unwrapped_rad[0]), float(self.heading_unwrapped_rad[-1])
        object.__setattr__(self, "samples_table", table)
        object.__setattr__(self, "end_directions", (math.cos(first), math.sin(first), math.cos(last), math.sin(last)))
        object.__setattr__(self, "lanelet_id_array", np.asarray(self.lanelet_ids, dtype=np.int64))
        object.__setattr__(self, "lanelet_starts", tuple(self.lanelet_start_s_m.tolist()))
        object.__setattr__(self, "lanelet_ends", tuple(self.lanelet_end_s_m.tolist()))
        object.__setattr__(self, "speed_limits", tuple(self.speed_limits_mps.tolist()))

    def lanelet_at(self, s_m: float) -> int:
        """Index of the lanelet at route s (the last one starting at or before it, clipped to the route's lanelets):
        ``clip(searchsorted(lanelet_start_s_m, s, "right") - 1, 0, k - 1)``, NaN past the end as there."""
        return min(max(bisect.bisect_right(self.lanelet_starts, s_m) - 1, 0), len(self.lanelet_starts) - 1)

    @property
    def length_m(self) -> float:
        return float(self.s_m[-1])


def route_hash(lanelet_ids: tuple[int, ...]) -> int:
    """A 63-bit id for a lanelet sequence (blake2b of the ids; stable across runs)."""
    data = ",".join(str(x) for x in lanelet_ids).encode()
    return int.from_bytes(hashlib.blake2b(data, digest_size=8).digest(), "big") >> 1


class RouteCache:
    """Routes per start lanelet and geometry per route, built on first use.

    With `lane_changes`, a route may also switch once, at a lanelet boundary,
    into a same-direction neighbour of the next lanelet (an *adjacent
    successor*: leaving a turn into the other exit lane, drifting into the
    next lane through the intersection). Its centreline blends from the
    successor it leaves to the neighbour over `lane_change_length_m` (at
    most 80 % of the neighbour's length), smoothstep in the lateral weight.
    """

    def __init__(
        self, road_map: RoadMap, route_length_m: float, *, lane_changes: bool = False, lane_change_length_m: float = 20.0
    ) -> None:
        self.road_map = road_map
        self.route_length_m = route_length_m
        self.lane_changes = lane_changes
        self.lane_change_length_m = lane_change_length_m
        self._paths: dict[tuple[int, int], tuple[tuple[int, ...], ...]] = {}
        self._geometry: dict[tuple[int, ...], RouteGeometry] = {}
        self._adjacent: dict[int, tuple[tuple[int, int], ...]] = {}

    def adjacent_successors(self, lanelet_id: int) -> tuple[tuple[int, int], ...]:
        """(neighbour, via): same-direction left/right neighbours of the successors `via`, not successors themselves."""
        found = self._adjacent.get(lanelet_id)
        if found is None:
            rm = self.road_map
            successors = set(rm.successors(lanelet_id))
            pairs = []
            for via in sorted(successors):
                heading = rm.lanelet(via).centreline.heading_rad[0]
                nb = rm.neighbours(via)
                for other in (nb.left_id, nb.right_id):
                    if other is None or other in successors or other == lanelet_id or not rm.has_lanelet(other):
                        continue
                    if abs(float(wrap_angle_rad(rm.lanelet(other).centreline.heading_rad[0] - heading))) > math.pi / 4:
                        continue
                    pairs.append((other, via))
            found = tuple(pairs)
            self._adjacent[lanelet_id] = found
        return found

    def routes_from(self, lanelet_id: int, min_length_m: float) -> tuple[tuple[int, ...], ...]:
        """Routes from a lanelet reaching `max(route_length_m, min_length_m)` or a dead end.

        The length is rounded up to multiples of `route_length_m` so that the
        cache stays small and the routes do not change with the speed. Routes
        without a lane change come first.
        """
        return self.routes_for(lanelet_id, self.length_steps(min_length_m))

    def length_steps(self, min_length_m: float) -> int:
        """The length class of `routes_from`: routes reach `steps` times `route_length_m` (at least once)."""
        return max(1, math.ceil(min_length_m / self.route_length_m))

    def routes_for(self, lanelet_id: int, steps: int) -> tuple[tuple[int, ...], ...]:
        """`routes_from` by length class (`length_steps`)."""
        key = (lanelet_id, steps)
        found = self._paths.get(key)
        if found is None:
            target = steps * self.route_length_m
            paths = list(self.road_map.possible_paths(lanelet_id, target))
            if self.lane_changes:
                seen = set(paths)
                for path in list(paths):
                    before = 0.0
                    for i in range(1, len(path)):
                        before += self.road_map.lanelet(path[i - 1]).length_m
                        for other, via in self.adjacent_successors(path[i - 1]):
                            if via != path[i] or other in path[:i]:
                                continue
                            for tail in self.road_map.possible_paths(other, max(target - before, 1.0)):
                                variant = path[:i] + tail
                                if variant not in seen and len(set(variant)) == len(variant):
                                    seen.add(variant)
                                    paths.append(variant)
            found = tuple(paths)
            self._paths[key] = found
        return found

    def geometry(self, lanelet_ids: tuple[int, ...]) -> RouteGeometry:
        found = self._geometry.get(lanelet_ids)
        if found is None:
            found = self._build(lanelet_ids)
            self._geometry[lanelet_ids] = found
        return found

    def _lane_change(self, previous: np.ndarray, previous_id: int, lanelet_id: int) -> tuple[np.ndarray, np.ndarray]:
        """Blend a lane change around the join of `previous_id` (points `previous`) and `lanelet_id`.

        `lanelet_id` is a neighbour of `via`, a successor of `previous_id`. The
        lateral weight w rises by smoothstep over `lane_change_length_m`,
        centred on the join (at most half of each lanelet's length on each
        side): before the join the previous centreline is shifted sideways by
        w times the offset between the two lanes' starts; after it the points
        are (1 - w) on `via` and w on the neighbour, at equal length fractions.
        Returns the new previous points and the neighbour's points.
        """
        rm = self.road_map
        target = rm.lanelet(lanelet_id).centreline
        via = next((v for other, v in self.adjacent_successors(previous_id) if other == lanelet_id), None)
        if via is None:
            return previous, target.points_m
        source = rm.lanelet(via).centreline
        seg = np.diff(previous, axis=0)
        arc = np.concatenate([[0.0], np.cumsum(np.hypot(seg[:, 0], seg[:, 1]))])
        pre_m = min(0.5 * self.lane_change_length_m, 0.5 * arc[-1])
        post_m = max(min(0.5 * self.lane_change_length_m, 0.8 * target.length_m), 1e-6)
        total = pre_m + post_m

        def weight(u):
            u = np.clip(u, 0.0, 1.0)
            return u * u * (3.0 - 2.0 * u)

        heading0 = float(source.heading_rad[0])
        offset = np.array([target.x_m[0] - source.x_m[0], target.y_m[0] - source.y_m[0]])
        lateral = -math.sin(heading0) * offset[0] + math.cos(heading0) * offset[1]
        shifted = previous.copy()
        if pre_m > 0.0:
            w = weight((arc - (arc[-1] - pre_m)) / total)
            tangent = np.gradient(previous, axis=0)
            tangent /= np.maximum(np.hypot(tangent[:, 0], tangent[:, 1]), 1e-12)[:, None]
            normal = np.column_stack([-tangent[:, 1], tangent[:, 0]])
            shifted = previous + (w * lateral)[:, None] * normal
        fraction = target.s_m / max(target.length_m, 1e-9)
        s_source = fraction * source.length_m
        from_x = np.interp(s_source, source.s_m, source.x_m)
        from_y = np.interp(s_source, source.s_m, source.y_m)
        w = weight((pre_m + target.s_m) / total)
        blended = np.column_stack([(1.0 - w) * from_x + w * target.x_m, (1.0 - w) * from_y + w * target.y_m])
        return shifted, blended

    def _build(self, lanelet_ids: tuple[int, ...]) -> RouteGeometry:
        rm = self.road_map
        infos = [rm.lanelet(x) for x in lanelet_ids]
        parts, first_index, count = [], [], 0
        for k, info in enumerate(infos):
            pts = info.centreline.points_m
            if k and lanelet_ids[k] not in rm.successors(lanelet_ids[k - 1]):
                parts[-1], pts = self._lane_change(parts[-1], lanelet_ids[k - 1], lanelet_ids[k])
            if parts and np.hypot(*(pts[0] - parts[-1][-1])) < 1e-6:
                first_index.append(count - 1)
                pts = pts[1:]
            else:
                first_index.append(count)
            parts.append(pts)
            count += len(pts)
        line = Centreline.from_resampled(np.concatenate(parts))
        starts = np.asarray(line.s_m)[first_index]
        ends = np.append(starts[1:], line.length_m)
        return RouteGeometry(
            lanelet_ids=tuple(lanelet_ids),
            lanelet_start_s_m=starts,
            lanelet_end_s_m=ends,
            widths_m=np.array([i.width_m for i in infos]),
            speed_limits_mps=np.array([i.speed_limit_mps for i in infos]),
            points_m=line.points_m,
            s_m=np.asarray(line.s_m),
            heading_unwrapped_rad=np.unwrap(line.heading_rad),
            curvature_1pm=np.asarray(line.curvature_1pm),
        )


def project_vehicle(route: RouteGeometry, xy_m, s_hint_m: float, window_m: float) -> tuple[float, float]:
    """Frenet (s, d) of a position on a route, searching within `window_m` of `s_hint_m` first (`maps.project_in_window`)."""
    x, y = (float(v) for v in xy_m) if len(xy_m) == 2 else np.asarray(xy_m, dtype=np.float64).reshape(2).tolist()
    found = kernels.project_point(x, y, route.points_m, route.s_m, s_hint_m, window_m)
    if found is not None:  # the kernel of project_in_window, called with numbers
        return float(found[0]), float(found[1])
    s, d = project_in_window(np.asarray(xy_m, dtype=np.float64).reshape(1, 2), route.points_m, route.s_m, s_hint_m, window_m)
    return float(s[0]), float(d[0])


def cut_corridor(
    route: RouteGeometry,
    *,
    corridor_id: int,
    vehicle_s_m: float,
    vehicle_d_m: float,
    behind_m: float,
    ahead_m: float,
    step_m: float,
    compiled: bool = True,
) -> Corridor:
    """Sample a route from `behind_m` behind to `ahead_m` ahead of the vehicle.

    The grid is uniform (`step_m`) and starts at the corridor's s = 0, so the
    vehicle sits at s = `behind_m` on every corridor of a vehicle and their
    samples can be compared index by index. Before the route's start and past
    its end the centreline continues straight with the end heading, zero
    curvature and the end lanelet's width. With `compiled` (and numba) the
    samples come from the kernel `maps.kernels.sample_route`, the numpy
    code's values bit for bit (`_sample` keeps that code as the reference
    and the fallback).
    """
    n = int(math.ceil((behind_m + ahead_m) / step_m - 1e-9)) + 1
    offset = vehicle_s_m - behind_m
    s_corridor, x, y, heading_wrapped, curvature, width = _sample(route, offset, step_m, n, compiled)
    end_s = offset + (n - 1) * step_m  # the last sample's s on the route
    # the lanelets the samples cover (the first one if none does), in plain Python over the route's few lanelets
    covered = [i for i, (a, b) in enumerate(zip(route.lanelet_starts, route.lanelet_ends)) if a < end_s and b > offset] or [0]
    limits = [route.speed_limits[i] for i in covered]
    if covered[-1] - covered[0] + 1 == len(covered):  # a run (the usual case): sliced, copied (what the indexing gives)
        covered = slice(covered[0], covered[-1] + 1)
    return Corridor(
        corridor_id=int(corridor_id),
        lanelet_ids=route.lanelet_id_array[covered].copy(),
        lanelet_start_s_m=route.lanelet_start_s_m[covered] - offset,
        x_m=x,
        y_m=y,
        s_m=s_corridor,
        heading_rad=heading_wrapped,
        curvature_1pm=curvature,
        width_m=width,
        extension_start_s_m=float(min(route.length_m - offset, end_s - offset)),
        vehicle_s_m=float(vehicle_s_m - offset),
        vehicle_d_m=float(vehicle_d_m),
        speed_limit_mps=math.nan if any(v != v for v in limits) else min(limits),  # as ndarray.min: NaN if any is
    )


def _sample(route: RouteGeometry, offset: float, step_m: float, n: int, compiled: bool = True):
    """The corridor's arrays (n,) at route s = offset + i·step (`cut_corridor`): s from the corridor's start, x, y,
    heading wrapped to [-pi, pi), curvature, width."""
    if compiled:
        found = kernels.sample_route(route.samples_table, route.s_m, route.lanelet_start_s_m, route.widths_m, offset, step_m, n,
                                     route.end_directions)
        if found is not None:
            return found
    h_first, h_last = float(route.heading_unwrapped_rad[0]), float(route.heading_unwrapped_rad[-1])
    s_route = offset + np.arange(n) * step_m
    s_line = route.s_m
    pts = route.points_m
    x = np.interp(s_route, s_line, pts[:, 0])
    y = np.interp(s_route, s_line, pts[:, 1])
    heading = np.interp(s_route, s_line, route.heading_unwrapped_rad)
    curvature = np.interp(s_route, s_line, route.curvature_1pm)
    for beyond, s_end, k, h in ((s_route < 0.0, 0.0, 0, h_first), (s_route > route.length_m, route.length_m, -1, h_last)):
        if beyond.any():
            x = np.where(beyond, pts[k, 0] + (s_route - s_end) * math.cos(h), x)
            y = np.where(beyond, pts[k, 1] + (s_route - s_end) * math.sin(h), y)
            curvature = np.where(beyond, 0.0, curvature)
    which = np.clip(np.searchsorted(route.lanelet_start_s_m, s_route, side="right") - 1, 0, len(route.lanelet_ids) - 1)
    heading_wrapped = (heading + math.pi) % (2.0 * math.pi) - math.pi
    return s_route - offset, x, y, heading_wrapped, curvature, route.widths_m[which].astype(np.float64)


def max_separation_m(a: Corridor, b: Corridor, from_index: int) -> float:
    """Largest distance between samples of equal index from `from_index` on (same grids)."""
    found = kernels.max_separation(a.x_m, a.y_m, b.x_m, b.y_m, from_index)
    if found is not None:  # the kernel: the same distances, their max
        return float(found)
    n = min(len(a.x_m), len(b.x_m))
    if from_index >= n:
        return 0.0
    dx = a.x_m[from_index:n] - b.x_m[from_index:n]
    dy = a.y_m[from_index:n] - b.y_m[from_index:n]
    return float(np.sqrt(dx * dx + dy * dy).max())
