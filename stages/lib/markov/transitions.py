"""Offline transition stencils Υ(τ) and Υ([0, τ]) by sampled push-forward (docs/method.md §3.1–3.3).

Model (§3.1): s' = v, v' = a with a held constant over one step of τ; v
saturates at 0 (the vehicle stays stopped, s frozen, no reversing) and at
v_max. The motion is piecewise quadratic and is integrated exactly.

Construction (§3.2, "sampled push-forward"): for every velocity cell j and
input cell α, the box (one s-cell) × (v-cell j) × (input cell α) is filled with
a regular grid of samples at sub-box centres; each sample is integrated to τ
and the end points are histogrammed into (s-offset Δi_s, target v-cell j′).
That gives the **time-point** stencil, the exact image of "uniform on the cell
× uniform on the input cell". The **interval** stencil histograms the same
samples at ``n_sub_times`` sub-times (centres of equal sub-intervals of
[0, τ]) and averages: the probability of being in a cell at a uniformly random
time of the step.

Storage (§3.3): the dynamics do not depend on s, so one stencil per (α, j)
describes every column. Both stencils are kept as dense kernels
``W[α, j′, j, d]`` (probability to move from v-cell j to v-cell j′ and d
s-cells forward), float64, which are tiny (M·N_v²·D). They expand to

- a scipy CSR matrix over the joint states (α, v, s) of one window plus an
  absorbing *outside* cell (mass past the end of the window), and
- a torch grouped 1-D convolution along s (groups = inputs, channels = v).

Stencils are cached on disk as ``.npz`` (never pickled), keyed by
``MarkovGridConfig.cache_key()``; a cache file that fails any check is rebuilt.
"""

from __future__ import annotations

import enum
import logging
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from stages.lib.base import atomic_write
from stages.lib.markov.grid import MarkovGridConfig

logger = logging.getLogger("iamp.markov")

#: Version of the ``.npz`` layout written by ``save_stencils``.
CACHE_FORMAT_VERSION = 1

#: Tolerance on stencil column sums, when built and when loaded.
COLUMN_SUM_TOLERANCE = 1e-9


class TransitionKind(enum.IntEnum):
    """Which of the two offline matrices."""

    TIME_POINT = 0
    """Υ(τ): distribution of the state at the end of the step."""
    TIME_INTERVAL = 1
    """Υ([0, τ]): distribution of the state at a uniformly random time of the step."""


# ---------------------------------------------------------------------------
# Continuous model
# ---------------------------------------------------------------------------


def integrate_saturated(
    s0_m: np.ndarray, v0_mps: np.ndarray, accel_mps2: np.ndarray, t_s: float, v_max_mps: float
) -> tuple[np.ndarray, np.ndarray]:
    """Exact (s, v) after ``t_s`` under constant acceleration with saturation at 0 and v_max.

    The arguments broadcast against each other. Before the clamp time
    t_c (v reaches 0 when braking or v_max when accelerating) the motion is
    s0 + v0·t + a·t²/2; from t_c on, v is held at the bound, so a stopped
    vehicle keeps its s and never reverses. ``v0_mps`` must lie in [0, v_max].
    """
    s0, v0, a = np.broadcast_arrays(
        np.asarray(s0_m, dtype=np.float64),
        np.asarray(v0_mps, dtype=np.float64),
        np.asarray(accel_mps2, dtype=np.float64),
    )
    t_clamp_s = np.full(a.shape, np.inf)
    braking = a < 0
    accelerating = a > 0
    t_clamp_s[braking] = v0[braking] / -a[braking]
    t_clamp_s[accelerating] = (v_max_mps - v0[accelerating]) / a[accelerating]
    t_free_s = np.minimum(t_s, t_clamp_s)
    clamped = t_s >= t_clamp_s
    v_bound_mps = np.where(braking, 0.0, v_max_mps)
    v_end_mps = np.where(clamped, v_bound_mps, np.clip(v0 + a * t_s, 0.0, v_max_mps))
    s_end_m = s0 + v0 * t_free_s + 0.5 * a * t_free_s**2 + np.where(clamped, v_bound_mps * (t_s - t_free_s), 0.0)
    return s_end_m, v_end_mps


