"""``ARInferenceConfig``: every parameter of the ar_inference stage, with units and defaults (it lives in
``stages.lib.ar.inference``, shared with markov_prediction's ``hybrid_profiles = "inline"``)."""

from __future__ import annotations

from stages.lib.ar.inference import ARInferenceConfig

__all__ = ["ARInferenceConfig"]
