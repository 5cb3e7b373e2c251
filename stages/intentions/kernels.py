"""Compiled (numba) kernels of the particle filter's hot paths, the numpy code's results bit for bit.

- `pose`, `admissible_speed`: `tables.PairTables.pose` and
  `tables.PairTables.admissible_speed`, locating each particle on its pair's
  centreline (`_locate_one`) and interpolating there;
- `admissible_speeds`: `tables.admissible_speeds` of a frame's pairs (the
  speed profiles of `tables.build_tables`);
- `intend_and_move`: `model.propagate`'s update of the intention I and of
  Φ (s, v, a, d) after the route switches;
- `conflict_stop`: `model.expected_stop`'s search of the conflicts ahead of
  each particle and the products of their factors (the sigmoids between
  the two stay numpy's ``tanh``);
- `gaussian_errors`: `model.log_likelihood`'s position, heading and speed
  terms from the particles' poses (`pose`);
- `switch_routes`: `model.switch_routes`' route switches (the eligible
  corridors, their order, the draw of the new one, the shift of s);
- `pair_sums`: the per-pair sums of the beliefs (`core.IntentionFilter._beliefs`):
  ``np.bincount``'s weighted sums, in its order, in one pass.

The numpy paths place every particle by one ``searchsorted`` over the
frame's concatenated key array (T ~ 5,000 samples at a busy junction) and
then gather and combine dozens of arrays of V × N particles, each numpy call
a pass over memory; here each particle is placed and evaluated in one pass.
Every value is computed with the same IEEE operations in the same order as
the numpy path (no fastmath: no reassociation, no fused multiply-add;
``sin``/``cos``/``sqrt`` are the C library's, which numpy's float64 ones give
bit for bit; the functions whose numpy SIMD versions differ from the C
library in the last bit, ``tanh``, ``exp``, ``power``, ``log``, stay in numpy
and their results are passed in), ``np.clip``/``np.maximum``/``np.minimum``
with numpy's NaN and signed-zero rules (`stages.lib.numpy_rules`), and the search is numpy's binary
search with its comparison (a NaN sorts last), so the results are the same
bit for bit (tests/stages/test_intentions.py compares them with the numpy
paths).

numba is a dependency; ``available()`` is False only where it cannot be
imported, and `tables` and `model` then use their numpy code.
"""

from __future__ import annotations

import math

import numpy as np

from stages.lib.numpy_rules import clip as _clip
from stages.lib.numpy_rules import maximum as _max
from stages.lib.numpy_rules import minimum as _min

NUMPY_RULES_SHA256 = "5c754381d8698fbd"
"""The first 16 hex digits of stages/lib/numpy_rules.py's sha256 the kernels here were written against: numba's cache
of this module does not notice edits of that file, so an edit there must change this line too (which renews the cache;
tests/stages/test_intentions.py checks it)."""

try:  # pragma: no cover - exercised where numba is missing only
    import numba

    if numba.config.DISABLE_JIT:  # NUMBA_DISABLE_JIT=1: the numpy reference path, not these kernels run as Python
        raise ImportError("NUMBA_DISABLE_JIT is set")
except Exception:  # noqa: BLE001 - any import failure leaves the numpy path
    numba = None

S_CLIP_M = 1.0e4
"""Arc lengths are clipped to ±this before the search (`tables.PairTables.locate`)."""


def available() -> bool:
    """True when the compiled kernels can be used."""
    return numba is not None


def _locate_one(key, start, end, s_line, g, s_m, key_offset):
    """(i, t, clipped s) of one particle: ``np.searchsorted(key, s + g·offset, 'right') − 1`` clipped to the pair's
    segments, and the fraction along segment i (`tables.PairTables.locate`)."""
    s = _clip(s_m, -S_CLIP_M, S_CLIP_M)
    value = s + g * key_offset
    lo = 0
    hi = key.shape[0]
    while lo < hi:  # numpy's binary search, side "right": first index whose key is greater (NaN greatest)
        mid = lo + ((hi - lo) >> 1)
        k = key[mid]
        if value < k or (k != k and value == value):
            hi = mid
        else:
            lo = mid + 1
    i = lo - 1
    first = start[g]
    last = end[g] - 2
    if i < first:
        i = first
    if i > last:
        i = last
    t = (s - s_line[i]) / (s_line[i + 1] - s_line[i])
    return i, t, s


