"""Corridors stage: the routes each vehicle may follow (docs/method.md §5.4 corridor generation, §5.5).

Consumes ``track_frame`` (``TrackFrame``) and the latched ``scene``
(``SceneInfo``: map file, origin, projection); produces ``corridor_set``
(``CorridorSet``): one ``VehicleCorridors`` entry per object of the frame, in
frame order, never dropped. Run it alone with ``python -m stages.corridors``.

Parameters (``CorridorsConfig``; lengths in m, angles in rad):

- ``horizon_s`` 4.0, ``a_plan_mps2`` 2.0, ``extra_length_m`` 10.0: a corridor
  reaches ``v0·T + ½·a_plan·T² + extra`` ahead of the vehicle (T = horizon),
  so the Markov mass cannot run off its end (docs/method.md §5, §5.4);
  ``behind_m`` 5.0: it starts that far behind the vehicle;
  ``resample_step_m`` 0.5: its centreline sampling.
- ``match_max_distance_m`` 1.5, ``match_max_heading_rad`` 0.8,
  ``ambiguity_margin_m`` 1.0, ``continuity_margin_m`` 1.0,
  ``entry_extension_m`` 50.0: matching (below).
- ``max_objects`` 200: bounded work per frame (issue 13; TAF-BW frames hold
  at most ~20 objects): beyond it the objects nearest to the map's centre
  are kept (``stages.lib.caps``: the middle of the car lanelets' bounding box,
  where the intersection is; non-finite positions dropped first) and the
  others become BAD_STATE entries without corridors, nothing computed for
  them, with one ``objects_capped`` issue per frame giving how many.
- ``merge_tolerance_m`` 1.0, ``max_corridors_per_vehicle`` 8 (enforced:
  beyond it the corridors are dropped after merging, issue
  ``corridors_truncated``),
  ``route_length_m`` 150.0, ``frenet_window_m`` 10.0,
  ``lane_change_corridors`` true, ``lane_change_length_m`` 20.0: corridors
  (below).
- ``heading_window_s`` 1.0, ``heading_min_travel_m`` 2.0,
  ``yaw_agreement_rad`` 0.5: the heading used for matching;
  ``track_timeout_s`` 2.0: per-track state is dropped after that long unseen
  (by stamps).
- ``fuse_reported_velocity`` true: the kinematic state (``VehicleCorridors``
  speed, velocity, acceleration, standing) comes from
  ``stages.lib.kinematic_state.KinematicEstimator``: positions, with the
  tracker's velocity fused once it is calibrated against them; false uses
  positions alone.
- ``state_accel_noise_bank`` [1, 3, 10]: the estimator runs one filter per
  acceleration noise (m²/s³) and publishes the one whose speed has best
  predicted the distance covered 2 s later, over the stream so far (starting
  with 10; ``[10]`` is the single filter).
- ``projection`` "auto": the scene's projection, and for "auto" there the
  measured one for its location (``maps.projection_for_location``: UTM for
  K729, scaled Mercator for K733).

- ``data`` "": the local data folder whose ``maps/`` holds the maps (the
  launcher passes its ``--data``; "" the embedded ``stages/data/taf-bw``).

Map. Loaded when the latched scene's ``scene_id`` changes (never per frame),
from the local data folder only (``stages.lib.maps.local_map_file``): the scene's
``map_name`` must be a plain file name (no separator, no ``..``) equal to an
entry of ``<data>/maps``, a regular file of at most 256 MB whose sha256 equals
the scene's ``map_sha256`` (checked before parsing); nothing on the bus names
a path to open. A map that cannot be used (invalid name, not found, too large,
another hash, failed to load) is cached (by map name, hash, projection and
origin; 32 scenes at most) and never retried:
``map_problem``/``map_sha256_mismatch`` once on load, then one ``no_map``
issue per frame and every vehicle OFF_MAP. The relations, intentions and
viewer stages resolve the map the same way (their own ``data`` parameter).

Objects. Non-vehicles (pedestrians, bicycles, UNKNOWN with an
``unknown_type`` issue) are NOT_A_VEHICLE without corridors: obstacles for the
relations. A frame whose objects are all UNKNOWN also has one ``all_untyped``
issue (agent -1): nothing of it is predicted. A vehicle whose position, or both speed and heading, cannot be
known is BAD_STATE (issue ``bad_state``); a repeated track id is BAD_STATE
(``duplicate_track``). Stopped vehicles get corridors like any other.

Heading for matching. The track's own motion: the chord from the newest
earlier position at least ``heading_min_travel_m`` (2 m: standing K733 cars
jitter by up to 0.8 m) away within ``heading_window_s``; the reported yaw
replaces it when they agree within ``yaw_agreement_rad`` (less lag). A
stopped vehicle keeps its last motion heading. With no motion yet the yaw is
used, matched modulo pi when it disagrees with the reported velocity (in
K733 the reported velocity points against the motion and the yaw is right
only about half the time). A car below 1 m/s never seen moving has no usable
heading (the K729 yaw of a standing car drifts by up to 90 degrees): if no
lanelet agrees with its yaw, it is matched by position alone.

Matching (one measurement of every vehicle against every car lanelet per
frame, ``matching.LaneletIndex``, compiled: ``maps.kernels``; a vehicle farther than
``match_max_distance_m`` from a lanelet's bounding box is not measured
against its centreline and polygon: it can be neither inside nor near). A candidate lanelet agrees in
heading within ``match_max_heading_rad`` and holds the position: inside its
polygon, outside but within ``match_max_distance_m`` of it, or on the
straight backward extension (up to ``entry_extension_m``, lateral offset
within half the width plus ``match_max_distance_m``) of a lanelet without
predecessor. The last matches vehicles on a lane whose first part the map
lacks (K733's fourth lane on Ostring's south-west approach, which continues
as lanelet -103591; without it K733's coverage drops sharply, measured:
docs/method.md §5.3) or
arriving from beyond the map's edge. If no lanelet agrees in heading, or the
heading is stale, the previous lanelets that are still candidates by
position count as agreeing (a heading glitch: the K733 tracker sometimes
moves a standing car back by 4 m, reporting 15 m/s).
Continuity: the previous frame's lanelets, their successors (two levels) and
their siblings (other successors of their predecessors) win over the other
candidates, so a vehicle in the intersection does not jump between
overlapping lanelets, unless another lies more than ``continuity_margin_m``
closer to its centreline (a lane change). Then every candidate whose
centreline distance is within ``ambiguity_margin_m`` of the best is kept
(e.g. the straight and the turning lanelet side by side or overlapping at
the intersection entrance): each becomes a corridor start. A kept lanelet
whose predecessor is kept too is dropped (the predecessor's routes contain
it). No candidate: OFF_MAP with issue ``off_map`` (nothing near) or
``off_map_heading`` (lanelets near, none in the vehicle's direction).
``VehicleCorridors.lanelet_id`` is the best match and ``match_distance_m``
its distance to that lanelet's centreline (or backward extension).

Routes. From each matched lanelet, every route (``RoadMap.possible_paths``,
no lane changes) to a dead end or ``route_length_m`` (more if the vehicle
needs it), with the predecessor in front when the corridor starts before the
lanelet (the one the vehicle came from: previously matched or routed, else
nearest to where the track was ``behind_m`` ago, else the straightest).
With ``lane_change_corridors``, also the routes that switch once, at a
lanelet boundary ahead, into a same-direction neighbour of the next lanelet
(an "adjacent successor": a turn into the other exit lane, drifting into the
next lane through the intersection), blended over ``lane_change_length_m``
centred on the boundary (``routes.RouteCache``). The TAF-BW maps route each
turn into one exit lane only; drivers use both, so these routes raise the
4 s coverage for somewhat more corridors per car (measured: docs/method.md
§5.4; README, Stages). A lane-change route is
dropped when the vehicle already has a plain route ending along the same
lanes (it was matched to both neighbouring lanes).

Geometry. A route's joined centreline is cached per lanelet sequence (the
map is static). The corridor samples it every ``resample_step_m`` from
``behind_m`` behind to the length above ahead of the vehicle; before the
route's start and past its end (the map's end) the centreline continues
straight: ``extension_start_s_m`` marks the end part, and
``lanelet_start_s_m[0] > 0`` a start part (``< 0`` when the first lanelet
begins before the corridor). The vehicle sits at ``vehicle_s_m =
behind_m``; its s is found by projecting onto the route within
``frenet_window_m`` of its previous s on the same corridor (continuity,
docs/method.md §5.5), and ``vehicle_d_m`` is its lateral offset.
``lanelet_ids`` are the lanelets the sampled part covers,
``speed_limit_mps`` their lowest limit, ``width_m`` the covering lanelet's
mean width. The projection and the sampling run in compiled kernels
(``stages.lib.maps.kernels``, loaded when the core is made: about 1 s once
per process), the same values bit for bit as the numpy code they replace
(kept as their reference and fallback; ``bench/upstream.py --check``
compares whole CorridorSets and RelationSets with a saved run).

Merge rule. Two corridors of a vehicle whose samples, from the vehicle to the
corridor end (the horizon length), stay within ``merge_tolerance_m`` of each
other (equal index = equal arc length from the vehicle) are one: parallel
overlapping lanelets, or routes that branch only beyond the vehicle's reach
(docs/method.md §7.6). The one kept is the one emitted last frame, else the one
with the longer mapped part, else the better match.

corridor_id. A route (lanelet sequence from the matched lanelet) inherits
the id of the previous matched frame's route of the same track that it
continues consistently (one is a suffix-consistent continuation of the
other), taken by largest overlap, each old id once. Otherwise it gets a
63-bit blake2b hash of its lanelet ids. So the id survives the vehicle
moving into the next lanelet (the route loses its first lanelet), the route
growing at its far end, merges and short OFF_MAP spells (state lives
``track_timeout_s``). Ids are per vehicle: (track_id, corridor_id) names a
corridor.

Per-track plan. The routes of a vehicle, the redundant lane changes
dropped and the ids inherited depend only on its matched lanelets, the
predecessors put in front, the route length class and its previous routes
with their ids; the track keeps that plan with this key (by content) and a
frame re-uses it while the key repeats (most frames: a vehicle stays on its
lanelets), so only the projection and the sampling run per frame. A
changed key (another lanelet, a re-used track id elsewhere) plans afresh;
the plan goes with the track after ``track_timeout_s``.
"""

from __future__ import annotations

from stages.corridors.core import CorridorBuilder, CorridorsConfig
from stages.lib.maps import SceneMap, SceneMaps, resolve_projection  # the library's scene-map cache, still importable from here

__all__ = ["CorridorBuilder", "CorridorsConfig", "SceneMap", "SceneMaps", "resolve_projection", "SPEC", "INPUTS", "OUTPUTS", "main"]

_BINDING = ("SPEC", "INPUTS", "OUTPUTS", "main", "make_core")


def __getattr__(name: str):
    """The binding lives in ``__main__.py``; importing it pulls in the runtime (zenoh) only when asked."""
    if name in _BINDING:
        from stages.corridors import __main__ as binding

        return getattr(binding, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
