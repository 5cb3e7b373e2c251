"""The pure part of the relations stage: `RelationsConfig`, `SceneTables` and `RelationExtractor`.

See the package docstring for the rules; nothing here touches the bus or the
wall clock.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Mapping

import numpy as np

from bus_schemas import (
    AgentType,
    ConflictKind,
    Corridor,
    CorridorRelations,
    CorridorSet,
    Header,
    RelationSet,
    SceneInfo,
    SignalState,
    TrackFrame,
    VehicleCorridors,
)
from stages.lib.base import ConfigMixin, Issue, StageResult, check_ranges
from stages.lib.caps import keep_nearest, map_centre_m
from stages.lib.datasets import DEFAULT_SIZES_M
from stages.lib.maps import ConflictKind as MapConflictKind
from stages.lib.maps import Projection, RoadMap, SceneMap, SceneMaps, kernels, parse_projection, project_in_window, shown_map_name, wrap_angle_rad

from stages.lib.influence import NO_INFLUENCE, RULES, choose_influencing, choose_influencing_grouped
from stages.relations.signals import SignalStops

_KIND_ON_BUS = {MapConflictKind.CROSSING: ConflictKind.CROSSING, MapConflictKind.MERGE: ConflictKind.MERGE}


@dataclass(frozen=True, kw_only=True)
class RelationsConfig(ConfigMixin):
    """Parameters of the relations stage (package docstring, docs/method.md §5)."""

    lateral_margin_m: float = 0.5
    lookahead_m: float = 100.0
    lookbehind_m: float = 20.0
    leader_max_heading_rad: float = math.pi / 3.0
    stopped_speed_mps: float = 0.5
    horizon_s: float = 4.0
    horizon_margin_s: float = 2.0
    min_time_speed_mps: float = 1.0
    clear_margin_m: float = 0.5
    duplicate_conflict_m: float = 1.0
    refine_window_m: float = 3.0
    min_route_probability: float = 0.1
    max_objects: int = 200
    max_pairs: int = 600
    projection: str = "auto"
    data: str = ""  # local data folder whose maps/ holds the scene's map (by name); "": the embedded stages/data/taf-bw

    def __post_init__(self) -> None:
        positive = ("horizon_s", "min_time_speed_mps", "leader_max_heading_rad")
        non_negative = ("lateral_margin_m", "lookahead_m", "lookbehind_m", "stopped_speed_mps", "horizon_margin_s",
                        "clear_margin_m", "duplicate_conflict_m", "refine_window_m", "min_route_probability")
        check_ranges(self, positive=positive, non_negative=non_negative)
        for name in ("max_objects", "max_pairs"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} = {getattr(self, name)}: must be >= 1")
        if self.min_route_probability > 1.0:
            raise ValueError(f"min_route_probability = {self.min_route_probability!r}: must be <= 1")
        if parse_projection(self.projection) is Projection.UNKNOWN:
            known = ", ".join(p.name.lower() for p in Projection if p is not Projection.UNKNOWN)
            raise ValueError(f"projection = {self.projection!r}: expected one of {known}")

    @property
    def conflict_horizon_s(self) -> float:
        """Bound on the other vehicle's time to a conflict for the influencing rule (4 s + 2 s)."""
        return self.horizon_s + self.horizon_margin_s


# --------------------------------------------------------------------------- per-map tables


class SceneTables:
    """The map's lanelet relations as arrays, built once per map: per frame, conflicts are lookups.

    Lanelets are numbered 0..n-1 in `RoadMap.lanelet_ids` order; index n
    stands for any id the map does not know. `pair_first[a, b]` is the first
    row of the point table for lanelets a and b (oriented: s on a, then on
    b), -1 if they do not conflict, and `pair_count[a, b]` the number of
    points. Point rows (p,): `point_kind` (bus ConflictKind values),
    `point_s_a_m`, `point_s_b_m`, `point_x_m`, `point_y_m` and
    `point_priority` (``RoadMap.priority(a, b)``: +1 when a has right of
    way). Per lanelet (n + 1,): `intersection_id` (-1 if none) and the
    member's `entry_s_m`/`exit_s_m`; `is_successor[a, b]` (n + 1, n + 1)
    tells whether b follows a in the routing graph.
    """

    def __init__(self, road_map: RoadMap) -> None:
        self.road_map = road_map
        ids = road_map.lanelet_ids
        n = len(ids)
        self.n_lanelets = n
        self._index = {lanelet_id: k for k, lanelet_id in enumerate(ids)}
        order = np.argsort(np.asarray(ids, dtype=np.int64), kind="stable")
        self._sorted_ids = np.asarray(ids, dtype=np.int64)[order]  # `indices`' sorted lookup: the ids ascending, their index
        self._sorted_index = order.astype(np.int64)
        self.pair_first = np.full((n + 1, n + 1), -1, dtype=np.int32)
        self.pair_count = np.zeros((n + 1, n + 1), dtype=np.int32)
        rows: list[tuple[int, float, float, float, float, int]] = []
        for conflict in road_map.conflicts():
            for a, b in ((conflict.lanelet_a_id, conflict.lanelet_b_id), (conflict.lanelet_b_id, conflict.lanelet_a_id)):
                oriented = road_map.conflict(a, b)
                if oriented is None or oriented.kind not in _KIND_ON_BUS:
                    continue
                i, j = self._index[a], self._index[b]
                self.pair_first[i, j] = len(rows)
                self.pair_count[i, j] = len(oriented.points)
                priority = road_map.priority(a, b)
                kind = int(_KIND_ON_BUS[oriented.kind])
                rows.extend((kind, p.s_a_m, p.s_b_m, p.x_m, p.y_m, priority) for p in oriented.points)
        table = np.array(rows, dtype=np.float64).reshape(-1, 6)
        self.point_kind = table[:, 0].astype(np.uint8)
        self.point_s_a_m = table[:, 1].copy()
        self.point_s_b_m = table[:, 2].copy()
        self.point_x_m = table[:, 3].copy()
        self.point_y_m = table[:, 4].copy()
        self.point_priority = table[:, 5].astype(np.int8)
        # the same relation sparse, per lanelet a: the lanelets b it conflicts with (ascending), CSR over a = 0..n
        conflict_a, conflict_b = np.nonzero(self.pair_first >= 0)
        self.conflict_indptr = np.searchsorted(conflict_a, np.arange(n + 2)).astype(np.int64)
        self.conflict_with = conflict_b.astype(np.int64)
        self.is_successor = np.zeros((n + 1, n + 1), dtype=bool)
        for lanelet_id in ids:
            for succ in road_map.successors(lanelet_id):
                self.is_successor[self._index[lanelet_id], self._index[succ]] = True
        self.intersection_id = np.full(n + 1, -1, dtype=np.int64)
        self.entry_s_m = np.full(n + 1, np.nan)
        self.exit_s_m = np.full(n + 1, np.nan)
        for intersection in road_map.intersections():
            for member in intersection.members:
                k = self._index[member.lanelet_id]
                self.intersection_id[k] = intersection.intersection_id
                self.entry_s_m[k] = member.entry_s_m
                self.exit_s_m[k] = member.exit_s_m

    def indices(self, lanelet_ids) -> np.ndarray:
        """Table indices (k,) int64 of lanelet ids; unknown ids map to `n_lanelets`.

        An int64 array (the bus type) is looked up by one sorted search, anything else id by id (the same indices)."""
        if isinstance(lanelet_ids, np.ndarray) and lanelet_ids.dtype == np.int64 and lanelet_ids.ndim == 1 and self.n_lanelets:
            k = np.minimum(np.searchsorted(self._sorted_ids, lanelet_ids), self.n_lanelets - 1)
            return np.where(self._sorted_ids[k] == lanelet_ids, self._sorted_index[k], self.n_lanelets)
        return np.fromiter((self._index.get(int(x), self.n_lanelets) for x in lanelet_ids), dtype=np.int64)


# --------------------------------------------------------------------------- per-frame inputs


