"""The rule-based priority vector λ of the baseline (docs/method.md §4.1–4.4), pure numpy.

Every array of restrictions uses the layout of the Markov chain without the
pair axis or with it first: ``(B, M, N_v, L)`` = (pair, input cell α,
velocity cell, s-cell of the part of the window being processed). A value is
a weight in [0, 1] per input: 1 allowed, 0 forbidden, in between soft.

- ``speed_restriction``: the speed-limit and curvature profile with a braking
  look-ahead (§4.2), four lateral accelerations mixed with weights;
- ``CriticalGaps`` and ``leader_restriction``: the leader interaction in its
  critical-gap form (§4.3), never a dense Θ;
- ``conflict_restriction``: the crossing restriction as an occupancy-window
  lookup against the influencing vehicle's predicted occupancy (§4.4);
- ``combine_with_preference``: the elementwise minimum of the restrictions
  combined with the free-driving preference q, CORA's carry-down rule
  (§4.1), with the strongest braking input kept where everything is
  forbidden.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from stages.lib.markov import kernels

#: Curvature below this (1/m) counts as straight: v_prof = √(a_lat / max(|κ|, this)).
MIN_CURVATURE_1PM = 1e-4


# ---------------------------------------------------------------------------
# Combination with the free-driving preference (§4.1)
# ---------------------------------------------------------------------------


def normalised_preference(values: tuple[float, ...] | np.ndarray, n_inputs: int) -> np.ndarray:
    """q over the ``n_inputs`` cells, float32, scaled so that its largest entry is 1.

    docs/method.md §4.1 gives q only up to a factor (CORA's sums to 1). Γ does not
    depend on the scale, but the combination min(m_α, q_α) does: a
    restriction m_α is the probability that input α is allowed, and it
    should cut the preferred inputs whenever it is below 1. With q summing
    to 1 (largest entry 0.3) a 63 % risk of meeting the crossing vehicle
    (m = 0.37) would not restrict anything. Raises ValueError when q cannot
    be a preference.
    """
    q = np.asarray(values, dtype=np.float64)
    if q.shape != (n_inputs,) or not np.all(np.isfinite(q)) or np.any(q < 0) or q.sum() <= 0:
        raise ValueError(f"free-driving preference must be {n_inputs} non-negative finite values, got {tuple(values)}")
    return (q / q.max()).astype(np.float32)


def preference_on_cells(values, from_edges, to_edges, tail_halving_mps2: float = 0.5) -> np.ndarray:
    """A preference given per cell of ``from_edges`` carried over to the cells of ``to_edges`` (both m/s², increasing).

    Read as a step function of the acceleration: each new cell gets the mean
    of the old steps over it (weighted by overlap). Beyond the old range the
    end values halve every ``tail_halving_mps2`` (as the default's own tails
    do, 0.15 → 0.08 → 0.04 and 0.02 → 0.01 → 0.005 per 0.5 m/s² cell), so a
    wider range adds ever less preferred inputs. On the same cells it returns
    ``values``. (M_to,) float64.
    """
    q = np.asarray(values, dtype=np.float64)
    a = np.asarray(from_edges, dtype=np.float64)
    b = np.asarray(to_edges, dtype=np.float64)
    if q.shape != (a.size - 1,):
        raise ValueError(f"preference_on_cells: {q.size} values for {a.size - 1} cells")
    if a.shape == b.shape and np.allclose(a, b, rtol=0.0, atol=1e-9):
        return q.copy()
    # fine steps over the union, each carrying the old value (or the halving tail) at its midpoint
    knots = np.unique(np.concatenate([a, b]))
    fine = np.unique(np.concatenate([knots, np.arange(min(a[0], b[0]), max(a[-1], b[-1]), tail_halving_mps2 / 8)]))
    mid, width = 0.5 * (fine[:-1] + fine[1:]), np.diff(fine)
    idx = np.clip(np.searchsorted(a, mid, side="right") - 1, 0, q.size - 1)
    val = q[idx] * np.exp2(-np.maximum(a[0] - mid, 0.0) / tail_halving_mps2 - np.maximum(mid - a[-1], 0.0) / tail_halving_mps2)
    out = np.empty(b.size - 1)
    for k in range(out.size):
        inside = (mid > b[k]) & (mid < b[k + 1])
        out[k] = float(np.sum(val[inside] * width[inside]) / np.sum(width[inside]))
    return out


def combine_with_preference(restriction: np.ndarray, preference: np.ndarray, forbid_threshold: float) -> np.ndarray:
    """The priority vector r from the restriction m and the preference q, along axis 1 (inputs).

    From the highest input down: r_α = min(m_α, q_α + carry) and the part of
    q_α + carry that m_α cuts is carried to the next lower input (a driver
    who may not use the preferred acceleration falls back to the next lower
    one). Where every m_α is at most ``forbid_threshold`` (everything
    forbidden or only ε-safe), r puts all weight on the strongest braking
    input α = 0 (docs/method.md §4.1 item 4, §4.1). The result has the shape of
    ``restriction`` (float32) and no all-zero column. ``preference`` is
    ``(M,)`` for every pair, or ``(B, M)`` per pair (hybrid mode with the speed
    restriction: the AR distribution scaled to a largest entry of 1).
    """
    m = np.asarray(restriction, dtype=np.float32)
    pref = np.asarray(preference, dtype=np.float32)
    n_in = m.shape[1]
    out = np.empty_like(m)
    carry = np.zeros(m.shape[:1] + m.shape[2:], dtype=np.float32)
    for alpha in range(n_in - 1, -1, -1):
        q = pref[alpha] if pref.ndim == 1 else pref[:, alpha].reshape((-1,) + (1,) * (m.ndim - 2))
        want = carry + q
        np.minimum(m[:, alpha], want, out=out[:, alpha])
        carry = want - out[:, alpha]
    dead = m.max(axis=1) <= forbid_threshold
    if np.any(dead):
        dead_b = np.broadcast_to(dead[:, None], out.shape)
        out[dead_b] = 0.0
        first = out[:, 0]
        first[dead] = 1.0
    return out


# ---------------------------------------------------------------------------
# Speed limit and curvature (§4.2)
# ---------------------------------------------------------------------------


def _median(values: np.ndarray) -> float:
    """``float(np.median(values))`` of a 1-D float64 array without np.median's overhead (the same number: the middle
    element, or the mean (a + b) / 2 of the two middle ones; np.median itself where a NaN is present)."""
    ordered = np.sort(values)
    n = ordered.shape[0]
    if n == 0 or np.isnan(ordered[-1]):
        return float(np.median(values))
    if n % 2:
        return float(ordered[n // 2])
    return float((ordered[n // 2 - 1] + ordered[n // 2]) / 2.0)


def admissible_speeds(
    s_m: np.ndarray,
    curvature_1pm: np.ndarray,
    speed_limit_mps: float,
    lat_accels_mps2: np.ndarray,
    brake_mps2: float,
    smoothing_m: float,
) -> np.ndarray:
    """v_adm(s) ``(J, n)`` for each lateral acceleration: the profile with a braking look-ahead.

    v_prof(s) = min(v_limit, √(a_lat / max(|κ(s)|, 1e-4))) with κ smoothed by
    a moving average over ``smoothing_m`` (lanelet joins give spikes), and
    v_adm(s) = min over s' ≥ s of √(v_prof(s')² + 2b(s' − s)), computed
    exactly as a reverse cumulative minimum of v_prof² + 2b·s'.
    """
    return admissible_speeds_batch([s_m], [curvature_1pm], [speed_limit_mps], lat_accels_mps2, brake_mps2, smoothing_m)[0]


_AVERAGING_KERNELS: dict[int, np.ndarray] = {}


def _moving_average(kappa: np.ndarray, half: int) -> np.ndarray:
    """The moving average over 2·half + 1 points of ``admissible_speeds`` (edges held: np.pad's "edge")."""
    kernel = _AVERAGING_KERNELS.get(half)
    if kernel is None:  # np.ones(2·half + 1) / (2·half + 1), made once per width (read only)
        kernel = _AVERAGING_KERNELS.setdefault(half, np.ones(2 * half + 1) / (2 * half + 1))
        kernel.flags.writeable = False
    n = kappa.shape[0]
    padded = np.empty(n + 2 * half)
    padded[:half] = kappa[0]
    padded[half : half + n] = kappa
    padded[half + n :] = kappa[-1]
    return np.convolve(padded, kernel, mode="valid")


def _smoothing_halves(s_all: np.ndarray, sizes: np.ndarray, smoothing_m: float) -> list[int]:
    """Per padded row of arc lengths (its first ``sizes[b]`` entries), the moving average's half-width in points:
    round(smoothing_m / 2 / max(median knot spacing, 1e-3)), 0 for a profile of two points or fewer."""
    n_b, n_max = s_all.shape
    if smoothing_m <= 0 or n_max <= 2:
        return [0] * n_b
    d = s_all[:, 1:] - s_all[:, :-1]
    valid = np.arange(n_max - 1)[None, :] < (sizes - 1)[:, None]
    if np.isnan(d[valid]).any():  # _median's NaN case: one row at a time
        medians = [_median(d[b, : sizes[b] - 1]) if sizes[b] > 2 else 0.0 for b in range(n_b)]
    else:
        ordered = np.sort(np.where(valid, d, np.inf), axis=1)  # each row's spacings sorted first, the padding after
        n = np.maximum(sizes - 1, 1)
        rows = np.arange(n_b)
        upper = ordered[rows, n // 2]
        lower = ordered[rows, np.maximum(n // 2 - 1, 0)]
        medians = np.where(n % 2 == 1, upper, (lower + upper) / 2.0).tolist()
    return [int(round(0.5 * smoothing_m / max(m, 1e-3))) if size > 2 else 0 for m, size in zip(medians, sizes.tolist())]


def admissible_speeds_batch(
    s_m: list[np.ndarray],
    curvature_1pm: list[np.ndarray],
    speed_limits_mps: list[float],
    lat_accels_mps2: np.ndarray,
    brake_mps2: float,
    smoothing_m: float,
) -> list[np.ndarray]:
    """``admissible_speeds`` of B profiles (their own lengths and speed limits): ``(J, n_b)`` each, the same numbers.

    The smoothing is one ``np.convolve`` per profile with some curvature (a
    profile of zeros, the hybrid mode's without curves, stays zeros); the rest is elementwise
    (and a reverse running minimum), done for all the profiles at once on
    rows padded to the longest one (+∞ past a profile's end, which the
    running minimum from the end never takes), or compiled where numba
    imports (``kernels.admissible_rows``: the same numbers, one pass per row).
    """
    n_b = len(s_m)
    a_lat = np.asarray(lat_accels_mps2, dtype=np.float64)
    if n_b == 0:
        return []
    s_list = [np.asarray(s, dtype=np.float64) for s in s_m]
    k_list = [np.asarray(c, dtype=np.float64) for c in curvature_1pm]
    sizes = [s.shape[0] for s in s_list]
    if any(s.ndim != 1 or k.shape != s.shape for s, k in zip(s_list, k_list)):  # (as one profile at a time would raise)
        raise ValueError("admissible_speeds: every profile needs 1-D arc lengths and curvatures of one length")
    n_max = max(sizes)
    inside = np.arange(n_max)[None, :] < np.asarray(sizes)[:, None]
    s_all = np.zeros((n_b, n_max))
    kappa_all = np.zeros((n_b, n_max))
    if n_max:
        s_all[inside] = np.concatenate(s_list)
        kappa_all[inside] = np.concatenate(k_list)
    kappa_all = np.abs(kappa_all)
    kappa_all = np.where(np.isfinite(kappa_all), kappa_all, 0.0)  # |κ|, non-finite as 0
    curved = kappa_all.any(axis=1)  # a row of zeros averages to zeros (+0.0 sums): no smoothing to do
    if curved.any():
        for b, half in enumerate(_smoothing_halves(s_all, np.asarray(sizes), smoothing_m)):
            if half > 0 and curved[b]:
                kappa_all[b, : sizes[b]] = _moving_average(kappa_all[b, : sizes[b]], half)
    limits = np.asarray(speed_limits_mps, dtype=np.float64).reshape(n_b, 1, 1)
    if kernels.available():  # the same numbers, compiled: one pass per row and lateral acceleration
        adm = kernels.admissible_rows(s_all, kappa_all, sizes, limits, a_lat, 2.0 * brake_mps2, MIN_CURVATURE_1PM)
        return [adm[b, :, : sizes[b]] for b in range(n_b)]
    v_prof = np.minimum(limits, np.sqrt(a_lat[None, :, None] / np.maximum(kappa_all[:, None, :], MIN_CURVATURE_1PM)))
    brake_s = 2.0 * brake_mps2 * s_all[:, None, :]
    key = v_prof**2 + brake_s
    lengths = np.asarray(sizes)
    if np.any(lengths < n_max):
        np.copyto(key, np.inf, where=(np.arange(n_max)[None, :] >= lengths[:, None])[:, None, :])  # past a profile's end
    suffix_min = np.minimum.accumulate(key[:, :, ::-1], axis=2)[:, :, ::-1]
    adm = np.sqrt(np.maximum(suffix_min - brake_s, 0.0))
    return [adm[b, :, : sizes[b]] for b in range(n_b)]


def speed_restriction(
    admissible_mps: np.ndarray,
    profile_s_m: np.ndarray,
    cell_s_m: np.ndarray,
    v_centres_mps: np.ndarray,
    input_centres_mps2: np.ndarray,
    weights: np.ndarray,
    tau_s: float,
) -> np.ndarray:
    """λ_speed ``(M, N_v, L) float32`` of one pair: Σ_j w_j · 1[v + a_α τ ≤ v_adm,j(s + vτ)].

    Each input is tested over one step from the cell centres (s, v) as in
    CORA (the ½aτ² term, at most a quarter of a 1 m cell, is left out so that
    the threshold is one acceleration per (v, s)). ``admissible_mps`` is
    ``(J, n)`` on ``profile_s_m``; past the profile's end its last value holds.
    """
    s_next = cell_s_m[None, :] + v_centres_mps[:, None] * tau_s  # (N_v, L)
    out = np.zeros((input_centres_mps2.shape[0],) + s_next.shape, dtype=np.float32)
    for j in range(admissible_mps.shape[0]):
        v_adm = np.interp(s_next, profile_s_m, admissible_mps[j])
        threshold = (v_adm - v_centres_mps[:, None]) / tau_s  # highest allowed acceleration
        out += np.float32(weights[j]) * (input_centres_mps2[:, None, None] <= threshold[None]).astype(np.float32)
    return out


# ---------------------------------------------------------------------------
# Leader (§4.3): critical gaps
# ---------------------------------------------------------------------------


def _held_then_braking(v0: np.ndarray, a: np.ndarray, hold_s: float, brake_mps2: float, v_max: float, t: np.ndarray):
    """Displacement (…, T) of vehicles that hold ``a`` for ``hold_s`` then brake at ``brake_mps2`` to a stop."""
    v0 = v0[..., None]
    a = a[..., None]

    def held(time):
        # exact saturated motion under constant a (v clamped to [0, v_max])
        bound = np.where(a > 0, v_max, 0.0)
        with np.errstate(divide="ignore", invalid="ignore"):
            t_clamp = np.where(a != 0, (bound - v0) / np.where(a != 0, a, 1.0), np.inf)
        t_clamp = np.maximum(t_clamp, 0.0)
        tt = np.minimum(time, t_clamp)
        x = v0 * tt + 0.5 * a * tt**2
        v_at = np.clip(v0 + a * tt, 0.0, v_max)
        return x + v_at * np.maximum(time - t_clamp, 0.0) * (a > 0), v_at

    x_hold, v_hold = held(np.minimum(t, hold_s))
    tb = np.maximum(t - hold_s, 0.0)
    tb = np.minimum(tb, v_hold / brake_mps2)
    return x_hold + v_hold * tb - 0.5 * brake_mps2 * tb**2


@dataclass(frozen=True, eq=False)
class CriticalGaps:
    """g*(horizon, v_F, α_F, v_L, α_L) ``(H, N_v, M, N_v, M) float32``, metres bumper to bumper.

    A follower input α_F is safe against a leader with (v_L, α_L) over the
    horizon Δt when the gap is at least g*: both hold their inputs (cell
    centres) for Δt, then both brake at ``brake_mps2`` to a stop, and the gap
    must stay positive throughout (CORA's crash check with an ODE event,
    here a dense time grid of ``dt_s``). The table depends only on the
    discretisation, so it is built once (docs/method.md §4.3 "efficient
    equivalent").
    """

    gaps_m: np.ndarray
    horizons_s: tuple[float, ...]

    @classmethod
    def build(
        cls,
        v_centres_mps: np.ndarray,
        input_centres_mps2: np.ndarray,
        v_max_mps: float,
        horizons_s: tuple[float, ...],
        brake_mps2: float,
        dt_s: float = 0.05,
    ) -> "CriticalGaps":
        n_v, n_in = v_centres_mps.shape[0], input_centres_mps2.shape[0]
        v = np.repeat(v_centres_mps, n_in)
        a = np.tile(input_centres_mps2, n_v)
        out = np.empty((len(horizons_s), n_v * n_in, n_v * n_in), dtype=np.float32)
        for h, hold_s in enumerate(horizons_s):
            t = np.arange(0.0, hold_s + v_max_mps / brake_mps2 + 2 * dt_s, dt_s)
            x = _held_then_braking(v, a, hold_s, brake_mps2, v_max_mps, t)  # (N, T)
            for start in range(0, x.shape[0], 50):
                diff = x[start : start + 50, None, :] - x[None, :, :]
                out[h, start : start + 50] = np.maximum(diff.max(axis=2), 0.0)
        gaps = out.reshape(len(horizons_s), n_v, n_in, n_v, n_in)
        return cls(gaps_m=gaps, horizons_s=tuple(horizons_s))


#: Resolution and start of the survival tables of leader displacements.
SURVIVAL_STEP_M = 0.25
SURVIVAL_START_M = -10.0
SURVIVAL_LENGTH_M = 250.0


def survival_grid() -> np.ndarray:
    """Displacements (J,) at which leader survival functions are tabulated."""
    return SURVIVAL_START_M + SURVIVAL_STEP_M * np.arange(int(SURVIVAL_LENGTH_M / SURVIVAL_STEP_M) + 1)


def survival_from_cells(position_probs: np.ndarray, edges_m: np.ndarray, grid_m: np.ndarray) -> np.ndarray:
    """P(displacement ≥ x) on ``grid_m`` from a cell distribution with ``edges_m`` (mass uniform in a cell).

    Mass missing from the cells (outside the window) lies beyond the last edge.
    """
    cdf = np.concatenate([[0.0], np.cumsum(position_probs, dtype=np.float64)])
    return 1.0 - np.interp(grid_m, edges_m, cdf, left=0.0, right=cdf[-1])


def survival_constant_speed(speed_mps: float, time_s: float, spread_m: float, grid_m: np.ndarray) -> np.ndarray:
    """P(displacement ≥ x) of an object moving at constant speed, uniform ±``spread_m`` around v·t."""
    centre = max(speed_mps, 0.0) * time_s
    return np.clip((centre + spread_m - grid_m) / (2.0 * spread_m), 0.0, 1.0)


def leader_restriction(
    gaps: CriticalGaps,
    survival: np.ndarray,
    offsets_m: np.ndarray,
    leader_v_cell: np.ndarray,
    leader_a_cell: np.ndarray,
    epsilon: float,
    geometric: bool = False,
) -> np.ndarray:
    """λ_lead ``(F, M, N_v, L) float32`` of F followers.

    ``survival`` ``(F, J)``: P(leader displacement ≥ x) on ``survival_grid()``;
    ``offsets_m`` ``(F, L)``: for each s-cell of the follower, c_F − s0_F −
    gap0 (cell centre minus the follower's start, minus the bumper-to-bumper
    gap at t0), so that the state is safe against a leader displacement Δ iff
    Δ ≥ offset + g*. ``leader_v_cell``, ``leader_a_cell`` ``(F,)``: the
    leader's mean speed and acceleration as cell indices (the cheaper
    variant of §4.3: the leader's position enters with its whole
    distribution, its speed and input through their means). Per horizon the
    weight is P(safe) + ε·(1 − P(safe)); the horizons are averaged
    arithmetically (CORA) or, with ``geometric``, geometrically, so that an
    input unsafe over one horizon is restricted as hard as ε^(1/H) (see
    ``conflict_restriction`` on why soft weights hardly move the chain).
    """
    table = gaps.gaps_m[:, :, :, leader_v_cell, leader_a_cell]  # (H, N_v, M, F)
    table = np.moveaxis(table, -1, 0) * np.float32(1.0 / SURVIVAL_STEP_M)  # (F, H, N_v, M), in table steps
    base = ((offsets_m - SURVIVAL_START_M) / SURVIVAL_STEP_M + 0.5).astype(np.float32)  # (F, L)
    n_f, n_j = survival.shape
    x = base[:, None, None, None, :] + table[..., None]  # (F, H, N_v, M, L): rounded index + 0.5
    np.clip(x, 0.0, n_j - 1, out=x)
    idx = x.astype(np.int32)
    idx += (np.arange(n_f, dtype=np.int32) * n_j)[:, None, None, None, None]
    safe = survival.astype(np.float32).reshape(-1)[idx]  # (F, H, N_v, M, L)
    weight = safe + np.float32(epsilon) * (1.0 - safe)
    combined = np.exp(np.log(weight).mean(axis=1)) if geometric else weight.mean(axis=1)
    return np.ascontiguousarray(combined.astype(np.float32).transpose(0, 2, 1, 3))


# ---------------------------------------------------------------------------
# Crossing restriction (§4.4): occupancy windows
# ---------------------------------------------------------------------------


def time_to_travel(distance_m: np.ndarray, v_mps: np.ndarray, a_mps2: np.ndarray, v_max_mps: float) -> np.ndarray:
    """Time to cover ``distance_m`` from speed v under a held acceleration a (saturated at 0 and v_max); inf if never.

    The arguments broadcast; a distance ≤ 0 takes no time.
    """
    d, v, a = np.broadcast_arrays(
        np.asarray(distance_m, dtype=np.float64), np.asarray(v_mps, dtype=np.float64), np.asarray(a_mps2, dtype=np.float64)
    )
    out = np.full(d.shape, np.inf)
    done = d <= 0
    out[done] = 0.0
    with np.errstate(divide="ignore", invalid="ignore"):
        # a > 0: quadratic until v_max, then constant speed
        acc = (a > 0) & ~done
        t_sat = (v_max_mps - v) / np.where(acc, a, 1.0)
        d_sat = v * t_sat + 0.5 * a * t_sat**2
        quad = (-v + np.sqrt(v**2 + 2 * a * d)) / np.where(acc, a, 1.0)
        out = np.where(acc & (d <= d_sat), quad, out)
        out = np.where(acc & (d > d_sat), t_sat + (d - d_sat) / v_max_mps, out)
        # a == 0: constant speed
        flat = (a == 0) & ~done & (v > 0)
        out = np.where(flat, d / np.where(v > 0, v, 1.0), out)
        # a < 0: reaches d only if it does not stop first
        dec = (a < 0) & ~done
        disc = v**2 + 2 * a * d
        reach = dec & (disc > 0)
        out = np.where(reach, (v - np.sqrt(np.maximum(disc, 0.0))) / np.where(dec, -a, 1.0), out)
    return out


def zone_occupancy(interval_probs: np.ndarray, edges_m: np.ndarray, zone_m: tuple[float, float]) -> np.ndarray:
    """P(centre in [zone_lo, zone_hi]) per step ``(K,)`` from cell distributions ``(K, N)`` (uniform in a cell)."""
    lo, hi = zone_m
    overlap = np.clip(np.minimum(edges_m[1:], hi) - np.maximum(edges_m[:-1], lo), 0.0, None) / np.diff(edges_m)
    return np.clip(interval_probs @ overlap, 0.0, 1.0)


def conflict_restriction(
    cell_s_m: np.ndarray,
    v_centres_mps: np.ndarray,
    input_centres_mps2: np.ndarray,
    v_max_mps: float,
    zone_m: tuple[float, float],
    now_s: float,
    other_occupancy: np.ndarray,
    tau_s: float,
    margin_s: float,
    epsilon: float,
) -> np.ndarray:
    """λ_conf ``(M, N_v, L) float32`` of one pair at time ``now_s`` after the frame.

    For each state (cell centres s, v) and input held, the window
    [t_in, t_out] in which the vehicle's centre is in the conflict zone is
    widened by ``margin_s`` on both sides; with q the maximum over the
    prediction steps j that overlap it of ``other_occupancy[j]`` (the
    influencing vehicle's probability to be in its own zone during step j),
    λ = ε^q: 1 when the zone is free, ``epsilon`` when it is surely taken,
    log-linear in between. (The linear 1 − q, floored at ε, barely moves the
    chain: Ψ keeps the current input with 0.67 and moves it two cells with
    0.01, so only weights near ε, like the entries of CORA's Θ, redirect it
    within the few steps before the zone.) States already in or past the
    zone, and states that cannot stop before it even with the strongest
    braking input (committed), are not restricted.
    """
    z_lo, z_hi = zone_m
    s = cell_s_m[None, None, :]
    v = v_centres_mps[None, :, None]
    a = input_centres_mps2[:, None, None]
    t_in = time_to_travel(z_lo - s, v, a, v_max_mps)
    t_out = time_to_travel(z_hi - s, v, a, v_max_mps)
    committed = np.isfinite(time_to_travel(z_lo - s, v, np.float64(input_centres_mps2[0]), v_max_mps))  # (1, N_v, L)
    committed = committed | (s >= z_lo)
    start = now_s + t_in - margin_s
    end = now_s + t_out + margin_s
    risk = np.zeros(t_in.shape)
    for j, q in enumerate(np.asarray(other_occupancy, dtype=np.float64)):
        if q <= 0:
            continue
        overlaps = (start < (j + 1) * tau_s) & (end > j * tau_s) & np.isfinite(t_in)
        risk = np.where(overlaps, np.maximum(risk, q), risk)
    out = np.power(max(epsilon, 1e-30), risk)
    out = np.where(committed, 1.0, out)
    return out.astype(np.float32)


def constant_speed_occupancy(distance_m: float, speed_mps: float, half_zone_m: float, tau_s: float, n_steps: int) -> np.ndarray:
    """Occupancy per step ``(K,)`` of an object at constant speed ``distance_m`` before its zone centre (fallback)."""
    v = max(speed_mps, 0.0)
    if v < 0.1:
        inside = abs(distance_m) <= half_zone_m
        return np.full(n_steps, 1.0 if inside else 0.0)
    t_in = (distance_m - half_zone_m) / v
    t_out = (distance_m + half_zone_m) / v
    j = np.arange(n_steps)
    return ((t_in < (j + 1) * tau_s) & (t_out > j * tau_s)).astype(np.float64)


def zone_half_width_m(length_m: float, other_width_m: float) -> float:
    """Half the conflict zone along a corridor: (L + w_other) / 2 (docs/method.md §4.4)."""
    value = 0.5 * (length_m + other_width_m)
    return value if math.isfinite(value) and value > 0 else 3.0
