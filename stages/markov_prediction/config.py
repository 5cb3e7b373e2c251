"""``MarkovPredictionConfig``: every parameter of the markov_prediction stage, with units and defaults."""

from __future__ import annotations

import math

from stages.lib.grid_fusion import parse_shard

from dataclasses import dataclass

from stages.lib.base import ConfigMixin, check_ranges
from stages.lib.markov.grid import DEFAULT_INPUT_MAX_MPS2, DEFAULT_INPUT_MIN_MPS2, DEFAULT_N_INPUTS, uniform_input_edges

#: ``hybrid``: AR-Net acceleration distributions replace λ (docs/method.md §8); ``baseline``: rule-based λ (§4).
MODES = ("hybrid", "baseline", "cv", "corridor_cv")
#: Modes that run the Markov chain (the others are closed-form constant-velocity predictions).
CHAIN_MODES = ("hybrid", "baseline")
#: ``intentions``: P(R = c) from the DBN's IntentionBelief; ``uniform``: 1/C over a vehicle's corridors.
CORRIDOR_WEIGHTS = ("intentions", "uniform")
#: Centre and half-widths of the initial (s, v) box: the measurement ± the §3.4 defaults, or the particles of the DBN;
#: ``auto`` (the default): the mode's own, ``MODE_INITIAL_BOX``.
INITIAL_BOXES = ("auto", "measurement", "particles")
#: ``initial_box = "auto"`` per mode. Chosen on K729 (the K733-trained AR model; in-sample for the choice), reported on
#: K733 (docs/evaluation.md "Initial box per mode"): the measured start speed helped hybrid (mADE 1.73 -> 1.68) and corridor_cv
#: (2.01 -> 1.86), the particles' box the baseline (1.61 with the measurement vs 1.63, but worse on fast cars of K733)
MODE_INITIAL_BOX = {"hybrid": "measurement", "corridor_cv": "measurement", "baseline": "particles", "cv": "measurement"}
#: Γ in hybrid mode: colnorm(diag(λ_AR(k)) Ψ) (docs/method.md §8.5), or the memoryless ``direct`` ablation λ_AR(k)·1ᵀ.
HYBRID_INPUTS = ("psi", "direct")
#: a moving pair's input at t0 in hybrid mode (``hybrid_initial_input``)
HYBRID_INITIAL_INPUTS = ("ar", "measured", "blend", "adaptive")
#: the chain's backend: ``numpy`` (numba kernels on the CPU), ``torch`` (on ``device``), or ``cuda``: numpy for every
#: chain but the hybrid mode's, whose whole run per frame is one CUDA kernel launch on ``device`` ("cuda", "cuda:N";
#: ``stages.lib.markov.cuda_chain``, numba.cuda: needs an NVIDIA GPU, the stage stops at start with a clear error
#: otherwise)
BACKENDS = ("numpy", "torch", "cuda")
GRID_DISTRIBUTIONS = ("interval", "point")
#: how a spread (table, online) widens the grids: ``isotropic`` blurs each vehicle's map grid with a round Gaussian
#: (``spread.blur_grid``); ``along`` blurs each pair's s-distribution along its corridor before it is rasterised
#: (``spread.blur_along``): the error of moving cars is mostly along the track, and the mass stays on the road;
#: ``auto`` (the default): the mode's own, ``MODE_SPREAD_SHAPE``
SPREAD_SHAPES = ("auto", "isotropic", "along")
#: ``spread_shape = "auto"`` per mode: along the map corridors; round for cv, whose "corridor" is a straight ray (a
#: turning car leaves it sideways: along it, its fast cars' coverage90 stayed at 0.75-0.85, docs/evaluation.md "Along the corridor")
MODE_SPREAD_SHAPE = {"hybrid": "along", "baseline": "along", "corridor_cv": "along", "cv": "isotropic"}
#: the parameters of raw grids, without the calibrated spread that is on by default (``launch.py --raw-grids``;
#: ``bench/generalisation.py`` without ``--calibrate``): the chain's own distributions rasterised, over-confident for
#: moving cars (docs/evaluation.md "Calibrated grids")
RAW_GRIDS = {"spread_calibration": "", "spread_online": False}
#: ``spread_online_max_mps = 0`` resolves to this per shape. isotropic 1.5 (fixed before any run, session 13); along
#: 3.0: with 1.5 its c sat at the cap and K733's fast cars' coverage90 stayed at 0.83 (docs/evaluation.md "Along the corridor";
#: chosen after seeing both locations)
SPREAD_ONLINE_MAX_MPS = {"isotropic": 1.5, "along": 3.0}

