"""Map matching for the corridors stage: which car lanelets a vehicle may be on.

`LaneletIndex` holds the static geometry of a `RoadMap` as padded numpy arrays
(centreline segments, polygon edges, widths), so that one call measures every
vehicle of a frame against every car lanelet at once. `select_lanelets` then
applies the matching rule of the package docstring to one vehicle.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from stages.lib.maps import RoadMap, kernels, wrap_angle_rad

INSIDE = 0
"""Candidate level: the position lies inside the lanelet's polygon."""
NEAR = 1
"""Candidate level: outside the polygon but within `match_max_distance_m` of it."""
ENTRY_EXTENSION = 2
"""Candidate level: on the straight backward extension of a lanelet without predecessor."""


@dataclass(frozen=True, slots=True, eq=False)
class Measurements:
    """Every vehicle of a frame against every car lanelet; arrays (n_vehicles, n_lanelets).

    `s_m` is the arc length of the centreline foot point (clipped to the
    lanelet; negative on an entry extension), `d_m` the signed lateral offset
    (left positive), `centre_distance_m` the distance to the centreline (or to
    the backward extension for level ENTRY_EXTENSION), `heading_rad` the
    centreline heading at the foot, `level` INSIDE / NEAR / ENTRY_EXTENSION or
    -1 (not a candidate by position).
    """

    s_m: np.ndarray
    d_m: np.ndarray
    centre_distance_m: np.ndarray
    heading_rad: np.ndarray
    level: np.ndarray
    candidates: tuple = ()  # per point, `candidates_by_point`'s lists (empty: `select_lanelets` reads the arrays)


def candidates_by_point(meas: Measurements, ids: np.ndarray) -> tuple:
    """Per point, its candidate columns by position (level >= 0) as plain lists: (columns, lanelet ids, centre distance,
    heading, level, s, d), from one ``nonzero`` over the frame (what `select_lanelets` reads, without numpy calls per vehicle)."""
    rows, cols = np.nonzero(meas.level >= 0)
    bounds = np.searchsorted(rows, np.arange(meas.level.shape[0] + 1)).tolist()
    columns = (
        cols.tolist(), ids[cols].tolist(), meas.centre_distance_m[rows, cols].tolist(), meas.heading_rad[rows, cols].tolist(),
        meas.level[rows, cols].tolist(), meas.s_m[rows, cols].tolist(), meas.d_m[rows, cols].tolist(),
    )
    return tuple(tuple(c[a:b] for c in columns) for a, b in zip(bounds[:-1], bounds[1:]))