# ---------------------------------------------------------------------------
# Building
# ---------------------------------------------------------------------------


def _offset_bound(config: MarkovGridConfig) -> int:
    """An upper bound on the number of s-offsets a one-step stencil can use."""
    return int(np.ceil((config.ds_m + config.v_max_mps * config.tau_s) / config.ds_m)) + 2


def _histogram(config: MarkovGridConfig, t_s: float, n_offsets: int) -> np.ndarray:
    """Counts of the push-forward samples at time ``t_s``, shape (M, N_v, N_v, n_offsets) int64.

    Axis order is [α, target v-cell, source v-cell, s-offset]. Every sample
    of every (α, source v-cell) is integrated in one vectorised call.
    """
    n_v, n_in = config.n_v_cells, config.n_inputs
    n_state, n_acc = config.n_state_samples, config.n_input_samples
    unit_state = (np.arange(n_state) + 0.5) / n_state
    unit_acc = (np.arange(n_acc) + 0.5) / n_acc
    edges = config.input_edges()
    s0_m = unit_state * config.ds_m  # (n_state,)
    v0_mps = (np.arange(n_v)[:, None] + unit_state[None, :]) * config.dv_mps  # (N_v, n_state)
    accel_mps2 = edges[:-1, None] + unit_acc[None, :] * np.diff(edges)[:, None]  # (M, n_acc)
    # Broadcast layout: (M, N_v, s-sample, v-sample, a-sample).
    s_end_m, v_end_mps = integrate_saturated(
        s0_m[None, None, :, None, None],
        v0_mps[None, :, None, :, None],
        accel_mps2[:, None, None, None, :],
        t_s,
        config.v_max_mps,
    )
    offsets = np.floor(s_end_m / config.ds_m).astype(np.int64)
    if offsets.min() < 0 or offsets.max() >= n_offsets:
        raise RuntimeError(f"push-forward offset out of range: {offsets.min()}..{offsets.max()} vs {n_offsets}")
    v_to = np.clip(np.floor(v_end_mps / config.dv_mps).astype(np.int64), 0, n_v - 1)
    alpha = np.arange(n_in).reshape(n_in, 1, 1, 1, 1)
    v_from = np.arange(n_v).reshape(1, n_v, 1, 1, 1)
    flat = ((alpha * n_v + v_to) * n_v + v_from) * n_offsets + offsets
    counts = np.bincount(flat.ravel(), minlength=n_in * n_v * n_v * n_offsets)
    return counts.reshape(n_in, n_v, n_v, n_offsets)


def build_stencils(config: MarkovGridConfig) -> TransitionStencils:
    """Build Υ(τ) and Υ([0, τ]) stencils by sampled push-forward, float64.

    Deterministic: the samples form a regular grid, so the same config always
    gives the same arrays.
    """
    bound = _offset_bound(config)
    n_samples = config.n_state_samples**2 * config.n_input_samples
    point = _histogram(config, config.tau_s, bound).astype(np.float64) / n_samples
    interval_counts = np.zeros_like(point)
    for k in range(config.n_sub_times):
        t_s = (k + 0.5) / config.n_sub_times * config.tau_s
        interval_counts += _histogram(config, t_s, bound)
    interval = interval_counts / (n_samples * config.n_sub_times)
    used = np.flatnonzero((point.sum(axis=(0, 1, 2)) + interval.sum(axis=(0, 1, 2))) > 0)
    n_offsets = int(used.max()) + 1
    return TransitionStencils(
        config=config,
        point_kernel=np.ascontiguousarray(point[..., :n_offsets]),
        interval_kernel=np.ascontiguousarray(interval[..., :n_offsets]),
    )


# ---------------------------------------------------------------------------
# The stencils and their expansions
# ---------------------------------------------------------------------------


