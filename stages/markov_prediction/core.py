"""The pure part of the markov_prediction stage: ``MarkovPredictor`` and its ``FramePrediction``.

See the package docstring for the rules; nothing here touches the bus or the
wall clock (time comes from ``header.stamp_ns``).
"""

from __future__ import annotations

import collections
import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any, Mapping

import numpy as np

from bus_schemas import (
    AccelerationProfiles,
    AgentType,
    CorridorPrediction,
    CorridorPredictions,
    CorridorRelations,
    CorridorSet,
    GridStep,
    Header,
    IntentionBelief,
    MatchStatus,
    MotionGrid,
    RelationSet,
    SceneInfo,
    TrackFrame,
)
from stages.lib.base import Issue, StageResult, isolate
from stages.lib.caps import cap_pairs
from stages.lib.datasets import DEFAULT_SIZES_M
from stages.lib.markov import InputMatrix, InputReplaced, MarkovGridConfig, gamma_from_priority, initial_state, load_or_build_stencils, psi_matrix
from stages.lib.markov.propagate import boxes_outside_grid

from stages.markov_prediction import priority as pr
from stages.markov_prediction.chain import InputPriority, PriorityPropagator
from stages.markov_prediction.config import CHAIN_MODES, MarkovPredictionConfig
from stages.markov_prediction.rasterise import Footprints, GridFrame, SparseGrid, cell_footprints, fuse, lateral_kernel, vehicle_grid

_NS = 1e-9
#: The Cartesian constant-velocity line of mode ``cv`` has this corridor id.
CV_LINE_ID = -1


# --------------------------------------------------------------------------- pairs


@dataclass(slots=True, eq=False)
class _Pair:
    """One vehicle-corridor pair of a frame, with what the chain needs (corridor arc lengths in m)."""

    track_id: int
    corridor_id: int
    probability: float
    s_m: np.ndarray
    x_m: np.ndarray
    y_m: np.ndarray
    heading_rad: np.ndarray
    curvature_1pm: np.ndarray
    speed_limit_mps: float
    s0_m: float
    v0_mps: float
    a0_mps2: float
    s_first_m: float
    length_m: float
    width_m: float
    d0_m: float = 0.0
    sigma_a0_mps2: float = 0.5
    start_rate_hz: float = 0.0  # > 0: the vehicle stands; it starts at this rate (standstill mixture)
    relation: CorridorRelations | None = None
    half_width_s_m: float = 0.0  # > 0: the initial box's half-widths from the DBN's particles (initial_box "particles")
    half_width_v_mps: float = 0.0
    input_probs: np.ndarray | None = None  # (K, M) hybrid mode: λ(0..K-1) from the AR model
    measured_v_mps: float = math.nan  # the vehicle's speed before clipping to [0, v_max] (a faster one is not chained)

    @property
    def end_s_m(self) -> float:
        return float(self.s_m[-1])

    def stay_probability(self, t_s: float | np.ndarray):
        """Weight of the standstill part at t (0 for a moving vehicle)."""
        if self.start_rate_hz <= 0:
            return 0.0 if np.ndim(t_s) == 0 else np.zeros(np.shape(t_s))
        return np.exp(-self.start_rate_hz * np.asarray(t_s, dtype=np.float64))


@dataclass(frozen=True, slots=True)
class PairInfo:
    """Identity and geometry of one predicted pair (the arrays of ``FramePrediction`` follow this order)."""

    track_id: int
    corridor_id: int
    probability: float
    vehicle_s_m: float
    s_first_m: float
    end_s_m: float


@dataclass(frozen=True, eq=False)
class FramePrediction:
    """Everything one frame's prediction computed, numpy; B pairs, K steps, N_s window cells.

    - ``position_probs`` (B, K, N_s) float32: time-point s-marginal at t_k
      (cells past the corridor's end moved to ``outside_mass``);
    - ``interval_probs`` (B, K, N_s) float32 or None: Υ([0, τ]) occupancy of step k;
    - ``velocity_probs`` (B, K, N_v) float32; ``outside_mass`` (B, K);
    - ``mean_xy_m`` (B, K, 2): probability-weighted mean of centreline points,
      ``mean_s_m`` (B, K) and ``xy_at_mean_s_m`` (B, K, 2) = X_c(E[s]);
    - ``vehicle_grids``: per track id, its sparse grid over all steps
      (``grid_distribution``), ``fused_grid`` the vehicles combined.
    """

    mode: str
    step_times_s: np.ndarray
    ds_m: float
    dv_mps: float
    pairs: tuple[PairInfo, ...]
    position_probs: np.ndarray
    interval_probs: np.ndarray | None
    velocity_probs: np.ndarray
    outside_mass: np.ndarray
    mean_xy_m: np.ndarray
    mean_s_m: np.ndarray
    xy_at_mean_s_m: np.ndarray
    grid_frame: GridFrame
    grid_distribution: str
    vehicle_grids: dict[int, SparseGrid]
    fused_grid: SparseGrid
    min_grid_value: float
    max_cells_per_step: int = 0  # 0: no cap; else the MotionGrid lists at most this many cells per step (the highest)

    def corridor_predictions(self, header: Header, scene_id: str) -> CorridorPredictions:
        """The ``CorridorPredictions`` message (s-distributions cropped to the cells ever occupied)."""
        out = []
        for b, info in enumerate(self.pairs):
            probs = self.position_probs[b]
            occupied = np.flatnonzero(probs.max(axis=0) > 0)
            lo, hi = (int(occupied[0]), int(occupied[-1]) + 1) if occupied.size else (0, 0)
            out.append(
                CorridorPrediction(
                    track_id=info.track_id,
                    corridor_id=info.corridor_id,
                    probability=float(info.probability),
                    vehicle_s_m=float(info.vehicle_s_m),
                    s_first_m=float(info.s_first_m + lo * self.ds_m),
                    s_probs=np.ascontiguousarray(probs[:, lo:hi], dtype=np.float32),
                    v_probs=np.ascontiguousarray(self.velocity_probs[b], dtype=np.float32),
                    outside_mass=self.outside_mass[b].astype(np.float32),
                    mean_x_m=self.mean_xy_m[b, :, 0].astype(np.float64),
                    mean_y_m=self.mean_xy_m[b, :, 1].astype(np.float64),
                    mean_s_m=self.mean_s_m[b].astype(np.float64),
                    x_at_mean_s_m=self.xy_at_mean_s_m[b, :, 0].astype(np.float64),
                    y_at_mean_s_m=self.xy_at_mean_s_m[b, :, 1].astype(np.float64),
                )
            )
        return CorridorPredictions(
            header=header,
            scene_id=scene_id,
            mode=self.mode,
            step_times_s=self.step_times_s.astype(np.float64),
            ds_m=float(self.ds_m),
            dv_mps=float(self.dv_mps),
            predictions=tuple(out),
        )

    def grid_cells_over_cap(self) -> int:
        """Cells above ``min_grid_value`` that ``motion_grid`` leaves out for ``max_cells_per_step``, all steps."""
        if not self.max_cells_per_step:
            return 0
        n_cells = self.grid_frame.n_cells
        over = 0
        for k in range(self.step_times_s.shape[0]):
            _cells, values = self.fused_grid.step(k, n_cells)
            over += max(0, int((values > self.min_grid_value).sum()) - self.max_cells_per_step)
        return over

    def motion_grid(self, header: Header, scene_id: str) -> MotionGrid:
        """The ``MotionGrid`` message: the fused grid, cells above ``min_grid_value``, one COO layer per step."""
        frame = self.grid_frame
        steps = []
        for k in range(self.step_times_s.shape[0]):
            cells, values = self.fused_grid.step(k, frame.n_cells)
            keep = values > self.min_grid_value
            if self.max_cells_per_step and int(keep.sum()) > self.max_cells_per_step:
                listed = np.flatnonzero(keep)
                top = listed[np.argsort(-values[listed], kind="stable")[: self.max_cells_per_step]]
                keep = np.zeros_like(keep)
                keep[top] = True
            rows, cols = np.divmod(cells[keep], frame.n_cols)
            steps.append(GridStep(rows=rows.astype(np.int32), cols=cols.astype(np.int32), values=values[keep].astype(np.float32)))
        return MotionGrid(
            header=header,
            scene_id=scene_id,
            mode=self.mode,
            distribution=self.grid_distribution,
            origin_x_m=float(frame.origin_x_m),
            origin_y_m=float(frame.origin_y_m),
            cell_m=float(frame.cell_m),
            n_rows=int(frame.n_rows),
            n_cols=int(frame.n_cols),
            min_value=float(self.min_grid_value),
            step_times_s=self.step_times_s.astype(np.float64),
            steps=tuple(steps),
        )


# --------------------------------------------------------------------------- the core