class LaneletIndex:
    """Padded per-lanelet geometry of a `RoadMap` for vectorised matching."""

    def __init__(self, road_map: RoadMap) -> None:
        self.road_map = road_map
        self.ids = np.asarray(road_map.lanelet_ids, dtype=np.int64)
        self.column = {int(x): k for k, x in enumerate(self.ids)}
        infos = [road_map.lanelet(int(x)) for x in self.ids]
        n = len(infos)
        self.widths_m = np.array([i.width_m for i in infos])
        self.lengths_m = np.array([i.length_m for i in infos])
        n_seg = max((len(i.centreline.s_m) - 1 for i in infos), default=1)
        self.seg_start = np.zeros((n, n_seg, 2))
        self.seg_vec = np.zeros((n, n_seg, 2))
        self.seg_s0 = np.zeros((n, n_seg))
        self.seg_heading = np.zeros((n, n_seg))
        self.seg_valid = np.zeros((n, n_seg), dtype=bool)
        n_edge = max((len(i.left_bound_m) + len(i.right_bound_m) for i in infos), default=1)
        self.edge_start = np.zeros((n, n_edge, 2))
        self.edge_vec = np.zeros((n, n_edge, 2))
        self.edge_valid = np.zeros((n, n_edge), dtype=bool)
        for k, info in enumerate(infos):
            line = info.centreline
            pts = line.points_m
            m = len(pts) - 1
            self.seg_start[k, :m] = pts[:-1]
            self.seg_vec[k, :m] = np.diff(pts, axis=0)
            self.seg_s0[k, :m] = line.s_m[:-1]
            self.seg_heading[k, :m] = np.arctan2(self.seg_vec[k, :m, 1], self.seg_vec[k, :m, 0])
            self.seg_valid[k, :m] = True
            polygon = np.concatenate([info.left_bound_m, info.right_bound_m[::-1]])
            e = len(polygon)
            self.edge_start[k, :e] = polygon
            self.edge_vec[k, :e] = np.roll(polygon, -1, axis=0) - polygon
            self.edge_valid[k, :e] = True
        self.seg_count = self.seg_valid.sum(axis=1).astype(np.int64)  # the valid segments are a prefix of each row
        self.edge_count = self.edge_valid.sum(axis=1).astype(np.int64)
        self.seg_len2 = np.maximum((self.seg_vec**2).sum(axis=2), 1e-18)
        self.edge_len2 = np.maximum((self.edge_vec**2).sum(axis=2), 1e-18)
        # bounding box of each lanelet's polygon and centreline: a point farther than max_distance_m from it is
        # neither inside nor near the lanelet, so `measure` computes nothing else for it
        corners = [np.concatenate([i.left_bound_m, i.right_bound_m, i.centreline.points_m]).reshape(-1, 2) for i in infos]
        self.box_lo = np.array([c.min(axis=0) for c in corners]).reshape(n, 2)
        self.box_hi = np.array([c.max(axis=0) for c in corners]).reshape(n, 2)
        self.is_entry = np.array([not road_map.predecessors(int(x)) for x in self.ids], dtype=bool)
        self.start_xy = np.array([i.centreline.points_m[0] for i in infos]).reshape(n, 2)
        self.start_heading = np.array([i.centreline.heading_rad[0] for i in infos])

    def columns_of(self, lanelet_ids) -> np.ndarray:
        """Mask (n_lanelets,) of the columns of the given lanelet ids (ids the index lacks are ignored): ``np.isin(ids, ...)``."""
        mask = np.zeros(len(self.ids), dtype=bool)
        mask[[self.column[x] for x in lanelet_ids if x in self.column]] = True
        return mask

    def measure(
        self, points_m: np.ndarray, *, max_distance_m: float, entry_extension_m: float, compiled: bool = True
    ) -> Measurements:
        """Measure points (n, 2) against every lanelet (one `inside_matrix` call).

        Only a (point, lanelet) inside the lanelet or within ``max_distance_m``
        of its bounding box is measured against its centreline and polygon;
        the others (level -1, unless on an entry extension) get NaN s, d,
        centre distance and heading, which no selection reads. With
        `compiled` (and numba) the kernel ``maps.kernels.measure_lanelets``
        measures them, the numpy code's values bit for bit (that code
        stays as the reference and the fallback).
        """
        p = np.asarray(points_m, dtype=np.float64).reshape(-1, 2)
        n_pts, n_l = len(p), len(self.ids)
        inside = self.road_map.inside_matrix(p) if n_pts else np.zeros((0, n_l), dtype=bool)
        grow = max_distance_m + 1e-6
        near_box = ((p[:, None, :] >= self.box_lo[None] - grow) & (p[:, None, :] <= self.box_hi[None] + grow)).all(axis=2)
        pi, li = np.nonzero(near_box | inside)
        s = np.full((n_pts, n_l), np.nan)
        d = np.full((n_pts, n_l), np.nan)
        centre = np.full((n_pts, n_l), np.nan)
        heading = np.full((n_pts, n_l), np.nan)
        poly_dist = np.full((n_pts, n_l), np.inf)
        measured = len(pi) and compiled and kernels.measure_lanelets(
            p, np.ascontiguousarray(pi), np.ascontiguousarray(li), self.seg_start, self.seg_vec, self.seg_len2, self.seg_s0, self.seg_heading, self.seg_count,
            self.edge_start, self.edge_vec, self.edge_len2, self.edge_count, s, d, centre, heading, poly_dist,
        )
        if len(pi) and not measured:
            # centreline foot points, clipped to each lanelet (the candidates only; the same arithmetic per element)
            rel = p[pi][:, None, :] - self.seg_start[li]
            t = np.clip((rel * self.seg_vec[li]).sum(axis=2) / self.seg_len2[li], 0.0, 1.0)
            diff = rel - t[..., None] * self.seg_vec[li]
            dist2 = np.where(self.seg_valid[li], (diff**2).sum(axis=2), np.inf)
            j = dist2.argmin(axis=1)
            c = np.arange(len(pi))
            centre[pi, li] = np.sqrt(dist2[c, j])
            tj = t[c, j]
            seg_len = np.sqrt(self.seg_len2[li, j])
            s[pi, li] = self.seg_s0[li, j] + tj * seg_len
            vec = self.seg_vec[li, j]
            r = rel[c, j]
            d[pi, li] = (vec[..., 0] * r[..., 1] - vec[..., 1] * r[..., 0]) / seg_len
            heading[pi, li] = self.seg_heading[li, j]
            # distance to the polygon boundary, for positions outside it
            rel_e = p[pi][:, None, :] - self.edge_start[li]
            te = np.clip((rel_e * self.edge_vec[li]).sum(axis=2) / self.edge_len2[li], 0.0, 1.0)
            de2 = ((rel_e - te[..., None] * self.edge_vec[li]) ** 2).sum(axis=2)
            poly_dist[pi, li] = np.sqrt(np.where(self.edge_valid[li], de2, np.inf).min(axis=1))
        level = np.full((n_pts, n_l), -1, dtype=np.int8)
        level[(poly_dist <= max_distance_m) & ~inside] = NEAR
        level[inside] = INSIDE
        if entry_extension_m > 0.0 and self.is_entry.any():
            # behind the start of an entry lanelet, along its straight backward extension
            ux, uy = np.cos(self.start_heading), np.sin(self.start_heading)
            rx = p[:, 0:1] - self.start_xy[None, :, 0]
            ry = p[:, 1:2] - self.start_xy[None, :, 1]
            s_ext = rx * ux[None] + ry * uy[None]
            d_ext = ux[None] * ry - uy[None] * rx
            on_ext = (
                self.is_entry[None]
                & (level < 0)
                & (s_ext < 0.0)
                & (s_ext >= -entry_extension_m)
                & (np.abs(d_ext) <= 0.5 * self.widths_m[None] + max_distance_m)
            )
            level[on_ext] = ENTRY_EXTENSION
            s = np.where(on_ext, s_ext, s)
            d = np.where(on_ext, d_ext, d)
            centre = np.where(on_ext, np.abs(d_ext), centre)
            heading = np.where(on_ext, self.start_heading[None], heading)
        meas = Measurements(s_m=s, d_m=d, centre_distance_m=centre, heading_rad=heading, level=level)
        return dataclasses.replace(meas, candidates=candidates_by_point(meas, self.ids))


