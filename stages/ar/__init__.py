"""AR acceleration model (METHOD.md §3): features, data set, the AR-Net model and its training.

- ``features``: ``FeatureTracker`` (per-vehicle feature history, the same
  code for training and online), ``FEATURE_NAMES``, ``HISTORY_STEPS``,
  ``HORIZON_STEPS``, ``STEP_S``;
- ``model``: ``ARNet``, ``ARModel`` (``predict``), ``save_model``,
  ``load_model``, ``DEFAULT_MODEL_PATH`` (the shipped
  ``weights/ar_taf_bw.pt``);
- ``dataset``: training windows from recordings; ``train``: ``iamp train``.

The torch-based names are imported on first use, so ``import stages.ar``
(and ``iamp --help``) stays light.
"""

from __future__ import annotations

from typing import Any

from .features import FEATURE_NAMES, HISTORY_STEPS, HORIZON_STEPS, STEP_S, FeatureConfig, FeatureTracker

_LAZY = {
    "ARModel": "model",
    "ARNet": "model",
    "DEFAULT_MODEL_PATH": "model",
    "load_model": "model",
    "save_model": "model",
    "ARDataset": "dataset",
    "DatasetConfig": "dataset",
    "build_dataset": "dataset",
    "TrainConfig": "train",
    "run_training": "train",
}


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    import importlib

    return getattr(importlib.import_module(f"{__name__}.{module}"), name)


__all__ = ["FEATURE_NAMES", "HISTORY_STEPS", "HORIZON_STEPS", "STEP_S", "FeatureConfig", "FeatureTracker", *_LAZY]
