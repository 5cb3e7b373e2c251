"""Bounded work per message (issue 13): which objects of an oversized frame a stage keeps.

Rule, the same in every stage that caps objects (corridors, relations): the
``max_objects`` objects nearest to the centre of the map (the middle of the
bounding box of its car lanelets' centrelines, where the intersection is)
are kept, ties in frame order; objects with a non-finite position go first.
Without a usable map the centre is the median of the frame's finite
positions. Stages report one ``objects_capped`` issue per capped frame with
the number dropped, and process the kept objects as usual.
"""

from __future__ import annotations

import numpy as np


def map_centre_m(road_map) -> np.ndarray | None:
    """The middle of the bounding box of the map's car-lanelet centrelines, (2,), or None without a map."""
    if road_map is None or not road_map.lanelet_ids:
        return None
    points = np.concatenate([np.asarray(road_map.lanelet(k).centreline.points_m, np.float64) for k in road_map.lanelet_ids])
    points = points[np.isfinite(points).all(axis=1)]
    if not len(points):
        return None
    return 0.5 * (points.min(axis=0) + points.max(axis=0))


def keep_nearest(xy: np.ndarray, centre: np.ndarray | None, max_objects: int) -> tuple[np.ndarray, int]:
    """Mask (n,) of the ``max_objects`` rows of ``xy`` (n, 2) nearest to ``centre``, and how many were dropped."""
    xy = np.asarray(xy, np.float64).reshape(-1, 2)
    n = len(xy)
    if n <= max_objects:
        return np.ones(n, dtype=bool), 0
    finite = np.isfinite(xy).all(axis=1)
    if centre is None:
        centre = np.median(xy[finite], axis=0) if finite.any() else np.zeros(2)
    distance = np.where(finite, np.hypot(xy[:, 0] - centre[0], xy[:, 1] - centre[1]), np.inf)
    keep = np.zeros(n, dtype=bool)
    keep[np.argsort(distance, kind="stable")[:max_objects]] = True
    return keep, n - max_objects


def cap_pairs(corridor_set, max_pairs: int):
    """``(corridor_set, dropped_pairs)``: whole vehicles in CorridorSet order while their pairs fit in ``max_pairs``.

    The vehicles beyond become BAD_STATE entries without corridors (skipped
    this frame), so a stage downstream of corridors (intentions,
    ar_inference, markov_prediction) does bounded work; the set is returned
    unchanged when it fits.
    """
    import dataclasses

    from bus_schemas import MatchStatus

    total = sum(len(v.corridors) for v in corridor_set.vehicles)
    if total <= max_pairs:
        return corridor_set, 0
    used, full, vehicles = 0, False, []
    for vehicle in corridor_set.vehicles:
        if vehicle.corridors and (full or used + len(vehicle.corridors) > max_pairs):
            full = True
            vehicles.append(dataclasses.replace(vehicle, status=MatchStatus.BAD_STATE, corridors=()))
            continue
        used += len(vehicle.corridors)
        vehicles.append(vehicle)
    return dataclasses.replace(corridor_set, vehicles=tuple(vehicles)), total - used
