"""The DBN's conditionals as vectorised numpy over particles ``(V, N)``: V vehicles × N particles each.

Pure functions of the particle arrays, the frame's `PairTables` and
pre-drawn random numbers (drawn per vehicle from its own seeded generator by
`IntentionFilter`), so no Python loop runs per particle. The hottest parts
(the pose and admissible speed of the particles, and `propagate`'s update of
I and Φ) run through the compiled kernels of `stages.intentions.kernels`,
which give the numpy code's values bit for bit. See the package docstring
for the model and its parameters (docs/method.md §7).
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

from stages.lib.maps import wrap_angle_rad

from stages.intentions import kernels
from stages.intentions.tables import KEY_OFFSET_M, PairTables
from stages.intentions.signals import combine, signal_stop_probability

REFERENCE_STEP_S = 0.1
"""The step the per-step probabilities and noises of docs/method.md §7 are stated for (10 Hz)."""


@dataclass(slots=True, eq=False)
class Particles:
    """Particle arrays ``(V, N)``: route slot, Frenet state, intention, driver style, weight.

    ``route`` indexes the vehicle's corridors (its slot); ``stop`` is I
    (True: stop before the next intersection entrance); ``style`` indexes the
    lateral accelerations of the admissible speed profile; ``p_expected_stop``
    is P(E = stop) of the particle at the last propagation (kept for the
    output); ``weight`` is normalised per vehicle.
    """

    route: np.ndarray  # int64
    s_m: np.ndarray
    d_m: np.ndarray
    v_mps: np.ndarray
    a_mps2: np.ndarray
    stop: np.ndarray  # bool
    style: np.ndarray  # int64
    p_expected_stop: np.ndarray
    weight: np.ndarray

    @classmethod
    def stack(cls, rows: list["Particles"]) -> "Particles":
        return cls(*(np.concatenate([getattr(r, name) for r in rows], axis=0) for name in PARTICLE_FIELDS))

    def row(self, v: int) -> "Particles":
        """Row v as (1, N) views (no copy): the filter keeps them between frames and never writes into them (`stack`
        copies), so each frame's arrays live on only while a vehicle unseen since then keeps its row."""
        return Particles(*(getattr(self, name)[v : v + 1] for name in PARTICLE_FIELDS))

    def take(self, rows: np.ndarray, index: np.ndarray) -> None:
        """Replace rows `rows` (R,) by the particles `index` (R, N) of themselves (resampling)."""
        n = index.shape[1]
        flat = (np.asarray(rows)[:, None] * n + index).ravel()  # one gather per field over the (V·N) particles
        for name in PARTICLE_FIELDS:
            arr = getattr(self, name)
            arr[rows] = arr.reshape(-1)[flat].reshape(index.shape)


PARTICLE_FIELDS = tuple(f.name for f in fields(Particles))
"""The field names of `Particles`, in order."""


@dataclass(frozen=True, slots=True)
class ModelParams:
    """The numbers of the conditionals (from `IntentionsConfig`)."""

    route_switch_per_step: float
    gap_critical_s: float
    gap_pass_s: float
    gap_scale_s: float
    min_time_speed_mps: float
    intention_keep: float
    intention_adapt: float
    intention_floor: float
    go_gain_per_s: float
    go_accel_sigma_mps2: float
    accel_relaxation_s: float
    accel_jerk_sigma_mps2: float
    stop_accel_sigma_mps2: float
    stop_margin_m: float
    stop_min_distance_m: float
    accel_min_mps2: float
    accel_max_mps2: float
    lateral_decay: float
    lateral_sigma_m: float
    position_sigma_m: float
    heading_sigma_rad: float
    speed_sigma_mps: float


def per_step(p: float | np.ndarray, dt_s: np.ndarray) -> np.ndarray:
    """A probability per 0.1 s as a probability per dt: 1 − (1 − p)^(dt/0.1)."""
    return 1.0 - np.power(1.0 - p, dt_s / REFERENCE_STEP_S)


def _sigmoid(x):
    return 0.5 * (1.0 + np.tanh(0.5 * x))