#: docs/method.md §4.1 "our 10-cell free-driving preference" over [-3, 2] m/s² in 0.5 m/s² cells. On other input
#: cells the default is carried over by acceleration (``priority.preference_on_cells``); a preference set by hand must
#: have one value per input cell.
DEFAULT_PREFERENCE = (0.005, 0.01, 0.02, 0.04, 0.10, 0.25, 0.30, 0.15, 0.08, 0.04)


@dataclass(frozen=True, kw_only=True)
class MarkovPredictionConfig(ConfigMixin):
    """Parameters of the markov_prediction stage (package docstring; docs/method.md §2–4, §9)."""

    mode: str = "baseline"
    backend: str = "numpy"
    device: str = "cpu"
    # threads of the hybrid chain's one compiled call per frame (kernels.speed_priority_run, numpy backend): its blocks
    # of 8 pairs are shared out between them; and of the vehicle grids' compiled call (frame_kernels.footprint_grids, every
    # mode): its vehicles. 1: all on the stage's own thread. The numbers do not depend on it
    kernel_threads: int = 2
    corridor_weights: str = "intentions"
    initial_box: str = "auto"  # "auto": MODE_INITIAL_BOX[mode]; after construction always the box in use
    # hybrid mode (docs/method.md §8.5): how the AR distributions enter the chain
    hybrid_input: str = "psi"
    hybrid_speed_restriction: bool = True
    # hybrid mode, with hybrid_speed_restriction: false cuts λ_AR(k) by the speed limit only (curvature taken as 0:
    # the AR model reads the curvature ahead itself). An experiment, off: with hybrid_initial_input "measured", chosen
    # on K729 (K733-trained GRU) hybrid mADE 1.507 -> 1.305, fast 3.26 -> 2.41; held out on K733 3.05 -> 3.60,
    # fast 4.83 -> 5.92 (README "Why hybrid loses to the baseline on fast cars"); alone on K729 1.507 -> 1.468
    hybrid_speed_restriction_curves: bool = True
    # hybrid mode, with hybrid_speed_restriction: two or more factors f of the curvature in the cut (√(a_lat / (f·κ)); 1 the
    # baseline's rule, 0 the limit alone), chosen online by back testing on the recording (curve_choice.py: 1 until another
    # is better by 3 standard errors). Held out, seed 0 (docs/evaluation.md "Online curve factor"): K729 (K733-trained model) chooses 0,
    # mADE 1.385 -> 1.354, fast 2.66 -> 2.47; K733 keeps 1 (outputs as before). () = the fixed rule of
    # hybrid_speed_restriction_curves
    hybrid_curve_factors: tuple[float, ...] = (0.0, 1.0, 2.0)
    # hybrid mode: two or more shifts (m/s², any sign) added to the acceleration of every AR input distribution of a
    # moving pair, chosen online by back testing as the curve factors are (curve_choice.OnlineShiftChoice: 0 until
    # another is better by 3 standard errors). Off (()): with (0, 0.25, 0.5), set from K729's along-track bias, it kept
    # 0 on both locations (K729 t = -1.4, K733 +0.1 for 0.25: docs/evaluation.md "Online acceleration shift"), so it only cost a
    # back-test chain per tested frame
    hybrid_accel_shifts: tuple[float, ...] = ()
    # hybrid mode: two or more leads L (s, >= 0): a moving pair's chain starts at the speed v0 + L·a, a the corridors
    # stage's estimated acceleration of the car (its speed a moment ahead: the estimate lags, and a car that accelerates
    # goes on for a while), chosen online by back testing as the curve factors are (curve_choice.OnlineLeadChoice: 0
    # until another is better by 3 standard errors); () = off. Held out, seed 0 (docs/evaluation.md "Online speed lead"):
    # K729 (K733-trained model) chooses 0.4 s, mADE 1.366 -> 1.250; K733 keeps 0 (outputs as before)
    hybrid_speed_leads_s: tuple[float, ...] = (0.0, 0.2, 0.4, 0.8)
    # hybrid mode: the AR profiles the chain reads. "frame": the frame's own (the chain waits for them); "previous":
    # the last ones received before the frame, at most hybrid_previous_max_age_s older (a pair without one holds its
    # measured acceleration), so the chain runs as soon as the relation set is in, beside intentions and ar_inference,
    # off the frame's critical path; iamp eval then runs the AR stage at every frame. Held out +1.3-2.5 % mADE (new pairs);
    # on 2 cores the MotionGrid came 1-2 ms sooner, inside the noise (docs/performance.md "Pipelined AR profiles");
    # "inline": see ar_model below
    hybrid_profiles: str = "frame"
    hybrid_previous_max_age_s: float = 0.25
    # "inline": the stage runs the AR model itself (stages.ar_inference's core, weights ``ar_model``) on the frame's corridor
    # set, relation set and track frame whenever its input set holds no acceleration_profiles: the same profiles as the
    # ar_inference stage's, one process and one bus hop fewer on the frame's path (pipelines/inline.toml: on 2 cores the
    # MotionGrid 1-4 ms sooner at p50, 2-5 at p95, docs/performance.md "Session 34"); it publishes them as its acceleration_profiles
    ar_model: str = ""
    # true: the AR distribution λ_AR(k) is the preference inside the baseline's full rule set (speed, leader,
    # crossing: λ = cut(min(λ_speed, λ_lead, λ_conf), λ_AR(k))) instead of the speed cut alone
    hybrid_rules: bool = False
    # with hybrid_rules: "rules" gives a standing vehicle the rules' own preference and its measured input, "ar" λ_AR too
    hybrid_rules_standing: str = "ar"
    # hybrid mode: the input at t0 of a moving pair (not in the standstill band): "ar" λ_AR(0), or "measured" the
    # normal around its measured acceleration, as the baseline starts (the later steps follow λ_AR(k) through Ψ).
    # An experiment, off: alone on K729 1.507 -> 1.326 (fast 3.26 -> 2.53); with the curves switch above it did not
    # carry over to K733 (README "Why hybrid loses to the baseline on fast cars"). "blend": a normal of the model's
    # spread at the precision-weighted mean of λ_AR(0) and the measured acceleration (weights 1/σ², σ_a the slope's
    # standard error; modes/hybrid.py blend_initial). Off: K729 1.507 -> 1.303 (fast 3.26 -> 2.51), held out on K733
    # 3.051 -> 3.085 (fast 4.83 -> 4.88), cov90/NLL no better (README). "adaptive" (the default): the model's mean
    # moved by w times the measured acceleration's difference from it, w learnt online on the recording from what the
    # cars then did (initial_blend.py; w = 0, the "ar" input, until 50 records are resolved). Held out, seeds 0-2: K733
    # learns w = 0 (mADE as "ar"), K729 w = 0.6 (mADE 1.55 -> 1.38 m; docs/evaluation.md "Online initial blend")
    hybrid_initial_input: str = "adaptive"
    # discretisation (the stencils are cached per ds, dv, v_max, τ)
    ds_m: float = 1.0
    dv_mps: float = 0.5
    v_max_mps: float = 20.0
    tau_s: float = 0.4
    n_steps: int = 10
    # input (acceleration) cells: n_inputs equal cells on [input_min, input_max] m/s² (defaults: stages.lib.markov.grid,
    # the one source that ar_inference's defaults read too; its profiles must be over the same cells, else bad_profile)
    input_min_mps2: float = DEFAULT_INPUT_MIN_MPS2
    input_max_mps2: float = DEFAULT_INPUT_MAX_MPS2
    n_inputs: int = DEFAULT_N_INPUTS
    window_cells: int = 100
    window_behind_m: float = 3.0
    # entries of p⁻ below this are dropped each step (their mass put back on the rest). 1e-6 (was 1e-7): the hybrid
    # chain's compiled call 20 % faster at 18 vehicles (bench/dense.py); held out, seed 0, hybrid alone without the
    # spread table: mADE equal to 4 decimals both ways, NLL +0.0004 (K729) / +0.003 (K733); 1e-5 NLL +0.002 / +0.018
    prune_threshold: float = 1e-6
    stencil_cache_dir: str = ""
    # initial distribution (§3.4)
    init_sigma_s_m: float = 0.25
    init_sigma_v_mps: float = 0.25
    init_sigma_a_mps2: float = 0.5
    accel_window_s: float = 1.0
    standstill_speed_mps: float = 0.5
    standstill_start_rate_hz: float = 0.055
    # hybrid mode: a standing vehicle's start rate from the scene (README "Standing vehicles"), per group of its corridor's
    # leader: (no leader within standstill_leader_gap_m, a standing leader, a leader faster than standstill_leader_moving_mps);
    # () = standstill_start_rate_hz for every standing vehicle. Default chosen on K729 (README "Standing vehicles"): it stays
    # unless its leader pulls away (K729: 100 % of those start within 4 s, 15 % behind a standing leader, 25 % with none)
    # the fourth rate: a standing vehicle inside an intersection or less than standstill_intersection_m before its entry,
    # without a leader that pulls away (it waits for a gap, not in a queue; K729: 60 of 61 such windows start within 4 s,
    # 13 % of those 10-20 m before the entry). Chosen on K729 with the K733-trained model: hybrid mADE 1.68 -> 1.60
    # (0.3 /s 1.61, 0.5 /s 1.60, 1.0 /s 1.60, the maximum-likelihood rate; 8 m and 12 m the same)
    hybrid_standstill_rates_hz: tuple[float, ...] = (0.0, 0.0, 1.7, 1.0)
    standstill_intersection_m: float = 8.0
    # hybrid mode: > 0: the part of a standing vehicle's mixture that starts accelerates at this rate (a normal of σ
    # hybrid_start_sigma_mps2 over the input cells, every step) instead of the AR distributions (which, for standing
    # cars, do not tell starting from staying); 0: the AR distributions. Measured on K729 (rates above): 1.5 m/s² gives
    # the same mADE (1.61 with the fourth rate 0.3 /s: accelerating cars better, cars that keep a low speed worse): off
    hybrid_start_accel_mps2: float = 0.0
    hybrid_start_sigma_mps2: float = 0.5
    # hybrid mode: a moving pair's λ_AR(k) mixed with a braking input by the intentions stage's P(stop | corridor):
    # (1 − P)·λ_AR(k) + P·N(−a, hybrid_start_sigma_mps2), a = v0² / (2 d) to stop within the distance d to the stop
    # position (or behind the leader, hybrid_stop_gap_m short of it), clipped to [0.5, 3] m/s². An experiment, off: on
    # K729 (K733-trained model, where it was chosen) hybrid mADE 1.60 -> 1.43, on the held-out K733 2.86 -> 3.07 (README)
    hybrid_stop_mixture: bool = False
    hybrid_stop_gap_m: float = 2.0
    # a leader further than this counts as none for a standing vehicle's start rate (hybrid). 15 m: every standing car
    # that K729 shows behind a leader that pulls away had it within 15 m (16 of 16; 15 within 10 m), so beyond that the
    # rule had no data; K729's hybrid is the same with 25 (the value before) and 15. Chosen after looking at K733's
    # windows, where cars waiting at a red light saw a leader 15-21 m ahead drive off and were predicted to follow
    # (docs/evaluation.md "Leader gap of a standing car"): K733's gain from it is informed, not held out
    standstill_leader_gap_m: float = 15.0
    standstill_leader_moving_mps: float = 1.0
    track_timeout_s: float = 2.0
    # Γ = colnorm(diag(λ) Ψ) (§4.1)
    psi_gamma: float = 0.2
    free_driving_preference: tuple[float, ...] = DEFAULT_PREFERENCE
    forbid_threshold: float = 1e-3
    # speed limit and curvature (§4.2)
    lat_accels_mps2: tuple[float, ...] = (3.0, 2.5, 2.0, 1.5)
    lat_accel_weights: tuple[float, ...] = (0.1, 0.2, 0.4, 0.3)
    lookahead_brake_mps2: float = 2.5
    speed_limit_factor: float = 1.0
    default_speed_limit_mps: float = 13.89
    curvature_smoothing_m: float = 3.0
    # leader (§4.3)
    leader_horizons_s: tuple[float, ...] = (0.4, 1.6, 3.2)
    leader_brake_mps2: float = 6.0
    leader_epsilon: float = 1e-4
    leader_horizon_mean: str = "arithmetic"
    static_leader_spread_m: float = 1.0
    # influencing corridor (§4.4)
    conflict_margin_s: float = 1.0
    conflict_epsilon: float = 1e-4
    # constant-velocity baselines
    cv_accel_sigma_mps2: float = 1.0
    # motion grid (§9): 1 m cells, the chain's own resolution along the corridor (ds_m); 0.5 m cells hold the same
    # mass in four times the cells (docs/method.md §9)
    grid_cell_m: float = 1.0
    grid_lateral_sigma_m: float = 0.4
    # samples along each s-cell's footprint; 0 (default): one every half grid cell, max(1, ⌈2·ds_m / grid_cell_m⌉)
    # (4 on 0.5 m cells, 2 on 1 m ones), as the lateral offsets are; resolved at construction
    grid_substeps: int = 0
    grid_extent_m: tuple[float, ...] = ()
    grid_margin_m: float = 3.0
    grid_min_value: float = 1e-5
    grid_distribution: str = "interval"
    lateral_offset_decay_s: float = 1e6
    # calibrated spread (README "Calibrated grids"): a JSON file written by ``iamp calibrate`` with, per mode, the
    # Gaussian σ (m) along the corridor that widens each pair's s-distribution at each step, per start-speed band,
    # for the grids only (the mean positions stay as they are); "" = none (raw grids: over-confident for moving
    # cars); "shipped" (default) = the shipped AR model's table for the shape, stages/lib/ar/weights/spread_taf_bw_along.json
    # or spread_taf_bw.json (fitted on all of TAF-BW; with weights of your own, fit yours with ``iamp calibrate``)
    spread_calibration: str = "shipped"
    # online spread (docs/evaluation.md "Online spread", online_spread.py): the grids of each start-speed band widened at each step
    # until their ``spread_online_target`` region holds the vehicles' later positions in that share of the checks
    # (the extra σ grows by c·t, c in [0, spread_online_max_mps] moved by spread_online_rate_mps per check); on top of
    # the spread table, if any; only for vehicles starting faster than spread_online_min_speed_mps. On by default
    # (it carries a table to a location it was not fitted on); false: the table alone
    spread_online: bool = True
    spread_online_min_speed_mps: float = 2.0
    spread_online_target: float = 0.9
    spread_online_rate_mps: float = 0.05
    # 0 (default): the shape's own cap, SPREAD_ONLINE_MAX_MPS (1.5 isotropic: its blur's cells grow with σ²; 3.0 along)
    spread_online_max_mps: float = 0.0
    # the shape of the spread (table and online): "isotropic" (a round Gaussian on the map grid) or "along" (a Gaussian
    # along each corridor, before rasterising, and the lateral kernel widened per step; fewer cells); "auto": the mode's
    # own (MODE_SPREAD_SHAPE: along, cv isotropic). After construction always the shape in use. ``iamp calibrate`` fits
    # a table for the shape it runs with (the file says which)
    spread_shape: str = "auto"
    # with spread_shape "along": what the blur carries behind a vehicle's position now is folded ahead of it (mirrored
    # about its cell; the chain's own mass there stays): a car is not predicted behind where it is. false: the blur
    # is symmetric (tables fitted before 2026-12-06)
    spread_fold_start: bool = True
    # with spread_shape "along": the grids widened across the corridor too, step k of a pair by
    # σ_lat = min(√(grid_lateral_sigma_m² + (ratio·σ_k)²), max) (σ_k the along σ): lane offsets grow with the horizon
    spread_lateral_ratio: float = 0.33
    spread_lateral_max_m: float = 1.5
    # issues
    outside_issue_mass: float = 0.01
    # bounded work per message (issue 13): pairs per frame (whole vehicles beyond, in CorridorSet order, skipped)
    max_pairs: int = 600
    # MotionGrid cells listed per step, the highest kept (12 B each: 10 steps of 100,000 is 12 MB, under its 16 MiB MAX_BYTES)
    grid_max_cells_per_step: int = 100_000
    # "i/n": predict only the vehicles whose id hashes to shard i of n (stages.lib.grid_fusion.shard_of, CRC-32);
    # stages.grid_fusion merges the shards' outputs. "" (default): every vehicle
    shard: str = ""

    def __post_init__(self) -> None:
        parse_shard(self.shard)  # raises with a message saying what to write
        if self.mode not in MODES:
            raise ValueError(f"mode = {self.mode!r}: expected one of {', '.join(MODES)}")
        if self.corridor_weights not in CORRIDOR_WEIGHTS:
            raise ValueError(f"corridor_weights = {self.corridor_weights!r}: expected one of {', '.join(CORRIDOR_WEIGHTS)}")
        if self.initial_box not in INITIAL_BOXES:
            raise ValueError(f"initial_box = {self.initial_box!r}: expected one of {', '.join(INITIAL_BOXES)}")
        if self.initial_box == "auto":  # resolved here so that every reader sees the box in use
            object.__setattr__(self, "initial_box", MODE_INITIAL_BOX[self.mode])
        if self.hybrid_rules_standing not in ("ar", "rules"):
            raise ValueError(f"hybrid_rules_standing = {self.hybrid_rules_standing!r}: expected ar or rules")
        if self.hybrid_curve_factors and (len(self.hybrid_curve_factors) < 2 or any(not (isinstance(f, (int, float)) and math.isfinite(f) and f >= 0)
                                                                                   for f in self.hybrid_curve_factors)):
            raise ValueError(f"hybrid_curve_factors = {self.hybrid_curve_factors!r}: expected () or two or more finite factors >= 0")
        if self.hybrid_accel_shifts and (len(self.hybrid_accel_shifts) < 2 or any(not (isinstance(f, (int, float)) and not isinstance(f, bool)
                                                                                      and math.isfinite(f)) for f in self.hybrid_accel_shifts)):
            raise ValueError(f"hybrid_accel_shifts = {self.hybrid_accel_shifts!r}: expected () or two or more finite shifts in m/s²")
        if self.hybrid_speed_leads_s and (len(self.hybrid_speed_leads_s) < 2 or any(not (isinstance(f, (int, float)) and not isinstance(f, bool)
                                                                                        and math.isfinite(f) and f >= 0) for f in self.hybrid_speed_leads_s)):
            raise ValueError(f"hybrid_speed_leads_s = {self.hybrid_speed_leads_s!r}: expected () or two or more finite leads in s, >= 0")
        if self.hybrid_profiles not in ("frame", "previous", "inline"):
            raise ValueError(f"hybrid_profiles = {self.hybrid_profiles!r}: expected frame, previous or inline")
        if self.ar_model and self.hybrid_profiles != "inline":
            raise ValueError(f"ar_model = {self.ar_model!r} is read with hybrid_profiles = \"inline\" only (now {self.hybrid_profiles!r}): "
                             "set both, or give the weights to the ar_inference stage (its model)")
        if not (isinstance(self.hybrid_previous_max_age_s, (int, float)) and math.isfinite(self.hybrid_previous_max_age_s)
                and self.hybrid_previous_max_age_s > 0):
            raise ValueError(f"hybrid_previous_max_age_s = {self.hybrid_previous_max_age_s!r}: expected a finite number of seconds > 0")
        if self.hybrid_initial_input not in HYBRID_INITIAL_INPUTS:
            raise ValueError(f"hybrid_initial_input = {self.hybrid_initial_input!r}: expected one of {', '.join(HYBRID_INITIAL_INPUTS)}")
        if self.hybrid_input not in HYBRID_INPUTS:
            raise ValueError(f"hybrid_input = {self.hybrid_input!r}: expected one of {', '.join(HYBRID_INPUTS)}")
        if self.backend not in BACKENDS:
            raise ValueError(f"backend = {self.backend!r}: expected one of {', '.join(BACKENDS)}")
        if self.backend == "numpy" and self.device != "cpu":
            raise ValueError(f"device = {self.device!r}: the numpy backend runs on cpu only (use backend = 'torch' or 'cuda')")
        if self.backend == "cuda":
            if self.device == "cpu":  # resolved here: the cuda backend's chain runs on the first GPU unless told otherwise
                object.__setattr__(self, "device", "cuda")
            head, _, tail = self.device.partition(":")
            if head != "cuda" or (self.device != "cuda" and not tail.isdigit()):
                raise ValueError(f"device = {self.device!r}: the cuda backend needs 'cuda' or 'cuda:N'")
        if self.leader_horizon_mean not in ("arithmetic", "geometric"):
            raise ValueError(f"leader_horizon_mean = {self.leader_horizon_mean!r}: expected 'arithmetic' or 'geometric'")
        if self.spread_shape not in SPREAD_SHAPES:
            raise ValueError(f"spread_shape = {self.spread_shape!r}: expected one of {', '.join(SPREAD_SHAPES)}")
        if self.spread_shape == "auto":  # resolved here so that every reader sees the shape in use
            object.__setattr__(self, "spread_shape", MODE_SPREAD_SHAPE[self.mode])
        if self.spread_online_max_mps == 0:  # resolved here so that every reader sees the cap in use
            object.__setattr__(self, "spread_online_max_mps", SPREAD_ONLINE_MAX_MPS[self.spread_shape])
        if self.grid_distribution not in GRID_DISTRIBUTIONS:
            raise ValueError(f"grid_distribution = {self.grid_distribution!r}: expected one of {', '.join(GRID_DISTRIBUTIONS)}")
        positive = (
            "ds_m", "dv_mps", "v_max_mps", "tau_s", "init_sigma_s_m", "init_sigma_v_mps", "init_sigma_a_mps2",
            "track_timeout_s", "psi_gamma", "lookahead_brake_mps2", "speed_limit_factor",
            "default_speed_limit_mps", "leader_brake_mps2", "static_leader_spread_m", "grid_cell_m",
            "grid_lateral_sigma_m", "cv_accel_sigma_mps2", "hybrid_start_sigma_mps2", "spread_online_rate_mps",
        )
        non_negative = (
            "window_behind_m", "accel_window_s", "prune_threshold", "standstill_speed_mps", "standstill_start_rate_hz", "forbid_threshold", "curvature_smoothing_m", "leader_epsilon",
            "conflict_margin_s", "conflict_epsilon", "standstill_leader_gap_m", "standstill_leader_moving_mps", "hybrid_start_accel_mps2", "spread_online_min_speed_mps", "spread_online_max_mps", "spread_lateral_ratio", "spread_lateral_max_m", "grid_margin_m", "lateral_offset_decay_s", "grid_min_value", "outside_issue_mass",
        )
        check_ranges(self, positive=positive, non_negative=non_negative)
        uniform_input_edges(self.input_min_mps2, self.input_max_mps2, self.n_inputs)  # ValueError on a bad range
        if self.kernel_threads < 1:
            raise ValueError(f"kernel_threads = {self.kernel_threads!r}: expected an integer >= 1 (1: the compiled chain on the"
                             " stage's own thread; 2 uses two cores)")
        if self.grid_substeps == 0:  # resolved here so that every reader sees the samples in use
            object.__setattr__(self, "grid_substeps", max(1, math.ceil(2.0 * self.ds_m / self.grid_cell_m - 1e-9)))
        for name in ("n_steps", "window_cells", "grid_substeps", "max_pairs", "grid_max_cells_per_step"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} = {getattr(self, name)!r}: must be >= 1")
        if self.hybrid_standstill_rates_hz and (len(self.hybrid_standstill_rates_hz) not in (3, 4) or any(not (r >= 0) for r in self.hybrid_standstill_rates_hz)):
            raise ValueError(f"hybrid_standstill_rates_hz = {self.hybrid_standstill_rates_hz!r}: expected () or three rates >= 0"
                             " (no leader, standing leader, moving leader) and optionally a fourth (at an intersection)")
        if len(self.lat_accels_mps2) != len(self.lat_accel_weights) or not self.lat_accels_mps2:
            raise ValueError("lat_accels_mps2 and lat_accel_weights must be non-empty and of equal length")
        if any(a <= 0 for a in self.lat_accels_mps2) or any(w < 0 for w in self.lat_accel_weights):
            raise ValueError("lat_accels_mps2 must be > 0 and lat_accel_weights >= 0")
        if not self.leader_horizons_s or any(h <= 0 for h in self.leader_horizons_s):
            raise ValueError(f"leader_horizons_s = {self.leader_horizons_s!r}: needs positive values")
        if not (0.0 < self.spread_online_target < 1.0):
            raise ValueError(f"spread_online_target = {self.spread_online_target!r}: must lie in (0, 1) (0.9: the 90 % region)")
        if self.grid_extent_m and (len(self.grid_extent_m) != 4 or self.grid_extent_m[2] <= self.grid_extent_m[0]
                                   or self.grid_extent_m[3] <= self.grid_extent_m[1]):
            raise ValueError(f"grid_extent_m = {self.grid_extent_m!r}: expected () (auto) or (x_min, y_min, x_max, y_max)")

    def input_cells(self) -> dict[str, float | int]:
        """The input cells as ar_inference's parameters (``input_min_mps2``, ``input_max_mps2``, ``n_inputs``): the AR
        stage that feeds this one must use these."""
        return {"input_min_mps2": self.input_min_mps2, "input_max_mps2": self.input_max_mps2, "n_inputs": self.n_inputs}
