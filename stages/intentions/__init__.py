"""Intentions stage: a Dynamic Bayesian Network per vehicle, estimated with a particle filter (docs/method.md §7).

Consumes ``track_frame`` (``TrackFrame``), ``corridor_set`` (``CorridorSet``)
and ``relation_set`` (``RelationSet``) of the same stamp, and the latched
``scene`` (``SceneInfo``); produces ``intention_belief``
(``IntentionBelief``): for every vehicle with corridors, P(R = c) per
corridor with the particles' mean and spread of s, v and a on it (the
Markov chain's weights and initial box), P(I = stop), P(E = stop), P(I ≠ E),
P(lane change), the most probable manoeuvre, the distance to the next
intersection entrance, the effective sample size. Run it alone with
``python -m stages.intentions``; ``python -m stages.offline.intentions_eval``
scores it on recordings.

The network (all numbers are ``IntentionsConfig`` fields, [R] starting values
of docs/method.md §7 unless said otherwise), per vehicle n at every frame:

- R (route): the vehicle's corridor. P(R_t | R_{t−1}): stays with 1 −
  ``route_switch_per_step`` (0.005 per 0.1 s), else switches uniformly to
  another corridor holding the vehicle's matched lanelet (only before the
  branch point; s follows that lanelet, d is kept).
- E (expected: go/stop under rules and gaps). For each conflict point ahead
  on the particle's corridor where the other corridor has priority
  (``conflict_priority`` −1 in the relations), with the other vehicle's time
  T' from the relations and the particle's own T_e = (s* − s)/max(v, 1):
  P(conflict) = σ((T' − T_e + ``gap_pass_s``)/β)·(1 − σ((T' − T_e −
  ``gap_critical_s``)/β)), β = ``gap_scale_s`` (0.6 s), t_c 5 s: the
  priority vehicle arrives less than t_c after the ego (gap rejected) and
  not more than ``gap_pass_s`` (1 s) before it (then it is gone; our
  addition to the logistic gap rule). It is weighted by the other vehicle's
  route probability from this stage's previous output. P(E = go) = Π(1 −
  q·P(conflict)). The TAF-BW maps carry no stop signs, so the stop-sign
  rule of docs/method.md §7 is not implemented.
- I (intended: stop before the next intersection entrance, or go).
  P(I_t | I_{t−1}, E_t): keeps I with ``intention_keep`` (0.98) when I =
  E, takes E with ``intention_adapt`` (0.10 per 0.1 s) when not, within
  [``intention_floor``, 1 − floor] (0.01); E is marginalised (its
  probability mixes the two rows).
- Φ = (s, d, v, a) on the particle's corridor, plus a driver style (the
  lateral acceleration of its speed profile, drawn at birth from
  ``lat_accels_mps2`` (3, 2.5, 2, 1.5) with ``lat_accel_weights`` (0.1,
  0.2, 0.4, 0.3)). Stop intention with an entrance ahead: a ~ N(−v²/(2
  max(d_stop − ``stop_margin_m``, ``stop_min_distance_m``)),
  ``stop_accel_sigma_mps2``²) clipped to [−8, 0], where d_stop runs to the
  entrance minus ``stop_offset_m``; go (or no entrance ahead): a ~ N(k_v
  (v_adm(s) − v), ``go_accel_sigma_mps2``² = 0.7²), k_v = ``go_gain_per_s``
  1.0 s⁻¹ (docs/method.md says 0.5; see below),
  v_adm = min(speed limit, √(a_lat/|κ|)) with a braking look-ahead of
  ``brake_lookahead_mps2`` 2.5 (docs/method.md §4.2; κ smoothed over
  ``curvature_smoothing_m``): a turning corridor demands lower speeds
  ahead, so an early slow-down gains weight on it. Then s += v dt + ½ a dt²,
  v = max(0, v + a dt) (never backwards), d = 0.9^(dt/0.1) d + N(0,
  0.05² dt/0.1). Longer gaps are split into steps of ``max_substep_s``.
  ``accel_relaxation_s`` > 0 makes a a state relaxing to the mode's mean
  (measured: stop/go much worse, so off; docs/method.md §7.5).
- Z = (x, y, ψ, v): the particle (s, d) on its corridor gives X(s) + d·n(s)
  and ψ(s); ln P(Z | Φ, R) = −½ (|Δxy|²/0.5² + wrap(Δψ)²/0.15² + Δv²/0.5²);
  the heading term only at speeds of ``heading_min_speed_mps`` (1 m/s) and
  more (a standing car's yaw drifts), a term whose measurement is not
  finite is left out. The speed is the corridors stage's.

``stop_offset_m`` 14 m: cars that stop first in line stand well before the
entrance the relations report (the first conflict point of the entry
lanelet), at the stop line; the target sits at the near end of those
positions because a car stopping beyond its target contradicts the stop
model hard, one stopping short of it only mildly (measured: docs/method.md
§7.5).

``go_gain_per_s`` 1.0 s⁻¹ instead of the 0.5 first chosen: with 0.5 the
particles' speed lagged cars pulling away from a standstill, and the
corridor whose speed profile happened to excuse the lag gained weight; 1.0
predicts routes better without hurting the stop/go separation (measured,
with the variants not taken: docs/method.md §7.5).

The particle filter, per frame (``particles_per_vehicle`` N = 300 per
vehicle: fewer lose route accuracy for little saving, more cost clearly
more for no gain beyond the seed-to-seed spread; measured with
``bench/intentions_particles.py``: docs/method.md §7.5):

1. Birth: a vehicle without particles gets N split evenly over its
   corridors, at its Frenet position on each (noise ``birth_sigma_*``), its
   speed, I uniform, a driver style each; the birth weight adds a prior
   N(d; 0, ``birth_lateral_sigma_m``) on the lateral offset.
2. Corridor changes: old corridors map onto the new ones by corridor_id,
   else by the longest common run of lanelets; s moves by the difference of
   a shared lanelet's start on both (exact: the corridors stage cuts one
   geometry per route). Particles of a corridor with no such successor are
   projected from their map position onto their new corridor, or the
   nearest one. A new corridor without particles gets ``floor_particles``
   (2 % of N) with the prior weight 1/N.
3. Propagation of E, I, R, Φ (all vehicles' particles as (V, N) arrays).
4. Weighting by the likelihood, normalised per vehicle with log-sum-exp;
   log weights are floored at ``min_log_weight`` (−40) below the best, so a
   corridor that keeps particles keeps a probability above 0.
5. ESS = 1/Σw². Below N/2 (``resample_ess_fraction``), or when a corridor
   has fewer than the floor, systematic resampling *within each corridor*:
   corridor c keeps its probability W_c exactly and gets the floor (2 % of
   N, at most N/C) plus a largest-remainder share ∝ W_c of the rest, each
   particle weighing W_c/n_c; then jitter (s 0.2 m, v 0.1 m/s). Plain
   systematic resampling over all particles let P(R) wander between
   corridors the measurements could not tell apart yet: sampling noise, not
   evidence (docs/method.md §7.3). Resampling
   within corridors removes that drift and keeps the 2 % particle floor
   per corridor by construction.
6. Death: a vehicle not updated for more than ``unseen_timeout_s`` (1 s,
   by stamps) is dropped; a vehicle present without a finite position is
   not updated (``nan_state``) and dies the same way.
7. Random numbers: every vehicle draws from its own
   ``np.random.default_rng([seed, frame_index, track_id])`` in a fixed
   order, so the same recording gives the same beliefs in-process and
   through the bus, whatever else is in the frame.

Manoeuvres (``tables.corridor_manoeuvre``, from the map): TURN_LEFT/RIGHT
when a member lanelet of the next intersection on the corridor turns, else
GO_STRAIGHT; without an intersection ahead LANE_CHANGE_LEFT/RIGHT when the
corridor switches lanes (consecutive lanelets that are not successors) less
than ``lane_change_reach_m`` behind the vehicle or ahead, else FOLLOW_LANE.
P(lane change) sums the corridors that switch lanes. The map is loaded
through ``stages.corridors.SceneMaps`` when the scene changes (all state is
reset then), from the ``data`` parameter's folder (``maps/``, by the scene's
map name, checked by sha256 as in the corridors stage; the launcher passes
its ``--data``; "" the embedded ``stages/data/taf-bw``).

Bounded work: ``max_pairs`` 600 vehicle-corridor pairs per frame (issue
13): beyond it whole vehicles are kept in CorridorSet order while their
corridors fit, the rest are not updated this frame (``stages.lib.caps.cap_pairs``;
one ``pairs_capped`` issue; a vehicle skipped for ``unseen_timeout_s`` dies).
TAF-BW frames (at most ~20 vehicles, ~2 corridors each) never are.

Issues (the other vehicles are still processed): ``stamp_mismatch`` (the
inputs differ in stamp: no output), ``stamp_not_increasing`` (all particles
reset), ``no_relations``, ``missing_track``, ``nan_state``,
``nan_velocity``, ``bad_corridor``, ``filter_degenerate``, ``no_map``,
``map_problem``, ``map_sha256_mismatch``, ``scene_mismatch``.
"""

from __future__ import annotations

from stages.intentions.core import IntentionFilter, IntentionsConfig

__all__ = ["IntentionFilter", "IntentionsConfig", "SPEC", "INPUTS", "OUTPUTS", "main"]

_BINDING = ("SPEC", "INPUTS", "OUTPUTS", "main", "make_core")


def __getattr__(name: str):
    """The binding lives in ``__main__.py``; importing it pulls in the runtime (zenoh) only when asked."""
    if name in _BINDING:
        from stages.intentions import __main__ as binding

        return getattr(binding, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
