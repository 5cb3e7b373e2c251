"""Relations stage: what surrounds each vehicle on each of its corridors (docs/method.md §5).

Consumes ``track_frame`` (``TrackFrame``) and ``corridor_set``
(``CorridorSet``) of the same stamp, and the latched ``scene``
(``SceneInfo``); produces ``relation_set`` (``RelationSet``): one
``CorridorRelations`` per (vehicle, corridor) pair, in CorridorSet order.
Run it alone with ``python -m stages.relations``.

Parameters (``RelationsConfig``):

- ``lateral_margin_m`` 0.5: an object is in the lane when |d| < half the
  corridor's width at its s + this margin;
- ``lookahead_m`` 100, ``lookbehind_m`` 20: and its s lies within this far
  ahead of the vehicle (never past the corridor's end) or behind it (behind
  the corridor's start, on the straight extension of its first segment);
- ``leader_max_heading_rad`` π/3, ``stopped_speed_mps`` 0.5: who may lead;
- ``horizon_s`` 4.0, ``horizon_margin_s`` 2.0: the influencing rule takes
  conflicts whose other vehicle arrives within 4 s + 2 s;
- ``min_time_speed_mps`` 1.0: times to a conflict are distance / max(v, 1);
- ``clear_margin_m`` 0.5: a vehicle has cleared a conflict point once its
  centre is half its length + this margin past it;
- ``duplicate_conflict_m`` 1.0: points of one corridor pair closer than this
  along the corridor are one (a crossing reached through two lanelet pairs at
  a lanelet join);
- ``refine_window_m`` 3.0: on a corridor that changes lane (consecutive
  lanelets that are not successors) the arc lengths of its conflict points
  are refined by projecting the point onto the corridor within this far of
  the lookup value (the blended centreline leaves the lanelets' own);
- ``min_route_probability`` 0.1: other corridors less likely than this do not
  influence (applies when the intentions give route probabilities, see
  ``RelationExtractor.process``);
- ``max_objects`` 200 and ``max_pairs`` 600: bounded work per frame
  (issue 13). Beyond ``max_objects`` the objects nearest to the map's
  centre are kept (the corridors stage's rule, ``stages.lib.caps``) and the
  others are neither vehicles nor obstacles this frame (one
  ``objects_capped`` issue); beyond ``max_pairs`` whole vehicles are kept
  in CorridorSet order while their corridors fit, the rest get no relation
  (one ``pairs_capped`` issue). TAF-BW frames (at most ~20 vehicles, ~2
  corridors each) are never capped. Memory: the projection of objects onto
  corridors is pruned by distance (only objects inside a corridor's
  bounding box grown by lookbehind + half width + margin are projected, and
  not those provably farther than half width + margin from it; each point is
  measured only against the blocks of 8 segments that can hold its nearest
  segment) and chunked, never one dense (pairs, objects, segments, 2) array (which ran
  out of memory on a large frame; README, Security). Budget: <= 1 GB peak RSS on a
  1,000-object frame (``bench/hostile.py --section big-frame``);
- ``projection`` "auto": as in the corridors stage, whose map loader
  (``stages.corridors.SceneMaps``) this stage uses, so both see one map.
- ``data`` "": the local data folder whose ``maps/`` holds the scene's map,
  found by name and checked by sha256 as in the corridors stage (the
  launcher passes its ``--data``; "" the embedded ``stages/data/taf-bw``).

Map. Loaded when the scene's ``scene_id`` changes; ``SceneTables`` then turns
the map's precomputed lanelet conflicts (``RoadMap.conflicts``), right of
way (``RoadMap.priority``) and intersections into arrays, once per map.
Without a usable map (no scene yet, unreadable file) only the lateral
relation is filled, with a ``no_map`` issue per frame.

Objects. Every object of the TrackFrame with a finite position is an
obstacle (vehicles, pedestrians, cyclists, unknown). A length that is not
finite and positive is the dataset default for the type. A matched
vehicle's heading is its first corridor's heading at its position and its
speed the corridors stage's; other objects use the velocity direction (yaw
below ``stopped_speed_mps``) and the reported speed (0 with a
``nan_velocity`` issue when not finite).

Lateral relation (arrays ``(o,)``, ordered by s). All objects are projected
onto all corridors' centrelines in one call (the projection of
``maps.project_to_polyline``: nearest segment, ends extended straight; by
branch and bound over blocks of segments, exact), compiled
(``maps.kernels.project_polylines``; the padded numpy computation is its
reference and fallback); the lane, range and leader tests run over every
pair at once; those within the lane and range above are kept with s, d, the
speed along the corridor (speed × cos of the heading difference) and the
bumper-to-bumper
gap: g = s_o − s_v − (L_o + L_v)/2 ahead (s_o ≥ s_v), s_o − s_v + (L_o +
L_v)/2 behind, clipped at 0 (0: they overlap along the corridor, negative:
behind). A car on another branch of the corridor tree drops out once the
branches are more than the lane margin apart, by its |d|. The leader is the
object ahead with the smallest gap among those heading along the corridor
(within ``leader_max_heading_rad``) or standing still; crossing traffic and
pedestrians walking across are listed but do not lead (the corridor-to-
corridor relation handles crossing vehicles).

Corridor to intersection (arrays ``(q,)``). Each run of consecutive corridor
lanelets that are members of one intersection (``RoadMap.intersections``):
entry s = the first member's start in the corridor + its member entry arc
length (its first conflict point), exit s likewise with the last member's
exit; the distance is entry − s_v (negative once inside); the entry lanelet
is the first member lanelet of the run. Intersections whose exit the vehicle
has passed are left out.

Corridor to corridor (arrays ``(c,)``, ordered by s). Every lanelet of
every corridor is joined with the lanelets of every other vehicle's
corridors that it conflicts with (``SceneTables.conflict_with``, the sparse
form of ``pair_first``: work in proportion to the pairs found): a CROSSING or
MERGE of the map gives s* = the lanelet's start in the corridor + the arc
length within it, on both corridors; merges are at the merge start, where the
lanes begin to overlap (``stages.lib.maps``); divergences are not conflicts.
Kept: points within both corridors that neither vehicle has cleared, and not
after a lanelet the two corridors share (a shared prefix with a later
divergence is a following relation); one point per corridor pair within
``duplicate_conflict_m``. Per point: s on both, x, y (the map's point: where
the centrelines cross; for a merge the midpoint of the two merge starts,
about half a lane width off each centreline), kind, the distance of each
vehicle to it, the other's speed, T = distance / max(v, 1) for both, and the
priority of this corridor's lanelet over the other's. A point is listed once
per pair of corridors, so a vehicle with two corridors through it appears
twice.

Influencing corridor: ``influence.choose_influencing`` (rules
``priority_other``, ``merge_ahead_other``, ``equal_first_other``, ``none``);
``influence.most_influencing`` gives the two most influencing vehicles for
the AR features.

Issues (the other pairs are still processed): ``stamp_mismatch`` (the two
messages differ in stamp: no output), ``missing_track`` (a vehicle with
corridors absent from the TrackFrame), ``missing_corridors`` (an object of
the TrackFrame absent from the CorridorSet: obstacle only), ``nan_state``,
``nan_velocity``, ``duplicate_track``, ``bad_corridor`` (fewer than two
points, non-finite values, zero length), ``no_map``, ``map_problem``,
``scene_mismatch``.
"""

from __future__ import annotations

from stages.relations.core import RelationExtractor, RelationsConfig, SceneTables
from stages.lib.influence import RULES, choose_influencing, most_influencing, rank_conflicts

__all__ = [
    "RULES",
    "INPUTS",
    "OUTPUTS",
    "SPEC",
    "RelationExtractor",
    "RelationsConfig",
    "SceneTables",
    "choose_influencing",
    "main",
    "most_influencing",
    "rank_conflicts",
]

_BINDING = ("SPEC", "INPUTS", "OUTPUTS", "main", "make_core")


def __getattr__(name: str):
    """The binding lives in ``__main__.py``; importing it pulls in the runtime (zenoh) only when asked."""
    if name in _BINDING:
        from stages.relations import __main__ as binding

        return getattr(binding, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
