"""Calibrated spread of the grids: each vehicle's grid blurred with a Gaussian per step and start-speed band.

``iamp calibrate`` (``stages.offline.calibrate``) fits, on the windows of one
location, the σ (m) per prediction step and start-speed band for which the
90 % region of each mode's grid holds the truth in 90 % of the windows, and
writes them to a JSON file; the stage reads it (``spread_calibration``) and
blurs every vehicle's grid step by step with an isotropic Gaussian of that σ
(``blur_grid``) before the vehicles are fused: along the track (most of the
error of moving cars) and across it (lane offsets the 0.4 m lateral kernel
does not hold). The corridor distributions and mean positions
(``CorridorPredictions``, mADE) do not change; a σ of 0 leaves a step as it
is (the spread is never narrowed). Mass blurred off the grid's frame is lost.

File layout (``SCHEMA``)::

    {"schema": "iamp-spread-calibration/1", "modes": {"hybrid": {"bands_mps": [0.5, 2.0],
     "sigma_m": [[...n_steps...], [...], [...]], "speed_noise_gain": 1.0}, ...}, "fitted_on": {...}}

With ``spread_shape = "along"`` the stage applies the same σ along each
corridor instead (``blur_along``, before rasterising; the lateral kernel
widened per step, ``rasterise.lateral_table``; docs/method.md §9.7): the
mass stays on the road and the grids hold fewer cells. ``iamp calibrate
--set spread_shape='"along"'`` fits a table for that shape (``"shape":
"along"`` in the mode's entry; absent: isotropic); the stage warns when a
table's shape is not the one it applies.

``bands_mps`` are the upper start-speed edges of all bands but the last
(speed ≤ 0.5: standing, ≤ 2: slow, above: fast); ``sigma_m`` has one row
per band and one σ per step. ``speed_noise_gain`` (optional, 0 when absent)
widens a vehicle's σ by its own speed noise (``SpreadTable``): a table fitted
on a location with smooth tracks carries over to one whose speeds scatter.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy.ndimage import gaussian_filter

from stages.lib.base import atomic_write
from stages.lib.markov import frame_kernels
from stages.markov_prediction.rasterise import GridFrame, SparseGrid, gaussian_rows

SCHEMA = "iamp-spread-calibration/1"
#: a blurred step keeps only the cells above this value: the blur's far tails (measured at σ = 6 m on 0.5 m cells: half
#: of the cells and about 0.1 % of the mass) are left out. Below ``iamp eval``'s NLL floor (1e-6, which scores a
#: missing cell the same) and a tenth of the MotionGrid's ``grid_min_value``; a highest-density region never
#: reaches them (its threshold is fixed by the cells above it)
BLUR_MIN_VALUE = 1e-6
#: ``spread_calibration = "shipped"`` names this file: the table of the shipped AR model (``iamp calibrate`` on all of
#: TAF-BW with it; in-sample, as the model), beside the weights with their licence and attribution
SHIPPED = Path(__file__).resolve().parents[1] / "lib" / "ar" / "weights" / "spread_taf_bw.json"
#: ... per spread_shape: the round table above, and the one fitted with ``spread_shape = "along"`` beside it
SHIPPED_BY_SHAPE = {"isotropic": SHIPPED, "along": SHIPPED.with_name("spread_taf_bw_along.json")}


@dataclass(frozen=True)
class SpreadTable:
    """σ (m) per start-speed band (rows) and step (columns) of one mode, and the gain of the vehicle's speed noise.

    With ``speed_noise_gain`` g > 0 a vehicle whose measured speed scatters by
    σ_v (m/s, the residual of its speeds around their straight-line fit over the
    last ``accel_window_s``) gets σ_k = √(table_k² + (g·σ_v·t_k)²) at step k
    (t_k = (k + 1)·τ): a speed known to ±σ_v puts the position ±σ_v·t off.
    """

    bands_mps: tuple[float, ...]
    sigma_m: np.ndarray  # (len(bands_mps) + 1, n_steps)
    speed_noise_gain: float = 0.0
    #: the spread_shape the table was fitted for ("isotropic" where the file does not say)
    shape: str = "isotropic"

    def band(self, speed_mps: float) -> int:
        return int(np.searchsorted(np.asarray(self.bands_mps), speed_mps, side="left"))

    def sigmas(self, speed_mps: float, speed_noise_mps: float = 0.0, step_times_s: np.ndarray | None = None) -> np.ndarray:
        table = self.sigma_m[self.band(speed_mps)]
        if self.speed_noise_gain <= 0 or step_times_s is None or not (speed_noise_mps > 0):
            return table
        return with_speed_noise(table, self.speed_noise_gain * speed_noise_mps, step_times_s)

    def max_sigma_m(self, step_times_s: np.ndarray, noise_cap_mps: float) -> float:
        """The widest σ this table gives (with the speed noise at its cap)."""
        return float(with_speed_noise(self.sigma_m.max(axis=0), self.speed_noise_gain * noise_cap_mps, step_times_s).max())

    def as_dict(self) -> dict[str, Any]:
        out = {"bands_mps": list(self.bands_mps), "sigma_m": np.round(self.sigma_m, 4).tolist()}
        if self.speed_noise_gain > 0:
            out["speed_noise_gain"] = float(self.speed_noise_gain)
        if self.shape != "isotropic":
            out["shape"] = self.shape
        return out


def with_speed_noise(sigmas_m: np.ndarray, noise_mps: float, step_times_s: np.ndarray) -> np.ndarray:
    """√(σ_k² + (noise·t_k)²) per step."""
    return np.hypot(np.asarray(sigmas_m, dtype=np.float64), noise_mps * np.asarray(step_times_s, dtype=np.float64))


def resolve(path: str, shape: str = "isotropic") -> Path:
    """The file of ``spread_calibration = path``: "shipped" names the shipped table fitted for ``shape``."""
    return SHIPPED_BY_SHAPE.get(shape, SHIPPED) if path == "shipped" else Path(path).expanduser()


def load_spread(path: str, mode: str, n_steps: int, shape: str = "isotropic") -> SpreadTable | None:
    """The table of ``mode`` in the file ``path`` (None when the file has none for it; "shipped": the shipped table of
    ``shape``); a bad file raises ValueError."""
    where = f"spread_calibration = {path!r}"
    file = resolve(path, shape)
    try:
        data = json.loads(file.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ValueError(f"{where}: cannot read {file}: {exc}; write it with `iamp calibrate` or set spread_calibration = \"\"") from exc
    if not isinstance(data, dict) or data.get("schema") != SCHEMA or not isinstance(data.get("modes"), dict):
        raise ValueError(f"{where}: {file} is not a {SCHEMA} file (write it with `iamp calibrate`)")
    entry = data["modes"].get(mode)
    if entry is None:
        return None
    try:
        bands = tuple(float(b) for b in entry["bands_mps"])
        sigma = np.asarray(entry["sigma_m"], dtype=np.float64)
        gain = float(entry.get("speed_noise_gain", 0.0))
        shape = str(entry.get("shape", "isotropic"))
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"{where}: mode {mode}: expected bands_mps and sigma_m ({exc})") from exc
    if not (math.isfinite(gain) and gain >= 0):
        raise ValueError(f"{where}: mode {mode}: speed_noise_gain must be a number >= 0, got {gain}")
    if sigma.shape != (len(bands) + 1, n_steps) or not np.all(np.isfinite(sigma)) or np.any(sigma < 0) or list(bands) != sorted(bands):
        other = (f": a table for n_steps = {sigma.shape[1]}; fit one for {n_steps} steps with `iamp calibrate`, or set"
                 f" spread_calibration = \"\" (the chain's own grids)") if sigma.ndim == 2 and sigma.shape[1] != n_steps else ""
        raise ValueError(f"{where}: mode {mode}: sigma_m must be {len(bands) + 1} x {n_steps} finite values >= 0 (one row per band,"
                         f" one per step) and bands_mps increasing; got shape {sigma.shape}{other}")
    if shape not in ("isotropic", "along"):
        raise ValueError(f"{where}: mode {mode}: shape must be \"isotropic\" or \"along\", got {shape!r}")
    return SpreadTable(bands, sigma, gain, shape)


def write_spread(path: Path, tables: dict[str, SpreadTable], fitted_on: dict[str, Any]) -> None:
    blob = {"schema": SCHEMA, "modes": {m: t.as_dict() for m, t in tables.items()}, "fitted_on": fitted_on}
    with atomic_write(path) as handle:  # (a stage starting meanwhile reads the old table or the new, never half of one)
        handle.write((json.dumps(blob, indent=2) + "\n").encode())


def _blocking(frame: GridFrame, sigma_m: float) -> tuple[float, int, int]:
    """σ in cells, the block size f (⌊σ / 2 cells⌋, at least 1) and the padding (⌈3σ⌉ cells) of a blur by σ (m)."""
    s_cells = sigma_m / frame.cell_m
    return s_cells, max(int(s_cells // 2.0), 1), int(math.ceil(3.0 * s_cells))


def blur_step(frame: GridFrame, cells: np.ndarray, values: np.ndarray, sigma_m: float):
    """One step of one vehicle's grid blurred by σ: (patch origin row, col, block size f, (R, C) block masses).

    A wide blur runs on blocks of f × f cells (f = ⌊σ / 2 cells⌋, at least 1),
    each cell's mass split linearly between the nearest block centres (the mean
    kept) and blurred with σ/f, so that its cost does not grow with σ; the
    blurred mass is smooth on the scale of σ, and a block spreads its mass
    evenly over its cells (``blur_grid``). Blocks past the
    frame's edge hold no cells: their mass is lost.
    """
    s_cells, f, pad = _blocking(frame, sigma_m)
    rows, cols = np.divmod(cells, frame.n_cols)
    r0, c0 = int(rows.min()) - pad - f, int(cols.min()) - pad - f
    n_r = (int(rows.max()) + pad + f + 1 - r0 + f - 1) // f + 1
    n_c = (int(cols.max()) + pad + f + 1 - c0 + f - 1) // f + 1
    # cloud in cell: each cell's mass split linearly between the two nearest block centres per axis (its mean kept);
    # one np.bincount over the four corners in turn: each block's sum takes its terms in the order of four
    # np.add.at passes, corner by corner (the same numbers)
    u = (rows - r0 - 0.5 * (f - 1)) / f
    w = (cols - c0 - 0.5 * (f - 1)) / f
    bu, bw = np.floor(u).astype(np.int64), np.floor(w).astype(np.int64)
    fu, fw = u - bu, w - bw
    index, weight = [], []
    for du, wu in ((0, 1.0 - fu), (1, fu)):
        for dw, ww in ((0, 1.0 - fw), (1, fw)):
            index.append((bu + du) * n_c + (bw + dw))
            weight.append(values * wu * ww)
    blocks = np.bincount(np.concatenate(index), weights=np.concatenate(weight), minlength=n_r * n_c).reshape(n_r, n_c)
    return r0, c0, f, gaussian_filter(blocks, s_cells / f, mode="constant", truncate=3.0)


def block_cells_sorted(frame: GridFrame, r0: int, c0: int, f: int, blocks: np.ndarray, min_value: float = BLUR_MIN_VALUE):
    """The cells (flat index, increasing) and values of ``blur_step``'s blocks inside the frame, each block's mass
    spread evenly over its f × f cells, those whose value (block / (f·f)) is above ``min_value``: the blocks as one
    dense patch, cut to the frame, its cells read row by row."""
    min_mass = min_value * (f * f)
    if not np.any(blocks > min_mass):
        return np.zeros(0, np.int64), np.zeros(0)
    n_r, n_c = blocks.shape
    row_lo, row_hi = max(r0, 0), min(r0 + n_r * f, frame.n_rows)
    col_lo, col_hi = max(c0, 0), min(c0 + n_c * f, frame.n_cols)
    if row_lo >= row_hi or col_lo >= col_hi:
        return np.zeros(0, np.int64), np.zeros(0)
    # the patch rows/cols inside the frame, and the block each lies in
    block_row = (np.arange(row_lo, row_hi) - r0) // f
    block_col = (np.arange(col_lo, col_hi) - c0) // f
    per_cell = blocks / (f * f)
    mask = (per_cell > min_value)[block_row][:, block_col]
    rr, cc = np.nonzero(mask)
    vals = per_cell[block_row[rr], block_col[cc]]
    return ((row_lo + rr) * frame.n_cols + (col_lo + cc)).astype(np.int64), vals


def _blurred(frame: GridFrame, cells: np.ndarray, values: np.ndarray, sigma_m: float):
    """One step blurred (cells sorted, values): ``blur_step`` then ``block_cells_sorted``, in one compiled call where
    numba imports (``frame_kernels.blur_cells``: the same numbers)."""
    found = frame_kernels.blur_cells(cells, values, frame.n_rows, frame.n_cols, *_blocking(frame, sigma_m), BLUR_MIN_VALUE)
    return found if found is not None else block_cells_sorted(frame, *blur_step(frame, cells, values, sigma_m))


#: ``blur_along``'s Gaussian is cut at this many σ (its weights then normalised)
ALONG_TRUNCATE = 4.0


def along_weights(sigma_cells: np.ndarray, centred: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For σ (cells, any shape): ``which`` (flat, the row of ``weights`` each σ uses, -1 where σ is 0 or not finite),
    ``weights`` (U, 2·max radius + 1: one normalised discrete Gaussian per distinct σ, from the front, zero-padded;
    ``centred``: each centred at the row's middle, as computed) and ``radii`` (U,): ⌈ALONG_TRUNCATE·σ⌉."""
    flat = np.asarray(sigma_cells, dtype=np.float64).reshape(-1)
    ok = np.isfinite(flat) & (flat > 0)
    which = np.full(flat.size, -1, np.int64)
    if not ok.any():
        return which, np.zeros((0, 1)), np.zeros(0, np.int64)
    unique, inverse = np.unique(flat[ok], return_inverse=True)
    which[ok] = inverse
    radii = np.ceil(ALONG_TRUNCATE * unique).astype(np.int64)
    top = int(radii.max())
    weights = gaussian_rows(np.arange(-top, top + 1, dtype=np.float64), unique, radii.astype(np.float64))
    if centred:
        return which, weights, radii
    # each row's weights from its own radius: row u's 2·radii[u] + 1 weights start at top − radii[u]; moved to the front
    # (all rows at once: a gather, then the places past each row's 2·radii[u] + 1 set to 0)
    col = np.arange(2 * top + 1)
    out = np.take_along_axis(weights, np.minimum((top - radii)[:, None] + col[None, :], 2 * top), axis=1)
    out[col[None, :] > 2 * radii[:, None]] = 0.0
    return which, out, radii


