"""Motion grid: corridor s-distributions rasterised onto a map-frame grid (docs/method.md §9), sparse.

Each s-cell's mass is spread along the centreline piece it covers
(``n_sub`` equally spaced sub-samples) and laterally with a Gaussian of
σ = ``lateral_sigma_m`` (samples every half grid cell out to ±2.5σ,
weights normalised), then binned to the nearest grid cell. A vehicle's grid
is the probability-weighted sum over its corridors, so it sums to
Σ_c w_c (1 − outside_c) minus what falls off the grid; vehicles combine as
1 − Π_n (1 − G_n). Grids are kept as sorted flat keys k·(rows·cols) +
row·cols + col with their values, never as dense arrays.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from stages.lib.markov import frame_kernels, kernels

#: Per-vehicle cell values are clipped below 1 by this much before log(1 − G).
_CLIP = 1e-7


@dataclass(frozen=True, slots=True)
class GridFrame:
    """Cell (row, col) covers [origin_x + col·cell, …) × [origin_y + row·cell, …); row 0 in the south."""

    origin_x_m: float
    origin_y_m: float
    cell_m: float
    n_rows: int
    n_cols: int

    @property
    def n_cells(self) -> int:
        return self.n_rows * self.n_cols

    @classmethod
    def around(cls, x_m: np.ndarray, y_m: np.ndarray, cell_m: float, margin_m: float) -> "GridFrame":
        """The smallest grid on the lattice of ``cell_m`` (multiples from 0) holding the points plus a margin."""
        if x_m.size == 0:
            return cls(0.0, 0.0, cell_m, 1, 1)
        x0 = math.floor((float(np.min(x_m)) - margin_m) / cell_m) * cell_m
        y0 = math.floor((float(np.min(y_m)) - margin_m) / cell_m) * cell_m
        n_cols = int(math.ceil((float(np.max(x_m)) + margin_m - x0) / cell_m))
        n_rows = int(math.ceil((float(np.max(y_m)) + margin_m - y0) / cell_m))
        return cls(x0, y0, cell_m, max(n_rows, 1), max(n_cols, 1))

    @classmethod
    def fixed(cls, extent_m: tuple[float, float, float, float], cell_m: float) -> "GridFrame":
        """A grid over (x_min, y_min, x_max, y_max)."""
        x_min, y_min, x_max, y_max = extent_m
        return cls(
            x_min, y_min, cell_m, max(int(math.ceil((y_max - y_min) / cell_m)), 1), max(int(math.ceil((x_max - x_min) / cell_m)), 1)
        )

    def flat_index(self, x_m: np.ndarray, y_m: np.ndarray) -> np.ndarray:
        """row·n_cols + col of points, -1 off the grid (same shape as the inputs)."""
        col = np.floor((x_m - self.origin_x_m) / self.cell_m)
        row = np.floor((y_m - self.origin_y_m) / self.cell_m)
        inside = (col >= 0) & (col < self.n_cols) & (row >= 0) & (row < self.n_rows) & np.isfinite(col) & np.isfinite(row)
        return np.where(inside, row * self.n_cols + col, -1).astype(np.int64)


def lateral_kernel(sigma_m: float, cell_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Lateral offsets (n,) every half cell out to ±2.5σ and their normalised Gaussian weights."""
    step = 0.5 * cell_m
    half = max(int(math.ceil(2.5 * sigma_m / step)), 0)
    offsets = step * np.arange(-half, half + 1, dtype=np.float64)
    weights = np.exp(-0.5 * (offsets / sigma_m) ** 2) if sigma_m > 0 else np.ones(1)
    return offsets, weights / weights.sum()


@dataclass(frozen=True, slots=True, eq=False)
class Footprints:
    """Where the mass of each s-cell of one pair lands: sample points ``(L, P)`` and their weights ``(P,)`` summing to 1.

    ``normal_x``, ``normal_y`` ``(L, P)``: the centreline's left normal at each
    sample, for a lateral shift of the whole footprint.
    """

    x_m: np.ndarray
    y_m: np.ndarray
    weights: np.ndarray
    normal_x: np.ndarray
    normal_y: np.ndarray


