"""The pure part of the intentions stage: `IntentionsConfig` and `IntentionFilter`.

See the package docstring for the DBN, the particle filter and the
parameters; nothing here touches the bus or the wall clock (time comes from
``header.stamp_ns``, random numbers from generators seeded by (seed, frame
index, track id)).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Mapping

import numpy as np

from bus_schemas import (
    Corridor,
    CorridorBelief,
    CorridorRelations,
    CorridorSet,
    Header,
    IntentionBelief,
    Manoeuvre,
    MatchStatus,
    RelationSet,
    SceneInfo,
    TrackFrame,
    VehicleBelief,
)
from stages.lib.base import ConfigMixin, Issue, StageResult, check_ranges, isolate
from stages.lib.caps import cap_pairs
from stages.lib.maps import DEFAULT_SPEED_LIMIT_MPS, Projection, RoadMap, SceneMaps, parse_projection, project_in_window, shown_map_name

from stages.intentions import kernels, model
from stages.intentions.model import PARTICLE_FIELDS, ModelParams, Particles
from stages.intentions.signals import with_signals
from stages.intentions.streams import Streams
from stages.intentions.tables import PairTables, VehicleInput, build_tables, common_run, corridor_manoeuvre, corridors_ok, lanelet_ids_of, lanelet_shift_m, map_corridors

_NS = 1e-9
_U64 = (1 << 64) - 1


@dataclass(frozen=True, kw_only=True)
class IntentionsConfig(ConfigMixin):
    """Parameters of the intentions stage (package docstring, docs/method.md §7)."""

    seed: int = 0
    particles_per_vehicle: int = 300
    # R
    route_switch_per_step: float = 0.005
    route_floor_fraction: float = 0.02
    # E
    gap_critical_s: float = 5.0
    gap_pass_s: float = 1.0
    gap_scale_s: float = 0.6
    min_time_speed_mps: float = 1.0
    # I
    intention_keep: float = 0.98
    intention_adapt: float = 0.10
    intention_floor: float = 0.01
    # Φ
    go_gain_per_s: float = 1.0
    go_accel_sigma_mps2: float = 0.7
    accel_relaxation_s: float = 0.0
    accel_jerk_sigma_mps2: float = 0.3
    stop_accel_sigma_mps2: float = 0.5
    stop_margin_m: float = 1.0
    stop_min_distance_m: float = 0.5
    stop_offset_m: float = 14.0
    accel_min_mps2: float = -8.0
    accel_max_mps2: float = 4.0
    lateral_decay: float = 0.9
    lateral_sigma_m: float = 0.05
    lat_accels_mps2: tuple[float, ...] = (3.0, 2.5, 2.0, 1.5)
    lat_accel_weights: tuple[float, ...] = (0.1, 0.2, 0.4, 0.3)
    brake_lookahead_mps2: float = 2.5
    curvature_smoothing_m: float = 1.0
    max_substep_s: float = 0.1
    # Z
    position_sigma_m: float = 0.5
    heading_sigma_rad: float = 0.15
    speed_sigma_mps: float = 0.5
    heading_min_speed_mps: float = 1.0
    # filter
    resample_ess_fraction: float = 0.5
    jitter_s_m: float = 0.2
    jitter_v_mps: float = 0.1
    min_log_weight: float = -40.0
    birth_sigma_s_m: float = 0.5
    birth_sigma_d_m: float = 0.2
    birth_sigma_v_mps: float = 0.3
    birth_sigma_a_mps2: float = 0.5
    birth_lateral_sigma_m: float = 1.0
    lost_gate_m: float = 10.0
    unseen_timeout_s: float = 1.0
    lane_change_reach_m: float = 10.0
    projection: str = "auto"
    max_pairs: int = 600
    data: str = ""  # local data folder whose maps/ holds the scene's map (by name); "": the embedded stages/data/taf-bw

    def __post_init__(self) -> None:
        positive = (
            "gap_critical_s", "gap_scale_s", "min_time_speed_mps", "go_accel_sigma_mps2", "stop_accel_sigma_mps2",
            "stop_min_distance_m", "brake_lookahead_mps2", "max_substep_s", "position_sigma_m", "heading_sigma_rad",
            "speed_sigma_mps", "birth_lateral_sigma_m", "lost_gate_m", "unseen_timeout_s", "accel_max_mps2",
        )
        non_negative = (
            "route_switch_per_step", "route_floor_fraction", "gap_pass_s", "go_gain_per_s", "stop_margin_m", "lateral_sigma_m",
            "curvature_smoothing_m", "heading_min_speed_mps", "accel_relaxation_s", "accel_jerk_sigma_mps2", "jitter_s_m",
            "jitter_v_mps", "birth_sigma_s_m", "birth_sigma_d_m",
            "birth_sigma_v_mps", "birth_sigma_a_mps2", "lane_change_reach_m",
        )
        check_ranges(self, positive=positive, non_negative=non_negative)
        if self.max_pairs < 1:
            raise ValueError(f"max_pairs = {self.max_pairs}: must be >= 1")
        for name in ("route_switch_per_step", "intention_keep", "intention_adapt", "resample_ess_fraction", "lateral_decay"):
            value = getattr(self, name)
            if not (0.0 <= value <= 1.0):
                raise ValueError(f"{name} = {value!r}: must lie in [0, 1]")
        if not (0.0 <= self.intention_floor < 0.5):
            raise ValueError(f"intention_floor = {self.intention_floor!r}: must lie in [0, 0.5)")
        if self.seed < 0:
            raise ValueError(f"seed = {self.seed}: must be >= 0")
        if self.particles_per_vehicle < 2:
            raise ValueError(f"particles_per_vehicle = {self.particles_per_vehicle}: must be >= 2")
        if self.route_floor_fraction > 0.5:
            raise ValueError(f"route_floor_fraction = {self.route_floor_fraction}: must be <= 0.5")
        if not math.isfinite(self.stop_offset_m):
            raise ValueError("stop_offset_m must be finite")
        if not (math.isfinite(self.accel_min_mps2) and self.accel_min_mps2 < 0.0):
            raise ValueError(f"accel_min_mps2 = {self.accel_min_mps2!r}: must be < 0")
        if not (math.isfinite(self.min_log_weight) and self.min_log_weight < 0.0):
            raise ValueError(f"min_log_weight = {self.min_log_weight!r}: must be < 0")
        if not self.lat_accels_mps2 or len(self.lat_accels_mps2) != len(self.lat_accel_weights):
            raise ValueError("lat_accels_mps2 and lat_accel_weights must be non-empty and of equal length")
        if any(a <= 0 for a in self.lat_accels_mps2) or any(w < 0 for w in self.lat_accel_weights) or sum(self.lat_accel_weights) <= 0:
            raise ValueError("lat_accels_mps2 must be > 0, lat_accel_weights >= 0 with a positive sum")
        if parse_projection(self.projection) is Projection.UNKNOWN:
            known = ", ".join(p.name.lower() for p in Projection if p is not Projection.UNKNOWN)
            raise ValueError(f"projection = {self.projection!r}: expected one of {known}")

    @property
    def floor_particles(self) -> int:
        """Particles every corridor keeps at least (2 % of N, at least 1)."""
        return max(1, int(math.ceil(self.route_floor_fraction * self.particles_per_vehicle - 1e-9)))

    def model_params(self) -> ModelParams:
        return ModelParams(**{f: getattr(self, f) for f in ModelParams.__dataclass_fields__})


@dataclass(slots=True, eq=False)
class _Vehicle:
    """What the filter keeps about one vehicle between frames: particles (one row) and its last corridors."""

    last_stamp_ns: int
    corridors: tuple[Corridor, ...]
    particles: Particles
    probabilities: dict[int, float] = field(default_factory=dict)


@dataclass(slots=True, eq=False)
class _Measurement:
    x_m: float
    y_m: float
    heading_rad: float
    speed_mps: float
    heading_ok: bool
    speed_ok: bool


class IntentionFilter:
    """TrackFrame + CorridorSet + RelationSet (+ latched SceneInfo) -> IntentionBelief; see the package docstring."""

    def __init__(self, config: IntentionsConfig, *, producer: str = "intentions", scene_maps: SceneMaps | None = None) -> None:
        self.config = config
        self.producer = producer
        self.scene_maps = scene_maps or SceneMaps(data=config.data)
        self.params = config.model_params()
        weights = np.asarray(config.lat_accel_weights, dtype=np.float64)
        self._style_cdf = np.cumsum(weights / weights.sum())
        self._vehicles: dict[int, _Vehicle] = {}
        self._last_stamp_ns: int | None = None
        self._scene_id: str | None = None
        self._road_map: RoadMap | None = None
        self._manoeuvres: dict[tuple, tuple[Manoeuvre, bool]] = {}
        self._lanelet_length: dict[int, float] = {}  # of the latched map's lanelets (NaN: not in the map), for the cache keys
        self._streams = Streams()  # np.random.default_rng([seed, frame, track]) per vehicle, all at once
        kernels.warm_up()  # the compiled kernels loaded (or compiled) now, not on the first frame
        self._streams(0, 0, [0])  # its compiled hash too

    @property
    def tracked_ids(self) -> frozenset[int]:
        """Track ids with particles kept between frames (dropped after `unseen_timeout_s` unseen)."""
        return frozenset(self._vehicles)

    def reset(self) -> None:
        """Forget every vehicle (a new recording)."""
        self._vehicles.clear()
        self._last_stamp_ns = None

    # ----- entry point -------------------------------------------------------

    def update(self, inputs: Mapping[str, object]) -> StageResult:
        """One frame: ``track_frame``, ``corridor_set``, ``relation_set`` (same stamp) and ``scene`` (latched, may be absent)."""
        frame = inputs.get("track_frame")
        corridor_set = inputs.get("corridor_set")
        relation_set = inputs.get("relation_set")
        scene = inputs.get("scene")
        if not isinstance(frame, TrackFrame) or not isinstance(corridor_set, CorridorSet):
            missing = [n for n, v in (("track_frame", frame), ("corridor_set", corridor_set)) if v is None]
            return StageResult(issues=[Issue("no_input", -1, f"update without {', '.join(missing) or 'the right types'}")])
        belief, issues = self.process(
            frame,
            corridor_set,
            relation_set if isinstance(relation_set, RelationSet) else None,
            scene if isinstance(scene, SceneInfo) else None,
        )
        return StageResult(outputs={"intention_belief": belief} if belief is not None else {}, issues=issues)

    def process(
        self, frame: TrackFrame, corridor_set: CorridorSet, relation_set: RelationSet | None, scene: SceneInfo | None
    ) -> tuple[IntentionBelief | None, list[Issue]]:
        """The pure function behind `update`: (output, issues); output None when the stamps disagree."""
        cfg = self.config
        issues: list[Issue] = []
        stamp = int(frame.header.stamp_ns)
        stamps = {"corridor_set": corridor_set.header.stamp_ns}
        if relation_set is not None:
            stamps["relation_set"] = relation_set.header.stamp_ns
        for name, other in stamps.items():
            if int(other) != stamp:
                issues.append(Issue("stamp_mismatch", -1, f"track_frame stamp {stamp} != {name} stamp {other}: frame skipped"))
                return None, issues
        if relation_set is None:
            issues.append(Issue("no_relations", -1, "no relation_set: no stop positions or priority conflicts this frame"))
        if self._last_stamp_ns is not None and stamp <= self._last_stamp_ns:
            issues.append(Issue("stamp_not_increasing", -1, f"stamp {stamp} <= {self._last_stamp_ns}: every vehicle's particles reset"))
            self._vehicles.clear()
        self._last_stamp_ns = stamp
        corridor_set, dropped = cap_pairs(corridor_set, cfg.max_pairs)
        if dropped:
            issues.append(Issue("pairs_capped", -1, f"{dropped} vehicle-corridor pairs beyond max_pairs = {cfg.max_pairs} (whole vehicles, in CorridorSet order): skipped this frame"))
        road_map = self._scene(scene, corridor_set, issues)
        timeout_ns = int(round(cfg.unseen_timeout_s * 1e9))
        for track_id in [t for t, v in self._vehicles.items() if stamp - v.last_stamp_ns > timeout_ns]:
            del self._vehicles[track_id]
        inputs, measurements = self._inputs(frame, corridor_set, issues)
        header = Header(
            run_id=frame.header.run_id, frame_index=frame.header.frame_index, stamp_ns=stamp, producer=self.producer,
            source_wall_ns=frame.header.source_wall_ns,  # the source frame's publish time, carried for end-to-end latency
        )
        scene_id = scene.scene_id if scene is not None else corridor_set.scene_id
        if not inputs:
            return IntentionBelief(header=header, scene_id=scene_id, vehicles=()), issues
        relations: dict[tuple[int, int], CorridorRelations] = {}
        if relation_set is not None:
            relations = {(r.track_id, r.corridor_id): r for r in relation_set.relations}
        route_probabilities = {(t, c): p for t, v in self._vehicles.items() for c, p in v.probabilities.items()}

        def attempt(idx: list[int]):  # the filter for the vehicles idx (each vehicle's random numbers are its own)
            found: list[Issue] = []
            sub = [inputs[i] for i in idx]
            if not sub:
                return sub, None, [], found
            tables = build_tables(
                sub,
                relations,
                route_probabilities,
                lat_accels_mps2=cfg.lat_accels_mps2,
                brake_lookahead_mps2=cfg.brake_lookahead_mps2,
                curvature_smoothing_m=cfg.curvature_smoothing_m,
                default_speed_limit_mps=scene.speed_limit_mps if scene is not None and scene.speed_limit_mps > 0 else DEFAULT_SPEED_LIMIT_MPS,
                stop_offset_m=cfg.stop_offset_m,
            )
            tables = with_signals(tables, sub, relations)  # unchanged without signal phases
            particles, ess = self._filter(frame.header.frame_index, stamp, sub, [measurements[i] for i in idx], tables, found)
            return sub, particles, self._beliefs(sub, tables, particles, ess, road_map), found

        (kept, particles, vehicles, found), failed = isolate(range(len(inputs)), attempt)  # one vehicle's failure: only it
        issues.extend(found)
        for i, exc in failed:
            issues.append(Issue("vehicle_failed", inputs[i].track_id, f"{type(exc).__name__}: {exc}: no belief, particles dropped"))
            self._vehicles.pop(inputs[i].track_id, None)
        for v, item in enumerate(kept):
            belief = vehicles[v]
            self._vehicles[item.track_id] = _Vehicle(
                last_stamp_ns=stamp,
                corridors=item.corridors,
                particles=particles.row(v),
                probabilities={c.corridor_id: c.probability for c in belief.corridors},
            )
        return IntentionBelief(header=header, scene_id=scene_id, vehicles=tuple(vehicles)), issues

    # ----- scene and inputs ----------------------------------------------------

    def _scene(self, scene: SceneInfo | None, corridor_set: CorridorSet, issues: list[Issue]) -> RoadMap | None:
        if scene is None:
            issues.append(Issue("no_map", -1, "no SceneInfo received yet: manoeuvres unknown"))
            return None
        if scene.scene_id != self._scene_id:
            self._scene_id = scene.scene_id
            scene_map = self.scene_maps.get(scene, self.config.projection)
            self._road_map = scene_map.road_map
            self._manoeuvres.clear()
            self._lanelet_length.clear()
            self._vehicles.clear()
            for problem in scene_map.problems:
                kind = "map_sha256_mismatch" if problem.startswith("map_sha256_mismatch") else "map_problem"
                issues.append(Issue(kind, -1, problem))
        if self._road_map is None:
            issues.append(Issue("no_map", -1, f"map {shown_map_name(scene)} unusable: manoeuvres unknown"))
        if corridor_set.scene_id and corridor_set.scene_id != scene.scene_id:
            detail = f"corridor_set names scene {corridor_set.scene_id}, latched scene is {scene.scene_id}"
            issues.append(Issue("scene_mismatch", -1, detail))
        return self._road_map

    def _inputs(self, frame: TrackFrame, corridor_set: CorridorSet, issues: list[Issue]):
        """The vehicles to update (matched, with usable corridors and a finite position) and their measurements."""
        cfg = self.config
        rows: dict[int, int] = {}
        for row, track_id in enumerate(frame.track_ids.tolist()):
            rows.setdefault(int(track_id), row)
        inputs: list[VehicleInput] = []
        measurements: list[_Measurement] = []
        seen: set[int] = set()
        candidates = []
        for vehicle in corridor_set.vehicles:
            if vehicle.status != MatchStatus.MATCHED or not vehicle.corridors or vehicle.track_id in seen:
                continue
            seen.add(vehicle.track_id)
            candidates.append(vehicle)
        problems = iter(corridors_ok([c for vehicle in candidates for c in vehicle.corridors]))
        for vehicle in candidates:
            good = []
            for corridor in vehicle.corridors:
                problem = next(problems)
                if problem is None:
                    good.append(corridor)
                else:
                    issues.append(Issue("bad_corridor", vehicle.track_id, f"corridor {corridor.corridor_id}: {problem}: skipped"))
            if not good:
                continue
            row = rows.get(vehicle.track_id)
            if row is None:
                issues.append(Issue("missing_track", vehicle.track_id, "in the CorridorSet but not in the TrackFrame: skipped"))
                continue
            x, y = float(frame.x_m[row]), float(frame.y_m[row])
            if not (math.isfinite(x) and math.isfinite(y)):
                issues.append(Issue("nan_state", vehicle.track_id, f"non-finite position ({x}, {y}): not updated"))
                continue
            vx, vy, yaw = float(frame.vx_mps[row]), float(frame.vy_mps[row]), float(frame.yaw_rad[row])
            speed = float(vehicle.speed_mps)
            if not math.isfinite(speed):
                speed = math.hypot(vx, vy)
            speed_ok = math.isfinite(speed)
            if not speed_ok:
                issues.append(Issue("nan_velocity", vehicle.track_id, "no finite speed: speed term left out"))
            # heading: the direction of the velocity estimated from positions when moving, else the yaw
            if speed_ok and speed >= cfg.heading_min_speed_mps and math.isfinite(vehicle.vx_mps) and math.isfinite(vehicle.vy_mps):
                heading = math.atan2(vehicle.vy_mps, vehicle.vx_mps)
            else:
                heading = yaw if math.isfinite(yaw) else math.atan2(vy, vx)
            heading_ok = math.isfinite(heading) and speed_ok and speed >= cfg.heading_min_speed_mps
            inputs.append(VehicleInput(track_id=vehicle.track_id, corridors=tuple(good), lanelet_id=int(vehicle.lanelet_id)))
            measurements.append(_Measurement(x, y, heading, speed, heading_ok, speed_ok))
        return inputs, measurements

    # ----- the particle filter -------------------------------------------------------

    def _filter(self, frame_index: int, stamp: int, inputs, measurements, tables: PairTables, issues: list[Issue]):
        """Birth or carry, propagate, weight, resample: particles (V, N) and the ESS (V,) before resampling."""
        cfg, mp = self.config, self.params
        n = cfg.particles_per_vehicle
        n_vehicles = len(inputs)
        first = tables.first_pair
        rows: list[Particles] = []
        born = np.zeros(n_vehicles, dtype=bool)
        dt = np.zeros(n_vehicles)
        n_sub = np.zeros(n_vehicles, dtype=np.int64)
        mappings: dict[int, tuple[tuple[Corridor, ...], list[tuple[int, float]]]] = {}
        reborn: list[tuple[int, Exception]] = []
        for v, item in enumerate(inputs):
            state = self._vehicles.get(item.track_id)
            if state is None:
                born[v] = True
                rows.append(_empty(n))
                continue
            try:
                mappings[v] = (state.corridors, _mapping(state, item.corridors))
            except Exception as exc:  # noqa: BLE001 - its particles cannot follow the new corridors: born again
                reborn.append((v, exc))
                born[v] = True
                rows.append(_empty(n))
                continue
            rows.append(state.particles)
            dt[v] = (stamp - state.last_stamp_ns) * _NS
            n_sub[v] = max(1, int(math.ceil(dt[v] / cfg.max_substep_s - 1e-9)))
        p = Particles.stack(rows)  # a copy: the kept particles change only when the frame is done
        for v, exc in self._carry(p, mappings, inputs):
            reborn.append((v, exc))
            born[v] = True
            dt[v] = 0.0
            n_sub[v] = 0
        for v, exc in sorted(reborn, key=lambda item: item[0]):
            issues.append(Issue("particles_reborn", inputs[v].track_id, f"moving its particles onto the new corridors raised {type(exc).__name__}: {exc}"))
        rngs = self._streams(cfg.seed, int(frame_index) & _U64, [int(item.track_id) & _U64 for item in inputs])
        offsets = np.array([r.random() for r in rngs])  # systematic resampling offsets
        frame_n = np.stack([r.standard_normal((4, n)) for r in rngs], axis=1)  # jitter s, jitter v, floor s, floor d
        names = ("x_m", "y_m", "heading_rad", "speed_mps", "heading_ok", "speed_ok")
        z = tuple(np.array([getattr(m, f) for m in measurements]) for f in names)
        # particles that lost their vehicle (a jump, a re-used id) are born again at the measurement
        carried = np.flatnonzero(~born)
        if carried.size:
            gap = np.abs(p.s_m[carried] - tables.vehicle_s_m[first[carried, None] + p.route[carried]])
            speed = z[3][carried]
            allowed = np.where(np.isfinite(speed), cfg.lost_gate_m + np.maximum(np.where(np.isfinite(speed), speed, 0.0), 0.0) * dt[carried], cfg.lost_gate_m)
            rows, distance = _lost_rows(gap, allowed)
            for v, median in zip(carried[rows].tolist(), distance.tolist()):
                issues.append(Issue("particles_lost", inputs[v].track_id, f"particles a median {median:.0f} m from the measurement: born again"))
                born[v] = True
                dt[v] = 0.0
                n_sub[v] = 0
        if born.any():
            self._birth(p, np.flatnonzero(born), rngs, tables, z)
        steps = int(n_sub.max())
        if steps:
            uniforms = np.ones((steps, 3, n_vehicles, n))
            normals = np.zeros((steps, 2, n_vehicles, n))
            for v in np.flatnonzero(~born):
                uniforms[: n_sub[v], :, v] = rngs[v].random((n_sub[v], 3, n))
                normals[: n_sub[v], :, v] = rngs[v].standard_normal((n_sub[v], 2, n))
            sub_dt = np.where(n_sub > 0, dt / np.maximum(n_sub, 1), 0.0)
            for k in range(steps):
                model.propagate(p, tables, first, sub_dt, (n_sub > k), (uniforms[k], normals[k]), mp)
        log_weight = np.log(p.weight) + model.log_likelihood(p, tables, first, z, mp)
        log_weight[born] -= 0.5 * (p.d_m[born] / cfg.birth_lateral_sigma_m) ** 2
        p.weight, ok = model.normalise(log_weight, cfg.min_log_weight)
        for v in np.flatnonzero(~ok):
            issues.append(Issue("filter_degenerate", inputs[v].track_id, "no particle has a finite likelihood: weights reset to uniform"))
        ess = 1.0 / np.sum(p.weight**2, axis=1)
        self._inject(p, inputs, tables, frame_n[2], frame_n[3])
        g = tables.first_pair[:, None] + p.route
        counts = np.bincount(g.ravel(), minlength=tables.n_pairs)
        short = np.zeros(n_vehicles, dtype=bool)
        floor = np.minimum(cfg.floor_particles, n // tables.n_slots[tables.vehicle])
        short[tables.vehicle[counts < floor]] = True
        resample = np.flatnonzero((ess < cfg.resample_ess_fraction * n) | short)
        if resample.size:
            index, weight = model.stratified_resample(
                p.route[resample], p.weight[resample], tables.n_slots[resample], cfg.floor_particles, offsets[resample]
            )
            p.take(resample, index)
            p.weight[resample] = weight
            p.s_m[resample] += cfg.jitter_s_m * frame_n[0, resample]
            p.v_mps[resample] = np.maximum(p.v_mps[resample] + cfg.jitter_v_mps * frame_n[1, resample], 0.0)
        return p, ess

    def _birth(self, p: Particles, rows: np.ndarray, rngs, tables: PairTables, z) -> None:
        """New vehicles: N particles split evenly over the corridors, placed at the measurement with noise."""
        cfg, mp = self.config, self.params
        n = cfg.particles_per_vehicle
        normals = np.stack([rngs[v].standard_normal((4, n)) for v in rows], axis=1)
        uniforms = np.stack([rngs[v].random((2, n)) for v in rows], axis=1)
        route = np.arange(n)[None, :] % tables.n_slots[rows][:, None]
        g = tables.first_pair[rows][:, None] + route
        speed = np.where(z[5][rows], z[3][rows], 0.0)[:, None]
        p.route[rows] = route
        p.s_m[rows] = tables.vehicle_s_m[g] + cfg.birth_sigma_s_m * normals[0]
        p.d_m[rows] = tables.vehicle_d_m[g] + cfg.birth_sigma_d_m * normals[1]
        p.v_mps[rows] = np.maximum(speed + cfg.birth_sigma_v_mps * normals[2], 0.0)
        p.a_mps2[rows] = cfg.birth_sigma_a_mps2 * normals[3]
        p.stop[rows] = uniforms[0] < 0.5
        p.style[rows] = np.minimum(np.searchsorted(self._style_cdf, uniforms[1], side="right"), len(self._style_cdf) - 1)
        p.p_expected_stop[rows] = model.expected_stop(tables, g, p.s_m[rows], p.v_mps[rows], mp)
        p.weight[rows] = 1.0 / n

    def _carry(self, p: Particles, mappings: dict[int, tuple[tuple[Corridor, ...], list[tuple[int, float]]]], inputs) -> list[tuple[int, Exception]]:
        """The particles of the rows `mappings` (row -> its vehicle's last corridors and `map_corridors` of them onto its new
        ones) moved onto the new corridors: same id or longest common lanelet run (s shifted, all rows at once); else by
        projection.

        Returns (row, exception) of the rows whose projection raised: they are reset (the caller has them born again).
        """
        if not mappings:
            return []
        carried = np.fromiter(mappings, dtype=np.int64, count=len(mappings))
        width = max(len(m) for _old, m in mappings.values())
        new_slot = np.full((carried.size, width), -1, dtype=np.int64)
        shift = np.full((carried.size, width), np.nan)
        for i, (_old, mapping) in enumerate(mappings.values()):
            new_slot[i, : len(mapping)] = [m[0] for m in mapping]
            shift[i, : len(mapping)] = [m[1] for m in mapping]
        old = p.route[carried]
        rows = np.arange(carried.size)[:, None]
        slot, sh = new_slot[rows, old], shift[rows, old]
        shifted = (slot >= 0) & np.isfinite(sh)
        s_m = p.s_m[carried]
        p.s_m[carried] = np.where(shifted, s_m + np.where(shifted, sh, 0.0), s_m)
        failed = []
        for i in np.flatnonzero(~shifted.all(axis=1)).tolist():
            v = int(carried[i])
            try:
                # no shared lanelet: project the particle's map position onto its new corridor, or the nearest new one
                slot[i] = _project(p, v, mappings[v][0], old[i], slot[i], ~shifted[i], inputs[v].corridors)
            except Exception as exc:  # noqa: BLE001 - its particles cannot follow the new corridors: born again
                failed.append((v, exc))
                empty = _empty(p.route.shape[1])
                for name in PARTICLE_FIELDS:
                    getattr(p, name)[v] = getattr(empty, name)[0]
                slot[i] = 0
        p.route[carried] = slot
        return failed

    def _inject(self, p: Particles, inputs, tables: PairTables, noise_s: np.ndarray, noise_d: np.ndarray) -> None:
        """A corridor without particles (new after a corridor-set change) gets `floor_particles` with the prior weight.

        They are the lowest-weight particles of the most populated corridor;
        each keeps its place along a lanelet both corridors hold (s shifted,
        d kept), else it is placed at the vehicle's projection on the new
        corridor with noise. They get the weight 1/N each and the vehicle's
        weights are renormalised. The per-corridor floor itself is kept by
        the stratified resampling (`model.stratified_resample`).
        """
        cfg = self.config
        n = cfg.particles_per_vehicle
        g = tables.first_pair[:, None] + p.route
        counts = np.bincount(g.ravel(), minlength=tables.n_pairs)
        empty = np.flatnonzero(counts == 0)
        for v in np.unique(tables.vehicle[empty]):
            corridors = inputs[v].corridors
            first = int(tables.first_pair[v])
            have = counts[first : first + len(corridors)].copy()
            floor = min(cfg.floor_particles, n // len(corridors))
            for k in np.flatnonzero(have == 0):
                donor = int(np.argmax(have))
                take = min(floor, int(have[donor]) - 1)
                if take <= 0:
                    continue
                members = np.flatnonzero(p.route[v] == donor)
                moved = members[np.argsort(p.weight[v, members], kind="stable")[:take]]
                run, lanelet = common_run(lanelet_ids_of(corridors[donor]), lanelet_ids_of(corridors[k]))
                if run:
                    p.s_m[v, moved] += lanelet_shift_m(corridors[donor], corridors[k], lanelet)
                else:
                    gk = first + k
                    p.s_m[v, moved] = tables.vehicle_s_m[gk] + cfg.birth_sigma_s_m * noise_s[v, moved]
                    p.d_m[v, moved] = tables.vehicle_d_m[gk] + cfg.birth_sigma_d_m * noise_d[v, moved]
                p.route[v, moved] = k
                p.weight[v, moved] = 1.0 / n
                have[donor] -= take
                have[k] += take
            p.weight[v] /= p.weight[v].sum()

    # ----- output ----------------------------------------------------------------------

    def _beliefs(self, inputs, tables: PairTables, p: Particles, ess: np.ndarray, road_map: RoadMap | None) -> list[VehicleBelief]:
        cfg = self.config
        n_pairs = tables.n_pairs
        g = (tables.first_pair[:, None] + p.route).ravel()
        w = p.weight.ravel()
        fields = (p.s_m, p.v_mps, p.a_mps2)
        # the per-pair sums in one compiled pass (np.bincount's, bit for bit), else numpy's bincount field by field
        found = kernels.pair_sums(g, w, [x.ravel() for x in fields], p.stop.ravel(), n_pairs)
        if found is not None:
            mass, count, sums, squares, stop_sum = found
        else:
            mass = np.bincount(g, w, minlength=n_pairs)
            count = np.bincount(g, minlength=n_pairs)
            sums = [np.bincount(g, w * x, minlength=n_pairs) for x in (f.ravel().astype(np.float64) for f in fields)]
            squares = [np.bincount(g, w * x * x, minlength=n_pairs) for x in (f.ravel().astype(np.float64) for f in fields)]
            stop_sum = np.bincount(g, w * p.stop.ravel(), minlength=n_pairs)
        safe = np.where(mass > 0, mass, 1.0)
        none = count == 0

        def moments(f: int) -> tuple[np.ndarray, np.ndarray]:
            mean = sums[f] / safe
            var = squares[f] / safe - mean**2
            return np.where(none, np.nan, mean), np.where(none, np.nan, np.sqrt(np.maximum(var, 0.0)))

        s_mean, s_std = moments(0)
        v_mean, v_std = moments(1)
        a_mean, a_std = moments(2)
        stop_given = stop_sum / safe
        p_stop = np.sum(p.weight * p.stop, axis=1)
        p_expected = np.sum(p.weight * p.p_expected_stop, axis=1)
        p_violation = np.sum(p.weight * np.where(p.stop, 1.0 - p.p_expected_stop, p.p_expected_stop), axis=1)
        # per pair and per vehicle as Python numbers once (the same values float()/int() of each element gives)
        mass_l, count_l, stop_given_l = mass.tolist(), count.tolist(), stop_given.tolist()
        s_mean_l, s_std_l, v_mean_l, v_std_l, a_mean_l, a_std_l = (a.tolist() for a in (s_mean, s_std, v_mean, v_std, a_mean, a_std))
        stop_distance_l = (tables.stop_s_m - tables.vehicle_s_m).tolist()
        entry_distance_l = (tables.entry_s_m - tables.vehicle_s_m).tolist()
        p_stop_l, p_expected_l, p_violation_l, ess_l = p_stop.tolist(), p_expected.tolist(), p_violation.tolist(), ess.tolist()
        found = self._manoeuvres_of([c for item in inputs for c in item.corridors], road_map)
        out = []
        for v, (item, first) in enumerate(zip(inputs, tables.first_pair.tolist())):
            slots = range(first, first + len(item.corridors))
            corridors = []
            lane_change = 0.0
            for gk, corridor in zip(slots, item.corridors):
                manoeuvre, changes = found[gk]
                lane_change += mass_l[gk] if changes else 0.0
                corridors.append(
                    CorridorBelief(
                        corridor_id=corridor.corridor_id,
                        probability=mass_l[gk],
                        manoeuvre=manoeuvre,
                        particle_count=count_l[gk],
                        s_mean_m=s_mean_l[gk],
                        s_std_m=s_std_l[gk],
                        v_mean_mps=v_mean_l[gk],
                        v_std_mps=v_std_l[gk],
                        a_mean_mps2=a_mean_l[gk],
                        a_std_mps2=a_std_l[gk],
                        p_stop=stop_given_l[gk] if count_l[gk] else math.nan,
                        stop_distance_m=stop_distance_l[gk],
                    )
                )
            masses = mass_l[first : first + len(item.corridors)]
            if any(m != m for m in masses):  # NaN: np.argmax's answer (the first NaN)
                best = first + int(np.argmax(mass[first : first + len(item.corridors)]))
            else:  # the first largest, as np.argmax
                best = first + masses.index(max(masses))
            entry_distance = entry_distance_l[best]
            if p_stop_l[v] > 0.5 and math.isfinite(entry_distance):
                expected = Manoeuvre.STOP
            else:
                expected = corridors[best - first].manoeuvre
            out.append(
                VehicleBelief(
                    track_id=item.track_id,
                    corridors=tuple(corridors),
                    p_stop=min(p_stop_l[v], 1.0),  # sums of particle weights may round past 1
                    p_expected_stop=min(p_expected_l[v], 1.0),
                    p_violation=min(p_violation_l[v], 1.0),
                    p_lane_change=min(lane_change, 1.0),
                    expected_manoeuvre=expected,
                    intersection_distance_m=entry_distance,
                    effective_sample_size=ess_l[v],
                    particle_count=cfg.particles_per_vehicle,
                )
            )
        return out

    def _manoeuvres_of(self, corridors: list[Corridor], road_map: RoadMap | None) -> list[tuple[Manoeuvre, bool]]:
        """(manoeuvre, changes lane) per corridor: `corridor_manoeuvre`, cached by what it depends on.

        `corridor_manoeuvre` reads a corridor's lanelet ids and, per lanelet
        of the map, only two comparisons with the vehicle's place: its start
        lies less than `lane_change_reach_m` behind the vehicle, its end lies
        ahead of it. The key is the ids and those two comparisons per
        lanelet (the same float operations, all corridors at once), so the
        cached result is exactly the function's and the key changes only
        when the vehicle crosses one of those points. A corridor whose
        starts and ids differ in length is looked up directly (uncached).
        """
        if road_map is None:
            return [(Manoeuvre.UNKNOWN, False)] * len(corridors)
        if not corridors:
            return []
        ids = [lanelet_ids_of(c) for c in corridors]
        starts = [np.asarray(c.lanelet_start_s_m, dtype=np.float64) for c in corridors]
        aligned = [len(i) == len(s) for i, s in zip(ids, starts)]
        lengths = [len(i) if ok else 0 for i, ok in zip(ids, aligned)]
        lanelet_length = self._lanelet_length
        flat = [x for i, ok in zip(ids, aligned) if ok for x in i]
        for x in flat:
            if x not in lanelet_length:
                lanelet_length[x] = road_map.lanelet(x).length_m if road_map.has_lanelet(x) else math.nan
        start = np.concatenate([s for s, ok in zip(starts, aligned) if ok]) if any(aligned) else np.zeros(0)
        s_v = np.repeat(np.array([float(c.vehicle_s_m) for c in corridors], dtype=np.float64), lengths)
        behind = (start > s_v - self.config.lane_change_reach_m).tolist()
        ahead = (start + np.array([lanelet_length[x] for x in flat], dtype=np.float64) > s_v).tolist()
        out = []
        at = 0
        for corridor, lanelets, ok, n in zip(corridors, ids, aligned, lengths):
            if not ok:
                out.append(corridor_manoeuvre(road_map, corridor, self.config.lane_change_reach_m))
                continue
            key = (tuple(lanelets), tuple(behind[at : at + n]), tuple(ahead[at : at + n]))
            at += n
            found = self._manoeuvres.get(key)
            if found is None:
                found = corridor_manoeuvre(road_map, corridor, self.config.lane_change_reach_m)
                if len(self._manoeuvres) > 100_000:
                    self._manoeuvres.clear()
                self._manoeuvres[key] = found
            out.append(found)
        return out

def _lost_rows(gap: np.ndarray, allowed: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(rows, their medians) of the rows of `gap` (R, N) whose median (np.median of the row alone) exceeds `allowed` (R,).

    A row's median exceeds `allowed` only where at least half of its values do (a row with NaN has a NaN median: never
    more): the medians are taken for those rows only (and where `allowed` is so large that the mean of the two middle
    values could overflow), the same values, the same rows.
    """
    rows = np.flatnonzero(((gap > allowed[:, None]).sum(axis=1) >= gap.shape[1] // 2) | ~(allowed < 1e300))
    distance = np.median(gap[rows], axis=1) if rows.size else np.zeros(0)
    lost = distance > allowed[rows]
    return rows[lost], distance[lost]


def _mapping(state: _Vehicle, corridors: tuple[Corridor, ...]) -> list[tuple[int, float]]:
    """`map_corridors` of the vehicle's last corridors onto `corridors`; IndexError when a particle's slot has no entry."""
    mapping = map_corridors(state.corridors, corridors)
    route = state.particles.route
    if route.size and not (0 <= int(route.min()) and int(route.max()) < len(mapping)):
        raise IndexError(f"particle slots {int(route.min())}..{int(route.max())} for {len(mapping)} corridors")
    return mapping


def _project(p: Particles, v: int, before: tuple[Corridor, ...], old: np.ndarray, slot: np.ndarray, lost_mask: np.ndarray,
             corridors: tuple[Corridor, ...]) -> np.ndarray:
    """Row v's particles `lost_mask` (no lanelet shared with their new corridor) projected from their map position on the
    corridors `before` (slots `old`) onto their new corridor, or the nearest new one; returns the row's new slots.

    Each new corridor projects only the particles that need it (those mapped to it, and those without a corridor, which
    take the nearest): `project_to_polyline` treats every point on its own, so the values are those of projecting all.
    The projection is `project_in_window` with an infinite window: `project_to_polyline`'s (s, d) without hints, bit for
    bit, compiled.
    """
    lost = np.flatnonzero(lost_mask)
    x, y = _frenet_to_xy(before, old[lost], p.s_m[v, lost], p.d_m[v, lost])
    xy = np.column_stack([x, y])
    target = slot[lost]
    nearest = target < 0
    s_all = np.full((len(corridors), lost.size), np.nan)
    d_all = np.full((len(corridors), lost.size), np.nan)
    for k, c in enumerate(corridors):
        need = np.flatnonzero((target == k) | nearest)
        if need.size:
            s_all[k, need], d_all[k, need] = project_in_window(xy[need], np.column_stack([c.x_m, c.y_m]), c.s_m, 0.0, math.inf)
    choice = np.where(target >= 0, target, np.argmin(np.abs(d_all), axis=0))
    cols = np.arange(lost.size)
    slot = slot.copy()
    slot[lost] = choice
    p.s_m[v, lost] = s_all[choice, cols]
    p.d_m[v, lost] = d_all[choice, cols]
    return slot


def _empty(n: int) -> Particles:
    z = np.zeros((1, n))
    return Particles(
        route=np.zeros((1, n), dtype=np.int64),
        s_m=z.copy(),
        d_m=z.copy(),
        v_mps=z.copy(),
        a_mps2=z.copy(),
        stop=np.zeros((1, n), dtype=bool),
        style=np.zeros((1, n), dtype=np.int64),
        p_expected_stop=z.copy(),
        weight=np.full((1, n), 1.0 / n),
    )


def _frenet_to_xy(corridors: tuple[Corridor, ...], slot: np.ndarray, s_m: np.ndarray, d_m: np.ndarray):
    """Map-frame x, y of Frenet points on given corridors (the end segments extended straight)."""
    x = np.empty(len(slot))
    y = np.empty(len(slot))
    for k in np.unique(slot):
        c = corridors[int(k)]
        sel = slot == k
        s = s_m[sel]
        i = np.clip(np.searchsorted(c.s_m, s, side="right") - 1, 0, len(c.s_m) - 2)
        t = (s - c.s_m[i]) / (c.s_m[i + 1] - c.s_m[i])
        heading = np.unwrap(np.asarray(c.heading_rad))
        h = heading[i] + np.clip(t, 0.0, 1.0) * (heading[i + 1] - heading[i])
        x[sel] = c.x_m[i] + t * (c.x_m[i + 1] - c.x_m[i]) - d_m[sel] * np.sin(h)
        y[sel] = c.y_m[i] + t * (c.y_m[i + 1] - c.y_m[i]) + d_m[sel] * np.cos(h)
    return x, y
