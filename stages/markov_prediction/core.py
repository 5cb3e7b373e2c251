"""The pure part of the markov_prediction stage: ``MarkovPredictor``, the chain loop, and its ``FramePrediction``.

The loop is the same for every mode: pairs, the chain (or the closed-form
constant speed), the per-pair fallbacks, the outputs. What a mode adds is its
``InputModel`` (``modes/``: λ(0), Γ after each step, the messages it reads),
looked up by name in ``modes.MODELS``. See the package docstring for the
rules; nothing here touches the bus or the wall clock.
"""

from __future__ import annotations

import bisect
import collections
import functools
import logging
import dataclasses
import math
import operator
from dataclasses import dataclass, field
from typing import Any, Callable, Mapping, NamedTuple

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
from stages.lib.base import ConfigError, Issue, StageResult, isolate
from stages.lib.caps import cap_pairs
from stages.lib.datasets import DEFAULT_SIZES_M
from stages.lib.grid_fusion import parse_shard, shard_of
from stages.lib.markov import MarkovGridConfig, SeparableState, initial_state, load_or_build_stencils, psi_matrix
from stages.lib.markov import frame_kernels, kernels
from stages.lib.markov.grid import uniform_input_edges
from stages.lib.markov.propagate import boxes_outside_grid

from stages.markov_prediction import priority as pr
from stages.markov_prediction.chain import PriorityPropagator
from stages.markov_prediction.config import DEFAULT_PREFERENCE, MarkovPredictionConfig
from stages.markov_prediction.modes import MODELS
from stages.markov_prediction.modes.base import InputModel, Messages, Pair, Vehicle, stay_probabilities
from stages.markov_prediction.modes.corridor_cv import constant_speed
from stages.markov_prediction.modes.cv import CV_LINE_ID
from stages.markov_prediction.initial_blend import OnlineInitialBlend
from stages.markov_prediction.curve_choice import OnlineCurveChoice, OnlineLeadChoice, OnlineShiftChoice, frame_tested, sampled
from stages.markov_prediction.online_spread import DEFAULT_BANDS_MPS, OnlineSpread
from stages.markov_prediction.spread import ALONG_TRUNCATE, SpreadTable, along_spread, blur_grid, load_spread
from stages.markov_prediction.rasterise import (
    Centrelines, FootprintBatch, GridFrame, SparseGrid, cell_footprints_arrays, fuse, lateral_kernel, lateral_table, vehicle_grids,
)
from stages.markov_prediction.signals import apply_signals, stop_line_wall

__all__ = ["CV_LINE_ID", "FramePrediction", "MarkovPredictor", "PairInfo"]

_NS = 1e-9
#: ``spread_shape = "along"`` widens each pair's window by at most this many cells at each end (the blur's reach, 4σ:
#: σ up to 16 m on 1 m cells)
ALONG_PAD_CELLS = 64
#: the online spread's state is logged this often (s of stamps), where the predictor has a logger
ONLINE_LOG_S = 30.0
#: ``MarkovPredictor.speed_noise`` is capped here (m/s): the calibrated spread's widest blur, and so the grid's margin, stays bounded
SPEED_NOISE_CAP_MPS = 2.0
#: the online curve choice back-tests vehicles faster than this (the slow/fast split) with a bend ahead sharper than
#: this curvature (a radius under 50 m); both set before any run
CURVE_MIN_SPEED_MPS = 2.0
CURVE_MIN_CURVATURE_1PM = 0.02


# --------------------------------------------------------------------------- outputs


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
    #: per track id, the start speed (m/s) that picked its grid's spread band (the measured speed, else v0); empty
    #: without a spread table or the online spread
    start_speeds_mps: dict[int, float] = dataclasses.field(default_factory=dict)
    #: with ``MarkovPredictor.keep_geometry``: regrid(track_id, σ per step) -> the vehicle's grid with the along spread of
    #: that σ (``iamp calibrate``'s candidates for ``spread_shape = "along"``); None otherwise
    regrid: Any = None

    def corridor_predictions(self, header: Header, scene_id: str, shard: str = "") -> CorridorPredictions:
        """The ``CorridorPredictions`` message (s-distributions cropped to the cells ever occupied); ``shard``: the
        stage's ("i/n" where it predicts only that shard's vehicles)."""
        out = []
        n_b = len(self.pairs)
        # every pair's arrays converted at once (each message gets its own rows); cells ever occupied: [lo, hi)
        lo: list[int] = []
        hi: list[int] = []
        if n_b and self.position_probs.shape[2]:
            occupied = self.position_probs.max(axis=1) > 0
            any_cell = occupied.any(axis=1)
            lo = np.where(any_cell, occupied.argmax(axis=1), 0).tolist()
            hi = np.where(any_cell, occupied.shape[1] - occupied[:, ::-1].argmax(axis=1), 0).tolist()
        elif n_b:
            lo = hi = [0] * n_b
        v_probs = np.asarray(self.velocity_probs, dtype=np.float32)
        outside = self.outside_mass.astype(np.float32)
        mean_x, mean_y = (self.mean_xy_m[..., j].astype(np.float64) for j in (0, 1))
        mean_s = self.mean_s_m.astype(np.float64)
        at_x, at_y = (self.xy_at_mean_s_m[..., j].astype(np.float64) for j in (0, 1))
        for b, info in enumerate(self.pairs):
            out.append(
                CorridorPrediction(
                    track_id=info.track_id,
                    corridor_id=info.corridor_id,
                    probability=float(info.probability),
                    vehicle_s_m=float(info.vehicle_s_m),
                    s_first_m=float(info.s_first_m + lo[b] * self.ds_m),
                    s_probs=np.ascontiguousarray(self.position_probs[b, :, lo[b]:hi[b]], dtype=np.float32),
                    v_probs=np.ascontiguousarray(v_probs[b]),
                    outside_mass=outside[b],
                    mean_x_m=mean_x[b],
                    mean_y_m=mean_y[b],
                    mean_s_m=mean_s[b],
                    x_at_mean_s_m=at_x[b],
                    y_at_mean_s_m=at_y[b],
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
            shard=shard,
        )

    @functools.cached_property
    def _above_min(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[int], np.ndarray]:
        """The fused grid's keys and values of the K steps, which are above ``min_grid_value``, each step's part
        [bounds[k], bounds[k + 1]) of them (``SparseGrid.step``'s) and the cells above the minimum per step. Found
        once per prediction (``grid_cells_over_cap`` and ``motion_grid`` both read it; neither changes it)."""
        n_k, n_cells = self.step_times_s.shape[0], self.grid_frame.n_cells
        bounds = np.searchsorted(self.fused_grid.keys, np.arange(n_k + 1) * n_cells)
        keys = self.fused_grid.keys[bounds[0]:bounds[-1]]
        values = self.fused_grid.values[bounds[0]:bounds[-1]]
        bounds = bounds - bounds[0]
        keep = values > self.min_grid_value
        counted = np.concatenate(([0], np.cumsum(keep)))
        return keys, values, keep, bounds.tolist(), counted[bounds[1:]] - counted[bounds[:-1]]

    def grid_cells_over_cap(self) -> int:
        """Cells above ``min_grid_value`` that ``motion_grid`` leaves out for ``max_cells_per_step``, all steps."""
        if not self.max_cells_per_step:
            return 0
        counts = self._above_min[4]
        return int(np.maximum(counts - self.max_cells_per_step, 0).sum())

    def motion_grid(self, header: Header, scene_id: str, shard: str = "") -> MotionGrid:
        """The ``MotionGrid`` message: the fused grid, cells above ``min_grid_value``, one COO layer per step; ``shard``
        as in ``corridor_predictions``."""
        frame = self.grid_frame
        n_k = self.step_times_s.shape[0]
        keys, values, keep, bounds, counts = self._above_min
        cap = self.max_cells_per_step
        over = np.flatnonzero(counts > cap).tolist() if cap else []
        if over:
            keep = keep.copy()  # (the cached mask stays as it was)
        for k in over:  # the step's highest cells only
            lo, hi = bounds[k], bounds[k + 1]
            listed = np.flatnonzero(keep[lo:hi])
            top = listed[np.argsort(-values[lo:hi][listed], kind="stable")[:cap]]
            keep[lo:hi] = False
            keep[lo + top] = True
        cells = keys - np.repeat(np.arange(n_k, dtype=np.int64) * frame.n_cells, np.diff(bounds))
        rows, cols = np.divmod(cells[keep], frame.n_cols)
        rows, cols, kept_values = rows.astype(np.int32), cols.astype(np.int32), values[keep].astype(np.float32)
        at = np.concatenate(([0], np.cumsum(keep)))[bounds].tolist()  # each step's part of the kept cells
        steps = [GridStep(rows=rows[at[k]:at[k + 1]], cols=cols[at[k]:at[k + 1]], values=kept_values[at[k]:at[k + 1]]) for k in range(n_k)]
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
            shard=shard,
        )


# --------------------------------------------------------------------------- the core


@dataclass(slots=True)
class _SpeedHistory:
    samples: collections.deque = field(default_factory=lambda: collections.deque(maxlen=64))
    last_stamp_ns: int = 0


def grid_config(config: MarkovPredictionConfig) -> MarkovGridConfig:
    """The Markov discretisation of a markov_prediction configuration (its stencils: ``load_or_build_stencils`` of it)."""
    return MarkovGridConfig(
        ds_m=config.ds_m, dv_mps=config.dv_mps, v_max_mps=config.v_max_mps, tau_s=config.tau_s, n_steps=config.n_steps,
        input_edges_mps2=uniform_input_edges(config.input_min_mps2, config.input_max_mps2, config.n_inputs),
    )


def _stencil_grid(grid: MarkovGridConfig) -> tuple:
    """What of a grid the stencils depend on, apart from the window length (a stencil is translation-invariant)."""
    return (grid.ds_m, grid.dv_mps, grid.v_max_mps, grid.tau_s, grid.input_edges_mps2)


def check_torch_device(config: MarkovPredictionConfig) -> None:
    """The torch backend's CUDA device is here (ConfigError otherwise); the core's start and the launcher's preflight
    (``stages.markov_prediction.__main__``) both ask."""
    if config.backend == "torch" and config.device.startswith("cuda"):
        import torch

        if not torch.cuda.is_available():
            raise ConfigError(f"device = {config.device!r}: no CUDA device here (torch {torch.__version__}); use device = 'cpu'")