@dataclass(frozen=True, slots=True, eq=False)
class _Objects:
    """Every object of the frame, arrays (n,); `valid` marks finite positions (first row of a track id)."""

    track_ids: np.ndarray
    types: np.ndarray
    xy: np.ndarray
    length_m: np.ndarray
    speed_mps: np.ndarray
    heading_rad: np.ndarray
    speed_known: np.ndarray
    valid: np.ndarray


@dataclass(slots=True, eq=False)
class _Pair:
    """One (vehicle, corridor) to relate; `g` numbers the pairs of the frame."""

    g: int
    vehicle: VehicleCorridors
    corridor: Corridor
    row: int
    speed_mps: float
    length_m: float
    xy: np.ndarray
    lanelet_index: np.ndarray
    follows_lanelets: bool
    width_max_m: float = math.nan  # the corridor's widest width


@dataclass(slots=True, eq=False)
class _Conflicts:
    """Every conflict of the frame from the view of pair `g`, arrays (c,), sorted by (g, s)."""

    g: np.ndarray
    other_g: np.ndarray
    kind: np.ndarray
    s_m: np.ndarray
    other_s_m: np.ndarray
    x_m: np.ndarray
    y_m: np.ndarray
    distance_m: np.ndarray
    other_distance_m: np.ndarray
    other_speed_mps: np.ndarray
    time_s: np.ndarray
    other_time_s: np.ndarray
    priority: np.ndarray


def _heading_at(corridor: Corridor, s_m: float) -> float:
    """The corridor's heading at s: its unwrapped heading interpolated, wrapped (the kernel where it can, numpy else)."""
    found = kernels.unwrapped_interp(s_m, corridor.s_m, corridor.heading_rad)
    if found is None:
        found = np.interp(s_m, corridor.s_m, np.unwrap(corridor.heading_rad))
    return float(wrap_angle_rad(found))


def _corridor_problem(corridor: Corridor) -> str | None:
    """Why a corridor cannot be related, or None."""
    arrays = (corridor.x_m, corridor.y_m, corridor.s_m, corridor.heading_rad, corridor.width_m)
    if len(corridor.x_m) < 2 or any(len(a) != len(corridor.x_m) for a in arrays):
        return f"{len(corridor.x_m)} centreline points"
    if not all(np.isfinite(a).all() for a in arrays):
        return "non-finite centreline values"
    if not corridor.s_m[-1] - corridor.s_m[0] > 0.0 or (np.diff(corridor.s_m) < 0.0).any():
        return f"length {corridor.s_m[-1] - corridor.s_m[0]:.2f} m (zero or s not increasing)"
    if not math.isfinite(corridor.vehicle_s_m):
        return f"vehicle_s_m = {corridor.vehicle_s_m}"
    if len(corridor.lanelet_ids) != len(corridor.lanelet_start_s_m) or not np.isfinite(corridor.lanelet_start_s_m).all():
        return "lanelet_ids and lanelet_start_s_m disagree"
    return None


_EMPTY_I64 = np.zeros(0, dtype=np.int64)
_EMPTY_F64 = np.zeros(0, dtype=np.float64)


def _checked_corridors(corridor_set: CorridorSet, tables: SceneTables | None) -> dict[int, tuple]:
    """Per corridor of the set (by ``id``): (`_corridor_problem`, table indices of its lanelets, whether they follow each other).

    All corridors of the frame at once: one finiteness test and one
    arc-length test over their concatenated arrays, the lanelet ids mapped
    by one sorted lookup; a corridor these say is sound has no problem
    (the conditions of `_corridor_problem`), any other is asked
    `_corridor_problem` itself for its message; if anything here raises,
    every corridor is checked one by one.
    """
    corridors = [c for v in corridor_set.vehicles for c in v.corridors]
    try:
        return _checked_batch(corridors, tables)
    except Exception:  # noqa: BLE001 - odd arrays: corridor by corridor, as `_corridor_problem` handles them
        out = {}
        for corridor in corridors:
            problem = _corridor_problem(corridor)
            if problem is not None:
                out[id(corridor)] = (problem, _EMPTY_I64, True)
                continue
            lanelet_index = tables.indices(corridor.lanelet_ids) if tables is not None else _EMPTY_I64
            follows = tables is None or bool(tables.is_successor[lanelet_index[:-1], lanelet_index[1:]].all())
            out[id(corridor)] = (None, lanelet_index, follows)
        return out


def _shaped(c: Corridor) -> bool:
    """The shape conditions of `_corridor_problem` (>= 2 points, equal lengths, a finite vehicle s)."""
    m = len(c.x_m)
    return (m >= 2 and len(c.y_m) == m and len(c.s_m) == m and len(c.heading_rad) == m and len(c.width_m) == m
            and len(c.lanelet_ids) == len(c.lanelet_start_s_m) and math.isfinite(c.vehicle_s_m))


def _checked_batch(corridors: list[Corridor], tables: SceneTables | None) -> dict[int, tuple]:
    if not corridors:
        return {}
    shaped = np.array([_shaped(c) for c in corridors], dtype=bool)
    fields = [a for c in corridors for a in (c.x_m, c.y_m, c.s_m, c.heading_rad, c.width_m, c.lanelet_start_s_m)]
    sizes = np.array([len(a) for a in fields], dtype=np.int64).reshape(len(corridors), 6).sum(axis=1)
    nonfinite = ~np.isfinite(np.concatenate(fields).astype(np.float64, copy=False))
    if nonfinite.any():  # which corridors hold them: counts before each corridor's end and start
        bad = np.concatenate([[0], np.cumsum(nonfinite)])
        ends = np.cumsum(sizes)
        finite = bad[ends] == bad[ends - sizes]
    else:
        finite = np.ones(len(corridors), dtype=bool)
    # s: increasing (no step back) and of positive length
    s_len = np.array([len(c.s_m) for c in corridors], dtype=np.int64)
    s_all = np.concatenate([np.asarray(c.s_m, np.float64) for c in corridors])
    s_end = np.cumsum(s_len)
    s_start = s_end - s_len
    steps_back = np.diff(s_all) < 0.0
    has = s_len > 0
    s_ok = np.zeros(len(corridors), dtype=bool)
    if steps_back.any():
        back = np.concatenate([[0], np.cumsum(steps_back)])
        s_ok[has] = back[s_end[has] - 1] == back[s_start[has]]  # steps back inside a corridor (not across the joins)
    else:
        s_ok[has] = True
    s_ok[has] &= (s_all[s_end[has] - 1] - s_all[s_start[has]]) > 0.0
    sound = shaped & finite & s_ok
    if tables is not None:
        k_len = np.array([len(c.lanelet_ids) for c in corridors], dtype=np.int64)
        all_index = tables.indices(np.concatenate([np.asarray(c.lanelet_ids, np.int64) for c in corridors]))
        k_end = np.cumsum(k_len)
        k_start = k_end - k_len
        step_ok = tables.is_successor[all_index[:-1], all_index[1:]] if len(all_index) > 1 else np.zeros(0, dtype=bool)
        breaks = np.concatenate([[0], np.cumsum(~step_ok)])
        long = k_len >= 2
        follows = np.ones(len(corridors), dtype=bool)
        follows[long] = breaks[k_end[long] - 1] == breaks[k_start[long]]
    out = {}
    sound = sound.tolist()
    if tables is not None:
        k_start, k_end, follows = k_start.tolist(), k_end.tolist(), follows.tolist()
    for i, corridor in enumerate(corridors):
        problem = None if sound[i] else _corridor_problem(corridor)
        if problem is not None:
            out[id(corridor)] = (problem, _EMPTY_I64, True)
        elif tables is None:
            out[id(corridor)] = (None, _EMPTY_I64, True)
        else:
            out[id(corridor)] = (None, all_index[k_start[i] : k_end[i]], follows[i])
    return out


# --------------------------------------------------------------------------- the core