@dataclass(slots=True)
class _SpeedHistory:
    samples: collections.deque = field(default_factory=lambda: collections.deque(maxlen=64))
    last_stamp_ns: int = 0


class MarkovPredictor:
    """CorridorSet + RelationSet (+ latched SceneInfo, optional TrackFrame) -> CorridorPredictions + MotionGrid.

    ``stencils`` may be passed to share the offline matrices between
    predictors (evaluation, tests); otherwise they come from the disk cache.
    """

    def __init__(self, config: MarkovPredictionConfig, *, producer: str = "markov_prediction", stencils: Any = None) -> None:
        self.config = config
        self.producer = producer
        self.grid = MarkovGridConfig(
            ds_m=config.ds_m, dv_mps=config.dv_mps, v_max_mps=config.v_max_mps, tau_s=config.tau_s, n_steps=config.n_steps
        )
        cfg = self.grid
        self.n_s = config.window_cells
        # the initial box is laid on the window itself (the stencils' grid may have another length)
        self._window_grid = dataclasses.replace(cfg, n_s_cells=self.n_s)
        self._default_half_s_m = max(0.5 * config.ds_m, 2 * config.init_sigma_s_m)
        self._default_half_v_mps = max(0.5 * config.dv_mps, 2 * config.init_sigma_v_mps)
        self.v_centres = cfg.v_centres_mps()
        self.a_centres = cfg.input_centres_mps2()
        self.step_times_s = config.tau_s * np.arange(1, config.n_steps + 1)
        self.preference = pr.normalised_preference(config.free_driving_preference, cfg.n_inputs)
        self.psi = psi_matrix(self.a_centres, gamma=config.psi_gamma)
        self._lateral = lateral_kernel(config.grid_lateral_sigma_m, config.grid_cell_m)
        self._history: dict[int, _SpeedHistory] = {}
        self.stencils = None
        self.propagator: PriorityPropagator | None = None
        self.gaps: pr.CriticalGaps | None = None
        if config.mode in CHAIN_MODES:
            if stencils is None:
                stencils = load_or_build_stencils(cfg, config.stencil_cache_dir or None)
            self.stencils = stencils
            self.propagator = PriorityPropagator(
                stencils,
                self.psi,
                backend=config.backend,
                device=config.device,
                n_s_cells=self.n_s,
                prune_threshold=config.prune_threshold,
            )
            self.gaps = pr.CriticalGaps.build(
                self.v_centres, self.a_centres, cfg.v_max_mps, tuple(config.leader_horizons_s), config.leader_brake_mps2
            )

    # ----- entry points ---------------------------------------------------------

    def update(self, inputs: Mapping[str, object]) -> StageResult:
        """One frame: ``corridor_set`` and ``relation_set`` (same stamp), ``scene`` (latched), and the optional
        ``track_frame``, ``intention_belief`` and ``acceleration_profiles`` of the same stamp."""
        corridor_set = inputs.get("corridor_set")
        relation_set = inputs.get("relation_set")
        scene = inputs.get("scene")
        frame = inputs.get("track_frame")
        belief = inputs.get("intention_belief")
        profiles = inputs.get("acceleration_profiles")
        if not isinstance(corridor_set, CorridorSet):
            return StageResult(issues=[Issue("no_input", -1, "update without a corridor_set")])
        prediction, issues = self.process(
            corridor_set,
            relation_set if isinstance(relation_set, RelationSet) else None,
            scene if isinstance(scene, SceneInfo) else None,
            frame if isinstance(frame, TrackFrame) else None,
            intention_belief=belief if isinstance(belief, IntentionBelief) else None,
            acceleration_profiles=profiles if isinstance(profiles, AccelerationProfiles) else None,
        )
        h = corridor_set.header
        header = Header(run_id=h.run_id, frame_index=h.frame_index, stamp_ns=h.stamp_ns, producer=self.producer)
        scene_id = scene.scene_id if isinstance(scene, SceneInfo) else corridor_set.scene_id
        outputs = {
            "corridor_predictions": prediction.corridor_predictions(header, scene_id),
            "motion_grid": prediction.motion_grid(header, scene_id),
        }
        return StageResult(outputs=outputs, issues=issues)

    def process(
        self,
        corridor_set: CorridorSet,
        relation_set: RelationSet | None = None,
        scene: SceneInfo | None = None,
        track_frame: TrackFrame | None = None,
        *,
        intention_belief: IntentionBelief | None = None,
        acceleration_profiles: AccelerationProfiles | None = None,
    ) -> tuple[FramePrediction, list[Issue]]:
        """The pure function behind ``update``: the frame's prediction and the issues met."""
        issues: list[Issue] = []
        stamp = int(corridor_set.header.stamp_ns)
        given = corridor_set
        corridor_set, dropped = cap_pairs(corridor_set, self.config.max_pairs)
        skipped = {v.track_id for v, w in zip(given.vehicles, corridor_set.vehicles) if v.corridors and not w.corridors}
        if dropped:
            issues.append(Issue("pairs_capped", -1, f"{dropped} vehicle-corridor pairs beyond max_pairs = {self.config.max_pairs} (whole vehicles, in CorridorSet order): skipped this frame"))
        beliefs = self._beliefs(intention_belief, stamp, issues)
        profiles = self._profiles(acceleration_profiles, stamp, issues)
        self.observe(corridor_set)
        relations: dict[tuple[int, int], CorridorRelations] = {}
        if relation_set is None:
            if self.config.mode == "baseline":
                issues.append(Issue("no_relations", -1, "no relation_set: no leader or crossing restriction this frame"))
        elif int(relation_set.header.stamp_ns) != stamp:
            issues.append(
                Issue("stamp_mismatch", -1, f"relation_set stamp {relation_set.header.stamp_ns} != corridor_set stamp {stamp}: relations ignored")
            )
        else:
            relations = {(r.track_id, r.corridor_id): r for r in relation_set.relations}
        speed_limit = scene.speed_limit_mps if scene is not None and _positive(scene.speed_limit_mps) else self.config.default_speed_limit_mps
        pairs = self._vehicle_pairs(corridor_set, track_frame, speed_limit, issues, beliefs, profiles)
        known = {(p.track_id, p.corridor_id): p for p in pairs}
        for key, relation in relations.items():
            pair = known.get(key)
            if pair is None:
                if key[0] not in skipped:  # a vehicle left out by max_pairs has relations but no prediction: no issue of its own
                    issues.append(Issue("unknown_corridor", key[0], f"relation for corridor {key[1]}, which has no prediction: ignored"))
            else:
                pair.relation = relation
        prediction = self._predict(pairs, issues)
        over = prediction.grid_cells_over_cap()
        if over:
            issues.append(Issue("grid_capped", -1, f"{over} grid cells beyond grid_max_cells_per_step = {self.config.grid_max_cells_per_step} (the lowest values) left out of the MotionGrid"))
        return prediction, issues

    def reset(self) -> None:
        """Forget every track's history (a new sequence starts; the offline tables are kept)."""
        self._history.clear()

    def observe(self, corridor_set: CorridorSet) -> None:
        """Record each vehicle's speed at this stamp (for its measured acceleration); forget stale tracks."""
        stamp = int(corridor_set.header.stamp_ns)
        for vehicle in corridor_set.vehicles:
            if not math.isfinite(vehicle.speed_mps):
                continue
            hist = self._history.setdefault(vehicle.track_id, _SpeedHistory())
            if hist.samples and stamp <= hist.samples[-1][0]:
                continue
            hist.samples.append((stamp, float(vehicle.speed_mps)))
            hist.last_stamp_ns = stamp
        limit = int(self.config.track_timeout_s / _NS)
        for track_id in [t for t, h in self._history.items() if stamp - h.last_stamp_ns > limit]:
            del self._history[track_id]

    # ----- pairs ------------------------------------------------------------------

    def _vehicle_pairs(self, corridor_set: CorridorSet, frame, scene_limit_mps: float, issues: list[Issue], beliefs, profiles) -> list[_Pair]:
        """``_pairs`` of the frame; a vehicle whose pairs cannot be built is left out (``vehicle_failed``), not the frame."""
        vehicles = corridor_set.vehicles

        def attempt(idx: list[int]):
            found: list[Issue] = []
            subset = corridor_set if len(idx) == len(vehicles) else dataclasses.replace(corridor_set, vehicles=tuple(vehicles[i] for i in idx))
            return self._pairs(subset, frame, scene_limit_mps, found, beliefs, profiles), found

        (pairs, found), failed = isolate(range(len(vehicles)), attempt)
        issues.extend(found)
        for i, exc in failed:
            issues.append(Issue("vehicle_failed", int(vehicles[i].track_id), f"building its pairs raised {type(exc).__name__}: {exc}: vehicle not predicted"))
        return pairs

    def _window_start(self, s0_m: float, vehicle_s_m: float, half_s_m: float) -> float:
        """Where the pair's window starts: ``window_behind_m`` (or the box's half-width, if larger) behind the box's
        centre or the measured arc length, whichever lies further back."""
        return min(s0_m, vehicle_s_m) - max(self.config.window_behind_m, half_s_m)

    def _particle_box_fits(self, s0_m: float, vehicle_s_m: float, half_s_m: float, track_id: int, corridor_id: int,
                           issues: list[Issue]) -> bool:
        """Whether the particles' box (centre ``s0_m`` ± ``half_s_m``) lies whole in the window it gets.

        It does not when the particles' mean lies about a window length from
        the measured arc length, or their spread is about as wide: a particle
        filter that lost the vehicle (after a jump of its measured position
        it stays where it was, frame after frame). Then ``initial_state``
        raised and the frame was lost; now the pair takes the measurement's
        box (``particle_box_rejected``), which always lies in its window.
        """
        length = self.n_s * self.config.ds_m
        if s0_m + half_s_m <= self._window_start(s0_m, vehicle_s_m, half_s_m) + length:
            return True
        issues.append(Issue("particle_box_rejected", track_id, f"corridor {corridor_id}: the particles' box {s0_m - vehicle_s_m:+.1f}"
                            f" ± {half_s_m:.1f} m from the measured arc length does not fit the {length:.0f} m window: measurement box used"))
        return False

    def _acceleration(self, track_id: int, stamp_ns: int) -> tuple[float, float]:
        """(a0, σ_a0): the vehicle's measured acceleration and its uncertainty.

        The least-squares slope of its speed over the last ``accel_window_s``
        (0 with less than 3 samples or half the window), shrunk towards 0 by
        its own standard error σ (a0 = slope · max(0, 1 − σ²/slope²)): the
        K733 tracker's speeds jitter by ±3 m/s from frame to frame, K729's
        are smooth. σ_a0 = √(``init_sigma_a_mps2``² + min(σ, 1)²).
        """
        base = self.config.init_sigma_a_mps2
        hist = self._history.get(track_id)
        if hist is None or self.config.accel_window_s <= 0:
            return 0.0, base
        window = int(self.config.accel_window_s / _NS)
        pts = [(t, v) for t, v in hist.samples if stamp_ns - window <= t <= stamp_ns]
        if len(pts) < 3 or (pts[-1][0] - pts[0][0]) * _NS < 0.5 * self.config.accel_window_s:
            return 0.0, base
        t = np.array([p[0] for p in pts], dtype=np.float64) * _NS
        v = np.array([p[1] for p in pts])
        t -= t.mean()
        sxx = float((t * t).sum())
        slope = float((t * (v - v.mean())).sum() / sxx)
        residual = v - v.mean() - slope * t
        sigma = math.sqrt(float((residual**2).sum()) / max(len(pts) - 2, 1) / sxx)
        shrunk = slope * max(0.0, 1.0 - sigma**2 / max(slope**2, 1e-12))
        edges = self.grid.input_edges()
        return float(np.clip(shrunk, edges[0], edges[-1])), math.hypot(base, min(sigma, 1.0))

    def _beliefs(self, belief: IntentionBelief | None, stamp: int, issues: list[Issue]) -> dict[int, dict[int, Any]] | None:
        """Per track, its CorridorBeliefs by corridor id; None when the config does not use them or none fit."""
        cfg = self.config
        if cfg.corridor_weights != "intentions" and cfg.initial_box != "particles":
            return None
        if belief is None:
            issues.append(Issue("no_intentions", -1, "no intention_belief: uniform corridor weights and measured boxes this frame"))
            return None
        if int(belief.header.stamp_ns) != stamp:
            issues.append(Issue("stamp_mismatch", -1, f"intention_belief stamp {belief.header.stamp_ns} != corridor_set stamp {stamp}: ignored"))
            return None
        return {v.track_id: {c.corridor_id: c for c in v.corridors} for v in belief.vehicles}

    def _profiles(self, profiles: AccelerationProfiles | None, stamp: int, issues: list[Issue]) -> dict[tuple[int, int], np.ndarray] | None:
        """Per (track, corridor), λ(0..K-1) as a (K, M) array; None outside hybrid mode or when unusable."""
        cfg = self.config
        if cfg.mode != "hybrid":
            return None
        if profiles is None:
            issues.append(Issue("no_acceleration_profiles", -1, "hybrid mode without acceleration_profiles: every pair falls back to its measured acceleration"))
            return None
        if int(profiles.header.stamp_ns) != stamp:
            issues.append(Issue("stamp_mismatch", -1, f"acceleration_profiles stamp {profiles.header.stamp_ns} != corridor_set stamp {stamp}: ignored"))
            return None
        edges = self.grid.input_edges()
        if profiles.input_edges_mps2.shape != edges.shape or not np.allclose(profiles.input_edges_mps2, edges, atol=1e-6):
            issues.append(Issue("bad_profile", -1, f"acceleration_profiles input edges {np.round(profiles.input_edges_mps2, 3).tolist()} != the chain's {edges.tolist()}: ignored"))
            return None
        if abs(profiles.chunk_s - cfg.tau_s) > 1e-6:
            issues.append(Issue("bad_profile", -1, f"acceleration_profiles chunk_s {profiles.chunk_s} != tau_s {cfg.tau_s}: ignored"))
            return None
        out: dict[tuple[int, int], np.ndarray] = {}
        for p in profiles.profiles:
            probs = np.asarray(p.input_probs, dtype=np.float64)
            if probs.ndim != 2 or probs.shape[1] != self.grid.n_inputs or probs.shape[0] < 1:
                issues.append(Issue("bad_profile", p.track_id, f"corridor {p.corridor_id}: input_probs shape {probs.shape}: pair falls back"))
                continue
            if not np.all(np.isfinite(probs)) or np.any(probs < 0) or np.any(probs.sum(axis=1) <= 0):
                issues.append(Issue("bad_profile", p.track_id, f"corridor {p.corridor_id}: input_probs not a distribution: pair falls back"))
                continue
            probs = probs / probs.sum(axis=1, keepdims=True)
            if probs.shape[0] < cfg.n_steps:  # a shorter profile holds its last distribution
                probs = np.vstack([probs, np.repeat(probs[-1:], cfg.n_steps - probs.shape[0], axis=0)])
            out[(p.track_id, p.corridor_id)] = probs[: cfg.n_steps]
        return out

    def _weights(self, vehicle, good: list, beliefs: dict[int, dict[int, Any]] | None, issues: list[Issue]) -> np.ndarray:
        """P(R = c) over the vehicle's predicted corridors: the DBN's, renormalised, or uniform."""
        uniform = np.full(len(good), 1.0 / len(good))
        if self.config.corridor_weights != "intentions" or beliefs is None:
            return uniform
        mine = beliefs.get(vehicle.track_id)
        if mine is None:
            issues.append(Issue("no_belief", vehicle.track_id, "no intention belief for this vehicle: uniform corridor weights"))
            return uniform
        w = np.array([mine[c.corridor_id].probability if c.corridor_id in mine else np.nan for c in good], dtype=np.float64)
        if np.any(~np.isfinite(w)) or np.any(w < 0) or w.sum() <= 0:
            issues.append(Issue("no_belief", vehicle.track_id, "intention belief misses some of this vehicle's corridors: uniform corridor weights"))
            return uniform
        return w / w.sum()

    def _pairs(
        self,
        corridor_set: CorridorSet,
        frame: TrackFrame | None,
        scene_limit_mps: float,
        issues: list[Issue],
        beliefs: dict[int, dict[int, Any]] | None = None,
        profiles: dict[tuple[int, int], np.ndarray] | None = None,
    ) -> list[_Pair]:
        cfg = self.config
        stamp = int(corridor_set.header.stamp_ns)
        rows: dict[int, int] = {}
        if frame is not None and int(frame.header.stamp_ns) == stamp:
            rows = {int(t): i for i, t in enumerate(frame.track_ids)}
        pairs: list[_Pair] = []
        for vehicle in corridor_set.vehicles:
            if vehicle.status != MatchStatus.MATCHED or not vehicle.corridors:
                continue
            if not math.isfinite(vehicle.speed_mps):
                issues.append(Issue("nan_state", vehicle.track_id, f"speed {vehicle.speed_mps}: vehicle not predicted"))
                continue
            length, width = DEFAULT_SIZES_M.get(AgentType(vehicle.agent_type), DEFAULT_SIZES_M[AgentType.CAR])
            row = rows.get(vehicle.track_id)
            if row is not None:
                if _positive(frame.length_m[row]):
                    length = float(frame.length_m[row])
                if _positive(frame.width_m[row]):
                    width = float(frame.width_m[row])
            v0 = float(np.clip(vehicle.speed_mps, 0.0, cfg.v_max_mps))
            a0, sigma_a0 = self._acceleration(vehicle.track_id, stamp)
            standing = cfg.mode in CHAIN_MODES and v0 <= cfg.standstill_speed_mps and cfg.standstill_start_rate_hz > 0
            good = [c for c in vehicle.corridors if _corridor_ok(c, vehicle.track_id, issues)]
            if not good:
                continue
            if cfg.mode == "cv":
                pairs.append(self._cv_line(vehicle, good[0], frame, row, v0, a0, length, width))
                continue
            weights = self._weights(vehicle, good, beliefs, issues)
            mine = beliefs.get(vehicle.track_id, {}) if beliefs is not None and cfg.initial_box == "particles" else {}
            for c, weight in zip(good, weights):
                limit = c.speed_limit_mps if _positive(c.speed_limit_mps) else scene_limit_mps
                s0, hs, hv, v_start = float(c.vehicle_s_m), 0.0, 0.0, v0
                cb = mine.get(c.corridor_id)
                if cb is not None and cb.particle_count > 0 and all(
                    math.isfinite(x) for x in (cb.s_mean_m, cb.s_std_m, cb.v_mean_mps, cb.v_std_mps)
                ):
                    s0, v_start = float(cb.s_mean_m), float(np.clip(cb.v_mean_mps, 0.0, cfg.v_max_mps))
                    hs = max(0.5 * cfg.ds_m, 2.0 * float(cb.s_std_m))
                    hv = max(0.5 * cfg.dv_mps, 2.0 * float(cb.v_std_mps))
                lam = None
                if profiles is not None:
                    lam = profiles.get((vehicle.track_id, c.corridor_id))
                    if lam is None:
                        issues.append(Issue("no_acceleration_profile", vehicle.track_id, f"corridor {c.corridor_id}: no AR profile, measured acceleration held"))
                if hs > 0 and not self._particle_box_fits(s0, float(c.vehicle_s_m), hs, vehicle.track_id, c.corridor_id, issues):
                    s0, hs, hv, v_start = float(c.vehicle_s_m), 0.0, 0.0, v0
                s_first = self._window_start(s0, float(c.vehicle_s_m), hs)
                pairs.append(
                    _Pair(
                        track_id=vehicle.track_id,
                        corridor_id=c.corridor_id,
                        probability=weight,
                        s_m=np.asarray(c.s_m, dtype=np.float64),
                        x_m=np.asarray(c.x_m, dtype=np.float64),
                        y_m=np.asarray(c.y_m, dtype=np.float64),
                        heading_rad=np.asarray(c.heading_rad, dtype=np.float64),
                        curvature_1pm=np.asarray(c.curvature_1pm, dtype=np.float64),
                        speed_limit_mps=float(limit) * cfg.speed_limit_factor,
                        s0_m=s0,
                        v0_mps=v_start,
                        a0_mps2=a0,
                        sigma_a0_mps2=sigma_a0,
                        s_first_m=s_first,
                        length_m=length,
                        width_m=width,
                        d0_m=float(c.vehicle_d_m) if math.isfinite(c.vehicle_d_m) else 0.0,
                        start_rate_hz=cfg.standstill_start_rate_hz if standing else 0.0,
                        half_width_s_m=hs,
                        half_width_v_mps=hv,
                        input_probs=lam,
                        measured_v_mps=float(vehicle.speed_mps),
                    )
                )
        return pairs

    def _cv_line(self, vehicle, corridor, frame, row, v0, a0, length, width) -> _Pair:
        """The straight line of mode ``cv``: from the vehicle along its velocity (the corridor's heading when unknown)."""
        cfg = self.config
        heading = float(np.interp(corridor.vehicle_s_m, corridor.s_m, np.unwrap(corridor.heading_rad)))
        x0, y0 = _corridor_point(corridor, corridor.vehicle_s_m, corridor.vehicle_d_m)
        if row is not None and math.isfinite(frame.x_m[row]) and math.isfinite(frame.y_m[row]):
            x0, y0 = float(frame.x_m[row]), float(frame.y_m[row])
            vx, vy = float(vehicle.vx_mps), float(vehicle.vy_mps)  # estimated from positions (corridors stage)
            if math.isfinite(vx) and math.isfinite(vy):
                v0 = float(np.clip(math.hypot(vx, vy), 0.0, cfg.v_max_mps))
                if math.hypot(vx, vy) > 0.5:
                    heading = math.atan2(vy, vx)
        behind = cfg.window_behind_m
        s = np.arange(0.0, behind + cfg.window_cells * cfg.ds_m + cfg.ds_m, 0.5)
        return _Pair(
            track_id=vehicle.track_id,
            corridor_id=CV_LINE_ID,
            probability=1.0,
            s_m=s,
            x_m=x0 + (s - behind) * math.cos(heading),
            y_m=y0 + (s - behind) * math.sin(heading),
            heading_rad=np.full(s.shape, heading),
            curvature_1pm=np.zeros(s.shape),
            speed_limit_mps=cfg.v_max_mps,
            s0_m=behind,
            v0_mps=v0,
            a0_mps2=a0,
            s_first_m=0.0,
            length_m=length,
            width_m=width,
        )

    # ----- one pair's failure never costs the frame ----------------------------------

    def _predict(self, pairs: list[_Pair], issues: list[Issue]) -> FramePrediction:
        """The frame's prediction, each pair's failure isolated.

        The mode predicts every pair it can. In the chain modes a pair the
        chain cannot take (``_screen``), or one the batched chain raises on
        (found by bisection, the batch run again without it), is predicted by
        constant speed along its corridor, the ``corridor_cv`` mode (issue
        ``pair_fallback_<reason>``); a pair that fails even so, or whose
        outputs raise, is left out (``pair_failed``). The other pairs are
        predicted exactly as without the failing one, unless they follow or
        yield to it.
        """
        chain = self.config.mode in CHAIN_MODES
        simple: dict[int, _Pair] = {}  # pair index -> the pair as the fallback predicts it
        screened = self._screen(pairs) if chain else {}
        for b, (kind, detail) in screened.items():
            p = pairs[b]
            issues.append(Issue(kind, p.track_id, f"corridor {p.corridor_id}: {detail}: constant speed along the corridor (corridor_cv)"))
            if kind == "pair_fallback_speed_above_vmax":
                p = dataclasses.replace(p, v0_mps=p.measured_v_mps)
            elif kind == "pair_fallback_box_outside_window":  # the fallback's distributions lie on a window placed from its s
                p = dataclasses.replace(p, s_first_m=self._window_start(p.s0_m, p.s0_m, 0.0))
            simple[b] = p

        def run(idx: list[int]):
            found: list[Issue] = []
            group = [pairs[b] for b in idx]
            return (self._markov(group, found) if chain else self._constant_velocity(group)), found

        (arrays, found), failed = isolate([b for b in range(len(pairs)) if b not in screened], run)
        issues.extend(found)
        for b, exc in failed:
            p = pairs[b]
            if chain:
                issues.append(Issue("pair_fallback_chain_failed", p.track_id, f"corridor {p.corridor_id}: the chain raised"
                                    f" {type(exc).__name__}: {exc}: constant speed along the corridor (corridor_cv)"))
                simple[b] = p
            else:
                issues.append(Issue("pair_failed", p.track_id, f"corridor {p.corridor_id}: {type(exc).__name__}: {exc}: not predicted"))
        lost = {b for b, _ in failed}
        main = [b for b in range(len(pairs)) if b not in screened and b not in lost]
        usable = []
        for b in sorted(simple):
            p = simple[b]
            if all(math.isfinite(x) for x in (p.s0_m, p.v0_mps, p.s_first_m)):
                usable.append(b)
            else:
                issues.append(Issue("pair_failed", p.track_id, f"corridor {p.corridor_id}: no finite arc length or speed for the fallback: not predicted"))
        fallback, failed = isolate(usable, lambda idx: self._constant_velocity([simple[b] for b in idx]))
        for b, exc in failed:
            issues.append(Issue("pair_failed", simple[b].track_id, f"corridor {simple[b].corridor_id}: the fallback raised {type(exc).__name__}: {exc}: not predicted"))
        gone = {b for b, _ in failed}
        usable = [b for b in usable if b not in gone]
        order = sorted(main + usable)
        final = [simple.get(b, pairs[b]) for b in order]
        merged = _merge(order, [(main, arrays), (usable, fallback)])

        def finish(idx: list[int]):
            found: list[Issue] = []
            subset = final if len(idx) == len(final) else [final[i] for i in idx]
            return self._finish(subset, _take(merged, idx, len(final)), found), found

        (prediction, found), failed = isolate(range(len(final)), finish)
        issues.extend(found)
        for i, exc in failed:
            issues.append(Issue("pair_failed", final[i].track_id, f"corridor {final[i].corridor_id}: its outputs raised {type(exc).__name__}: {exc}: not predicted"))
        return prediction

    def _screen(self, pairs: list[_Pair]) -> dict[int, tuple[str, str]]:
        """The pairs the chain cannot take, found before the batch: pair index -> (issue kind, why)."""
        out: dict[int, tuple[str, str]] = {}
        if not pairs:
            return out
        boxes = self._boxes(pairs)
        s_out, v_out = boxes_outside_grid(self._window_grid, **boxes)
        v_max = self.config.v_max_mps
        for b, p in enumerate(pairs):
            bad = _non_finite(p)
            if bad:
                out[b] = ("pair_fallback_nan_input", f"non-finite {', '.join(bad)}")
            elif p.measured_v_mps > v_max:
                out[b] = ("pair_fallback_speed_above_vmax", f"speed {p.measured_v_mps:.1f} m/s above the chain's v_max_mps {v_max:g}")
            elif s_out[b] or v_out[b]:
                out[b] = ("pair_fallback_box_outside_window", f"initial box s {boxes['s_m'][b]:.1f} ± {boxes['half_width_s_m'][b]:.1f} m,"
                          f" v {p.v0_mps:.1f} m/s misses its {self.n_s * self.config.ds_m:.0f} m window or the speed cells")
        return out

    # ----- constant-velocity baselines --------------------------------------------

    def _constant_velocity(self, pairs: list[_Pair]) -> dict[str, np.ndarray]:
        """Constant speed along each corridor (or the cv line): exact means, Gaussian spreads for the grid.

        The position at t_k is s0 + v0·t_k; the grid spreads it with
        σ_s(t) = √(σ0² + (½σ_a t²)²) along the line and σ_v(t) = σ_a·t in
        speed (σ_a = ``cv_accel_sigma_mps2``, σ0 = ``init_sigma_s_m``), so
        that calibration metrics have something to measure.
        """
        cfg = self.config
        t = self.step_times_s
        n_b, n_k = len(pairs), t.shape[0]
        edges = self.grid.s_edges_m()[: self.n_s + 1]
        v_edges = self.grid.v_edges_mps()
        pos = np.zeros((n_b, n_k, self.n_s), np.float32)
        vel = np.zeros((n_b, n_k, self.grid.n_v_cells), np.float32)
        outside = np.zeros((n_b, n_k), np.float32)
        exact_s = np.zeros((n_b, n_k))
        sigma_s = np.sqrt(cfg.init_sigma_s_m**2 + (0.5 * cfg.cv_accel_sigma_mps2 * t**2) ** 2)
        sigma_v = np.maximum(cfg.cv_accel_sigma_mps2 * t, 1e-3)
        for b, p in enumerate(pairs):
            mean_w = p.s0_m - p.s_first_m + p.v0_mps * t  # window coordinates
            exact_s[b] = p.s0_m + p.v0_mps * t
            cdf = _normal_cdf((edges[None, :] - mean_w[:, None]) / sigma_s[:, None])
            cdf[:, 0] = 0.0  # nothing behind the window's start (no reversing)
            pos[b] = np.diff(cdf, axis=1)
            outside[b] = 1.0 - cdf[:, -1]
            vcdf = _normal_cdf((v_edges[None, :] - p.v0_mps) / sigma_v[:, None])
            vcdf[:, 0], vcdf[:, -1] = 0.0, 1.0
            vel[b] = np.diff(vcdf, axis=1)
        return {"position": pos, "interval": None, "velocity": vel, "outside": outside, "exact_s": exact_s}

    # ----- the Markov chain ----------------------------------------------------------

    def _markov(self, pairs: list[_Pair], issues: list[Issue]) -> dict[str, np.ndarray]:
        cfg, grid = self.config, self.grid
        n_b, n_k, n_v, n_in = len(pairs), cfg.n_steps, grid.n_v_cells, grid.n_inputs
        if n_b == 0:
            empty = np.zeros((0, n_k, self.n_s), np.float32)
            return {"position": empty, "interval": empty.copy(), "velocity": np.zeros((0, n_k, n_v), np.float32),
                    "outside": np.zeros((0, n_k), np.float32), "exact_s": None}
        cell_lower = grid.s_edges_m()[: self.n_s]
        cell_centre = cell_lower + 0.5 * cfg.ds_m
        if cfg.mode == "hybrid":
            return self._hybrid(pairs, self._speed_restriction(pairs, cell_centre) if cfg.hybrid_speed_restriction else None)
        # λ_speed per pair, static over the steps, and the combined r where nothing else restricts
        lam_speed = self._speed_restriction(pairs, cell_centre)
        r_static = pr.combine_with_preference(lam_speed, self.preference, cfg.forbid_threshold)
        index = {(p.track_id, p.corridor_id): b for b, p in enumerate(pairs)}
        by_track: dict[int, list[int]] = collections.defaultdict(list)
        for b, p in enumerate(pairs):
            by_track[p.track_id].append(b)
        leaders = self._leaders(pairs, by_track, issues)
        conflicts = self._conflicts(pairs, index, issues)

        p0 = self._initial(pairs, self._measured_inputs(pairs))
        v0 = np.array([p.v0_mps for p in pairs])
        ctx = _PassContext(
            members=np.arange(n_b),
            lam_speed=lam_speed,
            r_static=r_static,
            leaders=leaders,
            conflicts={},
            stored=None,
            cell_centre=cell_centre,
            pairs=pairs,
        )
        with_interval = cfg.grid_distribution == "interval" or bool(conflicts)
        result = self.propagator.run(p0, self._step_inputs(ctx), with_interval=with_interval)
        everyone = np.arange(n_b)
        pos, vel, interval, outside = self._mix_standstill(
            pairs, everyone, p0.position_probs, result.position_probs, result.velocity_probs,
            result.interval_position_probs, result.outside_mass,
        )
        if conflicts:
            members = _closure(set(conflicts), leaders)
            m = np.array(sorted(members))
            stored = {"position": pos, "velocity": vel, "interval": interval, "v0": v0}
            ctx2 = _PassContext(
                members=m,
                lam_speed=lam_speed[m],
                r_static=r_static[m],
                leaders={int(np.searchsorted(m, f)): spec for f, spec in leaders.items() if f in members},
                conflicts={int(np.searchsorted(m, e)): spec for e, spec in conflicts.items()},
                stored=stored,
                cell_centre=cell_centre,
                pairs=pairs,
            )
            sub = type(p0)(input_probs=p0.input_probs[m], velocity_probs=p0.velocity_probs[m], position_probs=p0.position_probs[m])
            second = self.propagator.run(sub, self._step_inputs(ctx2), with_interval=with_interval)
            mixed = self._mix_standstill(
                pairs, m, sub.position_probs, second.position_probs, second.velocity_probs,
                second.interval_position_probs, second.outside_mass,
            )
            pos, vel, outside = pos.copy(), vel.copy(), outside.copy()
            pos[m], vel[m], outside[m] = mixed[0], mixed[1], mixed[3]
            if interval is not None:
                interval = interval.copy()
                interval[m] = mixed[2]
        return {"position": pos, "interval": interval, "velocity": vel, "outside": outside, "exact_s": None}

    def _speed_restriction(self, pairs: list[_Pair], cell_centre: np.ndarray) -> np.ndarray:
        """λ_speed (B, M, N_v, N_s) per pair, static over the steps (§2.2)."""
        cfg = self.config
        lam_speed = np.empty((len(pairs), self.grid.n_inputs, self.grid.n_v_cells, self.n_s), np.float32)
        weights = np.asarray(cfg.lat_accel_weights, dtype=np.float64)
        weights = weights / weights.sum()
        for b, p in enumerate(pairs):
            adm = pr.admissible_speeds(
                p.s_m, p.curvature_1pm, p.speed_limit_mps, np.asarray(cfg.lat_accels_mps2), cfg.lookahead_brake_mps2, cfg.curvature_smoothing_m
            )
            lam_speed[b] = pr.speed_restriction(adm, p.s_m, p.s_first_m + cell_centre, self.v_centres, self.a_centres, weights, cfg.tau_s)
        return lam_speed

    def _measured_inputs(self, pairs: list[_Pair]) -> np.ndarray:
        """(B, M): a normal distribution around each pair's measured acceleration over the input cells (tails folded)."""
        edges = self.grid.input_edges()
        a0 = np.array([p.a0_mps2 for p in pairs])
        sigma_a0 = np.array([p.sigma_a0_mps2 for p in pairs])
        cdf = _normal_cdf((edges[None, :] - a0[:, None]) / sigma_a0[:, None])
        cdf[:, 0], cdf[:, -1] = 0.0, 1.0  # fold the tails into the end cells
        probs = np.diff(cdf, axis=1)
        return probs / probs.sum(axis=1, keepdims=True)

    def _boxes(self, pairs: list[_Pair]) -> dict[str, np.ndarray]:
        """The initial boxes (§1.4) as ``initial_state`` takes them: centres in window coordinates, half-widths
        (the measurement's defaults, or the particles')."""
        return {
            "s_m": np.array([p.s0_m - p.s_first_m for p in pairs], dtype=np.float64),
            "v_mps": np.array([p.v0_mps for p in pairs], dtype=np.float64),
            "half_width_s_m": np.array([p.half_width_s_m if p.half_width_s_m > 0 else self._default_half_s_m for p in pairs]),
            "half_width_v_mps": np.array([p.half_width_v_mps if p.half_width_v_mps > 0 else self._default_half_v_mps for p in pairs]),
        }

    def _initial(self, pairs: list[_Pair], input_probs: np.ndarray):
        """p(t_0) (§1.4): a uniform box in (s, v) (the measurement's, or the particles') × ``input_probs``, on the window."""
        return initial_state(self._window_grid, **self._boxes(pairs), input_probs=input_probs)

    def _hybrid(self, pairs: list[_Pair], lam_speed: np.ndarray | None = None) -> dict[str, np.ndarray]:
        """Hybrid mode (METHOD.md §3.2): λ(0) starts the input, Γ_k = colnorm(diag(λ(k)) Ψ) (or λ(k)·1ᵀ) after step k;
        with ``lam_speed``, λ(k) (scaled to a largest entry of 1) is the preference that λ_speed cuts, per state."""
        cfg = self.config
        measured = self._measured_inputs(pairs)
        lam = np.stack([p.input_probs if p.input_probs is not None else np.repeat(measured[b][None], cfg.n_steps, axis=0)
                        for b, p in enumerate(pairs)])  # (B, K, M)
        p0 = self._initial(pairs, lam[:, 0])
        steps: list = []
        for k in range(cfg.n_steps):
            if k + 1 >= cfg.n_steps:
                steps.append(None)  # the input after the last step does not change any output
            elif lam_speed is not None:
                pref = lam[:, k + 1] / np.maximum(lam[:, k + 1].max(axis=1, keepdims=True), 1e-12)
                steps.append(InputPriority(  # built on the step's active s-window only
                    weights=lambda lo, hi, pref=pref: pr.combine_with_preference(lam_speed[..., lo:hi], pref, cfg.forbid_threshold)
                ))
            elif cfg.hybrid_input == "direct":
                steps.append(InputReplaced(probs=lam[:, k + 1]))
            else:
                steps.append(InputMatrix(gamma=gamma_from_priority(lam[:, k + 1], self.psi)))
        result = self.propagator.run(p0, steps, with_interval=cfg.grid_distribution == "interval")
        pos, vel, interval, outside = self._mix_standstill(
            pairs, np.arange(len(pairs)), p0.position_probs, result.position_probs, result.velocity_probs,
            result.interval_position_probs, result.outside_mass,
        )
        return {"position": pos, "interval": interval, "velocity": vel, "outside": outside, "exact_s": None}

    def _mix_standstill(self, pairs, members, start_probs, pos, vel, interval, outside):
        """Standing vehicles (package docstring, "Standstill"): P_stay(t)·(start box, v-cell 0) + (1 − P_stay(t))·chain."""
        stay = np.stack([pairs[g].stay_probability(self.step_times_s) for g in members]) if len(members) else np.zeros((0, self.config.n_steps))
        if not np.any(stay > 0):
            return pos, vel, interval, outside
        w = stay[:, :, None].astype(np.float32)
        pos = (1.0 - w) * pos + w * start_probs[:, None, :]
        vel = (1.0 - w) * vel
        vel[:, :, 0] += stay.astype(np.float32)
        if interval is not None:
            interval = (1.0 - w) * interval + w * start_probs[:, None, :]
        outside = (1.0 - stay.astype(np.float32)) * outside
        return pos.astype(np.float32), vel.astype(np.float32), None if interval is None else interval.astype(np.float32), outside

    def _leaders(self, pairs: list[_Pair], by_track: dict[int, list[int]], issues: list[Issue]) -> dict[int, "_LeaderSpec"]:
        """Leader of each follower pair: the leader's own pairs when it is predicted, else a constant-speed point."""
        out: dict[int, _LeaderSpec] = {}
        for f, p in enumerate(pairs):
            rel = p.relation
            if rel is None or rel.leader_track_id < 0:
                continue
            gap = float(rel.leader_gap_m)
            if not math.isfinite(gap):
                issues.append(Issue("nan_relation", p.track_id, f"corridor {p.corridor_id}: leader {rel.leader_track_id} with gap {gap}: ignored"))
                continue
            members = [b for b in by_track.get(int(rel.leader_track_id), []) if b != f]
            speed = float(rel.leader_speed_mps) if math.isfinite(rel.leader_speed_mps) else 0.0
            if not members and not math.isfinite(rel.leader_speed_mps):
                issues.append(Issue("nan_relation", p.track_id, f"corridor {p.corridor_id}: leader {rel.leader_track_id} speed"
                                    f" {rel.leader_speed_mps}: taken as standing"))
            out[f] = _LeaderSpec(gap_m=max(gap, 0.0), pairs=tuple(members), speed_mps=max(speed, 0.0))
        return out

    def _conflicts(self, pairs: list[_Pair], index: dict[tuple[int, int], int], issues: list[Issue]) -> dict[int, "_ConflictSpec"]:
        """The influencing corridor of each pair (§2.4), with its zone on both corridors."""
        out: dict[int, _ConflictSpec] = {}
        for e, p in enumerate(pairs):
            rel = p.relation
            if rel is None or rel.influencing_index < 0:
                continue
            i = int(rel.influencing_index)
            if i >= rel.conflict_s_m.shape[0]:
                issues.append(Issue("bad_relation", p.track_id, f"corridor {p.corridor_id}: influencing_index {i} out of range"))
                continue
            s_star, s_other = float(rel.conflict_s_m[i]), float(rel.conflict_other_s_m[i])
            if not (math.isfinite(s_star) and math.isfinite(s_other)):
                issues.append(Issue("nan_relation", p.track_id, f"corridor {p.corridor_id}: conflict point not finite: ignored"))
                continue
            other = index.get((int(rel.conflict_track_ids[i]), int(rel.conflict_corridor_ids[i])))
            other_len, other_wid = DEFAULT_SIZES_M[AgentType.CAR]
            if other is not None:
                other_len, other_wid = pairs[other].length_m, pairs[other].width_m
            half = pr.zone_half_width_m(p.length_m, other_wid)
            half_other = pr.zone_half_width_m(other_len, p.width_m)
            fallback = None
            if other is None:
                distance = float(rel.conflict_other_distance_m[i]) if rel.conflict_other_distance_m.shape[0] > i else math.nan
                speed = float(rel.conflict_other_speed_mps[i]) if rel.conflict_other_speed_mps.shape[0] > i else math.nan
                if not (math.isfinite(distance) and math.isfinite(speed)):
                    continue
                fallback = pr.constant_speed_occupancy(distance, speed, half_other, self.config.tau_s, self.config.n_steps)
            out[e] = _ConflictSpec(
                zone_m=(s_star - half, s_star + half),
                other=other,
                other_zone_m=(s_other - half_other, s_other + half_other),
                fallback_occupancy=fallback,
            )
        return out

    def _step_inputs(self, ctx: "_PassContext"):
        """The callable the propagator asks for Γ(t_{k+1}) after step k (all pairs of the pass at once)."""
        cfg, grid = self.config, self.grid
        n_steps = cfg.n_steps
        tau = cfg.tau_s
        survival_x = pr.survival_grid()
        edges_local = grid.s_edges_m()[: self.n_s + 1]
        followers = np.array(sorted(ctx.leaders), dtype=np.int64)
        conflicted = sorted(ctx.conflicts)
        member_pos = {int(g): i for i, g in enumerate(ctx.members)}
        pairs = ctx.pairs
        v_centres = self.v_centres
        # the other vehicles' zone occupancies, from the first pass (interval distributions)
        occupancy: dict[int, np.ndarray] = {}
        for e in conflicted:
            spec = ctx.conflicts[e]
            if spec.other is None or ctx.stored is None or ctx.stored["interval"] is None:
                occupancy[e] = spec.fallback_occupancy if spec.fallback_occupancy is not None else np.zeros(n_steps)
            else:
                o = pairs[spec.other]
                occupancy[e] = pr.zone_occupancy(ctx.stored["interval"][spec.other], o.s_first_m + edges_local, spec.other_zone_m)
        all_v0 = np.array([p.v0_mps for p in pairs])
        state = {"mean_v": all_v0.copy()}  # every pair's mean speed at the previous step

        def leader_state(k: int, pos_local: np.ndarray, vel_local: np.ndarray):
            """(survival (F, J), mean speed cell (F,), mean accel cell (F,)) of the followers' leaders at t_{k+1}.

            Leaders of this pass come from its marginals, mixed with their
            standstill part; the others from the first pass (already mixed).
            """
            t_next = (k + 1) * tau
            n_f = followers.shape[0]
            survival = np.empty((n_f, survival_x.shape[0]))
            v_cell = np.empty(n_f, np.int64)
            a_cell = np.empty(n_f, np.int64)
            mean_v = state["mean_v"].copy()
            if ctx.stored is not None:
                mean_v[:] = _mean_speed(ctx.stored["velocity"][:, k], v_centres, all_v0)
            local_v = _mean_speed(vel_local, v_centres, state["mean_v"][ctx.members])
            for g, i in member_pos.items():
                stay = pairs[g].stay_probability(t_next)
                mean_v[g] = (1.0 - stay) * local_v[i]
            for row, f in enumerate(followers):
                spec = ctx.leaders[int(f)]
                if not spec.pairs:
                    survival[row] = pr.survival_constant_speed(spec.speed_mps, t_next, cfg.static_leader_spread_m, survival_x)
                    v_now, v_before = spec.speed_mps, spec.speed_mps
                else:
                    acc = np.zeros(survival_x.shape[0])
                    for g in spec.pairs:
                        lp = pairs[g]
                        if g in member_pos:
                            moving = pr.survival_from_cells(pos_local[member_pos[g]], lp.s_first_m - lp.s0_m + edges_local, survival_x)
                            stay = lp.stay_probability(t_next)
                            if stay > 0:
                                standing = pr.survival_constant_speed(0.0, t_next, 0.5 * cfg.ds_m, survival_x)
                                moving = stay * standing + (1.0 - stay) * moving
                            acc += moving
                        else:
                            acc += pr.survival_from_cells(ctx.stored["position"][g, k], lp.s_first_m - lp.s0_m + edges_local, survival_x)
                    survival[row] = acc / len(spec.pairs)
                    v_now = float(np.mean(mean_v[list(spec.pairs)]))
                    v_before = float(np.mean(state["mean_v"][list(spec.pairs)]))
                v_cell[row] = min(int(v_now / cfg.dv_mps), grid.n_v_cells - 1)
                a_cell[row] = grid.input_cell_of((v_now - v_before) / tau)
            state["mean_v"] = mean_v
            return survival, v_cell, a_cell

        def step(k: int, marginals) -> InputPriority | None:
            if k >= n_steps - 1:
                return None  # Γ after the last step shapes nothing that is reported
            t_next = (k + 1) * tau
            if followers.size:
                survival, v_cell, a_cell = leader_state(k, _numpy(marginals.position), _numpy(marginals.velocity))
            restricted = sorted(set(int(f) for f in followers) | set(conflicted))

            def weights(lo: int, hi: int) -> np.ndarray:
                r = ctx.r_static[:, :, :, lo:hi]
                if not restricted:
                    return r
                r = r.copy()
                m = ctx.lam_speed[restricted, :, :, lo:hi].copy()
                where = {b: i for i, b in enumerate(restricted)}
                if followers.size:
                    offsets = np.empty((followers.size, hi - lo))
                    for row, f in enumerate(followers):
                        p = pairs[int(ctx.members[f])]
                        offsets[row] = p.s_first_m + ctx.cell_centre[lo:hi] - p.s0_m - ctx.leaders[int(f)].gap_m
                    lam_lead = pr.leader_restriction(
                        self.gaps, survival, offsets, v_cell, a_cell, cfg.leader_epsilon, cfg.leader_horizon_mean == "geometric"
                    )
                    for row, f in enumerate(followers):
                        i = where[int(f)]
                        np.minimum(m[i], lam_lead[row], out=m[i])
                for e in conflicted:
                    p = pairs[int(ctx.members[e])]
                    lam_conf = pr.conflict_restriction(
                        p.s_first_m + ctx.cell_centre[lo:hi],
                        v_centres,
                        self.a_centres,
                        grid.v_max_mps,
                        ctx.conflicts[e].zone_m,
                        t_next,
                        occupancy[e],
                        tau,
                        cfg.conflict_margin_s,
                        cfg.conflict_epsilon,
                    )
                    i = where[e]
                    np.minimum(m[i], lam_conf, out=m[i])
                r[restricted] = pr.combine_with_preference(m, self.preference, cfg.forbid_threshold)
                return r

            return InputPriority(weights=weights)

        return step

    # ----- outputs --------------------------------------------------------------------

    def _finish(self, pairs: list[_Pair], arrays: dict[str, Any], issues: list[Issue]) -> FramePrediction:
        cfg, grid = self.config, self.grid
        n_b, n_k = len(pairs), cfg.n_steps
        pos = np.asarray(arrays["position"], dtype=np.float32)
        interval = arrays["interval"]
        outside = np.asarray(arrays["outside"], dtype=np.float64).copy()
        lower = grid.s_edges_m()[: self.n_s]
        centre = lower + 0.5 * cfg.ds_m
        mean_xy = np.full((n_b, n_k, 2), np.nan)
        mean_s = np.full((n_b, n_k), np.nan)
        xy_at_mean = np.full((n_b, n_k, 2), np.nan)
        footprints: list[Footprints] = []
        pos = pos.copy()
        decay = cfg.lateral_offset_decay_s
        factor = np.exp(-self.step_times_s / decay) if decay > 0 else np.zeros(n_k)
        shifts = [p.d0_m * factor for p in pairs]
        if interval is not None:
            interval = np.asarray(interval, dtype=np.float32).copy()
        for b, p in enumerate(pairs):
            beyond = p.s_first_m + lower >= p.end_s_m  # cells past the corridor's end count as outside
            if np.any(beyond):
                outside[b] += pos[b][:, beyond].sum(axis=1)
                pos[b][:, beyond] = 0.0
                if interval is not None:
                    interval[b][:, beyond] = 0.0
            s_abs = p.s_first_m + centre
            shift = shifts[b]
            x_c, y_c = _corridor_xy(p, s_abs)
            nx_c, ny_c = _corridor_normal(p, s_abs)
            mass = pos[b].sum(axis=1, dtype=np.float64)
            ok = mass > 1e-9
            with np.errstate(invalid="ignore", divide="ignore"):
                mean_xy[b, ok, 0] = (pos[b][ok] @ x_c + shift[ok] * (pos[b][ok] @ nx_c)) / mass[ok]
                mean_xy[b, ok, 1] = (pos[b][ok] @ y_c + shift[ok] * (pos[b][ok] @ ny_c)) / mass[ok]
                mean_s[b, ok] = (pos[b][ok] @ s_abs) / mass[ok]
            exact = arrays.get("exact_s")
            if exact is not None and np.all(np.isfinite(exact[b])):  # constant velocity (a mode, or a fallback): the exact point
                mean_s[b] = exact[b]
                ex, ey = _corridor_xy(p, exact[b])
                enx, eny = _corridor_normal(p, exact[b])
                mean_xy[b, :, 0], mean_xy[b, :, 1] = ex + shift * enx, ey + shift * eny
            finite = np.isfinite(mean_s[b])
            at = np.where(finite, mean_s[b], p.s0_m)
            sx, sy = _corridor_xy(p, at)
            snx, sny = _corridor_normal(p, at)
            xy_at_mean[b, :, 0] = np.where(finite, sx + shift * snx, np.nan)
            xy_at_mean[b, :, 1] = np.where(finite, sy + shift * sny, np.nan)
            if outside[b, -1] > cfg.outside_issue_mass:
                issues.append(
                    Issue(
                        "corridor_too_short",
                        p.track_id,
                        f"corridor {p.corridor_id}: outside mass {outside[b, -1]:.3f} at {self.step_times_s[-1]:.1f} s"
                        f" (corridor ends {p.end_s_m - p.s0_m:.1f} m ahead, v0 {p.v0_mps:.1f} m/s)",
                    )
                )
            footprints.append(
                cell_footprints(
                    p.s_m, p.x_m, p.y_m, p.heading_rad, p.s_first_m + lower, cfg.ds_m, cfg.grid_substeps, *self._lateral
                )
            )
        grid_probs = interval if (cfg.grid_distribution == "interval" and interval is not None) else pos
        frame = self._grid_frame(footprints, grid_probs)
        by_track: dict[int, list[int]] = collections.defaultdict(list)
        for b, p in enumerate(pairs):
            by_track[p.track_id].append(b)
        vehicle_grids = {
            track: vehicle_grid(
                frame,
                [footprints[b] for b in members],
                [grid_probs[b] for b in members],
                [pairs[b].probability for b in members],
                [shifts[b] for b in members],
            )
            for track, members in by_track.items()
        }
        infos = tuple(PairInfo(p.track_id, p.corridor_id, p.probability, p.s0_m, p.s_first_m, p.end_s_m) for p in pairs)
        return FramePrediction(
            mode=cfg.mode,
            step_times_s=self.step_times_s.copy(),
            ds_m=cfg.ds_m,
            dv_mps=cfg.dv_mps,
            pairs=infos,
            position_probs=pos,
            interval_probs=interval,
            velocity_probs=np.asarray(arrays["velocity"], dtype=np.float32),
            outside_mass=outside.astype(np.float32),
            mean_xy_m=mean_xy,
            mean_s_m=mean_s,
            xy_at_mean_s_m=xy_at_mean,
            grid_frame=frame,
            grid_distribution=cfg.grid_distribution if interval is not None or cfg.grid_distribution == "point" else "point",
            vehicle_grids=vehicle_grids,
            fused_grid=fuse(list(vehicle_grids.values())),
            min_grid_value=cfg.grid_min_value,
            max_cells_per_step=cfg.grid_max_cells_per_step,
        )

    def _grid_frame(self, footprints: list[Footprints], probs: np.ndarray) -> GridFrame:
        cfg = self.config
        if cfg.grid_extent_m:
            return GridFrame.fixed(tuple(cfg.grid_extent_m), cfg.grid_cell_m)
        xs, ys = [], []
        for b, fp in enumerate(footprints):
            used = np.flatnonzero(probs[b].max(axis=0) > 0) if probs.shape[0] else np.zeros(0, np.int64)
            if used.size:
                xs.append(fp.x_m[used].ravel())
                ys.append(fp.y_m[used].ravel())
        if not xs:
            return GridFrame(0.0, 0.0, cfg.grid_cell_m, 1, 1)
        return GridFrame.around(np.concatenate(xs), np.concatenate(ys), cfg.grid_cell_m, cfg.grid_margin_m)


