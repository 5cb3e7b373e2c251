"""Compiled (numba) kernels of the numpy backend's hot path (docs/method.md §3.5).

One call of ``fused_step`` does what the scipy path of
``stages.lib.markov.propagate`` does with two CSR products, two marginals,
the leak and the pruning, in one pass over the *occupied* states of the
slab only:

- p⁻ = Υ(τ) p (time point) on the slab ``(L, M, N_v, B)``; mass moved past
  the window's last cell ``n_s`` is the leak (B,);
- the position marginal (L, B) of Υ([0, τ]) p (interval; only when asked)
  and its leak;
- the position (L, B) and velocity (N_v, B) marginals of p⁻;
- pruning of p⁻ (entries below ``threshold`` set to 0) and the pair totals
  before and after it.

A source row (s, α, v) whose B entries are all zero is skipped, so the cost
grows with the occupied states (a few percent of the window), not with the
window. The B pairs are the innermost (contiguous) axis: every stencil entry
is one vectorisable axpy over the pairs.

``priority_occupied`` applies Γ = colnorm(diag(λ) Ψ) at given occupied
states (the hybrid mode's speed restriction, ``InputPriority.at_states``)
without BLAS calls: on a small machine BLAS's worker threads cost more than
the products.

``speed_priority_run`` is the hybrid mode's whole chain (every step, its
speed restriction and Γ) in one call: the same arithmetic in the same order
as ``fused_step`` + ``priority_occupied`` step by step (the same numbers),
but in blocks of 8 similar pairs, each block on the cells its own pairs
occupy instead of the batch's window, which spans every pair's; the blocks
are independent and may be shared out between threads (``threads``; the
kernel releases the GIL), with the same numbers. Its 8-lane inner
operations (stencil scatter, marginals and pruning, the test for mass) are written as explicit
vector operations (``_axpy8``, ``_scatter8``, ``_prune8``, ``_has_mass8``): numba leaves its SLP vectoriser
off, and loops of 8 constant iterations then run scalar. ``_scatter8`` runs a source row's whole
stencil (its entries' targets relative to the row tabulated once per call) with the row's 8 lanes
loaded once; the rows that may leak past the window's end take the per-entry path.
The motion grid's rasterising and fusion kernels are in ``frame_kernels``.

numba is a dependency; ``available()`` is False only where it cannot be
imported, and the backend then uses the scipy path (the reference the tests
compare against).
"""

from __future__ import annotations

import concurrent.futures
import itertools
import os
import threading

import numpy as np

try:  # pragma: no cover - exercised where numba is missing only
    import numba

    if numba.config.DISABLE_JIT:  # NUMBA_DISABLE_JIT=1: the numpy reference path, not these kernels run as Python
        raise ImportError("NUMBA_DISABLE_JIT is set")

    _NUMBA_ERROR: str | None = None
except Exception as exc:  # noqa: BLE001 - any import failure leaves the scipy path
    numba = None
    _NUMBA_ERROR = f"{type(exc).__name__}: {exc}"

from stages.lib.numpy_rules import maximum as _max
from stages.lib.numpy_rules import minimum as _min
from stages.lib.numpy_rules import PAIRWISE_BLOCK
from stages.lib.numpy_rules import pairwise_sum as _pairwise_sum

NUMPY_RULES_SHA256 = "5c754381d8698fbd"
"""The first 16 hex digits of stages/lib/numpy_rules.py's sha256 the kernels here were written against: numba's cache
does not notice edits there, a test (tests/stages/test_intentions.py) compares it."""


def available() -> bool:
    """True when the compiled kernels can be used."""
    return numba is not None


def unavailable_reason() -> str | None:
    return _NUMBA_ERROR