def expected_stop(tables: PairTables, g: np.ndarray, s_m: np.ndarray, v_mps: np.ndarray, mp: ModelParams) -> np.ndarray:
    """P(E = stop) per particle from the conflicts with priority corridors on its route (`g`, `s_m`, `v_mps`: one shape).

    T_e = (s* − s)/max(v, 1) for every conflict point still ahead of the
    particle; a priority vehicle (time T' from the relations, route
    probability q from the last beliefs) conflicts with probability
    P_c = σ((T' − T_e + t_pass)/β)·(1 − σ((T' − T_e − t_c)/β)): it arrives
    less than t_c after the ego and not more than t_pass before it.
    P(E = go) = Π (1 − q·P_c).
    """
    g = np.asarray(g)
    # only the particles on a pair with a priority conflict at all (the others: no factor, P(E = stop) = 1 − 1 = 0), and
    # of those the sigmoids only where a conflict is ahead (C is the largest count over the frame's pairs: in dense
    # traffic most entries are padding or behind); the same values there, 1 elsewhere, so each product is unchanged
    found = kernels.conflict_stop(tables, g, s_m, v_mps, mp.min_time_speed_mps, lambda gap, weight: 1.0 - weight * _conflict_probability(gap, mp))
    if found is not None:  # compiled: the same bits (tests/stages/test_intentions.py)
        p_e = found
    else:
        p_e = _expected_stop_numpy(tables, g, s_m, v_mps, mp)
    if getattr(tables, "signal_line_s_m", None) is None:  # no signal phases: the conflicts alone, as before issue 17
        return p_e
    return combine(p_e, signal_stop_probability(tables, g, s_m, v_mps))


def _conflict_probability(gap: np.ndarray, mp: ModelParams) -> np.ndarray:
    """P_c of gaps T' − T_e (`expected_stop`)."""
    return _sigmoid((gap + mp.gap_pass_s) / mp.gap_scale_s) * (1.0 - _sigmoid((gap - mp.gap_critical_s) / mp.gap_scale_s))


def _expected_stop_numpy(tables: PairTables, g: np.ndarray, s_m: np.ndarray, v_mps: np.ndarray, mp: ModelParams) -> np.ndarray:
    """`expected_stop`'s P(E = stop) from the conflicts on numpy (where numba is missing)."""
    p_e = np.zeros(g.shape)
    on = np.isfinite(tables.conflict_s_m).any(axis=1)[g]
    if on.any():
        g_on = g[on]
        cs = tables.conflict_s_m[g_on]  # (K, C)
        ahead = cs - s_m[on][:, None]
        valid = np.isfinite(cs) & (ahead > 0.0)
        factor = np.ones(cs.shape)
        at = np.nonzero(valid)
        if at[0].size:
            g_at = g_on[at[0]]
            speed = np.maximum(v_mps[on], mp.min_time_speed_mps)[at[0]]
            t_ego = ahead[at] / speed
            gap = tables.conflict_other_time_s[g_at, at[1]] - t_ego
            factor[at] = 1.0 - tables.conflict_weight[g_at, at[1]] * _conflict_probability(gap, mp)
        p_e[on] = 1.0 - np.prod(factor, axis=-1)
    return p_e


def switch_routes(p: Particles, tables: PairTables, first_pair: np.ndarray, dt_s: np.ndarray, u_switch, u_choice, mp: ModelParams) -> None:
    """P(R_t | R_{t−1}): stay with 1 − ε_R, else switch uniformly to another corridor holding the vehicle's lanelet.

    Only corridors holding the vehicle's matched lanelet take part (before
    the branch point); s moves by the difference of that lanelet's start on
    the two corridors, d is kept.
    """
    n_vehicles = p.route.shape[0]
    n_max = int(tables.n_slots.max()) if n_vehicles else 0
    if n_max < 2:
        return
    switch_p = per_step(mp.route_switch_per_step, dt_s)
    found = kernels.switch_routes(p.route, p.s_m, tables, first_pair, u_switch, u_choice, switch_p, n_max)
    if found is not None:  # compiled: the same switches and s (tests/stages/test_intentions.py)
        if found:
            p.route, p.s_m = found
        return
    slot = np.arange(n_max)[None, :]
    pair = np.minimum(first_pair[:, None] + slot, tables.n_pairs - 1)
    eligible = (slot < tables.n_slots[:, None]) & np.isfinite(tables.switch_s_m[pair])
    n_eligible = eligible.sum(axis=1)
    order = np.argsort(~eligible, axis=1, kind="stable")  # eligible slots first, in slot order
    rank = np.argsort(order, axis=1, kind="stable")
    rows = np.arange(n_vehicles)[:, None]
    current_ok = eligible[rows, p.route]
    go = (u_switch < switch_p[:, None]) & current_ok & (n_eligible[:, None] >= 2)
    if not go.any():
        return
    j = np.minimum((u_choice * (n_eligible[:, None] - 1)).astype(np.int64), np.maximum(n_eligible[:, None] - 2, 0))
    j = j + (j >= rank[rows, p.route])
    new_route = np.where(go, order[rows, np.minimum(j, n_max - 1)], p.route)
    old_g = first_pair[:, None] + p.route
    new_g = first_pair[:, None] + new_route
    shifted = p.s_m - tables.switch_s_m[old_g] + tables.switch_s_m[new_g]
    p.s_m = np.where(go, shifted, p.s_m)
    p.route = np.where(go, new_route, p.route)