def blur_along(probs: np.ndarray, sigma_cells: np.ndarray, min_value: float = BLUR_MIN_VALUE) -> np.ndarray:
    """The pairs' s-distributions ``probs`` (B, K, L) each blurred along its corridor: step k of pair b by a discrete
    Gaussian of σ = ``sigma_cells[b, k]`` cells (0: as is), cut at ``ALONG_TRUNCATE``·σ; mass carried past either end
    of the window is dropped, and values at or below ``min_value`` become 0. float32, a new array. The compiled
    ``frame_kernels.along_rows`` where numba imports (the same sums in another order), else this definition."""
    probs = np.asarray(probs, dtype=np.float32)
    shape = probs.shape
    rows = probs.reshape(-1, shape[-1])
    if np.size(sigma_cells) != rows.shape[0]:
        raise ValueError(f"blur_along: {np.size(sigma_cells)} sigmas for {rows.shape[0]} rows")
    if frame_kernels.available():  # (along_rows without padding, fold or end)
        which, weights, radii = along_weights(sigma_cells, centred=True)
        return frame_kernels.along_rows(rows[None], 0, which, weights, radii, min_value, None, np.zeros((1, rows.shape[1]), np.bool_))[0].reshape(shape)
    which, weights, radii = along_weights(sigma_cells)
    out = rows.copy()
    n_l = rows.shape[1]
    for r in np.flatnonzero(which >= 0).tolist():
        u = int(which[r])
        rad = int(radii[u])
        full = np.convolve(rows[r].astype(np.float64), weights[u, : 2 * rad + 1])  # symmetric: a correlation
        row = full[rad: rad + n_l]
        out[r] = np.where(row > min_value, row, 0.0)
    return out.reshape(shape)


