"""The pure part of the corridors stage: `CorridorsConfig` and `CorridorBuilder`.

See the package docstring for the rules; nothing here touches the bus or the
wall clock (time comes from `header.stamp_ns`).
"""

from __future__ import annotations

import collections
import logging
import math
from dataclasses import dataclass, field
from typing import Mapping

import numpy as np

from bus_schemas import AgentType, Corridor, CorridorSet, Header, MatchStatus, SceneInfo, TrackFrame, VehicleCorridors
from stages.lib.base import ConfigMixin, Issue, StageResult, check_ranges, isolate
from stages.lib.caps import keep_nearest, map_centre_m
from stages.lib.kinematic_state import EstimatorConfig, KinematicEstimator, KinematicState
from stages.lib.maps import (  # the scene-map cache moved to the library; these names stay importable from here
    MAP_MAX_BYTES,
    Projection,
    RoadMap,
    SceneMap,
    SceneMaps,
    data_folder,
    kernels,
    local_map_file,
    parse_projection,
    resolve_projection,
    shown_map_name,
    wrap_angle_rad,
)

from stages.corridors.matching import LaneletIndex, LaneletMatch, select_lanelets
from stages.corridors.routes import RouteCache, RouteGeometry, cut_corridor, max_separation_m, project_vehicle, route_hash

_NS = 1e-9
#: on the bus (``update``) a frame stamped at most this much before the newest one seen arrived late and is skipped;
#: further back, a source that started over (every track reset, ``stamp_backwards``)
LATE_FRAME_NS = 500_000_000
#: a step between two frames' stamps below this (1 ms: no tracker runs at 1 kHz) says the stamps are not nanoseconds
MIN_FRAME_STEP_NS = 1_000_000
#: the agent type values a tracker may send that are a type (``AgentType``; 0 is UNKNOWN)
_KNOWN_TYPES = frozenset(int(t) for t in AgentType if t is not AgentType.UNKNOWN)


@dataclass(frozen=True, kw_only=True)
class CorridorsConfig(ConfigMixin):
    """Parameters of the corridors stage (package docstring, docs/method.md §5)."""

    horizon_s: float = 4.0
    a_plan_mps2: float = 2.0
    extra_length_m: float = 10.0
    behind_m: float = 5.0
    resample_step_m: float = 0.5
    match_max_distance_m: float = 1.5
    match_max_heading_rad: float = 0.8
    ambiguity_margin_m: float = 1.0
    continuity_margin_m: float = 1.0
    entry_extension_m: float = 50.0
    max_corridors_per_vehicle: int = 8
    max_objects: int = 200
    merge_tolerance_m: float = 1.0
    route_length_m: float = 150.0
    lane_change_corridors: bool = True
    lane_change_length_m: float = 20.0
    frenet_window_m: float = 10.0
    heading_window_s: float = 1.0
    heading_min_travel_m: float = 2.0
    yaw_agreement_rad: float = 0.5
    track_timeout_s: float = 2.0
    projection: str = "auto"
    fuse_reported_velocity: bool = True
    state_accel_noise_bank: tuple[float, ...] = (1.0, 3.0, 10.0)
    data: str = ""  # local data folder whose maps/ holds the scene's map (by name); "": the embedded stages/data/taf-bw

    def __post_init__(self) -> None:
        positive = ("horizon_s", "resample_step_m", "route_length_m", "lane_change_length_m", "frenet_window_m", "heading_window_s",
                    "heading_min_travel_m", "track_timeout_s", "match_max_heading_rad", "yaw_agreement_rad")
        non_negative = ("a_plan_mps2", "extra_length_m", "behind_m", "match_max_distance_m", "ambiguity_margin_m", "continuity_margin_m",
                        "entry_extension_m", "merge_tolerance_m")
        check_ranges(self, positive=positive, non_negative=non_negative)
        if self.max_corridors_per_vehicle < 1:
            raise ValueError(f"max_corridors_per_vehicle = {self.max_corridors_per_vehicle}: must be >= 1")
        if self.max_objects < 1:
            raise ValueError(f"max_objects = {self.max_objects}: must be >= 1")
        try:
            EstimatorConfig(accel_noise_bank=self.state_accel_noise_bank)
        except ValueError as exc:
            raise ValueError(f"state_accel_noise_bank: {exc}") from None
        object.__setattr__(self, "state_accel_noise_bank", tuple(float(q) for q in self.state_accel_noise_bank))
        if parse_projection(self.projection) is Projection.UNKNOWN:
            known = ", ".join(p.name.lower() for p in Projection if p is not Projection.UNKNOWN)
            raise ValueError(f"projection = {self.projection!r}: expected one of {known}")

    def ahead_m(self, speed_mps: float) -> float:
        """Corridor length ahead of the vehicle: v0·T + ½·a_plan·T² + extra (docs/method.md §5)."""
        t = self.horizon_s
        return max(speed_mps, 0.0) * t + 0.5 * self.a_plan_mps2 * t * t + self.extra_length_m


