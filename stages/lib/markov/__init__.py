"""Markov-chain motion prediction along a corridor (docs/method.md §3).

- ``grid``: the discretisation (``MarkovGridConfig``) and its cell helpers.
- ``transitions``: the offline stencils Υ(τ) and Υ([0, τ]) by sampled
  push-forward, their sparse and convolution forms, and the disk cache.
- ``propagate``: the batched online recursion over vehicle-corridor pairs,
  with the numpy/scipy and torch backends, Ψ and Γ helpers.
- ``kernels``: the numpy backend's compiled (numba) step over the occupied
  states and the input transition at occupied states.

Pure numpy/scipy/numba/torch: no bus, no wall clock.
"""

from stages.lib.markov.grid import MarkovGridConfig
from stages.lib.markov.propagate import (
    InputMatrix,
    InputPerState,
    InputReplaced,
    MarkovPropagator,
    PropagationResult,
    SeparableState,
    StepMarginals,
    gamma_from_priority,
    initial_state,
    psi_matrix,
)
from stages.lib.markov.transitions import TransitionKind, TransitionStencils, build_stencils, load_or_build_stencils

__all__ = [
    "InputMatrix",
    "InputPerState",
    "InputReplaced",
    "MarkovGridConfig",
    "MarkovPropagator",
    "PropagationResult",
    "SeparableState",
    "StepMarginals",
    "TransitionKind",
    "TransitionStencils",
    "build_stencils",
    "gamma_from_priority",
    "initial_state",
    "load_or_build_stencils",
    "psi_matrix",
]