def propagate(
    p: Particles, tables: PairTables, first_pair: np.ndarray, dt_s: np.ndarray, active: np.ndarray, draws, mp: ModelParams
) -> None:
    """One step of E, I, R and Φ for the rows `active` (V,) over `dt_s` (V,); `draws` = (uniforms (3, V, N), normals (2, V, N)).

    E: `expected_stop` at Φ_{t−1}. I: stays with `intention_keep` when it
    agrees with E, else adapts to E with `intention_adapt` (per 0.1 s),
    within [floor, 1 − floor]; E is marginalised (its probability mixes the
    two transition rows). Φ: stop intention with an entrance ahead: a ~
    N(−v²/(2 max(d_stop − margin, d_min)), σ_stop²) clipped to [a_min, 0];
    otherwise a ~ N(k_v (v_adm(s) − v), σ_go²); then s, v by constant
    acceleration over dt (never backwards), d_t = ρ^(dt/0.1) d + N(0,
    σ_d² dt/0.1).
    """
    (u_switch, u_choice, u_intent), (n_accel, n_lateral) = draws
    dt = np.where(active, dt_s, 0.0)
    g_before = first_pair[:, None] + p.route
    p_e = expected_stop(tables, g_before, p.s_m, p.v_mps, mp)
    keep = 1.0 - per_step(1.0 - mp.intention_keep, dt)[:, None]  # I agrees with E: keeps it
    adapt = per_step(mp.intention_adapt, dt)[:, None]  # I disagrees with E: takes E
    act = active[:, None]
    compiled = kernels.available()  # then I is drawn with Φ below, particle by particle (the route switch reads neither)
    if not compiled:
        p_stop = np.where(
            p.stop,
            p_e * keep + (1.0 - p_e) * (1.0 - adapt),
            p_e * adapt + (1.0 - p_e) * (1.0 - keep),
        )
        p_stop = np.clip(p_stop, mp.intention_floor, 1.0 - mp.intention_floor)
        p.stop = np.where(act, u_intent < p_stop, p.stop)
        p.p_expected_stop = np.where(act, p_e, p.p_expected_stop)
    switch_routes(p, tables, first_pair, dt, np.where(act, u_switch, 1.0), u_choice, mp)
    g = first_pair[:, None] + p.route
    step = dt[:, None]
    relax = mp.accel_relaxation_s > 0.0
    # acceleration as a state (τ_a > 0): it relaxes towards the mode's target with time constant τ_a, plus a jerk noise
    pull = 1.0 - np.exp(-dt / mp.accel_relaxation_s)[:, None] if relax else np.zeros_like(step)
    jerk = mp.accel_jerk_sigma_mps2 * np.sqrt(dt / REFERENCE_STEP_S)[:, None] if relax else np.zeros_like(step)
    decay = np.power(mp.lateral_decay, step / REFERENCE_STEP_S)
    lateral = mp.lateral_sigma_m * np.sqrt(step / REFERENCE_STEP_S)
    if compiled and kernels.intend_and_move(p, tables, g, p_e, u_intent, n_accel, n_lateral, active, dt,
                                            (keep, adapt, pull, jerk, decay, lateral), mp, KEY_OFFSET_M):
        return  # the same bits as below (tests/stages/test_intentions.py)
    v = p.v_mps
    target_go = mp.go_gain_per_s * (tables.admissible_speed(g, p.s_m, p.style) - v)
    to_stop = tables.stop_s_m[g] - p.s_m
    has_stop = np.isfinite(to_stop)
    target_stop = -(v**2) / (2.0 * np.maximum(np.where(has_stop, to_stop, 1.0) - mp.stop_margin_m, mp.stop_min_distance_m))
    stopping = p.stop & has_stop
    if relax:
        target = np.where(stopping, np.maximum(target_stop, mp.accel_min_mps2), target_go)
        a = p.a_mps2 + pull * (target - p.a_mps2) + jerk * n_accel
        a = np.where(stopping, np.minimum(a, 0.0), a)
    else:
        a_go = target_go + mp.go_accel_sigma_mps2 * n_accel
        a_stop = np.clip(target_stop + mp.stop_accel_sigma_mps2 * n_accel, mp.accel_min_mps2, 0.0)
        a = np.where(stopping, a_stop, a_go)
    a = np.clip(a, mp.accel_min_mps2, mp.accel_max_mps2)
    moving = np.where(a < 0.0, np.minimum(step, v / np.maximum(-a, 1e-9)), step)
    p.s_m = p.s_m + v * moving + 0.5 * a * moving**2
    p.v_mps = np.maximum(v + a * step, 0.0)
    p.a_mps2 = np.where(act, a, p.a_mps2)
    p.d_m = decay * p.d_m + lateral * n_lateral