def along_spread(probs: np.ndarray, sigma_cells: np.ndarray, pad: int, start_cell: np.ndarray | None, beyond: np.ndarray,
                 min_value: float = BLUR_MIN_VALUE) -> np.ndarray:
    """The grids' along spread of the pairs' s-distributions ``probs`` (B, K, L): the window padded by ``pad`` cells
    (zeros) at both ends, ``blur_along`` by ``sigma_cells`` (B, K), with ``start_cell`` (B,; in the padded window)
    ``fold_behind`` (None: no fold), and the cells ``beyond`` (B, L + 2·pad) (past the corridor's end) set to 0. float32,
    a new array. In one compiled pass where numba imports (``frame_kernels.along_rows``: the same numbers), else
    these functions one after the other."""
    probs = np.asarray(probs, dtype=np.float32)
    if np.size(sigma_cells) != probs.shape[0] * probs.shape[1]:
        raise ValueError(f"along_spread: {np.size(sigma_cells)} sigmas for {probs.shape[0] * probs.shape[1]} rows")
    if frame_kernels.available():
        which, weights, radii = along_weights(sigma_cells, centred=True)
        return frame_kernels.along_rows(probs, pad, which, weights, radii, min_value, start_cell, beyond)
    padded = np.pad(probs, ((0, 0), (0, 0), (pad, pad))) if pad > 0 else probs
    out = blur_along(padded, sigma_cells, min_value)
    if start_cell is not None:
        fold_behind(out, padded, np.asarray(start_cell, dtype=np.int64))
    np.copyto(out, 0.0, where=np.asarray(beyond, dtype=np.bool_)[:, None, :])
    return out


