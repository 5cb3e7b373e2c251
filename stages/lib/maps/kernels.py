"""Compiled (numba) kernels of the map library's hot paths: Frenet projections and route sampling.

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

    if numba.config.DISABLE_JIT:  # NUMBA_DISABLE_JIT=1: the numpy reference path, not these kernels run as Python
        raise ImportError("NUMBA_DISABLE_JIT is set")
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
    # with several points, each segment's length once per call, on first use (the same hypot of the same numbers for
    # every point: wide windows, e.g. an infinite one, measure every segment for every point)
    cached = n_pts > 1
    lengths = np.empty(n_seg if cached else 0)
    known = np.zeros(n_seg if cached else 0, np.bool_)
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
            if not cached:
                seg_len = math.hypot(vx, vy)
            elif known[k]:
                seg_len = lengths[k]
            else:
                seg_len = math.hypot(vx, vy)
                lengths[k] = seg_len
                known[k] = True
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


def _segment_d2(px, py, ax, ay, vx, vy, length2, lower, upper):
    """Squared distance of (px, py) to the segment a + t·v, t clipped to [lower, upper] (relations' `_segment_d2`)."""
    rx = px - ax
    ry = py - ay
    t = min(max((rx * vx + ry * vy) / length2, lower), upper)
    ox = rx - t * vx
    oy = ry - t * vy
    return ox * ox + oy * oy, t


def _project_polylines(points, xy, arc, offsets, reach, use_reach, radius, use_radius, block, n_blocks, m,
                       out_s, out_d, hit_g, hit_k, hit_ux, hit_uy):
    """`stages.relations.core._project_onto_corridors` (its numpy code: reach boxes, pruning bound, branch and bound)
    pair by pair and candidate by candidate, on the polylines concatenated (pair g: xy[offsets[g]:offsets[g + 1]]).

    The padded numpy arrays are not built; every value they would hold is
    computed where it is read, with the same operations: segment g, j is
    xy[o + j + 1] - xy[o + j], its squared length at least 1e-18, t free
    below on segment 0 and above on the last; the pruning limit from the
    sharpest turn (1.0 among the turns when the pair is shorter than the
    longest, `m` segments, as the padding gives it); block b of a pair holds
    segments [1 + b·block, min(1 + (b + 1)·block, n - 1)) and its box the
    vertices from 1 + b·block to 1 + (b + 1)·block, clipped to the last.
    Fills out_s, out_d and (hit_g, hit_k, hit_ux, hit_uy); returns the
    number of hits, -1 where a NaN appears (the numpy code decides then).
    """
    n_pairs = offsets.shape[0] - 1
    n_points = points.shape[0]
    box_lo_x = np.empty(n_blocks)
    box_lo_y = np.empty(n_blocks)
    box_hi_x = np.empty(n_blocks)
    box_hi_y = np.empty(n_blocks)
    used = np.zeros(n_blocks, dtype=np.bool_)
    box2 = np.empty(n_blocks)
    slack = 1.0 + 1e-9
    hits = 0
    for g in range(n_pairs):
        o = offsets[g]
        ns = offsets[g + 1] - o - 1
        last = ns - 1
        # the pruning limit: |d| >= distance * cos(sharpest turn)
        limit2 = math.inf
        if use_radius:
            cos_min = 1.0
            if m > 1:
                cos_min = 1.0 if ns < m else math.inf
                prev_ux = 0.0
                prev_uy = 0.0
                for j in range(ns):
                    vx = xy[o + j + 1, 0] - xy[o + j, 0]
                    vy = xy[o + j + 1, 1] - xy[o + j, 1]
                    length = math.sqrt(max(vx * vx + vy * vy, 1e-300))
                    ux = vx / length
                    uy = vy / length
                    if j > 0:
                        c = prev_ux * ux + prev_uy * uy
                        if c != c:
                            return -1
                        cos_min = min(cos_min, c)
                    prev_ux = ux
                    prev_uy = uy
            degenerate = False
            for j in range(ns):
                vx = xy[o + j + 1, 0] - xy[o + j, 0]
                vy = xy[o + j + 1, 1] - xy[o + j, 1]
                if vx * vx + vy * vy < 1e-12:
                    degenerate = True
            r = radius[g]
            if cos_min > 0.5 and not degenerate and math.isfinite(r):
                q = r / cos_min
                limit2 = q * q
        # the blocks' boxes and first vertices
        for b in range(n_blocks):
            bf = 1 + block * b
            used[b] = bf < min(bf + block, ns - 1)
            if used[b]:
                lx = math.inf
                ly = math.inf
                hx = -math.inf
                hy = -math.inf
                for i in range(block + 1):
                    v = min(bf + i, ns)
                    lx = min(lx, xy[o + v, 0])
                    ly = min(ly, xy[o + v, 1])
                    hx = max(hx, xy[o + v, 0])
                    hy = max(hy, xy[o + v, 1])
                box_lo_x[b] = lx
                box_lo_y[b] = ly
                box_hi_x[b] = hx
                box_hi_y[b] = hy
        # the reach box
        if use_reach:
            lx = math.inf
            ly = math.inf
            hx = -math.inf
            hy = -math.inf
            for v in range(ns + 1):
                lx = min(lx, xy[o + v, 0])
                ly = min(ly, xy[o + v, 1])
                hx = max(hx, xy[o + v, 0])
                hy = max(hy, xy[o + v, 1])
            lx -= reach[g]
            ly -= reach[g]
            hx += reach[g]
            hy += reach[g]
        for k in range(n_points):
            px = points[k, 0]
            py = points[k, 1]
            if use_reach and not (px >= lx and py >= ly and px <= hx and py <= hy):
                continue
            ax = xy[o, 0]
            ay = xy[o, 1]
            vx = xy[o + 1, 0] - ax
            vy = xy[o + 1, 1] - ay
            d2_first, t_first = _segment_d2(px, py, ax, ay, vx, vy, max(vx * vx + vy * vy, 1e-18), -math.inf,
                                            math.inf if last == 0 else 1.0)
            ax = xy[o + last, 0]
            ay = xy[o + last, 1]
            vx = xy[o + last + 1, 0] - ax
            vy = xy[o + last + 1, 1] - ay
            d2_last, t_last = _segment_d2(px, py, ax, ay, vx, vy, max(vx * vx + vy * vy, 1e-18),
                                          -math.inf if last == 0 else 0.0, math.inf)
            if d2_first != d2_first or d2_last != d2_last:
                return -1
            box_min = math.inf
            vertex_min = math.inf
            for b in range(n_blocks):
                if used[b]:
                    dx = max(max(box_lo_x[b] - px, px - box_hi_x[b]), 0.0)
                    dy = max(max(box_lo_y[b] - py, py - box_hi_y[b]), 0.0)
                    v = dx * dx + dy * dy
                    bf = 1 + block * b
                    sx = xy[o + bf, 0] - px
                    sy = xy[o + bf, 1] - py
                    w = sx * sx + sy * sy
                    if v != v or w != w:
                        return -1
                    box2[b] = v
                    box_min = min(box_min, v)
                    vertex_min = min(vertex_min, w)
                else:
                    box2[b] = math.inf
            lx2 = xy[o + ns, 0] - px
            ly2 = xy[o + ns, 1] - py
            ends = min(d2_first, d2_last)
            lower_bound = min(ends, box_min)
            upper_bound = min(ends, min(vertex_min, lx2 * lx2 + ly2 * ly2))
            if not (lower_bound <= limit2 * slack):
                continue
            threshold = upper_bound * slack + 1e-12
            best = 0
            best_d2 = d2_first
            best_t = t_first
            for b in range(n_blocks):
                if box2[b] <= threshold:
                    bf = 1 + block * b
                    for j in range(bf, min(bf + block, ns - 1)):
                        ax = xy[o + j, 0]
                        ay = xy[o + j, 1]
                        vx = xy[o + j + 1, 0] - ax
                        vy = xy[o + j + 1, 1] - ay
                        d2, t = _segment_d2(px, py, ax, ay, vx, vy, max(vx * vx + vy * vy, 1e-18), 0.0, 1.0)
                        if d2 != d2:
                            return -1
                        if d2 < best_d2:
                            best, best_d2, best_t = j, d2, t
            if last > 0 and d2_last < best_d2:
                best, best_d2, best_t = last, d2_last, t_last
            j = best
            ax = xy[o + j, 0]
            ay = xy[o + j, 1]
            vx = xy[o + j + 1, 0] - ax
            vy = xy[o + j + 1, 1] - ay
            seg_len = math.sqrt(max(vx * vx + vy * vy, 1e-18))
            ux = vx / seg_len
            uy = vy / seg_len
            out_s[g, k] = arc[o + j] + best_t * seg_len
            out_d[g, k] = ux * (py - ay) - uy * (px - ax)
            hit_g[hits] = g
            hit_k[hits] = k
            hit_ux[hits] = ux
            hit_uy[hits] = uy
            hits += 1
    return hits


def _sample_route(table, s_line, starts, widths, offset, step, n, cos_first, sin_first, cos_last, sin_last, out):
    """`stages.corridors.routes.cut_corridor`'s sampling, sample by sample; False where the numpy code must decide.

    ``table`` (4, m): x, y, unwrapped heading, curvature at the arc lengths
    ``s_line``; at s = offset + i·step, ``out`` (6, n) gets s - offset, then
    x, y, the heading wrapped to [-pi, pi) and the curvature, each as
    ``np.interp`` gives it (the segment found once per sample and shared:
    the four share ``s_line``), x and y extended straight and curvature 0
    outside the route, and the width of the sample's lanelet (searchsorted
    in ``starts``, clipped).
    """
    m = s_line.shape[0]
    k = starts.shape[0]
    if m < 2 or k < 1:
        return False
    for i in range(m - 1):
        if not (s_line[i + 1] >= s_line[i]):
            return False
    for i in range(k - 1):
        if not (starts[i + 1] >= starts[i]):
            return False
    length = s_line[m - 1]
    j = 0  # the last index with s_line[j] <= s, walked forward while s grows
    w = 0  # the first index with starts[w] > s
    previous = -math.inf
    for i in range(n):
        s = offset + i * step
        if s != s:
            return False
        if s < previous:  # not increasing (step <= 0): start the walks over
            j = 0
            w = 0
        previous = s
        out[0, i] = s - offset
        while j + 1 < m and s_line[j + 1] <= s:
            j += 1
        while w < k and starts[w] <= s:
            w += 1
        out[5, i] = widths[min(max(w - 1, 0), k - 1)]
        for c in range(4):
            fp = table[c]
            if s < s_line[0]:
                v = fp[0]
            elif s > length:
                v = fp[m - 1]
            elif j == m - 1 or s_line[j] == s:
                v = fp[j]
            else:
                slope = (fp[j + 1] - fp[j]) / (s_line[j + 1] - s_line[j])
                v = slope * (s - s_line[j]) + fp[j]
                if v != v:
                    v = slope * (s - s_line[j + 1]) + fp[j + 1]
                    if v != v and fp[j] == fp[j + 1]:
                        v = fp[j]
            out[c + 1, i] = v
        if s < 0.0:  # straight on before the route's start
            out[1, i] = table[0, 0] + (s - 0.0) * cos_first
            out[2, i] = table[1, 0] + (s - 0.0) * sin_first
            out[4, i] = 0.0
        elif s > length:  # and past its end
            out[1, i] = table[0, m - 1] + (s - length) * cos_last
            out[2, i] = table[1, m - 1] + (s - length) * sin_last
            out[4, i] = 0.0
        out[3, i] = (out[3, i] + math.pi) % (2.0 * math.pi) - math.pi
    return True


def _measure_lanelets(p, pi, li, seg_start, seg_vec, seg_len2, seg_s0, seg_heading, seg_count,
                      edge_start, edge_vec, edge_len2, edge_count, s, d, centre, heading, poly_dist):
    """`stages.corridors.matching.LaneletIndex.measure`'s centreline and polygon measurements, candidate by candidate.

    For each (point pi[c], lanelet li[c]): the first nearest centreline
    segment (clipped), its foot's arc length, signed offset and heading, the
    distance to the centreline, and the distance to the polygon's boundary;
    False (the numpy code decides) where a NaN appears.
    """
    for c in range(pi.shape[0]):
        a = pi[c]
        k = li[c]
        px = p[a, 0]
        py = p[a, 1]
        best = -1
        best_d2 = math.inf
        best_t = 0.0
        for j in range(seg_count[k]):
            d2, t = _segment_d2(px, py, seg_start[k, j, 0], seg_start[k, j, 1], seg_vec[k, j, 0], seg_vec[k, j, 1], seg_len2[k, j], 0.0, 1.0)
            if d2 != d2:
                return False
            if d2 < best_d2:
                best, best_d2, best_t = j, d2, t
        if best < 0:
            return False
        j = best
        rx = px - seg_start[k, j, 0]
        ry = py - seg_start[k, j, 1]
        seg_len = math.sqrt(seg_len2[k, j])
        centre[a, k] = math.sqrt(best_d2)
        s[a, k] = seg_s0[k, j] + best_t * seg_len
        d[a, k] = (seg_vec[k, j, 0] * ry - seg_vec[k, j, 1] * rx) / seg_len
        heading[a, k] = seg_heading[k, j]
        nearest = math.inf
        for e in range(edge_count[k]):
            d2, _ = _segment_d2(px, py, edge_start[k, e, 0], edge_start[k, e, 1], edge_vec[k, e, 0], edge_vec[k, e, 1], edge_len2[k, e], 0.0, 1.0)
            if d2 != d2:
                return False
            nearest = min(nearest, d2)
        poly_dist[a, k] = math.sqrt(nearest)
    return True


def _project_point(px, py, line, arc, hint, window_m):
    """`_project_window` for one point given as numbers: (ok, s, d)."""
    points = np.empty((1, 2))
    points[0, 0] = px
    points[0, 1] = py
    hints = np.empty(1)
    hints[0] = hint
    out_s = np.empty(1)
    out_d = np.empty(1)
    out_seg = np.empty(1, np.int64)
    ok = _project_window_compiled(points, line, arc, hints, window_m, out_s, out_d, out_seg)
    return ok, out_s[0], out_d[0]


def _project_window_groups(points, point_bounds, lines, line_bounds, arcs, hints, window_m, out_s, out_d, out_seg, ok):
    """`_project_window` for groups of points, each on its own polyline: group q's points
    points[point_bounds[q]:point_bounds[q + 1]] on lines[line_bounds[q]:line_bounds[q + 1]] (arcs the same rows);
    ok[q] False where that group must take the numpy path."""
    for q in range(point_bounds.shape[0] - 1):
        a, b = point_bounds[q], point_bounds[q + 1]
        c, d = line_bounds[q], line_bounds[q + 1]
        ok[q] = _project_window_compiled(points[a:b], lines[c:d], arcs[c:d], hints[a:b], window_m, out_s[a:b], out_d[a:b], out_seg[a:b])


def _max_separation(ax, ay, bx, by, start):
    """max over i >= start of sqrt(dx² + dy²) between samples i of two polylines (the shorter one's length); NaN if
    any distance is NaN (as ndarray.max), 0.0 when none is left."""
    n = min(ax.shape[0], bx.shape[0])
    if start >= n:
        return 0.0
    best = -math.inf
    for i in range(start, n):
        dx = ax[i] - bx[i]
        dy = ay[i] - by[i]
        v = math.sqrt(dx * dx + dy * dy)
        if v != v:
            return v
        if v > best:
            best = v
    return best


def _unwrapped_interp(x, xp, fp):
    """``np.interp(x, xp, np.unwrap(fp))`` for one x, the same float operations (unwrap's corrections summed in order
    up to the segment used); NaN flag (ok False) where xp is not strictly increasing or anything is NaN."""
    m = xp.shape[0]
    if m < 2 or fp.shape[0] != m or x != x:
        return False, 0.0
    for i in range(m):
        if xp[i] != xp[i] or fp[i] != fp[i]:
            return False, 0.0
        if i and not (xp[i] > xp[i - 1]):
            return False, 0.0
    # j: the segment of np.interp (xp[j] <= x < xp[j + 1]), -1 before the start, m - 1 at or past the end
    if x < xp[0]:
        j = -1
    elif x >= xp[m - 1]:
        j = m - 1
    else:
        j = 0
        while xp[j + 1] <= x:
            j += 1
    last = max(j + 1, 0) if j < m - 1 else m - 1
    # np.unwrap: up[0] = fp[0], up[i] = fp[i] + cumsum(correction)[i - 1]
    period = 2.0 * math.pi
    high = period / 2.0
    low = -high
    up_j = fp[0]
    up_next = fp[0]
    total = 0.0
    for i in range(1, last + 1):
        dd = fp[i] - fp[i - 1]
        ddmod = (dd - low) % period + low
        if ddmod == low and dd > 0:
            ddmod = high
        correction = ddmod - dd
        if abs(dd) < high:
            correction = 0.0
        total = total + correction
        if i == j:
            up_j = fp[i] + total
        if i == j + 1:
            up_next = fp[i] + total
    if j < 0:
        return True, fp[0]  # left of xp: fp[0] (== up[0])
    if j == m - 1:
        return True, up_j if m - 1 > 0 else fp[0]
    if xp[j] == x:
        return True, up_j
    slope = (up_next - up_j) / (xp[j + 1] - xp[j])
    v = slope * (x - xp[j]) + up_j
    if v != v:
        v = slope * (x - xp[j + 1]) + up_next
        if v != v and up_j == up_next:
            v = up_j
    return True, v


if numba is not None:
    _jit = numba.njit(cache=True, nogil=True, fastmath=False, boundscheck=False)
    _max_separation_compiled = _jit(_max_separation)
    _unwrapped_interp_compiled = _jit(_unwrapped_interp)
    _measure_lanelets_compiled = _jit(_measure_lanelets)
    _sample_route_compiled = _jit(_sample_route)
    _project_window_compiled = _jit(_project_window)
    _project_point_compiled = _jit(_project_point)
    _segment_d2 = _jit(_segment_d2)
    _project_polylines_compiled = _jit(_project_polylines)
    _project_window_groups_compiled = _jit(_project_window_groups)
else:  # pragma: no cover
    _max_separation_compiled = None
    _unwrapped_interp_compiled = None
    _project_window_compiled = None
    _project_point_compiled = None
    _project_polylines_compiled = None
    _project_window_groups_compiled = None
    _sample_route_compiled = None
    _measure_lanelets_compiled = None


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


def project_window_groups(points: np.ndarray, point_bounds: np.ndarray, lines: np.ndarray, line_bounds: np.ndarray,
                          arcs: np.ndarray, hints: np.ndarray, window_m: float):
    """`project_window` for groups of points, each on its own polyline, in one call (`_project_window_groups`; float64
    points (n, 2), lines (m, 2), arcs (m,), hints (n,); int64 bounds (groups + 1,)): (s, d, segment) (n,) and ok
    (groups,), False for a group that must take the numpy path; None: no kernel."""
    if _project_window_groups_compiled is None:
        return None
    n = len(points)
    out_s = np.empty(n)
    out_d = np.empty(n)
    out_seg = np.empty(n, dtype=np.int64)
    ok = np.zeros(len(point_bounds) - 1, dtype=np.bool_)
    _project_window_groups_compiled(points, point_bounds, lines, line_bounds, arcs, hints, float(window_m), out_s, out_d, out_seg, ok)
    return out_s, out_d, out_seg, ok


def project_point(x: float, y: float, line: np.ndarray, arc: np.ndarray, s_hint_m: float, window_m: float):
    """(s, d) of one point as `project_window` gives them, without arrays on the way in or out; None: take the numpy path."""
    if _project_point_compiled is None:
        return None
    ok, s, d = _project_point_compiled(float(x), float(y), line, arc, float(s_hint_m), float(window_m))
    return (s, d) if ok else None


def project_polylines(points, xy, arc, offsets, reach, radius, block: int, n_blocks: int, m: int, out_s, out_d):
    """`_project_polylines` compiled (``reach``, ``radius`` (pairs,) or None): fills out_s, out_d (pairs, points);
    returns (g, k, ux, uy) of the projected (pair, point), the foot segments' directions; None: take the numpy path."""
    if _project_polylines_compiled is None:
        return None
    n = out_s.size
    hit_g = np.empty(n, np.int64)
    hit_k = np.empty(n, np.int64)
    hit_ux = np.empty(n)
    hit_uy = np.empty(n)
    n_pairs = len(offsets) - 1
    hits = _project_polylines_compiled(
        points, xy, arc, offsets,
        np.zeros(n_pairs) if reach is None else np.asarray(reach, np.float64), reach is not None,
        np.zeros(n_pairs) if radius is None else np.asarray(radius, np.float64), radius is not None,
        int(block), int(n_blocks), int(m), out_s, out_d, hit_g, hit_k, hit_ux, hit_uy,
    )
    if hits < 0:
        return None
    return hit_g[:hits], hit_k[:hits], hit_ux[:hits], hit_uy[:hits]


def sample_route(table, s_line, starts, widths, offset: float, step: float, n: int, end_directions):
    """`_sample_route` compiled: the corridor's (s - offset, x, y, wrapped heading, curvature, width) (n,); None: numpy.

    ``end_directions``: cos and sin of the route's first and last heading.
    """
    if _sample_route_compiled is None:
        return None
    out = np.empty((6, n))
    cos_first, sin_first, cos_last, sin_last = end_directions
    if not _sample_route_compiled(table, s_line, starts, widths, offset, step, n, cos_first, sin_first, cos_last, sin_last, out):
        return None
    return out[0], out[1], out[2], out[3], out[4], out[5]


def measure_lanelets(p, pi, li, seg_start, seg_vec, seg_len2, seg_s0, seg_heading, seg_count,
                     edge_start, edge_vec, edge_len2, edge_count, s, d, centre, heading, poly_dist) -> bool:
    """`_measure_lanelets` compiled: fills s, d, centre, heading, poly_dist (points, lanelets) at the candidates; False: numpy."""
    if _measure_lanelets_compiled is None:
        return False
    return bool(_measure_lanelets_compiled(p, pi, li, seg_start, seg_vec, seg_len2, seg_s0, seg_heading, seg_count,
                                           edge_start, edge_vec, edge_len2, edge_count, s, d, centre, heading, poly_dist))


_F64 = np.dtype(np.float64)


def _plain(*arrays) -> bool:
    """All 1-D native float64 ndarrays (the layouts the small kernels are compiled for; anything else takes numpy)."""
    for a in arrays:
        if type(a) is not np.ndarray or a.dtype is not _F64 or a.ndim != 1:
            return False
    return True


def max_separation(ax: np.ndarray, ay: np.ndarray, bx: np.ndarray, by: np.ndarray, start: int) -> float | None:
    """`_max_separation` compiled (float64 (n,) arrays); None: take the numpy path."""
    if _max_separation_compiled is None or not _plain(ax, ay, bx, by):
        return None
    return _max_separation_compiled(ax, ay, bx, by, int(start))


def unwrapped_interp(x: float, xp: np.ndarray, fp: np.ndarray) -> float | None:
    """`_unwrapped_interp` compiled (float64 (m,) arrays); None: take the numpy path."""
    if _unwrapped_interp_compiled is None or not _plain(xp, fp):
        return None
    ok, value = _unwrapped_interp_compiled(float(x), xp, fp)
    return value if ok else None


_warm = False


def warm_up() -> None:
    """Load every kernel from numba's on-disk cache (compile it the first time) now, on tiny arrays laid out as the
    stages pass them (the routes' arc lengths are read-only, a corridor's are not): the corridors and relations
    stages pay it when they start (about a second), not on their first frame. Once per process."""
    global _warm
    if _warm or numba is None:
        return
    line = np.column_stack([np.arange(4.0), np.zeros(4)])
    arc = np.arange(4.0)
    frozen = arc.copy()
    frozen.flags.writeable = False
    point = np.array([[1.5, 0.5]])
    for s_m in (arc, frozen):
        project_window(point, line, s_m, np.array([1.0]), 2.0)
    project_point(1.5, 0.5, line, frozen, 1.0, 2.0)
    table = np.ascontiguousarray(np.stack([line[:, 0], line[:, 1], np.zeros(4), np.zeros(4)]))
    sample_route(table, frozen, np.array([0.0, 2.0]), np.array([3.0, 3.5]), -1.0, 0.5, 12, (1.0, 0.0, 1.0, 0.0))
    seg = np.zeros((1, 3, 2))
    seg[0, :, 0] = 1.0
    out = [np.full((1, 1), np.nan) for _ in range(4)]
    measure_lanelets(point, np.zeros(1, np.int64), np.zeros(1, np.int64), line[None, :3].copy(), seg, np.ones((1, 3)),
                     np.zeros((1, 3)), np.zeros((1, 3)), np.array([3], np.int64), line[None, :3].copy(), seg, np.ones((1, 3)),
                     np.array([3], np.int64), *out, np.full((1, 1), np.inf))
    project_polylines(point, line, arc, np.array([0, 4], np.int64), np.ones(1), np.ones(1), 8, 1, 3,
                      np.full((1, 1), np.nan), np.full((1, 1), np.nan))
    bounds = np.array([0, 1], np.int64)
    project_window_groups(point, bounds, line, np.array([0, 4], np.int64), arc, np.array([1.0]), 2.0)
    for a in (arc, frozen):  # the corridors' arrays as built (writable) and as decoded from the bus (read-only)
        max_separation(a, a, a, a, 1)
        unwrapped_interp(1.5, a, a)
    _warm = True
