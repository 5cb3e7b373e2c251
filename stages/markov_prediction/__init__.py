"""Markov prediction stage: rule-based Markov-chain motion prediction and the motion grid (docs/method.md §3.4, §4, §9).

Consumes ``corridor_set`` (``CorridorSet``) and ``relation_set``
(``RelationSet``) of the same stamp, the latched ``scene`` (``SceneInfo``) and,
optionally, ``track_frame`` (``TrackFrame``: vehicle sizes, and the velocity
of mode ``cv``), ``intention_belief`` (``IntentionBelief``: corridor weights
and particle boxes) and ``acceleration_profiles`` (``AccelerationProfiles``:
mode ``hybrid``), all of the same stamp; or, instead of the last, ``previous_profiles``
(the same messages as a latest value, outside the join: ``hybrid_profiles = "previous"``, whose chain reads the
profiles of the frame before and so runs before the frame's own come; ``launch.py pipelined``). With
``hybrid_profiles = "inline"`` the stage needs no profiles at all: where the set holds none, it runs the AR model
itself (the ar_inference stage's core, weights ``ar_model``) on the frame's corridor set, relation set and track
frame, once per frame, and publishes what it got as ``acceleration_profiles`` (``launch.py inline``: no
ar_inference stage, the same outputs byte for byte, one process and one bus hop fewer on each frame's path).
Produces ``motion_grid`` (``MotionGrid``) and ``corridor_predictions`` (``CorridorPredictions``), put in this order,
for every frame. Run it alone with ``python -m stages.markov_prediction``.

On the bus the work starts before the last input: the runtime offers the
core each incomplete set (``MarkovPredictor.prepare``; README, "Work before
the last input"). Where the chain does not read the intentions stage's
belief (``chain_reads_belief``: every mode but the baseline's particle boxes
and hybrid's stop mixture) the pairs are built once the corridor set and the
track frame are in (``_pairs_phase``), the chain and the weight-free part of
the outputs run once everything but the belief is in (``_chain_phase``), and
the belief leaves the corridor weights, the grids and the messages
(``_belief_phase``): the outputs of one ``update``, byte for byte.

Modes (``mode``), one ``InputModel`` each in ``modes/`` (the contract the
chain loop of ``core.py`` calls: ``modes/base.py``):

- ``hybrid``: the same chain with the AR model's distributions in place of
  the rule-based λ (docs/method.md §8.5): λ(0) of the pair's
  ``AccelerationProfile`` is the initial input distribution, and after step
  k the input transition is Γ_k = colnorm(diag(λ(k+1)) Ψ), one M × M matrix
  per pair (``hybrid_input`` "psi"), or λ(k+1)·1ᵀ (``hybrid_input``
  "direct", the memoryless ablation); saturation kept, the standstill
  mixture as in the baseline. ``hybrid_speed_restriction`` (default on,
  ours; docs/method.md §8.5 suggested off because the net sees the curvature):
  λ(k+1), scaled to a largest entry of 1, is the preference that the
  baseline's λ_speed (§4.2) cuts per state, CORA's combination, so Γ is
  per state. It lowers mADE leave-one-location-out on both locations, also
  with a model that always predicts 0: the AR model trained on so little
  data does not learn the slowing for curves (measured: docs/method.md
  §8.5). No leader or crossing restriction (the model saw those
  features). A pair without a usable profile (missing, wrong input
  cells, other stamp) holds a normal distribution around its measured
  acceleration (issue ``no_acceleration_profile(s)``/``bad_profile``);
- ``baseline``: the Markov chain of docs/method.md §3.4 with the rule-based
  priority vector λ of §4; all vehicle-corridor pairs of a frame propagate
  together, one batch per step (``backend`` "numpy" = scipy CSR, or
  "torch" on ``device`` "cpu"/"cuda"; "cuda": the numpy backend, with the
  hybrid mode's whole run per frame as one numba.cuda kernel on ``device``
  "cuda"/"cuda:N", ``stages.lib.markov.cuda_chain``);
- ``cv``: Cartesian constant velocity, one straight line per vehicle along its
  velocity (``corridor_id`` -1);
- ``corridor_cv``: constant speed along each corridor.
Every mode produces the same structures (s- and v-distributions per step,
mean positions, outside mass, grid), so comparisons share one code path.

Corridor weights (``corridor_weights``): ``uniform`` (1/C over the vehicle's
corridors) or ``intentions``: P(R = c) of the intentions stage's belief,
renormalised over the corridors predicted (uniform, with an issue
``no_intentions``/``no_belief``, when the belief is missing, of another
stamp or misses a corridor). ``initial_box`` ``particles`` takes the
initial box from the belief instead of the measurement (``auto``, the
default: ``measurement`` for hybrid and corridor_cv, ``particles`` for the
baseline, ``config.MODE_INITIAL_BOX``): centred on the
particles' mean s and v on that corridor, half-widths max(Δs/2, 2σ_s) and
max(Δv/2, 2σ_v) of the particles.

Initial distribution (§3.4). Per pair, a uniform box in (s, v) around the
vehicle's arc length on the corridor and its speed, ±max(Δs/2, 2σ_s) and
±max(Δv/2, 2σ_v) (``init_sigma_s_m`` 0.25, ``init_sigma_v_mps`` 0.25), times
a Gaussian input distribution around the measured acceleration: the
least-squares slope of the vehicle's speed over the last ``accel_window_s``
1 s of frames (0 with less history or with ``accel_window_s`` 0), shrunk
towards 0 by its standard error σ (slope·max(0, 1 − σ²/slope²); the K733
tracker's speeds jitter by ±3 m/s from frame to frame), with spread
√(``init_sigma_a_mps2``² + min(σ, 1)²). The window of ``window_cells`` 100
s-cells of ``ds_m`` 1 m starts ``window_behind_m`` 3 m behind the vehicle.

Standstill (ours, after CORA's standstill location). A cell-based chain
cannot hold a vehicle at v = 0: v-cell 0 is [0, 0.5] m/s and its mass is
re-spread over it every step, so a standing car creeps even under braking
inputs, and the preference q starts it (docs/method.md §3.6). A vehicle at or below
``standstill_speed_mps`` 0.5 is therefore predicted as the mixture
P_stay(t)·(its start box, v = 0) + (1 − P_stay(t))·chain, P_stay(t) =
exp(−``standstill_start_rate_hz``·t); 0.055 /s gives P(start within 4 s) =
0.2, what TAF-BW's standing cars show (measured: docs/method.md §3.6).
Followers see a standing leader through the same mixture. In hybrid mode the
rate comes from the scene (``hybrid_standstill_rates_hz``, per leader on the
corridor: none within ``standstill_leader_gap_m``, standing, faster than
``standstill_leader_moving_mps``; a fourth rate for a car standing inside
an intersection or less than ``standstill_intersection_m`` before its entry;
default 0, 0, 1.7, 1.0 /s: a car stays unless its leader pulls away or it
waits at the intersection for a gap). A rate of 0 is kept at 1e-9 /s, whose
P_stay is exactly 1 in float32 at every step: the chain of such a pair is
weighed by exactly 0, so the compiled chain call leaves it out
(``kernels.speed_priority_run(skip=...)``; the same outputs, byte for byte).

Calibrated spread (``spread_calibration``, default "shipped": the table the
shipped AR model was fitted with on TAF-BW; "" for raw grids, which are
over-confident for moving cars): a file written by ``iamp calibrate`` gives,
per mode, start-speed band and step, the σ of a Gaussian that blurs each
vehicle's grid before fusion, along its corridors (``spread_shape`` "along",
the corridor modes; the lateral kernel widened with it) or round (cv)
(``spread.py``; the corridor distributions and means do not change), widened
per vehicle by its own speed noise when the file has a ``speed_noise_gain``.
Online spread (``spread_online``, on by default; ``online_spread.py``): the
grids of vehicles starting faster than ``spread_online_min_speed_mps`` are
widened further, by c·t per step, c per start-speed band learnt as the
vehicles move on (each kept grid checked against the vehicle's later
positions, c up on a miss of the ``spread_online_target`` region, down on a
hit), so that the region holds the truth at the target rate on a location no
table was fitted on.

Lateral offset. Means and grids are placed at the vehicle's lateral offset
from the centreline, d(t) = d0·exp(−t/``lateral_offset_decay_s``); the
default 1e6 s keeps d0 (on TAF-BW, keeping it beat decaying it with 2 s and
the bare centreline; docs/method.md §3.6).

Priority vector λ (baseline). At every step, for every state (s, v) and
input α of every pair: m = min(λ_speed, λ_lead, λ_conf), then CORA's
combination with the free-driving preference q (``free_driving_preference``,
docs/method.md §4.1's 10-cell vector, scaled to a largest entry of 1 so that a
restriction below 1 cuts it; with q summing to 1 only restrictions below
0.3 would act): from the highest input down r_α = min(m_α, q_α + carry),
the cut carried to the next lower input; where every m_α ≤
``forbid_threshold`` only the strongest braking input is kept. Γ_i =
colnorm(diag(r_i) Ψ) (Ψ with γ = ``psi_gamma`` 0.2) is applied without being
built (``chain.InputPriority``).

- λ_speed (§4.2): v_prof(s) = min(v_limit, √(a_lat/|κ(s)|)) with κ smoothed
  over ``curvature_smoothing_m``, v_limit the corridor's (else the scene's)
  limit × ``speed_limit_factor``; a braking look-ahead v_adm(s) = min over s'
  ≥ s of √(v_prof(s')² + 2b(s' − s)) (``lookahead_brake_mps2`` 2.5); an input
  is allowed under one profile when v + aτ ≤ v_adm(s + vτ); the four a_lat
  of ``lat_accels_mps2`` are mixed with ``lat_accel_weights``.
- λ_lead (§4.3, critical-gap form, never a dense Θ): g*(Δt, v_F, α_F, v_L,
  α_L) is tabulated once (both hold their inputs for Δt ∈
  ``leader_horizons_s``, then both brake at ``leader_brake_mps2`` 6 m/s²; the
  gap must stay positive). λ_lead = mean over Δt of P(leader displacement ≥
  s_F − s_F0 − gap0 + g*) + ε·(1 − P) (``leader_horizon_mean`` "geometric"
  takes the geometric mean over Δt instead; on TAF-BW it did not help), with
  the leader's displacement
  distribution at the same step taken from its own pairs in the batch
  (averaged over its corridors) and its speed and input through their means;
  a leader without pairs (pedestrian, unmatched vehicle) moves at its
  relation speed, ±``static_leader_spread_m``.
- λ_conf (§4.4, occupancy windows): for the pair's influencing corridor, the
  conflict zone s* ± (L + w_other)/2 on both corridors; for every state and
  held input the time window in the zone, widened by ``conflict_margin_s``,
  gives q = the maximum over the overlapping steps of the other vehicle's
  probability to occupy its zone (from its interval distributions) and λ =
  ε^q (log-linear between free and taken: the linear 1 − q barely moves the
  chain, whose Ψ keeps the current input with 0.67 per step). States in or
  past the zone, or that cannot stop before it with the strongest braking
  input, are committed and not restricted. Because the
  window looks into the future, the batch runs twice when a frame has an
  influencing corridor: first with λ_speed and λ_lead for every pair, then
  again for the restricted pairs and (transitively) their followers, with
  the other vehicles' occupancies from the first pass.

Outputs (§9). Per pair the time-point s- and v-marginals at t_k = k·τ (k =
1..K), the outside mass (past the window or the corridor's end, never
renormalised), the probability-weighted mean of centreline points and
X_c(E[s]) (both moved by the lateral offset). Constant-velocity modes report the exact s0 + v0·t instead of
the cell average, and spread it with σ_s(t) = √(σ0² + (½·σ_a·t²)²) along
the line (``cv_accel_sigma_mps2`` 1) for the grid. The motion grid
rasterises each pair's ``grid_distribution`` ("interval": occupancy during
the step, Υ([0, τ]); "point": position at t_k) along the centreline with
``grid_substeps`` samples per s-cell (default: one every half grid cell) and
a lateral Gaussian of ``grid_lateral_sigma_m`` 0.4 (sampled every half cell),
weights corridors by their probability
(uniform over a vehicle's corridors), combines vehicles as 1 − Π(1 − G_n)
and keeps cells above ``grid_min_value`` 1e-5 on a ``grid_cell_m`` 1.0 grid
whose extent is ``grid_extent_m`` (x_min, y_min, x_max, y_max) or, when
empty, the occupied cells plus ``grid_margin_m``.

Sharding: ``shard`` "i/n" (default "": all vehicles) predicts only the
vehicles whose id hashes to shard i of n (CRC-32 of the decimal id,
``stages.lib.grid_fusion.shard_of``); the others are left out without
issues, and ``stages.grid_fusion`` merges the shards' outputs. A leader or
crossing vehicle of another shard is seen only through its relation.

Threads: ``kernel_threads`` (default 2, an integer >= 1) threads share out
the blocks of 8 pairs of the hybrid chain's one compiled call per frame
(numpy backend with numba, ``kernels.speed_priority_run``; each thread takes
the next block when it is free); 1 runs them all on the stage's thread. The
numbers do not depend on it (tests/stages/test_markov_kernel_threads.py).
With several shards or other busy stages on the same cores, 1 may suit better.

Bounded work: ``max_pairs`` 600 vehicle-corridor pairs per frame (issue
13): beyond it whole vehicles are kept in CorridorSet order while their
corridors fit, the rest are not predicted this frame (``stages.lib.caps.cap_pairs``;
one ``pairs_capped`` issue). TAF-BW frames (at most ~20 vehicles, ~2
corridors each) never are. The grid is sparse (COO cells per step), so its
size follows the pairs kept, not the extent; the MotionGrid lists at most
``grid_max_cells_per_step`` 100,000 cells per step (the highest values;
12 MB for 10 steps, under its 16 MiB ``MAX_BYTES``; one ``grid_capped``
issue with the number left out; TAF-BW frames list up to ~5,000).

Issues (every other pair is still predicted): ``corridor_too_short`` (outside
mass at the horizon above ``outside_issue_mass`` 1 %, per pair),
``nan_state`` (non-finite speed or arc length: vehicle or pair skipped),
``bad_corridor`` (fewer than two points, non-finite or non-increasing
centreline), ``unknown_corridor`` (a relation for a pair that is not
predicted: ignored), ``nan_relation``/``bad_relation`` (a leader gap or
conflict point that is not finite, an index out of range: that restriction
ignored), ``stamp_mismatch`` (relations of another stamp: ignored),
``no_relations``.

Another scene or place. What the stage learns online (the curve factor, the acceleration shift, the speed lead,
the initial blend, the online spread) belongs to a location and its tracker: when the latched ``scene`` names
another location (``location_id``, else the map's hash) the stage starts it from nothing
(``MarkovPredictor.forget_location``, issue ``location_changed``), and another scene of the same location starts
every track afresh (``reset``, issue ``scene_changed``), as the corridors and intentions stages do.

One pair's failure never costs the frame (``core.MarkovPredictor._predict``).
Before the batch, a pair the chain cannot take is predicted by constant
speed along its corridor, the ``corridor_cv`` mode's prediction:
``pair_fallback_nan_input`` (a non-finite number the chain reads, e.g. the
curvature), ``pair_fallback_speed_above_vmax`` (measured speed above
``v_max_mps``: constant speed at the measured speed; the chain would clip
it), ``pair_fallback_box_outside_window`` (an initial box that misses its
window, which ``initial_state`` would raise for). A pair the batched chain
raises on is found by bisection and falls back the same way
(``pair_fallback_chain_failed``), the batch run again without it. With
``backend`` "cuda", a GPU run that raises is done again by the CPU kernel,
and every later run too (``gpu_chain_failed``, once: no pair is lost). A pair
whose fallback or outputs raise is not predicted (``pair_failed``), a
vehicle whose pairs cannot be built neither (``vehicle_failed``). The other
pairs' predictions are exactly what they are without the failing one
(unless they follow it). ``particle_box_rejected``: the particles' box does
not fit the window it gets (their mean about a window length from the
measured arc length, or as wide: a particle filter that lost the vehicle);
the measurement's box is used, so the window always holds the initial box.
"""

from __future__ import annotations

from stages.markov_prediction.config import MODES, RAW_GRIDS, MarkovPredictionConfig
from stages.markov_prediction.core import CV_LINE_ID, FramePrediction, MarkovPredictor, PairInfo

__all__ = [
    "CV_LINE_ID",
    "INPUTS",
    "MODES",
    "OUTPUTS",
    "SPEC",
    "FramePrediction",
    "MarkovPredictionConfig",
    "MarkovPredictor",
    "PairInfo",
    "RAW_GRIDS",
    "main",
]

_BINDING = ("SPEC", "INPUTS", "OUTPUTS", "main", "make_core")


def __getattr__(name: str):
    """The binding lives in ``__main__.py``; importing it pulls in the runtime (zenoh) only when asked."""
    if name in _BINDING:
        from stages.markov_prediction import __main__ as binding

        return getattr(binding, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