def cell_footprints(
    centreline_s_m: np.ndarray,
    centreline_x_m: np.ndarray,
    centreline_y_m: np.ndarray,
    centreline_heading_rad: np.ndarray,
    cell_lower_s_m: np.ndarray,
    ds_m: float,
    n_sub: int,
    lateral_offsets_m: np.ndarray,
    lateral_weights: np.ndarray,
) -> Footprints:
    """Sample points of the s-cells with lower edges ``cell_lower_s_m`` (L,) along a centreline.

    The centreline is interpolated linearly in s (headings unwrapped first);
    beyond its ends it continues straight.
    """
    frac = (np.arange(n_sub) + 0.5) / n_sub
    s = cell_lower_s_m[:, None] + frac[None, :] * ds_m  # (L, n_sub)
    heading = np.unwrap(centreline_heading_rad)
    s0, s1 = centreline_s_m[0], centreline_s_m[-1]
    s_in = np.clip(s, s0, s1)
    x = np.interp(s_in, centreline_s_m, centreline_x_m)
    y = np.interp(s_in, centreline_s_m, centreline_y_m)
    h = np.interp(s_in, centreline_s_m, heading)
    beyond = s - s_in  # straight continuation past either end
    x = x + beyond * np.cos(h)
    y = y + beyond * np.sin(h)
    nx, ny = -np.sin(h), np.cos(h)
    px = x[:, :, None] + nx[:, :, None] * lateral_offsets_m[None, None, :]
    py = y[:, :, None] + ny[:, :, None] * lateral_offsets_m[None, None, :]
    n_cells = cell_lower_s_m.shape[0]
    n_lat = lateral_offsets_m.shape[0]
    weights = np.repeat((1.0 / n_sub) * np.ones(n_sub), n_lat) * np.tile(lateral_weights, n_sub)
    normal_x = np.repeat(nx, n_lat, axis=1)
    normal_y = np.repeat(ny, n_lat, axis=1)
    return Footprints(px.reshape(n_cells, -1), py.reshape(n_cells, -1), weights, normal_x, normal_y)


def unwrap_each(angles: list[np.ndarray]) -> np.ndarray:
    """``np.unwrap`` of each 1-D array, concatenated: the same numbers, with np.unwrap's steps done on all the arrays at
    once (the differences and their corrections elementwise), only the running sum of the corrections per array."""
    arrays = [np.asarray(a) for a in angles]
    if not all(a.ndim == 1 and a.dtype == np.float64 for a in arrays):
        return np.concatenate([np.unwrap(a) for a in arrays])
    p = np.concatenate(arrays)
    period = 2 * np.pi
    high = period / 2
    low = -high
    dd = p[1:] - p[:-1]
    ddmod = np.mod(dd - low, period) + low
    np.copyto(ddmod, high, where=(ddmod == low) & (dd > 0))
    correct = ddmod - dd
    np.copyto(correct, 0, where=abs(dd) < high)
    out = p.copy()
    ends = np.cumsum([a.shape[0] for a in arrays])
    if frame_kernels.add_running_sums(p, correct, ends, out):  # the loop below, compiled
        return out
    start = 0
    for end in ends.tolist():  # array [start, end): its corrections are correct[start:end - 1]
        if end - start > 1:
            out[start + 1:end] = p[start + 1:end] + correct[start:end - 1].cumsum()
        start = end
    return out