def _pose(key, start, end, s_line, x_line, y_line, h_line, g, s_m, d_m, key_offset, out_x, out_y, out_h):
    """`tables.PairTables.pose` of flat particles g, s_m, d_m (n,) into out_x, out_y, out_h (n,)."""
    for n in range(g.shape[0]):
        i, t, _s = _locate_one(key, start, end, s_line, g[n], s_m[n], key_offset)
        x = x_line[i] + t * (x_line[i + 1] - x_line[i])
        y = y_line[i] + t * (y_line[i + 1] - y_line[i])
        tc = _clip(t, 0.0, 1.0)
        heading = h_line[i] + tc * (h_line[i + 1] - h_line[i])
        d = d_m[n]
        out_x[n] = x - d * math.sin(heading)
        out_y[n] = y + d * math.cos(heading)
        out_h[n] = heading


def _gaussian_errors(x, y, heading, v, x_obs, y_obs, heading_obs, heading_ok, speed_obs, speed_ok, n_per_row,
                     position_var, heading_sigma, speed_sigma, out):
    """`model.log_likelihood` of flat particles (n,) (rows of `n_per_row`) from their poses x, y, heading and speeds v,
    the measurements (rows,), into out (n,): numpy's operations element by element (``x ** 2`` is ``x * x``; the wrap
    is ``(a + pi) % (2 pi) - pi``, Python's float modulo being numpy's; a term left out subtracts 0.0)."""
    two_pi = 2.0 * math.pi
    for n in range(x.shape[0]):
        r = n // n_per_row
        dx = x[n] - x_obs[r]
        dy = y[n] - y_obs[r]
        value = -0.5 * (dx * dx + dy * dy) / position_var
        ok = heading_ok[r]
        error = ((heading_obs[r] if ok else 0.0) - heading[n] + math.pi) % two_pi - math.pi
        q = error / heading_sigma
        value = value - (0.5 * (q * q) if ok else 0.0)
        ok = speed_ok[r]
        error = (speed_obs[r] if ok else 0.0) - v[n]
        q = error / speed_sigma
        out[n] = value - (0.5 * (q * q) if ok else 0.0)


def _switch_routes(route, s_m, n_slots, first_pair, switch_s, u_switch, u_choice, per_step, n_max, n_pairs, new_route, new_s):
    """`model.switch_routes` of particles route, s_m (V, N) into new_route, new_s; 1 if any particle switched, 0 if none,
    -1 where the numpy path must decide (a slot outside the vehicle's corridors)."""
    n_rows, n = route.shape
    eligible = np.zeros(n_max, np.bool_)
    order = np.empty(n_max, np.int64)
    rank = np.empty(n_max, np.int64)
    moved = 0
    for v in range(n_rows):
        first = first_pair[v]
        count = 0
        for k in range(n_max):
            pair = min(first + k, n_pairs - 1)
            ok = k < n_slots[v] and math.isfinite(switch_s[pair])
            eligible[k] = ok
            count += ok
        i = 0  # eligible slots first, in slot order (np.argsort(~eligible, kind="stable")), then the others
        for k in range(n_max):
            if eligible[k]:
                order[i] = k
                i += 1
        for k in range(n_max):
            if not eligible[k]:
                order[i] = k
                i += 1
        for i in range(n_max):
            rank[order[i]] = i
        cap = max(count - 2, 0)
        for m in range(n):
            r = route[v, m]
            if r < 0 or r >= n_max:
                return -1
            new_route[v, m] = r
            new_s[v, m] = s_m[v, m]
            if not (u_switch[v, m] < per_step[v]) or not eligible[r] or count < 2:
                continue
            j = min(int(u_choice[v, m] * (count - 1)), cap)
            if j >= rank[r]:
                j += 1
            to = order[min(j, n_max - 1)]
            new_route[v, m] = to
            new_s[v, m] = s_m[v, m] - switch_s[first + r] + switch_s[first + to]
            moved = 1
    return moved