# --------------------------------------------------------------------------- helpers


@dataclass(frozen=True, slots=True)
class _LeaderSpec:
    gap_m: float
    pairs: tuple[int, ...]  # the leader's own pairs (global indices); empty: constant-speed point
    speed_mps: float


@dataclass(frozen=True, slots=True, eq=False)
class _ConflictSpec:
    zone_m: tuple[float, float]
    other: int | None
    other_zone_m: tuple[float, float]
    fallback_occupancy: np.ndarray | None


@dataclass(frozen=True, slots=True, eq=False)
class _PassContext:
    """One propagation pass: its members (global pair indices) and their restrictions, indexed locally."""

    members: np.ndarray
    lam_speed: np.ndarray
    r_static: np.ndarray
    leaders: dict[int, _LeaderSpec]  # local follower index -> leader (leader pairs are global indices)
    conflicts: dict[int, _ConflictSpec]  # local index -> conflict (other is a global index)
    stored: dict[str, np.ndarray] | None  # first-pass results, global indices
    cell_centre: np.ndarray
    pairs: list[_Pair]


def _closure(seed: set[int], leaders: dict[int, _LeaderSpec]) -> set[int]:
    """The pairs whose prediction changes when ``seed`` changes: ``seed`` and, transitively, their followers."""
    members = set(seed)
    changed = True
    while changed:
        changed = False
        for f, spec in leaders.items():
            if f not in members and any(g in members for g in spec.pairs):
                members.add(f)
                changed = True
    return members