# --------------------------------------------------------------------------- maps of scenes


def _route_options(scene_maps: SceneMaps) -> tuple:
    """Route options of the config the cache was made with (default `CorridorsConfig`), as when the cache lived here."""
    cfg = scene_maps.config if isinstance(scene_maps.config, CorridorsConfig) else CorridorsConfig()
    return (cfg.route_length_m, cfg.lane_change_corridors, cfg.lane_change_length_m, cfg.resample_step_m)


def _matching_indices(scene_maps: SceneMaps, scene_map: SceneMap) -> tuple[LaneletIndex, RouteCache] | None:
    """The lanelet index and route cache of a loaded map, built once per cache entry (`SceneMap.derived`)."""
    options = _route_options(scene_maps)
    route_length_m, lane_changes, lane_change_length_m, _step_m = options

    def build(road_map: RoadMap) -> tuple[LaneletIndex, RouteCache]:
        routes = RouteCache(road_map, route_length_m, lane_changes=lane_changes, lane_change_length_m=lane_change_length_m)
        return LaneletIndex(road_map), routes

    return scene_map.derived(("corridors", options), build)


# --------------------------------------------------------------------------- per-track state


@dataclass(slots=True)
class _Track:
    """What the builder remembers about one track between frames."""

    last_stamp_ns: int
    history: collections.deque = field(default_factory=lambda: collections.deque(maxlen=64))
    motion_heading_rad: float | None = None
    matched: tuple[int, ...] = ()
    routes: dict[tuple[int, ...], int] = field(default_factory=dict)
    emitted: frozenset[int] = frozenset()
    frenet: dict[int, tuple[int, float]] = field(default_factory=dict)
    speed_mps: float = 0.0
    # the last frame's route plan (`CorridorBuilder._plan`): (key, plan), the key its whole input by content
    plan: tuple | None = None
    # the continuity set of `matched` (`CorridorBuilder._allowed`): (road map, matched, allowed), re-used while both repeat
    allowed: tuple | None = None


@dataclass(frozen=True, slots=True)
class _Kinematics:
    speed_mps: float
    heading_rad: float
    heading_ambiguous: bool
    heading_confident: bool
    heading_known: bool = True


@dataclass(slots=True)
class _Candidate:
    path: tuple[int, ...]
    geometry: RouteGeometry
    match: LaneletMatch | None  # None only inside `CorridorBuilder._plan`
    s_m: float
    d_m: float
    corridor_id: int = -1
    corridor: Corridor | None = None


def _route_overlap(old: tuple[int, ...], new: tuple[int, ...]) -> int:
    """Lanelets two routes share when one continues the other consistently; 0 if they do not."""
    for a, b in ((old, new), (new, old)):
        if b[0] in a:
            tail = a[a.index(b[0]) :]
            n = min(len(tail), len(b))
            if tail[:n] == b[:n]:
                return n
    return 0


# --------------------------------------------------------------------------- the core