def _pair_sums(g, w, values, stop, mass, count, sums, squares, stop_sum):
    """Per pair (bin of `g`): sum of w, count, sum of w·x and of (w·x)·x for each row x of `values` (F, n), sum of
    w·stop, each added particle by particle in order (``np.bincount(g, weights)``: out[g[i]] += weights[i])."""
    for i in range(g.shape[0]):
        k = g[i]
        wi = w[i]
        mass[k] += wi
        count[k] += 1
        for f in range(values.shape[0]):
            x = values[f, i]
            wx = wi * x
            sums[f, k] += wx
            squares[f, k] += wx * x
        stop_sum[k] += wi * (1.0 if stop[i] else 0.0)


def _admissible_speed(key, start, end, s_line, v_adm, g, s_m, style, key_offset, out):
    """`tables.PairTables.admissible_speed` of flat particles g, s_m, style (n,) into out (n,)."""
    for n in range(g.shape[0]):
        i, t, _s = _locate_one(key, start, end, s_line, g[n], s_m[n], key_offset)
        tc = _clip(t, 0.0, 1.0)
        j = style[n]
        v0 = v_adm[j, i]
        out[n] = v0 + tc * (v_adm[j, i + 1] - v0)


def _admissible_speeds(s_line, kappa_line, start, length, width, limit, lat, brake, smoothing, min_curvature, out):
    """`tables.admissible_speeds` of the pairs' concatenated samples (T,) into out (J, T), as the numpy path computes
    them on rows padded to `width`: the moving average over the padded rows' cumulative sums (the padding width the
    widest window's), then the reverse cumulative minimum of v_prof² + 2b·s."""
    n_pairs = start.shape[0]
    half = np.zeros(n_pairs, np.int64)
    h = 0
    for g in range(n_pairs):
        n = length[g]
        last = n - 1 if n - 1 > 0 else 0
        step = 1.0
        if n > 1:
            step = (s_line[start[g] + last] - s_line[start[g]]) / (last if last > 1 else 1)
        q = 0.5 * smoothing / _max(step, 1e-3)
        half[g] = np.int64(_clip(np.rint(q), 0.0, float(width)))
        if half[g] > h:
            h = half[g]
    smooth = smoothing > 0 and h > 0
    row = np.empty(width)
    padded = np.empty(width + 2 * h + 1)
    csum = np.empty(width + 2 * h + 2)
    n_styles = lat.shape[0]
    two_b = 2.0 * brake
    for g in range(n_pairs):
        n = length[g]
        a = start[g]
        for c in range(n):
            k = abs(kappa_line[a + c])
            row[c] = k if math.isfinite(k) else 0.0
        fill = row[n - 1] if n > 0 else 0.0
        for c in range(n, width):
            row[c] = fill
        if smooth:
            for c in range(h):
                padded[c] = row[0]
            for c in range(width):
                padded[h + c] = row[c]
            for c in range(h + 1):
                padded[h + width + c] = row[width - 1]
            csum[0] = 0.0
            total = 0.0
            for c in range(width + 2 * h + 1):
                total = total + padded[c]
                csum[c + 1] = total
            w = half[g]
            for c in range(n):
                row[c] = (csum[c + h + w + 1] - csum[c + h - w]) / (2 * w + 1)
        for j in range(n_styles):
            run = np.inf
            for c in range(n - 1, -1, -1):
                k = row[c]
                v = math.sqrt(lat[j] / _max(k, min_curvature))
                v = _min(limit[g], v)
                key = v * v + two_b * s_line[a + c]
                run = _min(run, key)
                x = run - two_b * s_line[a + c]
                out[j, a + c] = math.sqrt(_max(x, 0.0))