def log_likelihood(p: Particles, tables: PairTables, first_pair: np.ndarray, z, mp: ModelParams) -> np.ndarray:
    """ln P(Z | Φ, R) per particle: Gaussian position, heading (wrapped) and speed errors.

    `z` = (x, y, heading, speed, heading_ok, speed_ok), arrays (V,); a term
    whose measurement is not usable (NaN, or the heading of a slow vehicle)
    is left out.
    """
    x_obs, y_obs, heading_obs, speed_obs, heading_ok, speed_ok = z
    g = first_pair[:, None] + p.route
    x, y, heading = tables.pose(g, p.s_m, p.d_m)
    found = kernels.gaussian_errors(x, y, heading, p.v_mps, z, mp.position_sigma_m, mp.heading_sigma_rad, mp.speed_sigma_mps)
    if found is not None:  # compiled: the same bits as below (tests/stages/test_intentions.py)
        return found
    position2 = (x - x_obs[:, None]) ** 2 + (y - y_obs[:, None]) ** 2
    out = -0.5 * position2 / mp.position_sigma_m**2
    heading_error = wrap_angle_rad(np.where(heading_ok, heading_obs, 0.0)[:, None] - heading)
    out = out - np.where(heading_ok[:, None], 0.5 * (heading_error / mp.heading_sigma_rad) ** 2, 0.0)
    speed_error = np.where(speed_ok, speed_obs, 0.0)[:, None] - p.v_mps
    out = out - np.where(speed_ok[:, None], 0.5 * (speed_error / mp.speed_sigma_mps) ** 2, 0.0)
    return out


def normalise(log_weight: np.ndarray, min_log_weight: float) -> tuple[np.ndarray, np.ndarray]:
    """(weights, ok) per row by log-sum-exp; relative log weights are floored at `min_log_weight`.

    The floor keeps every particle's weight positive, so a corridor that
    keeps particles keeps a probability above 0. A row whose log weights
    are all non-finite is not ok (weights uniform).
    """
    finite = np.isfinite(log_weight)
    top = np.max(np.where(finite, log_weight, -np.inf), axis=1)
    ok = np.isfinite(top)
    rel = np.where(finite, log_weight - np.where(ok, top, 0.0)[:, None], min_log_weight)
    w = np.exp(np.maximum(rel, min_log_weight))
    w = np.where(ok[:, None], w, 1.0)
    return w / w.sum(axis=1, keepdims=True), ok