def fold_behind(out: np.ndarray, before: np.ndarray, start_cell: np.ndarray) -> None:
    """In place: what the along blur carried behind each pair's start folded ahead of it. ``out`` (B, K, L) the
    blurred s-distributions, ``before`` (B, K, L) the same unblurred, ``start_cell`` (B,) the cell that holds the
    vehicle's position now. In a cell behind it the blurred mass above the unblurred (the blur's, not the chain's own
    measurement spread) moves to the cell mirrored about the start cell (2·start − j; dropped past the window's end,
    as the blur drops it): a car is not predicted behind where it is now, and the mass is kept, close to where the blur
    put it. The means and the chain's distributions are not touched (the grids only)."""
    n_b, _n_k, n_l = out.shape
    j = np.arange(n_l)
    behind = j[None, :] < np.clip(start_cell, 0, n_l)[:, None]  # (B, L)
    if not behind.any():
        return
    bb, jj = np.nonzero(behind)
    blurred = out[bb, :, jj]  # (n, K)
    excess = blurred - np.minimum(blurred, before[bb, :, jj])
    out[bb, :, jj] = blurred - excess
    target = 2 * start_cell[bb] - jj
    keep = target < n_l
    out[bb[keep], :, target[keep]] += excess[keep]  # (each target once per pair: the mirror is one to one)


def blur_grid(frame: GridFrame, grid: SparseGrid, sigmas_m: np.ndarray) -> SparseGrid:
    """One vehicle's grid (all steps) with step k blurred by an isotropic Gaussian of σ = ``sigmas_m[k]`` (m; 0: as is);
    a blurred step keeps its cells above ``BLUR_MIN_VALUE``."""
    sigmas = np.asarray(sigmas_m, dtype=np.float64)
    if not np.any(sigmas > 0) or grid.keys.size == 0:
        return grid
    n_cells = frame.n_cells
    keys, values = [], []
    for k, sigma in enumerate(sigmas):
        cells, vals = grid.step(k, n_cells)
        if cells.size == 0:
            continue
        if sigma > 0 and math.isfinite(sigma):
            cells, vals = _blurred(frame, cells, vals, float(sigma))
        keys.append(cells + k * n_cells)
        values.append(vals)
    if not keys:
        return grid
    # each step's cells in increasing order (a step of the grid is; block_cells_sorted's are), the steps in order:
    # the keys are sorted as they come
    return SparseGrid(np.concatenate(keys).astype(np.int64), np.concatenate(values))