def _intend_and_move(n_per_row, g, s_m, v_mps, a_mps2, d_m, stop, style, p_expected, p_e, u_intent, n_accel, n_lateral,
                     active, dt, keep, adapt, pull, jerk, decay, lateral, key, start, end, s_line, v_adm, stop_s_m, key_offset,
                     go_gain, go_sigma, stop_sigma, stop_margin, stop_min_distance, a_min, a_max, floor, relax):
    """`model.propagate` after the route switches, per particle (flat (V·N,) arrays, per-row values (V,)): the intention
    I from P(E = stop) `p_e`, then Φ; writes stop, p_expected, s_m, v_mps, a_mps2 and d_m in place."""
    for n in range(g.shape[0]):
        r = n // n_per_row
        on = active[r]
        pe = p_e[n]
        if stop[n]:
            p_stop = pe * keep[r] + (1.0 - pe) * (1.0 - adapt[r])
        else:
            p_stop = pe * adapt[r] + (1.0 - pe) * (1.0 - keep[r])
        p_stop = _clip(p_stop, floor, 1.0 - floor)
        if on:
            stop[n] = u_intent[n] < p_stop
            p_expected[n] = pe
        s = s_m[n]
        v = v_mps[n]
        i, t, _s = _locate_one(key, start, end, s_line, g[n], s, key_offset)
        tc = _clip(t, 0.0, 1.0)
        j = style[n]
        v0 = v_adm[j, i]
        target_go = go_gain * ((v0 + tc * (v_adm[j, i + 1] - v0)) - v)
        to_stop = stop_s_m[g[n]] - s
        has_stop = math.isfinite(to_stop)
        target_stop = -(v * v) / (2.0 * _max((to_stop if has_stop else 1.0) - stop_margin, stop_min_distance))
        stopping = stop[n] and has_stop
        noise = n_accel[n]
        if relax:
            target = _max(target_stop, a_min) if stopping else target_go
            a_old = a_mps2[n]
            a = a_old + pull[r] * (target - a_old) + jerk[r] * noise
            if stopping:
                a = _min(a, 0.0)
        elif stopping:
            a = _clip(target_stop + stop_sigma * noise, a_min, 0.0)
        else:
            a = target_go + go_sigma * noise
        a = _clip(a, a_min, a_max)
        step = dt[r]
        moving = _min(step, v / _max(-a, 1e-9)) if a < 0.0 else step
        s_m[n] = s + v * moving + 0.5 * a * (moving * moving)
        v_mps[n] = _max(v + a * step, 0.0)
        if on:
            a_mps2[n] = a
        d_m[n] = decay[r] * d_m[n] + lateral[r] * n_lateral[n]


def _conflict_gaps(g, s_m, v_mps, conflict_s, other_time, weight, has_conflict, min_speed, fill, out_gap, out_weight, out_owner):
    """`model.expected_stop`'s conflicts ahead, in numpy's order (particle by particle, conflict by conflict): the gap
    T' − T_e, the route weight and the particle of each; returns their count (with ``fill`` False: only counts)."""
    m = 0
    n_conflicts = conflict_s.shape[1]
    for n in range(g.shape[0]):
        gn = g[n]
        if not has_conflict[gn]:
            continue
        s = s_m[n]
        speed = _max(v_mps[n], min_speed)
        for c in range(n_conflicts):
            cs = conflict_s[gn, c]
            ahead = cs - s
            if math.isfinite(cs) and ahead > 0.0:
                if fill:
                    out_gap[m] = other_time[gn, c] - ahead / speed
                    out_weight[m] = weight[gn, c]
                    out_owner[m] = n
                m += 1
    return m