def stratified_resample(
    route: np.ndarray, weight: np.ndarray, n_slots: np.ndarray, floor: int, u0: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Systematic resampling within each corridor: (indices (R, N), new weights (R, N)) for rows (R, N).

    Every corridor of a row keeps its probability mass W_c exactly: it gets
    n_c = floor + a largest-remainder share of the other N − C·floor
    particles in proportion to W_c, drawn by systematic resampling among its
    own particles (offset u0 of the row), each with weight W_c / n_c. So
    resampling never moves probability between corridors (no drift between
    corridors the measurements cannot tell apart yet), and every corridor
    holding particles keeps at least `floor` of them (at most N // C). A
    corridor without particles gets none. Rows are vehicles, `route` their
    particles' corridor slots, `n_slots` (R,) their corridor counts.
    """
    n_rows, n = weight.shape
    n_max = int(n_slots.max())
    key_of = np.arange(n_rows)[:, None] * n_max + route  # (row, slot) -> group id
    groups = n_rows * n_max
    flat_key = key_of.ravel()
    flat_w = weight.ravel()
    mass = np.bincount(flat_key, flat_w, minlength=groups).reshape(n_rows, n_max)
    count = np.bincount(flat_key, minlength=groups).reshape(n_rows, n_max)
    usable = count > 0
    k = usable.sum(axis=1)
    per = np.minimum(floor, n // np.maximum(k, 1))
    extra = n - per * k
    share = np.where(usable, mass, 0.0)
    share = extra[:, None] * share / share.sum(axis=1, keepdims=True)
    alloc = np.where(usable, np.floor(share).astype(np.int64) + per[:, None], 0)
    left = n - alloc.sum(axis=1)
    remainder = np.where(usable, share - np.floor(share), -1.0)
    order = np.argsort(-remainder, axis=1, kind="stable")
    rank = np.argsort(order, axis=1, kind="stable")
    alloc += (rank < left[:, None]) & usable
    # the stable order of the group ids: rows are contiguous in `flat_key`, so it is each row's stable order of its slots
    # (offset by the row's start); slots fit int8, whose stable argsort is numpy's radix sort (the same permutation)
    if n_max <= 127 and n_rows:
        sort = (np.argsort(route.astype(np.int8), axis=1, kind="stable") + (np.arange(n_rows) * n)[:, None]).ravel()
    else:
        sort = np.argsort(flat_key, kind="stable")
    sorted_key = flat_key[sort]
    sorted_w = flat_w[sort]
    group_mass = mass.ravel()[sorted_key]
    cumulative = np.cumsum(sorted_w)
    starts = np.searchsorted(sorted_key, np.arange(groups), side="left")
    ends = np.searchsorted(sorted_key, np.arange(groups), side="right")
    before = np.concatenate([[0.0], cumulative])[starts]
    within = (cumulative - before[sorted_key]) / np.where(group_mass > 0, group_mass, 1.0)
    last = ends[ends > starts] - 1
    within[last] = 1.0
    keys = sorted_key + within
    flat_alloc = alloc.ravel()
    target = np.repeat(np.arange(groups), flat_alloc)
    k_in = np.arange(target.size) - np.repeat(np.cumsum(flat_alloc) - flat_alloc, flat_alloc)
    positions = target + (u0[target // n_max] + k_in) / flat_alloc[target]
    pick = np.searchsorted(keys, positions, side="right")
    pick = np.clip(pick, starts[target], ends[target] - 1)
    source = sort[pick]
    index = (source - (source // n) * n).reshape(n_rows, n)
    new_weight = (mass.ravel()[target] / flat_alloc[target]).reshape(n_rows, n)
    return index, new_weight


def systematic_indices(weight: np.ndarray, u0: np.ndarray) -> np.ndarray:
    """Systematic resampling of every row at once: indices (R, N) for weights (R, N) and offsets u0 (R,) in [0, 1)."""
    n_rows, n = weight.shape
    cumulative = np.cumsum(weight, axis=1)
    cumulative[:, -1] = 1.0
    keys = (cumulative + np.arange(n_rows)[:, None]).ravel()
    positions = ((u0[:, None] + np.arange(n)[None, :]) / n + np.arange(n_rows)[:, None]).ravel()
    flat = np.searchsorted(keys, positions, side="right")
    index = flat.reshape(n_rows, n) - np.arange(n_rows)[:, None] * n
    return np.clip(index, 0, n - 1)