class MarkovPredictor:
    """CorridorSet + RelationSet (+ latched SceneInfo, optional TrackFrame) -> CorridorPredictions + MotionGrid.

    ``stencils`` may be passed to share the offline matrices between
    predictors (evaluation, tests); otherwise they come from the disk cache.
    """

    def __init__(self, config: MarkovPredictionConfig, *, producer: str = "markov_prediction", stencils: Any = None,
                 log: Any = None) -> None:
        check_torch_device(config)  # else the first frame failed deep in torch, every frame
        self.config = config
        self.producer = producer
        #: FramePrediction.regrid kept (iamp calibrate with spread_shape "along"): each frame's geometry stays referenced
        self.keep_geometry = False
        self._log = log  # a logging.Logger (the node's): the online spread's state, every ONLINE_LOG_S of stamps
        self._online_logged_ns: int | None = None
        self._blend_logged_ns: int | None = None
        self._shard = parse_shard(config.shard)
        self._shard_label = "" if self._shard is None else f"{self._shard[0]}/{self._shard[1]}"  # the outputs' ``shard``
        self.grid = grid_config(config)
        cfg = self.grid
        self.n_s = config.window_cells
        # the initial box is laid on the window itself (the stencils' grid may have another length)
        self._window_grid = dataclasses.replace(cfg, n_s_cells=self.n_s)
        self._default_half_s_m = max(0.5 * config.ds_m, 2 * config.init_sigma_s_m)
        self._default_half_v_mps = max(0.5 * config.dv_mps, 2 * config.init_sigma_v_mps)
        self.v_centres = cfg.v_centres_mps()
        self.a_centres = cfg.input_centres_mps2()
        self.step_times_s = config.tau_s * np.arange(1, config.n_steps + 1)
        preference = config.free_driving_preference
        if tuple(preference) == DEFAULT_PREFERENCE:  # the default is over [-3, 2] in 0.5 cells: carried over to these cells
            preference = pr.preference_on_cells(preference, uniform_input_edges(), cfg.input_edges())
        self.preference = pr.normalised_preference(preference, cfg.n_inputs)
        self.psi = psi_matrix(self.a_centres, gamma=config.psi_gamma)
        self._lateral = lateral_kernel(config.grid_lateral_sigma_m, config.grid_cell_m)
        frame_kernels.warm_up()  # the output kernels compiled (or loaded from numba's cache) now, not on the first frame
        self._history: dict[int, _SpeedHistory] = {}
        # _speed_line's fits of this frame's vehicles, made together (_fit_speed_lines); emptied when a speed comes in
        self._lines: dict[tuple[int, int], tuple | None] = {}
        self.stencils = None
        self.propagator: PriorityPropagator | None = None
        model_cls = MODELS[config.mode]
        if model_cls.chain:
            if stencils is None:
                stencils = load_or_build_stencils(cfg, config.stencil_cache_dir or None)
            elif _stencil_grid(stencils.config) != _stencil_grid(cfg):
                raise ValueError(f"markov_prediction: the stencils given are for another grid ({_stencil_grid(stencils.config)})"
                                 f" than this configuration's ({_stencil_grid(cfg)}); build them with grid_config(config)")
            self.stencils = stencils
            self.propagator = PriorityPropagator(
                stencils,
                self.psi,
                backend="numpy" if config.backend == "cuda" else config.backend,
                device="cpu" if config.backend == "cuda" else config.device,
                chain_device=config.device if config.backend == "cuda" else None,
                n_s_cells=self.n_s,
                prune_threshold=config.prune_threshold,
                kernel_threads=config.kernel_threads,
            )
        #: the mode's input model (``modes/``): the only mode-specific code the loop calls
        self.model: InputModel = model_cls(self)
        #: the calibrated spread of this mode's grids (``spread.py``), or None
        self.spread: SpreadTable | None = load_spread(config.spread_calibration, config.mode, config.n_steps, config.spread_shape) if config.spread_calibration else None
        if self.spread is not None and self.spread.shape != config.spread_shape:
            (log or logging.getLogger(__name__)).warning(
                "spread_calibration %s: its %s table was fitted for spread_shape %r, applied %r: its coverage will differ (refit"
                " it with `iamp calibrate --set spread_shape='\"%s\"'`)", config.spread_calibration, config.mode, self.spread.shape,
                config.spread_shape, config.spread_shape)
        self._new_learners()
        #: hybrid_profiles "previous": the newest AccelerationProfiles received, by stamp (``remember_profiles``); the
        #: chain of a frame reads the newest from before it (``_chain_profiles``)
        self._recent_profiles: dict[int, AccelerationProfiles] = {}
        self._told_unused = False  # (issue profiles_port_unused: said once)
        self.previous_profiles = config.mode == "hybrid" and config.hybrid_profiles == "previous"
        #: hybrid_profiles "inline": the AR stage's core, run here on every frame whose set holds no profiles, and the
        #: last frame's (stamp, profiles, issues) it gave (a frame's chain phase may run twice; the AR history once)
        self._inline_ar: Any = None
        self._inline_last: tuple | None = None
        if config.mode == "hybrid" and config.hybrid_profiles == "inline":
            from stages.lib.ar.inference import ARInference, ARInferenceConfig  # (torch: only for this mode)

            # over this stage's input cells (the ar_inference stage is told them apart; here they are the stage's own)
            self._inline_ar = ARInference(ARInferenceConfig(model=config.ar_model, input_min_mps2=config.input_min_mps2,
                                                            input_max_mps2=config.input_max_mps2, n_inputs=config.n_inputs),
                                          producer=producer)
        #: whether the chain itself reads the intentions stage's belief (the particle boxes, the stop mixture); where it
        #: does not, ``prepare`` runs the chain before the belief comes
        self.chain_reads_belief = config.initial_box == "particles" or (config.mode == "hybrid" and config.hybrid_stop_mixture)
        self._prepared: tuple[tuple, _Early] | None = None  # (the messages, ``_frame_args``, and ``prepare``'s chain phase of them)
        self._prepared_pairs: tuple[tuple, _PairsPhase] | None = None  # (corridor set, scene, track frame; ``prepare``'s pairs of them)
        #: the last chain phase's back test (``_back_test``'s arguments but the issues), done by ``idle``: off the frame's path
        self._back_test_pending: tuple | None = None
        #: the last update's online spread learning (``_learn_spread``'s arguments but the issues), done by ``idle`` (or
        #: first thing in the next update, pairs or chain phase): off the frame's path
        self._learn_pending: tuple | None = None
        self._carried_issues: list[Issue] = []  # issues of work done by ``idle``: they go out with the next frame's
        #: the scene and the location (``location_id``, else the map's hash) the stage works on, and the stamp it took
        #: them at (``_follow_scene``): another scene starts the tracks afresh, another location the online learners too
        self._scene_id: str | None = None
        self._location: str | None = None
        self._scene_since_ns = -(2**63)
        self._newest_ns = -(2**63)  # the newest stamp of a frame finished (``_follow_scene``, ``_belief_phase``)

    # ----- entry points ---------------------------------------------------------

    def update(self, inputs: Mapping[str, object]) -> StageResult:
        """One frame: ``corridor_set`` and ``relation_set`` (same stamp), ``scene`` (latched), and the optional
        ``track_frame``, ``intention_belief`` and ``acceleration_profiles`` of the same stamp. The chain phase
        ``prepare`` ran for these very messages is used, not run again."""
        corridor_set = inputs.get("corridor_set")
        if not isinstance(corridor_set, CorridorSet):
            return StageResult(issues=[Issue("no_input", -1, "update without a corridor_set")])
        self._learn_now()  # the last frame's online spread learning, if idle has not done it (outputs never depend on when)
        args = _frame_args(inputs)
        belief = inputs.get("intention_belief")
        belief = belief if isinstance(belief, IntentionBelief) else None
        prepared, self._prepared = self._prepared, None
        if prepared is not None and _same_messages(self._chain_key(prepared[0]), self._chain_key(args)):
            early = prepared[1]
        else:
            early = self._chain_phase(*args, intention_belief=belief)
        self.remember_profiles(args[4])
        self.remember_profiles(inputs.get("previous_profiles"))
        prediction, issues = self._belief_phase(early, belief)
        issues.extend(self._take_carried_issues())
        if not self.previous_profiles and not self._told_unused and isinstance(inputs.get("previous_profiles"), AccelerationProfiles):
            self._told_unused = True  # the port is bound where nothing reads it
            issues.append(Issue("profiles_port_unused", -1, "previous_profiles is bound but hybrid_profiles is not \"previous\" (or the mode"
                                " is not hybrid): those profiles are not read; bind acceleration_profiles, or set hybrid_profiles"))
        scene, frame = args[2], args[3]
        if self.online is not None:  # learnt by idle, after this frame's outputs are out (its issues go with the next frame's)
            self._learn_pending = (early.stamp, frame, prediction)
        self._log_initial_blend(early.stamp)
        h = corridor_set.header
        # the source frame's publish time (end-to-end latency): from the TrackFrame when joined, else as the corridors carried it
        wall = frame.header.source_wall_ns if isinstance(frame, TrackFrame) else h.source_wall_ns
        header = Header(run_id=h.run_id, frame_index=h.frame_index, stamp_ns=h.stamp_ns, producer=self.producer, source_wall_ns=wall)
        scene_id = scene.scene_id if isinstance(scene, SceneInfo) else corridor_set.scene_id
        # the grid first: the runtime puts the outputs in this order, and the grid is what the frame's consumers wait for
        outputs: dict[str, Any] = {
            "motion_grid": prediction.motion_grid(header, scene_id, self._shard_label),
            "corridor_predictions": prediction.corridor_predictions(header, scene_id, self._shard_label),
        }
        inline = self._inline_last
        if inline is not None and inline[0] == early.stamp and isinstance(inline[1], AccelerationProfiles):
            outputs["acceleration_profiles"] = inline[1]  # hybrid_profiles "inline": what the ar_inference stage would publish
        return StageResult(outputs=outputs, issues=issues)

    def idle(self) -> None:
        """Work kept off the frames' critical path, done now: the online spread's learning from the last frame's
        grids (``_learn_spread``: with ``spread_online``) and the online curve choice's back test of the last chain
        phase (``_back_test``: the chain again for a car and the other curve factors, every few frames). The runtime
        calls it when the stage's input queues are empty (after a frame's outputs are out); the next pairs or chain
        phase calls it first otherwise (the next update the learning), so what a frame predicts does not depend on
        when it ran. Their issues go out with the next frame's."""
        self._learn_now()
        pending, self._back_test_pending = self._back_test_pending, None
        if pending is not None:
            pairs, stamp, chained = pending
            self._back_test(pairs, stamp, self._carried_issues, chained)

    def prepare(self, inputs: Mapping[str, object], missing: frozenset[str] | set[str]) -> bool:
        """Work on a set that is still ``missing`` inputs, ahead of them: the pairs, then the chain.

        Where the chain does not read the intentions stage's belief (``chain_reads_belief`` false: every mode but
        the baseline's particle boxes and hybrid's stop mixture), all of a frame's work but the corridor weights,
        the grids and the messages can run before the belief comes, and the pairs (with hybrid's speed
        restriction) before the acceleration profiles and the relations too. The runtime offers each incomplete
        set (``stages.runtime.node``); once the corridor set and the track frame are in this builds the pairs
        (``_pairs_phase``), once everything but the belief is in it runs the chain (``_chain_phase``), and
        ``update`` with the whole set then finishes the frame from there. The outputs are those of ``update``
        alone. Returns whether it did any work.
        """
        if self.chain_reads_belief or not isinstance(inputs.get("corridor_set"), CorridorSet):
            return False
        args = _frame_args(inputs)
        self.remember_profiles(args[4])
        self.remember_profiles(inputs.get("previous_profiles"))
        ahead = {"intention_belief", "acceleration_profiles"} if self.previous_profiles else {"intention_belief"}
        if set(missing) <= ahead:
            if self._prepared is not None and _same_messages(self._chain_key(self._prepared[0]), self._chain_key(args)):
                return False  # (hybrid_profiles "previous": the chain ran before the frame's own profiles came)
            self._prepared = None
            self._prepared = (args, self._chain_phase(*args))
            return True
        head = (args[0], args[2], args[3])  # the corridor set, scene and track frame the pairs are built from
        if set(missing) <= {"intention_belief", "acceleration_profiles", "relation_set"} and not (
                self._prepared_pairs is not None and _same_messages(self._prepared_pairs[0], head)):
            self._prepared_pairs = None
            self._prepared_pairs = (head, self._pairs_phase(*head))
            return True
        return False

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
        early = self._chain_phase(corridor_set, relation_set, scene, track_frame, acceleration_profiles, intention_belief=intention_belief)
        self.remember_profiles(acceleration_profiles)
        prediction, issues = self._belief_phase(early, intention_belief)
        issues.extend(self._take_carried_issues())
        self._learn_spread(early.stamp, track_frame, prediction, issues)
        return prediction, issues

    def _take_carried_issues(self) -> list[Issue]:
        """The issues of ``idle``'s work since the last frame went out (they go out with this one)."""
        carried, self._carried_issues = self._carried_issues, []
        return carried

    def _learn_now(self) -> None:
        """The pending online spread learning of the last update (``_learn_spread``), if any."""
        pending, self._learn_pending = self._learn_pending, None
        if pending is not None:
            self._learn_spread(*pending, self._carried_issues)

    def _learn_spread(self, stamp: int, track_frame: TrackFrame | None, prediction: FramePrediction, issues: list[Issue]) -> None:
        """The online spread (``online_spread.py``): the kept grids checked against this frame's positions, this
        frame's grids kept. Without a track frame of this stamp nothing is checked (the grids are still kept). A
        failure costs only this frame's checks (issue ``online_spread_failed``), never its outputs."""
        if self.online is None:
            return
        try:
            self._learn_spread_now(stamp, track_frame, prediction)
        except Exception as exc:  # noqa: BLE001 - the learning is beside the prediction: the frame is published as it is
            self.online.reset()
            issues.append(Issue("online_spread_failed", -1, f"{type(exc).__name__}: {exc}: this frame's checks skipped, the kept grids dropped"))

    def _log_initial_blend(self, stamp: int) -> None:
        """Every ``ONLINE_LOG_S`` of stamps, the weight the online initial blend has learnt (``initial_blend.py``)."""
        if self.initial_blend is None or self._log is None:
            return
        if self._blend_logged_ns is None or abs(stamp - self._blend_logged_ns) >= ONLINE_LOG_S * 1e9:
            self._blend_logged_ns = stamp
            o = self.initial_blend.summary()
            self._log.info("initial blend: weight of the measured acceleration %.2f (least squares %.2f) from %d resolved records"
                           " (%d unresolved)", o["weight"], o["raw_weight"], o["resolved"], o["unresolved"])

    def _choose_all(self, stamp: int, track_frame: TrackFrame | None, issues: list[Issue]) -> None:
        """Every online choice by back testing (``_CHOICES``: the curve factor, the acceleration shift, the speed lead):
        this stamp's positions kept, the samples whose futures are known scored, the value the frame's pairs get set. A
        failure keeps the value it had (the choice's issue, e.g. ``curve_choice_failed``)."""
        for c in _CHOICES:
            choice = getattr(self, c.choice)
            if choice is not None:
                setattr(self, c.value, self._choose(choice, getattr(self, c.value), stamp, track_frame, issues, c.failed, c.what, c.choice))

    def _choose(self, choice: OnlineCurveChoice, current: float, stamp: int, track_frame: TrackFrame | None, issues: list[Issue],
                failed: str, what: str, name: str) -> float:
        """One online choice's step (``_choose_all``); returns the candidate in use."""
        try:
            if isinstance(track_frame, TrackFrame) and int(track_frame.header.stamp_ns) == stamp:
                choice.add_positions(stamp, track_frame.track_ids.tolist(), track_frame.x_m.tolist(), track_frame.y_m.tolist())
            choice.resolve(stamp)
            chosen = choice.factor
        except Exception as exc:  # noqa: BLE001 - the choice is beside the prediction
            choice.reset()
            issues.append(Issue(failed, -1, f"{type(exc).__name__}: {exc}: {what % current} kept"))
            return current
        logged = self._choice_logged_ns.get(name)
        if self._log is not None and (logged is None or abs(stamp - logged) >= ONLINE_LOG_S * 1e9) and (o := choice.summary())["samples"]:
            self._choice_logged_ns[name] = stamp  # (not before the first back-tested vehicle: "mean ADE [nan, nan, nan] m over 0")
            self._log.info(what + " of %s: mean ADE %s m over %d back-tested vehicles (%d unresolved, %d whose track jumped)",
                           o["factor"], o["factors"], np.round(o["mean_ade_m"], 3).tolist(), o["samples"], o["unresolved"], o["jumped"])
        return chosen

    def _back_test(self, pairs: list[Pair], stamp: int, issues: list[Issue], chained: tuple[list[Pair], dict[str, Any], list[int]]) -> None:
        """The online choices' samples of this frame (``curve_choice.frame_tested``): per choice of ``_CHOICES``, at most
        ``curve_choice.PER_FRAME`` of the vehicles the AR model drives that it tests (the curve choice: moving with a curve
        ahead; the shift: any; the lead: with an estimated acceleration); each has its chain run for every candidate but
        the frame's own in one batch (copies of its pairs with that value in the choice's Pair field; ``chained``: the
        frame's chain, as ``_predict_chain`` returns it, whose rows give the candidate in use), their mean positions kept
        to be scored later. The frame's own chain is not touched; a failure costs only this frame's samples of that
        choice (its issue, e.g. ``curve_choice_failed``)."""
        if not frame_tested(stamp, len(pairs)):
            return
        by_track: dict[int, list[Pair]] = {}
        for p in pairs:
            by_track.setdefault(p.track_id, []).append(p)
        driven = {t for t, ps in by_track.items() if all(p.start_rate_hz == 0 and p.input_probs is not None for p in ps)}
        horizon = self.step_times_s[-1]
        for c in _CHOICES:
            choice = getattr(self, c.choice)
            if choice is None:
                continue
            try:
                # each choice its own vehicle where there are several: the stamp's hash moved by c.hash_offset_ns
                eligible = [t for t in sorted(driven) if c.eligible(by_track[t], horizon)]
                self._back_test_choice(choice, c.field, sampled(eligible, stamp + c.hash_offset_ns), by_track, pairs, stamp, issues, chained)
            except Exception as exc:  # noqa: BLE001
                issues.append(Issue(c.failed, -1, f"back test: {type(exc).__name__}: {exc}: this frame's samples skipped"))

    def _back_test_choice(self, choice: OnlineCurveChoice, field_name: str, chosen: list[int], by_track: dict[int, list[Pair]],
                          pairs: list[Pair], stamp: int, issues: list[Issue], chained: tuple[list[Pair], dict[str, Any], list[int]]) -> None:
        """One choice's back test of this frame (``_back_test``): the ``chosen`` vehicles' chains for ``choice``'s other
        candidates of the pair field ``field_name``, recorded with the frame's own rows for the candidate in use."""
        if not chosen:
            return
        final, merged, order = chained
        row_of = {id(final[r]): r for r, b in enumerate(order) if final[r] is pairs[b]}  # pairs the chain itself predicted
        factors = choice.factors
        for track_id in chosen:
            subset = by_track[track_id]
            rows = [row_of.get(id(p)) for p in subset]
            if None in rows:  # a fallback or a failure among its pairs
                continue
            live = getattr(subset[0], field_name)
            others = [f for f in factors if f != live]
            found: list[Issue] = []
            position = self._markov([dataclasses.replace(p, **{field_name: f}) for f in others for p in subset], found)["position"]
            issues.extend(i for i in found if i.kind == "gpu_chain_failed")  # (the copies' own issues are not news)
            n = len(subset)
            done = {f: position[i * n:(i + 1) * n] for i, f in enumerate(others)}
            done[live] = np.asarray(merged["position"])[rows]
            means = self._pair_means(subset * len(factors), np.concatenate([done[f] for f in factors]))
            choice.record(track_id, stamp, means.reshape(len(factors), n, *means.shape[1:]))

    def _pair_means(self, pairs: list[Pair], position: np.ndarray) -> np.ndarray:
        """(P, K, 2): the pairs' mean positions on the map from their chain's position distributions, as
        ``_finish_geometry`` makes them for the outputs (cells past a corridor's end left out)."""
        cfg = self.config
        lower = self.grid.s_edges_m()[: self.n_s]
        pos = np.asarray(position, dtype=np.float32).copy()
        s_first = np.array([p.s_first_m for p in pairs], dtype=np.float64)
        end_s = np.array([p.end_s_m for p in pairs], dtype=np.float64)
        np.copyto(pos, 0.0, where=(s_first[:, None] + lower[None, :] >= end_s[:, None])[:, None, :])
        lines = Centrelines([p.s_m for p in pairs], [p.x_m for p in pairs], [p.y_m for p in pairs], [p.heading_rad for p in pairs])
        mx, my, _ms, ok = _means_on_map(lines, pos, s_first[:, None] + (lower + 0.5 * cfg.ds_m)[None, :], self._lateral_shift(pairs))
        return np.stack([np.where(ok, mx, np.nan), np.where(ok, my, np.nan)], axis=-1)

    def _lateral_shift(self, pairs: list[Pair]) -> np.ndarray:
        """(B, K): each pair's lateral offset d0 at each step, decaying with ``lateral_offset_decay_s`` (§3.6; 0 without)."""
        decay = self.config.lateral_offset_decay_s
        factor = np.exp(-self.step_times_s / decay) if decay > 0 else np.zeros(self.config.n_steps)
        return np.array([p.d0_m for p in pairs], dtype=np.float64).reshape(len(pairs), 1) * factor[None, :]

    def _learn_spread_now(self, stamp: int, track_frame: TrackFrame | None, prediction: FramePrediction) -> None:
        positions: dict[int, tuple[float, float]] = {}
        if isinstance(track_frame, TrackFrame) and int(track_frame.header.stamp_ns) == stamp:
            positions = dict(zip(track_frame.track_ids.tolist(), zip(track_frame.x_m.tolist(), track_frame.y_m.tolist())))
        self.online.update(stamp, positions, prediction.grid_frame, prediction.vehicle_grids, prediction.start_speeds_mps)
        if self._log is not None and (self._online_logged_ns is None or abs(stamp - self._online_logged_ns) >= ONLINE_LOG_S * 1e9):
            self._online_logged_ns = stamp
            o = self.online.summary()
            self._log.info("online spread: checks %s, misses %s, extra sigma at %.1f s %s m (per start-speed band)",
                           o["checks"], o["misses"], float(self.step_times_s[-1]), o["extra_m_last_step"])

    def _pairs_phase(self, corridor_set: CorridorSet, scene: SceneInfo | None = None, track_frame: TrackFrame | None = None, *,
                     intention_belief: IntentionBelief | None = None) -> _PairsPhase:
        """The frame's pairs, without the mode's inputs (``pair_input``) or relations; what the mode prepares from them
        (``InputModel.prepare_pairs``). Reads ``intention_belief`` only where the chain does (``chain_reads_belief``)."""
        self.idle()  # the last frame's back test, if the runtime has not run it: before this frame touches any state
        issues: list[Issue] = []
        stamp = int(corridor_set.header.stamp_ns)
        self._follow_scene(scene, stamp, issues)
        corridor_set, others = self._own_vehicles(corridor_set)
        given = corridor_set
        corridor_set, dropped = cap_pairs(corridor_set, self.config.max_pairs)
        skipped = {v.track_id for v, w in zip(given.vehicles, corridor_set.vehicles) if v.corridors and not w.corridors} | others
        if dropped:
            issues.append(Issue("pairs_capped", -1, f"{dropped} vehicle-corridor pairs beyond max_pairs = {self.config.max_pairs} (whole vehicles, in CorridorSet order): skipped this frame"))
        beliefs = self._beliefs(intention_belief, stamp, issues) if self.chain_reads_belief else None
        self.observe(corridor_set)
        speed_limit = scene.speed_limit_mps if scene is not None and _positive(scene.speed_limit_mps) else self.config.default_speed_limit_mps
        self._choose_all(stamp, track_frame, issues)
        weighed: list[tuple[Any, list, int]] = []
        pairs = self._vehicle_pairs(corridor_set, track_frame, speed_limit, issues, beliefs, weighed)
        if self.model.chain and pairs:  # the chain's batch as _predict_chain will screen it (the inputs are not known yet)
            screened = self._screen(pairs)
            self.model.prepare_pairs([p for b, p in enumerate(pairs) if b not in screened])
        return _PairsPhase(stamp, issues, pairs, weighed, skipped, beliefs)

    def _chain_phase(
        self,
        corridor_set: CorridorSet,
        relation_set: RelationSet | None = None,
        scene: SceneInfo | None = None,
        track_frame: TrackFrame | None = None,
        acceleration_profiles: AccelerationProfiles | None = None,
        *,
        intention_belief: IntentionBelief | None = None,
    ) -> _Early:
        """Everything up to the chain's results: pairs (``_pairs_phase``'s, where ``prepare`` built them from these
        very messages), the mode's inputs, relations, signals, the chain (or the closed form) and the fallbacks.
        Reads ``intention_belief`` only where the chain does (``chain_reads_belief``)."""
        self.idle()  # (prepare may have built this frame's pairs before the last frame's back test ran)
        prepared, self._prepared_pairs = self._prepared_pairs, None
        if prepared is not None and _same_messages(prepared[0], (corridor_set, scene, track_frame)):
            pp = prepared[1]
        else:
            pp = self._pairs_phase(corridor_set, scene, track_frame, intention_belief=intention_belief)
        issues, pairs, stamp = list(pp.issues), pp.pairs, pp.stamp
        if self._inline_ar is not None and acceleration_profiles is None:
            acceleration_profiles = self._inline_profiles(corridor_set, relation_set, track_frame, issues)
        frame_data = self.model.read(Messages(stamp, relation_set, track_frame, intention_belief if self.chain_reads_belief else None,
                                              self._chain_profiles(acceleration_profiles, stamp)), issues)
        for vehicle, good, first in pp.weighed:
            for pair, c in zip(pairs[first:first + len(good)], good):
                pair.input_probs = self.model.pair_input(vehicle.track_id, c.corridor_id, frame_data, issues)
        relations: dict[tuple[int, int], CorridorRelations] = {}
        if relation_set is not None and int(relation_set.header.stamp_ns) != stamp:
            issues.append(
                Issue("stamp_mismatch", -1, f"relation_set stamp {relation_set.header.stamp_ns} != corridor_set stamp {stamp}: relations ignored")
            )
        elif relation_set is not None:
            relations = {(r.track_id, r.corridor_id): r for r in relation_set.relations}
        known = {(p.track_id, p.corridor_id): p for p in pairs}
        for key, relation in relations.items():
            pair = known.get(key)
            if pair is None:
                if key[0] not in pp.skipped:  # a vehicle left out by max_pairs has relations but no prediction: no issue of its own
                    issues.append(Issue("unknown_corridor", key[0], f"relation for corridor {key[1]}, which has no prediction: ignored"))
            else:
                pair.relation = relation
        if self.config.mode == "hybrid" and self.config.hybrid_standstill_rates_hz:
            for pair in pairs:
                if pair.start_rate_hz > 0:
                    # a rate of 0 (stays) is kept just above 0: start_rate_hz 0 marks a moving vehicle
                    pair.start_rate_hz = max(self.config.hybrid_standstill_rates_hz[standstill_group(pair.relation, self.config)], 1e-9)
        self._signal_walls = apply_signals(self, pairs, issues)  # stages.markov_prediction.signals: nothing without signal phases
        final, merged, order = self._predict_chain(pairs, issues)
        if any(getattr(self, c.choice) is not None for c in _CHOICES):  # done by idle, after this frame's outputs (or first thing in the next frame)
            self._back_test_pending = (pairs, stamp, (final, merged, order))
        found: list[Issue] = []
        try:  # the outputs' part that needs no weights, now (a failure: _belief_phase isolates the pairs, from the arrays)
            geometry = (self._finish_geometry(final, merged, found), found)
        except Exception:  # noqa: BLE001 - done again there, pair by pair
            geometry = None
        return _Early(stamp, issues, final, merged, order, pp.weighed, self.chain_reads_belief, pp.beliefs, geometry)

    def _follow_scene(self, scene: SceneInfo | None, stamp: int, issues: list[Issue]) -> None:
        """A frame of another scene than the last starts every track afresh (``reset``: a new sequence, its track ids
        are not the last one's), one of another location (``location_id``, else the map's hash) forgets what was
        learnt online as well (``forget_location``: the curve factor, the speed lead, ... belong to a place and its
        tracker), as a stage started there would be. One issue per change (the runtime logs it). A frame older than the
        one that brought the current scene (``prepare`` may run the next frame first) is the old scene's last: no
        change."""
        # against the newest frame finished (``_belief_phase``), not the newest begun: ``prepare`` works ahead on a later
        # set while an earlier one waits for its belief, and under load (a replay at 4x) that later set was seconds
        # ahead, so the earlier one's update took it for a replay started again and reset every track (44 times in 12 min)
        newest = self._newest_ns
        if stamp < newest - self.config.track_timeout_s * 1e9:  # a replay started again: the tracks' histories lie ahead
            self.reset()
            self._newest_ns = stamp
            what = f"stamp {stamp} is {(newest - stamp) / 1e9:.1f} s before the newest seen (more than track_timeout_s): every track starts afresh"
            issues.append(Issue("stamp_went_back", -1, what))
        if not isinstance(scene, SceneInfo) or stamp < self._scene_since_ns:
            return
        location = scene.location_id or scene.map_sha256 or scene.scene_id
        if scene.scene_id == self._scene_id and location == self._location:
            return
        if self._location is not None and location != self._location:
            issues.append(Issue("location_changed", -1, f"location {self._location!r} -> {location!r}: tracks and what was learnt"
                                " online (curve factor, speed lead, ...) start afresh"))
            self.forget_location()
        elif self._scene_id is not None:  # (the same location: a scene set, and not this one)
            issues.append(Issue("scene_changed", -1, f"scene {self._scene_id!r} -> {scene.scene_id!r} at the same location: every"
                                " track starts afresh"))
            self.reset()
        self._scene_id, self._location, self._scene_since_ns = scene.scene_id, location, stamp

    def _own_vehicles(self, corridor_set: CorridorSet) -> tuple[CorridorSet, set[int]]:
        """The set with this shard's vehicles only, and the track ids of the others (another shard predicts them: left
        out here, without issues); the set as it is and none without shards."""
        if self._shard is None:
            return corridor_set, set()
        index, n_shards = self._shard
        others = {v.track_id for v in corridor_set.vehicles if shard_of(v.track_id, n_shards) != index}
        return dataclasses.replace(corridor_set, vehicles=tuple(v for v in corridor_set.vehicles if v.track_id not in others)), others

    def _inline_profiles(self, corridor_set: CorridorSet, relation_set: RelationSet | None, track_frame: TrackFrame | None,
                         issues: list[Issue]) -> AccelerationProfiles | None:
        """hybrid_profiles "inline": the frame's AR profiles from the stage's own AR core (once per frame: a chain
        phase run again for the same frame reads the first run's), for this shard's vehicles; its issues are the
        frame's. A failure of the AR core costs the frame its profiles (every pair holds its measured acceleration), not
        the frame."""
        stamp = int(corridor_set.header.stamp_ns)
        last = self._inline_last
        if last is None or last[0] != stamp:
            try:  # (another shard's vehicles: their features are that shard's work)
                profiles, ar_issues = self._inline_ar.process(self._own_vehicles(corridor_set)[0], relation_set, track_frame)
            except Exception as exc:  # noqa: BLE001 - the frame goes on without profiles
                profiles, ar_issues = None, [Issue("inline_ar_failed", -1, f"the AR model raised {type(exc).__name__}: {str(exc)[:200]}; no profiles this frame")]
            last = self._inline_last = (stamp, profiles, ar_issues)
        issues.extend(last[2])
        return last[1]

    def remember_profiles(self, profiles: AccelerationProfiles | None) -> None:
        """hybrid_profiles "previous": keep ``profiles`` for the chains of later frames (the newest ``_KEEP_PROFILES``
        by stamp), from the joined ``acceleration_profiles`` or the latest-value ``previous_profiles`` port
        (``pipelines/pipelined.toml``). ``prepare`` calls it as soon as a frame's profiles are in (the next frame's
        chain may run before this one is finished), ``update`` and ``process`` with their frame's; ``iamp eval`` also
        between its instants."""
        if not (self.previous_profiles and isinstance(profiles, AccelerationProfiles)):
            return
        self._recent_profiles[int(profiles.header.stamp_ns)] = profiles
        while len(self._recent_profiles) > _KEEP_PROFILES:
            del self._recent_profiles[min(self._recent_profiles)]

    def _chain_profiles(self, profiles: AccelerationProfiles | None, stamp: int) -> AccelerationProfiles | None:
        """The profiles the chain of the frame at ``stamp`` reads: the frame's own, or with hybrid_profiles "previous"
        the newest kept from before the frame, at most ``hybrid_previous_max_age_s`` older, stamped as the frame (so that
        the mode reads them as its own; None: every pair holds its measured acceleration)."""
        if not self.previous_profiles:
            return profiles
        before = [t for t in self._recent_profiles if t < stamp]
        if not before or stamp - max(before) > self.config.hybrid_previous_max_age_s * 1e9 + _MS_NS:
            return None
        last = self._recent_profiles[max(before)]
        return dataclasses.replace(last, header=dataclasses.replace(last.header, stamp_ns=stamp))

    def _chain_key(self, args: tuple) -> tuple:
        """The messages a chain phase depends on (``_frame_args``): with hybrid_profiles "previous" not the frame's own
        profiles."""
        return args[:4] if self.previous_profiles else args

    def _belief_phase(self, early: _Early, intention_belief: IntentionBelief | None) -> tuple[FramePrediction, list[Issue]]:
        """The rest of the frame: each vehicle's corridor weights (from ``intention_belief`` where the chain phase did
        not read it already), its grid and the outputs."""
        self._newest_ns = max(self._newest_ns, early.stamp)  # the newest frame finished (``_follow_scene``)
        issues = list(early.issues)
        beliefs = early.beliefs if early.beliefs_read else self._beliefs(intention_belief, early.stamp, issues)
        weights: dict[int, float] = {}  # index of the pair (in the chain phase's list) -> P(R = its corridor)
        for vehicle, good, first in early.weighed:
            # (np.float64 items, not Python floats: the grids' arithmetic promotes by the type)
            weights.update(zip(range(first, first + len(good)), self._weights(vehicle, good, beliefs, issues)))
        for p, b in zip(early.final, early.order):  # the pairs as the outputs take them (a fallback's is a copy of its pair)
            w = weights.get(b)
            if w is not None:
                p.probability = w
        prediction = self._predict_finish(early.final, early.merged, issues, early.geometry)
        over = prediction.grid_cells_over_cap()
        if over:
            issues.append(Issue("grid_capped", -1, f"{over} grid cells beyond grid_max_cells_per_step = {self.config.grid_max_cells_per_step} (the lowest values) left out of the MotionGrid"))
        return prediction, issues

    def _new_learners(self) -> None:
        """What the stage learns online about its location, its tracker and the model, from nothing (``__init__``,
        ``forget_location``)."""
        config = self.config
        #: the online spread (``online_spread.py``, ``spread_online``), or None
        self.online: OnlineSpread | None = OnlineSpread(
            self.step_times_s, bands_mps=self.spread.bands_mps if self.spread is not None else DEFAULT_BANDS_MPS,
            target=config.spread_online_target, rate_mps=config.spread_online_rate_mps, max_mps=config.spread_online_max_mps,
            min_speed_mps=config.spread_online_min_speed_mps, stride_s=config.tau_s,
        ) if config.spread_online else None
        #: the learnt weight of the measured acceleration in λ(0) (``initial_blend.py``, hybrid_initial_input "adaptive")
        self.initial_blend: OnlineInitialBlend | None = OnlineInitialBlend(config.accel_window_s) \
            if config.mode == "hybrid" and config.hybrid_initial_input == "adaptive" and config.accel_window_s > 0 else None
        #: hybrid: the factor of the curvature in the speed restriction's cut that the latest pairs phase gave its pairs
        #: (``Pair.curve_factor``; 0: the speed limit alone), and its online choice by back testing (``curve_choice.py``,
        #: ``hybrid_curve_factors``), or None
        self.curve_factor = 1.0 if config.hybrid_speed_restriction_curves else 0.0
        self.curve_choice: OnlineCurveChoice | None = OnlineCurveChoice(config.hybrid_curve_factors, self.step_times_s) \
            if config.mode == "hybrid" and config.hybrid_speed_restriction and config.hybrid_speed_restriction_curves \
            and config.hybrid_curve_factors else None
        #: hybrid: the shift of the AR input distributions that the latest pairs phase gave its moving pairs
        #: (``Pair.accel_shift_mps2``), and its online choice by back testing (``hybrid_accel_shifts``), or None
        self.accel_shift = 0.0
        self.shift_choice: OnlineShiftChoice | None = OnlineShiftChoice(config.hybrid_accel_shifts, self.step_times_s) \
            if config.mode == "hybrid" and config.hybrid_accel_shifts else None
        #: hybrid: the lead (s) of the chain's start speed that the latest pairs phase gave its pairs (``Pair.speed_lead_s``),
        #: and its online choice by back testing (``hybrid_speed_leads_s``), or None
        self.speed_lead = 0.0
        self.lead_choice: OnlineLeadChoice | None = OnlineLeadChoice(config.hybrid_speed_leads_s, self.step_times_s) \
            if config.mode == "hybrid" and config.hybrid_speed_leads_s else None
        #: per online choice (``_CHOICES``), the stamp its state was last logged at
        self._choice_logged_ns: dict[str, int] = {}

    def forget_location(self) -> None:
        """``reset``, and forget what was learnt online as well (the online spread, the initial blend's weight, the curve
        factor, the acceleration shift, the speed lead), which ``reset`` keeps because it belongs to the location, the
        tracker and the model: for a recording of another place, started as a stage started on it would be (``iamp eval``
        calls it between recordings)."""
        self.reset()
        self._new_learners()
        self._location = None  # (with reset's: the next frame's scene is taken as it comes, without an issue)

    def learnt(self) -> dict[str, Any]:
        """What has been learnt online so far: ``initial_blend``, ``curve_choice``, ``accel_shift``, ``speed_lead``
        (each learner's ``summary()``; a learner the config leaves off is absent)."""
        learners = [("initial_blend", self.initial_blend), *((c.key, getattr(self, c.choice)) for c in _CHOICES)]
        return {key: learner.summary() for key, learner in learners if learner is not None}

    def reset(self) -> None:
        """Forget every track's history (a new sequence starts; the offline tables are kept)."""
        if self._inline_ar is not None:
            self._inline_ar.reset()
            self._inline_last = None
        self._history.clear()
        self._lines.clear()
        self._prepared = None
        self._prepared_pairs = None
        self._recent_profiles.clear()
        self._scene_id = None  # (the caller starts a sequence: its scene is taken without an issue; the location is kept)
        self._scene_since_ns = self._newest_ns = -(2**63)  # (nor are its stamps compared with the last one's)
        self._back_test_pending = None  # its samples would be pending in the curve choice, which forgets those too
        self._learn_pending = None  # (the online spread forgets its kept grids too)
        self._carried_issues = []
        if self.online is not None:
            self.online.reset()
        if self.initial_blend is not None:
            self.initial_blend.reset()
        for c in _CHOICES:
            if getattr(self, c.choice) is not None:
                getattr(self, c.choice).reset()

    def observe(self, corridor_set: CorridorSet) -> None:
        """Record each vehicle's speed at this stamp (for its measured acceleration); forget stale tracks.

        The samples are kept in stamp order whatever order the frames come in (``prepare`` may observe a frame
        before the one in front of it is finished): an older stamp is put in its place, one already held is not
        added again."""
        stamp = int(corridor_set.header.stamp_ns)
        self._lines.clear()
        for vehicle in corridor_set.vehicles:
            if not math.isfinite(vehicle.speed_mps):
                continue
            hist = self._history.setdefault(vehicle.track_id, _SpeedHistory())
            if hist.samples and stamp <= hist.samples[-1][0]:
                stamps = [t for t, _ in hist.samples]
                i = bisect.bisect_left(stamps, stamp)
                if stamps[i] == stamp:  # held already
                    continue
                if i == 0 and len(hist.samples) == hist.samples.maxlen:  # older than a full history's every sample
                    continue
                # (i == 0 with room: the vehicle's first frame observed after its second, as prepare can do)
                if len(hist.samples) == hist.samples.maxlen:
                    hist.samples.popleft()
                    i -= 1
                hist.samples.insert(i, (stamp, float(vehicle.speed_mps)))
                continue
            hist.samples.append((stamp, float(vehicle.speed_mps)))
            hist.last_stamp_ns = stamp
        limit = int(self.config.track_timeout_s / _NS)
        for track_id in [t for t, h in self._history.items() if stamp - h.last_stamp_ns > limit]:
            del self._history[track_id]

    # ----- pairs ------------------------------------------------------------------

    def _vehicle_pairs(self, corridor_set: CorridorSet, frame, scene_limit_mps: float, issues: list[Issue], beliefs,
                       weighed: list | None = None) -> list[Pair]:
        """``_pairs`` of the frame; a vehicle whose pairs cannot be built is left out (``vehicle_failed``), not the frame.
        ``weighed`` gets ``_pairs``'s list of the vehicles whose corridor weights are still to be set."""
        vehicles = corridor_set.vehicles

        def attempt(idx: list[int]):
            found: list[Issue] = []
            subset = corridor_set if len(idx) == len(vehicles) else dataclasses.replace(corridor_set, vehicles=tuple(vehicles[i] for i in idx))
            out: list = []
            return self._pairs(subset, frame, scene_limit_mps, found, beliefs, out), found, out

        (pairs, found, out), failed = isolate(range(len(vehicles)), attempt)
        if weighed is not None:
            weighed.extend(out)
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
        slope, sigma = self.measured_acceleration(track_id, stamp_ns)
        if not math.isfinite(slope):
            return 0.0, base
        shrunk = slope * max(0.0, 1.0 - sigma**2 / max(slope**2, 1e-12))
        edges = self.grid.input_edges_mps2
        return float(_clip(shrunk, edges[0], edges[-1])), math.hypot(base, min(sigma, 1.0))

    def measured_acceleration(self, track_id: int, stamp_ns: int) -> tuple[float, float]:
        """(slope, σ_a): the least-squares slope (m/s²) of the vehicle's speeds over the last ``accel_window_s``,
        unshrunk and unclipped, and its standard error √(RSS / (n − 2) / Σ(t − t̄)²) from the fit's residuals;
        (NaN, NaN) with fewer than 3 samples or less than half the window (no measurement). Read by
        ``_acceleration`` and by ``hybrid_initial_input`` "blend" (modes/hybrid.py)."""
        fit = self._speed_line(track_id, stamp_ns)
        if fit is None or fit[1] < 0.5 * self.config.accel_window_s:
            return math.nan, math.nan
        n, _, slope, rss, sxx = fit
        return slope, math.sqrt(rss / (n - 2) / sxx)

    def speed_noise(self, track_id: int, stamp_ns: int) -> float:
        """The scatter (m/s) of the vehicle's measured speeds over the last ``accel_window_s``: the standard deviation
        of their residuals around the least-squares line (0 with fewer than 3 samples); capped at
        ``SPEED_NOISE_CAP_MPS``. Read by a calibrated spread with ``speed_noise_gain`` (spread.py)."""
        fit = self._speed_line(track_id, stamp_ns)
        if fit is None:
            return 0.0
        n, _, _, rss, _ = fit
        return min(math.sqrt(rss / (n - 2)), SPEED_NOISE_CAP_MPS)

    def _speed_line(self, track_id: int, stamp_ns: int) -> tuple[int, float, float, float, float] | None:
        """The least-squares line through the vehicle's measured speeds over the last ``accel_window_s``:
        (samples n, their time span s, slope m/s², residual sum of squares, Σ(t − t̄)²); None with fewer than 3
        samples or ``accel_window_s`` 0. Shared by ``_acceleration`` and ``speed_noise``; the frame's vehicles' lines
        are made together first (``_fit_speed_lines``: the same numbers)."""
        key = (track_id, stamp_ns)
        if key in self._lines:
            return self._lines[key]
        pts = self._window_samples(track_id, stamp_ns)
        if len(pts) < 3:
            return None
        n = len(pts)
        t = np.array([p[0] - pts[-1][0] for p in pts], dtype=np.float64) * _NS  # from the newest, in integer ns first (wall-clock stamps)
        v = np.array([p[1] for p in pts])
        t -= t.sum() / n  # (np.mean's number: the same sum divided by n)
        v_mean = v.sum() / n
        sxx = max(float((t * t).sum()), 1e-12)
        slope = float((t * (v - v_mean)).sum() / sxx)
        residual = v - v_mean - slope * t
        return n, (pts[-1][0] - pts[0][0]) * _NS, slope, float((residual**2).sum()), sxx

    def _window_samples(self, track_id: int, stamp_ns: int) -> list[tuple[int, float]]:
        """The vehicle's (stamp, speed) samples over the last ``accel_window_s`` up to ``stamp_ns``, oldest first (none
        without a history or with ``accel_window_s`` 0)."""
        hist = self._history.get(track_id)
        if hist is None or self.config.accel_window_s <= 0:
            return []
        window = int(self.config.accel_window_s / _NS)
        pts = []
        for t, v in reversed(hist.samples):  # stamps increase (observe): walked back from the newest to the window's start
            if t > stamp_ns:
                continue
            if t < stamp_ns - window:
                break
            pts.append((t, v))
        pts.reverse()
        return pts

    def _fit_speed_lines(self, track_ids: list[int], stamp_ns: int) -> None:
        """``_speed_line`` of every vehicle ``track_ids`` at ``stamp_ns``, kept for this frame: one compiled call over all
        of them (``kernels.speed_lines``: the numpy code's numbers); nothing kept where it cannot take them."""
        found: dict[tuple[int, int], tuple | None] = {}
        stamps: list[int] = []
        speeds: list[float] = []
        ptr = [0]
        fitted: list[tuple[int, int]] = []
        for track_id in track_ids:
            pts = self._window_samples(track_id, stamp_ns)
            if len(pts) < 3:
                found[(track_id, stamp_ns)] = None
                continue
            stamps.extend(p[0] for p in pts)
            speeds.extend(p[1] for p in pts)
            ptr.append(len(stamps))
            fitted.append((track_id, stamp_ns))
        if fitted:
            try:
                lines = kernels.speed_lines(np.array(stamps, dtype=np.int64), np.array(speeds, dtype=np.float64), np.array(ptr, np.int64), _NS)
            except (OverflowError, TypeError, ValueError):  # stamps or speeds numpy cannot take so: each line on its own
                lines = None
            if lines is None:
                return
            counts = np.diff(ptr).tolist()
            for key, n, (span, slope, rss, sxx) in zip(fitted, counts, lines.tolist()):
                found[key] = (n, span, slope, rss, sxx)
        self._lines.update(found)

    def _beliefs(self, belief: IntentionBelief | None, stamp: int, issues: list[Issue]) -> dict[int, dict[int, Any]] | None:
        """Per track, its CorridorBeliefs by corridor id; None when the config does not use them or none fit."""
        cfg = self.config
        if cfg.corridor_weights != "intentions" and cfg.initial_box != "particles" and not (cfg.mode == "hybrid" and cfg.hybrid_stop_mixture):
            return None
        if belief is None:
            issues.append(Issue("no_intentions", -1, "no intention_belief: uniform corridor weights and measured boxes this frame"))
            return None
        if int(belief.header.stamp_ns) != stamp:
            issues.append(Issue("stamp_mismatch", -1, f"intention_belief stamp {belief.header.stamp_ns} != corridor_set stamp {stamp}: ignored"))
            return None
        return {v.track_id: {c.corridor_id: c for c in v.corridors} for v in belief.vehicles}

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
        if not all(math.isfinite(x) and x >= 0 for x in w.tolist()) or w.sum() <= 0:
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
        weighed: list | None = None,
    ) -> list[Pair]:
        """The frame's pairs: per matched vehicle, one per usable corridor (or the mode's own, ``vehicle_pairs``).
        Their ``input_probs`` are None here and their ``probability`` uniform over the vehicle's corridors:
        ``weighed`` gets ``(vehicle, corridors, index of its first pair)`` of each vehicle whose inputs
        ``_chain_phase`` sets (``pair_input``) and whose weights ``_belief_phase`` sets (``_weights``; without
        ``weighed``, this sets the weights, from ``beliefs``)."""
        cfg = self.config
        stamp = int(corridor_set.header.stamp_ns)
        rows: dict[int, int] = {}
        if frame is not None and int(frame.header.stamp_ns) == stamp:
            rows = {int(t): i for i, t in enumerate(frame.track_ids)}
        pairs: list[Pair] = []
        clean = _clean_centrelines(corridor_set.vehicles)
        self._fit_speed_lines([v.track_id for v in corridor_set.vehicles], stamp)  # every vehicle's speed line at once
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
            v0 = float(_clip(vehicle.speed_mps, 0.0, cfg.v_max_mps))
            a0, sigma_a0 = self._acceleration(vehicle.track_id, stamp)
            a_fit, a_fit_se = self.measured_acceleration(vehicle.track_id, stamp) if cfg.mode == "hybrid" and cfg.hybrid_initial_input in ("blend", "adaptive") else (math.nan, math.nan)
            noise = self.speed_noise(vehicle.track_id, stamp) if self.spread is not None and self.spread.speed_noise_gain > 0 else 0.0
            standing = self.model.chain and v0 <= cfg.standstill_speed_mps and cfg.standstill_start_rate_hz > 0
            good = [c for c in vehicle.corridors if _corridor_ok(c, vehicle.track_id, issues, id(c) in clean)]
            if not good:
                continue
            own = self.model.vehicle_pairs(Vehicle(vehicle, good, frame, row, v0, a0, length, width))
            if own is not None:
                for q in own:
                    q.speed_noise_mps = noise
                pairs.extend(own)
                continue
            if weighed is None:
                weights = self._weights(vehicle, good, beliefs, issues)
            else:
                weighed.append((vehicle, good, len(pairs)))
                weights = np.full(len(good), 1.0 / len(good))
            mine = beliefs.get(vehicle.track_id, {}) if beliefs is not None and cfg.initial_box == "particles" else {}
            stops = beliefs.get(vehicle.track_id, {}) if beliefs is not None else {}  # P(stop) per corridor (hybrid_stop_mixture)
            for c, weight in zip(good, weights):
                limit = c.speed_limit_mps if _positive(c.speed_limit_mps) else scene_limit_mps
                s0, hs, hv, v_start = float(c.vehicle_s_m), 0.0, 0.0, v0
                cb = mine.get(c.corridor_id)
                if cb is not None and cb.particle_count > 0 and all(
                    math.isfinite(x) for x in (cb.s_mean_m, cb.s_std_m, cb.v_mean_mps, cb.v_std_mps)
                ):
                    s0, v_start = float(cb.s_mean_m), float(_clip(cb.v_mean_mps, 0.0, cfg.v_max_mps))
                    hs = max(0.5 * cfg.ds_m, 2.0 * float(cb.s_std_m))
                    hv = max(0.5 * cfg.dv_mps, 2.0 * float(cb.v_std_mps))
                if hs > 0 and not self._particle_box_fits(s0, float(c.vehicle_s_m), hs, vehicle.track_id, c.corridor_id, issues):
                    s0, hs, hv, v_start = float(c.vehicle_s_m), 0.0, 0.0, v0
                s_first = self._window_start(s0, float(c.vehicle_s_m), hs)
                pairs.append(
                    Pair(
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
                        a_fit_mps2=a_fit,
                        a_fit_se_mps2=a_fit_se,
                        stamp_ns=stamp,
                        curve_factor=self.curve_factor,
                        accel_shift_mps2=self.accel_shift,
                        speed_lead_s=self.speed_lead,
                        accel_est_mps2=float(vehicle.accel_mps2) if math.isfinite(vehicle.accel_mps2) else math.nan,
                        s_first_m=s_first,
                        length_m=length,
                        width_m=width,
                        d0_m=float(c.vehicle_d_m) if math.isfinite(c.vehicle_d_m) else 0.0,
                        start_rate_hz=cfg.standstill_start_rate_hz if standing else 0.0,
                        half_width_s_m=hs,
                        half_width_v_mps=hv,
                        input_probs=None,  # the mode's λ(0..K-1): set by the chain phase (``pair_input``), once read
                        measured_v_mps=float(vehicle.speed_mps),
                        speed_noise_mps=noise,
                        p_stop=float(stops[c.corridor_id].p_stop) if c.corridor_id in stops else math.nan,
                        stop_distance_m=float(stops[c.corridor_id].stop_distance_m) if c.corridor_id in stops else math.nan,
                    )
                )
        return pairs

    # ----- one pair's failure never costs the frame ----------------------------------

    def _predict(self, pairs: list[Pair], issues: list[Issue]) -> FramePrediction:
        """The frame's prediction (``_predict_chain`` then ``_predict_finish``)."""
        return self._predict_finish(*self._predict_chain(pairs, issues)[:2], issues)

    def _predict_chain(self, pairs: list[Pair], issues: list[Issue]) -> tuple[list[Pair], dict[str, Any], list[int]]:
        """The chain's (or closed form's) arrays of the frame's pairs, each pair's failure isolated: the pairs as the
        outputs take them, the arrays, and each one's index in ``pairs``.

        The mode predicts every pair it can. In the chain modes a pair the
        chain cannot take (``_screen``), or one the batched chain raises on
        (found by bisection, the batch run again without it), is predicted by
        constant speed along its corridor, the ``corridor_cv`` mode (issue
        ``pair_fallback_<reason>``); a pair that fails even so, or whose
        outputs raise, is left out (``pair_failed``). The other pairs are
        predicted exactly as without the failing one, unless they follow or
        yield to it.
        """
        chain = self.model.chain
        simple: dict[int, Pair] = {}  # pair index -> the pair as the fallback predicts it
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
        return final, merged, order

    def _predict_finish(self, final: list[Pair], merged: dict[str, Any], issues: list[Issue],
                        geometry: tuple[dict[str, Any], list[Issue]] | None = None) -> FramePrediction:
        """The outputs of ``_predict_chain``'s pairs and arrays, each pair's failure isolated (``pair_failed``);
        ``geometry``: ``_finish_geometry`` of all of them made before (and its issues), for the first try."""

        def finish(idx: list[int]):
            found: list[Issue] = []
            if geometry is not None and len(idx) == len(final):
                found.extend(geometry[1])
                return self._finish_grids(final, geometry[0]), found
            subset = final if len(idx) == len(final) else [final[i] for i in idx]
            return self._finish(subset, _take(merged, idx, len(final)), found), found

        (prediction, found), failed = isolate(range(len(final)), finish)
        issues.extend(found)
        for i, exc in failed:
            issues.append(Issue("pair_failed", final[i].track_id, f"corridor {final[i].corridor_id}: its outputs raised {type(exc).__name__}: {exc}: not predicted"))
        return prediction

    def _screen(self, pairs: list[Pair]) -> dict[int, tuple[str, str]]:
        """The pairs the chain cannot take, found before the batch: pair index -> (issue kind, why)."""
        out: dict[int, tuple[str, str]] = {}
        if not pairs:
            return out
        boxes = self._boxes(pairs)
        s_out, v_out = boxes_outside_grid(self._window_grid, **boxes)
        v_max = self.config.v_max_mps
        finite = _all_finite(pairs)
        for b, p in enumerate(pairs):
            bad = [] if finite else _non_finite(p)
            if bad:
                out[b] = ("pair_fallback_nan_input", f"non-finite {', '.join(bad)}")
            elif p.measured_v_mps > v_max:
                out[b] = ("pair_fallback_speed_above_vmax", f"speed {p.measured_v_mps:.1f} m/s above the chain's v_max_mps {v_max:g}")
            elif s_out[b] or v_out[b]:
                out[b] = ("pair_fallback_box_outside_window", f"initial box s {boxes['s_m'][b]:.1f} ± {boxes['half_width_s_m'][b]:.1f} m,"
                          f" v {p.v0_mps:.1f} m/s misses its {self.n_s * self.config.ds_m:.0f} m window or the speed cells")
        return out

    # ----- the closed form (modes without the chain, and the fallback) ---------------

    def _constant_velocity(self, pairs: list[Pair]) -> dict[str, np.ndarray]:
        """Constant speed along each pair's line (``modes.corridor_cv.constant_speed``): the closed-form modes and
        the chain modes' fallback."""
        return constant_speed(self, pairs)

    # ----- the chain loop --------------------------------------------------------------

    def _report_gpu(self, issues: list[Issue]) -> None:
        """``gpu_chain_failed`` (frame-level) for a failed GPU run of the chain: the CPU kernel did that run and does
        every later one, so the frame keeps every pair."""
        failures = self.propagator.gpu_failures
        while failures:
            issues.append(Issue("gpu_chain_failed", -1, failures.pop(0)))

    def _markov(self, pairs: list[Pair], issues: list[Issue]) -> dict[str, np.ndarray]:
        """The chain for a batch of pairs: the mode's λ(0) and Γ per step (``InputModel.start``), one pass, and
        another over the pairs the mode names (``ChainInputs.rerun``), whose rows replace the first pass's."""
        cfg, grid = self.config, self.grid
        n_b, n_k, n_v = len(pairs), cfg.n_steps, grid.n_v_cells
        if n_b == 0:
            empty = np.zeros((0, n_k, self.n_s), np.float32)
            return {"position": empty, "interval": empty.copy(), "velocity": np.zeros((0, n_k, n_v), np.float32),
                    "outside": np.zeros((0, n_k), np.float32), "exact_s": None}
        inputs = self.model.start(pairs, issues)
        p0 = self._initial(pairs, inputs.initial())
        steps = inputs.fixed_steps()
        stay = stay_probabilities(pairs, self.step_times_s)  # (B, K) P_stay of standing vehicles, 0 for moving ones
        # a standing vehicle that surely stays (float32 stay probability 1 at every step: _mix_standstill weighs its
        # chain by exactly 0) needs no chain: the compiled path leaves it out (the same numbers)
        frozen = np.all(stay.astype(np.float32) == 1.0, axis=1)
        result = self.propagator.run(p0, inputs.step if steps is None else steps, with_interval=inputs.with_interval,
                                     skip=frozen if frozen.any() else None)
        self._report_gpu(issues)
        pos, vel, interval, outside = self._mix_standstill(
            stay, p0.position_probs, result.position_probs, result.velocity_probs, result.interval_position_probs, result.outside_mass,
        )
        while (m := inputs.rerun({"position": pos, "velocity": vel, "interval": interval, "outside": outside})) is not None:
            sub = SeparableState(input_probs=p0.input_probs[m], velocity_probs=p0.velocity_probs[m], position_probs=p0.position_probs[m])
            again = self.propagator.run(sub, inputs.step, with_interval=inputs.with_interval)
            self._report_gpu(issues)
            mixed = self._mix_standstill(
                stay[m], sub.position_probs, again.position_probs, again.velocity_probs, again.interval_position_probs, again.outside_mass,
            )
            pos, vel, outside = pos.copy(), vel.copy(), outside.copy()
            pos[m], vel[m], outside[m] = mixed[0], mixed[1], mixed[3]
            if interval is not None:
                interval = interval.copy()
                interval[m] = mixed[2]
        pos, vel, interval, outside = stop_line_wall(pairs, getattr(self, "_signal_walls", {}), cfg.ds_m, pos, vel, interval, outside)
        return {"position": pos, "interval": interval, "velocity": vel, "outside": outside, "exact_s": None}

    def measured_inputs(self, pairs: list[Pair]) -> np.ndarray:
        """(B, M): a normal distribution around each pair's measured acceleration over the input cells (tails folded)."""
        edges = self.grid.input_edges()
        a0 = np.array([p.a0_mps2 for p in pairs])
        sigma_a0 = np.array([p.sigma_a0_mps2 for p in pairs])
        cdf = _normal_cdf((edges[None, :] - a0[:, None]) / sigma_a0[:, None])
        cdf[:, 0], cdf[:, -1] = 0.0, 1.0  # fold the tails into the end cells
        probs = np.diff(cdf, axis=1)
        return probs / probs.sum(axis=1, keepdims=True)

    def _boxes(self, pairs: list[Pair]) -> dict[str, np.ndarray]:
        """The initial boxes (§1.4) as ``initial_state`` takes them: centres in window coordinates, half-widths
        (the measurement's defaults, or the particles')."""
        return {
            "s_m": np.array([p.s0_m - p.s_first_m for p in pairs], dtype=np.float64),
            "v_mps": np.array([_chain_start_speed(p, self.config.v_max_mps) for p in pairs], dtype=np.float64),
            "half_width_s_m": np.array([p.half_width_s_m if p.half_width_s_m > 0 else self._default_half_s_m for p in pairs]),
            "half_width_v_mps": np.array([p.half_width_v_mps if p.half_width_v_mps > 0 else self._default_half_v_mps for p in pairs]),
        }

    def _initial(self, pairs: list[Pair], input_probs: np.ndarray):
        """p(t_0) (§1.4): a uniform box in (s, v) (the measurement's, or the particles') × ``input_probs``, on the window."""
        return initial_state(self._window_grid, **self._boxes(pairs), input_probs=input_probs)

    @staticmethod
    def _mix_standstill(stay, start_probs, pos, vel, interval, outside):
        """Standing vehicles (package docstring, "Standstill"): P_stay(t)·(start box, v-cell 0) + (1 − P_stay(t))·chain,
        ``stay`` (B, K) the pairs' ``stay_probabilities``."""
        rows = np.flatnonzero(np.any(stay > 0, axis=1))
        if rows.size == 0:
            return pos, vel, interval, outside
        # only the standing pairs' rows are mixed (a moving pair's P_stay is 0 at every step: its rows stay as they are,
        # 1·x + 0·start being x), into copies of the chain's arrays, each row by the formulas below
        w = stay[rows, :, None].astype(np.float32)
        start = start_probs[rows, None, :]
        pos, vel = np.array(pos), np.array(vel)  # (copies in their own dtype: float32 at the end, as every row was)
        pos[rows] = (1.0 - w) * pos[rows] + w * start
        vel[rows] = (1.0 - w) * vel[rows]
        vel[rows, :, 0] += stay[rows].astype(np.float32)
        if interval is not None:
            interval = np.array(interval)
            interval[rows] = (1.0 - w) * interval[rows] + w * start
            interval = interval.astype(np.float32, copy=False)
        outside = (1.0 - stay.astype(np.float32)) * outside
        return pos.astype(np.float32, copy=False), vel.astype(np.float32, copy=False), interval, outside

    # ----- outputs --------------------------------------------------------------------

    def _finish(self, pairs: list[Pair], arrays: dict[str, Any], issues: list[Issue]) -> FramePrediction:
        """The outputs of the pairs' chain arrays: ``_finish_grids`` of ``_finish_geometry``."""
        return self._finish_grids(pairs, self._finish_geometry(pairs, arrays, issues))

    def _finish_geometry(self, pairs: list[Pair], arrays: dict[str, Any], issues: list[Issue]) -> dict[str, Any]:
        """What of the outputs does not depend on the corridor weights: the distributions cut at each corridor's end,
        the means on the map, the cells' footprints and the grid's frame (``arrays`` is not changed)."""
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
        pos = pos.copy()
        if interval is not None:
            interval = np.asarray(interval, dtype=np.float32).copy()
        s_first = np.array([p.s_first_m for p in pairs], dtype=np.float64).reshape(n_b)
        end_s = np.array([p.end_s_m for p in pairs], dtype=np.float64).reshape(n_b)
        s0 = np.array([p.s0_m for p in pairs], dtype=np.float64).reshape(n_b)  # each vehicle's position now
        beyond_all = s_first[:, None] + lower[None, :] >= end_s[:, None]  # cells past the corridor's end count as outside
        past = np.flatnonzero(beyond_all.any(axis=1))
        if past.size:
            # a pair whose cells past the end hold only +0.0 adds +0.0 to its outside mass (all at once); one with mass
            # (or a -0.0) there, its own sum
            held = pos[past]
            own = (((held != 0) | np.signbit(held)) & beyond_all[past][:, None, :]).any(axis=(1, 2))
            for b in past[own].tolist():
                outside[b] += pos[b][:, beyond_all[b]].sum(axis=1)
            outside[past[~own]] += 0.0
            np.copyto(pos, 0.0, where=beyond_all[:, None, :])
            if interval is not None:
                np.copyto(interval, 0.0, where=beyond_all[:, None, :])
        # every pair at once (rasterise.Centrelines: one np.interp per quantity over all the pairs' centrelines)
        lines = Centrelines([p.s_m for p in pairs], [p.x_m for p in pairs], [p.y_m for p in pairs], [p.heading_rad for p in pairs])
        shift_all = self._lateral_shift(pairs)
        if n_b:
            mx, my, ms, ok = _means_on_map(lines, pos, s_first[:, None] + centre[None, :], shift_all)
            mean_xy[..., 0] = np.where(ok, mx, np.nan)
            mean_xy[..., 1] = np.where(ok, my, np.nan)
            mean_s[:] = np.where(ok, ms, np.nan)
            exact = arrays.get("exact_s")
            if exact is not None:  # constant velocity (a mode, or a fallback): the exact point
                exact = np.asarray(exact, dtype=np.float64)
                rows = np.flatnonzero(np.all(np.isfinite(exact), axis=1))
                if rows.size:
                    sub = Centrelines([pairs[b].s_m for b in rows], [pairs[b].x_m for b in rows], [pairs[b].y_m for b in rows],
                                      [pairs[b].heading_rad for b in rows])
                    ex, ey, eh = sub.xy_heading(exact[rows])
                    mean_s[rows] = exact[rows]
                    mean_xy[rows, :, 0] = ex + shift_all[rows] * -np.sin(eh)
                    mean_xy[rows, :, 1] = ey + shift_all[rows] * np.cos(eh)
            finite = np.isfinite(mean_s)
            at = np.where(finite, mean_s, s0[:, None])
            sx, sy, _h, cos_at, sin_at = lines.xy_heading_trig(at)
            xy_at_mean[..., 0] = np.where(finite, sx + shift_all * -sin_at, np.nan)
            xy_at_mean[..., 1] = np.where(finite, sy + shift_all * cos_at, np.nan)
        for b, p in enumerate(pairs):
            if outside[b, -1] > cfg.outside_issue_mass:
                issues.append(
                    Issue(
                        "corridor_too_short",
                        p.track_id,
                        f"corridor {p.corridor_id}: outside mass {outside[b, -1]:.3f} at {self.step_times_s[-1]:.1f} s"
                        f" (corridor ends {p.end_s_m - p.s0_m:.1f} m ahead, v0 {p.v0_mps:.1f} m/s)",
                    )
                )
        grid_probs = interval if (cfg.grid_distribution == "interval" and interval is not None) else pos
        raw_grid_probs, lateral, lateral_kernel_ = grid_probs, None, self._lateral
        raw_lower = cell_lower = s_first[:, None] + lower[None, :]  # (B, L)
        if cfg.spread_shape == "along" and (self.spread is not None or self.online is not None) and n_b:
            # the grids only (pos and interval stay): along the corridor, and across it per step
            grid_probs, cell_lower, lateral_kernel_, lateral = self._along(grid_probs, self._vehicle_sigmas(pairs), cell_lower, end_s, s0)
        used = grid_probs.max(axis=1) > 0 if n_b else None  # (B, L): the cells that hold mass at some step, the only ones rasterised
        batch = cell_footprints_arrays(lines, cell_lower, cfg.ds_m, cfg.grid_substeps, *lateral_kernel_, used=used) if n_b else None
        frame = self._grid_frame(batch, used)
        return {"position": pos, "interval": interval, "velocity": np.asarray(arrays["velocity"], dtype=np.float32), "outside": outside,
                "mean_xy": mean_xy, "mean_s": mean_s, "xy_at_mean": xy_at_mean, "frame": frame, "batch": batch, "grid_probs": grid_probs,
                "shift": shift_all, "lateral": lateral,
                # for ``regrid`` (``keep_geometry``): the grids rebuilt with another along spread
                "lines": lines, "cell_lower": raw_lower, "end_s": end_s, "start_s": s0, "raw_grid_probs": raw_grid_probs}

    def _finish_grids(self, pairs: list[Pair], geo: dict[str, Any]) -> FramePrediction:
        """The outputs from ``_finish_geometry``'s: each vehicle's grid (its corridors' weighted by ``probability``),
        blurred by the calibrated spread, and their fusion."""
        cfg, n_b = self.config, len(pairs)
        frame, batch, grid_probs, shift_all, interval = geo["frame"], geo["batch"], geo["grid_probs"], geo["shift"], geo["interval"]
        by_track: dict[int, list[int]] = collections.defaultdict(list)
        for b, p in enumerate(pairs):
            by_track[p.track_id].append(b)
        # every vehicle's grid in one compiled call (rasterise.vehicle_grids: vehicle_grid's numbers)
        grids = vehicle_grids(frame, batch, grid_probs, [p.probability for p in pairs], list(by_track.values()), shift_all,
                              threads=cfg.kernel_threads, lateral=geo.get("lateral")) if n_b else []
        vehicle_grids_ = dict(zip(by_track.keys(), grids))
        start_speeds: dict[int, float] = {}
        to_fuse = grids  # (a VehicleGrids: the fusion takes the compiled call's arrays as they are, unless blurred below)
        if self.spread is not None or self.online is not None:  # calibrated (spread.py) and online spread: each vehicle's
            isotropic = cfg.spread_shape == "isotropic"  # grid blurred per step and start-speed band (``along``: its
            for track, members in by_track.items():  # pairs' s-distributions were, in _finish_geometry)
                p = pairs[members[0]]
                start_speeds[track] = _start_speed(p)
                if isotropic:
                    vehicle_grids_[track] = blur_grid(frame, vehicle_grids_[track], self._sigmas(start_speeds[track], p.speed_noise_mps))
            if isotropic:
                to_fuse = list(vehicle_grids_.values())
        infos = tuple(PairInfo(p.track_id, p.corridor_id, p.probability, p.s0_m, p.s_first_m, p.end_s_m) for p in pairs)
        return FramePrediction(
            mode=cfg.mode,
            step_times_s=self.step_times_s.copy(),
            ds_m=cfg.ds_m,
            dv_mps=cfg.dv_mps,
            pairs=infos,
            position_probs=geo["position"],
            interval_probs=interval,
            velocity_probs=geo["velocity"],
            outside_mass=geo["outside"].astype(np.float32),
            mean_xy_m=geo["mean_xy"],
            mean_s_m=geo["mean_s"],
            xy_at_mean_s_m=geo["xy_at_mean"],
            grid_frame=frame,
            grid_distribution=cfg.grid_distribution if interval is not None or cfg.grid_distribution == "point" else "point",
            vehicle_grids=vehicle_grids_,
            fused_grid=fuse(to_fuse, frame.n_cells, threads=cfg.kernel_threads),
            min_grid_value=cfg.grid_min_value,
            max_cells_per_step=cfg.grid_max_cells_per_step,
            start_speeds_mps=start_speeds,
            regrid=functools.partial(self._regrid, pairs, geo) if self.keep_geometry else None,
        )

    def _vehicle_sigmas(self, pairs: list[Pair]) -> np.ndarray:
        """(B, K) the spread's σ (m) of each pair: its vehicle's (``_sigmas``)."""
        sigma = np.zeros((len(pairs), self.step_times_s.size))
        by_track: dict[int, np.ndarray] = {}
        for b, p in enumerate(pairs):
            if p.track_id not in by_track:
                by_track[p.track_id] = self._sigmas(_start_speed(p), p.speed_noise_mps)
            sigma[b] = by_track[p.track_id]
        return sigma

    def _along(self, probs: np.ndarray, sigma: np.ndarray, cell_lower: np.ndarray, end_s: np.ndarray, start_s: np.ndarray):
        """``spread_shape = "along"``: the s-distributions ``probs`` (B, K, L) on the cells of lower edges ``cell_lower``
        (B, L) blurred along their corridors by σ (m, (B, K)), and the lateral kernel widened per step
        (``lateral_table``). The window grows by the blur's reach (at most ``ALONG_PAD_CELLS``) at both ends, so that
        what is blurred behind the window's start or past its end stays (the footprints continue the centreline
        straight past its ends); none past the corridor's end (``end_s``, (B,)). With ``spread_fold_start`` what the
        blur carries behind each pair's start (``start_s``, (B,): the vehicle's position now) is folded ahead of it
        (``fold_behind``). Returns (probs, a new array or ``probs`` itself where every σ is 0; their cells' lower edges
        (B, L'); the footprints' (offsets, weights); the ``lateral`` (rows, table) of ``vehicle_grids`` or None)."""
        cfg = self.config
        if not np.any(sigma > 0):
            return probs, cell_lower, self._lateral, None
        pad = min(int(math.ceil(ALONG_TRUNCATE * float(np.nanmax(np.where(np.isfinite(sigma), sigma, 0.0))) / cfg.ds_m)), ALONG_PAD_CELLS)
        if pad > 0:
            cell_lower = np.concatenate([cell_lower[:, :1] - cfg.ds_m * np.arange(pad, 0, -1)[None, :], cell_lower,
                                         cell_lower[:, -1:] + cfg.ds_m * np.arange(1, pad + 1)[None, :]], axis=1)
        # padded, blurred, folded ahead of the start (spread_fold_start), none past the corridor's end (outside)
        start_cell = np.floor((start_s - cell_lower[:, 0]) / cfg.ds_m).astype(np.int64) if cfg.spread_fold_start else None
        out = along_spread(probs, sigma / cfg.ds_m, pad, start_cell, cell_lower >= end_s[:, None])
        if cfg.spread_lateral_ratio > 0:
            base = cfg.grid_lateral_sigma_m
            wide = np.minimum(np.hypot(base, cfg.spread_lateral_ratio * sigma), max(cfg.spread_lateral_max_m, base))
            offsets, base_w, rows, table = lateral_table(np.where(sigma > 0, wide, base), base, cfg.grid_cell_m)
            if table is not None:
                return out, cell_lower, (offsets, base_w), (rows, table)
        return out, cell_lower, self._lateral, None

    def _regrid(self, pairs: list[Pair], geo: dict[str, Any], track_id: int, sigmas_m: np.ndarray) -> SparseGrid | None:
        """The grid of vehicle ``track_id`` rebuilt from this frame's unblurred distributions with the along spread
        of σ = ``sigmas_m`` (K,) at each step (``iamp calibrate``'s candidates; ``keep_geometry``); None for a
        vehicle not predicted."""
        cfg = self.config
        members = [b for b, p in enumerate(pairs) if p.track_id == track_id]
        if not members:
            return None
        raw = geo["raw_grid_probs"]
        probs = np.zeros_like(raw)
        sigma = np.zeros(raw.shape[:2])
        sigma[members] = np.asarray(sigmas_m, dtype=np.float64)[None, :]
        probs[members] = raw[members]
        probs, cell_lower, kernel, lateral = self._along(probs, sigma, geo["cell_lower"], geo["end_s"], geo["start_s"])
        used = probs.max(axis=1) > 0
        batch = cell_footprints_arrays(geo["lines"], cell_lower, cfg.ds_m, cfg.grid_substeps, *kernel, used=used)
        return vehicle_grids(geo["frame"], batch, probs, [p.probability for p in pairs], [members], geo["shift"], lateral=lateral)[0]

    def _sigmas(self, speed_mps: float, speed_noise_mps: float) -> np.ndarray:
        """The blur σ per step of a vehicle's grid: the spread table's (with its speed noise), widened by the online
        spread's extra σ (√(table² + extra²))."""
        table = self.spread.sigmas(speed_mps, speed_noise_mps, self.step_times_s) if self.spread is not None else np.zeros(self.step_times_s.size)
        return np.hypot(table, self.online.extra_sigmas(speed_mps)) if self.online is not None else table

    def _grid_frame(self, footprints: FootprintBatch | None, used: np.ndarray | None) -> GridFrame:
        """The frame's grid: the configured extent, or around the samples of every cell ``used`` (B, L): the cells that
        hold mass at some step."""
        cfg = self.config
        if cfg.grid_extent_m:
            return GridFrame.fixed(tuple(cfg.grid_extent_m), cfg.grid_cell_m)
        bounds = footprints.bounds(used) if footprints is not None and used is not None else None
        if bounds is None:
            return GridFrame(0.0, 0.0, cfg.grid_cell_m, 1, 1)
        widest = 0.0  # along: blurred before rasterising, the cells it reaches are among the bounds
        if cfg.spread_shape == "isotropic":
            widest = float(self.spread.max_sigma_m(self.step_times_s, SPEED_NOISE_CAP_MPS)) if self.spread is not None else 0.0
            if self.online is not None:
                widest = math.hypot(widest, self.online.max_sigma_m())
        margin = cfg.grid_margin_m + 3.0 * widest  # the blur stays on the grid
        x_lo, x_hi, y_lo, y_hi = bounds
        return GridFrame.around(np.array([x_lo, x_hi]), np.array([y_lo, y_hi]), cfg.grid_cell_m, margin)


