"""``ARInferenceConfig``: every parameter of the ar_inference stage, with units and defaults."""

from __future__ import annotations

from dataclasses import dataclass

from stages.lib.base import ConfigMixin, check_ranges
from stages.lib.markov.grid import DEFAULT_INPUT_MAX_MPS2, DEFAULT_INPUT_MIN_MPS2, DEFAULT_N_INPUTS, uniform_input_edges


@dataclass(frozen=True, kw_only=True)
class ARInferenceConfig(ConfigMixin):
    """Parameters of the ar_inference stage (package docstring; docs/method.md §8.5)."""

    #: weights file; empty: the shipped ``stages/lib/ar/weights/ar_taf_bw.pt``
    model: str = ""
    #: torch device of the model ("cpu", "cuda", "cuda:0")
    device: str = "cpu"
    #: Markov step τ: one distribution per chunk of ``chunk_s`` / the profile's 0.1 s steps
    chunk_s: float = 0.4
    #: input cells of the chain: ``n_inputs`` equal cells on [input_min, input_max] m/s². Must be the markov_prediction
    #: stage's (same three parameters, same defaults from ``stages.lib.markov.grid``); profiles over other cells are
    #: ignored there with a ``bad_profile`` issue
    input_min_mps2: float = DEFAULT_INPUT_MIN_MPS2
    input_max_mps2: float = DEFAULT_INPUT_MAX_MPS2
    n_inputs: int = DEFAULT_N_INPUTS
    #: σ_k = max(floor, √(var(chunk) + (scale·σ_res,k)²)): ``sigma_scale`` multiplies the validation RMSE of the weights file
    sigma_scale: float = 1.0
    sigma_floor_mps2: float = 0.25
    #: vehicle-corridor pairs per frame; whole vehicles beyond, in CorridorSet order, are skipped (issue ``pairs_capped``)
    max_pairs: int = 600

    def __post_init__(self) -> None:
        check_ranges(self, positive=("chunk_s", "sigma_floor_mps2"), non_negative=("sigma_scale",))
        if not self.input_max_mps2 > self.input_min_mps2:
            raise ValueError(f"input_min_mps2 = {self.input_min_mps2}, input_max_mps2 = {self.input_max_mps2}: need min < max")
        if self.max_pairs < 1:
            raise ValueError(f"max_pairs = {self.max_pairs}: must be >= 1")
        if self.n_inputs < 2:
            raise ValueError(f"n_inputs = {self.n_inputs}: must be >= 2")
        if not (self.device == "cpu" or self.device.startswith("cuda")):
            raise ValueError(f"device = {self.device!r}: expected 'cpu' or 'cuda[:N]'")

    def input_edges(self):
        """Edges of the input cells, ``(n_inputs + 1,) float64`` m/s² (``stages.lib.markov.grid.uniform_input_edges``)."""
        import numpy as np

        return np.asarray(uniform_input_edges(self.input_min_mps2, self.input_max_mps2, self.n_inputs), dtype=np.float64)