class CorridorBuilder:
    """TrackFrame (+ latched SceneInfo) -> CorridorSet; see the package docstring."""

    def __init__(
        self,
        config: CorridorsConfig,
        *,
        scene_maps: SceneMaps | None = None,
        producer: str = "corridors",
        log: logging.Logger | None = None,
    ) -> None:
        self.config = config
        self.producer = producer
        self.log = log
        self.scene_maps = scene_maps or SceneMaps(config)
        self._scene_id: str | None = None
        self._scene_content: tuple | None = None  # what of the scene the map depends on (``_scene_content``)
        self._scene_ignored: tuple | None = None  # another content under the same scene_id, already reported
        self._map: SceneMap | None = None
        self._indices: tuple[LaneletIndex, RouteCache] | None = None  # of `_map` (`_matching_indices`)
        self._centre_of: object = False  # the road map whose centre `_centre` is (False: none yet)
        self._centre: np.ndarray | None = None
        self._tracks: dict[int, _Track] = {}
        self._last_stamp_ns: int | None = None
        self.estimator = KinematicEstimator(
            EstimatorConfig(fuse_reported=config.fuse_reported_velocity, accel_noise_bank=config.state_accel_noise_bank)
        )
        self._estimated_ns: dict[int, int] = {}
        kernels.warm_up()  # the compiled kernels loaded now, not on the first frame

    @property
    def scene_map(self) -> SceneMap | None:
        """The map of the current scene (None before the first scene)."""
        return self._map

    @property
    def tracked_ids(self) -> frozenset[int]:
        """Track ids with state kept between frames (dropped after `track_timeout_s` unseen)."""
        return frozenset(self._tracks)

    # ----- entry point -------------------------------------------------------

    def update(self, inputs: Mapping[str, object]) -> StageResult:
        """One frame: `inputs["track_frame"]` (TrackFrame) and `inputs["scene"]` (SceneInfo or absent)."""
        frame = inputs.get("track_frame")
        scene = inputs.get("scene")
        if not isinstance(frame, TrackFrame):
            return StageResult(issues=[Issue("no_frame", -1, "update without a track_frame")])
        stamp, last = int(frame.header.stamp_ns), self._last_stamp_ns
        if last is not None and 0 < last - stamp <= LATE_FRAME_NS:
            # a frame that arrived after a newer one (the bus or the tracker reordered them): skipped, so that the
            # vehicles' states go on from the newer frame; before, it reset every track (stamp_backwards) and the other
            # stages, which reset only after track_timeout_s, disagreed. A step back beyond LATE_FRAME_NS is a source
            # that started over: process resets its state (stamp_backwards)
            return StageResult(issues=[Issue("frame_late", -1, f"frame {frame.header.frame_index} stamped {(last - stamp) / 1e6:.0f} ms"
                                             " before the last one: arrived out of order, skipped (no CorridorSet; the"
                                             " tracks go on from the newer frame)")])
        corridor_set, issues = self.process(frame, scene if isinstance(scene, SceneInfo) else None)
        return StageResult(outputs={"corridor_set": corridor_set}, issues=issues)

    def process(self, frame: TrackFrame, scene: SceneInfo | None) -> tuple[CorridorSet, list[Issue]]:
        """The pure function behind `update`: (output, issues)."""
        issues: list[Issue] = []
        scene_map = self._scene(frame, scene, issues)
        stamp = int(frame.header.stamp_ns)
        self._check_step(stamp, scene, issues)
        self._expire(stamp, issues)
        n = len(frame)
        entries: list[VehicleCorridors | None] = [None] * n
        to_match: list[tuple[int, int, AgentType, _Kinematics]] = []
        seen: set[int] = set()
        states: dict[int, KinematicState] = {}
        kept = self._cap(frame, scene_map, issues)
        if n and not any(t in _KNOWN_TYPES for t in np.asarray(frame.agent_types).tolist()):
            # (each object has its own unknown_type too; this says what it means for the frame, once per episode)
            issues.append(Issue("all_untyped", -1, f"all {n} objects have agent type 0 (unknown) or a value that is no type: none is"
                                " predicted, they are obstacles only; a tracker that does not classify sends 1 (car) for what it wants predicted"))
        for row in range(n):
            track_id = int(frame.track_ids[row])
            if kept is not None and not kept[row]:  # beyond max_objects: an entry without corridors, nothing computed
                skipped = KinematicState(math.nan, math.nan, math.nan, math.nan, False, "unknown", math.nan)
                try:
                    agent_type = AgentType(int(frame.agent_types[row]))
                except ValueError:
                    agent_type = AgentType.UNKNOWN
                entries[row] = _entry(track_id, agent_type, MatchStatus.BAD_STATE, skipped, math.nan)
                continue
            agent_type = self._agent_type(int(frame.agent_types[row]), track_id, issues)
            vx, vy = float(frame.vx_mps[row]), float(frame.vy_mps[row])
            reported_speed = math.hypot(vx, vy) if math.isfinite(vx) and math.isfinite(vy) else math.nan
            unknown = KinematicState(math.nan, math.nan, math.nan, math.nan, False, "unknown", reported_speed)
            if track_id in seen:
                issues.append(Issue("duplicate_track", track_id, "track id appears twice in one frame; later row skipped"))
                entries[row] = _entry(track_id, agent_type, MatchStatus.BAD_STATE, unknown)
                continue
            seen.add(track_id)
            x, y = float(frame.x_m[row]), float(frame.y_m[row])
            if math.isfinite(x) and math.isfinite(y):
                state = self.estimator.update(track_id, stamp, x, y, vx, vy, issues)
                self._estimated_ns[track_id] = stamp
                if self.estimator.started_ns(track_id) == stamp:
                    # a new state (a jump, a gap, a re-used id): what this builder kept of the track (its positions for
                    # the heading and the fallback speed, its routes) belongs to the car before; a speed of 113 m/s
                    # came from the chord across the jump
                    self._tracks.pop(track_id, None)
            else:
                state = unknown
            states[row] = state
            if not agent_type.is_vehicle:
                entries[row] = _entry(track_id, agent_type, MatchStatus.NOT_A_VEHICLE, state)
                continue
            kin = self._kinematics(frame, row, track_id, stamp, state)
            if kin is None and state.source == "unknown" and math.isfinite(x) and math.isfinite(y):
                if scene_map is None or scene_map.road_map is None:
                    entries[row] = _entry(track_id, agent_type, MatchStatus.OFF_MAP, state)
                    continue
                issues.append(Issue("state_pending", track_id, "first sample with no usable speed: corridors from the next frame"))
                entries[row] = _entry(track_id, agent_type, MatchStatus.BAD_STATE, state)
                continue
            if kin is None:
                detail = f"non-finite state x={frame.x_m[row]} y={frame.y_m[row]} vx={vx} vy={vy} yaw={frame.yaw_rad[row]}"
                issues.append(Issue("bad_state", track_id, detail))
                entries[row] = _entry(track_id, agent_type, MatchStatus.BAD_STATE, state)
                continue
            if scene_map is None or scene_map.road_map is None:
                entries[row] = _entry(track_id, agent_type, MatchStatus.OFF_MAP, state, kin.speed_mps)
                continue
            to_match.append((row, track_id, agent_type, kin))
        if to_match:  # a vehicle whose matching or corridors raise is left out (found by bisection), not the frame
            def attempt(idx: list[int]) -> list[Issue]:
                found: list[Issue] = []
                self._match_and_build(frame, scene_map, [to_match[i] for i in idx], entries, found, states)
                return found

            found, failed = isolate(range(len(to_match)), attempt)
            issues.extend(found)
            for i, exc in failed:
                row, track_id, agent_type, kin = to_match[i]
                issues.append(Issue("vehicle_failed", track_id, f"matching or building corridors raised {type(exc).__name__}: {exc}: BAD_STATE"))
                entries[row] = _entry(track_id, agent_type, MatchStatus.BAD_STATE, states[row], kin.speed_mps)
        warning = self.estimator.warning()
        if warning is not None and self.log is not None:
            self.log.warning("%s", warning)
        header = Header(
            run_id=frame.header.run_id,
            frame_index=frame.header.frame_index,
            stamp_ns=stamp,
            producer=self.producer,
            source_wall_ns=frame.header.source_wall_ns,
        )
        scene_id = scene.scene_id if scene is not None else frame.scene_id
        return CorridorSet(header=header, scene_id=scene_id, vehicles=tuple(entries)), issues

    def _cap(self, frame: TrackFrame, scene_map: SceneMap | None, issues: list[Issue]):
        """Mask of the rows within `max_objects` (nearest to the map's centre, `stages.lib.caps`), or None when all are."""
        cap = self.config.max_objects
        if len(frame) <= cap:
            return None
        road_map = scene_map.road_map if scene_map is not None else None
        if self._centre_of is not road_map:
            self._centre_of, self._centre = road_map, map_centre_m(road_map)
        xy = np.column_stack([np.asarray(frame.x_m, np.float64), np.asarray(frame.y_m, np.float64)])
        kept, dropped = keep_nearest(xy, self._centre, cap)
        issues.append(Issue("objects_capped", -1, f"{dropped} of {len(frame)} objects beyond max_objects = {cap} (the farthest from the map's centre): BAD_STATE without corridors"))
        return kept

    # ----- scene and time ------------------------------------------------------

    def _scene(self, frame: TrackFrame, scene: SceneInfo | None, issues: list[Issue]) -> SceneMap | None:
        if scene is None:
            issues.append(Issue("no_map", -1, "no SceneInfo received yet: every vehicle is OFF_MAP"))
            return None
        content = _scene_content(scene)
        if scene.scene_id == self._scene_id and content != self._scene_content and content != self._scene_ignored:
            # the stages take a scene once per scene_id: a tracker that corrects its map, projection or origin under the
            # same id would otherwise be ignored without a word (once per such content)
            self._scene_ignored = content
            issues.append(Issue("scene_changed_same_id", -1, f"scene {scene.scene_id!r} published again with another map,"
                                " projection or origin: ignored (the stages load a scene once per scene_id; give a changed"
                                " scene a new scene_id)"))
        if scene.scene_id != self._scene_id:
            self._scene_id, self._scene_content, self._scene_ignored = scene.scene_id, content, None
            self._map = self.scene_maps.get(scene, self.config.projection)
            self._indices = None
            if self._map.road_map is not None:
                try:
                    self._indices = _matching_indices(self.scene_maps, self._map)
                except Exception as error:  # noqa: BLE001 - as a map that fails to load: unusable, not a crash per frame
                    self._map = SceneMap(None, (f"map_load_failed: {type(error).__name__}: {error}",), self._map.projection)
            self._tracks.clear()
            self.estimator.reset()
            self._estimated_ns.clear()
            for problem in self._map.problems:
                kind = "map_sha256_mismatch" if problem.startswith("map_sha256_mismatch") else "map_problem"
                issues.append(Issue(kind, -1, problem))
            if self.log is not None:
                road_map = self._map.road_map
                self.log.info(
                    "scene loaded: scene_id=%s map=%s projection=%s car_lanelets=%d problems=%d",
                    scene.scene_id,
                    shown_map_name(scene),
                    self._map.projection.name.lower(),
                    len(road_map.lanelet_ids) if road_map is not None else 0,
                    len(self._map.problems),
                )
        if self._map is None or self._map.road_map is None:
            detail = "; ".join(self._map.problems) if self._map is not None else "no map"
            issues.append(Issue("no_map", -1, f"map {shown_map_name(scene)} unusable: {detail}"))
        if frame.scene_id and frame.scene_id != scene.scene_id:
            issues.append(Issue("scene_mismatch", -1, f"frame names scene {frame.scene_id}, latched scene is {scene.scene_id}"))
        return self._map

    def _check_step(self, stamp_ns: int, scene: SceneInfo | None, issues: list[Issue]) -> None:
        """One ``stamp_step_implausible`` issue per frame whose stamp is less than ``MIN_FRAME_STEP_NS`` after the last
        one: stamps in milliseconds or microseconds (every speed and acceleration from them is wrong, and the stages
        after this one drop the vehicles as out of range), said where the cause is."""
        step = stamp_ns - self._last_stamp_ns if self._last_stamp_ns is not None else 0
        if 0 < step < MIN_FRAME_STEP_NS:
            rate = scene.frame_rate_hz if scene is not None else math.nan
            said = f" where the SceneInfo says {rate:g} Hz ({1e9 / rate:,.0f} ns a frame)" if math.isfinite(rate) and rate > 0 else ""
            issues.append(Issue("stamp_step_implausible", -1, f"stamps advance {step} ns from the last frame{said}: header.stamp_ns"
                                " must be nanoseconds (milliseconds or microseconds?); speeds and accelerations from them are wrong"))

    def _expire(self, stamp_ns: int, issues: list[Issue]) -> None:
        if self._last_stamp_ns is not None and stamp_ns < self._last_stamp_ns:
            issues.append(Issue("stamp_backwards", -1, f"stamp {stamp_ns} < {self._last_stamp_ns}: track state reset"))
            self._tracks.clear()
            self.estimator.reset()
            self._estimated_ns.clear()
        self._last_stamp_ns = stamp_ns
        timeout_ns = self.config.track_timeout_s / _NS
        stale = [k for k, t in self._tracks.items() if stamp_ns - t.last_stamp_ns > timeout_ns]
        for k in stale:
            del self._tracks[k]
        for k in [k for k, t in self._estimated_ns.items() if stamp_ns - t > timeout_ns]:
            del self._estimated_ns[k]
            self.estimator.forget(k)

    @staticmethod
    def _agent_type(value: int, track_id: int, issues: list[Issue]) -> AgentType:
        try:
            agent_type = AgentType(value)
        except ValueError:
            agent_type = AgentType.UNKNOWN
        if agent_type is AgentType.UNKNOWN:
            issues.append(Issue("unknown_type", track_id, f"agent type {value}: treated as not a vehicle"))
        return agent_type

    # ----- kinematics ------------------------------------------------------------

    def _kinematics(self, frame: TrackFrame, row: int, track_id: int, stamp: int, state: KinematicState) -> _Kinematics | None:
        """Speed and heading for matching; heading from the track's own motion when they disagree.

        The speed is the estimator's (from positions; the reported one at a
        track's first sample).

        The motion heading is the chord from the newest earlier position at
        least `heading_min_travel_m` away (within `heading_window_s`). The
        reported yaw is used when it agrees with it within
        `yaw_agreement_rad`. A stopped car keeps its last motion heading.
        Without any motion history the yaw is used, and the direction is
        ambiguous (matched modulo pi) when yaw and reported velocity disagree
        (the k733 quirk); below 1 m/s it is not known at all (the K729 yaw
        of a standing car drifts by up to 90 degrees).
        """
        cfg = self.config
        x, y = float(frame.x_m[row]), float(frame.y_m[row])
        if not (math.isfinite(x) and math.isfinite(y)):
            return None
        vx, vy, yaw = float(frame.vx_mps[row]), float(frame.vy_mps[row]), float(frame.yaw_rad[row])
        track = self._tracks.get(track_id)
        if track is None:
            track = _Track(last_stamp_ns=stamp)
            self._tracks[track_id] = track
        motion = None
        history_speed = None
        window_ns = cfg.heading_window_s / _NS
        for t_ns, hx, hy in reversed(track.history):
            if stamp - t_ns > window_ns or t_ns >= stamp:
                break
            dist = math.hypot(x - hx, y - hy)
            if dist >= cfg.heading_min_travel_m:
                motion = math.atan2(y - hy, x - hx)
                history_speed = dist / ((stamp - t_ns) * _NS)
                break
        if track.history and history_speed is None:
            t_ns, hx, hy = track.history[0]
            if 0 < stamp - t_ns <= window_ns:
                history_speed = math.hypot(x - hx, y - hy) / ((stamp - t_ns) * _NS)
        track.history.append((stamp, x, y))
        track.last_stamp_ns = stamp
        velocity_ok = math.isfinite(vx) and math.isfinite(vy)
        speed = state.speed_mps if math.isfinite(state.speed_mps) else history_speed
        if speed is None:
            return None
        yaw_ok = math.isfinite(yaw)
        if motion is not None:
            track.motion_heading_rad = motion
            if yaw_ok and abs(float(wrap_angle_rad(yaw - motion))) <= cfg.yaw_agreement_rad:
                return _Kinematics(speed, yaw, False, True)
            return _Kinematics(speed, motion, False, True)
        if track.motion_heading_rad is not None:
            return _Kinematics(speed, track.motion_heading_rad, False, False)
        moving = velocity_ok and speed >= 1.0
        if yaw_ok:
            ambiguous = moving and abs(float(wrap_angle_rad(math.atan2(vy, vx) - yaw))) > 0.5 * math.pi
            return _Kinematics(speed, yaw, ambiguous, False, heading_known=moving)
        if moving:
            return _Kinematics(speed, math.atan2(vy, vx), True, False)
        return None

    # ----- matching and corridors -----------------------------------------------

    def _match_and_build(self, frame: TrackFrame, scene_map: SceneMap, to_match, entries, issues: list[Issue], states) -> None:
        cfg = self.config
        index = self._indices[0]
        rows = [r for r, *_ in to_match]
        points = np.column_stack([np.asarray(frame.x_m)[rows], np.asarray(frame.y_m)[rows]])
        meas = index.measure(points, max_distance_m=cfg.match_max_distance_m, entry_extension_m=cfg.entry_extension_m)
        for k, (row, track_id, agent_type, kin) in enumerate(to_match):
            track = self._tracks[track_id]
            matches, near = select_lanelets(
                index,
                meas,
                k,
                heading_rad=kin.heading_rad,
                heading_ambiguous=kin.heading_ambiguous,
                heading_confident=kin.heading_confident,
                heading_known=kin.heading_known,
                allowed=self._continuity(scene_map.road_map, track),
                previous=track.matched,
                max_heading_rad=cfg.match_max_heading_rad,
                ambiguity_margin_m=cfg.ambiguity_margin_m,
                continuity_margin_m=cfg.continuity_margin_m,
            )
            if not matches:
                if near:
                    issues.append(Issue("off_map_heading", track_id, f"near car lanelets but heading {kin.heading_rad:.2f} rad agrees with none (wrong way or manoeuvring)"))
                else:
                    issues.append(Issue("off_map", track_id, f"no car lanelet within {cfg.match_max_distance_m} m of ({points[k, 0]:.1f}, {points[k, 1]:.1f})"))
                entries[row] = _entry(track_id, agent_type, MatchStatus.OFF_MAP, states[row], kin.speed_mps)
                continue
            corridors, truncated = self._corridors(scene_map, track, points[k], kin, matches)
            if truncated:
                issues.append(Issue("corridors_truncated", track_id, f"{truncated} corridors beyond max_corridors_per_vehicle dropped"))
            track.matched = tuple(m.lanelet_id for m in matches)
            track.speed_mps = kin.speed_mps
            entries[row] = VehicleCorridors(
                track_id=track_id,
                agent_type=agent_type,
                status=MatchStatus.MATCHED,
                lanelet_id=matches[0].lanelet_id,
                match_distance_m=matches[0].centre_distance_m,
                speed_mps=kin.speed_mps,
                corridors=corridors,
                **_state_fields(states[row]),
            )

    def _continuity(self, road_map: RoadMap, track: _Track) -> frozenset[int]:
        """`_allowed` for the track's matched lanelets, kept on the track while the map and those lanelets stay."""
        if track.allowed is None or track.allowed[0] is not road_map or track.allowed[1] != track.matched:
            track.allowed = (road_map, track.matched, self._allowed(road_map, track.matched))
        return track.allowed[2]

    @staticmethod
    def _allowed(road_map: RoadMap, previous: tuple[int, ...]) -> frozenset[int]:
        """Continuity set: the previous lanelets, two levels of successors, and siblings."""
        allowed = set(previous)
        for lanelet_id in previous:
            for succ in road_map.successors(lanelet_id):
                allowed.add(succ)
                allowed.update(road_map.successors(succ))
            for pred in road_map.predecessors(lanelet_id):
                allowed.update(road_map.successors(pred))
        return frozenset(allowed)

    def _predecessor(self, road_map: RoadMap, lanelet_id: int, track: _Track) -> int | None:
        """The lanelet the vehicle came from.

        A previously matched or routed predecessor; else the only one; else
        the one nearest to where the track was `behind_m` ago; else the one
        continuing the lanelet's start heading most closely.
        """
        preds = road_map.predecessors(lanelet_id)
        if not preds:
            return None
        for known in (set(track.matched), set().union(*track.routes) if track.routes else set()):
            for pred in preds:
                if pred in known:
                    return pred
        if len(preds) == 1:
            return preds[0]
        if track.history:
            _t, x, y = track.history[-1]
            for _t_ns, hx, hy in reversed(track.history):
                if math.hypot(hx - x, hy - y) >= self.config.behind_m:
                    back = np.array([hx, hy])
                    return min(
                        preds,
                        key=lambda p: (float(np.hypot(*(road_map.lanelet(p).centreline.points_m - back).T).min()), p),
                    )
        start = road_map.lanelet(lanelet_id).centreline.heading_rad[0]
        return min(preds, key=lambda p: (abs(float(wrap_angle_rad(road_map.lanelet(p).centreline.heading_rad[-1] - start))), p))

    def _corridors(self, scene_map: SceneMap, track: _Track, xy, kin: _Kinematics, matches):
        cfg = self.config
        road_map, cache = scene_map.road_map, self._indices[1]
        ahead = cfg.ahead_m(kin.speed_mps)
        dt_s = 0.0
        if len(track.history) >= 2:
            dt_s = (track.history[-1][0] - track.history[-2][0]) * _NS
        position = (float(xy[0]), float(xy[1]))
        starts = []  # per match: its lanelet, the predecessor in front of it (if any) and the route length class
        for match in matches:
            front: tuple[int, ...] = ()
            if match.s_m - cfg.behind_m < 0.0:
                pred = self._predecessor(road_map, match.lanelet_id, track)
                front = (pred,) if pred is not None else ()
            starts.append((match.lanelet_id, front, cache.length_steps(match.s_m + ahead)))
        candidates = [
            _Candidate(path, geometry, matches[k], s_first + matches[k].s_m, matches[k].d_m, corridor_id)
            for path, geometry, k, s_first, corridor_id in self._plan(road_map, cache, track, tuple(starts))
        ]
        for cand in candidates:
            # continuity (docs/method.md §5.5): search near the previous s of this corridor, else near the match
            hint = cand.s_m
            previous = track.frenet.get(cand.corridor_id)
            if previous is not None and previous[0] in cand.geometry.lanelet_ids:
                k = cand.geometry.lanelet_ids.index(previous[0])
                hint = cand.geometry.lanelet_starts[k] + previous[1] + track.speed_mps * dt_s
            cand.s_m, cand.d_m = project_vehicle(cand.geometry, position, hint, cfg.frenet_window_m)
        for cand in candidates:
            cand.corridor = cut_corridor(
                cand.geometry,
                corridor_id=cand.corridor_id,
                vehicle_s_m=cand.s_m,
                vehicle_d_m=cand.d_m,
                behind_m=cfg.behind_m,
                ahead_m=ahead,
                step_m=cfg.resample_step_m,
            )
        # merge near-identical corridors; keep ids seen last frame, then the most map-backed
        order = sorted(
            range(len(candidates)),
            key=lambda i: (
                candidates[i].corridor_id not in track.emitted,
                -candidates[i].corridor.extension_start_s_m,
                i,
            ),
        )
        vehicle_index = int(round(cfg.behind_m / cfg.resample_step_m))
        kept: list[_Candidate] = []
        for i in order:
            cand = candidates[i]
            if any(max_separation_m(cand.corridor, other.corridor, vehicle_index) <= cfg.merge_tolerance_m for other in kept):
                continue
            kept.append(cand)
        truncated = max(0, len(kept) - cfg.max_corridors_per_vehicle)
        kept = kept[: cfg.max_corridors_per_vehicle]
        rank = {id(c): i for i, c in enumerate(candidates)}
        kept.sort(key=lambda c: rank[id(c)])  # output in match, then route order
        track.routes = {c.path: c.corridor_id for c in candidates}
        track.emitted = frozenset(c.corridor_id for c in kept)
        track.frenet = {}
        for c in kept:
            geometry = c.geometry
            k = geometry.lanelet_at(c.s_m)
            track.frenet[c.corridor_id] = (geometry.lanelet_ids[k], c.s_m - geometry.lanelet_starts[k])
        return tuple(c.corridor for c in kept), truncated

    def _plan(self, road_map: RoadMap, cache: RouteCache, track: _Track, starts: tuple) -> tuple:
        """The vehicle's candidate routes: (path, geometry, match index, where the match's lanelet starts on it, corridor id).

        A function of `starts` (per match: lanelet, predecessor in front,
        `RouteCache.length_steps`) and the track's previous routes and ids
        only: the route enumeration, the redundant lane changes dropped and
        the ids inherited (`_assign_ids`). While a vehicle stays on the same
        lanelets these repeat from frame to frame, so the track keeps the
        last plan with its key (by content, never by track id: a track whose
        lanelets or routes changed, or a re-used track id, gets a fresh one)
        and a frame re-uses it when the key is the same.
        """
        key = (cache, starts, tuple(track.routes.items()))  # the cache (by identity): the map the routes are on
        if track.plan is not None and track.plan[0] == key:
            return track.plan[1]
        candidates: list[_Candidate] = []
        where: dict[int, tuple[int, float]] = {}
        for k, (lanelet_id, front, steps) in enumerate(starts):
            for path in cache.routes_for(lanelet_id, steps):
                geometry = cache.geometry(front + path)
                cand = _Candidate(path, geometry, None, math.nan, math.nan)
                where[id(cand)] = (k, geometry.lanelet_starts[len(front)])
                candidates.append(cand)
        candidates = self._drop_redundant_lane_changes(road_map, candidates)
        self._assign_ids(track, candidates)
        plan = tuple((c.path, c.geometry, *where[id(c)], c.corridor_id) for c in candidates)
        track.plan = (key, plan)
        return plan

    @staticmethod
    def _drop_redundant_lane_changes(road_map: RoadMap, candidates: list[_Candidate]) -> list[_Candidate]:
        """Drop a lane-change route whose part after the switch ends a plain route of the same vehicle.

        A vehicle matched to two neighbouring lanes already has a corridor
        along the other lane; switching into it later adds nothing.
        """
        def switch_index(path: tuple[int, ...]) -> int | None:
            for k in range(1, len(path)):
                if path[k] not in road_map.successors(path[k - 1]):
                    return k
            return None

        switches = [switch_index(c.path) for c in candidates]
        plain = [c.path for c, k in zip(candidates, switches) if k is None]
        kept = []
        for cand, k in zip(candidates, switches):
            if k is not None:
                after = cand.path[k:]
                if any(len(p) >= len(after) and p[len(p) - len(after) :] == after for p in plain):
                    continue
            kept.append(cand)
        return kept

    @staticmethod
    def _assign_ids(track: _Track, candidates: list[_Candidate]) -> None:
        """Inherit the id of the previous frame's route each candidate continues, else hash the route.

        Pairs (candidate, old route) are taken by decreasing overlap; an old
        id goes to one candidate only.
        """
        pairs = []
        for i, cand in enumerate(candidates):
            for old, cid in track.routes.items():
                overlap = _route_overlap(old, cand.path)
                if overlap:
                    pairs.append((-overlap, cid, i))
        pairs.sort()
        taken_ids: set[int] = set()
        for _neg, cid, i in pairs:
            if candidates[i].corridor_id < 0 and cid not in taken_ids:
                candidates[i].corridor_id = cid
                taken_ids.add(cid)
        for cand in candidates:
            if cand.corridor_id < 0:
                cid = route_hash(cand.path)
                while cid in taken_ids:
                    cid = (cid + 1) & ((1 << 63) - 1)
                cand.corridor_id = cid
                taken_ids.add(cid)


def _state_fields(state: KinematicState) -> dict:
    return {
        "vx_mps": state.vx_mps,
        "vy_mps": state.vy_mps,
        "accel_mps2": state.accel_mps2,
        "standing": state.standing,
        "reported_speed_mps": state.reported_speed_mps,
    }


def _entry(
    track_id: int, agent_type: AgentType, status: MatchStatus, state: KinematicState, speed_mps: float | None = None
) -> VehicleCorridors:
    """An entry without corridors; the speed is the state's unless given (a fallback from matching)."""
    speed = state.speed_mps if speed_mps is None else speed_mps
    return VehicleCorridors(
        track_id=track_id,
        agent_type=agent_type,
        status=status,
        lanelet_id=-1,
        match_distance_m=-1.0,
        speed_mps=float(speed),
        corridors=(),
        **_state_fields(state),
    )


def _scene_content(scene: SceneInfo) -> tuple:
    """What of a SceneInfo decides the map and its frame: file, sha256, projection, origin."""
    return (scene.map_name, scene.map_sha256, scene.projection, scene.origin_lat_deg, scene.origin_lon_deg)