# --------------------------------------------------------------------------- helpers


_CHAIN_SCALARS = ("s0_m", "v0_mps", "a0_mps2", "sigma_a0_mps2", "s_first_m", "speed_limit_mps", "d0_m", "length_m", "width_m",
                  "half_width_s_m", "half_width_v_mps", "start_rate_hz", "probability")
_CHAIN_ARRAYS = ("s_m", "x_m", "y_m", "heading_rad", "curvature_1pm", "input_probs")
_chain_scalars = operator.attrgetter(*_CHAIN_SCALARS)  # a pair's scalars (a tuple), as getattr of each gives them
_chain_arrays = operator.attrgetter(*_CHAIN_ARRAYS)


@dataclass(slots=True)
class _Early:
    """A frame after ``_chain_phase``: what ``_belief_phase`` finishes it from."""

    stamp: int
    issues: list[Issue]
    final: list[Pair]  # the pairs as the outputs take them
    merged: dict[str, Any]  # their arrays
    order: list[int]  # each one's index in the chain phase's pair list
    weighed: list[tuple[Any, list, int]]  # (vehicle, its corridors, index of its first pair): weights still to set
    beliefs_read: bool  # whether the chain phase read the belief (then ``beliefs`` is what it read)
    beliefs: dict[int, dict[int, Any]] | None
    geometry: tuple[dict[str, Any], list[Issue]] | None = None  # ``_finish_geometry`` of ``final`` and its issues (None: failed)


