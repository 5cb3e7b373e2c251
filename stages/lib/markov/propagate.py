"""Online Markov recursion for a batch of vehicle-corridor pairs (docs/method.md §3.4, §4.1, §8.5).

**Layout.** The joint distribution of B pairs is ``p[b, α, v, s]``:
b the vehicle-corridor pair, α the input cell, v the velocity cell, s the
s-cell of the pair's window (``(B, M, N_v, N_s) float32``). The mass that
has left the window (the absorbing outside cell) is a separate ``(B,)``
vector. For every b, ``p[b].sum() + outside[b] (+ pruned mass when it is not
renormalised)`` is 1.

One step k → k+1 (CORA's order):

1. p⁻ = Υ(τ) p — state transition with the input held;
2. p_int = Υ([0, τ]) p — interval distribution, only when asked (it costs as
   much as step 1);
3. marginals over α (velocity) and over α, v (position), of p⁻ and p_int;
4. pruning: entries of p⁻ below ``prune_threshold`` are zeroed; by default the
   dropped mass is put back proportionally onto the kept entries of the same
   pair (so the outside mass is untouched) and reported;
5. input transition Γ: p(t_{k+1})[b, :, v, s] = Γ[b, :, :, v, s] p⁻[b, :, v, s].

Γ is never needed for the marginals of step k (Γ is column-stochastic and
acts at fixed (v, s)); it shapes the steps after. In hybrid mode step k is
given ``InputReplaced(probs=λ(k+1))``.

Backends with one API: ``"numpy"`` (single thread: numba kernels over the
occupied states, ``stages/lib/markov/kernels.py``, or the scipy CSR products,
``kernel="scipy"``, the reference) and ``"torch"`` (grouped conv1d along s on
``"cpu"`` or ``"cuda"``). All run in float32 and check at the end of a run
that the mass is conserved to 1e-5.

Active-window cropping (docs/method.md §3.5): mass never moves backwards and
moves at most D-1 cells per step, so each step only touches the s-cells from
the first occupied cell (over the batch) to the last occupied cell + D - 1,
rounded up to a multiple of ``crop_quantum_cells``.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any, Literal, Union

import numpy as np
import scipy.sparse as sp

from stages.lib.markov import kernels
from stages.lib.markov.grid import MarkovGridConfig
from stages.lib.markov.transitions import TransitionKind, TransitionStencils

logger = logging.getLogger("iamp.markov")

#: Largest |total mass - 1| a run tolerates before it logs a warning.
MASS_TOLERANCE = 1e-5

_STOCHASTIC_TOLERANCE = 1e-4

Backend = Literal["numpy", "torch"]

#: The numpy backend's step: ``"numba"`` (``stages.lib.markov.kernels``: one compiled pass over the occupied states),
#: ``"scipy"`` (CSR products over the whole active window: the reference), ``"auto"`` (numba where it imports).
NumpyKernel = Literal["auto", "numba", "scipy"]


# ---------------------------------------------------------------------------
# Ψ and Γ (docs/method.md §4.1)
# ---------------------------------------------------------------------------


def psi_matrix(input_centres_mps2: np.ndarray, *, gamma: float = 0.2, unit_mps2: float = 0.5) -> np.ndarray:
    """Inherent input behaviour Ψ, ``(M, M) float64``, column-stochastic.

    Ψ[a, b] ∝ 1 / (((c_a − c_b) / unit)² + γ) over the input cell centres c,
    columns normalised. The distance is measured in units of ``unit_mps2``
    (the nominal cell width), so that with 0.5 m/s² cells it equals the
    index distance of CORA's Ψ: the middle column of the 10-cell grid is then
    [.005 .008 .014 .032 .111 .665 .111 .032 .014 .008] (docs/method.md §4.1).
    """
    centres = np.asarray(input_centres_mps2, dtype=np.float64)
    if centres.ndim != 1 or centres.size < 1:
        raise ValueError(f"psi_matrix: input_centres_mps2 must be a non-empty 1-D array, got shape {centres.shape}")
    if gamma <= 0 or unit_mps2 <= 0:
        raise ValueError(f"psi_matrix: gamma and unit_mps2 must be positive, got {gamma}, {unit_mps2}")
    distance = (centres[:, None] - centres[None, :]) / unit_mps2
    psi = 1.0 / (distance**2 + gamma)
    return psi / psi.sum(axis=0, keepdims=True)


def gamma_from_priority(lambda_: np.ndarray, psi: np.ndarray) -> np.ndarray:
    """Input transition Γ = colnorm(diag(λ) Ψ) for every leading index of ``lambda_``.

    ``lambda_`` is ``(..., M)`` priorities in [0, 1]; the result is
    ``(..., M, M) float64`` with Γ[..., a, b] = λ[a] Ψ[a, b] / Σ_a′ λ[a′] Ψ[a′, b]:
    column b is the distribution of the next input given the previous input b.
    Where every λ of a state is zero (every input forbidden) the strongest
    braking input (index 0) is kept, so that no column is all zeros.
    """
    lam = np.asarray(lambda_, dtype=np.float64)
    psi = np.asarray(psi, dtype=np.float64)
    n_in = psi.shape[0]
    if psi.shape != (n_in, n_in) or lam.shape[-1:] != (n_in,):
        raise ValueError(
            f"gamma_from_priority: lambda_ (..., {n_in}) and psi ({n_in}, {n_in}) expected, got {lam.shape}, {psi.shape}"
        )
    if not np.all(np.isfinite(lam)) or np.any(lam < 0):
        raise ValueError("gamma_from_priority: lambda_ must be finite and non-negative")
    all_zero = ~np.any(lam > 0, axis=-1)
    if np.any(all_zero):
        lam = lam.copy()
        lam[all_zero] = 0.0
        lam[all_zero, 0] = 1.0
    weighted = lam[..., :, None] * psi  # (..., M, M)
    return weighted / weighted.sum(axis=-2, keepdims=True)


# ---------------------------------------------------------------------------
# Input transitions (step 5)
# ---------------------------------------------------------------------------


@dataclass(frozen=True, kw_only=True, eq=False)
class InputMatrix:
    """State-independent Γ per pair for one step: ``gamma`` is ``(B, M, M)``, column-stochastic.

    p(t_{k+1})[b, :, v, s] = gamma[b] @ p⁻[b, :, v, s]. numpy array or torch tensor.
    """

    gamma: Any


@dataclass(frozen=True, kw_only=True, eq=False)
class InputReplaced:
    """Input distribution replaced for one step: ``probs`` is ``(B, M)``, rows summing to 1.

    p(t_{k+1})[b, α, v, s] = probs[b, α] · Σ_α′ p⁻[b, α′, v, s]: the same
    distribution in every state (hybrid mode: the AR distribution λ(k+1);
    also the "direct" ablation). numpy array or torch tensor.
    """

    probs: Any


@dataclass(frozen=True, kw_only=True, eq=False)
class InputPerState:
    """General Γ for one step: ``gamma`` is ``(B, M, M, N_v, N_s)``, column-stochastic over axis 1.

    p(t_{k+1})[b, :, v, s] = gamma[b, :, :, v, s] @ p⁻[b, :, v, s]. Columns of
    states without mass may be anything finite. numpy array or torch tensor.
    """

    gamma: Any


InputTransition = Union[InputMatrix, InputReplaced, InputPerState]


# ---------------------------------------------------------------------------
# Initial state (§3.4 "Initialisation")
# ---------------------------------------------------------------------------


def _overlaps(edges: np.ndarray, centres: np.ndarray, half_widths: np.ndarray) -> np.ndarray:
    """Overlap lengths (B, N) of boxes [c - h, c + h] with the cells between ``edges``."""
    lower = np.maximum(edges[None, :-1], (centres - half_widths)[:, None])
    upper = np.minimum(edges[None, 1:], (centres + half_widths)[:, None])
    return np.clip(upper - lower, 0.0, None)


def _box_overlaps(edges: np.ndarray, centres: np.ndarray, half_widths: np.ndarray, what: str) -> np.ndarray:
    """Overlap fractions (B, N) of boxes [c - h, c + h] with cells; the part outside the grid is dropped."""
    overlap = _overlaps(edges, centres, half_widths)
    total = overlap.sum(axis=1, keepdims=True)
    empty = np.flatnonzero(total[:, 0] <= 0)
    if empty.size:
        raise ValueError(f"initial_state: the {what} box of pair(s) {empty.tolist()} does not intersect the grid")
    return overlap / total


def boxes_outside_grid(
    config: MarkovGridConfig,
    *,
    s_m: np.ndarray,
    v_mps: np.ndarray,
    half_width_s_m: np.ndarray,
    half_width_v_mps: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """(position, velocity): (B,) bool, the pairs whose box misses the window or the speed cells (or is not finite).

    ``initial_state`` raises for exactly these pairs; a caller checks them
    first to predict such a pair some other way instead of losing the batch.
    """
    s, v, hs, hv = (np.atleast_1d(np.asarray(x, dtype=np.float64)) for x in (s_m, v_mps, half_width_s_m, half_width_v_mps))
    s_ok = np.isfinite(s) & np.isfinite(hs) & (hs > 0)
    v_ok = np.isfinite(v) & np.isfinite(hv) & (hv > 0)
    with np.errstate(invalid="ignore"):
        s_hit = _hits(config.s_edges_m(), np.where(s_ok, s, 0.0), np.where(s_ok, hs, 1.0))
        v_hit = _hits(config.v_edges_mps(), np.where(v_ok, v, 0.0), np.where(v_ok, hv, 1.0))
    return ~(s_ok & s_hit), ~(v_ok & v_hit)


def _hits(edges: np.ndarray, centres: np.ndarray, half_widths: np.ndarray) -> np.ndarray:
    """(B,) whether ``_overlaps(edges, centres, half_widths).sum(axis=1) > 0``, without the (B, N) array: for cells
    that tile [edges[0], edges[-1]] (increasing edges), some cell's overlap min(e_j+1, c + h) − max(e_j, c − h) is
    > 0 exactly when max(edges[0], c − h) < min(edges[-1], c + h) (the cell holding the start of that interval has
    it; a difference of two floats is 0 only when they are equal), and a sum of terms >= 0 is > 0 exactly when one is."""
    return np.maximum(edges[0], centres - half_widths) < np.minimum(edges[-1], centres + half_widths)


@dataclass(frozen=True, kw_only=True, eq=False)
class SeparableState:
    """A joint distribution in product form: p[b, α, v, s] = input[b, α] · velocity[b, v] · position[b, s].

    ``input_probs`` (B, M), ``velocity_probs`` (B, N_v), ``position_probs``
    (B, N_s), float32, each row a distribution.
    """

    input_probs: np.ndarray
    velocity_probs: np.ndarray
    position_probs: np.ndarray

    def joint(self) -> np.ndarray:
        """The dense ``(B, M, N_v, N_s) float32`` array."""
        joint = (
            self.input_probs[:, :, None, None]
            * self.velocity_probs[:, None, :, None]
            * self.position_probs[:, None, None, :]
        )
        return joint.astype(np.float32)


def initial_state(
    config: MarkovGridConfig,
    *,
    s_m: np.ndarray,
    v_mps: np.ndarray,
    half_width_s_m: np.ndarray | float,
    half_width_v_mps: np.ndarray | float,
    input_probs: np.ndarray,
) -> SeparableState:
    """p(t_0) for B pairs: a uniform box in (s, v) times an input distribution.

    ``s_m`` (position in the pair's window, 0 at its start) and ``v_mps`` are
    ``(B,)``; the half-widths are ``(B,)`` or scalars and must be positive
    (docs/method.md suggests ±max(Δs/2, 2σ_s) and ±max(Δv/2, 2σ_v)). Each axis
    gets the overlap fractions of its box with the cells; the part of a box
    outside the grid (v < 0, past v_max, outside the window) is dropped and
    the rest renormalised. ``input_probs`` is ``(B, M)`` or ``(M,)`` with rows
    summing to 1 (λ(0) in hybrid mode). The result is kept in product form;
    ``MarkovPropagator.run`` takes it as it is (cheaper than a dense array),
    and ``.joint()`` gives the dense p(t_0).
    """
    s_m = np.atleast_1d(np.asarray(s_m, dtype=np.float64))
    v_mps = np.atleast_1d(np.asarray(v_mps, dtype=np.float64))
    n_pairs = s_m.shape[0]
    if s_m.shape != (n_pairs,) or v_mps.shape != (n_pairs,):
        raise ValueError(f"initial_state: s_m and v_mps must both be (B,), got {s_m.shape} and {v_mps.shape}")
    hs = np.broadcast_to(np.asarray(half_width_s_m, dtype=np.float64), (n_pairs,))
    hv = np.broadcast_to(np.asarray(half_width_v_mps, dtype=np.float64), (n_pairs,))
    values = np.concatenate([s_m, v_mps, hs, hv])
    if not np.all(np.isfinite(values)) or np.any(hs <= 0) or np.any(hv <= 0):
        raise ValueError("initial_state: positions, speeds and half-widths must be finite, half-widths positive")
    probs = np.asarray(input_probs, dtype=np.float64)
    probs = np.broadcast_to(probs, (n_pairs, config.n_inputs)) if probs.ndim == 1 else probs
    if probs.shape != (n_pairs, config.n_inputs):
        raise ValueError(
            f"initial_state: input_probs must be (B, {config.n_inputs}) or ({config.n_inputs},), got {probs.shape}"
        )
    if np.any(probs < 0) or np.max(np.abs(probs.sum(axis=1) - 1.0)) > 1e-6:
        raise ValueError("initial_state: every row of input_probs must be a distribution")
    s_frac = _box_overlaps(config.s_edges_m(), s_m, hs, "position")
    v_frac = _box_overlaps(config.v_edges_mps(), v_mps, hv, "velocity")
    return SeparableState(
        input_probs=probs.astype(np.float32),
        velocity_probs=v_frac.astype(np.float32),
        position_probs=s_frac.astype(np.float32),
    )


# ---------------------------------------------------------------------------
# Results
# ---------------------------------------------------------------------------


@dataclass(frozen=True, kw_only=True, eq=False)
class StepMarginals:
    """Marginals of one step in the backend's array type (numpy or torch), pair axis first.

    ``position`` (B, N_s) and ``velocity`` (B, N_v) of p⁻ at t_{k+1};
    ``interval_position`` (B, N_s) of Υ([0, τ]) p(t_k) or None;
    ``outside`` (B,) cumulative outside mass at t_{k+1}.
    """

    position: Any
    velocity: Any
    interval_position: Any
    outside: Any


@dataclass(frozen=True, kw_only=True, eq=False)
class PropagationResult:
    """Output of a run of K steps for B pairs, numpy float32 (step k is time t_{k+1} = (k+1)·τ).

    - ``position_probs`` (B, K, N_s): time-point position marginal;
    - ``velocity_probs`` (B, K, N_v): time-point velocity marginal;
    - ``interval_position_probs`` (B, K, N_s) or None: position marginal of
      Υ([0, τ]) p(t_k), the occupancy of step k;
    - ``outside_mass`` (B, K): mass past the end of the window at t_{k+1}
      (cumulative; never renormalised away);
    - ``interval_outside_mass`` (B, K) or None: outside part of the interval
      distribution;
    - ``pruned_mass`` (B, K): mass below the threshold at step k (put back
      onto the kept entries when ``renormalise_pruned``, lost otherwise);
    - ``final_state`` (B, M, N_v, N_s) or None: p(t_K) after the last Γ, when asked;
    - ``mass_error`` (B,): |Σ final_state + outside (+ pruned if lost) − 1|.
    """

    position_probs: np.ndarray
    velocity_probs: np.ndarray
    interval_position_probs: np.ndarray | None
    outside_mass: np.ndarray
    interval_outside_mass: np.ndarray | None
    pruned_mass: np.ndarray
    final_state: np.ndarray | None
    mass_error: np.ndarray


# ---------------------------------------------------------------------------
# Backends
#
# Both work on a *slab*: the state restricted to the s-cells [lo, hi) of the
# window (the whole window when cropping is off). Cells outside the slab hold
# no mass.
# ---------------------------------------------------------------------------


class _NumpyBackend:
    """scipy CSR products or the numba kernels, single thread. Slab layout (L, M, N_v, B): s outermost, pairs innermost.

    With s outermost a window is a contiguous block, and the CSR product
    runs over all pairs at once (B right-hand sides). With ``kernel`` numba
    (``fused``) one compiled call per step (``kernels.fused_step``) replaces
    the products, marginals, leak and pruning, touching occupied states only.
    """

    def __init__(self, stencils: TransitionStencils, n_s: int, kernel: NumpyKernel = "auto") -> None:
        self.stencils = stencils
        self.n_s = n_s
        cfg = stencils.config
        self.n_in, self.n_v = cfg.n_inputs, cfg.n_v_cells
        if kernel not in ("auto", "numba", "scipy"):
            raise ValueError(f"MarkovPropagator: kernel must be 'auto', 'numba' or 'scipy', got {kernel!r}")
        if kernel == "numba" and not kernels.available():
            raise ValueError(f"MarkovPropagator: kernel 'numba' asked but numba does not import ({kernels.unavailable_reason()})")
        self.fused = kernel == "numba" or (kernel == "auto" and kernels.available())
        self._tables = None
        self._occupied: tuple[np.ndarray, list[np.ndarray]] | None = None
        if self.fused:
            kernels.warm_up()  # compiled or loaded now, not on the first frame
            self._tables = (
                *kernels.stencil_tables(stencils.kernel(TransitionKind.TIME_POINT)),
                *kernels.collapsed_tables(stencils.kernel(TransitionKind.TIME_INTERVAL)),
            )
        self._matrices: dict[tuple[TransitionKind, int], sp.csr_matrix] = {}
        # Leak in the slab layout (N_s, M, N_v); non-zero only in the last D-1 cells.
        self._leak = {
            kind: np.ascontiguousarray(np.moveaxis(stencils.leak(kind, n_s), -1, 0)).astype(np.float32)
            for kind in TransitionKind
        }
        self._leak_start = max(n_s - (stencils.n_offsets - 1), 0)
        self._collapsed: dict[tuple[TransitionKind, int], sp.csr_matrix] = {}

    @property
    def tables(self) -> tuple[np.ndarray, ...] | None:
        """The numba kernels' stencil tables (``kernels.stencil_tables`` of Υ(τ), ``collapsed_tables`` of Υ([0, τ])), or None."""
        return self._tables

    def _position_matrix(self, kind: TransitionKind, n_cells: int) -> sp.csr_matrix:
        """Slab state -> s-cell of the next step, ``(n_cells, n_cells·M·N_v)`` float32: the block summed over (α, v) per
        target s-cell, so that the position marginal of one step costs D entries per state instead of the block's ~3·D."""
        key = (kind, n_cells)
        if key not in self._collapsed:
            per_offset = self.stencils.kernel(kind).sum(axis=1)  # (M, N_v source, D)
            a_idx, v_idx, d = np.nonzero(per_offset)
            s_from = np.arange(n_cells)
            s_to = s_from[None, :] + d[:, None]
            cols = s_from[None, :] * (self.n_in * self.n_v) + (a_idx * self.n_v + v_idx)[:, None]
            data = np.broadcast_to(per_offset[a_idx, v_idx, d][:, None], s_to.shape)
            inside = s_to < n_cells  # the rest leaves the window (``leak``)
            block = sp.coo_matrix(
                (data[inside], (s_to[inside], cols[inside])), shape=(n_cells, n_cells * self.n_in * self.n_v)
            ).tocsr().astype(np.float32)
            block.sum_duplicates()
            block.sort_indices()
            self._collapsed[key] = block
        return self._collapsed[key]

    def transition_position(self, kind: TransitionKind, slab: np.ndarray, lo: int, hi: int) -> tuple[np.ndarray, np.ndarray]:
        """The position marginal (B, L) of one step of ``kind`` and the leaked mass (B,), without the next state."""
        n_pairs = slab.shape[-1]
        position = (self._position_matrix(kind, hi - lo) @ slab.reshape(-1, n_pairs)).T
        return position, self._leaked(kind, slab, lo, hi)

    def _leaked(self, kind: TransitionKind, slab: np.ndarray, lo: int, hi: int) -> np.ndarray:
        n_pairs = slab.shape[-1]
        tail = max(lo, self._leak_start)
        if tail < hi:
            leak = self._leak[kind][tail:hi].reshape(-1)
            return leak @ slab[tail - lo :].reshape(-1, n_pairs)
        return np.zeros(n_pairs, np.float32)

    def _matrix(self, kind: TransitionKind, n_cells: int) -> sp.csr_matrix:
        """State-to-state block for a window of ``n_cells``, in slab order (s, α, v), float32."""
        key = (kind, n_cells)
        if key not in self._matrices:
            full = self.stencils.expand_sparse(kind, n_cells)
            n_states = self.n_in * self.n_v * n_cells
            s_idx, av_idx = np.divmod(np.arange(n_states), self.n_in * self.n_v)
            order = av_idx * n_cells + s_idx  # slab index → (α, v, s) index
            block = full[:n_states, :n_states][order][:, order].tocsr().astype(np.float32)
            block.sort_indices()
            self._matrices[key] = block
        return self._matrices[key]

    def initial_slab(self, p0: np.ndarray | SeparableState, lo: int, hi: int) -> np.ndarray:
        if isinstance(p0, SeparableState):
            return (
                p0.position_probs[:, lo:hi].T[:, None, None, :]
                * p0.input_probs.T[None, :, None, :]
                * p0.velocity_probs.T[None, None, :, :]
            )
        return np.ascontiguousarray(np.transpose(p0[..., lo:hi], (3, 1, 2, 0)), dtype=np.float32)

    def to_external(self, slab: np.ndarray, lo: int, hi: int) -> np.ndarray:
        full = np.zeros((slab.shape[-1], self.n_in, self.n_v, self.n_s), np.float32)
        full[..., lo:hi] = np.transpose(slab, (3, 1, 2, 0))
        return full

    def reslab(self, slab: np.ndarray, lo: int, hi: int, new_lo: int, new_hi: int) -> np.ndarray:
        if (lo, hi) == (new_lo, new_hi):
            return slab
        out = np.zeros((new_hi - new_lo,) + slab.shape[1:], np.float32)
        a, b = max(lo, new_lo), min(hi, new_hi)
        if b > a:
            out[a - new_lo : b - new_lo] = slab[a - lo : b - lo]
        return out

    def fused_step(
        self, slab: np.ndarray, src_lo: int, lo: int, hi: int, with_interval: bool, threshold: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None, np.ndarray]:
        """One step in one compiled call, from the slab on [src_lo, ...) to p⁻ on [lo, hi) (no ``reslab``): (p⁻ pruned,
        leaked (B,), position (B, L) and velocity (B, N_v) of p⁻ before pruning, interval position (B, L) and its leak
        (B,) or None, totals after pruning (B,))."""
        out, leaked, pos, vel, ipos, ileaked, kept, *occupied = kernels.fused_step(
            slab, src_lo, lo, hi, self.n_s, self._tables, with_interval, threshold)
        self._occupied = (out, occupied)
        return out, leaked, pos.T, vel.T, (ipos.T if with_interval else None), (ileaked if with_interval else None), kept

    def priority_occupied(self, slab: np.ndarray, s_idx: np.ndarray, v_idx: np.ndarray, b_idx: np.ndarray, lam: np.ndarray,
                          psi: np.ndarray, factors: np.ndarray) -> np.ndarray:
        """Γ = colnorm(diag(λ) Ψ) at the listed states (``kernels.priority_occupied``); every other state 0."""
        return kernels.priority_occupied(slab, s_idx, v_idx, b_idx, lam, psi, factors)

    def occupied_states(self, slab: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(s, v, b) of the slab's states holding mass, C order: from the last ``fused_step`` when ``slab`` is its
        output (not changed since), else found by a scan."""
        if self._occupied is not None and self._occupied[0] is slab:
            s_idx, v_idx, b_idx = self._occupied[1]
            return s_idx, v_idx, b_idx
        return kernels.occupied_states(slab)

    def transition(self, kind: TransitionKind, slab: np.ndarray, lo: int, hi: int) -> tuple[np.ndarray, np.ndarray]:
        n_pairs = slab.shape[-1]
        flat = slab.reshape(-1, n_pairs)
        moved = (self._matrix(kind, hi - lo) @ flat).reshape(slab.shape)
        return moved, self._leaked(kind, slab, lo, hi)

    def position(self, slab: np.ndarray) -> np.ndarray:
        # einsum measured 1.5-4x faster than .sum(axis=1) on this layout.
        return np.einsum("lcb->bl", slab.reshape(slab.shape[0], -1, slab.shape[-1]))

    def velocity(self, slab: np.ndarray) -> np.ndarray:
        return slab.sum(axis=(0, 1)).T

    def prune(self, slab: np.ndarray, threshold: float) -> None:
        np.multiply(slab, slab >= threshold, out=slab)

    def apply_input(
        self, slab: np.ndarray, transition: InputTransition | None, lo: int, hi: int, before: np.ndarray | None,
        kept: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """Γ p⁻ on the slab; with ``before`` (pre-pruning totals), rescale to them and return the kept totals
        (``kept``: those totals when the caller already has them)."""
        n_pairs = slab.shape[-1]
        if isinstance(transition, InputReplaced):
            q = _to_numpy(_validated(transition.probs, (n_pairs, self.n_in), "InputReplaced.probs rows", 1))
            summed = slab.sum(axis=1)  # (L, N_v, B)
            weights = q.T
            if before is None:
                kept = None
            else:
                kept = summed.sum(axis=(0, 1)) if kept is None else kept
                weights = weights * (before / _where_positive(kept))
            return summed[:, None] * np.ascontiguousarray(weights, dtype=np.float32)[None, :, None, :], kept
        if before is None:
            kept = None
        elif kept is None:
            kept = self.position(slab).sum(axis=1)
        factors = None if kept is None else (before / _where_positive(kept)).astype(np.float32)
        if transition is None:
            out = slab
        elif isinstance(transition, InputMatrix):
            gamma = _to_numpy(_validated(transition.gamma, (n_pairs, self.n_in, self.n_in), "InputMatrix.gamma", 1))
            # (L, M, N_v, B) → (B, M, L·N_v) so that one batched matmul applies Γ.
            by_pair = np.ascontiguousarray(np.transpose(slab, (3, 1, 0, 2))).reshape(n_pairs, self.n_in, -1)
            mixed = np.matmul(gamma, by_pair).reshape(n_pairs, self.n_in, slab.shape[0], self.n_v)
            out = np.ascontiguousarray(np.transpose(mixed, (2, 1, 3, 0)))
        elif isinstance(transition, InputPerState):
            shape = (n_pairs, self.n_in, self.n_in, self.n_v, self.n_s)
            gamma = _to_numpy(_validated(transition.gamma, shape, "InputPerState.gamma", 1))
            out = np.einsum("bxyvs,syvb->sxvb", gamma[..., lo:hi], slab, optimize=True)
        else:
            raise TypeError(f"unknown input transition {type(transition).__name__}")
        if factors is not None:
            out *= factors
        return out, kept

    def total(self, slab: np.ndarray) -> np.ndarray:
        return self.position(slab).sum(axis=1, dtype=np.float64)

    def support(self, position: np.ndarray) -> tuple[int, int] | None:
        occupied = np.flatnonzero(position.sum(axis=0) > 0)
        return None if occupied.size == 0 else (int(occupied[0]), int(occupied[-1]))

    def zeros(self, shape: tuple[int, ...]) -> np.ndarray:
        return np.zeros(shape, np.float32)

    def vector(self, values: np.ndarray) -> np.ndarray:
        return np.asarray(values, dtype=np.float32)

    def to_numpy(self, x: np.ndarray) -> np.ndarray:
        return np.asarray(x, dtype=np.float32)

    def precision_guard(self) -> contextlib.AbstractContextManager[None]:
        return contextlib.nullcontext()


class _TorchBackend:
    """Grouped conv1d along s (groups = inputs, channels = v). Slab layout (B, M·N_v, L)."""

    def __init__(self, stencils: TransitionStencils, n_s: int, device: str) -> None:
        import torch
        import torch.nn.functional as functional

        self.torch = torch
        self.functional = functional
        self.device = torch.device(device)
        self.stencils = stencils
        self.n_s = n_s
        cfg = stencils.config
        self.n_in, self.n_v = cfg.n_inputs, cfg.n_v_cells
        self.n_offsets = stencils.n_offsets
        self._weight = {
            kind: torch.as_tensor(stencils.conv_weight(kind), dtype=torch.float32, device=self.device)
            for kind in TransitionKind
        }
        self._leak = {
            kind: torch.as_tensor(
                stencils.leak(kind, n_s).reshape(self.n_in * self.n_v, n_s), dtype=torch.float32, device=self.device
            )
            for kind in TransitionKind
        }
        self._leak_start = max(n_s - (stencils.n_offsets - 1), 0)
        # the weight summed over the target v per source channel: one output channel, the position marginal
        self._position_weight = {
            kind: torch.as_tensor(
                np.ascontiguousarray(stencils.kernel(kind).sum(axis=1)[..., ::-1].reshape(1, self.n_in * self.n_v, self.n_offsets)),
                dtype=torch.float32, device=self.device,
            )
            for kind in TransitionKind
        }

    def transition_position(self, kind: TransitionKind, slab: Any, lo: int, hi: int) -> tuple[Any, Any]:
        """The position marginal (B, L) of one step of ``kind`` and the leaked mass (B,), without the next state."""
        padded = self.functional.pad(slab, (self.n_offsets - 1, 0))
        position = self.functional.conv1d(padded, self._position_weight[kind])[:, 0]
        return position, self._leaked(kind, slab, lo, hi)

    def _leaked(self, kind: TransitionKind, slab: Any, lo: int, hi: int) -> Any:
        tail = max(lo, self._leak_start)
        if tail < hi:
            return (slab[:, :, tail - lo :] * self._leak[kind][:, tail:hi]).sum(dim=(1, 2))
        return self.torch.zeros(slab.shape[0], dtype=slab.dtype, device=slab.device)

    def initial_slab(self, p0: np.ndarray | SeparableState, lo: int, hi: int) -> Any:
        if isinstance(p0, SeparableState):
            as_tensor = lambda x: self.torch.as_tensor(x, dtype=self.torch.float32, device=self.device)  # noqa: E731
            q, v, s = as_tensor(p0.input_probs), as_tensor(p0.velocity_probs), as_tensor(p0.position_probs[:, lo:hi])
            joint = q[:, :, None, None] * v[:, None, :, None] * s[:, None, None, :]
            return joint.reshape(joint.shape[0], self.n_in * self.n_v, hi - lo)
        t = self.torch.as_tensor(np.ascontiguousarray(p0[..., lo:hi], dtype=np.float32), device=self.device)
        return t.reshape(t.shape[0], self.n_in * self.n_v, hi - lo)

    def to_external(self, slab: Any, lo: int, hi: int) -> np.ndarray:
        full = np.zeros((slab.shape[0], self.n_in * self.n_v, self.n_s), np.float32)
        full[..., lo:hi] = slab.cpu().numpy()
        return full.reshape(slab.shape[0], self.n_in, self.n_v, self.n_s)

    def reslab(self, slab: Any, lo: int, hi: int, new_lo: int, new_hi: int) -> Any:
        if (lo, hi) == (new_lo, new_hi):
            return slab
        out = self.torch.zeros(slab.shape[:2] + (new_hi - new_lo,), dtype=slab.dtype, device=slab.device)
        a, b = max(lo, new_lo), min(hi, new_hi)
        if b > a:
            out[:, :, a - new_lo : b - new_lo] = slab[:, :, a - lo : b - lo]
        return out

    def transition(self, kind: TransitionKind, slab: Any, lo: int, hi: int) -> tuple[Any, Any]:
        padded = self.functional.pad(slab, (self.n_offsets - 1, 0))
        moved = self.functional.conv1d(padded, self._weight[kind], groups=self.n_in)
        return moved, self._leaked(kind, slab, lo, hi)

    def position(self, slab: Any) -> Any:
        return slab.sum(dim=1)

    def velocity(self, slab: Any) -> Any:
        return slab.reshape(slab.shape[0], self.n_in, self.n_v, -1).sum(dim=(1, 3))

    def prune(self, slab: Any, threshold: float) -> None:
        slab.masked_fill_(slab < threshold, 0.0)

    def _tensor(self, x: Any, shape: tuple[int, ...], what: str) -> Any:
        return self.torch.as_tensor(_validated(x, shape, what, 1), dtype=self.torch.float32, device=self.device)

    def apply_input(
        self, slab: Any, transition: InputTransition | None, lo: int, hi: int, before: Any
    ) -> tuple[Any, Any]:
        """Γ p⁻ on the slab; with ``before`` (pre-pruning totals), rescale to them and return the kept totals."""
        n_pairs, length = slab.shape[0], slab.shape[2]
        joint = slab.reshape(n_pairs, self.n_in, self.n_v, length)
        kept = None if before is None else slab.sum(dim=(1, 2))
        factors = None if kept is None else before / _where_positive(kept)
        if transition is None:
            out = joint
        elif isinstance(transition, InputReplaced):
            q = self._tensor(transition.probs, (n_pairs, self.n_in), "InputReplaced.probs rows")
            if factors is not None:
                q = q * factors[:, None]
                factors = None
            out = joint.sum(dim=1, keepdim=True) * q[:, :, None, None]
        elif isinstance(transition, InputMatrix):
            gamma = self._tensor(transition.gamma, (n_pairs, self.n_in, self.n_in), "InputMatrix.gamma")
            if factors is not None:
                gamma = gamma * factors[:, None, None]
                factors = None
            out = self.torch.bmm(gamma, joint.reshape(n_pairs, self.n_in, self.n_v * length))
        elif isinstance(transition, InputPerState):
            shape = (n_pairs, self.n_in, self.n_in, self.n_v, self.n_s)
            gamma = self._tensor(transition.gamma, shape, "InputPerState.gamma")
            out = self.torch.einsum("bxyvs,byvs->bxvs", gamma[..., lo:hi], joint)
        else:
            raise TypeError(f"unknown input transition {type(transition).__name__}")
        if factors is not None:
            out = out * factors[:, None, None, None]
        return out.reshape(n_pairs, self.n_in * self.n_v, length).contiguous(), kept

    def total(self, slab: Any) -> np.ndarray:
        return slab.sum(dim=(1, 2), dtype=self.torch.float64).cpu().numpy()

    def support(self, position: Any) -> tuple[int, int] | None:
        occupied = self.torch.nonzero(position.sum(dim=0) > 0).flatten()
        if occupied.numel() == 0:
            return None
        bounds = self.torch.stack([occupied[0], occupied[-1]]).tolist()
        return int(bounds[0]), int(bounds[1])

    def zeros(self, shape: tuple[int, ...]) -> Any:
        return self.torch.zeros(shape, dtype=self.torch.float32, device=self.device)

    def vector(self, values: np.ndarray) -> Any:
        return self.torch.as_tensor(np.asarray(values, dtype=np.float32), device=self.device)

    def to_numpy(self, x: Any) -> np.ndarray:
        return x.detach().to("cpu", self.torch.float32).numpy()

    @contextlib.contextmanager
    def precision_guard(self) -> Iterator[None]:
        """Force IEEE float32 in cuDNN convolutions and CUDA matmuls for the duration of a run.

        cuDNN defaults to TF32 for float32 convolutions on Ampere and later,
        whose 10-bit mantissa breaks mass conservation at 1e-5. The previous
        settings are restored afterwards.
        """
        if self.device.type != "cuda":
            yield
            return
        settings = []
        holders = (getattr(self.torch.backends.cudnn, "conv", None), getattr(self.torch.backends.cuda, "matmul", None))
        for holder in holders:
            if holder is not None and hasattr(holder, "fp32_precision"):
                settings.append((holder, holder.fp32_precision))
                holder.fp32_precision = "ieee"
        try:
            yield
        finally:
            for holder, previous in settings:
                holder.fp32_precision = previous


def mass_error(final_total: np.ndarray, outside: np.ndarray, lost: np.ndarray | None) -> np.ndarray:
    """(B,) float32 |Σ final state + outside (+ pruned mass lost) − 1| of a run; a warning when one is above
    ``MASS_TOLERANCE``."""
    error = np.abs(np.asarray(final_total, dtype=np.float64) + np.asarray(outside, dtype=np.float64)
                   + (0.0 if lost is None else lost) - 1.0)
    if error.size and error.max() > MASS_TOLERANCE:
        worst = int(np.argmax(error))
        logger.warning("markov mass not conserved: pair=%d error=%.3g", worst, error[worst])
    return error.astype(np.float32)


def _validated(x: Any, shape: tuple[int, ...], what: str, sum_axis: int) -> Any:
    """``x`` as float32 in its own library (numpy or torch), checked: shape, finite, >= 0, sums to 1 along ``sum_axis``.

    A torch tensor is checked where it lives, with a single device sync.
    """
    if hasattr(x, "detach"):
        arr = x.detach().float()
        if tuple(arr.shape) != shape:
            raise ValueError(f"{what}: expected shape {shape}, got {tuple(arr.shape)}")
        if arr.numel() == 0:
            return arr
        import torch

        bad = (~arr.isfinite() | (arr < 0)).any().float()
        worst = (arr.sum(dim=sum_axis) - 1.0).abs().max()
        n_bad, deviation = torch.stack([bad, worst]).tolist()
    else:
        arr = np.asarray(x, dtype=np.float32)
        if arr.shape != shape:
            raise ValueError(f"{what}: expected shape {shape}, got {arr.shape}")
        if arr.size == 0:
            return arr
        n_bad = float(not np.all(np.isfinite(arr)) or np.any(arr < 0))
        deviation = float(np.max(np.abs(arr.sum(axis=sum_axis) - 1.0)))
    if n_bad:
        raise ValueError(f"{what}: entries must be finite and non-negative")
    if deviation > _STOCHASTIC_TOLERANCE:
        raise ValueError(f"{what} must sum to 1 (worst deviation {deviation:.3g})")
    return arr


def _to_numpy(x: Any) -> np.ndarray:
    """A numpy float32 view or copy of a numpy array or torch tensor."""
    if hasattr(x, "detach"):
        return x.detach().cpu().numpy()
    return np.asarray(x, dtype=np.float32)


def _where_positive(x: Any) -> Any:
    """``x`` with non-positive entries replaced by 1 (a safe divisor for the renormalisation)."""
    if hasattr(x, "new_ones"):
        return x.where(x > 0, x.new_ones(()))
    return np.where(x > 0, x, 1.0).astype(np.float32)


# ---------------------------------------------------------------------------
# The propagator
# ---------------------------------------------------------------------------


Inputs = Union[
    Sequence[Union[InputTransition, None]],
    Callable[[int, StepMarginals], Union[InputTransition, None]],
    None,
]


class MarkovPropagator:
    """Propagates B vehicle-corridor pairs K steps through Υ(τ), Υ([0, τ]) and Γ.

    ``backend`` is ``"numpy"`` (scipy CSR) or ``"torch"`` (conv1d on
    ``device`` ``"cpu"`` or ``"cuda"``). ``n_s_cells`` overrides the window
    length of the stencils' config. Entries of p⁻ below ``prune_threshold``
    are zeroed each step; with ``renormalise_pruned`` (the default) their
    mass is put back onto the kept entries of the same pair, otherwise it is
    lost (CORA's behaviour); either way it is reported. ``crop`` limits each
    step to the active s-window, rounded up to ``crop_quantum_cells`` (the
    same results, less work). ``kernel`` picks the numpy backend's step
    (``NumpyKernel``; default numba where it imports, the scipy products
    otherwise: the same results within float32 rounding).
    """

    def __init__(
        self,
        stencils: TransitionStencils,
        *,
        backend: Backend = "numpy",
        device: str = "cpu",
        n_s_cells: int | None = None,
        prune_threshold: float = 1e-7,
        renormalise_pruned: bool = True,
        crop: bool = True,
        crop_quantum_cells: int = 8,
        kernel: NumpyKernel = "auto",
    ) -> None:
        self.stencils = stencils
        self.config = stencils.config
        self.n_s = self.config.n_s_cells if n_s_cells is None else int(n_s_cells)
        if self.n_s < 1:
            raise ValueError(f"MarkovPropagator: n_s_cells must be >= 1, got {self.n_s}")
        if not prune_threshold >= 0:
            raise ValueError(f"MarkovPropagator: prune_threshold must be >= 0, got {prune_threshold}")
        if crop_quantum_cells < 1:
            raise ValueError(f"MarkovPropagator: crop_quantum_cells must be >= 1, got {crop_quantum_cells}")
        self.prune_threshold = float(prune_threshold)
        self.renormalise_pruned = bool(renormalise_pruned)
        self.crop = bool(crop)
        self.crop_quantum_cells = int(crop_quantum_cells)
        if backend == "numpy":
            if device != "cpu":
                raise ValueError(f"MarkovPropagator: the numpy backend runs on cpu only, got device={device!r}")
            self._backend: Any = _NumpyBackend(stencils, self.n_s, kernel)
        elif backend == "torch":
            if kernel == "numba":
                raise ValueError("MarkovPropagator: kernel 'numba' is the numpy backend's; the torch backend has its own")
            self._backend = _TorchBackend(stencils, self.n_s, device)
        else:
            raise ValueError(f"MarkovPropagator: backend must be 'numpy' or 'torch', got {backend!r}")
        self.backend = backend
        self.device = device

    @property
    def state_shape(self) -> tuple[int, int, int]:
        """(M, N_v, N_s): the shape of one pair's joint distribution."""
        return (self.config.n_inputs, self.config.n_v_cells, self.n_s)

    def _window(self, support: tuple[int, int] | None) -> tuple[int, int]:
        """The s-cells [lo, hi) one step must touch, given the occupied cells [first, last]."""
        if not self.crop:
            return 0, self.n_s
        if support is None:
            return 0, min(self.crop_quantum_cells, self.n_s)
        first, last = support
        length = last + self.stencils.n_offsets - first
        length = min(-(-length // self.crop_quantum_cells) * self.crop_quantum_cells, self.n_s)
        hi = min(first + length, self.n_s)
        return hi - length, hi

    def _check_start(
        self, p0: Any, initial_outside: np.ndarray | None
    ) -> tuple[Any, np.ndarray, tuple[int, int] | None]:
        """Validate p(t_0); return it (numpy or SeparableState), the outside mass and the occupied s-cells."""
        n_s, n_v, n_in = self.n_s, self.config.n_v_cells, self.config.n_inputs
        if isinstance(p0, SeparableState):
            n_pairs = p0.input_probs.shape[0]
            shapes = (p0.input_probs.shape, p0.velocity_probs.shape, p0.position_probs.shape)
            if shapes != ((n_pairs, n_in), (n_pairs, n_v), (n_pairs, n_s)):
                raise ValueError(f"run: SeparableState shapes {shapes} do not fit (B, {n_in}), (B, {n_v}), (B, {n_s})")
            parts = (p0.input_probs, p0.velocity_probs, p0.position_probs)
            if any(not np.all(np.isfinite(x)) or np.any(x < 0) for x in parts):
                raise ValueError("run: p0 must be finite and non-negative")
            sums = np.prod([x.sum(axis=1, dtype=np.float64) for x in parts], axis=0)
            occupied_s = p0.position_probs.sum(axis=0)
        else:
            p0 = p0.detach().cpu().numpy() if hasattr(p0, "detach") else np.asarray(p0)
            if p0.ndim != 4 or p0.shape[1:] != self.state_shape:
                raise ValueError(f"run: p0 must be (B, {n_in}, {n_v}, {n_s}), got {p0.shape}")
            if not np.all(np.isfinite(p0)) or np.any(p0 < 0):
                raise ValueError("run: p0 must be finite and non-negative")
            n_pairs = p0.shape[0]
            sums = p0.sum(axis=(1, 2, 3), dtype=np.float64)
            occupied_s = p0.sum(axis=(0, 1, 2))
        outside0 = np.zeros(n_pairs) if initial_outside is None else np.asarray(initial_outside, dtype=np.float64)
        if outside0.shape != (n_pairs,):
            raise ValueError(f"run: initial_outside must be ({n_pairs},), got {outside0.shape}")
        start_error = np.abs(sums + outside0 - 1.0)
        if n_pairs and start_error.max() > MASS_TOLERANCE:
            raise ValueError(f"run: p0 + initial_outside must sum to 1 per pair (worst {start_error.max():.3g})")
        occupied = np.flatnonzero(occupied_s > 0)
        support = (int(occupied[0]), int(occupied[-1])) if occupied.size else None
        return p0, outside0, support

    def run(
        self,
        p0: np.ndarray | SeparableState,
        inputs: Inputs = None,
        *,
        n_steps: int | None = None,
        with_interval: bool = False,
        with_final_state: bool = False,
        initial_outside: np.ndarray | None = None,
    ) -> PropagationResult:
        """Propagate p(t_0) for ``n_steps`` steps (default ``config.n_steps``).

        ``p0`` is a dense ``(B, M, N_v, N_s)`` array (layout p[b, α, v, s]) or
        the ``SeparableState`` of ``initial_state``. ``inputs`` gives the input
        transition applied at the end of each step k (producing p(t_{k+1})):
        None (Γ = identity at every step), a sequence of ``n_steps`` entries
        (None = identity), or a callable ``(k, StepMarginals) ->
        InputTransition | None`` for a Γ that depends on this step's marginals
        (e.g. a leader's occupancy). ``with_interval`` also computes
        Υ([0, τ]) p(t_k); ``with_final_state`` returns the dense p(t_K).
        ``initial_outside`` is the (B,) mass already outside (default 0);
        p(t_0) plus it must sum to 1 per pair.
        """
        be = self._backend
        k_steps = self.config.n_steps if n_steps is None else int(n_steps)
        if k_steps < 0:
            raise ValueError(f"run: n_steps must be >= 0, got {k_steps}")
        if isinstance(inputs, Sequence) and len(inputs) != k_steps:
            raise ValueError(f"run: {len(inputs)} input transitions for {k_steps} steps")
        p0, outside0, support = self._check_start(p0, initial_outside)
        n_pairs = outside0.shape[0]
        with be.precision_guard():
            return self._run(p0, outside0, support, n_pairs, inputs, k_steps, with_interval, with_final_state)

    def _run(
        self,
        p0: Any,
        outside0: np.ndarray,
        support: tuple[int, int] | None,
        n_pairs: int,
        inputs: Inputs,
        k_steps: int,
        with_interval: bool,
        with_final_state: bool,
    ) -> PropagationResult:
        be = self._backend
        positions = be.zeros((n_pairs, k_steps, self.n_s))
        velocities = be.zeros((n_pairs, k_steps, self.config.n_v_cells))
        interval_positions = be.zeros((n_pairs, k_steps, self.n_s)) if with_interval else None
        outsides = be.zeros((n_pairs, k_steps))
        interval_outsides = be.zeros((n_pairs, k_steps)) if with_interval else None
        pruned = be.zeros((n_pairs, k_steps))

        fused = bool(getattr(be, "fused", False))
        lo, hi = self._window(support)
        slab = be.initial_slab(p0, lo, hi)
        outside = be.vector(outside0)
        for k in range(k_steps):
            new_lo, new_hi = self._window(support)
            src_lo = lo
            if not fused:  # the fused step reads the slab where it is
                slab = be.reslab(slab, lo, hi, new_lo, new_hi)
            lo, hi = new_lo, new_hi
            kept_fused = None
            if fused:  # one compiled pass: p⁻ (pruned), leaks, marginals, interval position
                p_minus, leaked, position, velocity, interval_position, leaked_interval, kept_fused = be.fused_step(
                    slab, src_lo, lo, hi, with_interval, self.prune_threshold)
                if with_interval:
                    interval_positions[:, k, lo:hi] = interval_position
                    interval_outsides[:, k] = outside + leaked_interval
            else:
                p_minus, leaked = be.transition(TransitionKind.TIME_POINT, slab, lo, hi)
                if with_interval:  # only its position marginal is returned: never the interval state itself
                    interval_position, leaked_interval = be.transition_position(TransitionKind.TIME_INTERVAL, slab, lo, hi)
                    interval_positions[:, k, lo:hi] = interval_position
                    interval_outsides[:, k] = outside + leaked_interval
                position = be.position(p_minus)
                velocity = be.velocity(p_minus)
            outside = outside + leaked
            outsides[:, k] = outside
            positions[:, k, lo:hi] = position
            velocities[:, k] = velocity
            if self.crop:
                support = be.support(position)
                if support is not None:
                    support = (support[0] + lo, support[1] + lo)
            before = None
            if self.prune_threshold > 0:
                before = position.sum(1)
                if not fused:
                    be.prune(p_minus, self.prune_threshold)
            if callable(inputs):
                marginals = StepMarginals(
                    position=positions[:, k],
                    velocity=velocities[:, k],
                    interval_position=None if interval_positions is None else interval_positions[:, k],
                    outside=outsides[:, k],
                )
                transition = inputs(k, marginals)
            else:
                transition = None if inputs is None else inputs[k]
            if kept_fused is not None and before is not None and self.renormalise_pruned:
                slab, kept = be.apply_input(p_minus, transition, lo, hi, before, kept=kept_fused)
            else:
                slab, kept = be.apply_input(p_minus, transition, lo, hi, before if self.renormalise_pruned else None)
                if kept is None and kept_fused is not None and before is not None:
                    kept = kept_fused
            if before is not None:
                if kept is None:
                    kept = be.position(p_minus).sum(1)
                dropped = before - kept
                pruned[:, k] = dropped.clip(0.0) if hasattr(dropped, "clip") else dropped

        lost = None if self.renormalise_pruned else be.to_numpy(pruned).astype(np.float64).sum(axis=1)
        errors = mass_error(be.total(slab), be.to_numpy(outside), lost)
        return PropagationResult(
            position_probs=be.to_numpy(positions),
            velocity_probs=be.to_numpy(velocities),
            interval_position_probs=None if interval_positions is None else be.to_numpy(interval_positions),
            outside_mass=be.to_numpy(outsides),
            interval_outside_mass=None if interval_outsides is None else be.to_numpy(interval_outsides),
            pruned_mass=be.to_numpy(pruned),
            final_state=be.to_external(slab, lo, hi) if with_final_state else None,
            mass_error=errors,
        )
