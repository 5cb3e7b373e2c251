"""Compiled (numba) kernels of the particle filter's hot paths: locating particles on their corridors, their pose and
their admissible speed (`tables.PairTables.pose`, `tables.PairTables.admissible_speed`).

The numpy path places every particle by one ``searchsorted`` over the
frame's concatenated key array (T ~ 5,000 samples at a busy junction) and
then gathers and combines ten arrays of V × N particles, a few dozen numpy
calls per filter step; here each particle is placed and evaluated in one
pass. Every value is computed with the same IEEE operations in the same
order as the numpy path (no fastmath: no reassociation, no fused
multiply-add; ``sin``/``cos`` are the C library's, which numpy's float64
``sin``/``cos`` give bit for bit), and the search is numpy's binary search
with its comparison (a NaN sorts last), so the results are the same bit for
bit (tests/stages/test_intentions_kernels.py compares them).

numba is a dependency; ``available()`` is False only where it cannot be
imported, and `tables` then uses its numpy code.
"""

from __future__ import annotations

import math

import numpy as np

try:  # pragma: no cover - exercised where numba is missing only
    import numba
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


def _clip(x, lo, hi):
    """``np.clip(x, lo, hi)`` of one float as numpy's loop computes it: NaN stays NaN, max then min (so −0.0 → lo = 0.0)."""
    if x != x:
        return x
    r = x if x > lo else lo
    return r if r < hi else hi


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


def _admissible_speed(key, start, end, s_line, v_adm, g, s_m, style, key_offset, out):
    """`tables.PairTables.admissible_speed` of flat particles g, s_m, style (n,) into out (n,)."""
    for n in range(g.shape[0]):
        i, t, _s = _locate_one(key, start, end, s_line, g[n], s_m[n], key_offset)
        tc = _clip(t, 0.0, 1.0)
        j = style[n]
        v0 = v_adm[j, i]
        out[n] = v0 + tc * (v_adm[j, i + 1] - v0)


if numba is not None:
    _jit = numba.njit(cache=True, nogil=True, fastmath=False, boundscheck=False)
    _clip = _jit(_clip)
    _locate_one = _jit(_locate_one)
    _pose_compiled = _jit(_pose)
    _admissible_speed_compiled = _jit(_admissible_speed)
else:  # pragma: no cover
    _pose_compiled = None
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


def admissible_speed(tables, g: np.ndarray, s_m: np.ndarray, style: np.ndarray, key_offset_m: float):
    """v_adm as `tables.PairTables.admissible_speed` computes it; None: take the numpy path."""
    if _admissible_speed_compiled is None:
        return None
    (gf, sf, jf), shape = _flat(np.asarray(g, dtype=np.int64), np.asarray(s_m, dtype=np.float64), np.asarray(style, dtype=np.int64))
    out = np.empty(gf.size)
    _admissible_speed_compiled(tables.key, tables.start, tables.end, tables.s_m, np.ascontiguousarray(tables.v_adm_mps), gf, sf, jf,
                               float(key_offset_m), out)
    return out.reshape(shape)


_warm = False


def warm_up() -> None:
    """Load the kernels from numba's on-disk cache (compile them the first time) now, on a one-pair table: the stage
    pays it when it starts, not on its first frame. Once per process."""
    global _warm
    if _warm or numba is None:
        return
    from stages.intentions.tables import KEY_OFFSET_M

    class _Table:
        key = np.array([0.0, 1.0, 2.0])
        start = np.zeros(1, np.int64)
        end = np.full(1, 3, np.int64)
        s_m = key
        x_m = key
        y_m = np.zeros(3)
        heading_rad = np.zeros(3)
        v_adm_mps = np.ones((1, 3))

    one = np.zeros((1, 1), np.int64)
    pose(_Table, one, np.full((1, 1), 0.5), np.zeros((1, 1)), KEY_OFFSET_M)
    admissible_speed(_Table, one, np.full((1, 1), 0.5), one, KEY_OFFSET_M)
    _warm = True