@dataclass(slots=True)
class _PairsPhase:
    """A frame after ``_pairs_phase``: its pairs, before the mode's inputs, relations and the chain."""

    stamp: int
    issues: list[Issue]
    pairs: list[Pair]
    weighed: list[tuple[Any, list, int]]  # (vehicle, its corridors, index of its first pair): inputs and weights still to set
    skipped: set[int]  # vehicles left out (max_pairs, other shards): their relations raise no issue
    beliefs: dict[int, dict[int, Any]] | None  # what it read of the belief (``chain_reads_belief``), else None


_MS_NS = 1_000_000  # (a frame period's rounding in stamps: 1 ms)
_KEEP_PROFILES = 4  # hybrid_profiles "previous": profiles messages kept (frames handled a little out of order find theirs)
#: the inputs of ``_chain_phase``, in its order, with the type each must have (else None)
_FRAME_INPUTS = (("corridor_set", CorridorSet), ("relation_set", RelationSet), ("scene", SceneInfo), ("track_frame", TrackFrame),
                 ("acceleration_profiles", AccelerationProfiles))


def _frame_args(inputs: Mapping[str, object]) -> tuple:
    """``_chain_phase``'s positional arguments from a set of inputs (a message of the wrong type: None)."""
    return tuple(m if isinstance(m := inputs.get(name), cls) else None for name, cls in _FRAME_INPUTS)