def _stop_from_factors(owner, factor, out):
    """P(E = stop) = 1 − the product of each particle's factors in order (np.prod's sequential product: the factors of
    1 it multiplies in elsewhere change nothing) into out (n,)."""
    product = np.ones(out.shape[0])
    for k in range(owner.shape[0]):
        product[owner[k]] = product[owner[k]] * factor[k]
    for n in range(out.shape[0]):
        out[n] = 1.0 - product[n]


if numba is not None:
    _jit = numba.njit(cache=True, nogil=True, fastmath=False, boundscheck=False)
    _locate_one = _jit(_locate_one)
    _pose_compiled = _jit(_pose)
    _gaussian_errors_compiled = _jit(_gaussian_errors)
    _switch_routes_compiled = _jit(_switch_routes)
    _pair_sums_compiled = _jit(_pair_sums)
    _admissible_speed_compiled = _jit(_admissible_speed)
    _admissible_speeds_compiled = _jit(_admissible_speeds)
    _intend_and_move_compiled = _jit(_intend_and_move)
    _conflict_gaps_compiled = _jit(_conflict_gaps)
    _stop_from_factors_compiled = _jit(_stop_from_factors)
else:  # pragma: no cover
    _conflict_gaps_compiled = None
    _stop_from_factors_compiled = None
    _intend_and_move_compiled = None
    _admissible_speeds_compiled = None
    _pose_compiled = None
    _gaussian_errors_compiled = None
    _switch_routes_compiled = None
    _pair_sums_compiled = None
    _admissible_speed_compiled = None


def _flat(*arrays):
    """The arrays broadcast to one shape, each as a contiguous 1-D array, and that shape."""
    b = np.broadcast_arrays(*arrays)
    return [np.ascontiguousarray(a).reshape(-1) for a in b], b[0].shape


def pose(tables, g: np.ndarray, s_m: np.ndarray, d_m: np.ndarray, key_offset_m: float):
    """(x, y, heading) as `tables.PairTables.pose` computes them; None: take the numpy path."""
    if _pose_compiled is None:
        return None
    (gf, sf, df), shape = _flat(np.asarray(g, dtype=np.int64), np.asarray(s_m, dtype=np.float64), np.asarray(d_m, dtype=np.float64))
    out_x, out_y, out_h = np.empty(gf.size), np.empty(gf.size), np.empty(gf.size)
    _pose_compiled(tables.key, tables.start, tables.end, tables.s_m, tables.x_m, tables.y_m, tables.heading_rad, gf, sf, df,
                   float(key_offset_m), out_x, out_y, out_h)
    return out_x.reshape(shape), out_y.reshape(shape), out_h.reshape(shape)


def gaussian_errors(x, y, heading, v, z, position_sigma_m: float, heading_sigma_rad: float, speed_sigma_mps: float):
    """`model.log_likelihood`'s sum of terms from poses x, y, heading and speeds v (V, N) and the measurements `z` =
    (x, y, heading, speed, heading_ok, speed_ok) (V,); None: take the numpy path (no numba, other shapes or dtypes)."""
    if _gaussian_errors_compiled is None:
        return None
    x_obs, y_obs, heading_obs, speed_obs, heading_ok, speed_ok = (np.asarray(a) for a in z)
    arrays = (x, y, heading, v)
    if any(type(a) is not np.ndarray or a.dtype != np.float64 or a.ndim != 2 or a.shape != x.shape for a in arrays):
        return None
    rows = (x.shape[0],)
    if any(a.dtype != np.float64 or a.shape != rows for a in (x_obs, y_obs, heading_obs, speed_obs)):
        return None
    if any(a.dtype != np.bool_ or a.shape != rows for a in (heading_ok, speed_ok)):
        return None
    out = np.empty(x.shape)
    flat = [np.ascontiguousarray(a).reshape(-1) for a in arrays]
    _gaussian_errors_compiled(*flat, *(np.ascontiguousarray(a) for a in (x_obs, y_obs, heading_obs, heading_ok, speed_obs, speed_ok)),
                              max(x.shape[1], 1), float(position_sigma_m) ** 2, float(heading_sigma_rad), float(speed_sigma_mps),
                              out.reshape(-1))
    return out