class RelationExtractor:
    """TrackFrame + CorridorSet (+ latched SceneInfo) -> RelationSet; see the package docstring."""

    def __init__(
        self,
        config: RelationsConfig,
        *,
        producer: str = "relations",
        scene_maps: SceneMaps | None = None,
    ) -> None:
        self.config = config
        self.producer = producer
        self.scene_maps = scene_maps or SceneMaps(data=config.data)
        self._scene_id: str | None = None
        self._map: SceneMap | None = None
        self._tables: SceneTables | None = None
        self._centre_of: object = False  # the road map whose centre `_centre` is (False: none yet)
        self._centre: np.ndarray | None = None
        self.signals = SignalStops(self.scene_maps.data_dir)
        kernels.warm_up()  # the compiled kernels loaded now, not on the first frame

    @property
    def tables(self) -> SceneTables | None:
        """The current scene's tables (None before a usable scene)."""
        return self._tables

    # ----- entry point -------------------------------------------------------

    def update(self, inputs: Mapping[str, object]) -> StageResult:
        """One frame: ``track_frame``, ``corridor_set`` (same stamp) and ``scene`` (latched, may be absent)."""
        frame = inputs.get("track_frame")
        corridor_set = inputs.get("corridor_set")
        scene = inputs.get("scene")
        if not isinstance(frame, TrackFrame) or not isinstance(corridor_set, CorridorSet):
            missing = [n for n, v in (("track_frame", frame), ("corridor_set", corridor_set)) if v is None]
            return StageResult(issues=[Issue("no_input", -1, f"update without {', '.join(missing) or 'the right types'}")])
        signal_state = inputs.get("signal_state")
        relation_set, issues = self.process(
            frame, corridor_set, scene if isinstance(scene, SceneInfo) else None,
            signal_state=signal_state if isinstance(signal_state, SignalState) else None,
        )
        outputs = {"relation_set": relation_set} if relation_set is not None else {}
        return StageResult(outputs=outputs, issues=issues)

    def process(
        self,
        frame: TrackFrame,
        corridor_set: CorridorSet,
        scene: SceneInfo | None,
        *,
        route_probabilities: Mapping[tuple[int, int], float] | None = None,
        signal_state: SignalState | None = None,
    ) -> tuple[RelationSet | None, list[Issue]]:
        """The pure function behind `update`: (output, issues); output None on a stamp mismatch.

        `route_probabilities` maps (track_id, corridor_id) to P(R = corridor)
        from the intentions; when given, the influencing rule skips other
        corridors below `min_route_probability`. `signal_state` gives the
        phases of the scene's signal groups (``stages.relations.signals``).
        """
        issues: list[Issue] = []
        stamp = int(frame.header.stamp_ns)
        if int(corridor_set.header.stamp_ns) != stamp:
            issues.append(Issue("stamp_mismatch", -1, f"track_frame stamp {stamp} != corridor_set stamp {corridor_set.header.stamp_ns}: frame skipped"))
            return None, issues
        tables = self._scene(scene, corridor_set, issues)
        objects = self._objects(frame, corridor_set, issues)
        pairs = self._pairs(corridor_set, objects, tables, issues)
        if len(pairs) > self.config.max_pairs:  # whole vehicles in CorridorSet order while they fit
            kept: list[_Pair] = []
            for vehicle_pairs in _by_vehicle(pairs):
                if len(kept) + len(vehicle_pairs) > self.config.max_pairs:
                    break
                kept.extend(vehicle_pairs)
            issues.append(Issue("pairs_capped", -1, f"{len(pairs) - len(kept)} of {len(pairs)} vehicle-corridor pairs beyond max_pairs = {self.config.max_pairs}: no relation"))
            pairs = kept
            for g, pair in enumerate(pairs):
                pair.g = g
        conflicts = None
        if tables is not None and pairs:
            try:
                conflicts = self._conflicts(pairs, tables)
            except Exception as exc:  # noqa: BLE001 - the lateral and intersection relations are still published
                issues.append(Issue("conflicts_failed", -1, f"{type(exc).__name__}: {exc}: no conflict points this frame"))
        relations = []
        smap = self._signal_map(scene, issues)
        state = self.signals.usable_state(signal_state, stamp, issues) if smap is not None else None
        starts = np.searchsorted(conflicts.g, np.arange(len(pairs) + 1)) if conflicts is not None else None
        projected = _project_onto_corridors(objects.xy[objects.valid], pairs, self._reach(pairs), self._radius(pairs)) if pairs else None
        batched = None
        if pairs:
            try:
                batched = self._lateral_batched(pairs, objects, projected)
            except Exception:  # noqa: BLE001 - then pair by pair (`_lateral`), where a failure costs one pair's relation
                batched = None
        owners = None
        if conflicts is not None and len(conflicts.g):
            try:
                owners = self._conflict_owners(pairs, conflicts, route_probabilities)
                owners = (owners[0].tolist(), owners[1].tolist(), owners[2], owners[3])  # Python ints, read pair by pair
            except Exception:  # noqa: BLE001 - then pair by pair (`_relations`), where a failure costs one pair's relation
                owners = None
        columns = [(name, getattr(conflicts, name)) for name in _Conflicts.__dataclass_fields__] if conflicts is not None else None
        for pair in pairs:
            try:
                lateral = self._lateral(pair, objects, projected, batched)
                crossings = self._intersections(pair, tables)
                span = slice(starts[pair.g], starts[pair.g + 1]) if starts is not None else slice(0, 0)
                rel = self._relations(pair, pairs, objects, lateral, crossings, conflicts, span, route_probabilities, owners, columns)
                relations.append(self._with_signal(rel, pair, smap, state))
            except Exception as exc:  # noqa: BLE001 - one pair's failure costs only its relation
                issues.append(Issue("pair_failed", pair.vehicle.track_id, f"corridor {pair.corridor.corridor_id}: {type(exc).__name__}: {exc}: no relation"))
        header = Header(
            run_id=frame.header.run_id, frame_index=frame.header.frame_index, stamp_ns=stamp, producer=self.producer,
            source_wall_ns=frame.header.source_wall_ns,  # the source frame's publish time, carried for end-to-end latency
        )
        scene_id = scene.scene_id if scene is not None else corridor_set.scene_id
        return RelationSet(header=header, scene_id=scene_id, relations=tuple(relations)), issues

    # ----- signals (RelationSet v2) ---------------------------------------------

    def _signal_map(self, scene: SceneInfo | None, issues: list[Issue]):
        road_map = self._map.road_map if self._map is not None and self._tables is not None else None
        projection = self._map.projection if self._map is not None else None
        return self.signals.signal_map(scene, road_map, projection, issues)

    def _with_signal(self, rel: CorridorRelations, pair: _Pair, smap, state: SignalState | None) -> CorridorRelations:
        fields = self.signals.fields(smap, pair.corridor, pair.length_m, state)
        return dataclasses.replace(rel, **fields) if fields else rel

    # ----- scene -------------------------------------------------------------

    def _scene(self, scene: SceneInfo | None, corridor_set: CorridorSet, issues: list[Issue]) -> SceneTables | None:
        if scene is None:
            issues.append(Issue("no_map", -1, "no SceneInfo received yet: lateral relations only"))
            return None
        if scene.scene_id != self._scene_id:
            self._scene_id = scene.scene_id
            self._map = self.scene_maps.get(scene, self.config.projection)
            road_map = self._map.road_map
            self._tables = SceneTables(road_map) if road_map is not None else None
            for problem in self._map.problems:
                kind = "map_sha256_mismatch" if problem.startswith("map_sha256_mismatch") else "map_problem"
                issues.append(Issue(kind, -1, problem))
        if self._tables is None:
            issues.append(Issue("no_map", -1, f"map {shown_map_name(scene)} unusable: lateral relations only"))
        if corridor_set.scene_id and corridor_set.scene_id != scene.scene_id:
            issues.append(Issue("scene_mismatch", -1, f"corridor_set names scene {corridor_set.scene_id}, latched scene is {scene.scene_id}"))
        return self._tables

    # ----- inputs --------------------------------------------------------------

    def _objects(self, frame: TrackFrame, corridor_set: CorridorSet, issues: list[Issue]) -> _Objects:
        """Objects with length, speed and heading; a matched vehicle's heading is its corridor's."""
        n = len(frame)
        track_ids = np.asarray(frame.track_ids, dtype=np.int64)
        xy = np.column_stack([np.asarray(frame.x_m, np.float64), np.asarray(frame.y_m, np.float64)]).reshape(n, 2)
        valid = np.isfinite(xy).all(axis=1)
        _, first = np.unique(track_ids, return_index=True)
        unique = np.zeros(n, dtype=bool)
        unique[first] = True
        for row in np.flatnonzero(~unique):
            issues.append(Issue("duplicate_track", int(track_ids[row]), "track id appears twice in the frame; later row ignored"))
        for row in np.flatnonzero(unique & ~valid):
            issues.append(Issue("nan_state", int(track_ids[row]), f"non-finite position ({xy[row, 0]}, {xy[row, 1]}): ignored"))
        valid &= unique
        if n > self.config.max_objects:  # beyond the cap: neither vehicle nor obstacle this frame (stages.lib.caps)
            road_map = self._map.road_map if self._map is not None else None
            if self._centre_of is not road_map:
                self._centre_of, self._centre = road_map, map_centre_m(road_map)
            kept, dropped = keep_nearest(xy, self._centre, self.config.max_objects)
            valid &= kept
            issues.append(Issue("objects_capped", -1, f"{dropped} of {n} objects beyond max_objects = {self.config.max_objects} (the farthest from the map's centre): ignored"))
        types = np.asarray(frame.agent_types, dtype=np.uint8)
        length = np.asarray(frame.length_m, dtype=np.float64).copy()
        bad_length = ~(np.isfinite(length) & (length > 0.0))
        for row in np.flatnonzero(bad_length):
            try:
                agent_type = AgentType(int(types[row]))
            except ValueError:
                agent_type = AgentType.UNKNOWN
            length[row] = DEFAULT_SIZES_M[agent_type][0]
        # velocity: the corridors stage's estimate from positions where it has one, the reported one otherwise
        vx, vy = np.array(frame.vx_mps, np.float64), np.array(frame.vy_mps, np.float64)
        first_row = {int(track_ids[r]): int(r) for r in first}
        for vehicle in corridor_set.vehicles:
            row = first_row.get(vehicle.track_id)
            if row is not None and math.isfinite(vehicle.vx_mps) and math.isfinite(vehicle.vy_mps):
                vx[row], vy[row] = vehicle.vx_mps, vehicle.vy_mps
        speed = np.hypot(vx, vy)
        heading = np.where(speed >= self.config.stopped_speed_mps, np.arctan2(vy, vx), np.asarray(frame.yaw_rad, np.float64))
        known = np.isfinite(speed)
        speed = np.where(known, speed, 0.0)
        with_corridors = np.zeros(n, dtype=bool)
        for vehicle in corridor_set.vehicles:
            row = first_row.get(vehicle.track_id)
            if row is None or not vehicle.corridors:
                continue
            with_corridors[row] = True
            corridor = vehicle.corridors[0]
            if len(corridor.s_m) >= 2 and len(corridor.heading_rad) == len(corridor.s_m) and math.isfinite(corridor.vehicle_s_m):
                along = _heading_at(corridor, corridor.vehicle_s_m)
                if math.isfinite(along):
                    heading[row] = along
            if math.isfinite(vehicle.speed_mps):
                speed[row] = max(float(vehicle.speed_mps), 0.0)
                known[row] = True
        for row in np.flatnonzero(valid & ~known & ~with_corridors):
            issues.append(Issue("nan_velocity", int(track_ids[row]), "non-finite velocity: obstacle with speed 0"))
        return _Objects(track_ids, types, xy, length, speed, heading, known, valid)

    def _pairs(self, corridor_set, objects: _Objects, tables, issues) -> list[_Pair]:
        """The (vehicle, corridor) pairs to relate; bad vehicles and corridors become issues."""
        rows = {int(t): r for r, t in enumerate(objects.track_ids) if objects.valid[r]}
        all_rows = {int(t) for t in objects.track_ids}
        listed = {v.track_id for v in corridor_set.vehicles}
        for track_id in sorted(all_rows - listed):
            issues.append(Issue("missing_corridors", track_id, "in the TrackFrame but not in the CorridorSet: obstacle only"))
        pairs: list[_Pair] = []
        accepted: list[tuple] = []
        checked = _checked_corridors(corridor_set, tables)
        for vehicle in corridor_set.vehicles:
            if not vehicle.corridors:
                continue
            row = rows.get(vehicle.track_id)
            if row is None:
                if vehicle.track_id not in all_rows:
                    issues.append(Issue("missing_track", vehicle.track_id, "in the CorridorSet but not in the TrackFrame: skipped"))
                continue
            if not objects.speed_known[row]:
                issues.append(Issue("nan_state", vehicle.track_id, "no finite speed: skipped (obstacle with speed 0)"))
                continue
            speed = float(objects.speed_mps[row])
            for corridor in vehicle.corridors:
                problem, lanelet_index, follows = checked[id(corridor)]
                if problem is not None:
                    issues.append(Issue("bad_corridor", vehicle.track_id, f"corridor {corridor.corridor_id}: {problem}: skipped"))
                    continue
                accepted.append((vehicle, corridor, row, speed, lanelet_index, follows))
        if not accepted:
            return pairs
        # every pair's centreline (x, y) as a view into one (points, 2) array, and its widest width, a few numpy calls
        sizes = [len(a[1].x_m) for a in accepted]
        bounds = np.concatenate([[0], np.cumsum(sizes)])
        xy = np.column_stack([np.concatenate([a[1].x_m for a in accepted]), np.concatenate([a[1].y_m for a in accepted])])
        widest = np.maximum.reduceat(np.concatenate([a[1].width_m for a in accepted]).astype(np.float64, copy=False), bounds[:-1]).tolist()
        for g, (vehicle, corridor, row, speed, lanelet_index, follows) in enumerate(accepted):
            pairs.append(
                _Pair(
                    g=g,
                    vehicle=vehicle,
                    corridor=corridor,
                    row=row,
                    speed_mps=max(speed, 0.0),
                    length_m=float(objects.length_m[row]),
                    xy=xy[bounds[g] : bounds[g + 1]],
                    lanelet_index=lanelet_index,
                    follows_lanelets=follows,
                    width_max_m=widest[g],
                )
            )
        return pairs

    # ----- lateral relation --------------------------------------------------------

    def _reach(self, pairs: list[_Pair]) -> np.ndarray:
        """Per pair, how far (m) outside its centreline's bounding box an object can still be on the corridor.

        `_lateral` keeps objects with |d| < half width + `lateral_margin_m`
        and s >= vehicle s - `lookbehind_m` (possibly on the straight
        extension before the corridor's start); anything farther from the
        box is not projected at all (1 m slack for resampling).
        """
        cfg = self.config
        return np.array(
            [
                cfg.lookbehind_m + max(0.0, float(p.corridor.s_m[0]) - p.corridor.vehicle_s_m)
                + 0.5 * p.width_max_m + cfg.lateral_margin_m + 1.0
                for p in pairs
            ]
        )

    def _radius(self, pairs: list[_Pair]) -> np.ndarray:
        """Per pair, the largest |d| `_lateral` can keep: half the corridor's widest width + `lateral_margin_m` (+1 mm)."""
        margin = self.config.lateral_margin_m
        return np.array([0.5 * p.width_max_m + margin + 1e-3 for p in pairs])

    def _lateral(self, pair: _Pair, objects: _Objects, projected, batched=None):
        """Objects within the lane of the corridor, ordered by s, and the leader (row into them or -1).

        `projected` is (s, d, heading) of every valid object on every
        corridor, arrays (pairs, valid objects), from `_project_onto_corridors`.
        `batched` is `_lateral_batched`'s list (the same values for every
        pair at once), taken when given; this pair-by-pair code is its
        reference and its fallback.
        """
        if batched is not None:
            return batched[pair.g]
        cfg = self.config
        corridor = pair.corridor
        candidates = np.flatnonzero(objects.valid)
        all_s, all_d, all_heading = (a[pair.g] for a in projected)
        s_v = corridor.vehicle_s_m
        half_width = 0.5 * np.interp(all_s, corridor.s_m, corridor.width_m)
        inside = (
            (objects.track_ids[candidates] != pair.vehicle.track_id)
            & (np.abs(all_d) < half_width + cfg.lateral_margin_m)
            & (all_s >= s_v - cfg.lookbehind_m)
            & (all_s <= min(s_v + cfg.lookahead_m, float(corridor.s_m[-1])))
        )
        keep = np.flatnonzero(inside)
        keep = keep[np.argsort(all_s[keep], kind="stable")]
        rows = candidates[keep]
        s, d = all_s[keep], all_d[keep]
        relative = wrap_angle_rad(objects.heading_rad[rows] - all_heading[keep])
        along = objects.speed_mps[rows] * np.cos(relative)
        along = np.where(np.isfinite(along), along, 0.0)
        half_lengths = 0.5 * (objects.length_m[rows] + pair.length_m)
        ahead = s >= s_v
        gap = np.where(ahead, np.maximum(s - s_v - half_lengths, 0.0), np.minimum(s - s_v + half_lengths, 0.0))
        can_lead = ahead & (
            (np.abs(np.nan_to_num(relative, nan=math.pi)) <= cfg.leader_max_heading_rad)
            | (objects.speed_mps[rows] < cfg.stopped_speed_mps)
        )
        leader = int(np.flatnonzero(can_lead)[0]) if can_lead.any() else -1
        return rows, s, d, gap, along, leader

    def _lateral_batched(self, pairs: list[_Pair], objects: _Objects, projected) -> list[tuple]:
        """`_lateral` of every pair at once: the same tests and values element by element, a few numpy calls per frame.

        Only the (pair, object) combinations with a finite projection inside
        the pair's s range are looked at (the others fail `_lateral`'s tests:
        NaN compares false); the half width is interpolated on each pair's
        corridor for those; the kept objects are ordered by (pair, s, object)
        as `_lateral`'s stable sort by s orders them per pair.
        """
        cfg = self.config
        candidates = np.flatnonzero(objects.valid)
        all_s, all_d, all_heading = projected
        n_pairs = len(pairs)
        s_v = np.array([p.corridor.vehicle_s_m for p in pairs], dtype=np.float64)
        own = np.array([p.vehicle.track_id for p in pairs], dtype=np.int64)
        lo = s_v - cfg.lookbehind_m
        hi = np.array([min(p.corridor.vehicle_s_m + cfg.lookahead_m, float(p.corridor.s_m[-1])) for p in pairs], dtype=np.float64)
        g, k = np.nonzero((all_s >= lo[:, None]) & (all_s <= hi[:, None]))
        keep = objects.track_ids[candidates[k]] != own[g]
        g, k = g[keep], k[keep]
        s = all_s[g, k]
        d = all_d[g, k]
        half_width = np.empty(len(g))
        bounds = np.searchsorted(g, np.arange(n_pairs + 1))
        for q in np.flatnonzero(bounds[1:] > bounds[:-1]):
            corridor = pairs[q].corridor
            part = slice(bounds[q], bounds[q + 1])
            half_width[part] = 0.5 * np.interp(s[part], corridor.s_m, corridor.width_m)
        inside = np.abs(d) < half_width + cfg.lateral_margin_m
        g, k, s, d = g[inside], k[inside], s[inside], d[inside]
        order = np.lexsort((k, s, g))
        g, k, s, d = g[order], k[order], s[order], d[order]
        rows = candidates[k]
        relative = wrap_angle_rad(objects.heading_rad[rows] - all_heading[g, k])
        along = objects.speed_mps[rows] * np.cos(relative)
        along = np.where(np.isfinite(along), along, 0.0)
        pair_length = np.array([p.length_m for p in pairs], dtype=np.float64)
        half_lengths = 0.5 * (objects.length_m[rows] + pair_length[g])
        sv = s_v[g]
        ahead = s >= sv
        gap = np.where(ahead, np.maximum(s - sv - half_lengths, 0.0), np.minimum(s - sv + half_lengths, 0.0))
        can_lead = ahead & (
            (np.abs(np.nan_to_num(relative, nan=math.pi)) <= cfg.leader_max_heading_rad)
            | (objects.speed_mps[rows] < cfg.stopped_speed_mps)
        )
        bounds = np.searchsorted(g, np.arange(n_pairs + 1))
        leads = np.flatnonzero(can_lead)
        first_lead = np.searchsorted(leads, bounds[:-1])  # the first leader candidate at or after each pair's start
        out = []
        for q in range(n_pairs):
            a, b = int(bounds[q]), int(bounds[q + 1])
            f = int(first_lead[q])
            leader = int(leads[f]) - a if f < len(leads) and leads[f] < b else -1
            out.append((rows[a:b], s[a:b], d[a:b], gap[a:b], along[a:b], leader))
        return out

    # ----- corridor to intersection ------------------------------------------------

    @staticmethod
    def _intersections(pair: _Pair, tables: SceneTables | None):
        """(ids, entry, exit, entry lanelet ids) of the intersections the corridor still has ahead or is in."""
        if tables is None or not len(pair.lanelet_index):
            return _EMPTY_I64, _EMPTY_F64, _EMPTY_F64, _EMPTY_I64
        corridor = pair.corridor
        ids = tables.intersection_id[pair.lanelet_index].tolist()
        if max(ids) < 0:  # no intersection on the corridor
            return _EMPTY_I64, _EMPTY_F64, _EMPTY_F64, _EMPTY_I64
        starts = corridor.lanelet_start_s_m
        found = []
        k, n = 0, len(ids)
        while k < n:
            if ids[k] < 0:
                k += 1
                continue
            j = k
            while j + 1 < n and ids[j + 1] == ids[k]:
                j += 1
            entry = float(starts[k] + tables.entry_s_m[pair.lanelet_index[k]])
            exit_ = float(starts[j] + tables.exit_s_m[pair.lanelet_index[j]])
            if exit_ >= corridor.vehicle_s_m:
                found.append((ids[k], entry, exit_, int(corridor.lanelet_ids[k])))
            k = j + 1
        if not found:
            return _EMPTY_I64, _EMPTY_F64, _EMPTY_F64, _EMPTY_I64
        cols = list(zip(*found))
        return (
            np.asarray(cols[0], dtype=np.int64),
            np.asarray(cols[1], dtype=np.float64),
            np.asarray(cols[2], dtype=np.float64),
            np.asarray(cols[3], dtype=np.int64),
        )

    # ----- corridor to corridor -------------------------------------------------------

    def _conflicts(self, pairs: list[_Pair], tables: SceneTables) -> _Conflicts:
        """All conflict points between corridors of different vehicles, by table lookups.

        Every lanelet occurrence of every corridor is joined with the
        occurrences of the lanelets it conflicts with (`conflict_with`, the
        sparse form of `pair_first`; work in proportion to the pairs found),
        which gives s* = lanelet start in the corridor + arc length within the
        lanelet on both corridors.
        """
        cfg = self.config
        occ_g = np.concatenate([np.full(len(p.lanelet_index), p.g, dtype=np.int64) for p in pairs])
        occ_lanelet = np.concatenate([p.lanelet_index for p in pairs])
        occ_start = np.concatenate([np.asarray(p.corridor.lanelet_start_s_m, np.float64) for p in pairs])
        vehicle_of = np.array([p.row for p in pairs], dtype=np.int64)
        length_of = np.array([float(p.corridor.s_m[-1]) for p in pairs])
        s_v = np.array([p.corridor.vehicle_s_m for p in pairs])
        speed = np.array([p.speed_mps for p in pairs])
        half_length = 0.5 * np.array([p.length_m for p in pairs])
        occ_vehicle = vehicle_of[occ_g]
        # occurrence pairs of different vehicles on conflicting lanelets (found) and on the same lanelet (shared), by a
        # join over the lanelets (work in proportion to the pairs found, not occurrences squared), in the order of a
        # dense occurrence x occurrence scan (i, then j ascending)
        n_occ = len(occ_g)
        order = np.argsort(occ_lanelet, kind="stable")
        by_lanelet = np.searchsorted(occ_lanelet[order], np.arange(tables.n_lanelets + 2))  # occurrences of lanelet k: [k], [k + 1]
        occ_index = np.arange(n_occ, dtype=np.int64)
        n_neighbours = tables.conflict_indptr[occ_lanelet + 1] - tables.conflict_indptr[occ_lanelet]
        i_nb = np.repeat(occ_index, n_neighbours)
        b_nb = tables.conflict_with[np.repeat(tables.conflict_indptr[occ_lanelet], n_neighbours) + _ranges(n_neighbours)]
        i, j = _join(i_nb, b_nb, order, by_lanelet)
        keep = occ_vehicle[i] != occ_vehicle[j]
        i, j = _row_major(i[keep], j[keep])
        known = occ_lanelet < tables.n_lanelets
        si, sj = _join(occ_index[known], occ_lanelet[known], order, by_lanelet)
        keep = occ_vehicle[si] != occ_vehicle[sj]
        si, sj = _row_major(si[keep], sj[keep])
        count = tables.pair_count[occ_lanelet[i], occ_lanelet[j]]
        point = np.repeat(tables.pair_first[occ_lanelet[i], occ_lanelet[j]], count) + _ranges(count)
        i, j = np.repeat(i, count), np.repeat(j, count)
        g, other_g = occ_g[i], occ_g[j]
        s = occ_start[i] + tables.point_s_a_m[point]
        other_s = occ_start[j] + tables.point_s_b_m[point]
        self._refine(pairs, tables, point, g, s)
        self._refine(pairs, tables, point, other_g, other_s)
        distance = s - s_v[g]
        other_distance = other_s - s_v[other_g]
        keep = (
            (s >= 0.0) & (s <= length_of[g]) & (other_s >= 0.0) & (other_s <= length_of[other_g])
            & (distance > -(half_length[g] + cfg.clear_margin_m))
            & (other_distance > -(half_length[other_g] + cfg.clear_margin_m))
        )
        # a shared lanelet before the point on both corridors: a following relation, not a conflict
        shared_start = np.full((len(pairs), len(pairs)), np.inf)
        np.minimum.at(shared_start, (occ_g[si], occ_g[sj]), occ_start[si])
        keep &= ~((shared_start[g, other_g] <= s) & (shared_start[other_g, g] <= other_s))
        idx = np.flatnonzero(keep)
        idx = idx[np.lexsort((s[idx], other_g[idx], g[idx]))]
        # one point per place: the same crossing reached through two lanelet pairs (at a lanelet join)
        if len(idx) > 1:
            same_pair = (g[idx][1:] == g[idx][:-1]) & (other_g[idx][1:] == other_g[idx][:-1])
            close = np.diff(s[idx]) < cfg.duplicate_conflict_m
            idx = idx[np.concatenate([[True], ~(same_pair & close)])]
        idx = idx[np.lexsort((other_g[idx], s[idx], g[idx]))]
        floor = cfg.min_time_speed_mps
        return _Conflicts(
            g=g[idx],
            other_g=other_g[idx],
            kind=tables.point_kind[point[idx]],
            s_m=s[idx],
            other_s_m=other_s[idx],
            x_m=tables.point_x_m[point[idx]],
            y_m=tables.point_y_m[point[idx]],
            distance_m=distance[idx],
            other_distance_m=other_distance[idx],
            other_speed_mps=speed[other_g[idx]],
            time_s=distance[idx] / np.maximum(speed[g[idx]], floor),
            other_time_s=other_distance[idx] / np.maximum(speed[other_g[idx]], floor),
            priority=tables.point_priority[point[idx]],
        )

    def _refine(self, pairs: list[_Pair], tables: SceneTables, point, g, s) -> None:
        """Arc lengths on corridors that change lane: the point projected onto the corridor near the lookup.

        A lane-change corridor blends from one lane into its neighbour, so it
        leaves its lanelets' centrelines around the join and the lookup s*
        can be off by up to a metre there; elsewhere lookups are exact.
        """
        window = self.config.refine_window_m
        if window <= 0.0 or not len(g):
            return
        changes_lane = np.array([not p.follows_lanelets for p in pairs], dtype=bool)
        candidates = np.flatnonzero(changes_lane[g] & (s > -window))
        candidates = candidates[np.argsort(g[candidates], kind="stable")]  # by pair, ascending rows within one
        starts = np.flatnonzero(np.concatenate([[True], g[candidates][1:] != g[candidates][:-1]])) if len(candidates) else candidates
        groups = []  # (pair, its rows)
        for a, b in zip(starts, [*starts[1:], len(candidates)]):
            pair = pairs[g[candidates[a]]]
            rows = candidates[a:b]
            rows = rows[s[rows] < pair.corridor.s_m[-1] + window]
            if len(rows):
                groups.append((pair, rows))
        if not groups:
            return
        # every group's points on its own corridor in one kernel call (`kernels.project_window_groups`: the arithmetic
        # of `project_in_window`, group by group); a group the kernel declines goes through `project_in_window`
        all_rows = np.concatenate([rows for _pair, rows in groups])
        xy = np.column_stack([tables.point_x_m[point[all_rows]], tables.point_y_m[point[all_rows]]])
        hints = s[all_rows]
        counts = np.array([len(rows) for _pair, rows in groups], dtype=np.int64)
        point_bounds = np.concatenate([[0], np.cumsum(counts)])
        found = kernels.project_window_groups(
            xy, point_bounds,
            np.concatenate([pair.xy for pair, _rows in groups]).astype(np.float64, copy=False),
            np.concatenate([[0], np.cumsum([len(pair.xy) for pair, _rows in groups])]).astype(np.int64),
            np.concatenate([np.asarray(pair.corridor.s_m, np.float64) for pair, _rows in groups]),
            hints, window,
        )
        ok = found[3] if found is not None else np.zeros(len(groups), dtype=bool)
        done = np.repeat(ok, counts)
        s[all_rows[done]] = found[0][done] if found is not None else s[all_rows[done]]
        for q in np.flatnonzero(~ok):
            pair, rows = groups[q]
            part = slice(point_bounds[q], point_bounds[q + 1])
            s[rows] = project_in_window(xy[part], pair.xy, pair.corridor.s_m, hints[part], window)[0]

    # ----- assembly ------------------------------------------------------------------

    def _conflict_owners(self, pairs: list[_Pair], conflicts: _Conflicts, route_probabilities) -> tuple[np.ndarray, ...]:
        """For every conflict of the frame at once: the influencing choice of every pair (`choose_influencing_grouped`:
        index within the pair's conflicts, rule), and the other vehicle's track and corridor id of each conflict."""
        track_of = np.array([p.vehicle.track_id for p in pairs], dtype=np.int64)
        corridor_of = np.array([p.corridor.corridor_id for p in pairs], dtype=np.int64)
        probability = None
        if route_probabilities is not None:
            probability = np.array([route_probabilities.get((int(track_of[k]), int(corridor_of[k])), 1.0) for k in conflicts.other_g])
        index, rule = choose_influencing_grouped(
            conflicts.g, len(pairs), conflicts.kind, conflicts.priority, conflicts.distance_m, conflicts.other_distance_m,
            conflicts.time_s, conflicts.other_time_s,
            horizon_s=self.config.conflict_horizon_s, other_probability=probability, min_probability=self.config.min_route_probability,
        )
        return index, rule, track_of[conflicts.other_g], corridor_of[conflicts.other_g]

    def _relations(self, pair, pairs, objects, lateral, crossings, conflicts, span, route_probabilities, owners=None,
                   columns=None) -> CorridorRelations:
        """One corridor's message part, with the influencing conflict chosen by the rules.

        `owners` is `_conflict_owners`' result for the frame (taken when
        given); the pair-by-pair code here is its reference and fallback.
        `columns`: (name, array) of every `_Conflicts` field, read once per
        frame (else read here).
        """
        rows, s, d, gap, along, leader = lateral
        corridor = pair.corridor
        isect_ids, entry, exit_, entry_lanelets = crossings
        if conflicts is not None and span.stop > span.start:
            if columns is None:
                columns = [(name, getattr(conflicts, name)) for name in _Conflicts.__dataclass_fields__]
            c = {name: values[span] for name, values in columns}
        else:
            c = None
        if c is not None and owners is not None:
            index, rule = int(owners[0][pair.g]), RULES[int(owners[1][pair.g])]
            conflict_tracks, conflict_corridors = owners[2][span], owners[3][span]
        elif c is not None:
            other_pairs = [pairs[k] for k in c["other_g"]]
            probability = None
            if route_probabilities is not None:
                probability = np.array(
                    [route_probabilities.get((p.vehicle.track_id, p.corridor.corridor_id), 1.0) for p in other_pairs]
                )
            index, rule = choose_influencing(
                c["kind"], c["priority"], c["distance_m"], c["other_distance_m"], c["time_s"], c["other_time_s"],
                horizon_s=self.config.conflict_horizon_s,
                other_probability=probability,
                min_probability=self.config.min_route_probability,
            )
            conflict_tracks = np.array([p.vehicle.track_id for p in other_pairs], dtype=np.int64)
            conflict_corridors = np.array([p.corridor.corridor_id for p in other_pairs], dtype=np.int64)
        else:
            index, rule = -1, NO_INFLUENCE
            conflict_tracks = conflict_corridors = _EMPTY_I64
            c = {
                "kind": np.zeros(0, np.uint8), "priority": np.zeros(0, np.int8),
                **{k: _EMPTY_F64 for k in ("s_m", "other_s_m", "x_m", "y_m", "distance_m", "other_distance_m",
                                           "other_speed_mps", "time_s", "other_time_s")},
            }
        return CorridorRelations(
            track_id=pair.vehicle.track_id,
            corridor_id=corridor.corridor_id,
            object_track_ids=np.asarray(objects.track_ids[rows], dtype=np.int64),
            object_types=np.asarray(objects.types[rows], dtype=np.uint8),
            object_s_m=s,
            object_d_m=d,
            object_gap_m=gap,
            object_speed_mps=along,
            leader_track_id=-1 if leader < 0 else int(objects.track_ids[rows[leader]]),
            leader_gap_m=math.nan if leader < 0 else float(gap[leader]),
            leader_speed_mps=math.nan if leader < 0 else float(along[leader]),
            intersection_ids=isect_ids,
            intersection_entry_s_m=entry,
            intersection_exit_s_m=exit_,
            intersection_distance_m=entry - corridor.vehicle_s_m,
            intersection_entry_lanelet_ids=entry_lanelets,
            conflict_track_ids=conflict_tracks,
            conflict_corridor_ids=conflict_corridors,
            conflict_kinds=np.asarray(c["kind"], np.uint8),
            conflict_s_m=c["s_m"],
            conflict_other_s_m=c["other_s_m"],
            conflict_x_m=c["x_m"],
            conflict_y_m=c["y_m"],
            conflict_distance_m=c["distance_m"],
            conflict_other_distance_m=c["other_distance_m"],
            conflict_other_speed_mps=c["other_speed_mps"],
            conflict_time_s=c["time_s"],
            conflict_other_time_s=c["other_time_s"],
            conflict_priority=np.asarray(c["priority"], np.int8),
            influencing_index=index,
            influencing_rule=rule,
        )


