"""AR acceleration profiles (``iamp.AccelerationProfiles``): the ar_inference stage's output (docs/method.md §8).

For every vehicle-corridor pair of a frame, the AR-Net's predicted
longitudinal acceleration at 0.1 … 4.0 s, and its conversion into one normal
distribution per Markov step (0.4 s chunks) over the chain's acceleration
input cells: what markov_prediction's hybrid mode uses in place of the
rule-based priority vector λ.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Annotated, ClassVar

import numpy as np

from ._wire import Array, Message, Range, register
from .common import HEADER_WALL_UPGRADE, MAX_ACCEL_MPS2, NON_NEG_INT, PROB, Header

_ACC = Range(-MAX_ACCEL_MPS2, MAX_ACCEL_MPS2, unit="m/s2")


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class AccelerationProfile:
    """The AR prediction for one vehicle on one of its corridors.

    - ``accel_mps2`` ``(h,) float32``: the model's acceleration at
      ``step_s``·1 … ``step_s``·h after the frame (m/s², along the corridor);
    - ``chunk_mean_mps2``, ``chunk_sigma_mps2`` ``(k,) float32``: mean and
      standard deviation of the normal distribution of chunk k (steps
      4k+1 … 4k+4 at the defaults): σ² = var(chunk) + σ_res,k², floored;
    - ``input_probs`` ``(k, m) float32``: that distribution over the message's
      input cells, tails beyond the outer edges folded into the end cells;
      every row sums to 1. Row 0 is λ(0), the chain's initial input
      distribution; row k is λ(k) for the step from t_k to t_{k+1}.
    - ``history_steps``: how many of the model's history steps were real
      (the rest padded and masked: a vehicle seen for less than the history).
    """

    track_id: Annotated[int, NON_NEG_INT]
    corridor_id: Annotated[int, NON_NEG_INT]
    history_steps: Annotated[int, NON_NEG_INT]
    accel_mps2: Annotated[np.ndarray, Array("float32", ("h",)), _ACC]
    chunk_mean_mps2: Annotated[np.ndarray, Array("float32", ("k",)), _ACC]
    chunk_sigma_mps2: Annotated[np.ndarray, Array("float32", ("k",)), Range(0.0, MAX_ACCEL_MPS2, unit="m/s2")]
    input_probs: Annotated[np.ndarray, Array("float32", ("k", "m")), PROB]


@register
@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class AccelerationProfiles(Message):
    """Every vehicle-corridor acceleration profile of one frame (the frame of ``header.stamp_ns``).

    ``model`` names the weights (file name and the first 12 hex digits of
    their SHA-256); ``step_s`` is the profile's time step (0.1 s),
    ``chunk_s`` the Markov step τ (0.4 s); ``input_edges_mps2`` ``(m+1,)``
    are the edges of the input cells (-3 … 2 m/s² in 0.5 steps by default).
    """

    SCHEMA: ClassVar[str] = "iamp.AccelerationProfiles"
    VERSION: ClassVar[int] = 2  # v2: Header.source_wall_ns
    UPGRADES: ClassVar[dict[int, Any]] = {1: HEADER_WALL_UPGRADE}  # v1 reads as v2 with source_wall_ns 0 (unknown)
    # measured 0.9-1.1 kB per (vehicle, corridor) profile: 4 MiB is about 4,000 profiles
    MAX_BYTES: ClassVar[int] = 4 * 1024 * 1024
    # a profile with a value out of range is dropped (recorded): that pair falls back as if it had none
    DROP_ELEMENTS: ClassVar[tuple[str, ...]] = ("profiles",)

    header: Header
    scene_id: str
    model: str
    step_s: Annotated[float, Range(1e-3, 60.0, unit="s")]
    chunk_s: Annotated[float, Range(1e-3, 60.0, unit="s")]
    input_edges_mps2: Annotated[np.ndarray, Array("float64", ("e",)), _ACC]
    profiles: tuple[AccelerationProfile, ...]

    def by_pair(self) -> dict[tuple[int, int], AccelerationProfile]:
        """The profiles keyed by (track_id, corridor_id)."""
        return {(p.track_id, p.corridor_id): p for p in self.profiles}