def switch_routes(route, s_m, tables, first_pair, u_switch, u_choice, per_step, n_max: int):
    """`model.switch_routes` after its early return: (new route, new s) (V, N) when a particle switches, () when none
    does; None: take the numpy path (no numba, other dtypes or shapes, a slot outside the vehicle's corridors)."""
    if _switch_routes_compiled is None:
        return None
    shape = route.shape
    if route.dtype != np.int64 or s_m.dtype != np.float64 or route.ndim != 2 or s_m.shape != shape:
        return None
    u_switch = np.asarray(u_switch, dtype=np.float64)
    u_choice = np.asarray(u_choice, dtype=np.float64)
    if u_switch.shape != shape or u_choice.shape != shape or tables.switch_s_m.dtype != np.float64:
        return None
    new_route = np.empty(shape, np.int64)
    new_s = np.empty(shape)
    moved = _switch_routes_compiled(
        np.ascontiguousarray(route), np.ascontiguousarray(s_m), np.ascontiguousarray(tables.n_slots, dtype=np.int64),
        np.ascontiguousarray(first_pair, dtype=np.int64), np.ascontiguousarray(tables.switch_s_m), np.ascontiguousarray(u_switch),
        np.ascontiguousarray(u_choice), np.ascontiguousarray(per_step, dtype=np.float64), int(n_max), int(tables.n_pairs), new_route, new_s)
    if moved < 0:
        return None
    return (new_route, new_s) if moved else ()


def pair_sums(g: np.ndarray, w: np.ndarray, values: list[np.ndarray], stop: np.ndarray, n_pairs: int):
    """(mass, count, sums (F, G), squares (F, G), stop sum) of flat particles g (int64), w, each of `values` (float64)
    and stop (bool), (n,) each: what ``np.bincount(g, w)``, ``np.bincount(g)``, ``np.bincount(g, w * x)``,
    ``np.bincount(g, w * x * x)`` and ``np.bincount(g, w * stop)`` give with minlength `n_pairs`; None: numpy."""
    if _pair_sums_compiled is None:
        return None
    n = g.shape[0]
    if (g.dtype != np.int64 or w.dtype != np.float64 or stop.dtype != np.bool_ or g.ndim != 1 or w.shape != (n,) or stop.shape != (n,)
            or any(x.dtype != np.float64 or x.shape != (n,) for x in values)):
        return None
    if not n or int(g.min()) < 0 or int(g.max()) >= n_pairs:
        return None  # bincount would grow (or refuse), or answer int64 zeros for no particles: numpy
    stacked = np.stack(values) if values else np.zeros((0, n))
    mass, count = np.zeros(n_pairs), np.zeros(n_pairs, np.int64)
    sums, squares, stop_sum = np.zeros((len(values), n_pairs)), np.zeros((len(values), n_pairs)), np.zeros(n_pairs)
    _pair_sums_compiled(np.ascontiguousarray(g), np.ascontiguousarray(w), stacked, np.ascontiguousarray(stop), mass, count, sums,
                        squares, stop_sum)
    return mass, count, sums, squares, stop_sum


def admissible_speed(tables, g: np.ndarray, s_m: np.ndarray, style: np.ndarray, key_offset_m: float):
    """v_adm as `tables.PairTables.admissible_speed` computes it; None: take the numpy path."""
    if _admissible_speed_compiled is None:
        return None
    (gf, sf, jf), shape = _flat(np.asarray(g, dtype=np.int64), np.asarray(s_m, dtype=np.float64), np.asarray(style, dtype=np.int64))
    out = np.empty(gf.size)
    _admissible_speed_compiled(tables.key, tables.start, tables.end, tables.s_m, np.ascontiguousarray(tables.v_adm_mps), gf, sf, jf,
                               float(key_offset_m), out)
    return out.reshape(shape)