def _project_onto_corridors(points_m: np.ndarray, pairs: list[_Pair], reach_m: np.ndarray | None = None,
                            radius_m: np.ndarray | None = None, *, compiled: bool = True):
    """Frenet (s, d, heading) of points (n, 2) on every pair's corridor; arrays (pairs, n).

    The same projection as `maps.project_to_polyline` (nearest segment, the
    end segments extended straight, d positive to the left, heading of the
    foot segment), bit for bit, over all pairs at once, so a frame costs a few
    numpy calls instead of a few per corridor.

    Only the (pair, point) combinations with the point inside the corridor's
    bounding box grown by ``reach_m[pair]`` are projected (all of them when
    `reach_m` is None); the others are NaN, which no relation test passes.
    With ``radius_m`` (pairs,), a combination is also left NaN when the point
    is provably farther than ``radius_m`` from the corridor in |d| (the
    lateral test `_lateral` needs |d| < half width + margin): its distance to
    the polyline exceeds ``radius_m / cos(θ)``, θ the corridor's sharpest
    turn between two segments (at a vertex |d| >= distance·cos θ; a corridor
    that turns by 60° or more, or has a zero-length segment, is not pruned).

    Branch and bound, exact: the segments between the two (extended) end
    segments are grouped in blocks of ``_BLOCK`` with their vertices'
    bounding box; a block whose box lies farther from the point than some
    vertex of the corridor cannot hold the nearest segment and is skipped,
    the others are measured segment by segment with the arithmetic of the
    dense projection (same nearest segment, ties to the lower index). The
    work per chunk is bounded by ``_CHUNK_ELEMENTS`` (issue 13: memory stays
    bounded however many objects a frame holds).

    With ``compiled`` (and numba), all of it (boxes, bounds, candidates)
    runs pair by pair and candidate by candidate in the kernel
    ``stages.lib.maps.kernels.project_polylines`` on the concatenated
    corridors: the same bounds, the same segments measured in the same
    order with the same arithmetic, so the same values bit for bit without
    the padded arrays and the numpy calls (the numpy code below is its
    reference, and the fallback where the kernel meets a NaN).
    """
    n_pairs, n = len(pairs), len(points_m)
    n_segments = np.array([len(p.xy) - 1 for p in pairs], dtype=np.int64)
    m = int(n_segments.max())
    n_blocks = max(1, -(-max(m - 2, 0) // _BLOCK))
    if (compiled and n and np.isfinite(points_m).all() and all(p.g == g and len(p.corridor.s_m) == len(p.xy) for g, p in enumerate(pairs))):
        out_s = np.full((n_pairs, n), np.nan)
        out_d = np.full((n_pairs, n), np.nan)
        found = kernels.project_polylines(
            np.ascontiguousarray(points_m, dtype=np.float64), np.concatenate([p.xy for p in pairs]).astype(np.float64, copy=False),
            np.concatenate([np.asarray(p.corridor.s_m, np.float64) for p in pairs]), np.concatenate([[0], np.cumsum(n_segments + 1)]),
            reach_m, radius_m, _BLOCK, n_blocks, m, out_s, out_d,
        )
        if found is not None:
            hit_g, hit_k, ux, uy = found
            out_heading = np.full((n_pairs, n), np.nan)
            out_heading[hit_g, hit_k] = np.arctan2(uy, ux)
            return out_s, out_d, out_heading
    line = np.zeros((n_pairs, m + 1, 2))
    arc = np.zeros((n_pairs, m + 1))
    for p in pairs:
        line[p.g, : len(p.xy)] = p.xy
        arc[p.g, : len(p.xy)] = p.corridor.s_m
    segment = np.diff(line, axis=1)
    valid = np.arange(m)[None, :] < n_segments[:, None]
    length2 = np.where(valid, np.maximum((segment**2).sum(axis=2), 1e-18), 1.0)
    lower = np.zeros((n_pairs, m))
    upper = np.ones((n_pairs, m))
    lower[:, 0] = -np.inf
    upper[np.arange(n_pairs), n_segments - 1] = np.inf
    out_s = np.full((n_pairs, n), np.nan)
    out_d = np.full((n_pairs, n), np.nan)
    out_heading = np.full((n_pairs, n), np.nan)
    if n == 0:
        return out_s, out_d, out_heading
    # interior blocks: segments 1 .. ns-2 in blocks of _BLOCK; block i holds segments [1 + i·B, 1 + (i+1)·B) and
    # its box the vertices 1 + i·B .. 1 + (i+1)·B (indices past the last vertex repeat it: a larger box, still a bound)
    block_first = 1 + _BLOCK * np.arange(n_blocks)
    vertex = np.minimum(block_first[:, None] + np.arange(_BLOCK + 1)[None, :], m)  # (blocks, B + 1)
    vertex = np.minimum(vertex[None], n_segments[:, None, None])  # (pairs, blocks, B + 1)
    corners = line[np.arange(n_pairs)[:, None, None], vertex]  # (pairs, blocks, B + 1, 2)
    box_lo, box_hi = corners.min(axis=2), corners.max(axis=2)
    block_end = np.minimum(block_first[None, :] + _BLOCK, (n_segments - 1)[:, None])  # exclusive; the last segment apart
    block_used = block_first[None, :] < block_end  # (pairs, blocks)
    start_vertex = line[np.arange(n_pairs)[:, None], np.minimum(block_first[None, :], n_segments[:, None])]  # (pairs, blocks, 2)
    last_vertex = line[np.arange(n_pairs), n_segments]
    # the pruning bound: |d| >= distance * cos(sharpest turn); none where a corridor turns by 60 deg or more
    if radius_m is not None:
        seg_len_all = np.sqrt(np.where(valid, np.maximum((segment**2).sum(axis=2), 1e-300), 1.0))
        unit = segment / seg_len_all[..., None]
        turn_cos = (unit[:, :-1] * unit[:, 1:]).sum(axis=2)
        turn_cos = np.where(valid[:, 1:], turn_cos, 1.0)
        cos_min = turn_cos.min(axis=1) if m > 1 else np.ones(n_pairs)
        degenerate = (np.where(valid, (segment**2).sum(axis=2), 1.0) < 1e-12).any(axis=1)
        prunable = (cos_min > 0.5) & ~degenerate & np.isfinite(radius_m)
        limit2 = np.where(prunable, (np.asarray(radius_m, np.float64) / np.where(prunable, cos_min, 1.0)) ** 2, np.inf)
    else:
        limit2 = np.full(n_pairs, np.inf)
    if reach_m is None:
        cand_g, cand_k = np.nonzero(np.ones((n_pairs, n), dtype=bool))
    else:
        lo = np.array([p.xy.min(axis=0) for p in pairs]) - reach_m[:, None]
        hi = np.array([p.xy.max(axis=0) for p in pairs]) + reach_m[:, None]
        cand_g, cand_k = np.nonzero(((points_m[None, :, :] >= lo[:, None, :]) & (points_m[None, :, :] <= hi[:, None, :])).all(axis=2))
    per_chunk = max(1, _CHUNK_ELEMENTS // (n_blocks + 2 * _BLOCK))
    for first in range(0, len(cand_g), per_chunk):
        g, k = cand_g[first : first + per_chunk], cand_k[first : first + per_chunk]
        p = points_m[k]
        last = n_segments[g] - 1
        # exact squared distances to the two end segments (extended), the dense projection's arithmetic
        d2_first = _segment_d2(p, line[g, 0], segment[g, 0], length2[g, 0], lower[g, 0], upper[g, 0])
        d2_last = _segment_d2(p, line[g, last], segment[g, last], length2[g, last], lower[g, last], upper[g, last])
        # interior blocks: the distance from the point to each box (a lower bound of its segments' distances)
        dx = np.maximum(np.maximum(box_lo[g, :, 0] - p[:, None, 0], p[:, None, 0] - box_hi[g, :, 0]), 0.0)
        dy = np.maximum(np.maximum(box_lo[g, :, 1] - p[:, None, 1], p[:, None, 1] - box_hi[g, :, 1]), 0.0)
        box2 = np.where(block_used[g], dx * dx + dy * dy, np.inf)
        lower_bound = np.minimum(np.minimum(d2_first, d2_last), box2.min(axis=1))
        # an upper bound of the nearest distance: the nearest of the end segments and the blocks' first vertices
        sv = start_vertex[g] - p[:, None, :]
        vertex2 = np.where(block_used[g], (sv**2).sum(axis=2), np.inf)
        lv = last_vertex[g] - p
        upper_bound = np.minimum(np.minimum(d2_first, d2_last), np.minimum(vertex2.min(axis=1), (lv**2).sum(axis=1)))
        wanted = lower_bound <= limit2[g] * (1.0 + 1e-9)
        keep_block = (box2 <= upper_bound[:, None] * (1.0 + 1e-9) + 1e-12) & wanted[:, None]
        # the segments to measure, per candidate in ascending order: 0, the kept blocks', the last (unless it is 0)
        c_b, b_b = np.nonzero(keep_block)
        count_b = block_end[g[c_b], b_b] - block_first[b_b]
        c_mid = np.repeat(c_b, count_b)
        j_mid = np.repeat(block_first[b_b], count_b) + _ranges(count_b)
        c_end = np.flatnonzero(wanted)
        c_tail = c_end[last[c_end] > 0]
        cc = np.concatenate([c_end, c_mid, c_tail])
        jj = np.concatenate([np.zeros(len(c_end), np.int64), j_mid, last[c_tail]])
        order = np.argsort(cc, kind="stable")  # by candidate; within one, segment order is kept
        cc, jj = cc[order], jj[order]
        if not len(cc):
            continue
        ge = g[cc]
        rel = p[cc] - line[ge, jj]
        seg = segment[ge, jj]
        t = np.clip((rel * seg).sum(axis=1) / length2[ge, jj], lower[ge, jj], upper[ge, jj])
        off = rel - t[:, None] * seg
        dist2 = (off**2).sum(axis=1)
        # the first nearest segment of each candidate
        starts = np.flatnonzero(np.concatenate([[True], cc[1:] != cc[:-1]]))
        nearest = np.minimum.reduceat(dist2, starts)
        group = np.cumsum(np.concatenate([[False], cc[1:] != cc[:-1]]))
        hit = np.flatnonzero(dist2 == nearest[group])
        e = hit[np.concatenate([[True], group[hit][1:] != group[hit][:-1]])]
        gc, kc, j = ge[e], k[cc[e]], jj[e]
        seg_len = np.sqrt(length2[gc, j])
        ux, uy = segment[gc, j, 0] / seg_len, segment[gc, j, 1] / seg_len
        out_s[gc, kc] = arc[gc, j] + t[e] * seg_len
        out_d[gc, kc] = ux * rel[e, 1] - uy * rel[e, 0]
        out_heading[gc, kc] = np.arctan2(uy, ux)
    return out_s, out_d, out_heading


def _segment_d2(p, a, seg, length2, lower, upper) -> np.ndarray:
    """Squared distance of points p (c, 2) to segments a + t·seg, t clipped to [lower, upper] (all (c,) or (c, 2))."""
    rel = p - a
    t = np.clip((rel * seg).sum(axis=1) / length2, lower, upper)
    off = rel - t[:, None] * seg
    return (off**2).sum(axis=1)


_CHUNK_ELEMENTS = 1 << 19  # (candidate, block) elements per chunk of the projection
_BLOCK = 8  # segments per block of the projection's branch and bound


def _by_vehicle(pairs: list[_Pair]) -> list[list[_Pair]]:
    """The pairs grouped by vehicle (consecutive in `_pairs`' order)."""
    groups: list[list[_Pair]] = []
    for pair in pairs:
        if groups and groups[-1][0].row == pair.row:
            groups[-1].append(pair)
        else:
            groups.append([pair])
    return groups


def _join(i: np.ndarray, lanelet: np.ndarray, order: np.ndarray, by_lanelet: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Every (i[k], j) with j an occurrence of lanelet[k] (`order`: occurrences sorted by lanelet, `by_lanelet` their starts)."""
    count = by_lanelet[lanelet + 1] - by_lanelet[lanelet]
    return np.repeat(i, count), order[np.repeat(by_lanelet[lanelet], count) + _ranges(count)]


def _row_major(i: np.ndarray, j: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(i, j) sorted by i, then j (the order of ``np.nonzero`` on a dense i x j mask)."""
    o = np.lexsort((j, i))
    return i[o], j[o]


def _ranges(count: np.ndarray) -> np.ndarray:
    """0..count[k]-1 for every k, concatenated (count (n,) int)."""
    total = int(count.sum())
    if total == 0:
        return np.zeros(0, dtype=np.int64)
    starts = np.repeat(np.cumsum(count) - count, count)
    return np.arange(total, dtype=np.int64) - starts
