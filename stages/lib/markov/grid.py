"""The Markov discretisation: position, velocity and input cells (docs/method.md §2, §3).

A Markov state of one vehicle-corridor pair is a cell (s-cell, v-cell) of a
window of ``n_s_cells`` cells of ``ds_m`` along the corridor and of
``v_max_mps / dv_mps`` velocity cells on [0, v_max]. An input cell α is an
acceleration interval between consecutive ``input_edges_mps2``. The step is
``tau_s`` and the horizon ``n_steps`` steps.

The push-forward sample counts and the number of sub-times of the interval
matrix are part of the configuration because they change the matrices, and
hence the cache key.
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass, fields

import numpy as np

from stages.lib.base import ConfigMixin

#: Bumped whenever the dynamics or the way the stencils are built changes, so
#: that a cache written by an older build is never read as current.
MODEL_VERSION = 1

#: The chain's input (acceleration) cells: ``DEFAULT_N_INPUTS`` equal cells on
#: [``DEFAULT_INPUT_MIN_MPS2``, ``DEFAULT_INPUT_MAX_MPS2``]. The one source of the
#: defaults of ``MarkovGridConfig``, ``MarkovPredictionConfig`` and
#: ``ARInferenceConfig`` (whose distributions are over these cells).
DEFAULT_INPUT_MIN_MPS2 = -3.0
DEFAULT_INPUT_MAX_MPS2 = 2.0
DEFAULT_N_INPUTS = 10


def uniform_input_edges(lo_mps2: float = DEFAULT_INPUT_MIN_MPS2, hi_mps2: float = DEFAULT_INPUT_MAX_MPS2,
                        n_inputs: int = DEFAULT_N_INPUTS) -> tuple[float, ...]:
    """Edges of ``n_inputs`` equal input cells on [lo, hi] (m/s²), ``n_inputs + 1`` floats; ValueError on a bad range."""
    if not (isinstance(n_inputs, int) and not isinstance(n_inputs, bool) and n_inputs >= 2):
        raise ValueError(f"n_inputs = {n_inputs!r}: must be an int >= 2")
    if not (math.isfinite(lo_mps2) and math.isfinite(hi_mps2) and hi_mps2 > lo_mps2):
        raise ValueError(f"input cells [{lo_mps2}, {hi_mps2}] m/s²: need finite min < max")
    return tuple(float(lo_mps2 + (hi_mps2 - lo_mps2) * i / n_inputs) for i in range(n_inputs + 1))


_DEFAULT_INPUT_EDGES_MPS2 = uniform_input_edges()

#: Continuous models the stencil builder implements. ``point_mass_saturated``:
#: s' = v, v' = a, v clamped to [0, v_max] (docs/method.md §3.1).
MODEL_VARIANTS = ("point_mass_saturated",)


@dataclass(frozen=True, kw_only=True)
class MarkovGridConfig(ConfigMixin):
    """Discretisation of the longitudinal Markov chain (defaults: docs/method.md §2).

    ``n_state_samples`` is the number of push-forward samples per cell per
    state axis (s and v), ``n_input_samples`` the number of accelerations per
    input cell, ``n_sub_times`` the number of sub-times (centres of equal
    sub-intervals of [0, τ]) that Υ([0, τ]) averages over. ``model_variant``
    names the continuous model; it enters the cache key.
    """

    ds_m: float = 1.0
    dv_mps: float = 0.5
    v_max_mps: float = 20.0
    n_s_cells: int = 100
    input_edges_mps2: tuple[float, ...] = _DEFAULT_INPUT_EDGES_MPS2
    tau_s: float = 0.4
    n_steps: int = 10
    n_state_samples: int = 10
    n_input_samples: int = 8
    n_sub_times: int = 8
    model_variant: str = "point_mass_saturated"

    def __post_init__(self) -> None:
        for name in ("ds_m", "dv_mps", "v_max_mps", "tau_s"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ValueError(f"MarkovGridConfig.{name} must be a positive finite number, got {value!r}")
        for name in ("n_s_cells", "n_steps", "n_state_samples", "n_input_samples", "n_sub_times"):
            value = getattr(self, name)
            if not (isinstance(value, int) and not isinstance(value, bool) and value >= 1):
                raise ValueError(f"MarkovGridConfig.{name} must be an int >= 1, got {value!r}")
        ratio = self.v_max_mps / self.dv_mps
        if abs(ratio - round(ratio)) > 1e-9 * max(1.0, ratio):
            raise ValueError(
                f"MarkovGridConfig: v_max_mps / dv_mps must be an integer, got {self.v_max_mps} / {self.dv_mps}"
            )
        edges = tuple(float(e) for e in self.input_edges_mps2)
        if len(edges) < 2 or any(not math.isfinite(e) for e in edges):
            raise ValueError(f"MarkovGridConfig.input_edges_mps2 needs >= 2 finite edges, got {edges!r}")
        if any(b <= a for a, b in zip(edges, edges[1:])):
            raise ValueError(f"MarkovGridConfig.input_edges_mps2 must be strictly increasing, got {edges!r}")
        object.__setattr__(self, "input_edges_mps2", edges)
        if self.model_variant not in MODEL_VARIANTS:
            raise ValueError(
                f"MarkovGridConfig.model_variant {self.model_variant!r} is not implemented;"
                f" known: {', '.join(MODEL_VARIANTS)}"
            )

    # -- sizes ---------------------------------------------------------------

    @property
    def n_v_cells(self) -> int:
        """Number of velocity cells on [0, v_max]."""
        return int(round(self.v_max_mps / self.dv_mps))

    @property
    def n_inputs(self) -> int:
        """Number of input (acceleration) cells M."""
        return len(self.input_edges_mps2) - 1

    @property
    def n_states_per_pair(self) -> int:
        """Joint states (α, v, s) of one vehicle-corridor pair, without the outside cell."""
        return self.n_inputs * self.n_v_cells * self.n_s_cells

    @property
    def horizon_s(self) -> float:
        """Prediction horizon K·τ."""
        return self.n_steps * self.tau_s

    # -- cell geometry -------------------------------------------------------

    def s_edges_m(self) -> np.ndarray:
        """Edges of the s-cells of one window, ``(n_s_cells + 1,) float64``, from 0."""
        return np.arange(self.n_s_cells + 1, dtype=np.float64) * self.ds_m

    def s_centres_m(self) -> np.ndarray:
        """Centres of the s-cells, ``(n_s_cells,) float64``."""
        return (np.arange(self.n_s_cells, dtype=np.float64) + 0.5) * self.ds_m

    def v_edges_mps(self) -> np.ndarray:
        """Edges of the velocity cells, ``(n_v_cells + 1,) float64``, 0 … v_max."""
        return np.arange(self.n_v_cells + 1, dtype=np.float64) * self.dv_mps

    def v_centres_mps(self) -> np.ndarray:
        """Centres of the velocity cells, ``(n_v_cells,) float64``."""
        return (np.arange(self.n_v_cells, dtype=np.float64) + 0.5) * self.dv_mps

    def input_edges(self) -> np.ndarray:
        """Edges of the input cells, ``(n_inputs + 1,) float64`` in m/s²."""
        return np.asarray(self.input_edges_mps2, dtype=np.float64)

    def input_centres_mps2(self) -> np.ndarray:
        """Centres of the input cells, ``(n_inputs,) float64`` in m/s²."""
        edges = self.input_edges()
        return 0.5 * (edges[:-1] + edges[1:])

    def input_cell_of(self, accel_mps2: float) -> int:
        """Index of the input cell that holds ``accel_mps2``; values outside fold into the end cells."""
        index = int(np.searchsorted(self.input_edges(), accel_mps2, side="right")) - 1
        return min(max(index, 0), self.n_inputs - 1)

    # -- cache identity --------------------------------------------------------

    def params(self) -> dict[str, object]:
        """Every parameter plus the model version, as a JSON-able dict."""
        out: dict[str, object] = {}
        for f in fields(self):
            value = getattr(self, f.name)
            out[f.name] = list(value) if isinstance(value, tuple) else value
        out["model_version"] = MODEL_VERSION
        return out

    def params_json(self) -> str:
        """Canonical JSON of ``params()`` (sorted keys, floats as shortest repr)."""
        return json.dumps(self.params(), sort_keys=True, separators=(",", ":"))

    def cache_key(self) -> str:
        """Stable hash of every parameter and the model variant/version (hex, 20 chars).

        It does not depend on the Python process (no ``hash()``), so it names
        the cache file across runs and machines.
        """
        return hashlib.sha256(self.params_json().encode("utf-8")).hexdigest()[:20]