def admissible_speeds(s_line, kappa_line, lengths, limits, lat_accels_mps2, brake_mps2: float, smoothing_m: float, min_curvature_1pm: float):
    """`tables.admissible_speeds` of the pairs' concatenated arc lengths and curvatures (T,) as (J, T), its valid
    samples; None: take the numpy path (no numba, or curvatures and arc lengths of different sizes)."""
    if _admissible_speeds_compiled is None:
        return None
    s_line = np.ascontiguousarray(s_line, dtype=np.float64)
    kappa_line = np.ascontiguousarray(kappa_line, dtype=np.float64)
    lengths = np.asarray(lengths, dtype=np.int64)
    if s_line.shape != kappa_line.shape or s_line.ndim != 1 or int(lengths.sum()) != s_line.size or (lengths < 0).any():
        return None
    lat = np.ascontiguousarray(lat_accels_mps2, dtype=np.float64).reshape(-1)
    start = np.zeros(lengths.size, np.int64)
    np.cumsum(lengths[:-1], out=start[1:])
    width = int(lengths.max()) if lengths.size else 0
    out = np.empty((lat.size, s_line.size))
    _admissible_speeds_compiled(s_line, kappa_line, start, lengths, width, np.ascontiguousarray(limits, dtype=np.float64), lat,
                                float(brake_mps2), float(smoothing_m), float(min_curvature_1pm), out)
    return out


def intend_and_move(p, tables, g, p_e, u_intent, n_accel, n_lateral, active, dt, per_row, mp, key_offset_m: float) -> bool:
    """`model.propagate`'s intention and motion update of the particles `p` (V, N) on pairs `g` (V, N), in place (new
    arrays for the fields it changes); `per_row` = (keep, adapt, pull, jerk, decay, lateral), each (V,). False: numpy."""
    if _intend_and_move_compiled is None:
        return False
    shape = p.s_m.shape
    n_rows, n_per_row = shape

    def flat(x, dtype):
        return np.ascontiguousarray(np.broadcast_to(np.asarray(x, dtype=dtype), shape)).reshape(-1)

    fields = {name: np.array(getattr(p, name), dtype=dtype, copy=True).reshape(-1) for name, dtype in (
        ("s_m", np.float64), ("v_mps", np.float64), ("a_mps2", np.float64), ("d_m", np.float64), ("stop", np.bool_),
        ("p_expected_stop", np.float64))}
    rows = [np.ascontiguousarray(np.broadcast_to(np.asarray(x, dtype=np.float64).reshape(-1), (n_rows,))) for x in per_row]
    _intend_and_move_compiled(
        n_per_row, flat(g, np.int64), fields["s_m"], fields["v_mps"], fields["a_mps2"], fields["d_m"], fields["stop"],
        flat(p.style, np.int64), fields["p_expected_stop"], flat(p_e, np.float64), flat(u_intent, np.float64),
        flat(n_accel, np.float64), flat(n_lateral, np.float64), np.ascontiguousarray(active, dtype=np.bool_),
        np.ascontiguousarray(dt, dtype=np.float64), *rows,
        tables.key, tables.start, tables.end, tables.s_m, np.ascontiguousarray(tables.v_adm_mps), tables.stop_s_m, float(key_offset_m),
        float(mp.go_gain_per_s), float(mp.go_accel_sigma_mps2), float(mp.stop_accel_sigma_mps2), float(mp.stop_margin_m),
        float(mp.stop_min_distance_m), float(mp.accel_min_mps2), float(mp.accel_max_mps2), float(mp.intention_floor),
        bool(mp.accel_relaxation_s > 0.0),
    )
    for name, value in fields.items():
        setattr(p, name, value.reshape(shape))
    return True