def _same_messages(a: tuple, b: tuple) -> bool:
    """Whether two ``_frame_args`` hold the very same message objects (not equal copies: a prepared chain phase is
    used only for the set it ran on)."""
    return len(a) == len(b) and all(x is y for x, y in zip(a, b))


def standstill_group(relation: CorridorRelations | None, config: MarkovPredictionConfig) -> int:
    """A standing vehicle's scene on one corridor: 0 no leader within ``standstill_leader_gap_m`` (or no relations),
    1 a standing leader, 2 a leader faster than ``standstill_leader_moving_mps`` (it pulls away: the queue discharges);
    with a fourth rate in ``hybrid_standstill_rates_hz``, 3 (instead of 0 or 1): the vehicle stands inside an
    intersection of the corridor or less than ``standstill_intersection_m`` before its entry (it waits for a gap)."""
    group = 0
    if relation is not None and relation.leader_track_id >= 0 and math.isfinite(relation.leader_gap_m) \
            and relation.leader_gap_m <= config.standstill_leader_gap_m:
        speed = relation.leader_speed_mps
        group = 2 if math.isfinite(speed) and speed > config.standstill_leader_moving_mps else 1
    if group != 2 and len(config.hybrid_standstill_rates_hz) == 4 and relation is not None and at_intersection(relation, config.standstill_intersection_m):
        return 3
    return group