@dataclass(frozen=True, kw_only=True, eq=False)
class TransitionStencils:
    """Υ(τ) and Υ([0, τ]) of one grid, as translation-invariant stencils.

    ``point_kernel`` and ``interval_kernel`` are ``(M, N_v, N_v, D) float64``
    indexed ``[α, j′ (target v-cell), j (source v-cell), d (s-offset in
    cells, 0 … D-1)]``: the probability that mass in v-cell j of any s-cell i
    under input α is in (s-cell i + d, v-cell j′) after the step. Every column
    (α, j) sums to 1.
    """

    config: MarkovGridConfig
    point_kernel: np.ndarray
    interval_kernel: np.ndarray

    @property
    def n_offsets(self) -> int:
        """Number D of s-offsets (0 … D-1) used by either stencil."""
        return int(self.point_kernel.shape[-1])

    def kernel(self, kind: TransitionKind) -> np.ndarray:
        """The dense kernel ``(M, N_v, N_v, D) float64`` of ``kind``."""
        return self.point_kernel if kind == TransitionKind.TIME_POINT else self.interval_kernel

    def column_sums(self, kind: TransitionKind) -> np.ndarray:
        """Total probability per source column (α, j), ``(M, N_v) float64`` (all 1)."""
        return self.kernel(kind).sum(axis=(1, 3))

    def nnz(self, kind: TransitionKind) -> int:
        """Number of stencil entries (all (α, j) columns together)."""
        return int(np.count_nonzero(self.kernel(kind)))

    def stencil(self, kind: TransitionKind, alpha: int, v_cell: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Stencil of the column (α, v-cell): ``(ds_cells, v_targets, probs)`` int64, int64, float64 arrays."""
        column = self.kernel(kind)[alpha, :, v_cell, :]  # (N_v target, D)
        v_targets, ds_cells = np.nonzero(column)
        return ds_cells, v_targets, column[v_targets, ds_cells]

    def leak(self, kind: TransitionKind, n_s_cells: int | None = None) -> np.ndarray:
        """Probability that one step moves mass past the end of the window, ``(M, N_v, N_s) float64``.

        Entry [α, j, i] is the mass of state (α, j, i) that the step sends to
        the outside cell. It is zero except in the last D-1 s-cells.
        """
        n_s = self.config.n_s_cells if n_s_cells is None else int(n_s_cells)
        per_offset = self.kernel(kind).sum(axis=1)  # (M, N_v source, D)
        # tail[..., m] = mass moved by m or more cells.
        tail = np.cumsum(per_offset[..., ::-1], axis=-1)[..., ::-1]
        tail = np.concatenate([tail, np.zeros(tail.shape[:-1] + (1,))], axis=-1)
        remaining = n_s - np.arange(n_s)  # cells from s to the end, >= 1
        index = np.minimum(remaining, self.n_offsets)
        return tail[..., index]

    def expand_sparse(
        self, kind: TransitionKind, n_s_cells: int | None = None, alpha: int | None = None
    ) -> sp.csr_matrix:
        """Column-stochastic CSR matrix of one step over a window of ``n_s_cells``.

        With ``alpha=None`` the states are all (α, v, s) of one window, flat
        index ``(α·N_v + v)·N_s + s`` (block-diagonal over α), and the last
        index ``M·N_v·N_s`` is the absorbing outside cell. With an ``alpha``
        the matrix is that input's block: index ``v·N_s + s``, outside last.
        Entry (row, col) is P(next state row | state col). float64.
        """
        n_s = self.config.n_s_cells if n_s_cells is None else int(n_s_cells)
        if n_s < 1:
            raise ValueError(f"expand_sparse: n_s_cells must be >= 1, got {n_s}")
        n_v = self.config.n_v_cells
        kernel = self.kernel(kind)
        if alpha is not None:
            if not 0 <= alpha < self.config.n_inputs:
                raise ValueError(f"expand_sparse: alpha {alpha} outside 0..{self.config.n_inputs - 1}")
            kernel = kernel[alpha : alpha + 1]
        n_blocks = kernel.shape[0]
        a_idx, v_to, v_from, d = np.nonzero(kernel)
        probs = kernel[a_idx, v_to, v_from, d]
        s_from = np.arange(n_s)
        s_to = s_from[None, :] + d[:, None]  # (E, N_s)
        n_states = n_blocks * n_v * n_s
        cols = ((a_idx * n_v + v_from) * n_s)[:, None] + s_from[None, :]
        rows = np.where(s_to < n_s, ((a_idx * n_v + v_to) * n_s)[:, None] + s_to, n_states)
        data = np.broadcast_to(probs[:, None], rows.shape)
        rows = np.concatenate([rows.ravel(), [n_states]])
        cols = np.concatenate([cols.ravel(), [n_states]])
        data = np.concatenate([data.ravel(), [1.0]])
        matrix = sp.coo_matrix((data, (rows, cols)), shape=(n_states + 1, n_states + 1)).tocsr()
        matrix.sum_duplicates()
        return matrix

    def conv_weight(self, kind: TransitionKind) -> np.ndarray:
        """Weight for ``torch.nn.functional.conv1d(..., groups=M)``: ``(M·N_v, N_v, D) float64``.

        conv1d computes a cross-correlation, so the s-offset axis is flipped:
        with the input left-padded by D-1 zeros, output cell i gets
        Σ_d W[α, j′, j, d] · p[α, j, i − d].
        """
        kernel = self.kernel(kind)
        n_in, n_v = kernel.shape[0], kernel.shape[1]
        return np.ascontiguousarray(kernel[..., ::-1].reshape(n_in * n_v, n_v, self.n_offsets))


# ---------------------------------------------------------------------------
# Disk cache
# ---------------------------------------------------------------------------


class _InvalidCache(Exception):
    """A cache file that must not be trusted; the message says why."""


def default_cache_dir() -> Path:
    """``~/.cache/hybrid-iamp/markov``."""
    return Path.home() / ".cache" / "hybrid-iamp" / "markov"


def cache_path(config: MarkovGridConfig, cache_dir: str | os.PathLike[str] | None = None) -> Path:
    """Where the stencils of ``config`` are cached: ``<dir>/stencils-<cache_key>.npz`` (``~`` in ``cache_dir`` is the
    home folder, as in the other path parameters; it made a folder named ``~`` in the current one)."""
    directory = default_cache_dir() if cache_dir is None else Path(cache_dir).expanduser()
    return directory / f"stencils-{config.cache_key()}.npz"


_KIND_PREFIX = {TransitionKind.TIME_POINT: "point", TransitionKind.TIME_INTERVAL: "interval"}


def save_stencils(stencils: TransitionStencils, path: str | os.PathLike[str]) -> None:
    """Write ``stencils`` to ``path`` atomically (``stages.lib.base.atomic_write``: a file of its own, then renamed).

    Each kind is stored as parallel arrays of its non-zero entries:
    ``<kind>_alpha, <kind>_v_from, <kind>_ds_cells, <kind>_v_to`` (int16) and
    ``<kind>_prob`` (float64), plus ``params_json``, ``format_version`` and
    ``kernel_shape``. No object arrays, so it loads with ``allow_pickle=False``.
    """
    path = Path(path)
    arrays: dict[str, np.ndarray] = {
        "format_version": np.array(CACHE_FORMAT_VERSION, dtype=np.int64),
        "params_json": np.array(stencils.config.params_json()),
        "kernel_shape": np.array(stencils.point_kernel.shape, dtype=np.int64),
    }
    for kind, prefix in _KIND_PREFIX.items():
        kernel = stencils.kernel(kind)
        alpha, v_to, v_from, ds_cells = np.nonzero(kernel)
        arrays[f"{prefix}_alpha"] = alpha.astype(np.int16)
        arrays[f"{prefix}_v_from"] = v_from.astype(np.int16)
        arrays[f"{prefix}_ds_cells"] = ds_cells.astype(np.int16)
        arrays[f"{prefix}_v_to"] = v_to.astype(np.int16)
        arrays[f"{prefix}_prob"] = kernel[alpha, v_to, v_from, ds_cells]
    with atomic_write(path) as handle:
        np.savez(handle, **arrays)


def load_stencils(path: str | os.PathLike[str], config: MarkovGridConfig) -> TransitionStencils:
    """Read stencils written by ``save_stencils`` and check them against ``config``.

    Raises ``ValueError`` (with the reason) unless the file parses without
    pickle, its parameters equal ``config``'s, every index is in range, every
    probability is finite and non-negative, and every column of both stencils
    sums to 1 within ``COLUMN_SUM_TOLERANCE``.
    """
    try:
        return _load_checked(Path(path), config)
    except _InvalidCache as exc:
        raise ValueError(str(exc)) from None


def _load_checked(path: Path, config: MarkovGridConfig) -> TransitionStencils:
    try:
        with np.load(path, allow_pickle=False) as npz:
            arrays = {name: npz[name] for name in npz.files}
    except Exception as exc:  # any parse failure means the file is not trusted
        raise _InvalidCache(f"unreadable ({type(exc).__name__}: {exc})") from None
    try:
        version = int(arrays["format_version"])
        params_json = str(arrays["params_json"])
        shape = tuple(int(x) for x in arrays["kernel_shape"])
    except (KeyError, TypeError, ValueError) as exc:
        raise _InvalidCache(f"missing or malformed header ({type(exc).__name__}: {exc})") from None
    if version != CACHE_FORMAT_VERSION:
        raise _InvalidCache(f"format_version {version}, this build reads {CACHE_FORMAT_VERSION}")
    if params_json != config.params_json():
        raise _InvalidCache("parameters differ from the requested grid")
    n_in, n_v = config.n_inputs, config.n_v_cells
    if len(shape) != 4 or shape[:3] != (n_in, n_v, n_v) or not 1 <= shape[3] <= _offset_bound(config):
        raise _InvalidCache(f"kernel_shape {shape} does not fit the grid")
    kernels = {}
    for kind, prefix in _KIND_PREFIX.items():
        try:
            columns = [arrays[f"{prefix}_{name}"] for name in ("alpha", "v_to", "v_from", "ds_cells")]
            probs = arrays[f"{prefix}_prob"]
        except KeyError as exc:
            raise _InvalidCache(f"missing array {exc}") from None
        n_entries = probs.shape[0] if probs.ndim == 1 else -1
        if probs.dtype != np.float64 or any(c.ndim != 1 or c.shape[0] != n_entries for c in columns):
            raise _InvalidCache(f"{prefix} stencil arrays have inconsistent shapes or dtypes")
        if not all(np.issubdtype(c.dtype, np.integer) for c in columns):
            raise _InvalidCache(f"{prefix} stencil indices are not integers")
        for c, bound in zip(columns, shape):
            if c.size and (c.min() < 0 or c.max() >= bound):
                raise _InvalidCache(f"{prefix} stencil index out of range")
        if not np.all(np.isfinite(probs)) or np.any(probs < 0):
            raise _InvalidCache(f"{prefix} stencil has negative or non-finite probabilities")
        kernel = np.zeros(shape, dtype=np.float64)
        np.add.at(kernel, tuple(c.astype(np.int64) for c in columns), probs)
        sums = kernel.sum(axis=(1, 3))
        worst = float(np.max(np.abs(sums - 1.0)))
        if worst > COLUMN_SUM_TOLERANCE:
            raise _InvalidCache(f"{prefix} stencil column sums off by {worst:.3g}")
        kernels[kind] = kernel
    return TransitionStencils(
        config=config,
        point_kernel=kernels[TransitionKind.TIME_POINT],
        interval_kernel=kernels[TransitionKind.TIME_INTERVAL],
    )


def load_or_build_stencils(
    config: MarkovGridConfig, cache_dir: str | os.PathLike[str] | None = None
) -> TransitionStencils:
    """The stencils of ``config``, from the disk cache when a valid file is there.

    A missing file is built and written. A file that fails any check of
    ``load_stencils`` is logged with one warning line, rebuilt and
    overwritten. A cache that cannot be written is logged and the built
    stencils are returned anyway.
    """
    path = cache_path(config, cache_dir)
    if path.exists():
        try:
            return _load_checked(path, config)
        except _InvalidCache as exc:
            logger.warning("markov stencil cache rejected, rebuilding: path=%s reason=%s", path, exc)
    stencils = build_stencils(config)
    try:
        save_stencils(stencils, path)
    except OSError as exc:
        logger.warning("markov stencil cache not written: path=%s reason=%s", path, exc)
    else:
        logger.info("markov stencils built and cached: path=%s", path)
    return stencils
