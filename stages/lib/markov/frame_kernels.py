"""Compiled (numba) kernels of the markov_prediction stage's outputs: rasterising and fusing the motion grid.

- ``footprint_grids``: every vehicle's sparse grid in one call, the numbers of
  ``stages.markov_prediction.rasterise.vehicle_grid``, from the compact
  footprints (sub-sample centres and normals, lateral offsets) without the
  ``(B, L, P)`` sample arrays: each sample point is formed where it is used,
  with the same float64 operations numpy does (x + n·offset, then + d·n for a
  lateral shift).
- ``footprint_bounds``: the extent of the samples of the used cells (what
  ``GridFrame.around`` is given), without gathering them.
- ``fuse_sorted``: the fused grid, 1 − Π (1 − g) per cell over vehicles
  whose keys are each sorted and unique (``rasterise.fuse``): each cell's
  product in vehicle order, step by step through a table of the grid's
  cells (in cache) instead of one over every key; ranges of steps on
  threads of their own where there are many terms.
- ``add_running_sums``: ``rasterise.unwrap_each``'s running sums of the corrections, every corridor's in one
  pass (np.cumsum's order).
- ``along_rows``: the s-distributions of the pairs blurred along their corridors, every row in one call, only the
  cells that hold mass scattered (``spread.blur_along``), and with ``spread.along_spread`` the window padded, what
  the blur put behind the car folded ahead of it and the cells past the corridor's end cut, in the same pass
  (without a padded copy of the input).
- ``blur_cells``: one step of a vehicle's grid blurred as ``spread.blur_step`` and ``spread.block_cells_sorted``
  do it (cloud in cell onto blocks, scipy's ``gaussian_filter`` arithmetic, the blocks' cells above a value in
  cell order), in one call: the same numbers.

numba is a dependency; ``available()`` is False only where it cannot be
imported, and ``rasterise`` then uses its numpy definitions (the reference
tests/stages/test_markov_batched_outputs.py compares against).
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
    """True when the compiled kernels can be used."""
    return numba is not None


def exact_inverse(cell: float) -> float:
    """1/cell when x/cell == x·(1/cell) for every x (cell a power of two: both are the exact quotient rounded
    once), else 0.0 (divide)."""
    mantissa, _ = math.frexp(cell)
    return 1.0 / cell if cell > 0 and mantissa == 0.5 else 0.0


if numba is not None:
    from stages.lib.markov import kernels
    from stages.lib.markov.kernels import _slot_add

    @numba.njit(cache=True, nogil=True, boundscheck=False)
    def _footprint_grids(x_c, y_c, nx, ny, offsets, sample_w, cell_rows, probs, pair_w, wide, shifts, has_shift, lat_rows, ptr, members, origin_x, origin_y, cell, inv_cell, n_rows, n_cols, min_mass):  # pragma: no cover - compiled
        """Per vehicle (its pairs ``members[ptr[n]:ptr[n + 1]]``), the sorted keys and sums of ``vehicle_grid``: the
        same float64 operations, each key's sum taken in the order ``vehicle_grid`` concatenates its terms (as
        np.bincount adds them). Sample q = sub·n_lat + lat of cell i lies at x_c[r, sub] + nx[r, sub]·offsets[lat], r =
        cell_rows[b, i] (``FootprintBatch.x_m``; a cell with mass and no row, -1, has its samples off the grid, NaN).
        Step by step (keys of different steps never meet): first the box of the step's cells from the two end samples
        of each footprint line (a sample's column and row are linear in its offset, so every sample of the line lies
        between its ends; one cell wider on each side for rounding, cut to the grid), then each sample added to its
        cell's sum as it is formed (a dense table over the box, kept all 0.0 between steps, read row by row for the
        keys' order; or, when the box is much larger than its samples, a slot per cell of the grid and a sort).
        ``sample_w`` (W, P): with ``lat_rows`` None its row 0 weighs every step's samples; else step k of pair b takes
        row ``lat_rows[b, k]`` and every sample of weight 0 is left out (a lateral spread per step:
        ``rasterise.lateral_table``). Returns keys, sums and the (n_vehicles + 1,) offsets of each vehicle's part."""
        n_k, n_l = probs.shape[1], probs.shape[2]
        n_sub = x_c.shape[1]
        n_lat = offsets.shape[0]
        n_p = n_sub * n_lat
        n_cells = n_rows * n_cols
        n_veh = ptr.shape[0] - 1
        n_w = sample_w.shape[0]
        # per weight row: its first and last lateral offset of weight > 0 (the ends of a footprint line, for the box)
        lat_first = np.zeros(n_w, np.int64)
        lat_last = np.full(n_w, n_lat - 1, np.int64)
        if lat_rows is not None:
            for u in range(n_w):
                lo, hi = n_lat, -1
                for sub in range(n_sub):
                    for lat in range(n_lat):
                        if sample_w[u, sub * n_lat + lat] != 0.0:
                            lo, hi = min(lo, lat), max(hi, lat)
                lat_first[u], lat_last[u] = lo, hi
        total = 0
        for n in range(n_veh):
            for k in range(n_k):
                for m in range(ptr[n], ptr[n + 1]):
                    b = members[m]
                    if pair_w[b] <= 0:
                        continue
                    for i in range(n_l):
                        if probs[b, k, i] > min_mass:
                            total += n_p
        keys_out = np.empty(total, np.int64)
        sums_out = np.empty(total, np.float64)
        out_ptr = np.zeros(n_veh + 1, np.int64)
        box = np.zeros(4096, np.float64)
        touched = np.zeros(4096, np.bool_)
        slot = np.full(0, -1, np.int32)
        uniq = np.empty(0, np.int64)
        sums = np.empty(0, np.float64)
        f32 = np.float32
        use_inv = inv_cell > 0.0
        col_at = np.empty(n_lat, np.float64)  # one footprint line's samples: column and row (cells, not yet floored)
        row_at = np.empty(n_lat, np.float64)
        at = 0
        for n in range(n_veh):
            for k in range(n_k):
                # pass 1: the box of the step's samples from each footprint line's two end samples (a sample's column and
                # row are linear along its line), one cell wider on each side for rounding, within the grid
                c = 0
                col_min, col_max, row_min, row_max = np.inf, -np.inf, np.inf, -np.inf
                for m in range(ptr[n], ptr[n + 1]):
                    b = members[m]
                    if pair_w[b] <= 0:
                        continue
                    d = shifts[b, k]
                    w_row = 0
                    if lat_rows is not None:
                        w_row = lat_rows[b, k]
                    l0, l1 = lat_first[w_row], lat_last[w_row]
                    if l1 < l0:
                        continue
                    for i in range(n_l):
                        if not probs[b, k, i] > min_mass:
                            continue
                        r = cell_rows[b, i]
                        if r < 0:
                            continue
                        c += n_p
                        for sub in range(n_sub):
                            xs, ys, nxs, nys = x_c[r, sub], y_c[r, sub], nx[r, sub], ny[r, sub]
                            for lat in (l0, l1):
                                off = offsets[lat]
                                x = xs + nxs * off
                                y = ys + nys * off
                                if has_shift:
                                    x = x + d * nxs
                                    y = y + d * nys
                                if use_inv:
                                    col = (x - origin_x) * inv_cell
                                    row = (y - origin_y) * inv_cell
                                else:
                                    col = (x - origin_x) / cell
                                    row = (y - origin_y) / cell
                                if col == col and row == row:  # (a NaN line has no sample on the grid)
                                    col_min, col_max = min(col_min, col), max(col_max, col)
                                    row_min, row_max = min(row_min, row), max(row_max, row)
                if c == 0 or not (col_max >= 0 and row_max >= 0 and col_min < n_cols and row_min < n_rows):  # (NaN: none)
                    continue
                c_lo = max(np.int64(np.floor(max(col_min, -2.0))) - 1, 0)
                c_hi = min(np.int64(np.floor(min(col_max, n_cols + 1.0))) + 1, n_cols - 1)
                r_lo = max(np.int64(np.floor(max(row_min, -2.0))) - 1, 0)
                r_hi = min(np.int64(np.floor(min(row_max, n_rows + 1.0))) + 1, n_rows - 1)
                width = c_hi - c_lo + 1
                area = (r_hi - r_lo + 1) * width
                dense = area <= 8 * c + 4096
                if dense:
                    if box.shape[0] < area:
                        box = np.zeros(max(area, 2 * box.shape[0]), np.float64)
                        touched = np.zeros(box.shape[0], np.bool_)
                else:
                    if slot.shape[0] == 0:
                        slot = np.full(n_cells, -1, np.int32)
                    if uniq.shape[0] < c:
                        uniq = np.empty(max(c, 2 * uniq.shape[0]), np.int64)
                        sums = np.empty(uniq.shape[0], np.float64)
                u = 0
                # pass 2: every sample, in vehicle_grid's order, added to its cell's sum as it is formed
                for m in range(ptr[n], ptr[n + 1]):
                    b = members[m]
                    w = pair_w[b]
                    if w <= 0:
                        continue
                    d = shifts[b, k]
                    w32 = f32(w)
                    w_row = 0
                    if lat_rows is not None:
                        w_row = lat_rows[b, k]
                    for i in range(n_l):
                        p = probs[b, k, i]
                        if not p > min_mass:
                            continue
                        mass = w * np.float64(p) if wide[b] else np.float64(w32 * p)
                        r = cell_rows[b, i]
                        if r < 0:
                            continue
                        for sub in range(n_sub):
                            xs, ys, nxs, nys = x_c[r, sub], y_c[r, sub], nx[r, sub], ny[r, sub]
                            # the line's samples first, in loops without branches (vectorised; the same operations:
                            # (x + n·offset) + d·n, then (· − origin)·(1/cell) or / cell)
                            if has_shift:
                                dx, dy = d * nxs, d * nys
                                if use_inv:
                                    for lat in range(n_lat):
                                        col_at[lat] = ((xs + nxs * offsets[lat]) + dx - origin_x) * inv_cell
                                        row_at[lat] = ((ys + nys * offsets[lat]) + dy - origin_y) * inv_cell
                                else:
                                    for lat in range(n_lat):
                                        col_at[lat] = ((xs + nxs * offsets[lat]) + dx - origin_x) / cell
                                        row_at[lat] = ((ys + nys * offsets[lat]) + dy - origin_y) / cell
                            elif use_inv:
                                for lat in range(n_lat):
                                    col_at[lat] = ((xs + nxs * offsets[lat]) - origin_x) * inv_cell
                                    row_at[lat] = ((ys + nys * offsets[lat]) - origin_y) * inv_cell
                            else:
                                for lat in range(n_lat):
                                    col_at[lat] = ((xs + nxs * offsets[lat]) - origin_x) / cell
                                    row_at[lat] = ((ys + nys * offsets[lat]) - origin_y) / cell
                            for lat in range(n_lat):
                                sw = sample_w[w_row, sub * n_lat + lat]
                                if lat_rows is not None:
                                    if sw == 0.0:
                                        continue
                                col = col_at[lat]
                                row = row_at[lat]
                                if not (col >= 0 and col < n_cols and row >= 0 and row < n_rows):
                                    continue
                                ri, ci = np.int64(row), np.int64(col)
                                if dense:
                                    idx = (ri - r_lo) * width + (ci - c_lo)
                                    box[idx] += mass * sw
                                    touched[idx] = True
                                else:
                                    u = _slot_add(ri * n_cols + ci, mass * sw, slot, uniq, sums, u)
                base = k * n_cells
                j = at
                if dense:
                    for idx in range(area):
                        if touched[idx]:
                            r2, cc = divmod(idx, width)
                            keys_out[j] = base + (r_lo + r2) * n_cols + (c_lo + cc)
                            sums_out[j] = box[idx]
                            j += 1
                            box[idx] = 0.0
                            touched[idx] = False
                else:
                    ordered = np.sort(uniq[:u])
                    for q in range(u):
                        idx = ordered[q]
                        keys_out[j] = base + idx
                        sums_out[j] = sums[slot[idx]]
                        j += 1
                    for q in range(u):
                        slot[ordered[q]] = -1
                at = j
            out_ptr[n + 1] = at
        return keys_out[:at], sums_out[:at], out_ptr

    @numba.njit(cache=True, nogil=True, boundscheck=False)
    def _correlate_symmetric(line, out, w, radius):  # pragma: no cover - compiled
        """scipy.ndimage.correlate1d of one line with a symmetric kernel ``w`` (2·radius + 1, centre ``w[radius]``),
        mode "constant" (0 outside), in its arithmetic: out[i] = line[i]·w[r], then + (line[i − j] + line[i + j])·w[r − j]
        for j = r, r − 1, ..., 1."""
        n = line.shape[0]
        for i in range(n):
            acc = line[i] * w[radius]
            for jj in range(-radius, 0):
                lo = i + jj
                hi = i - jj
                a = line[lo] if lo >= 0 else 0.0
                b = line[hi] if hi < n else 0.0
                acc += (a + b) * w[radius + jj]
            out[i] = acc

    @numba.njit(cache=True, nogil=True, boundscheck=False)
    def _blur_cells(cells, values, n_rows, n_cols, f, pad, w, radius, min_value):  # pragma: no cover - compiled
        """``spread.blur_step`` then ``spread.block_cells_sorted`` of one step (cells sorted, values float64): the cells
        (increasing) and values of the blurred step above ``min_value``, the same float64 operations in the same order
        (the cloud-in-cell sums corner by corner in the cells' order, as np.bincount of the four corners; the filter
        along the block rows, then along the block columns, as scipy's gaussian_filter)."""
        n = cells.shape[0]
        r_min, r_max, c_min, c_max = n_rows, -1, n_cols, -1
        for q in range(n):
            r, c = cells[q] // n_cols, cells[q] % n_cols
            r_min, r_max, c_min, c_max = min(r_min, r), max(r_max, r), min(c_min, c), max(c_max, c)
        r0, c0 = r_min - pad - f, c_min - pad - f
        n_r = (r_max + pad + f + 1 - r0 + f - 1) // f + 1
        n_c = (c_max + pad + f + 1 - c0 + f - 1) // f + 1
        blocks = np.zeros((n_r, n_c))
        half = 0.5 * (f - 1)
        bu, bw = np.empty(n, np.int64), np.empty(n, np.int64)
        fu, fw = np.empty(n), np.empty(n)
        for q in range(n):  # each cell's nearest block centres (below, left) and its fractions towards the next
            u = ((cells[q] // n_cols - r0) - half) / f
            v = ((cells[q] % n_cols - c0) - half) / f
            bu[q], bw[q] = np.int64(np.floor(u)), np.int64(np.floor(v))
            fu[q], fw[q] = u - bu[q], v - bw[q]
        for corner in range(4):  # the corners in turn, each over the cells in order
            du, dw = corner // 2, corner % 2
            for q in range(n):
                wu = fu[q] if du else 1.0 - fu[q]
                ww = fw[q] if dw else 1.0 - fw[q]
                blocks[bu[q] + du, bw[q] + dw] += values[q] * wu * ww
        line = np.empty(max(n_r, n_c))
        out = np.empty(max(n_r, n_c))
        for j in range(n_c):  # along axis 0 (down each column of blocks)
            for i in range(n_r):
                line[i] = blocks[i, j]
            _correlate_symmetric(line[:n_r], out[:n_r], w, radius)
            for i in range(n_r):
                blocks[i, j] = out[i]
        for i in range(n_r):  # then along axis 1
            for j in range(n_c):
                line[j] = blocks[i, j]
            _correlate_symmetric(line[:n_c], out[:n_c], w, radius)
            for j in range(n_c):
                blocks[i, j] = out[j]
        ff = f * f
        for i in range(n_r):  # each block's value per cell, once (the division of every cell of the block)
            for j in range(n_c):
                blocks[i, j] = blocks[i, j] / ff
        row_lo, row_hi = max(r0, 0), min(r0 + n_r * f, n_rows)
        col_lo, col_hi = max(c0, 0), min(c0 + n_c * f, n_cols)
        n_out = max(row_hi - row_lo, 0) * max(col_hi - col_lo, 0)
        keys = np.empty(n_out, np.int64)
        vals = np.empty(n_out, np.float64)
        block_col = np.empty(max(col_hi - col_lo, 0), np.int64)
        for col in range(col_lo, col_hi):
            block_col[col - col_lo] = (col - c0) // f
        k = 0
        for row in range(row_lo, row_hi):
            per_cell = blocks[(row - r0) // f]
            base = row * n_cols
            for col in range(col_lo, col_hi):
                x = per_cell[block_col[col - col_lo]]
                if x > min_value:
                    keys[k] = base + col
                    vals[k] = x
                    k += 1
        return keys[:k].copy(), vals[:k].copy()

    @numba.njit(cache=True, nogil=True, boundscheck=False)
    def _along_rows(probs, pad, which, weights, radii, min_value, start_cell, fold, beyond, out):  # pragma: no cover - compiled
        """``spread.along_spread`` in one pass per row (b, k): row k of pair b of ``probs`` (B, K, L), placed ``pad``
        cells into its row of ``out`` (B, K, L + 2·pad; the pad cells 0), blurred: each sum of v·w over the cells that
        hold mass (v ≠ 0), taken in float64 in cell order, what falls past either end dropped, a sum at or below
        ``min_value`` set to 0 (``spread.blur_along``'s numpy definition, each sum in another order; the pad's zeros add
        nothing; each row of ``weights`` centred at its middle), a row without a σ (``which`` < 0) copied as is; then
        with ``fold`` the blur's excess behind ``start_cell[b]`` moved to the mirrored cell (``spread.fold_behind``'s
        float32 operations), then the cells ``beyond[b]`` set to 0."""
        n_b, n_k, n_l = probs.shape
        n_o = out.shape[2]
        top = (weights.shape[1] - 1) // 2  # each row of ``weights`` centred there
        acc = np.zeros(n_o)
        zero = np.float32(0.0)
        for b in range(n_b):
            start = start_cell[b]
            behind = min(max(start, 0), n_o)
            for k in range(n_k):
                u = which[b * n_k + k]
                row = out[b, k]
                if u < 0:
                    for l in range(n_o):
                        row[l] = zero
                    for l in range(n_l):
                        row[l + pad] = probs[b, k, l]
                else:
                    rad = radii[u]
                    for l in range(n_o):
                        acc[l] = 0.0
                    for l in range(n_l):
                        v = np.float64(probs[b, k, l])
                        if v == 0.0:
                            continue
                        lp = l + pad
                        lo = lp - rad if lp > rad else 0
                        hi = lp + rad + 1 if lp + rad + 1 < n_o else n_o
                        for m in range(lo, hi):
                            acc[m] += v * weights[u, m - lp + top]
                    for l in range(n_o):
                        a = acc[l]
                        row[l] = a if a > min_value else 0.0
                if fold:
                    for j in range(behind):
                        blurred = row[j]
                        i = j - pad
                        before = probs[b, k, i] if 0 <= i < n_l else zero
                        excess = blurred - (blurred if blurred <= before else before)
                        row[j] = blurred - excess
                        target = 2 * start - j
                        if target < n_o:
                            row[target] = row[target] + excess
                for l in range(n_o):
                    if beyond[b, l]:
                        row[l] = zero

    @numba.njit(cache=True, nogil=True, boundscheck=False)
    def _add_running_sums(p, correct, ends, out):  # pragma: no cover - compiled
        """Per run [ends[n - 1], ends[n]) of ``p`` (ends[-1] taken as 0): out[start + 1 + j] = p[start + 1 + j] +
        correct[start : start + 1 + j].cumsum()[-1], the running sum taken as np.cumsum takes it (from its first term,
        each next one added in order); out[start] is left as it is."""
        start = 0
        for n in range(ends.shape[0]):
            end = ends[n]
            if end - start > 1:
                r = correct[start]
                out[start + 1] = p[start + 1] + r
                for i in range(start + 2, end):
                    r = r + correct[i - 1]
                    out[i] = p[i] + r
            start = end

    @numba.njit(cache=True, nogil=True, boundscheck=False)
    def _footprint_bounds(x_c, y_c, nx, ny, offsets, cell_rows, used):  # pragma: no cover - compiled
        """(x min, x max, y min, y max, samples seen, a NaN seen) over the samples of the cells ``used[b, i]`` (a cell
        without a row in ``cell_rows`` counts as NaN). A footprint line of finite centre and normal, with the offsets
        increasing and finite, is read at its two end samples only: x = xs + nxs·offset rounds monotonically in the
        offset (a product and a sum, each correctly rounded), so its extremes are the ends' to the bit, and none of
        its samples is NaN; any other line sample by sample."""
        x_lo, x_hi, y_lo, y_hi = np.inf, -np.inf, np.inf, -np.inf
        seen = 0
        nan = False
        n_lat = offsets.shape[0]
        ends_only = n_lat > 0 and np.isfinite(offsets[0]) and np.isfinite(offsets[n_lat - 1])
        for lat in range(1, n_lat):
            if not offsets[lat] > offsets[lat - 1]:
                ends_only = False
        for b in range(used.shape[0]):
            for i in range(used.shape[1]):
                if not used[b, i]:
                    continue
                r = cell_rows[b, i]
                if r < 0:
                    nan = True
                    continue
                for sub in range(x_c.shape[1]):
                    xs, ys, nxs, nys = x_c[r, sub], y_c[r, sub], nx[r, sub], ny[r, sub]
                    if ends_only and np.isfinite(xs) and np.isfinite(ys) and np.isfinite(nxs) and np.isfinite(nys):
                        for lat in (0, n_lat - 1):
                            x = xs + nxs * offsets[lat]
                            y = ys + nys * offsets[lat]
                            x_lo, x_hi, y_lo, y_hi = min(x_lo, x), max(x_hi, x), min(y_lo, y), max(y_hi, y)
                        seen += n_lat
                        continue
                    for lat in range(n_lat):
                        x = xs + nxs * offsets[lat]
                        y = ys + nys * offsets[lat]
                        if np.isnan(x) or np.isnan(y):
                            nan = True
                        x_lo, x_hi, y_lo, y_hi = min(x_lo, x), max(x_hi, x), min(y_lo, y), max(y_hi, y)
                        seen += 1
        return x_lo, x_hi, y_lo, y_hi, seen, nan

    @numba.njit(cache=True, nogil=True, boundscheck=False)
    def _step_bounds(keys, ptr, n_cells, n_steps):  # pragma: no cover - compiled
        """(n_runs, n_steps + 1): where each run ``keys[ptr[n]:ptr[n + 1]]`` (sorted) reaches k·n_cells, k = 0 … n_steps
        (np.searchsorted from the step before's place, so they never decrease; on a run that is not sorted some index,
        which ``_fuse_steps`` then finds out)."""
        n_runs = ptr.shape[0] - 1
        out = np.empty((n_runs, n_steps + 1), np.int64)
        for n in range(n_runs):
            lo = ptr[n]
            for k in range(n_steps + 1):
                lo += np.searchsorted(keys[lo:ptr[n + 1]], k * n_cells)
                out[n, k] = lo
        return out

    @numba.njit(cache=True, nogil=True, boundscheck=False)
    def _fuse_steps(keys, values, ptr, bounds, n_cells, top, k0, k1):  # pragma: no cover - compiled
        """Steps k0 … k1 − 1 of the fusion (``fuse_sorted``): the sorted unique keys of those steps over the runs
        ``keys[ptr[n]:ptr[n + 1]]`` (the part of run n in step k: ``bounds[n, k]`` to ``bounds[n, k + 1]``) and each
        key's 1 − Π (1 − g) over its terms g = ``values`` clipped to [0, ``top``] (NaN stays NaN), the product taken in
        run order from 1.0; a key of one term keeps its g (no rounding through 1 − g); ok False (nothing else
        meaningful) when a run's part is not sorted and unique, or a key lies outside the step ``bounds`` put it in."""
        n_runs = ptr.shape[0] - 1
        size = 0
        for n in range(n_runs):
            for k in range(k0, k1):
                for j in range(bounds[n, k], bounds[n, k + 1]):
                    key = keys[j]
                    if key < k * n_cells or key >= (k + 1) * n_cells or (j > ptr[n] and key <= keys[j - 1]):
                        return np.empty(0, np.int64), np.empty(0, np.float64), False
            size += bounds[n, k1] - bounds[n, k0]
        keys_out = np.empty(size, np.int64)
        sums_out = np.empty(size, np.float64)
        if size == 0:
            return keys_out, sums_out, True
        # per cell of a step: the product of its (1 − g) (from 1.0), its first g and its number of terms (0: none yet;
        # kept so between steps); the cells listed as they first come
        prod = np.ones(n_cells, np.float64)
        first = np.zeros(n_cells, np.float64)
        count = np.zeros(n_cells, np.int32)
        uniq = np.empty(min(size, n_cells) + 1, np.int64)
        at = 0
        for k in range(k0, k1):
            base = k * n_cells
            u = 0
            lo, hi = n_cells, -1
            for n in range(n_runs):  # in run order: each cell's terms in the order of the concatenated runs
                for j in range(bounds[n, k], bounds[n, k + 1]):
                    idx = keys[j] - base
                    g = values[j]
                    if g < 0.0:
                        g = 0.0
                    elif g > top:
                        g = top
                    prod[idx] *= 1.0 - g
                    if count[idx] == 0:
                        first[idx] = g
                        uniq[u] = idx
                        u += 1
                    count[idx] += 1
                    lo, hi = min(lo, idx), max(hi, idx)
            if u == 0:
                continue
            if hi - lo + 1 <= 16 * u:  # a scan of the cells' range lists them in key order
                for idx in range(lo, hi + 1):
                    if count[idx] > 0:
                        keys_out[at] = base + idx
                        sums_out[at] = first[idx] if count[idx] == 1 else 1.0 - prod[idx]
                        prod[idx] = 1.0
                        count[idx] = 0
                        at += 1
            else:
                ordered = np.sort(uniq[:u])
                for j in range(u):
                    idx = ordered[j]
                    keys_out[at + j] = base + idx
                    sums_out[at + j] = first[idx] if count[idx] == 1 else 1.0 - prod[idx]
                    prod[idx] = 1.0
                    count[idx] = 0
                at += u
        return keys_out[:at], sums_out[:at], True
#: ``footprint_grids`` shares its vehicles out between threads only with at least this many pairs per thread: at 6
#: vehicles (12 pairs) two threads measured slower than one (0.54-0.57 vs 0.41-0.52 ms per frame, the hand-off), at 18
#: (44 pairs) faster (wall 1.97-2.65 vs 2.60-2.85 ms; CPU 2.65-3.41)
PAIRS_PER_THREAD = 16


def footprint_grids(x_c, y_c, nx, ny, offsets, sample_weights, cell_rows, probs, pair_weights, wide, shifts, members, origin_x, origin_y,
                    cell, n_rows, n_cols, min_mass, threads=1, lat_rows=None):
    """The sparse grids of ``stages.markov_prediction.rasterise.vehicle_grid`` for every vehicle in one call (see
    ``rasterise.vehicle_grids``) from compact footprints (``rasterise.FootprintBatch``); None where numba is missing.
    ``members``: per vehicle its pair indices. Returns (keys, sums, offsets (n_vehicles + 1,)). ``threads`` > 1: the
    vehicles are split into that many runs of about equal work (cells with mass), each a call of its own on a thread
    of ``kernels._on_threads`` (at most one per ``PAIRS_PER_THREAD`` pairs), their outputs put end to end: every
    vehicle's grid is computed on its own, so the numbers do not depend on it."""
    if numba is None:
        return None
    c = np.ascontiguousarray
    has_shift = shifts is not None
    shifts = shifts if has_shift else np.zeros(probs.shape[:2])
    # sample_weights (P,), or (W, P) with lat_rows (B, K): step k of pair b weighs by row lat_rows[b, k]
    # (rasterise.sample_weight_rows); lat_rows None: the default path's own compiled specialisation
    weights = np.atleast_2d(np.asarray(sample_weights, dtype=np.float64))
    args = (c(x_c, dtype=np.float64), c(y_c, dtype=np.float64), c(nx, dtype=np.float64), c(ny, dtype=np.float64),
            c(offsets, dtype=np.float64), c(weights), c(cell_rows, dtype=np.int64), c(probs, dtype=np.float32),
            c(pair_weights, dtype=np.float64), c(wide, dtype=np.bool_), c(shifts, dtype=np.float64), has_shift,
            None if lat_rows is None else c(lat_rows, dtype=np.int64))
    tail = (float(origin_x), float(origin_y), float(cell), exact_inverse(float(cell)), int(n_rows), int(n_cols), float(min_mass))

    def run(part):
        ptr = np.zeros(len(part) + 1, np.int64)
        ptr[1:] = np.cumsum([len(m) for m in part])
        flat = np.fromiter((b for m in part for b in m), np.int64, count=int(ptr[-1]))
        return _footprint_grids(*args, ptr, flat, *tail)

    # a run per PAIRS_PER_THREAD pairs at most: below that, handing a run to another thread costs about what it saves
    n_parts = min(int(threads), len(members), sum(len(m) for m in members) // PAIRS_PER_THREAD)
    if n_parts <= 1:
        return run(members)
    # work per vehicle: its pairs' samples, (step, cell) entries with mass times the samples of weight > 0 of the step's
    # row (all of them without a lateral spread; with one, a wide step's row has several times a narrow one's)
    entries = (args[7] > min_mass).sum(axis=2)  # (B, K)
    if lat_rows is None:
        per_pair = entries.sum(axis=1)
    else:
        per_pair = (entries * np.count_nonzero(weights, axis=1)[args[12]]).sum(axis=1)
    work = np.cumsum([int(per_pair[list(m)].sum()) if len(m) else 0 for m in members], dtype=np.float64)
    cuts = [0, *np.searchsorted(work, work[-1] * np.arange(1, n_parts) / n_parts, side="right").tolist(), len(members)]
    parts = [members[lo:hi] for lo, hi in zip(cuts[:-1], cuts[1:])]
    found: list = [None] * len(parts)
    kernels._on_threads(len(parts), lambda i: found.__setitem__(i, run(parts[i])), n_parts)
    ptrs = [found[0][2]]
    for keys, _sums, ptr in found[1:]:
        ptrs.append(ptr[1:] + ptrs[-1][-1])
    return np.concatenate([f[0] for f in found]), np.concatenate([f[1] for f in found]), np.concatenate(ptrs)


def add_running_sums(p: np.ndarray, correct: np.ndarray, ends: np.ndarray, out: np.ndarray) -> bool:
    """``rasterise.unwrap_each``'s last step, compiled: for each run [start, end) of ``p`` (``ends`` its ends, in
    order), out[start + 1:end] = p[start + 1:end] + correct[start:end - 1].cumsum() (the same numbers); False (nothing
    done) where numba is missing or the arrays are not float64."""
    if numba is None or p.dtype != np.float64 or correct.dtype != np.float64 or out.dtype != np.float64:
        return False
    _add_running_sums(p, correct, np.asarray(ends, dtype=np.int64), out)
    return True


def footprint_bounds(x_c, y_c, nx, ny, offsets, cell_rows, used):
    """(x min, x max, y min, y max) of the samples of the cells ``used`` (B, L), None when there is none, or when a
    sample is NaN (the caller then takes numpy's own path) or numba is missing."""
    if numba is None:
        return None
    c = np.ascontiguousarray
    x_lo, x_hi, y_lo, y_hi, seen, nan = _footprint_bounds(c(x_c, dtype=np.float64), c(y_c, dtype=np.float64), c(nx, dtype=np.float64),
                                                          c(ny, dtype=np.float64), c(offsets, dtype=np.float64),
                                                          c(cell_rows, dtype=np.int64), c(used, dtype=np.bool_))
    if nan or not seen:
        return None
    return x_lo, x_hi, y_lo, y_hi


#: ``fuse_sorted`` shares its steps out between threads only with at least this many terms per thread: below it the
#: hand-off costs about what it saves (an 18-vehicle frame holds ~60k terms, ~490k with the calibrated spread)
TERMS_PER_THREAD = 40_000


def fuse_sorted(keys: list[np.ndarray] | np.ndarray, values: np.ndarray, n_cells: int, top: float, threads: int = 1,
                ptr: np.ndarray | None = None):
    """(sorted unique keys, per-key 1 − Π (1 − g)) over the runs ``keys`` (each sorted and unique; ``values`` their
    concatenation, each g clipped to [0, ``top``]), each product in run order from 1.0 and a key of one term its g
    itself (``rasterise.fuse``); None where numba is missing or a run is not sorted and unique in [0, ∞).
    ``threads`` > 1: the steps (keys k·n_cells … (k + 1)·n_cells − 1) are split into that many ranges of about equal
    terms (at most one per ``TERMS_PER_THREAD``), each a call of its own on a thread of ``kernels._on_threads``, their
    outputs put end to end: every cell's product is taken as in one call, so the numbers do not depend on it.
    ``ptr`` given: ``keys`` is the runs end to end already (run n ``keys[ptr[n]:ptr[n + 1]]``), taken without a copy."""
    if numba is None or n_cells <= 0:
        return None
    if ptr is None:
        ptr = np.zeros(len(keys) + 1, np.int64)
        ptr[1:] = np.cumsum([k.shape[0] for k in keys])
        flat = np.ascontiguousarray(np.concatenate(keys).astype(np.int64, copy=False) if len(keys) else np.zeros(0, np.int64))
    else:
        ptr = np.ascontiguousarray(ptr, dtype=np.int64)
        flat = np.ascontiguousarray(keys, dtype=np.int64)
        if ptr.shape[0] < 1 or ptr[0] != 0 or ptr[-1] != flat.shape[0] or np.any(np.diff(ptr) < 0):
            return None
    values = np.ascontiguousarray(values, dtype=np.float64)
    total = int(ptr[-1])
    if total == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.float64)
    last = flat[ptr[1:][ptr[1:] > ptr[:-1]] - 1]  # each non-empty run's last key: its largest where it is sorted
    if last.min() < 0:
        return None
    n_steps = int(last.max()) // int(n_cells) + 1
    bounds = _step_bounds(flat, ptr, int(n_cells), n_steps)
    if np.any(bounds[:, 0] != ptr[:-1]) or np.any(bounds[:, -1] != ptr[1:]):  # a key below 0 or past the largest last
        return None
    n_parts = max(1, min(int(threads), n_steps, total // TERMS_PER_THREAD))
    if n_parts == 1:
        cuts = [0, n_steps]
    else:  # ranges of steps with about equal terms
        work = np.cumsum((bounds[:, 1:] - bounds[:, :-1]).sum(axis=0), dtype=np.float64)
        inner = np.searchsorted(work, work[-1] * np.arange(1, n_parts) / n_parts, side="right").tolist()
        cuts = sorted({0, n_steps, *(min(max(c, 1), n_steps - 1) for c in inner)})
    found: list = [None] * (len(cuts) - 1)

    def run(i: int) -> None:
        found[i] = _fuse_steps(flat, values, ptr, bounds, int(n_cells), float(top), cuts[i], cuts[i + 1])

    kernels._on_threads(len(found), run, len(found))  # (one range: on this thread, no pool)
    if not all(f[2] for f in found):
        return None
    if len(found) == 1:
        return found[0][0], found[0][1]
    return np.concatenate([f[0] for f in found]), np.concatenate([f[1] for f in found])


_warm = False


def warm_up() -> None:
    """Compile (or load from numba's on-disk cache) the kernels now, on tiny arrays. Once per process."""
    global _warm
    if _warm or numba is None:
        return
    box = np.zeros((1, 1))
    rows = np.zeros((1, 1), np.int64)
    footprint_grids(box, box, box, box, np.zeros(1), np.ones(1), rows, np.ones((1, 1, 1), np.float32), np.ones(1), np.ones(1, np.bool_),
                    np.zeros((1, 1)), [[0]], -1.0, -1.0, 1.0, 2, 2, 1e-9)
    footprint_grids(box, box, box, box, np.zeros(1), np.ones(1), rows, np.ones((1, 1, 1), np.float32), np.ones(1), np.ones(1, np.bool_),
                    np.zeros((1, 1)), [[0]], -1.0, -1.0, 1.0, 2, 2, 1e-9, lat_rows=np.zeros((1, 1), np.int64))
    footprint_bounds(box, box, box, box, np.zeros(1), rows, np.ones((1, 1), np.bool_))
    fuse_sorted([np.array([0, 3], np.int64), np.array([3], np.int64)], np.full(3, 0.5), 2, 1.0 - 1e-7)
    add_running_sums(np.zeros(3), np.zeros(2), np.array([3], np.int64), np.zeros(3))
    along_rows(np.ones((1, 1, 3), np.float32), 1, np.zeros(1, np.int64), np.array([[0.25, 0.5, 0.25]]), np.ones(1, np.int64), 1e-6,
               np.ones(1, np.int64), np.zeros((1, 5), np.bool_))
    _warm = True


def blur_cells(cells: np.ndarray, values: np.ndarray, n_rows: int, n_cols: int, sigma_cells: float, f: int, pad: int,
               min_value: float):
    """One step of a vehicle's grid blurred in one compiled call (``spread.blur_grid``'s numbers): the cells
    (increasing) and values above ``min_value``; None where numba is missing. ``sigma_cells`` σ in cells, ``f`` the
    block size and ``pad`` the padding (cells) of ``spread.blur_step``; the kernel is scipy's (``gaussian_kernel``)."""
    if numba is None or cells.size == 0:
        return None
    w, radius = gaussian_kernel(sigma_cells / f)
    return _blur_cells(np.ascontiguousarray(cells, dtype=np.int64), np.ascontiguousarray(values, dtype=np.float64), int(n_rows),
                       int(n_cols), int(f), int(pad), w, radius, float(min_value))


def along_rows(probs: np.ndarray, pad: int, which: np.ndarray, weights: np.ndarray, radii: np.ndarray, min_value: float,
               start_cell: np.ndarray | None, beyond: np.ndarray) -> np.ndarray | None:
    """``spread.along_spread`` in one compiled call: ``probs`` (B, K, L) float32 padded by ``pad`` cells at both ends,
    blurred (``which`` (B·K,) into ``weights`` (U, 2·max radius + 1; each row centred) / ``radii``), folded ahead of ``start_cell`` (B,) (None:
    not), the cells ``beyond`` (B, L + 2·pad) set to 0; float32 (B, K, L + 2·pad). None where numba is missing."""
    if numba is None:
        return None
    n_b, n_k, n_l = probs.shape
    out = np.empty((n_b, n_k, n_l + 2 * int(pad)), np.float32)
    fold = start_cell is not None
    _along_rows(np.ascontiguousarray(probs, dtype=np.float32), int(pad), np.ascontiguousarray(which, dtype=np.int64),
                np.ascontiguousarray(weights, dtype=np.float64), np.ascontiguousarray(radii, dtype=np.int64), float(min_value),
                np.ascontiguousarray(start_cell if fold else np.zeros(n_b), dtype=np.int64), fold,
                np.ascontiguousarray(beyond, dtype=np.bool_), out)
    return out


def gaussian_kernel(sigma: float, truncate: float = 3.0) -> tuple[np.ndarray, int]:
    """scipy.ndimage.gaussian_filter's 1-D weights for σ (in samples) and its radius int(truncate·σ + 0.5): exp(−0.5 / σ²
    · x²) over x = −radius … radius, divided by their sum."""
    radius = int(truncate * float(sigma) + 0.5)
    x = np.arange(-radius, radius + 1)
    phi = np.exp(-0.5 / (sigma * sigma) * x ** 2)
    return phi / phi.sum(), radius
