"""Mode ``baseline``: the Markov chain with the rule-based priority vector λ (docs/method.md §4), CORA's combination.

λ = min(λ_speed, λ_lead, λ_conf) cut against the free-driving preference,
applied per state without building Γ (``chain.InputPriority``). The rules
themselves are ``priority.py``'s pure functions (a library, also used by the
hybrid mode's speed restriction); this module holds what the baseline makes of
them per frame: the leaders and conflicts of the pairs, λ per step, and the
second pass that a crossing conflict needs (``rerun``).
"""

from __future__ import annotations

import collections
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from bus_schemas import AgentType
from stages.lib.base import Issue
from stages.lib.datasets import DEFAULT_SIZES_M
from stages.markov_prediction import priority as pr
from stages.markov_prediction.chain import InputPriority
from stages.markov_prediction.modes.base import ChainInputs, InputModel, Messages, Pair, Predictor


class Baseline(InputModel):
    """λ_speed, λ_lead and λ_conf per pair and step; no input of its own beyond the relations."""

    def __init__(self, predictor: Predictor) -> None:
        super().__init__(predictor)
        p = predictor
        self.config, self.grid, self.n_s = p.config, p.grid, p.n_s
        self.v_centres, self.a_centres, self.preference = p.v_centres, p.a_centres, p.preference
        cfg = p.config
        self.gaps = pr.CriticalGaps.build(
            self.v_centres, self.a_centres, p.grid.v_max_mps, tuple(cfg.leader_horizons_s), cfg.leader_brake_mps2
        )

    def read(self, messages: Messages, issues: list[Issue]) -> None:
        if messages.relation_set is None:
            issues.append(Issue("no_relations", -1, "no relation_set: no leader or crossing restriction this frame"))

    def start(self, pairs: list[Pair], issues: list[Issue]) -> ChainInputs:
        return _BaselineInputs(self, pairs, issues)

    def _leaders(self, pairs: list[Pair], by_track: dict[int, list[int]], issues: list[Issue]) -> dict[int, "_LeaderSpec"]:
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

    def _conflicts(self, pairs: list[Pair], index: dict[tuple[int, int], int], issues: list[Issue]) -> dict[int, "_ConflictSpec"]:
        """The influencing corridor of each pair (§4.4), with its zone on both corridors."""
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

            pref = self.preference if ctx.preference_k is None else ctx.preference_k[:, k + 1]

            def weights(lo: int, hi: int) -> np.ndarray:
                if ctx.preference_k is None:
                    r = ctx.r_static[:, :, :, lo:hi]
                else:
                    r = pr.combine_with_preference(ctx.lam_speed[:, :, :, lo:hi], pref, cfg.forbid_threshold)
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
                r[restricted] = pr.combine_with_preference(m, pref if pref.ndim == 1 else pref[restricted], cfg.forbid_threshold)
                return r

            return InputPriority(weights=weights)

        return step


