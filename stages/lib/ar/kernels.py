"""Compiled (numba) kernels of the AR features' hot paths, bit for bit as the numpy code computes them:
`curvature_rows` (`features.curvature_rows`: the curvature integrals ahead of each vehicle on each of its corridors)
and `causal_slope` (`features.causal_acceleration` without shrinking: a dozen numpy calls per vehicle and frame).

The numpy code pads the corridors to one width, cleans the curvatures, integrates max(κ, 0) and min(κ, 0) by the
trapezoidal rule with one cumulative sum per row (sequential, so each row is what it alone gives) and then takes two
``np.interp`` per corridor, a few dozen numpy calls per frame plus two per corridor; here each corridor is one pass.
The same IEEE operations run in the same order (no fastmath), with numpy's rules for ``np.maximum``/``np.minimum``
and ``np.interp`` (`stages.lib.numpy_rules`). A corridor whose arc length is not strictly increasing (where
``np.interp``'s search may answer otherwise) is left to the numpy code (tests/stages/test_ar_features.py compares).

numba is a dependency; ``available()`` is False only where it cannot be imported, and `features` then uses its numpy
code.
"""

from __future__ import annotations

import math

import numpy as np

from stages.lib.numpy_rules import PAIRWISE_BLOCK, interp, maximum, minimum, pairwise_sum

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


def available() -> bool:
    """True when the compiled kernel can be used."""
    return numba is not None


def _curvature_rows(s_line, k_line, start, length, vehicle_s, offsets, out, done):
    """out (P, S, 2) of the rows whose s increases strictly (done[p] True); the rest is left to the numpy code."""
    n_seg = offsets.shape[0] - 1
    width = 0
    for p in range(start.shape[0]):
        width = max(width, length[p])
    cumulative = np.empty((2, width))
    at = np.empty((2, n_seg + 1))
    for p in range(start.shape[0]):
        n = length[p]
        a = start[p]
        if n < 2 or not math.isfinite(vehicle_s[p]):
            done[p] = True  # no usable corridor: zeros, as the numpy code leaves it
            continue
        increasing = True
        for j in range(n - 1):
            if not (s_line[a + j + 1] > s_line[a + j]):
                increasing = False
                break
        if not increasing:
            continue
        k0 = k_line[a]
        k0 = k0 if math.isfinite(k0) else 0.0
        pos0 = maximum(k0, 0.0)
        neg0 = minimum(k0, 0.0)
        cumulative[0, 0] = 0.0
        cumulative[1, 0] = 0.0
        for j in range(n - 1):
            k1 = k_line[a + j + 1]
            k1 = k1 if math.isfinite(k1) else 0.0
            pos1 = maximum(k1, 0.0)
            neg1 = minimum(k1, 0.0)
            ds = s_line[a + j + 1] - s_line[a + j]
            x_pos = 0.5 * (pos1 + pos0) * ds
            x_neg = 0.5 * (neg1 + neg0) * ds
            if j == 0:  # np.cumsum's first element is the term itself
                cumulative[0, 1] = x_pos
                cumulative[1, 1] = x_neg
            else:
                cumulative[0, j + 1] = cumulative[0, j] + x_pos
                cumulative[1, j + 1] = cumulative[1, j] + x_neg
            pos0 = pos1
            neg0 = neg1
        for b in range(n_seg + 1):
            x = vehicle_s[p] + offsets[b]
            for col in range(2):
                at[col, b] = interp(x, s_line[a : a + n], cumulative[col, :n], 0, n)
        for b in range(n_seg):
            for col in range(2):
                out[p, b, col] = at[col, b + 1] - at[col, b]
        done[p] = True


def _causal_slope(stamps_ns, speeds_mps, window_ns, half_window_s, ns):
    """`features.causal_acceleration` without shrinking, on numpy's arithmetic: the stamps within the window, then the
    least-squares slope with numpy's means and sums (`pairwise_sum`)."""
    n = stamps_ns.shape[0]
    if n < 3:
        return 0.0
    newest = stamps_ns[n - 1]
    threshold = newest - window_ns - 1_000_000
    m = 0
    for i in range(n):
        m += stamps_ns[i] >= threshold
    t = np.empty(m)
    v = np.empty(m)
    k = 0
    for i in range(n):
        if stamps_ns[i] >= threshold:
            t[k] = (stamps_ns[i] - newest) * ns
            v[k] = speeds_mps[i]
            k += 1
    if m < 3 or -t[0] < half_window_s:
        return 0.0
    t_mean = pairwise_sum(t, 0, m) / m
    v_mean = pairwise_sum(v, 0, m) / m
    for i in range(m):
        t[i] = t[i] - t_mean
    squares = np.empty(m)
    products = np.empty(m)
    for i in range(m):
        squares[i] = t[i] * t[i]
        products[i] = t[i] * (v[i] - v_mean)
    return pairwise_sum(products, 0, m) / pairwise_sum(squares, 0, m)


if numba is not None:
    _curvature_rows_compiled = numba.njit(cache=True, nogil=True, fastmath=False, boundscheck=False)(_curvature_rows)
    _causal_slope_compiled = numba.njit(cache=True, nogil=True, fastmath=False, boundscheck=False)(_causal_slope)
else:  # pragma: no cover
    _curvature_rows_compiled = None
    _causal_slope_compiled = None


def curvature_rows(s_parts, k_parts, vehicle_s: np.ndarray, offsets: np.ndarray, out: np.ndarray) -> np.ndarray | None:
    """Fill out (P, S, 2) for the corridors' arc lengths and curvatures (P arrays of equal sizes each); returns a (P,)
    bool array of the rows done (the others are the numpy code's), or None (no numba: all of them are)."""
    if _curvature_rows_compiled is None:
        return None
    lengths = np.fromiter((s.size for s in s_parts), dtype=np.int64, count=len(s_parts))
    start = np.zeros(lengths.size, np.int64)
    np.cumsum(lengths[:-1], out=start[1:])
    done = np.zeros(lengths.size, dtype=bool)
    if lengths.size:
        _curvature_rows_compiled(np.concatenate(s_parts), np.concatenate(k_parts), start, lengths,
                                 np.ascontiguousarray(vehicle_s, dtype=np.float64), np.array(offsets, dtype=np.float64), out, done)  # a writable copy: one compiled signature
    return done


def causal_slope(stamps_ns: np.ndarray, speeds_mps: np.ndarray, window_s: float, ns: float) -> float | None:
    """`features.causal_acceleration` (no shrinking) of int64 stamps and float64 speeds; None: take the numpy path (no
    numba, or more stamps than one block of numpy's pairwise sum; the tracker keeps 64)."""
    if _causal_slope_compiled is None or stamps_ns.shape != speeds_mps.shape or stamps_ns.size > PAIRWISE_BLOCK:
        return None
    return float(_causal_slope_compiled(stamps_ns, speeds_mps, int(round(window_s / ns)), 0.5 * window_s - 1e-6, float(ns)))


_warm = False


def warm_up() -> None:
    """Load the kernel from numba's on-disk cache (compile it the first time) now, on one small corridor: the stage pays
    it when it starts, not on its first frame. Once per process."""
    global _warm
    if _warm or numba is None:
        return
    curvature_rows([np.arange(3.0)], [np.zeros(3)], np.zeros(1), np.arange(2.0), np.zeros((1, 1, 2)))
    causal_slope(np.arange(3, dtype=np.int64), np.zeros(3), 1.0, 1e-9)
    _warm = True
