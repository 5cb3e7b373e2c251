"""AR acceleration model (docs/method.md §8): its features and the AR-Net model.

- ``features``: ``FeatureTracker`` (per-vehicle feature history, the same
  code for training and online), ``FEATURE_NAMES``, ``HISTORY_STEPS``,
  ``HORIZON_STEPS``, ``STEP_S``;
- ``model``: ``ARNet`` (linear / MLP), ``GRUNet``, ``ARModel``
  (``predict``), ``save_model``, ``load_model``, ``DEFAULT_MODEL_PATH`` (the
  shipped ``weights/ar_taf_bw.pt``, a GRU; ``weights/MODEL_CARD.md``).

- ``kernels``: the features' compiled hot paths (curvature integrals, causal
  acceleration; numba, the numpy code's values bit for bit), loaded on first use.

Training (data set and ``iamp train``) is offline code: ``stages.offline.train``.

The torch-based names are imported on first use, so ``import stages.lib.ar``
(and ``iamp --help``) stays light.
"""

from __future__ import annotations

from typing import Any

from stages.lib.ar.features import FEATURE_NAMES, HISTORY_STEPS, HORIZON_STEPS, STEP_S, FeatureConfig, FeatureTracker

_LAZY = {
    "ARModel": "model",
    "ARNet": "model",
    "GRUNet": "model",
    "DEFAULT_MODEL_PATH": "model",
    "load_model": "model",
    "save_model": "model",
}


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    import importlib

    return getattr(importlib.import_module(f"{__name__}.{module}"), name)


__all__ = ["FEATURE_NAMES", "HISTORY_STEPS", "HORIZON_STEPS", "STEP_S", "FeatureConfig", "FeatureTracker", *_LAZY]
