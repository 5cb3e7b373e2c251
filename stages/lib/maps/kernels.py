"""Compiled (numba) kernel of the map library's hot path: the windowed Frenet projection.

``project_window`` is `geometry._project_in_window`'s arithmetic, point by
point and segment by segment, without numpy's per-call overhead: the
corridors stage projects each vehicle onto each of its routes (one point, a
window of ~40 segments) and the relations stage conflict points onto
lane-change corridors, thousands of small calls per frame at a busy
junction. Every value is computed with the same IEEE operations in the same
order as the numpy path (no fastmath: no reassociation, no fused
multiply-add; ``hypot`` is the C library's, as numpy's), so the results are
the same bit for bit (tests/stages/test_maps_projection_window.py compares
them); where the numpy path would not take the windowed route (a non-finite
hint or point, an arc that decreases, a point without a segment in its
window) the kernel says so and the caller takes the numpy path.

numba is a dependency; ``available()`` is False only where it cannot be
imported, and `geometry` then uses its numpy code.
"""

from __future__ import annotations

import math

import numpy as np

try:  # pragma: no cover - exercised where numba is missing only
    import numba
except Exception:  # noqa: BLE001 - any import failure leaves the numpy path
    numba = None


def available() -> bool:
    """True when the compiled kernel can be used."""
    return numba is not None


def _project_window(points, line, arc, hints, window_m, out_s, out_d, out_seg):
    """Fill out_s, out_d, out_seg (n,) for points (n, 2) on `line` (m + 1, 2); False where the numpy path must be taken.

    For each point the segments k in [lo, hi) (lo = first k with
    arc[k + 1] >= hint - window, hi = first k with arc[k] > hint + window)
    are measured (the end segments extended: t unclipped below on segment 0
    and above on the last), the first nearest wins, as in
    `geometry._project_in_window`.
    """
    n_pts = points.shape[0]
    n_seg = line.shape[0] - 1
    if n_pts == 0 or n_seg < 2 or arc.shape[0] != n_seg + 1:
        return False
    for k in range(n_seg):
        if not (arc[k + 1] >= arc[k]):
            return False
    for i in range(n_pts):
        h = hints[i]
        px = points[i, 0]
        py = points[i, 1]
        if not (math.isfinite(h) and math.isfinite(px) and math.isfinite(py)):
            return False
        below = h - window_m
        above = h + window_m
        # lo: searchsorted(arc[1:], below, "left"); hi: searchsorted(arc[:-1], above, "right")
        a, b = 0, n_seg
        while a < b:
            mid = (a + b) >> 1
            if arc[mid + 1] < below:
                a = mid + 1
            else:
                b = mid
        lo = a
        a, b = 0, n_seg
        while a < b:
            mid = (a + b) >> 1
            if arc[mid] <= above:
                a = mid + 1
            else:
                b = mid
        hi = a
        if lo >= hi:
            return False
        best = -1
        best_d2 = math.inf
        best_t = 0.0
        for k in range(lo, hi):
            if arc[k + 1] < below or arc[k] > above:
                continue
            sx = line[k, 0]
            sy = line[k, 1]
            vx = line[k + 1, 0] - sx
            vy = line[k + 1, 1] - sy
            seg_len = math.hypot(vx, vy)
            seg_len2 = max(seg_len * seg_len, 1e-18)
            rx = px - sx
            ry = py - sy
            t = (rx * vx + ry * vy) / seg_len2
            if k != 0:
                t = max(t, 0.0)
            if k != n_seg - 1:
                t = min(t, 1.0)
            fx = sx + t * vx
            fy = sy + t * vy
            ex = px - fx
            ey = py - fy
            d2 = ex * ex + ey * ey
            if d2 != d2:
                return False  # NaN: the numpy path decides
            if d2 < best_d2:
                best = k
                best_d2 = d2
                best_t = t
        if best < 0:
            return False
        k = best
        sx = line[k, 0]
        sy = line[k, 1]
        vx = line[k + 1, 0] - sx
        vy = line[k + 1, 1] - sy
        seg_len = math.hypot(vx, vy)
        root = math.sqrt(max(seg_len * seg_len, 1e-18))
        out_s[i] = arc[k] + best_t * seg_len
        out_d[i] = (vx / root) * (py - sy) - (vy / root) * (px - sx)
        out_seg[i] = k
    return True


if numba is not None:
    _project_window_compiled = numba.njit(cache=True, nogil=True, fastmath=False, boundscheck=False)(_project_window)
else:  # pragma: no cover
    _project_window_compiled = None


def project_window(points: np.ndarray, line: np.ndarray, arc: np.ndarray, hints: np.ndarray, window_m: float):
    """(s, d, segment) (n,) of points (n, 2) float64 on a polyline within `window_m` of their hints; None: take the numpy path."""
    if _project_window_compiled is None:
        return None
    n = len(points)
    out_s = np.empty(n)
    out_d = np.empty(n)
    out_seg = np.empty(n, dtype=np.int64)
    ok = _project_window_compiled(points, line, arc, hints, float(window_m), out_s, out_d, out_seg)
    return (out_s, out_d, out_seg) if ok else None