def stencil_tables(kernel: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The non-zero entries of a kernel ``W[α, j′, j, d]`` grouped by source (α, j), CSR-like.

    Returns ``ptr`` ((M·N_v + 1,) int64: the entries of source row α·N_v + j
    are ptr[r]:ptr[r+1]), ``v_to``, ``offset`` (int64) and ``weight`` (float32).
    """
    n_in, n_v, _, _ = kernel.shape
    src = np.transpose(kernel, (0, 2, 1, 3))  # (α, j source, j′ target, d)
    a, j, jt, d = np.nonzero(src)
    rows = a * n_v + j
    order = np.lexsort((d, jt, rows))
    rows, jt, d = rows[order], jt[order], d[order]
    weight = src[a[order], j[order], jt, d].astype(np.float32)
    ptr = np.zeros(n_in * n_v + 1, np.int64)
    np.add.at(ptr, rows + 1, 1)
    return np.cumsum(ptr), jt.astype(np.int64), d.astype(np.int64), weight


def collapsed_tables(kernel: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``W`` summed over the target velocity, per source (α, j): ``ptr``, ``offset``, ``weight`` (position only)."""
    n_in, n_v, _, n_d = kernel.shape
    per = kernel.sum(axis=1).reshape(n_in * n_v, n_d)  # (α·N_v + j, d)
    rows, d = np.nonzero(per)
    weight = per[rows, d].astype(np.float32)
    ptr = np.zeros(n_in * n_v + 1, np.int64)
    np.add.at(ptr, rows + 1, 1)
    return np.cumsum(ptr), d.astype(np.int64), weight


#: pairs per block of ``speed_priority_run``'s kernel (its innermost, vectorised axis: 8 float32 lanes of AVX2; its
#: stencil scatter is written for 8, ``_axpy8``). 16 measured no faster at 18 and 72 vehicles and slower at 6
_LANES = 8

if numba is not None:

    @numba.njit(cache=True, nogil=True, fastmath=True, boundscheck=False)
    def _occupied_rows(slab):  # pragma: no cover - compiled
        """(L, M, N_v) bool: rows with any mass (entries are >= 0: a row is empty iff its sum is 0; the sum vectorises,
        an early exit on the first non-zero entry does not and costs ~10x more)."""
        n_l, n_in, n_v, n_b = slab.shape
        flat = slab.reshape(n_l * n_in * n_v, n_b)
        rows = np.empty(n_l * n_in * n_v, np.bool_)
        for r in range(flat.shape[0]):
            acc = np.float32(0.0)
            for b in range(n_b):
                acc += flat[r, b]
            rows[r] = acc > 0
        return rows.reshape(n_l, n_in, n_v)

    @numba.njit(cache=True, nogil=True, boundscheck=False)
    def _marked_indices(mark, n):  # pragma: no cover - compiled
        """The (s, v, b) indices of the n marked cells of mark (n_l, n_v, n_b), in (s, v, b) order
        (np.nonzero's order)."""
        n_l, n_v, n_b = mark.shape
        s_idx = np.empty(n, np.int64)
        v_idx = np.empty(n, np.int64)
        b_idx = np.empty(n, np.int64)
        i = 0
        for s in range(n_l):
            for v in range(n_v):
                for b in range(n_b):
                    if mark[s, v, b]:
                        s_idx[i], v_idx[i], b_idx[i] = s, v, b
                        i += 1
        return s_idx, v_idx, b_idx

    @numba.njit(cache=True, nogil=True, fastmath=False, boundscheck=False)
    def _fused_step(slab, src_lo, lo, n_l, n_s, ptr, v_to, offset, weight, iptr, ioffset, iweight, with_interval, threshold):  # pragma: no cover - compiled
        n_src, n_in, n_v, n_b = slab.shape
        out = np.zeros((n_l, n_in, n_v, n_b), np.float32)
        # sums over many states accumulate in float64 (sequential float32 sums of ~10⁴ terms drift by ~1e-6)
        leaked = np.zeros(n_b, np.float64)
        ipos = np.zeros((n_l, n_b), np.float64)
        ileaked = np.zeros(n_b, np.float64)
        occupied = _occupied_rows(slab)
        moved = src_lo - lo  # the slab's cells in the output window: the window only moves forward, over empty cells
        for s in range(n_src):
            for a in range(n_in):
                for v in range(n_v):
                    if not occupied[s, a, v]:
                        continue
                    row = slab[s, a, v]
                    r = a * n_v + v
                    for e in range(ptr[r], ptr[r + 1]):
                        t = s + moved + offset[e]
                        w = weight[e]
                        if t < n_l:
                            target = out[t, a, v_to[e]]
                            for b in range(n_b):
                                target[b] += w * row[b]
                        elif lo + t >= n_s:
                            for b in range(n_b):
                                leaked[b] += w * row[b]
                    if with_interval:
                        for e in range(iptr[r], iptr[r + 1]):
                            t = s + moved + ioffset[e]
                            w = iweight[e]
                            if t < n_l:
                                target = ipos[t]
                                for b in range(n_b):
                                    target[b] += w * row[b]
                            elif lo + t >= n_s:
                                for b in range(n_b):
                                    ileaked[b] += w * row[b]
        pos = np.zeros((n_l, n_b), np.float64)
        vel = np.zeros((n_v, n_b), np.float64)
        kept = np.zeros(n_b, np.float64)
        mark = np.zeros((n_l, n_v, n_b), np.uint8)  # (s, v, pair) holding mass after pruning
        for t in range(n_l):
            for a in range(n_in):
                for v in range(n_v):
                    row = out[t, a, v]
                    marks = mark[t, v]
                    for b in range(n_b):  # branch-free: it vectorises over the pairs
                        x = row[b]
                        pos[t, b] += x
                        vel[v, b] += x
                        y = x if x >= threshold else np.float32(0.0)
                        row[b] = y
                        kept[b] += y
                        marks[b] |= y > 0
        n_marked = 0
        for t in range(n_l):
            for v in range(n_v):
                for b in range(n_b):
                    n_marked += mark[t, v, b]
        s_idx, v_idx, b_idx = _marked_indices(mark, n_marked)
        f32 = np.float32
        return out, leaked.astype(f32), pos.astype(f32), vel.astype(f32), ipos.astype(f32), ileaked.astype(f32), kept.astype(f32), s_idx, v_idx, b_idx

    @numba.njit(cache=True, nogil=True, boundscheck=False)
    def _priority_occupied(slab, s_idx, v_idx, b_idx, lam, psi, factors):  # pragma: no cover - compiled
        """The products run input by input over all the states at once (the inner loops over the states vectorise;
        per state they would be 10-long); each state's sums are taken in the same order as per state."""
        n_l, n_in, n_v, n_b = slab.shape
        n = s_idx.shape[0]
        out = np.zeros(slab.shape, np.float32)
        lam_t = np.ascontiguousarray(lam.T)  # (M, n)
        x = np.empty((n_in, n), np.float32)
        for i in range(n):
            for j in range(n_in):
                x[j, i] = slab[s_idx[i], j, v_idx[i], b_idx[i]]
        ratio = np.empty((n_in, n), np.float32)
        z = np.empty(n, np.float32)
        acc = np.empty(n, np.float32)
        f = np.empty(n, np.float32)
        for i in range(n):
            f[i] = factors[b_idx[i]]
        for a in range(n_in):  # out[a] = λ[a] · Σ_j Ψ[a, j] ratio[j] · factor
            _gamma_input(a, x, lam_t, psi, n, z, ratio, acc)
            la = lam_t[a]
            for i in range(n):
                out[s_idx[i], a, v_idx[i], b_idx[i]] = la[i] * acc[i] * f[i]
        return out

    @numba.njit(cache=True, nogil=True, boundscheck=False)
    def _gamma_input(a, x, lam_t, psi, n, z, ratio, acc):  # pragma: no cover - compiled
        """Γ over the first ``n`` states, columns of ``x`` (p⁻, (M, ≥n)) and ``lam_t`` (λ, (M, ≥n)): at ``a == 0``
        ``ratio[j] = p⁻[j] / Z[j]`` (0 where Z[j] = 0), Z[j] = Σ_a λ[a] Ψ[a, j]; then ``acc = Σ_j Ψ[a, j] ratio[j]``
        for input ``a`` (the caller multiplies by λ[a] and the factor). One definition of the float32 sums' order for
        both the step-by-step and the one-call kernels."""
        n_in = psi.shape[0]
        if a == 0:
            for j in range(n_in):
                z[:n] = 0.0
                for b in range(n_in):
                    w = psi[b, j]
                    row = lam_t[b]
                    for i in range(n):
                        z[i] += row[i] * w
                xj = x[j]
                rj = ratio[j]
                for i in range(n):
                    rj[i] = xj[i] / z[i] if z[i] > 0 else np.float32(0.0)
        acc[:n] = 0.0
        for j in range(n_in):
            w = psi[a, j]
            rj = ratio[j]
            for i in range(n):
                acc[i] += w * rj[i]

    @numba.njit(cache=True, nogil=True, boundscheck=False)
    def _occupied_states(slab):  # pragma: no cover - compiled
        n_l, n_in, n_v, n_b = slab.shape
        # (s, v, b) with any input holding mass, in (s, v, b) order like np.nonzero(slab.any(axis=1))
        mark = np.zeros((n_l, n_v, n_b), np.bool_)
        n = 0
        for s in range(n_l):
            for a in range(n_in):
                for v in range(n_v):
                    for b in range(n_b):
                        if slab[s, a, v, b] != 0.0 and not mark[s, v, b]:
                            mark[s, v, b] = True
                            n += 1
        return _marked_indices(mark, n)


    @numba.njit(cache=True, nogil=True, boundscheck=False)
    def _priority_at_states(restriction, preference, b_idx, v_idx, s_idx, forbid_threshold):  # pragma: no cover - compiled
        n_in = restriction.shape[1]
        out = np.empty((b_idx.shape[0], n_in), np.float32)
        for n in range(b_idx.shape[0]):
            b, v, s = b_idx[n], v_idx[n], s_idx[n]
            carry = np.float32(0.0)
            top = restriction[b, 0, v, s]
            for alpha in range(n_in - 1, -1, -1):
                m = restriction[b, alpha, v, s]
                top = max(top, m)
                want = carry + preference[b, alpha]
                r = min(m, want)
                out[n, alpha] = r
                carry = want - r
            if top <= forbid_threshold:
                for alpha in range(n_in):
                    out[n, alpha] = np.float32(0.0)
                out[n, 0] = np.float32(1.0)
        return out

    @numba.njit(cache=True, nogil=True, fastmath=False, boundscheck=False)
    def _speed_fill(xp, fp, start, bucket, inv_h, cell_s, v_c, a_c, w32, tau, values, done, b_idx, v_idx, s_idx):  # pragma: no cover - compiled
        """λ_speed into values (B, L, N_v, M) at every state (b_idx empty) or at the listed states, where not yet
        ``done`` (then marked): v_adm,j(x) at x = s + vτ as np.interp gives it for every profile j, the inputs up to
        (v_adm − v)/τ allowed, Σ_j w_j in the order of j. One loop body for both (a helper per state costs 3x)."""
        n_b, n_l = cell_s.shape
        n_v, n_in, n_j = v_c.shape[0], a_c.shape[0], fp.shape[0]
        n_query = n_v * n_l
        count = np.empty(n_j, np.int64)
        a0 = a_c[0]
        inv_da = (n_in - 1) / (a_c[n_in - 1] - a_c[0]) if n_in > 1 else 0.0
        total = np.float32(0.0)  # Σ_j w_j, all of them, in the order of j
        for jj in range(n_j):
            total += w32[jj]
        every = b_idx.shape[0] == 0
        n_states = n_b * n_v * n_l if every else b_idx.shape[0]
        for i in range(n_states):
            if every:
                b, rest = divmod(i, n_l * n_v)
                l, vi = divmod(rest, n_v)
            else:
                b, vi, l = b_idx[i], v_idx[i], s_idx[i]
            if done[b, l, vi]:
                continue
            done[b, l, vi] = True
            lo, n = start[b], start[b + 1] - start[b]
            v = v_c[vi]
            x = cell_s[b, l] + v * tau
            # np.interp's search: -2 for a NaN x, -1 left of the knots, n right of them, else the last knot <= x
            # (xp non-decreasing: from the knot its bucket of the knots' mean spacing holds, walked back and on)
            if np.isnan(x):
                j = -2
            elif x > xp[lo + n - 1]:
                j = n
            elif x < xp[lo]:
                j = -1
            else:
                k = int((x - xp[lo]) * inv_h[lo])
                k = min(max(k, 0), n - 1)
                j = bucket[lo + k]
                while j > 0 and xp[lo + j] > x:
                    j -= 1
                while j + 1 < n and xp[lo + j + 1] <= x:
                    j += 1
            inner = j >= 0 and j < n - 1 and xp[lo + j] != x
            dx, rdx, off = 1.0, 0.0, 0.0
            if inner:
                dx = xp[lo + j + 1] - xp[lo + j]
                rdx = 1.0 / dx
                off = x - xp[lo + j]
            c_min = n_in
            for jj in range(n_j):
                if inner:
                    y0, y1 = fp[jj, lo + j], fp[jj, lo + j + 1]
                    if n <= n_query:  # np.interp precomputes the slopes with 1/dx then
                        slope = (y1 - y0) * rdx
                    else:
                        slope = (y1 - y0) / dx
                    val = slope * off + y0
                    if np.isnan(val):
                        val = slope * (x - xp[lo + j + 1]) + y1
                        if np.isnan(val) and y0 == y1:
                            val = y0
                elif j == -2:
                    val = x
                elif j == -1:
                    val = fp[jj, lo]
                elif j >= n - 1:
                    val = fp[jj, lo + n - 1]
                else:  # on a knot
                    val = fp[jj, lo + j]
                threshold = (val - v) / tau
                # the inputs are ascending: those allowed (a_α <= threshold) are the first c; a guess from their mean
                # spacing, then exact
                g = (threshold - a0) * inv_da
                if g < 0.0:
                    c = 0
                elif g >= n_in:
                    c = n_in
                else:
                    c = int(g) + 1
                while c > 0 and not (a_c[c - 1] <= threshold):
                    c -= 1
                while c < n_in and a_c[c] <= threshold:
                    c += 1
                count[jj] = c
                c_min = min(c_min, c)
            for a in range(n_in):
                if a < c_min:
                    values[b, l, vi, a] = total
                else:
                    acc = np.float32(0.0)  # Σ_j w_j in the order of j, as the numpy definition adds them
                    for jj in range(n_j):
                        if a < count[jj]:
                            acc += w32[jj]
                    values[b, l, vi, a] = acc

    @numba.njit(cache=True, nogil=True, fastmath=False, boundscheck=False)
    def _admissible_rows(s_all, kappa_all, sizes, limits, a_lat, two_b, min_curvature, out):  # pragma: no cover - compiled
        """``priority.admissible_speeds_batch`` after the smoothing, the numpy code's numbers, into out (B, J, n_max) (the
        columns past a row's size left as they are): v = min(limit, √(a_lat / max(κ, min_curvature))), the reverse
        running minimum of v² + 2b·s from the row's end, then √max(run − 2b·s, 0) (numpy's NaN and tie rules)."""
        for b in range(s_all.shape[0]):
            for j in range(a_lat.shape[0]):
                run = np.inf
                for c in range(sizes[b] - 1, -1, -1):
                    v = _min(limits[b], np.sqrt(a_lat[j] / _max(kappa_all[b, c], min_curvature)))
                    brake_s = two_b * s_all[b, c]
                    run = _min(run, v * v + brake_s)
                    out[b, j, c] = np.sqrt(_max(run - brake_s, 0.0))

    @numba.njit(cache=True, nogil=True, fastmath=False, boundscheck=False)
    def _speed_lines(t_ns, v, ptr, ns, out):  # pragma: no cover - compiled
        """Per vehicle n (its samples [ptr[n], ptr[n + 1]), at least 3, at most PAIRWISE_BLOCK), the least-squares line of
        ``MarkovPredictor._speed_line`` into out[n]: (time span, slope, residual sum of squares, Σ(t − t̄)²), the numpy
        code's float64 operations in its order (its sums numpy's pairwise sums, ``numpy_rules.pairwise_sum``)."""
        most = 0
        for n in range(ptr.shape[0] - 1):
            most = max(most, ptr[n + 1] - ptr[n])
        t = np.empty(most)
        work = np.empty(most)
        for n in range(ptr.shape[0] - 1):
            lo, m = ptr[n], ptr[n + 1] - ptr[n]
            for i in range(m):
                t[i] = np.float64(t_ns[lo + i] - t_ns[lo + m - 1]) * ns  # from the newest sample, in integer ns first
            mean_t = _pairwise_sum(t, 0, m) / m
            for i in range(m):
                t[i] = t[i] - mean_t
            v_mean = _pairwise_sum(v, lo, m) / m
            for i in range(m):
                work[i] = t[i] * t[i]
            sxx = _pairwise_sum(work, 0, m)
            if 1e-12 > sxx:  # max(sxx, 1e-12) as Python's max takes it (NaN kept)
                sxx = 1e-12
            for i in range(m):
                work[i] = t[i] * (v[lo + i] - v_mean)
            slope = _pairwise_sum(work, 0, m) / sxx
            for i in range(m):
                r = v[lo + i] - v_mean - slope * t[i]
                work[i] = r * r
            out[n, 0] = np.float64(t_ns[lo + m - 1] - t_ns[lo]) * ns
            out[n, 1] = slope
            out[n, 2] = _pairwise_sum(work, 0, m)
            out[n, 3] = sxx

    @numba.njit(cache=True, nogil=True, fastmath=False, boundscheck=False)
    def _knot_buckets(xp, start, bucket, inv_h):  # pragma: no cover - compiled
        """``SpeedRestriction``'s per-pair knot buckets, the numpy loop's numbers: for a pair of n > 1 knots over a span
        > 0, h = span / n, inv_h[first knot] = 1 / h and bucket[k] = max(searchsorted(s, s_0 + h·k, "right") − 1, 0)
        (a binary search of the pair's sorted, finite knots with numpy's comparison)."""
        for b in range(start.shape[0] - 1):
            lo, hi = start[b], start[b + 1]
            n = hi - lo
            if n <= 1:
                continue
            span = xp[hi - 1] - xp[lo]
            if not span > 0:
                continue
            h = span / n
            inv_h[lo] = 1.0 / h
            for k in range(n):
                q = xp[lo] + h * np.float64(k)
                left, right = lo, hi  # the first knot > q (side="right")
                while left < right:
                    mid = (left + right) >> 1
                    if xp[mid] <= q:
                        left = mid + 1
                    else:
                        right = mid
                i = left - lo - 1
                bucket[lo + k] = i if i > 0 else 0

    @numba.njit(cache=True, nogil=True, boundscheck=False)
    def _priority_from_states(values, preference, b_idx, v_idx, s_idx, forbid_threshold):  # pragma: no cover - compiled
        """``_priority_at_states`` with the restriction stored per state, (B, L, N_v, M)."""
        n, n_in = b_idx.shape[0], values.shape[3]
        width = (n + 7) // 8 * 8
        out_t = np.empty((n_in, width), np.float32)
        _priority_into(values, preference, b_idx, v_idx, s_idx, n, forbid_threshold, out_t, np.empty((2 * n_in, width), np.float32))
        return np.ascontiguousarray(out_t[:, :n].T)

    @numba.njit(cache=True, nogil=True, boundscheck=False, inline="always")
    def _slot_add(key, value, slot, uniq, sums, m):  # pragma: no cover - compiled
        """Adds ``value`` to the sum of ``key`` (its slot ``slot[key]``; a key without one, -1, gets slot ``m``, is
        listed in ``uniq`` and its sum starts from 0.0); returns the number of keys listed. The one accumulation of
        ``_sum_by_key`` and the grid kernels (``frame_kernels``): each sum in the order of its terms."""
        j = slot[key]
        if j < 0:
            j = m
            slot[key] = m
            uniq[m] = key
            sums[m] = 0.0
            m += 1
        sums[j] += value
        return m

    @numba.njit(cache=True, nogil=True, boundscheck=False)
    def _sum_by_key(keys, values, slot):  # pragma: no cover - compiled
        """Sorted unique keys and the sum of their values, each sum taken in the order of the input from 0.0 (as
        np.bincount adds); ``slot`` (> max key, all -1) is scratch, left all -1."""
        n = keys.shape[0]
        uniq = np.empty(n, np.int64)
        sums = np.empty(n, np.float64)
        m = 0
        for i in range(n):
            m = _slot_add(keys[i], values[i], slot, uniq, sums, m)
        ordered = np.sort(uniq[:m])
        out = np.empty(m, np.float64)
        for i in range(m):
            out[i] = sums[slot[ordered[i]]]
        for i in range(m):
            slot[uniq[i]] = -1
        return ordered, out


    from llvmlite import ir as _ir
    from numba.core import cgutils as _cgutils
    from numba.core import types
    from numba.extending import intrinsic as _intrinsic

    def _splat8(builder, value):  # pragma: no cover - used at compile time
        """An LLVM vector of 8 copies of ``value``."""
        vec = _ir.VectorType(value.type, 8)
        one = builder.insert_element(vec(_ir.Undefined), value, _ir.Constant(_ir.IntType(32), 0))
        return builder.shuffle_vector(one, vec(_ir.Undefined), _ir.Constant(_ir.VectorType(_ir.IntType(32), 8), [0] * 8))

    @_intrinsic
    def _axpy8(typingctx, dst, d, w, src, s):  # pragma: no cover - compiled
        """``dst[d:d + 8] += w * src[s:s + 8]`` (1-D C arrays, src and w float32, dst float32 or float64) as one 8-lane vector
        operation: per lane the float32 product then the add in dst's type (after exact widening), no fused
        multiply-add: the numbers of the scalar loop, which numba leaves scalar (its SLP vectoriser is off)."""
        if not (isinstance(dst, types.Array) and isinstance(src, types.Array) and dst.ndim == 1 and src.ndim == 1
                and dst.layout == "C" and src.layout == "C" and src.dtype == types.float32
                and dst.dtype in (types.float32, types.float64) and w == types.float32):
            return None

        def codegen(context, builder, signature, args):
            dst_v, d_v, w_v, src_v, s_v = args
            dty, d_ty, _w_ty, sty, s_ty = signature.args
            dary = context.make_array(dty)(context, builder, dst_v)
            sary = context.make_array(sty)(context, builder, src_v)
            f32 = _ir.FloatType()
            elem = _ir.DoubleType() if dty.dtype == types.float64 else f32
            lanes32, lanes = _ir.VectorType(f32, 8), _ir.VectorType(elem, 8)
            dptr = builder.bitcast(builder.gep(dary.data, [context.cast(builder, d_v, d_ty, types.intp)]), lanes.as_pointer())
            sptr = builder.bitcast(builder.gep(sary.data, [context.cast(builder, s_v, s_ty, types.intp)]), lanes32.as_pointer())
            product = builder.fmul(_splat8(builder, w_v), builder.load(sptr, align=4))
            if elem is not f32:
                product = builder.fpext(product, lanes)
            align = 8 if elem is not f32 else 4
            builder.store(builder.fadd(builder.load(dptr, align=align), product), dptr, align=align)
            return context.get_dummy_value()

        return types.void(dst, d, w, src, s), codegen

    @_intrinsic
    def _scatter8(typingctx, dst, base, rel, weight, lo, hi, src, s):  # pragma: no cover - compiled
        """``_axpy8(dst, base + rel[e], weight[e], src, s)`` for e in range(lo, hi), in that order, with the 8 lanes of
        ``src`` loaded once (``dst`` is another array than ``src``): each lane's numbers those of ``_axpy8``, a stencil row's
        entries in one loop without the indexing arithmetic per entry (``rel`` int64, ``weight`` float32, 1-D C)."""
        arr = types.Array
        if not (isinstance(dst, arr) and dst.ndim == 1 and dst.layout == "C" and dst.dtype in (types.float32, types.float64)
                and src == arr(types.float32, 1, "C") and rel == arr(types.int64, 1, "C") and weight == arr(types.float32, 1, "C")):
            return None

        def codegen(context, builder, signature, args):
            dst_v, base_v, rel_v, w_v, lo_v, hi_v, src_v, s_v = args
            tys = signature.args
            intp = context.get_value_type(types.intp)
            dary = context.make_array(tys[0])(context, builder, dst_v)
            rary = context.make_array(tys[2])(context, builder, rel_v)
            wary = context.make_array(tys[3])(context, builder, w_v)
            sary = context.make_array(tys[6])(context, builder, src_v)
            base_i = context.cast(builder, base_v, tys[1], types.intp)
            lo_i = context.cast(builder, lo_v, tys[4], types.intp)
            hi_i = context.cast(builder, hi_v, tys[5], types.intp)
            s_i = context.cast(builder, s_v, tys[7], types.intp)
            f32 = _ir.FloatType()
            elem = _ir.DoubleType() if tys[0].dtype == types.float64 else f32
            lanes32, lanes = _ir.VectorType(f32, 8), _ir.VectorType(elem, 8)
            x = builder.load(builder.bitcast(builder.gep(sary.data, [s_i]), lanes32.as_pointer()), align=4)
            align = 8 if elem is not f32 else 4
            with _cgutils.for_range_slice(builder, lo_i, hi_i, _ir.Constant(intp, 1)) as (e, _count):
                r = builder.load(builder.gep(rary.data, [e]))
                w = builder.load(builder.gep(wary.data, [e]))
                product = builder.fmul(_splat8(builder, w), x)
                if elem is not f32:
                    product = builder.fpext(product, lanes)
                dptr = builder.bitcast(builder.gep(dary.data, [builder.add(base_i, r)]), lanes.as_pointer())
                builder.store(builder.fadd(builder.load(dptr, align=align), product), dptr, align=align)
            return context.get_dummy_value()

        return types.void(dst, base, rel, weight, lo, hi, src, s), codegen

    @_intrinsic
    def _priority8(typingctx, out, m, q, i, n_in, stride, threshold):  # pragma: no cover - compiled
        """``_priority_into``'s arithmetic for the 8 states (columns) i:i + 8 of ``m`` and ``q`` (m_α and q_α in row α,
        rows ``stride`` apart, 1-D C float32) into ``out``, as 8-lane vector operations: from α = n_in − 1 down
        top = max(top, m_α), want = carry + q_α, r_α = min(m_α, want), carry = want − r_α; then where top <=
        ``threshold`` r = (1, 0, ..., 0). Each lane's numbers those of one state at a time (its values are >= 0, not NaN).
        """
        f32_1d = types.Array(types.float32, 1, "C")
        if not (out == f32_1d and m == f32_1d and q == f32_1d and threshold == types.float32):
            return None

        def codegen(context, builder, signature, args):
            out_v, m_v, q_v, i_v, n_v, stride_v, thr_v = args
            tys = signature.args
            intp = context.get_value_type(types.intp)
            oary, mary, qary = (context.make_array(tys[k])(context, builder, args[k]) for k in range(3))
            i_i, n_i, stride_i = (context.cast(builder, args[k], tys[k], types.intp) for k in (3, 4, 5))
            v32 = _ir.VectorType(_ir.FloatType(), 8)

            def at(ary, row):
                return builder.bitcast(builder.gep(ary.data, [builder.add(builder.mul(row, stride_i), i_i)]), v32.as_pointer())

            top = _cgutils.alloca_once_value(builder, builder.load(at(mary, _ir.Constant(intp, 0)), align=4))
            carry = _cgutils.alloca_once_value(builder, v32(None))
            last = builder.sub(n_i, _ir.Constant(intp, 1))
            with _cgutils.for_range(builder, n_i) as loop:
                alpha = builder.sub(last, loop.index)
                mv = builder.load(at(mary, alpha), align=4)
                t = builder.load(top)
                builder.store(builder.select(builder.fcmp_ordered(">", mv, t), mv, t), top)
                want = builder.fadd(builder.load(carry), builder.load(at(qary, alpha), align=4))
                r = builder.select(builder.fcmp_ordered("<", want, mv), want, mv)
                builder.store(r, at(oary, alpha), align=4)
                builder.store(builder.fsub(want, r), carry)
            forbid = builder.fcmp_ordered("<=", builder.load(top), _splat8(builder, thr_v))
            one, zero = _splat8(builder, _ir.Constant(_ir.FloatType(), 1.0)), v32(None)
            with _cgutils.for_range(builder, n_i) as loop:
                fill = builder.select(builder.icmp_signed("==", loop.index, _ir.Constant(intp, 0)), one, zero)
                ptr = at(oary, loop.index)
                builder.store(builder.select(forbid, fill, builder.load(ptr, align=4)), ptr, align=4)
            return context.get_dummy_value()

        return types.void(out, m, q, i, n_in, stride, threshold), codegen

    @_intrinsic
    def _has_mass8(typingctx, row, r):  # pragma: no cover - compiled
        """Whether the 8 lanes ``row[r:r + 8]`` (float32, each >= 0 or NaN) sum to > 0 in order: none is NaN and one is
        > 0 (a sum of non-negative terms is at least its largest), as two 8-lane compares."""
        if row != types.Array(types.float32, 1, "C"):
            return None

        def codegen(context, builder, signature, args):
            ary = context.make_array(signature.args[0])(context, builder, args[0])
            index = context.cast(builder, args[1], signature.args[1], types.intp)
            v32 = _ir.VectorType(_ir.FloatType(), 8)
            y = builder.load(builder.bitcast(builder.gep(ary.data, [index]), v32.as_pointer()), align=4)
            as_int = _ir.IntType(8)
            positive = builder.bitcast(builder.fcmp_ordered(">", y, v32(None)), as_int)
            nan = builder.bitcast(builder.fcmp_unordered("uno", y, y), as_int)
            zero = _ir.Constant(as_int, 0)
            return builder.and_(builder.icmp_unsigned("!=", positive, zero), builder.icmp_unsigned("==", nan, zero))

        return types.boolean(row, r), codegen

    @_intrinsic
    def _prune8(typingctx, row, r, pos, p, vel, q, kept, mark, m, threshold):  # pragma: no cover - compiled
        """For the 8 lanes y = ``row[r:r + 8]`` (float32; ``threshold`` float32): ``pos[p:p + 8] += y`` and ``vel[q:q + 8] += y`` (float64), y
        set to 0 where not ``y >= threshold``, ``kept[0:8] += y`` (float64), ``mark[m:m + 8] |= y > 0``; as 8-lane vector
        operations, each lane's numbers those of the scalar loop."""
        f64_1d = types.Array(types.float64, 1, "C")
        if not (row == types.Array(types.float32, 1, "C") and pos == f64_1d and vel == f64_1d and kept == f64_1d
                and mark == types.Array(types.boolean, 1, "C") and threshold == types.float32):
            return None

        def codegen(context, builder, signature, args):
            thr_v = args[9]
            tys = signature.args
            f32, f64, i8 = _ir.FloatType(), _ir.DoubleType(), _ir.IntType(8)
            v32, v64, v8 = _ir.VectorType(f32, 8), _ir.VectorType(f64, 8), _ir.VectorType(i8, 8)

            def at(k, vec, indexed=True):  # the 8 lanes of argument k from the offset that follows it (else from 0)
                ary = context.make_array(tys[k])(context, builder, args[k])
                index = context.cast(builder, args[k + 1], tys[k + 1], types.intp) if indexed else _ir.Constant(_ir.IntType(64), 0)
                return builder.bitcast(builder.gep(ary.data, [index]), vec.as_pointer())

            row_p, pos_p, vel_p = at(0, v32), at(2, v64), at(4, v64)
            kept_p, mark_p = at(6, v64, indexed=False), at(7, v8)
            y = builder.load(row_p, align=4)
            wide = builder.fpext(y, v64)
            builder.store(builder.fadd(builder.load(pos_p, align=8), wide), pos_p, align=8)
            builder.store(builder.fadd(builder.load(vel_p, align=8), wide), vel_p, align=8)
            y = builder.select(builder.fcmp_ordered(">=", y, _splat8(builder, thr_v)), y, v32(None))
            builder.store(y, row_p, align=4)
            builder.store(builder.fadd(builder.load(kept_p, align=8), builder.fpext(y, v64)), kept_p, align=8)
            positive = builder.zext(builder.fcmp_ordered(">", y, v32(None)), v8)
            builder.store(builder.or_(builder.load(mark_p, align=1), positive), mark_p, align=1)
            return context.get_dummy_value()

        return types.void(row, r, pos, p, vel, q, kept, mark, m, threshold), codegen

    @numba.njit(cache=True, nogil=True, boundscheck=False)
    def _priority_into(values, preference, b_idx, v_idx, s_idx, n_states, forbid_threshold, out_t, gathered):  # pragma: no cover - compiled
        """The priority of the first ``n_states`` listed states into ``out_t[:, :n_states]`` (M, n): from the highest input
        down r_α = min(m_α, q_α + carry), where every m_α is at most ``forbid_threshold`` all to α = 0. Each state's
        arithmetic is that of one state at a time; m and q gathered input by input (``gathered`` (2M, w)), then 8 states
        at a time as 8-lane vector operations (``_priority8``). ``out_t`` and ``gathered`` need w >= n rounded up to 8
        columns (those past n hold nothing meaningful)."""
        n_in = values.shape[3]
        n = n_states
        width = gathered.shape[1]
        m_t, q_t = gathered[:n_in], gathered[n_in:]
        for i in range(n):
            row = values[b_idx[i], s_idx[i], v_idx[i]]
            q = preference[b_idx[i]]
            for alpha in range(n_in):
                m_t[alpha, i] = row[alpha]
                q_t[alpha, i] = q[alpha]
        flat, m_flat, q_flat = out_t.reshape(-1), m_t.reshape(-1), q_t.reshape(-1)
        for i in range(0, n, 8):
            _priority8(flat, m_flat, q_flat, i, n_in, width, forbid_threshold)

    @numba.njit(cache=True, nogil=True, fastmath=False, boundscheck=False)
    def _speed_priority_blocks(blocks, inp, vel0, pos0, outside0, order, n_steps, ptr, v_to, offset, weight, iptr, ioffset, iweight,
                               with_interval, threshold, psi, prefs, has_input, forbid_threshold, xp, fp, start, bucket, inv_h, cell_s,
                               v_c, a_c, w32, tau, values, done, positions, velocities, ipositions, outsides, ioutsides, pruned,
                               totals, cur, nxt, s_buf, v_buf, b_buf, l_buf, o_buf, f_buf, x_t, lam_t, ratio_t, gathered, z,
                               acc):  # pragma: no cover - compiled
        """The whole chain of ``speed_priority_run`` for the blocks of ``_LANES`` pairs ``order[blk:blk + _LANES]``, blk
        in ``blocks`` (``order``: similar pairs side by side), each block on the cells its pairs occupy: per s-row of the
        state the velocity cells [vlo, vhi] that may hold mass, per row of p⁻ those its sources reach; the pairs of a
        block are the innermost (vectorised) axis. Writes the rows of its pairs only (of the outputs, zeros on entry,
        and of ``values``/``done``): calls on disjoint blocks may run at the same time, each with its own scratch arrays
        ``cur`` … ``acc`` (``_block_workspace``: made once per thread, not per call; none is read before it is written)."""
        n_b, n_in = inp.shape
        n_v, n_s = vel0.shape[1], pos0.shape[1]
        n_ln = _LANES
        n_d = 1  # the furthest any stencil moves mass, + 1
        for e in range(offset.shape[0]):
            n_d = max(n_d, offset[e] + 1)
        for e in range(ioffset.shape[0]):
            n_d = max(n_d, ioffset[e] + 1)
        dv_lo, dv_hi = 0, 0  # how far a target's velocity cell lies from its source's
        for a in range(n_in):
            for v in range(n_v):
                r = a * n_v + v
                for e in range(ptr[r], ptr[r + 1]):
                    dv_lo = min(dv_lo, v_to[e] - v)
                    dv_hi = max(dv_hi, v_to[e] - v)
        # each entry's target relative to its source row's s-cell (flat, in the (L, M, N_v, lanes) buffers)
        rel = np.empty(offset.shape[0], np.int64)
        for a in range(n_in):
            for v in range(n_v):
                r = a * n_v + v
                for e in range(ptr[r], ptr[r + 1]):
                    rel[e] = ((offset[e] * n_in + a) * n_v + v_to[e]) * _LANES
        irel = np.empty(ioffset.shape[0], np.int64)
        for e in range(ioffset.shape[0]):
            irel[e] = ioffset[e] * _LANES
        f32 = np.float32
        zero = f32(0.0)
        # the block's state ``cur`` (rows [first, last], in row s the cells [vlo[s], vhi[s]]) and p⁻ ``nxt`` (in row t the
        # cells [tlo[t], thi[t]]), (n_s, n_in, n_v, n_ln) float32 as the caller gives them, not zeroed (1.3 MB each, a
        # few % of it used): every cell is written before it is read, the state's box at the block's start and after each
        # step, p⁻'s box at each step's start (as the blocks of one call reuse them, each on what the block before left)
        vlo = np.zeros(n_s, np.int64)
        vhi = np.zeros(n_s, np.int64)
        tlo = np.zeros(n_s, np.int64)
        thi = np.zeros(n_s, np.int64)
        pos = np.zeros((n_s, n_ln), np.float64)
        ipos = np.zeros((n_s, n_ln), np.float64)
        vel = np.zeros((n_v, n_ln), np.float64)
        mark = np.zeros((n_s, n_v, n_ln), np.bool_)
        leaked = np.zeros(n_ln, np.float64)
        ileaked = np.zeros(n_ln, np.float64)
        kept = np.zeros(n_ln, np.float64)
        # the same memory as 1-D arrays, for _axpy8 and _prune8
        cur_flat, nxt_flat, ipos_flat, pos_flat = cur.reshape(-1), nxt.reshape(-1), ipos.reshape(-1), pos.reshape(-1)
        vel_flat, mark_flat = vel.reshape(-1), mark.reshape(-1)
        outside = np.zeros(n_ln, f32)
        factor = np.zeros(n_ln, f32)
        pair = np.zeros(n_ln, np.int64)
        # the per-state scratch (``_block_workspace``): s_buf … o_buf, f_buf, z, acc (n_states,), x_t, ratio_t (n_in,
        # n_states), lam_t (n_in, n_states + _LANES) and gathered (2 n_in, n_states + _LANES) (spare columns:
        # _priority_into works 8 states at a time), n_states = n_s · n_v · n_ln
        for blk in blocks:
            n_live = min(n_ln, order.shape[0] - blk)
            first, last, v_first, v_last = -1, -1, -1, -1
            for ln in range(n_ln):
                b = order[blk + ln] if ln < n_live else -1
                pair[ln] = b
                outside[ln] = outside0[b] if b >= 0 else zero
                if b < 0:
                    continue
                for s in range(n_s):
                    if pos0[b, s] > 0:
                        first = s if first < 0 else min(first, s)
                        last = max(last, s)
                for v in range(n_v):
                    if vel0[b, v] > 0:
                        v_first = v if v_first < 0 else min(v_first, v)
                        v_last = max(v_last, v)
            if v_first < 0:
                first, last = -1, -1
            for s in range(max(first, 0), last + 1):  # p(t_0) = position · input · velocity, in that order (initial_slab's)
                vlo[s], vhi[s] = v_first, v_last
                for a in range(n_in):
                    for v in range(v_first, v_last + 1):
                        cell = cur[s, a, v]
                        for ln in range(n_ln):
                            b = pair[ln]
                            cell[ln] = (pos0[b, s] * inp[b, a]) * vel0[b, v] if b >= 0 else zero
            for k in range(n_steps):
                if first < 0:  # no mass left in the window
                    for ln in range(n_live):
                        outsides[pair[ln], k] = outside[ln]
                        ioutsides[pair[ln], k] = outside[ln]
                    continue
                hi = min(last + n_d, n_s)  # every target of the rows [first, last]
                for t in range(first, hi):
                    tlo[t], thi[t] = n_v, -1
                for s in range(first, last + 1):
                    if vhi[s] >= vlo[s]:
                        lo_v, hi_v = max(vlo[s] + dv_lo, 0), min(vhi[s] + dv_hi, n_v - 1)
                        for t in range(s, min(s + n_d, n_s)):
                            tlo[t] = min(tlo[t], lo_v)
                            thi[t] = max(thi[t], hi_v)
                for t in range(first, hi):
                    pos[t] = 0.0
                    ipos[t] = 0.0
                    for a in range(n_in):
                        for v in range(tlo[t], thi[t] + 1):
                            nxt[t, a, v] = 0.0
                vel[:] = 0.0
                leaked[:] = 0.0
                ileaked[:] = 0.0
                # sources in (s, α, v, entry) order, the order of _fused_step: every sum gets its non-zero terms in the
                # same order (the zero ones it adds change nothing)
                for s in range(first, last + 1):
                    inside = s + n_d <= n_s  # every target of the row lies in the window: no leak
                    for a in range(n_in):
                        for v in range(vlo[s], vhi[s] + 1):
                            src = ((s * n_in + a) * n_v + v) * n_ln
                            if not _has_mass8(cur_flat, src):
                                continue
                            r = a * n_v + v
                            if inside:
                                _scatter8(nxt_flat, s * n_in * n_v * n_ln, rel, weight, ptr[r], ptr[r + 1], cur_flat, src)
                                if with_interval:
                                    _scatter8(ipos_flat, s * n_ln, irel, iweight, iptr[r], iptr[r + 1], cur_flat, src)
                                continue
                            for e in range(ptr[r], ptr[r + 1]):
                                t = s + offset[e]
                                if t < n_s:
                                    _axpy8(nxt_flat, ((t * n_in + a) * n_v + v_to[e]) * n_ln, weight[e], cur_flat, src)
                                else:
                                    _axpy8(leaked, 0, weight[e], cur_flat, src)
                            if with_interval:
                                for e in range(iptr[r], iptr[r + 1]):
                                    t = s + ioffset[e]
                                    if t < n_s:
                                        _axpy8(ipos_flat, t * n_ln, iweight[e], cur_flat, src)
                                    else:
                                        _axpy8(ileaked, 0, iweight[e], cur_flat, src)
                kept[:] = 0.0
                new_first, new_last = -1, -1
                for t in range(first, hi):  # marginals, then pruning; the rows' cells holding mass after it
                    marks = mark[t]
                    for v in range(tlo[t], thi[t] + 1):
                        marks[v] = False
                    for a in range(n_in):
                        for v in range(tlo[t], thi[t] + 1):
                            _prune8(nxt_flat, ((t * n_in + a) * n_v + v) * n_ln, pos_flat, t * n_ln, vel_flat, v * n_ln, kept, mark_flat,
                                    (t * n_v + v) * n_ln, threshold)
                    vlo[t], vhi[t] = n_v, -1
                    for v in range(tlo[t], thi[t] + 1):
                        mv = marks[v]
                        hit = False
                        for ln in range(n_ln):
                            hit |= mv[ln]
                        if hit:
                            vlo[t] = min(vlo[t], v)
                            vhi[t] = v
                    if vhi[t] >= 0:
                        if new_first < 0:
                            new_first = t
                        new_last = t
                for ln in range(n_live):
                    b = pair[ln]
                    if with_interval:
                        ioutsides[b, k] = outside[ln] + f32(ileaked[ln])
                    outside[ln] = outside[ln] + f32(leaked[ln])
                    outsides[b, k] = outside[ln]
                    before = zero  # the pair's position total, summed as numpy sums the (B, L) marginal over L (B > 1)
                    for t in range(first, hi):
                        p32 = f32(pos[t, ln])
                        positions[b, k, t] = p32
                        before += p32
                        if with_interval:
                            ipositions[b, k, t] = f32(ipos[t, ln])
                    for v in range(n_v):
                        velocities[b, k, v] = f32(vel[v, ln])
                    kept32 = f32(kept[ln])
                    factor[ln] = before / (kept32 if kept32 > 0 else f32(1.0))
                    pruned[b, k] = max(before - kept32, zero)
                first, last = new_first, new_last
                if first < 0:
                    continue
                if not has_input[k]:  # identity: p⁻ rescaled to the total before pruning
                    for t in range(first, last + 1):
                        for a in range(n_in):
                            for v in range(vlo[t], vhi[t] + 1):
                                src = nxt[t, a, v]
                                dst = cur[t, a, v]
                                for ln in range(n_ln):
                                    dst[ln] = src[ln] * factor[ln]
                    continue
                n = 0
                for t in range(first, last + 1):
                    for v in range(vlo[t], vhi[t] + 1):
                        for ln in range(n_live):
                            if mark[t, v, ln]:
                                s_buf[n], v_buf[n], b_buf[n], l_buf[n] = t, v, pair[ln], ln
                                n += 1
                _speed_fill(xp, fp, start, bucket, inv_h, cell_s, v_c, a_c, w32, tau, values, done, b_buf[:n], v_buf[:n], s_buf[:n])
                _priority_into(values, prefs[k], b_buf, v_buf, s_buf, n, forbid_threshold, lam_t, gathered)
                for t in range(first, last + 1):
                    for a in range(n_in):
                        for v in range(vlo[t], vhi[t] + 1):
                            cur[t, a, v] = 0.0
                # Γ = colnorm(diag(λ) Ψ) at the states, input by input over all of them (the arithmetic of
                # _priority_occupied: each state's sums in the same order); o_buf: the state's input-0 cell (flat)
                for i in range(n):
                    o = (s_buf[i] * n_in * n_v + v_buf[i]) * n_ln + l_buf[i]
                    o_buf[i] = o
                    f_buf[i] = factor[l_buf[i]]
                    for j in range(n_in):
                        x_t[j, i] = nxt_flat[o + j * n_v * n_ln]
                for a in range(n_in):  # p[a] = λ[a] · Σ_j Ψ[a, j] ratio[j] · factor
                    _gamma_input(a, x_t, lam_t, psi, n, z, ratio_t, acc)
                    la = lam_t[a]
                    step = a * n_v * n_ln
                    for i in range(n):
                        cur_flat[o_buf[i] + step] = la[i] * acc[i] * f_buf[i]
            for ln in range(n_live):
                total = 0.0
                for t in range(max(first, 0), last + 1):
                    for a in range(n_in):
                        for v in range(vlo[t], vhi[t] + 1):
                            total += cur[t, a, v, ln]
                totals[pair[ln]] = total

def fused_step(slab, src_lo, lo, hi, n_s, tables, with_interval, threshold):
    """See the module docstring. The slab holds the s-cells [src_lo, src_lo + L) and p⁻ the cells [lo, hi) (the
    window of this step: the slab's occupied cells lie in it), so that a moving window costs no copy. ``tables``: ``stencil_tables`` of Υ(τ) then ``collapsed_tables`` of Υ([0, τ]).

    Returns (p⁻ pruned (L, M, N_v, B), leaked (B,), position (L, B), velocity (N_v, B), interval position (L, B),
    interval leaked (B,), totals after pruning (B,), and the (s, v, b) index arrays of the states holding mass after
    pruning, in C order like ``occupied_states``)."""
    ptr, v_to, offset, weight, iptr, ioffset, iweight = tables
    return _fused_step(np.ascontiguousarray(slab, dtype=np.float32), int(src_lo), int(lo), int(hi - lo), int(n_s), ptr, v_to, offset, weight,
                       iptr, ioffset, iweight, bool(with_interval), np.float32(threshold))


def occupied_states(slab):
    """(s, v, b) indices of the slab's states where any input holds mass, in C order (``np.nonzero(slab.any(axis=1))``)."""
    return _occupied_states(np.ascontiguousarray(slab, dtype=np.float32))


def priority_occupied(slab, s_idx, v_idx, b_idx, lam, psi, factors):
    """Γ = colnorm(diag(λ) Ψ) applied at the listed states (λ ``(n, M)``), scaled per pair by ``factors`` (B,)."""
    return _priority_occupied(np.ascontiguousarray(slab, dtype=np.float32), s_idx, v_idx, b_idx,
                              np.ascontiguousarray(lam, dtype=np.float32), np.ascontiguousarray(psi, dtype=np.float32),
                              np.ascontiguousarray(factors, dtype=np.float32))



def speed_priority_run(state, outside0, tables, n_steps, with_interval, threshold, psi, restriction, preferences, has_input,
                       forbid_threshold, threads=1, skip=None):
    """A whole run of the hybrid chain in one compiled call: Υ(τ) (and Υ([0, τ])), pruning with the pruned mass put back,
    then after step k (where ``has_input[k]``) Γ = colnorm(diag(λ) Ψ) with λ = ``restriction``'s priority for the
    preference ``preferences[k]`` (B, M) at the states holding mass (``SpeedRestriction.priority_at_states``); where
    not ``has_input[k]`` the identity.

    What ``MarkovPropagator.run`` with ``InputPriority(at_states=...)`` steps and the numba kernels
    (``fused_step``, ``priority_occupied``) computes, in blocks of ``_LANES`` pairs of similar speed and place (the
    block's pairs innermost, vectorised), each block on the (s, v) cells its pairs occupy (not on the batch's window,
    which spans every pair's), one (L, M, N_v, lanes) buffer for all: the same float32 operations in the same order,
    so the same numbers, bit for bit, with one exception: with a single pair (B = 1) numpy sums a
    pair's position marginal pairwise, here it is summed in order as numpy does for B > 1 (the renormalisation
    factor may differ in the last bit). tests/stages/test_markov_occupied.py compares the two.

    ``state``: (input (B, M), velocity (B, N_v), position (B, N_s)) float32 of p(t_0) (``SeparableState``), ``outside0``
    (B,) float32, ``tables`` as for ``fused_step``, ``psi`` (M, M), ``preferences`` (K, B, M); ``threads`` (>= 1): the
    blocks are shared out between that many threads (the caller and a pool kept per count), each taking the next block
    when free; every block writes only its own pairs' rows (of the outputs and of ``restriction``'s caches), so the
    numbers do not depend on it (tests/stages/test_markov_kernel_threads.py). ``skip`` (B,) bool: pairs left out of the
    blocks (their outputs zeros, their total 0), for pairs whose chain the caller weighs by 0.
    Returns position (B, K, N_s), velocity (B, K, N_v), interval position (B, K, N_s) or None, outside (B, K),
    interval outside (B, K) or None, pruned mass (B, K), float32, and the final totals (B,) float64."""
    ptr, v_to, offset, weight, iptr, ioffset, iweight = tables
    inp, vel0, pos0 = (np.ascontiguousarray(a, dtype=np.float32) for a in state)
    n_b, n_in = inp.shape
    n_steps = int(n_steps)
    n_s, n_v = pos0.shape[1], vel0.shape[1]
    # pairs of similar speed and place side by side: a block of them occupies fewer cells together
    order = np.lexsort((np.argmax(pos0 > 0, axis=1), vel0 @ np.arange(n_v, dtype=np.float32))).astype(np.int64)
    if skip is not None:  # pairs whose chain nobody reads: left out of the blocks, their outputs zeros
        order = order[~np.asarray(skip, dtype=np.bool_)[order]]
    f32 = np.float32
    outputs = (np.zeros((n_b, n_steps, n_s), f32), np.zeros((n_b, n_steps, n_v), f32),
               np.zeros((n_b, n_steps if with_interval else 0, n_s), f32), np.zeros((n_b, n_steps), f32), np.zeros((n_b, n_steps), f32),
               np.zeros((n_b, n_steps), f32), np.zeros(n_b, np.float64))
    args = (inp, vel0, pos0, np.ascontiguousarray(outside0, dtype=f32), order, n_steps, ptr, v_to, offset, weight, iptr, ioffset,
            iweight, bool(with_interval), f32(threshold), np.ascontiguousarray(psi, dtype=f32),
            np.ascontiguousarray(preferences, dtype=f32).reshape(n_steps, n_b, n_in), np.asarray(has_input, dtype=np.bool_),
            f32(forbid_threshold), *restriction._args, restriction._values, restriction._done, *outputs)
    blocks = np.arange(0, order.shape[0], _LANES, dtype=np.int64)
    n_threads = min(int(threads), blocks.shape[0])
    if n_threads <= 1:
        _speed_priority_blocks(blocks, *args, *_block_workspace(n_s, n_in, n_v))
    else:
        _on_threads(blocks.shape[0], lambda i: _speed_priority_blocks(blocks[i:i + 1], *args, *_block_workspace(n_s, n_in, n_v)), n_threads)
    pos, vel, ipos, out, iout, pruned, totals = outputs
    return pos, vel, (ipos if with_interval else None), out, (iout if with_interval else None), pruned, totals


_WORKSPACES = threading.local()


def _block_workspace(n_s: int, n_in: int, n_v: int) -> tuple[np.ndarray, ...]:
    """This thread's scratch arrays for ``_speed_priority_blocks`` (cur, nxt, s_buf … acc, as its parameters), made
    once per thread and grid (~10 MB for 100 × 10 × 40 cells) instead of on every call: allocated per call, they were
    paged in again whenever the allocator had given the memory back (on a pool thread, 8 ms in ~15 % of the calls at
    18 vehicles)."""
    key = (int(n_s), int(n_in), int(n_v))
    found = getattr(_WORKSPACES, "arrays", None)
    if found is None or found[0] != key:
        n_states = n_s * n_v * _LANES
        f32 = np.float32
        found = _WORKSPACES.arrays = (key, (
            np.empty((n_s, n_in, n_v, _LANES), f32), np.empty((n_s, n_in, n_v, _LANES), f32),
            *(np.empty(n_states, np.int64) for _ in range(5)), np.empty(n_states, f32),
            np.empty((n_in, n_states), f32), np.empty((n_in, n_states + _LANES), f32), np.empty((n_in, n_states), f32),
            np.empty((2 * n_in, n_states + _LANES), f32), np.empty(n_states, f32), np.empty(n_states, f32),
        ))
    return found[1]


def _on_threads(n_tasks: int, task, n_threads: int) -> None:
    """``task(i)`` for every i < ``n_tasks`` on ``n_threads`` threads, the caller one of them, each thread taking the next
    i when it is free (tasks differ in cost, and another process may hold a core for a while); returns when all are done
    and raises the first exception of any."""
    counter = itertools.count()  # next() on it is atomic under the GIL

    def work() -> None:
        while (i := next(counter)) < n_tasks:
            task(i)

    n_threads = min(n_threads, os.cpu_count() or n_threads)  # (threads beyond the cores only take turns)
    futures = [_pool(n_threads).submit(work) for _ in range(n_threads - 1)]
    try:
        work()
    finally:
        concurrent.futures.wait(futures)
    for f in futures:
        f.result()


_pools: dict[int, concurrent.futures.ThreadPoolExecutor] = {}  # one pool, under the key 0: the most workers asked for yet
if hasattr(os, "register_at_fork"):  # a forked child has none of its parent's threads: it makes its own pools
    os.register_at_fork(after_in_child=_pools.clear)


def _pool(n_threads: int) -> concurrent.futures.ThreadPoolExecutor:
    """A pool of at least ``n_threads − 1`` worker threads for ``_on_threads`` (the caller is the other), made on first
    use: one pool, grown when more are asked for (a pool per thread count kept every size a frame's blocks asked for,
    each with its threads and their workspaces)."""
    pool = _pools.get(0)
    if pool is None or pool._max_workers < n_threads - 1:
        if pool is not None:
            pool.shutdown(wait=False)  # (its threads end once idle; work already submitted still runs)
        pool = _pools[0] = concurrent.futures.ThreadPoolExecutor(max_workers=n_threads - 1, thread_name_prefix="markov-kernel")
    return pool


def priority_at_states(restriction, preference, b_idx, v_idx, s_idx, forbid_threshold):
    """The priority r = combine(m, q) of ``stages.markov_prediction.priority.combine_with_preference`` at listed states.

    ``restriction`` (B, M, N_v, N_s) float32 (m per state), ``preference`` (B, M) float32 (q per pair), the states
    ``(b, v, s)`` as index arrays; returns (n, M) float32. The same float32 arithmetic: from the highest input down
    r_α = min(m_α, q_α + carry), the cut part carried to the next lower input; where every m_α is at most
    ``forbid_threshold`` all weight goes to α = 0. tests/stages/test_markov_occupied.py checks it against
    ``combine_with_preference`` (the definition).
    """
    return _priority_at_states(np.asarray(restriction, dtype=np.float32), np.ascontiguousarray(preference, dtype=np.float32),
                               np.asarray(b_idx, dtype=np.int64), np.asarray(v_idx, dtype=np.int64), np.asarray(s_idx, dtype=np.int64),
                               np.float32(forbid_threshold))


def speed_lines(t_ns: np.ndarray, v: np.ndarray, ptr: np.ndarray, ns: float) -> np.ndarray | None:
    """(V, 4) float64: per vehicle n, whose speed samples (stamps ``t_ns`` int64, speeds ``v``) are [ptr[n], ptr[n + 1]),
    at least 3 each, its least-squares line as ``MarkovPredictor._speed_line`` computes it (time span, slope, residual sum
    of squares, Σ(t − t̄)²; the same numbers); None where numba is missing or a vehicle has fewer than 3 or more than
    ``numpy_rules.PAIRWISE_BLOCK`` samples (the callers then take the numpy code)."""
    ptr = np.asarray(ptr, dtype=np.int64)
    counts = np.diff(ptr)
    if numba is None or (counts.size and (counts.min() < 3 or counts.max() > PAIRWISE_BLOCK)):
        return None
    out = np.empty((counts.shape[0], 4))
    _speed_lines(np.ascontiguousarray(t_ns, dtype=np.int64), np.ascontiguousarray(v, dtype=np.float64), ptr, float(ns), out)
    return out


def admissible_rows(s_all, kappa_all, sizes, limits, a_lat, two_b: float, min_curvature: float) -> np.ndarray:
    """(B, J, n_max) float64 admissible speeds of ``priority.admissible_speeds_batch`` from its padded rows of arc
    lengths and smoothed |κ| (B, n_max), the rows' ``sizes``, speed ``limits`` (B,) and lateral accelerations (J,), the
    numpy code's numbers (its columns past a row's size are not meant to be read); compiled, one pass per row."""
    s_all = np.ascontiguousarray(s_all, dtype=np.float64)
    out = np.zeros((s_all.shape[0], np.shape(a_lat)[0], s_all.shape[1]))
    _admissible_rows(s_all, np.ascontiguousarray(kappa_all, dtype=np.float64), np.asarray(sizes, dtype=np.int64),
                     np.ascontiguousarray(limits, dtype=np.float64).reshape(-1), np.ascontiguousarray(a_lat, dtype=np.float64),
                     float(two_b), float(min_curvature), out)
    return out


class SpeedRestriction:
    """λ_speed of B pairs, the numbers of ``stages.markov_prediction.priority.speed_restriction`` per pair
    (Σ_j w_j · 1[a_α ≤ (v_adm,j(s + vτ) − v)/τ], float32 sums in the order of j, v_adm interpolated as ``np.interp``
    does), compiled and computed on demand: ``priority_at_states`` fills only the states it is asked for that are not
    yet (the hybrid mode needs λ_speed only where the chain holds mass, a few percent of the states); ``full()`` is
    every state as ``(B, M, N_v, L)``.

    ``profile_s_m`` and ``admissible_mps`` are lists of the pairs' profiles ((n_b,) non-decreasing, and (J, n_b)),
    ``cell_s_m`` (B, L) the s-cell centres of each pair, ``input_centres_mps2`` ascending (ValueError otherwise).
    tests/stages/test_markov_occupied.py checks it bit for bit against the numpy definition.
    """

    def __init__(self, profile_s_m, admissible_mps, cell_s_m, v_centres_mps, input_centres_mps2, weights, tau_s) -> None:
        n_b = len(profile_s_m)
        n_j = int(np.shape(weights)[0])
        a_c = np.asarray(input_centres_mps2, dtype=np.float64)
        if np.any(np.diff(a_c) <= 0):
            raise ValueError("SpeedRestriction: the input centres must be ascending")
        start = np.zeros(n_b + 1, np.int64)
        start[1:] = np.cumsum([len(s) for s in profile_s_m])
        xp = np.concatenate([np.asarray(s, dtype=np.float64).reshape(-1) for s in profile_s_m]) if n_b else np.zeros(0)
        if n_b and (np.any(start[1:] == start[:-1]) or not np.all(np.isfinite(xp))
                    or not np.all(np.delete(np.diff(xp), start[1:-1] - 1) >= 0)):  # (the steps between pairs left out)
            raise ValueError("SpeedRestriction: every profile needs at least one knot, non-decreasing and finite")
        fp = np.concatenate([np.asarray(a, dtype=np.float64).reshape(n_j, -1) for a in admissible_mps], axis=1) if n_b else np.zeros((n_j, 0))
        # per pair: buckets of the knots' mean spacing h over [s_0, s_n) and the last knot at or before each bucket's start
        bucket = np.zeros(xp.shape[0], np.int64)
        inv_h = np.zeros(xp.shape[0], np.float64)
        _knot_buckets(xp, start, bucket, inv_h)  # (h = span / n, the last knot at or before s_0 + h·k, as np.searchsorted finds it)
        cell_s = np.ascontiguousarray(cell_s_m, dtype=np.float64).reshape(n_b, -1)
        v_c = np.asarray(v_centres_mps, dtype=np.float64)
        self._args = (xp, np.ascontiguousarray(fp), start, bucket, inv_h, cell_s, v_c, a_c,
                      np.asarray(weights, dtype=np.float64).astype(np.float32), float(tau_s))
        # (B, L, N_v, M), valid where _done (B, L, N_v): a pair's states of one s-cell side by side, as the chain visits them
        self._values = np.empty((n_b, cell_s.shape[1], v_c.shape[0], a_c.shape[0]), np.float32)
        self._done = np.zeros((n_b, cell_s.shape[1], v_c.shape[0]), np.bool_)
        self._dense: np.ndarray | None = None

    @staticmethod
    def supports(profile_s_m) -> bool:
        """True for a profile this class interpolates exactly as np.interp: at least one knot, finite, non-decreasing."""
        s = np.asarray(profile_s_m, dtype=np.float64)
        return s.ndim == 1 and s.size > 0 and bool(np.all(np.isfinite(s))) and bool(np.all(np.diff(s) >= 0))

    def priority_at_states(self, preference, b_idx, v_idx, s_idx, forbid_threshold) -> np.ndarray:
        """``priority_at_states`` (module function) of λ_speed, computed first where it is not yet."""
        b_idx = np.asarray(b_idx, dtype=np.int64)
        v_idx = np.asarray(v_idx, dtype=np.int64)
        s_idx = np.asarray(s_idx, dtype=np.int64)
        if b_idx.shape[0]:
            _speed_fill(*self._args, self._values, self._done, b_idx, v_idx, s_idx)
        return _priority_from_states(self._values, np.ascontiguousarray(preference, dtype=np.float32), b_idx, v_idx, s_idx,
                                     np.float32(forbid_threshold))

    def full(self) -> np.ndarray:
        """λ_speed at every state, ``(B, M, N_v, L) float32``."""
        if self._dense is None:
            empty = np.zeros(0, np.int64)
            _speed_fill(*self._args, self._values, self._done, empty, empty, empty)
            self._dense = np.ascontiguousarray(np.transpose(self._values, (0, 3, 2, 1)))
        return self._dense


def speed_restriction(profile_s_m, admissible_mps, cell_s_m, v_centres_mps, input_centres_mps2, weights, tau_s):
    """``SpeedRestriction(...).full()``: every state of every pair."""
    return SpeedRestriction(profile_s_m, admissible_mps, cell_s_m, v_centres_mps, input_centres_mps2, weights, tau_s).full()


#: ``sum_by_key`` uses its compiled scratch for keys below this (an int32 per key), np.unique above.
SUM_BY_KEY_MAX_KEY = 1 << 24
_slots = threading.local()


def sum_by_key(keys: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(sorted unique keys, sum of the values of each), the numbers of ``u, inv = np.unique(keys,
    return_inverse=True); np.bincount(inv, weights=values)`` (each sum in input order), without the sort of every key:
    one pass through a scratch table of slots per key (per thread, kept between calls), then a sort of the unique keys
    only. Keys must be non-negative integers; at or above ``SUM_BY_KEY_MAX_KEY`` (or without numba) np.unique."""
    keys = np.asarray(keys, dtype=np.int64)
    values = np.asarray(values, dtype=np.float64)
    if keys.size == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.float64)
    top = int(keys.max())
    if numba is None or top >= SUM_BY_KEY_MAX_KEY or int(keys.min()) < 0:
        unique, inverse = np.unique(keys, return_inverse=True)
        return unique, np.bincount(inverse.reshape(-1), weights=values.reshape(-1), minlength=unique.size)
    return _sum_by_key(np.ascontiguousarray(keys.reshape(-1)), np.ascontiguousarray(values.reshape(-1)), _slot_table(top))


def _slot_table(top: int) -> np.ndarray:
    """The calling thread's scratch table of slots (all -1) for keys up to ``top`` (< ``SUM_BY_KEY_MAX_KEY``)."""
    slot = getattr(_slots, "table", None)
    if slot is None or slot.shape[0] <= top:
        slot = np.full(max(top + 1, 1 << 16, 2 * (0 if slot is None else slot.shape[0])), -1, np.int32)
        slot = slot[: min(slot.shape[0], SUM_BY_KEY_MAX_KEY)]
        _slots.table = slot
    return slot


_warm = False


def warm_up() -> None:
    """Compile (or load from numba's on-disk cache) every kernel now, on tiny arrays: a stage pays it when it starts,
    not on its first frame (about a second from the cache, several seconds when compiling). Once per process."""
    global _warm
    if _warm or numba is None:
        return
    slab = np.zeros((2, 2, 2, 1), np.float32)
    slab[0, 0, 0, 0] = 1.0
    ptr = np.array([0, 1, 1, 1, 1], np.int64)
    one = np.zeros(1, np.int64)
    w = np.ones(1, np.float32)
    fused_step(slab, 0, 0, 2, 2, (ptr, one, one, w, ptr, one, w), True, 0.0)
    s_idx, v_idx, b_idx = occupied_states(slab)
    lam = np.ones((s_idx.shape[0], 2), np.float32)
    priority_occupied(slab, s_idx, v_idx, b_idx, lam, np.eye(2, dtype=np.float32), np.ones(1, np.float32))
    priority_at_states(np.ones((1, 2, 2, 2), np.float32), np.ones((1, 2), np.float32), b_idx, v_idx, s_idx, 0.0)
    lazy = SpeedRestriction([np.arange(3.0)], [np.ones((1, 3))], np.zeros((1, 2)), np.ones(2), np.arange(2.0), np.ones(1), 0.4)
    lazy.priority_at_states(np.ones((1, 2), np.float32), np.zeros(1, np.int64), np.zeros(1, np.int64), np.zeros(1, np.int64), 0.0)
    lazy.full()
    half = np.full((1, 2), 0.5, np.float32)
    speed_priority_run((half, half, half), np.zeros(1, np.float32), (ptr, one, one, w, ptr, one, w), 2, True, 1e-7, np.eye(2),
                       lazy, np.ones((2, 1, 2), np.float32), [True, False], 0.0)
    sum_by_key(np.array([3, 1, 3], np.int64), np.ones(3))
    admissible_rows(np.zeros((1, 2)), np.zeros((1, 2)), [2], np.ones(1), np.ones(1), 1.0, 1e-4)
    speed_lines(np.arange(3, dtype=np.int64), np.ones(3), np.array([0, 3], np.int64), 1e-9)
    _warm = True