class _BaselineInputs(ChainInputs):
    """One frame: λ_speed and λ_lead for every pair; then, when a pair has an influencing corridor, a second pass
    over the restricted pairs and (transitively) their followers, with the first pass's occupancies."""

    def __init__(self, model: Baseline, pairs: list[Pair], issues: list[Issue], ar_lam: np.ndarray | None = None) -> None:
        cfg, grid = model.config, model.grid
        cell_centre = grid.s_edges_m()[: model.n_s] + 0.5 * cfg.ds_m
        # λ_speed per pair, static over the steps, and the combined r where nothing else restricts;
        # with ``ar_lam`` (B, K, M) (hybrid_rules) the preference is λ_AR(k) scaled to a largest entry of 1, per step
        self.lam_speed = lam_speed = speed_restriction(model.predictor, pairs)
        self.ar_lam = ar_lam
        self.pref_k = None if ar_lam is None else ar_lam / np.maximum(ar_lam.max(axis=2, keepdims=True), 1e-12)
        self.measured = model.predictor.measured_inputs(pairs)
        if ar_lam is not None and cfg.hybrid_rules_standing == "rules":
            # a standing vehicle (inside the standstill band: it gets the start-rate mixture) keeps the rules'
            # own preference and its measured input: the learned profiles start queues that do not move
            standing = np.array([q.start_rate_hz > 0 for q in pairs], dtype=bool)
            if standing.any():
                self.pref_k = self.pref_k.copy()
                self.pref_k[standing] = np.asarray(model.preference, dtype=self.pref_k.dtype)[None, None, :]
                self.ar_lam = ar_lam.copy()
                self.ar_lam[standing, 0] = self.measured[standing]
        self.r_static = pr.combine_with_preference(lam_speed, model.preference, cfg.forbid_threshold) if ar_lam is None else None
        index = {(p.track_id, p.corridor_id): b for b, p in enumerate(pairs)}
        by_track: dict[int, list[int]] = collections.defaultdict(list)
        for b, p in enumerate(pairs):
            by_track[p.track_id].append(b)
        self.leaders = model._leaders(pairs, by_track, issues)
        self.conflicts = model._conflicts(pairs, index, issues)
        self.model, self.pairs, self.cell_centre = model, pairs, cell_centre
        self.with_interval = cfg.grid_distribution == "interval" or bool(self.conflicts)
        self.second = False
        self._step = model._step_inputs(_PassContext(
            members=np.arange(len(pairs)), lam_speed=lam_speed, r_static=self.r_static, leaders=self.leaders,
            conflicts={}, stored=None, cell_centre=cell_centre, pairs=pairs, preference_k=self.pref_k,
        ))

    def initial(self) -> np.ndarray:
        return self.measured if self.ar_lam is None else self.ar_lam[:, 0]

    def step(self, k: int, marginals):
        return self._step(k, marginals)

    def rerun(self, arrays: dict[str, np.ndarray]) -> np.ndarray | None:
        if not self.conflicts or self.second:
            return None
        self.second = True
        leaders = self.leaders
        members = _closure(set(self.conflicts), leaders)
        m = np.array(sorted(members))
        stored = {"position": arrays["position"], "velocity": arrays["velocity"], "interval": arrays["interval"]}
        self._step = self.model._step_inputs(_PassContext(
            members=m,
            lam_speed=self.lam_speed[m],
            r_static=None if self.r_static is None else self.r_static[m],
            leaders={int(np.searchsorted(m, f)): spec for f, spec in leaders.items() if f in members},
            conflicts={int(np.searchsorted(m, e)): spec for e, spec in self.conflicts.items()},
            stored=stored,
            cell_centre=self.cell_centre,
            pairs=self.pairs,
            preference_k=None if self.pref_k is None else self.pref_k[m],
        ))
        return m


def speed_restriction(predictor: Predictor, pairs: list[Pair]) -> np.ndarray:
    """λ_speed (B, M, N_v, N_s) per pair, static over the steps (§4.2); also the hybrid mode's cut."""
    grid, cfg = predictor.grid, predictor.config
    adm, cells, weights = speed_profiles(predictor, pairs)
    lam_speed = np.empty((len(pairs), grid.n_inputs, grid.n_v_cells, predictor.n_s), np.float32)
    for b, p in enumerate(pairs):
        lam_speed[b] = pr.speed_restriction(adm[b], p.s_m, cells[b], predictor.v_centres, predictor.a_centres, weights, cfg.tau_s)
    return lam_speed


def speed_profiles(predictor: Predictor, pairs: list[Pair]) -> tuple[list[np.ndarray], np.ndarray, np.ndarray]:
    """What λ_speed is made of: v_adm (J, n) on each pair's profile ``p.s_m``, the s-cell centres (B, N_s) and the
    normalised weights (J,) of the lateral accelerations."""
    cfg, grid, n_s = predictor.config, predictor.grid, predictor.n_s
    cell_centre = grid.s_edges_m()[:n_s] + 0.5 * cfg.ds_m
    weights = np.asarray(cfg.lat_accel_weights, dtype=np.float64)
    weights = weights / weights.sum()
    lat_accels = np.asarray(cfg.lat_accels_mps2)
    # hybrid: the curvature times the pair's curve factor (0: the limit alone; ``Pair.curve_factor``)
    hybrid = cfg.mode == "hybrid"
    adm = pr.admissible_speeds_batch([p.s_m for p in pairs],
                                     [np.asarray(p.curvature_1pm, dtype=np.float64) * p.curve_factor if hybrid and p.curve_factor != 1.0
                                      else p.curvature_1pm for p in pairs],
                                     [p.speed_limit_mps for p in pairs], lat_accels, cfg.lookahead_brake_mps2, cfg.curvature_smoothing_m)
    cells = np.array([p.s_first_m for p in pairs], dtype=np.float64).reshape(-1, 1) + cell_centre[None, :]
    return adm, cells, weights


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
    pairs: list[Pair]
    preference_k: np.ndarray | None = None  # (B, K, M) per-pair, per-step preference (hybrid_rules); None: the static one


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