@dataclass(frozen=True, slots=True)
class LaneletMatch:
    """One lanelet a vehicle was matched to, with its Frenet position on it."""

    lanelet_id: int
    level: int
    s_m: float
    d_m: float
    centre_distance_m: float
    heading_error_rad: float


def heading_errors_rad(vehicle_heading_rad: float, lane_heading_rad: np.ndarray, ambiguous: bool) -> np.ndarray:
    """|heading difference|; modulo pi when the vehicle's direction is ambiguous."""
    err = np.abs(wrap_angle_rad(np.asarray(lane_heading_rad) - vehicle_heading_rad))
    return np.minimum(err, math.pi - err) if ambiguous else err


def select_lanelets(
    index: LaneletIndex,
    meas: Measurements,
    row: int,
    *,
    heading_rad: float,
    heading_ambiguous: bool,
    heading_confident: bool,
    heading_known: bool = True,
    allowed: frozenset[int],
    previous: tuple[int, ...] = (),
    max_heading_rad: float,
    ambiguity_margin_m: float,
    continuity_margin_m: float,
) -> tuple[tuple[LaneletMatch, ...], bool]:
    """The lanelets vehicle `row` is matched to, best first, and whether any lay near by position.

    Rule (package docstring): a candidate lies inside, near or on an entry
    extension of the lanelet and agrees in heading; a `previous` lanelet
    that is still a candidate by position counts as agreeing when the
    heading is not confident (no fresh motion) or when nothing else agrees;
    without `heading_known` (a slow car never seen moving) every candidate
    by position counts if none agrees in heading.
    Among the candidates, the lanelets of `allowed` (continuity) win unless
    another lies more than `continuity_margin_m` closer to its centreline (a
    lane change); then
    every candidate within `ambiguity_margin_m` of the best centreline
    distance is kept. A kept lanelet whose predecessor is also kept is
    dropped (the route from the predecessor contains it).
    """
    # only the columns near by position can be candidates: the rule in plain Python over those few (the same
    # float operations as `heading_errors_rad` and the masks over every column would do, value for value)
    if meas.candidates:
        near, ids, centre, lane_headings, levels, s_list, d_list = meas.candidates[row]
    else:
        near = np.flatnonzero(meas.level[row] >= 0).tolist()
        ids = index.ids[near].tolist()
        centre = meas.centre_distance_m[row, near].tolist()
        lane_headings = meas.heading_rad[row, near].tolist()
        levels, s_list, d_list = (a[row, near].tolist() for a in (meas.level, meas.s_m, meas.d_m))
    if not len(near):
        return (), False
    errors = []
    for lane_heading in lane_headings:
        err = abs((lane_heading - heading_rad + math.pi) % (2.0 * math.pi) - math.pi)
        errors.append(min(err, math.pi - err) if heading_ambiguous else err)
    ok = [e <= max_heading_rad for e in errors]
    if previous and (not heading_confident or not any(ok)):
        # a heading glitch (yaw noise of a slow car, a tracker jump) does not move a car out of its lane
        ok = [o or x in previous for o, x in zip(ok, ids)]
    if not heading_known and not any(ok):
        # a standing car seen for the first time: its yaw may be anything (K729), go by position
        ok = [True] * len(ids)
    if not any(ok):
        return (), True
    pool = ok
    if allowed:
        cont = [o and x in allowed for o, x in zip(pool, ids)]
        if any(cont) and min(c for c, o in zip(centre, cont) if o) <= min(c for c, o in zip(centre, pool) if o) + continuity_margin_m:
            pool = cont
    best = min(c for c, o in zip(centre, pool) if o)
    keep = sorted((centre[i], ids[i], i) for i in range(len(ids)) if pool[i] and centre[i] <= best + ambiguity_margin_m)
    kept_ids = {x for _c, x, _i in keep}
    matches = []
    for _c, lanelet_id, i in keep:
        if any(p in kept_ids for p in index.road_map.predecessors(lanelet_id)):
            continue
        matches.append(
            LaneletMatch(
                lanelet_id=lanelet_id,
                level=levels[i],
                s_m=s_list[i],
                d_m=d_list[i],
                centre_distance_m=centre[i],
                heading_error_rad=errors[i],
            )
        )
    return tuple(matches), True
