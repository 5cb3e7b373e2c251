"""A per-state input transition Γ_i = colnorm(diag(λ_i) Ψ) given by λ alone (docs/method.md §4.1).

``stages.lib.markov``'s ``InputPerState`` takes the full Γ, ``(B, M, M, N_v, N_s)``:
1.6 MB per pair and step at the default grid. The baseline only ever needs
Γ of that form, whose product with p⁻ is cheap without building it::

    Z[b] = Σ_a λ[a] Ψ[a, b]             (per state, b = previous input)
    p(t_{k+1})[a] = λ[a] · Σ_b Ψ[a, b] p⁻[b] / Z[b]

``InputPriority`` carries λ as a function of the s-window the step works on
(so λ is only built on the active window), and ``PriorityPropagator`` is a
``MarkovPropagator`` whose backend applies it; every other input transition
goes to the backend unchanged. The wrapper relies on the backends' slab
layouts (numpy ``(L, M, N_v, B)``, torch ``(B, M·N_v, L)``), which
``stages/lib/markov/propagate.py`` documents; moving ``InputPriority`` into
``stages.lib.markov`` would remove that coupling.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from stages.lib.markov import MarkovPropagator, PropagationResult, SeparableState, TransitionStencils, kernels
from stages.lib.markov.propagate import mass_error


@dataclass(frozen=True, kw_only=True, eq=False)
class InputPriority:
    """Γ_i = colnorm(diag(λ_i) Ψ) at every state of every pair for one step.

    ``weights(lo, hi)`` returns λ for the s-cells [lo, hi) of the window,
    ``(B, M, N_v, hi − lo)`` float32, non-negative, with no all-zero column
    (``priority.combine_with_preference`` guarantees it).
    """

    weights: Callable[[int, int], np.ndarray]
    #: Optional: λ at given states only, ``at_states(b, v, s) -> (n, M) float32`` for n states (pair, v-cell,
    #: s-cell of the window). When given, the numpy backend applies Γ only where p⁻ holds mass (a pair's
    #: occupied states are a few percent of the batch's active window) instead of on the whole window.
    at_states: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray] | None = None
    #: Optional: λ as ``restriction`` (a ``kernels.SpeedRestriction``, or its ``full()`` array (B, M, N_v, N_s)) gives
    #: it for the preference ``preference`` (B, M) float32 and ``forbid_threshold`` (what ``at_states`` computes then).
    #: When every step of a run is such an input with a ``SpeedRestriction`` (or None), ``PriorityPropagator`` runs the
    #: whole chain in one compiled call (``kernels.speed_priority_run``); the torch backend builds λ on its device from
    #: either form (moved there once per run) instead of calling ``weights`` every step.
    restriction: Any = None
    preference: np.ndarray | None = None
    forbid_threshold: float = 0.0


class _PriorityBackend:
    """Wraps a ``stages.lib.markov`` backend: applies ``InputPriority``, delegates everything else."""

    def __init__(self, inner: Any, psi: np.ndarray, kind: str) -> None:
        self._inner = inner
        self._kind = kind
        self._psi = np.asarray(psi, dtype=np.float32)
        self._restriction: Any = None
        self._restriction_t: Any = None
        if kind == "torch":
            torch = inner.torch
            self._psi_t = torch.as_tensor(self._psi, device=inner.device)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._inner, name)

    def apply_input(self, slab: Any, transition: Any, lo: int, hi: int, before: Any, kept: Any = None) -> tuple[Any, Any]:
        if not isinstance(transition, InputPriority):
            if kept is not None:
                return self._inner.apply_input(slab, transition, lo, hi, before, kept=kept)
            return self._inner.apply_input(slab, transition, lo, hi, before)
        if self._kind == "numpy" and transition.at_states is not None:
            if getattr(self._inner, "fused", False):
                return self._numba_occupied(slab, transition, lo, before, kept)
            return self._numpy_occupied(slab, transition, lo, before)
        if self._kind == "torch" and transition.restriction is not None and transition.preference is not None:
            return self._torch(slab, self._torch_priority(transition, lo, hi), before)
        lam = np.asarray(transition.weights(lo, hi), dtype=np.float32)
        if self._kind == "numpy":
            return self._numpy(slab, lam, before)
        return self._torch(slab, self._inner.torch.as_tensor(lam, device=slab.device), before)

    def _torch_priority(self, transition: InputPriority, lo: int, hi: int) -> Any:
        """λ on the window [lo, hi) on the torch device: λ_speed of every state moved there once per restriction (one
        copy per run, not one per step) and combined with the step's preference there, the numbers of
        ``priority.combine_with_preference`` (the same float32 min and subtraction, from the highest input down)."""
        torch = self._inner.torch
        device = self._inner.device
        if self._restriction is not transition.restriction:
            r = transition.restriction
            dense = r.full() if isinstance(r, kernels.SpeedRestriction) else np.asarray(r, dtype=np.float32)
            self._restriction_t = torch.as_tensor(dense, device=device)  # (B, M, N_v, N_s)
            self._restriction = transition.restriction  # held: an id is not reused while the tensor is kept
        m = self._restriction_t[..., lo:hi]
        pref = torch.as_tensor(np.asarray(transition.preference, dtype=np.float32), device=device)  # (B, M)
        out = torch.empty_like(m)
        carry = torch.zeros_like(m[:, 0])
        for alpha in range(m.shape[1] - 1, -1, -1):
            want = carry + pref[:, alpha, None, None]
            torch.minimum(m[:, alpha], want, out=out[:, alpha])
            carry = want - out[:, alpha]
        dead = m.amax(dim=1) <= transition.forbid_threshold  # (B, N_v, L): everything forbidden -> strongest braking
        out = out.masked_fill(dead[:, None], 0.0)
        out[:, 0].masked_fill_(dead, 1.0)
        return out

    def _numba_occupied(self, slab: np.ndarray, transition: InputPriority, lo: int, before: np.ndarray | None,
                        kept: np.ndarray | None) -> tuple[np.ndarray, np.ndarray | None]:
        """``_numpy_occupied`` with the compiled kernels (``stages.lib.markov.kernels``): no BLAS, no temporaries."""
        s_idx, v_idx, b_idx = self._inner.occupied_states(slab)
        lam = np.asarray(transition.at_states(b_idx, v_idx, s_idx + lo), dtype=np.float32)
        if before is None:
            kept, factors = None, np.ones(slab.shape[-1], np.float32)
        else:
            if kept is None:
                kept = self._inner.position(slab).sum(axis=1)
            factors = (before / np.where(kept > 0, kept, 1.0)).astype(np.float32)
        return self._inner.priority_occupied(slab, s_idx, v_idx, b_idx, lam, self._psi, factors), kept

    def _numpy_occupied(self, slab: np.ndarray, transition: InputPriority, lo: int, before: np.ndarray | None) -> tuple[np.ndarray, np.ndarray | None]:
        """``_numpy`` on the states (s, v, pair) that hold mass only: the same products, gathered and scattered back."""
        s_idx, v_idx, b_idx = np.nonzero(slab.any(axis=1))  # slab (L, M, N_v, B)
        x = slab[s_idx, :, v_idx, b_idx]  # (n, M)
        lam = np.asarray(transition.at_states(b_idx, v_idx, s_idx + lo), dtype=np.float32)
        norm = lam @ self._psi  # Z[n, b] = Σ_a λ[n, a] Ψ[a, b]
        ratio = np.divide(x, norm, out=np.zeros_like(x), where=norm > 0)
        out = np.zeros_like(slab)
        out[s_idx, :, v_idx, b_idx] = lam * (ratio @ self._psi.T)
        kept = None
        if before is not None:
            kept = self._inner.position(slab).sum(axis=1)
            factors = (before / np.where(kept > 0, kept, 1.0)).astype(np.float32)
            out *= factors
        return out, kept

    def _numpy(self, slab: np.ndarray, lam: np.ndarray, before: np.ndarray | None) -> tuple[np.ndarray, np.ndarray | None]:
        # slab (L, M, N_v, B); λ (B, M, N_v, L) -> slab layout
        lam_s = np.ascontiguousarray(np.transpose(lam, (3, 1, 2, 0)))
        shape = lam_s.shape
        flat = (shape[0], shape[1], shape[2] * shape[3])
        norm = np.matmul(self._psi.T, lam_s.reshape(flat)).reshape(shape)  # Z[b] = Σ_a λ[a] Ψ[a, b]
        ratio = np.divide(slab, norm, out=np.zeros_like(slab), where=norm > 0)
        out = lam_s * np.matmul(self._psi, ratio.reshape(flat)).reshape(shape)
        kept = None
        if before is not None:
            kept = self._inner.position(slab).sum(axis=1)
            factors = (before / np.where(kept > 0, kept, 1.0)).astype(np.float32)
            out *= factors
        return out.astype(np.float32, copy=False), kept

    def _torch(self, slab: Any, lam_t: Any, before: Any) -> tuple[Any, Any]:
        torch = self._inner.torch
        n_pairs, length = slab.shape[0], slab.shape[2]
        n_in, n_v = self._inner.n_in, self._inner.n_v
        joint = slab.reshape(n_pairs, n_in, n_v, length)
        norm = torch.einsum("ab,xavl->xbvl", self._psi_t, lam_t)
        ratio = torch.where(norm > 0, joint / torch.where(norm > 0, norm, torch.ones_like(norm)), torch.zeros_like(joint))
        out = lam_t * torch.einsum("ab,xbvl->xavl", self._psi_t, ratio)
        kept = None
        if before is not None:
            kept = slab.sum(dim=(1, 2))
            factors = before / torch.where(kept > 0, kept, torch.ones_like(kept))
            out = out * factors[:, None, None, None]
        return out.reshape(n_pairs, n_in * n_v, length).contiguous(), kept


class PriorityPropagator(MarkovPropagator):
    """``MarkovPropagator`` that also accepts ``InputPriority`` input transitions (Ψ given here).

    A run whose every step is None or an ``InputPriority`` with a ``restriction`` (the hybrid mode's speed
    restriction), from a ``SeparableState``, on the numpy backend's numba kernels, with the pruned mass put back and
    no final state asked for, is one compiled call (``kernels.speed_priority_run``: blocks of similar pairs, each on the
    cells its pairs occupy); it gives the numbers of the step-by-step run (see there). ``kernel_threads`` (>= 1) threads
    run that call's blocks (1: all on the calling thread); the numbers do not depend on it.

    ``chain_device`` ("cuda", "cuda:N"; numpy backend only): that one call runs as one CUDA kernel launch on the GPU
    (``stages.lib.markov.cuda_chain``: the same numbers to float32 rounding); ValueError here where numba.cuda finds
    no GPU. Every other run stays on the CPU. A GPU run that raises is done again by the CPU kernel, and so is every
    run after it (``gpu_failures`` says why).
    """

    def __init__(self, stencils: TransitionStencils, psi: np.ndarray, *, kernel_threads: int = 1, chain_device: str | None = None,
                 **kwargs: Any) -> None:
        if isinstance(kernel_threads, bool) or not isinstance(kernel_threads, (int, np.integer)) or kernel_threads < 1:
            raise ValueError(f"kernel_threads = {kernel_threads!r}: expected an integer >= 1")
        super().__init__(stencils, **kwargs)
        self.kernel_threads = int(kernel_threads)
        self.chain_device = chain_device
        #: why the GPU run failed, once (then ``chain_device`` is None: the CPU kernel takes every run after it, with
        #: the same numbers to float32 rounding); the caller reports and clears it
        self.gpu_failures: list[str] = []
        #: a dict to have each GPU run write where its time went into it (``cuda_chain.speed_priority_run``'s
        #: ``timings``; bench/markov_kernel.py), or None
        self.gpu_timings: dict | None = None
        if chain_device is not None:
            from stages.lib.markov import cuda_chain

            cuda_chain.device_index(chain_device)
            if self.backend != "numpy" or not getattr(self._backend, "fused", False):
                raise ValueError(f"chain_device = {chain_device!r}: needs the numpy backend with its numba kernels")
            reason = cuda_chain.unavailable_reason()
            if reason is not None:
                raise ValueError(f"backend = 'cuda' (device {chain_device!r}): {reason}; use backend = 'numpy' on this machine")
            cuda_chain.warm_up(chain_device)
        self._psi = np.asarray(psi, dtype=np.float32)
        self._backend = _PriorityBackend(self._backend, psi, self.backend)

    def _one_call(self, p0: Any, inputs: Any, k_steps: int, with_final_state: bool) -> bool:
        """Whether ``run`` can take the compiled whole-run path."""
        if not (getattr(self._backend, "fused", False) and isinstance(p0, SeparableState) and not with_final_state
                and self.prune_threshold > 0 and self.renormalise_pruned and isinstance(inputs, Sequence) and len(inputs) == k_steps):
            return False
        given = [t for t in inputs if t is not None]
        return bool(given) and all(isinstance(t, InputPriority) and t.restriction is given[0].restriction
                                   and t.preference is not None and t.forbid_threshold == given[0].forbid_threshold for t in given) \
            and isinstance(given[0].restriction, kernels.SpeedRestriction)

    @staticmethod
    def _on_gpu(p0: SeparableState, restriction: Any) -> bool:
        """Whether the CUDA kernel's fixed-size arrays hold this run (else the CPU kernel takes it: the same numbers)."""
        from stages.lib.markov import cuda_chain

        return cuda_chain.supports(p0.position_probs.shape[1], p0.velocity_probs.shape[1], p0.input_probs.shape[1],
                                   restriction._args[1].shape[0])

    def run(self, p0: Any, inputs: Any = None, *, n_steps: int | None = None, with_interval: bool = False,
            with_final_state: bool = False, initial_outside: np.ndarray | None = None, skip: np.ndarray | None = None) -> PropagationResult:
        """``MarkovPropagator.run``; ``skip`` (B,) bool: pairs whose results the caller will not read (a standing vehicle
        that surely stays): the compiled one-call path leaves them out and gives them zeros (no mass anywhere), the
        other paths run them as every pair."""
        k_steps = self.config.n_steps if n_steps is None else int(n_steps)
        if not self._one_call(p0, inputs, k_steps, with_final_state):
            return super().run(p0, inputs, n_steps=n_steps, with_interval=with_interval, with_final_state=with_final_state,
                               initial_outside=initial_outside)
        p0, outside0, _support = self._check_start(p0, initial_outside)
        given = [t for t in inputs if t is not None]
        n_pairs, n_in = p0.input_probs.shape
        preferences = np.zeros((k_steps, n_pairs, n_in), np.float32)
        for k, t in enumerate(inputs):
            if t is not None:
                q = np.asarray(t.preference, dtype=np.float32)
                if q.shape != (n_pairs, n_in) or not np.all(np.isfinite(q)) or np.any(q < 0):
                    raise ValueError(f"InputPriority.preference: ({n_pairs}, {n_in}) finite and non-negative expected, got {q.shape}")
                preferences[k] = q
        args = ((p0.input_probs, p0.velocity_probs, p0.position_probs), outside0, self._backend.tables, k_steps, with_interval,
                self.prune_threshold, self._psi, given[0].restriction, preferences, [t is not None for t in inputs],
                given[0].forbid_threshold)
        out = None
        if self.chain_device is not None and self._on_gpu(p0, given[0].restriction):
            from stages.lib.markov import cuda_chain

            try:
                out = cuda_chain.speed_priority_run(*args, device=self.chain_device, timings=self.gpu_timings)
            except Exception as exc:  # noqa: BLE001 - a GPU failing mid-run (driver, memory) must not cost the frame
                self.gpu_failures.append(f"{self.chain_device}: {type(exc).__name__}: {exc}: the chain runs on the CPU from now on")
                self.chain_device = None
        left = None  # the pairs the CPU kernel left out (the GPU runs every pair)
        if out is None:
            left = None if skip is None else np.asarray(skip, dtype=np.bool_)
            out = kernels.speed_priority_run(*args, threads=self.kernel_threads, skip=left)
        pos, vel, ipos, outside, ioutside, pruned, totals = out
        last = outside[:, -1] if k_steps else outside0
        if left is not None:
            totals[left] = 1.0 - last[left]  # (not run: no mass to account for)
        return PropagationResult(
            position_probs=pos, velocity_probs=vel, interval_position_probs=ipos, outside_mass=outside,
            interval_outside_mass=ioutside, pruned_mass=pruned, final_state=None, mass_error=mass_error(totals, last, None),
        )
