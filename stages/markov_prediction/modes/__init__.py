"""The prediction modes, one ``InputModel`` each (contract in ``base.py``); ``MODELS`` is the loop's registry.

A new mode is one module here with its ``InputModel``, one line below and its
name in ``config.MODES``.
"""

from __future__ import annotations

from stages.markov_prediction.modes.base import InputModel
from stages.markov_prediction.modes.baseline import Baseline
from stages.markov_prediction.modes.corridor_cv import CorridorCV
from stages.markov_prediction.modes.cv import CartesianCV
from stages.markov_prediction.modes.hybrid import Hybrid


#: mode name (``MarkovPredictionConfig.mode``) -> its input model
MODELS: dict[str, type[InputModel]] = {"cv": CartesianCV, "corridor_cv": CorridorCV, "baseline": Baseline, "hybrid": Hybrid}

__all__ = ["MODELS", "InputModel"]