def at_intersection(relation: CorridorRelations, within_m: float) -> bool:
    """The vehicle is inside one of the corridor's intersections or less than ``within_m`` before its entry."""
    d = np.asarray(relation.intersection_distance_m, dtype=np.float64)
    length = np.asarray(relation.intersection_exit_s_m, dtype=np.float64) - np.asarray(relation.intersection_entry_s_m, dtype=np.float64)
    ok = np.isfinite(d) & np.isfinite(length)
    return bool(np.any(ok & (d < within_m) & (d + length > 0)))


def _start_speed(p: Pair) -> float:
    """The start speed that picks a vehicle's spread band: its measured speed, else the chain's v0."""
    return p.measured_v_mps if math.isfinite(p.measured_v_mps) else p.v0_mps


def _non_finite(p: Pair) -> list[str]:
    """The names of the pair's numbers the chain reads that are not finite (none: [])."""
    bad = [name for name in _CHAIN_SCALARS if not math.isfinite(getattr(p, name))]
    return bad + [name for name in _CHAIN_ARRAYS if getattr(p, name) is not None and not np.all(np.isfinite(getattr(p, name)))]


def _all_finite(pairs: list[Pair]) -> bool:
    """Whether every number the chain reads of every pair is finite (``_non_finite`` of each is []), checked at once."""
    try:
        scalars = np.array([_chain_scalars(p) for p in pairs], dtype=np.float64)
        if not np.isfinite(scalars).all():
            return False
        arrays = np.concatenate([a for p in pairs for a in _chain_arrays(p) if a is not None], axis=None)  # each flattened
        return bool(np.isfinite(arrays).all())
    except (TypeError, ValueError, OverflowError):  # numbers numpy cannot check together: each pair on its own
        return False


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