def conflict_stop(tables, g, s_m, v_mps, min_speed_mps: float, factors):
    """`model.expected_stop`'s P(E = stop) from the priority conflicts, of particles g, s_m, v_mps (one shape): the
    conflicts ahead found and the products taken here, ``factors(gap, weight)`` (numpy: the sigmoids) in between;
    None: take the numpy path."""
    if _conflict_gaps_compiled is None:
        return None
    (gf, sf, vf), shape = _flat(np.asarray(g, dtype=np.int64), np.asarray(s_m, dtype=np.float64), np.asarray(v_mps, dtype=np.float64))
    conflict_s = np.ascontiguousarray(tables.conflict_s_m, dtype=np.float64)
    other = np.ascontiguousarray(tables.conflict_other_time_s, dtype=np.float64)
    weight = np.ascontiguousarray(tables.conflict_weight, dtype=np.float64)
    has_conflict = np.isfinite(conflict_s).any(axis=1)
    args = (gf, sf, vf, conflict_s, other, weight, has_conflict, float(min_speed_mps))
    count = _conflict_gaps_compiled(*args, False, np.empty(0), np.empty(0), np.empty(0, np.int64))
    gap, w, owner = np.empty(count), np.empty(count), np.empty(count, np.int64)
    _conflict_gaps_compiled(*args, True, gap, w, owner)
    out = np.empty(gf.size)
    _stop_from_factors_compiled(owner, np.ascontiguousarray(factors(gap, w), dtype=np.float64), out)
    return out.reshape(shape)


_warm = False


def warm_up() -> None:
    """Load the kernels from numba's on-disk cache (compile them the first time) now, on a one-pair table: the stage
    pays it when it starts, not on its first frame. Once per process."""
    global _warm
    if _warm or numba is None:
        return
    from types import SimpleNamespace

    class _Table:
        key = np.array([0.0, 1.0, 2.0])
        start = np.zeros(1, np.int64)
        end = np.full(1, 3, np.int64)
        s_m = key
        x_m = key
        y_m = np.zeros(3)
        heading_rad = np.zeros(3)
        v_adm_mps = np.ones((1, 3))
        stop_s_m = np.full(1, np.nan)

    one = np.zeros((1, 1), np.int64)
    pose(_Table, one, np.full((1, 1), 0.5), np.zeros((1, 1)), 1.0e6)
    admissible_speed(_Table, one, np.full((1, 1), 0.5), one, 1.0e6)
    admissible_speeds(np.arange(3.0), np.zeros(3), np.array([3]), np.ones(1), (1.0,), 1.0, 1.0, 1e-4)
    zero = np.zeros((1, 1))
    particles = SimpleNamespace(s_m=zero + 0.5, v_mps=zero, a_mps2=zero, d_m=zero, stop=zero > 0, style=one, p_expected_stop=zero)
    params = SimpleNamespace(go_gain_per_s=1.0, go_accel_sigma_mps2=1.0, stop_accel_sigma_mps2=1.0, stop_margin_m=1.0, stop_min_distance_m=1.0,
                             accel_min_mps2=-1.0, accel_max_mps2=1.0, intention_floor=0.0, accel_relaxation_s=0.0)
    per_row = tuple(np.zeros(1) for _ in range(6))
    intend_and_move(particles, _Table, one, zero, zero, zero, zero, np.ones(1, bool), np.zeros(1), per_row, params, 1.0e6)
    _Table.conflict_s_m = np.ones((1, 1))
    _Table.conflict_other_time_s = np.ones((1, 1))
    _Table.conflict_weight = np.ones((1, 1))
    conflict_stop(_Table, one, zero, zero, 1.0, lambda gap, w: 1.0 - w * gap)
    row, yes = np.zeros(1), np.ones(1, bool)
    gaussian_errors(zero, zero, zero, zero, (row, row, row, row, yes, yes), 1.0, 1.0, 1.0)
    _Table.n_slots = np.array([2])
    _Table.switch_s_m = np.zeros(2)
    _Table.n_pairs = 2
    switch_routes(one, zero, _Table, np.zeros(1, np.int64), zero, zero, np.ones(1), 2)
    pair_sums(np.zeros(1, np.int64), np.ones(1), [np.zeros(1)] * 3, np.zeros(1, bool), 1)
    _warm = True