class Centrelines:
    """The centrelines of B pairs packed for one ``np.interp`` call per quantity over all of them.

    Pair b's arc lengths are moved to start at b·period (period: the longest
    centreline plus 1 m), so that the packed knots increase; a query is first
    clipped to its pair's own range, so it never reaches a neighbour's knots.
    The headings are unwrapped per pair. The same numbers as one ``np.interp``
    per pair, up to the rounding of the shift (~1e-12 m).
    """

    def __init__(self, s_m: list[np.ndarray], x_m: list[np.ndarray], y_m: list[np.ndarray], heading_rad: list[np.ndarray]) -> None:
        n = len(s_m)
        plain = n > 0 and all(isinstance(s, np.ndarray) and s.ndim == 1 and s.dtype == np.float64 and s.size for s in s_m)
        if plain:  # every pair's arc lengths packed at once (the same numbers as pair by pair below)
            sizes = np.array([s.shape[0] for s in s_m])
            s_all = np.concatenate(s_m)
            ends = np.cumsum(sizes)
            self.first, self.last = s_all[ends - sizes], s_all[ends - 1]
        else:
            self.first = np.array([float(s[0]) for s in s_m]) if n else np.zeros(0)
            self.last = np.array([float(s[-1]) for s in s_m]) if n else np.zeros(0)
        self.period = float(np.max(self.last - self.first)) + 1.0 if n else 1.0
        shift = np.arange(n) * self.period
        self._shift = shift
        if plain:
            self._xp = (s_all - np.repeat(self.first, sizes)) + np.repeat(shift, sizes)
        else:
            self._xp = np.concatenate([s - s[0] + o for s, o in zip(s_m, shift)]) if n else np.zeros(0)
        self._x = np.concatenate(x_m) if n else np.zeros(0)
        self._y = np.concatenate(y_m) if n else np.zeros(0)
        self._h = unwrap_each(heading_rad) if n else np.zeros(0)

    def _packed(self, s_in: np.ndarray, pairs: np.ndarray | None = None) -> np.ndarray:
        lead = (slice(None) if pairs is None else pairs,) + (None,) * (s_in.ndim - 1)
        return s_in - self.first[lead] + self._shift[lead]

    def clip(self, s_m: np.ndarray, pairs: np.ndarray | None = None) -> np.ndarray:
        """``s_m`` (B, ...) clipped to each pair's centreline (``pairs``: row r of ``s_m`` is on pair ``pairs[r]``)."""
        lead = (slice(None) if pairs is None else pairs,) + (None,) * (s_m.ndim - 1)
        return np.clip(s_m, self.first[lead], self.last[lead])

    def heading(self, s_in: np.ndarray) -> np.ndarray:
        """The unwrapped heading at clipped arc lengths ``s_in`` (B, ...)."""
        return np.interp(self._packed(s_in), self._xp, self._h)

    def xy_heading(self, s_m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """X_c(s) with straight continuation past either end, and the heading there, at ``s_m`` (B, ...)."""
        return self.xy_heading_trig(s_m)[:3]

    def xy_heading_trig(self, s_m: np.ndarray, pairs: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``xy_heading`` and the cosine and sine of the heading (each computed once); ``pairs``: row r of ``s_m`` is on
        the centreline of pair ``pairs[r]`` (None: row b on pair b)."""
        s_in = self.clip(s_m, pairs)
        q = self._packed(s_in, pairs)
        heading = np.interp(q, self._xp, self._h)
        beyond = s_m - s_in
        cos, sin = np.cos(heading), np.sin(heading)
        x = np.interp(q, self._xp, self._x) + beyond * cos
        y = np.interp(q, self._xp, self._y) + beyond * sin
        return x, y, heading, cos, sin


@dataclass(frozen=True, slots=True, eq=False)
class FootprintBatch:
    """The ``Footprints`` of B pairs, compact: for the s-cells computed, the centreline at each cell's ``n_sub``
    sub-samples, ``centre_x``, ``centre_y``, and the left normal there, ``centre_nx``, ``centre_ny``
    ``(R, n_sub)``, cell i of pair b on row ``rows[b, i]`` (-1: not computed); the lateral ``offsets`` ``(n_lat,)``;
    ``weights`` ``(P,)``, P = n_sub·n_lat.

    Sample q = sub·n_lat + lat lies at centre + normal·offsets[lat]: ``x_m``,
    ``y_m``, ``normal_x``, ``normal_y`` ``(B, L, P)`` build those arrays (the
    numbers of ``cell_footprints``; NaN for a cell not computed); the compiled
    grid kernels (``stages.lib.markov.frame_kernels``) form each sample where
    they use it.
    """

    centre_x: np.ndarray
    centre_y: np.ndarray
    centre_nx: np.ndarray
    centre_ny: np.ndarray
    offsets: np.ndarray
    weights: np.ndarray
    rows: np.ndarray

    def _expanded(self, centre: np.ndarray, normal: np.ndarray | None, b: int | None = None) -> np.ndarray:
        rows = self.rows if b is None else self.rows[b]
        n_lat = self.offsets.shape[0]
        if normal is None:  # the normal itself, repeated over the lateral samples
            values = np.repeat(centre, n_lat, axis=-1)
        else:
            values = (centre[..., None] + normal[..., None] * self.offsets).reshape(centre.shape[0], -1)
        out = np.full(rows.shape + (values.shape[1],), np.nan)
        out[rows >= 0] = values[rows[rows >= 0]]
        return out

    @property
    def x_m(self) -> np.ndarray:
        return self._expanded(self.centre_x, self.centre_nx)

    @property
    def y_m(self) -> np.ndarray:
        return self._expanded(self.centre_y, self.centre_ny)

    @property
    def normal_x(self) -> np.ndarray:
        return self._expanded(self.centre_nx, None)

    @property
    def normal_y(self) -> np.ndarray:
        return self._expanded(self.centre_ny, None)

    def pair(self, b: int) -> Footprints:
        return Footprints(self._expanded(self.centre_x, self.centre_nx, b), self._expanded(self.centre_y, self.centre_ny, b),
                          self.weights, self._expanded(self.centre_nx, None, b), self._expanded(self.centre_ny, None, b))

    def pairs(self) -> list[Footprints]:
        return [self.pair(b) for b in range(self.rows.shape[0])]

    def bounds(self, used: np.ndarray) -> tuple[float, float, float, float] | None:
        """(x min, x max, y min, y max) of the samples of the cells ``used`` (B, L) bool, the numbers np.min and np.max
        give over ``x_m[b][used[b]]``, ``y_m[b][used[b]]``; None when no cell is used."""
        found = frame_kernels.footprint_bounds(self.centre_x, self.centre_y, self.centre_nx, self.centre_ny, self.offsets, self.rows,
                                               used)
        if found is not None:
            return found
        if not np.any(used):
            return None
        xs = np.concatenate([fp.x_m[u].ravel() for fp, u in zip(self.pairs(), used) if u.any()])
        ys = np.concatenate([fp.y_m[u].ravel() for fp, u in zip(self.pairs(), used) if u.any()])
        return float(np.min(xs)), float(np.max(xs)), float(np.min(ys)), float(np.max(ys))


def cell_footprints_batch(
    centrelines: Centrelines,
    cell_lower_s_m: np.ndarray,
    ds_m: float,
    n_sub: int,
    lateral_offsets_m: np.ndarray,
    lateral_weights: np.ndarray,
) -> list[Footprints]:
    """``cell_footprints`` of B pairs at once: ``cell_lower_s_m`` (B, L), one ``Footprints`` per pair."""
    return cell_footprints_arrays(centrelines, cell_lower_s_m, ds_m, n_sub, lateral_offsets_m, lateral_weights).pairs()


def cell_footprints_arrays(
    centrelines: Centrelines,
    cell_lower_s_m: np.ndarray,
    ds_m: float,
    n_sub: int,
    lateral_offsets_m: np.ndarray,
    lateral_weights: np.ndarray,
    used: np.ndarray | None = None,
) -> FootprintBatch:
    """``cell_footprints_batch`` as one (compact) ``FootprintBatch``, of the cells ``used`` (B, L) bool only (None:
    every cell)."""
    frac = (np.arange(n_sub) + 0.5) / n_sub
    n_b, n_cells = cell_lower_s_m.shape
    if used is None:
        used = np.ones((n_b, n_cells), np.bool_)
    b_idx, i_idx = np.nonzero(used)
    rows = np.full((n_b, n_cells), -1, np.int64)
    rows[b_idx, i_idx] = np.arange(b_idx.shape[0])
    s = cell_lower_s_m[b_idx, i_idx][:, None] + frac[None, :] * ds_m  # (R, n_sub)
    x, y, _h, cos, sin = centrelines.xy_heading_trig(s, b_idx)
    n_lat = lateral_offsets_m.shape[0]
    weights = np.repeat((1.0 / n_sub) * np.ones(n_sub), n_lat) * np.tile(lateral_weights, n_sub)
    return FootprintBatch(x, y, -sin, cos, np.asarray(lateral_offsets_m, dtype=np.float64), weights, rows)


@dataclass(frozen=True, slots=True, eq=False)
class SparseGrid:
    """Sorted unique keys k·n_cells + flat cell index ``(n,) int64`` and values ``(n,) float64``."""

    keys: np.ndarray
    values: np.ndarray

    def step(self, k: int, n_cells: int) -> tuple[np.ndarray, np.ndarray]:
        """(flat cell indices, values) of step k."""
        lo, hi = np.searchsorted(self.keys, [k * n_cells, (k + 1) * n_cells])
        return self.keys[lo:hi] - k * n_cells, self.values[lo:hi]


def _reduce(keys: np.ndarray, values: np.ndarray) -> SparseGrid:
    if keys.size == 0:
        return SparseGrid(np.zeros(0, np.int64), np.zeros(0, np.float64))
    unique, sums = kernels.sum_by_key(keys, values)  # np.unique + np.bincount's numbers, without sorting every key
    return SparseGrid(unique, sums)


def vehicle_grid(
    frame: GridFrame,
    footprints: list[Footprints],
    probs: list[np.ndarray],
    corridor_weights: list[float],
    lateral_shifts_m: list[np.ndarray] | None = None,
    min_mass: float = 1e-9,
    step_weights: list[np.ndarray | None] | None = None,
) -> SparseGrid:
    """G_n for all steps: Σ_c w_c · rasterised probs_c, probs ``(K, L)`` per corridor on its footprints.

    ``lateral_shifts_m`` ``(K,)`` per corridor moves the footprints of step k
    sideways (to the left when positive). ``step_weights`` ``(K, P)`` per
    corridor (or None: its footprints' weights): the samples' weights step by
    step (a lateral spread per step, ``lateral_table``); a sample of weight 0
    is left out.
    """
    all_keys, all_values = [], []
    n_cells = frame.n_cells
    shifts = lateral_shifts_m if lateral_shifts_m is not None else [None] * len(footprints)
    per_step = step_weights if step_weights is not None else [None] * len(footprints)
    for fp, p, w, shift, sw in zip(footprints, probs, corridor_weights, shifts, per_step):
        k_idx, i_idx = np.nonzero(p > min_mass)
        if k_idx.size == 0 or w <= 0:
            continue
        x, y = fp.x_m[i_idx], fp.y_m[i_idx]
        if shift is not None:
            d = shift[k_idx][:, None]
            x = x + d * fp.normal_x[i_idx]
            y = y + d * fp.normal_y[i_idx]
        cells = frame.flat_index(x, y)  # (n, P)
        weights = fp.weights[None, :] if sw is None else sw[k_idx]
        mass = (w * p[k_idx, i_idx])[:, None] * weights
        keys = k_idx[:, None] * n_cells + cells
        keep = cells >= 0 if sw is None else (cells >= 0) & (weights > 0)
        all_keys.append(keys[keep])
        all_values.append(mass[keep])
    if not all_keys:
        return _reduce(np.zeros(0, np.int64), np.zeros(0))
    return _reduce(np.concatenate(all_keys), np.concatenate(all_values))


def vehicle_grids(
    frame: GridFrame,
    footprints: FootprintBatch,
    probs: np.ndarray,
    corridor_weights: list[float],
    members: list[list[int]],
    lateral_shifts_m: np.ndarray | None = None,
    min_mass: float = 1e-9,
    threads: int = 1,
    lateral: tuple[np.ndarray, np.ndarray] | None = None,
) -> list[SparseGrid]:
    """``vehicle_grid`` of every vehicle (a ``VehicleGrids`` from the compiled call), vehicle n of the pairs ``members[n]`` (``probs`` ``(B, K, L)``, ``corridor_weights``
    and ``lateral_shifts_m`` ``(B, K)`` per pair): in one compiled call (``frame_kernels.footprint_grids``: the same
    numbers, no Python per vehicle, no (B, L, P) sample arrays) where numba imports, else one ``vehicle_grid``
    per vehicle. tests/stages/test_markov_batched_outputs.py compares the two. ``threads``: the compiled call's vehicles shared
    out between that many threads (the same numbers). ``lateral``: (rows (B, K), table (U, n_lat)) of ``lateral_table``:
    step k of pair b with rows[b, k] = u >= 0 weighs its lateral samples by table[u] (the footprints' offsets)."""
    probs = np.asarray(probs)
    found = None
    if probs.dtype == np.float32 and probs.ndim == 3:
        # w · p is float64 for a numpy float64 weight and float32 for a Python float (numpy's promotion), as vehicle_grid has it
        wide = np.array([type(w) is not float and np.result_type(w, probs.dtype) == np.float64 for w in corridor_weights], dtype=np.bool_)
        fp = footprints
        lat_rows, weights = sample_weight_rows(fp, lateral) if lateral is not None else (None, fp.weights)
        found = frame_kernels.footprint_grids(fp.centre_x, fp.centre_y, fp.centre_nx, fp.centre_ny, fp.offsets, weights, fp.rows, probs,
                                              np.asarray(corridor_weights, dtype=np.float64), wide, lateral_shifts_m, members,
                                              frame.origin_x_m, frame.origin_y_m, frame.cell_m, frame.n_rows, frame.n_cols, min_mass,
                                              threads=threads, lat_rows=lat_rows)
    if found is None:
        shifts = [None] * probs.shape[0] if lateral_shifts_m is None else list(lateral_shifts_m)
        step_w = [None] * probs.shape[0]
        if lateral is not None:
            lat_rows, weights = sample_weight_rows(footprints, lateral)
            step_w = [weights[lat_rows[b]] for b in range(probs.shape[0])]
        return [vehicle_grid(frame, [footprints.pair(b) for b in m], [probs[b] for b in m], [corridor_weights[b] for b in m],
                             None if lateral_shifts_m is None else [shifts[b] for b in m], min_mass, [step_w[b] for b in m])
                for m in members]
    keys, sums, ptr = found
    out = VehicleGrids(SparseGrid(keys[ptr[n]:ptr[n + 1]], sums[ptr[n]:ptr[n + 1]]) for n in range(len(members)))
    out.flat = (keys, sums, ptr)
    return out


def lateral_table(sigmas_m: np.ndarray, base_sigma_m: float, cell_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
    """A lateral spread per step: for σ_lat (m) per pair and step ``sigmas_m`` (B, K), the footprints' lateral offsets
    (every half cell out to ±2.5 of the widest σ, as ``lateral_kernel``) with the weights of ``base_sigma_m`` on them
    (zero beyond its ±2.5σ), and ``rows`` (B, K) and ``table`` (U, n_lat) for ``vehicle_grids(lateral=...)``: one
    normalised Gaussian per distinct σ, cut at ±2.5σ (rows -1 where σ is the base one: the footprints' own weights).
    ``table`` is None when no σ is wider than the base one."""
    sig = np.asarray(sigmas_m, dtype=np.float64)
    wider = np.isfinite(sig) & (sig > base_sigma_m)
    top = float(sig[wider].max()) if wider.any() else base_sigma_m
    offsets, _w = lateral_kernel(top, cell_m)
    base = gaussian_rows(offsets, np.array([base_sigma_m]), np.array([2.5 * base_sigma_m + 1e-12]))[0]
    rows = np.full(sig.shape, -1, np.int64)
    if not wider.any():
        return offsets, base, rows, None
    unique, inverse = np.unique(sig[wider], return_inverse=True)
    rows[wider] = inverse
    return offsets, base, rows, gaussian_rows(offsets, unique, 2.5 * unique + 1e-12)


def gaussian_rows(x: np.ndarray, sigmas: np.ndarray, reach: np.ndarray) -> np.ndarray:
    """(U, n) one Gaussian per σ over the points ``x`` (n,), zero where |x| > its ``reach``, each row normalised to 1
    (the along blur's and the lateral spread's kernels)."""
    rows = np.exp(-0.5 * (x[None, :] / sigmas[:, None]) ** 2)
    rows[np.abs(x)[None, :] > reach[:, None]] = 0.0
    rows /= rows.sum(axis=1, keepdims=True)
    return rows


def sample_weight_rows(footprints: "FootprintBatch", lateral: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """``lateral`` (rows (B, K), table (U, n_lat)) as the samples' weights: (rows (B, K) into ``weights``, weights
    (U + 1, P)): row u < U is table[u] / n_sub per sub-sample (P = n_sub·n_lat, sample q = sub·n_lat + lat), row U the
    footprints' own weights (where rows was -1). What the compiled grids and ``vehicle_grid`` both weigh by."""
    rows, table = lateral
    n_sub = footprints.centre_x.shape[1]
    weights = np.concatenate([np.tile(table, (1, n_sub)) / n_sub, footprints.weights[None, :]]) if table.size else footprints.weights[None, :]
    return np.where(rows >= 0, rows, weights.shape[0] - 1), weights


class VehicleGrids(list):
    """``vehicle_grids``' list of grids, with ``flat``: (keys, values, ptr) of the one compiled call they are views of
    (grid n: ``keys[ptr[n]:ptr[n + 1]]``), for ``fuse`` to take without joining them again; None on numpy's path."""

    flat: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None


def fuse(grids: list[SparseGrid], n_cells: int = 0, threads: int = 1) -> SparseGrid:
    """1 − Π_n (1 − G_n) over vehicles, cell by cell, each G clipped to [0, 1 − 1e-7]; a cell of one vehicle keeps
    its G. The product is taken directly, in vehicle order (1 − G is exact to 1e-16 absolute, so a fused value of
    1e-5, the MotionGrid's floor, is exact to 1e-11 relative, far below its float32; a sum of log1p terms cost a
    logarithm per term, most of the fusion's time with the spread on). With the grid's ``n_cells`` (keys k·n_cells
    + cell) step by step in one compiled call (``frame_kernels.fuse_sorted``, each grid's keys being sorted and
    unique); else the keys sorted stably (vehicle order within a cell) and reduced with numpy (the same products up
    to numpy's order of multiplication). ``threads``: the compiled call's ranges of steps on that many threads at most
    (the same numbers). ``grids`` a ``VehicleGrids`` with ``flat``: its arrays are taken as they are (no copy)."""
    if not grids:
        return _reduce(np.zeros(0, np.int64), np.zeros(0))
    flat = getattr(grids, "flat", None)
    if flat is not None and n_cells > 0 and len(flat[2]) == len(grids) + 1:
        found = frame_kernels.fuse_sorted(flat[0], flat[1], n_cells, 1.0 - _CLIP, threads, ptr=flat[2])
        if found is not None:
            return SparseGrid(*found)
    values = np.concatenate([g.values for g in grids])
    found = frame_kernels.fuse_sorted([g.keys for g in grids], values, n_cells, 1.0 - _CLIP, threads) if n_cells > 0 else None
    if found is not None:
        return SparseGrid(*found)
    keys = np.concatenate([g.keys for g in grids]).astype(np.int64, copy=False)
    order = np.argsort(keys, kind="stable")
    keys, g = keys[order], np.clip(values[order], 0.0, 1.0 - _CLIP)
    if keys.size == 0:
        return _reduce(keys, g)
    unique, starts, counts = np.unique(keys, return_index=True, return_counts=True)
    fused = np.where(counts == 1, g[starts], 1.0 - np.multiply.reduceat(1.0 - g, starts))
    return SparseGrid(unique, fused)


def highest_density_threshold(values: np.ndarray, level: float) -> float:
    """The smallest cell value inside the ``level`` highest-probability region (all cells if the mass is below it)."""
    if values.size == 0:
        return math.inf
    ordered = np.sort(values)[::-1]
    cumulative = np.cumsum(ordered)
    n = int(np.searchsorted(cumulative, level, side="left"))
    return float(ordered[min(n, ordered.size - 1)])