def _means_on_map(lines: Centrelines, pos: np.ndarray, s_abs: np.ndarray, shift_all: np.ndarray):
    """(mean x, mean y, mean s, has mass), each (B, K): the position distributions ``pos`` (B, K, L) over the cells
    centred at ``s_abs`` (B, L) on the centrelines ``lines``, moved sideways by ``shift_all`` (B, K)."""
    x_c, y_c, _h, ny_c, sin_c = lines.xy_heading_trig(s_abs)
    nx_c = -sin_c
    mass = pos.sum(axis=2, dtype=np.float64)  # (B, K)
    ok = mass > 1e-9
    pos64 = pos.astype(np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        mx = (np.einsum("bkl,bl->bk", pos64, x_c) + shift_all * np.einsum("bkl,bl->bk", pos64, nx_c)) / mass
        my = (np.einsum("bkl,bl->bk", pos64, y_c) + shift_all * np.einsum("bkl,bl->bk", pos64, ny_c)) / mass
        ms = np.einsum("bkl,bl->bk", pos64, s_abs) / mass
    return mx, my, ms, ok


class _Choice(NamedTuple):
    """One online choice by back testing (``curve_choice.py``), as the predictor wires it."""

    choice: str  # the predictor's attribute holding it (None: off)
    key: str  # its summary's key in ``learnt`` (and in the eval JSON)
    value: str  # the predictor's attribute holding the value in use
    field: str  # the Pair field the value goes to (its back test runs copies of the pairs with each candidate there)
    failed: str  # the issue of a failure (the frame keeps its value)
    what: str  # its value in words, for the log and the issue
    hash_offset_ns: int  # where the stamp's hash starts choosing among the eligible vehicles (each choice its own)
    eligible: Callable[[list[Pair], float], bool]  # (a driven vehicle's pairs, horizon s): whether it is back-tested


def _curve_eligible(pairs: list[Pair], horizon_s: float) -> bool:
    """The curve choice tests a moving vehicle with a bend ahead."""
    return all(p.v0_mps > CURVE_MIN_SPEED_MPS for p in pairs) and any(_curve_ahead(p, horizon_s) for p in pairs)


def _leads(p: Pair) -> bool:
    """Whether the pair's chain may start ahead of its speed (``hybrid_speed_leads_s``): moving, with an estimated acceleration."""
    return p.start_rate_hz == 0 and math.isfinite(p.accel_est_mps2)


def _chain_start_speed(p: Pair, v_max_mps: float) -> float:
    """The centre of the pair's initial speed box: v0, or v0 + ``speed_lead_s`` · the estimated acceleration (within
    [0, ``v_max_mps``]) for a moving pair with one (``hybrid_speed_leads_s``)."""
    if p.speed_lead_s == 0.0 or not _leads(p):
        return p.v0_mps
    return float(min(max(p.v0_mps + p.speed_lead_s * p.accel_est_mps2, 0.0), v_max_mps))


#: the online choices by back testing, in the order they are chosen and back-tested
_CHOICES = (
    _Choice("curve_choice", "curve_choice", "curve_factor", "curve_factor", "curve_choice_failed", "curve factor %g", 0, _curve_eligible),
    _Choice("shift_choice", "accel_shift", "accel_shift", "accel_shift_mps2", "accel_shift_failed", "acceleration shift %g m/s²", 1000,
            lambda pairs, horizon_s: True),  # any vehicle the AR model drives
    _Choice("lead_choice", "speed_lead", "speed_lead", "speed_lead_s", "speed_lead_failed", "speed lead %g s", 2000,
            lambda pairs, horizon_s: all(_leads(p) for p in pairs)),  # moving, with an estimated acceleration
)


def _curve_ahead(p: Pair, horizon_s: float) -> bool:
    """Whether the pair's corridor bends (|κ| above ``CURVE_MIN_CURVATURE_1PM``) within the distance it may cover in
    ``horizon_s`` (at its speed + 2 m/s, and 10 m more) ahead of it."""
    s = np.asarray(p.s_m, dtype=np.float64)
    kappa = np.abs(np.asarray(p.curvature_1pm, dtype=np.float64))
    ahead = (s >= p.s0_m) & (s <= p.s0_m + (p.v0_mps + 2.0) * horizon_s + 10.0)
    return bool(np.any(np.where(np.isfinite(kappa), kappa, 0.0)[ahead] > CURVE_MIN_CURVATURE_1PM))


def _normal_cdf(z: np.ndarray) -> np.ndarray:
    from scipy.special import ndtr

    return ndtr(z)


def _clip(value: float, lo: float, hi: float) -> float:
    """``np.clip`` of one number (the same result, signed zeros and NaN included), without its array overhead."""
    return min(max(value, lo), hi)


def _positive(value: float) -> bool:
    return math.isfinite(value) and value > 0


def _clean_centrelines(vehicles) -> set[int]:
    """The ``id()`` of every corridor of ``vehicles`` whose centreline passes ``_corridor_ok``'s array checks (1-D, at
    least two points, arrays of one shape, finite, s increasing), checked for all of them at once; the others (none on
    clean input) go through ``_corridor_ok``'s own checks, with its issues. Empty when the arrays cannot be checked so."""
    corridors, parts = [], []
    for vehicle in vehicles:
        for c in vehicle.corridors:
            arrays = [np.asarray(a) for a in (c.s_m, c.x_m, c.y_m, c.heading_rad)]
            shape = arrays[0].shape
            if len(shape) == 1 and shape[0] >= 2 and all(a.shape == shape for a in arrays[1:]):
                corridors.append(c)
                parts.append(arrays)
    if not corridors:
        return set()
    try:
        s, x, y, h = (np.concatenate([arrays[j] for arrays in parts]) for j in range(4))
        starts = np.cumsum([0] + [arrays[0].shape[0] for arrays in parts[:-1]])
        ok = np.isfinite(s) & np.isfinite(x) & np.isfinite(y) & np.isfinite(h)
        ok[1:] &= s[1:] - s[:-1] > 0  # np.diff(s) > 0 inside each corridor ...
        ok[starts] = np.isfinite(s[starts]) & np.isfinite(x[starts]) & np.isfinite(y[starts]) & np.isfinite(h[starts])  # ... not across
        clean = np.logical_and.reduceat(ok, starts)
    except (TypeError, ValueError):  # arrays numpy cannot check together: each corridor on its own
        return set()
    return {id(c) for c, good in zip(corridors, clean) if good}


def _corridor_ok(corridor, track_id: int, issues: list[Issue], centreline_checked: bool = False) -> bool:
    """Whether the pair's corridor can be predicted on (else one issue); ``centreline_checked``: its arrays passed
    ``_clean_centrelines`` (only the vehicle's arc length is left to check)."""
    if centreline_checked:
        if not math.isfinite(corridor.vehicle_s_m):
            issues.append(Issue("nan_state", track_id, f"corridor {corridor.corridor_id}: vehicle_s_m {corridor.vehicle_s_m}"))
            return False
        return True
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

