"""Relations between car lanelets: crossings, merges, divergences, and the intersections they form.

`find_relations` refines a road map's candidate pairs with the smoothed
centrelines and `find_intersections` clusters the conflicting lanelets;
`RoadMap` runs both once when it is built and answers the queries
(`RoadMap.relation`, `conflicts_of`, `intersection_of`).

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
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np

from stages.lib.maps.geometry import _distance_to_polyline_m, segment_intersections, wrap_angle_rad


class ConflictKind(enum.Enum):
    UNKNOWN = 0
    CROSSING = 1
    MERGE = 2
    DIVERGE = 3



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


def find_relations(lanelet_ids, infos, successors, predecessors, lanelet2_conflicts) -> dict[tuple[int, int], Conflict]:
    """The relations of every candidate pair (module docstring), keyed (a, b) with a < b.

    `infos` maps a lanelet id to its `LaneletInfo`; `successors`, `predecessors`
    and `lanelet2_conflicts` map it to the ids the routing graph relates it to.
    """
    candidates: set[tuple[int, int]] = set()
    for a, others in lanelet2_conflicts.items():
        candidates.update((min(a, b), max(a, b)) for b in others)
    for groups in (successors, predecessors):
        for members in groups.values():
            candidates.update((a, b) for a in members for b in members if a < b)
    ids = np.asarray(lanelet_ids)
    for end in (0, -1):
        ends = np.array([infos[x].centreline.points_m[end] for x in lanelet_ids]).reshape(-1, 2)
        close = np.hypot(*(ends[:, None, :] - ends[None, :, :]).transpose(2, 0, 1)) < 0.5
        i, j = np.nonzero(np.triu(close, k=1))
        candidates.update((int(min(ids[p], ids[q])), int(max(ids[p], ids[q]))) for p, q in zip(i, j))
    relations = {}
    for a, b in sorted(candidates):
        relation = relate(a, b, infos, successors, predecessors)
        if relation is not None:
            relations[(a, b)] = relation
    return relations


def relate(a: int, b: int, infos, successors, predecessors) -> Conflict | None:
    """The crossing, merge or divergence of lanelets a and b (module docstring), or None."""
    info_a, info_b = infos[a], infos[b]
    line_a, line_b = info_a.centreline, info_b.centreline
    pts_a, pts_b = line_a.points_m, line_b.points_m
    overlap_m = 0.5 * (info_a.width_m + info_b.width_m)
    touch_m = 0.5
    merge = bool(set(successors[a]) & set(successors[b])) or (
        np.hypot(*(pts_a[-1] - pts_b[-1])) < touch_m
    )
    diverge = not merge and (
        bool(set(predecessors[a]) & set(predecessors[b])) or np.hypot(*(pts_a[0] - pts_b[0])) < touch_m
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


def find_intersections(lanelet_ids, infos, relations) -> tuple[tuple[Intersection, ...], dict[int, Intersection]]:
    """The intersections, numbered in lanelet order, and the intersection of each member lanelet."""
    index = {lanelet_id: k for k, lanelet_id in enumerate(lanelet_ids)}
    parent = {lanelet_id: lanelet_id for lanelet_id in lanelet_ids}

    def root(x: int) -> int:
        while parent[x] != x:
            parent[x] = parent[parent[x]]
            x = parent[x]
        return x

    spans: dict[int, list[float]] = {}
    for (a, b), relation in relations.items():
        if not relation.is_conflict:
            continue
        parent[root(a)] = root(b)
        for lanelet_id, values in (
            (a, [p.s_a_m for p in relation.points]),
            (b, [p.s_b_m for p in relation.points]),
        ):
            if relation.kind is ConflictKind.MERGE:
                values = values + [infos[lanelet_id].length_m]
            spans.setdefault(lanelet_id, []).extend(values)
    clusters: dict[int, list[int]] = {}
    for lanelet_id in lanelet_ids:
        if lanelet_id in spans:
            clusters.setdefault(root(lanelet_id), []).append(lanelet_id)
    ordered = sorted(clusters.values(), key=lambda ids: min(index[x] for x in ids))
    result = []
    for number, ids in enumerate(ordered):
        members = tuple(
            IntersectionMember(
                lanelet_id,
                float(max(0.0, min(spans[lanelet_id]))),
                float(min(infos[lanelet_id].length_m, max(spans[lanelet_id]))),
            )
            for lanelet_id in sorted(ids, key=index.get)
        )
        result.append(Intersection(number, members))
    intersection_of = {m.lanelet_id: x for x in result for m in x.members}
    return tuple(result), intersection_of