def _mean_speed(velocity_probs: np.ndarray, v_centres: np.ndarray, fallback: np.ndarray) -> np.ndarray:
    mass = velocity_probs.sum(axis=1, dtype=np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = (velocity_probs @ v_centres) / mass
    return np.where(mass > 1e-9, mean, fallback)


def _numpy(x: Any) -> np.ndarray:
    if hasattr(x, "detach"):
        return x.detach().to("cpu").numpy()
    return np.asarray(x)


_CHAIN_SCALARS = ("s0_m", "v0_mps", "a0_mps2", "sigma_a0_mps2", "s_first_m", "speed_limit_mps", "d0_m", "length_m", "width_m",
                  "half_width_s_m", "half_width_v_mps", "start_rate_hz", "probability")
_CHAIN_ARRAYS = ("s_m", "x_m", "y_m", "heading_rad", "curvature_1pm", "input_probs")


def _non_finite(p: _Pair) -> list[str]:
    """The names of the pair's numbers the chain reads that are not finite (none: [])."""
    bad = [name for name in _CHAIN_SCALARS if not math.isfinite(getattr(p, name))]
    return bad + [name for name in _CHAIN_ARRAYS if getattr(p, name) is not None and not np.all(np.isfinite(getattr(p, name)))]


def _take(arrays: dict[str, Any], idx: list[int], n: int) -> dict[str, Any]:
    """The rows ``idx`` of a frame's prediction arrays (all ``n`` of them: the arrays themselves)."""
    if len(idx) == n:
        return arrays
    rows = np.asarray(idx, dtype=np.int64)
    return {k: (None if v is None else np.asarray(v)[rows]) for k, v in arrays.items()}


def _merge(order: list[int], groups: list[tuple[list[int], dict[str, Any]]]) -> dict[str, Any]:
    """The prediction arrays of several groups of pairs as one, rows in ``order`` (every group's indices lie in it).

    A group without interval distributions (constant velocity) gives its
    time-point ones where another group has them; a group without exact
    means (the chain) gets NaN rows in ``exact_s``.
    """
    live = [(idx, a) for idx, a in groups if idx]
    if len(live) <= 1:
        return live[0][1] if live else groups[0][1]
    row = {b: i for i, b in enumerate(order)}
    first = live[0][1]
    n = len(order)
    pos = np.zeros((n,) + np.shape(first["position"])[1:], np.float32)
    vel = np.zeros((n,) + np.shape(first["velocity"])[1:], np.float32)
    outside = np.zeros((n,) + np.shape(first["outside"])[1:], np.float64)
    interval = np.zeros_like(pos) if any(a["interval"] is not None for _, a in live) else None
    exact = np.full(outside.shape, np.nan) if any(a.get("exact_s") is not None for _, a in live) else None
    for idx, a in live:
        rows = np.array([row[b] for b in idx], dtype=np.int64)
        pos[rows], vel[rows], outside[rows] = a["position"], a["velocity"], a["outside"]
        if interval is not None:
            interval[rows] = a["interval"] if a["interval"] is not None else a["position"]
        if exact is not None and a.get("exact_s") is not None:
            exact[rows] = a["exact_s"]
    return {"position": pos, "interval": interval, "velocity": vel, "outside": outside, "exact_s": exact}


def _normal_cdf(z: np.ndarray) -> np.ndarray:
    from scipy.special import ndtr

    return ndtr(z)


def _positive(value: float) -> bool:
    return math.isfinite(value) and value > 0


def _corridor_ok(corridor, track_id: int, issues: list[Issue]) -> bool:
    s = np.asarray(corridor.s_m)
    arrays = (corridor.s_m, corridor.x_m, corridor.y_m, corridor.heading_rad)
    if s.shape[0] < 2 or any(np.asarray(a).shape != s.shape for a in arrays):
        issues.append(Issue("bad_corridor", track_id, f"corridor {corridor.corridor_id}: fewer than two points or ragged arrays"))
        return False
    if not all(np.all(np.isfinite(a)) for a in arrays) or np.any(np.diff(s) <= 0):
        issues.append(Issue("bad_corridor", track_id, f"corridor {corridor.corridor_id}: non-finite or non-increasing centreline"))
        return False
    if not math.isfinite(corridor.vehicle_s_m):
        issues.append(Issue("nan_state", track_id, f"corridor {corridor.corridor_id}: vehicle_s_m {corridor.vehicle_s_m}"))
        return False
    return True


def _corridor_point(corridor, s_m: float, d_m: float) -> tuple[float, float]:
    heading = float(np.interp(s_m, corridor.s_m, np.unwrap(corridor.heading_rad)))
    x = float(np.interp(s_m, corridor.s_m, corridor.x_m))
    y = float(np.interp(s_m, corridor.s_m, corridor.y_m))
    d = d_m if math.isfinite(d_m) else 0.0
    return x - d * math.sin(heading), y + d * math.cos(heading)


def _corridor_normal(p: _Pair, s_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The left unit normal of the centreline at s (its end headings past either end)."""
    heading = np.interp(np.clip(s_m, p.s_m[0], p.s_m[-1]), p.s_m, np.unwrap(p.heading_rad))
    return -np.sin(heading), np.cos(heading)


def _corridor_xy(p: _Pair, s_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """X_c(s) with straight continuation past either end."""
    s_in = np.clip(s_m, p.s_m[0], p.s_m[-1])
    heading = np.interp(s_in, p.s_m, np.unwrap(p.heading_rad))
    x = np.interp(s_in, p.s_m, p.x_m) + (s_m - s_in) * np.cos(heading)
    y = np.interp(s_in, p.s_m, p.y_m) + (s_m - s_in) * np.sin(heading)
    return x, y
