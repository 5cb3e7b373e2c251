"""``ARInference``: CorridorSet + RelationSet (+ TrackFrame) -> AccelerationProfiles (package docstring). The core lives in
``stages.lib.ar.inference``, shared with markov_prediction's ``hybrid_profiles = "inline"``, which runs it in its own
process."""

from __future__ import annotations

from stages.lib.ar.inference import ARInference, chunk_distributions

__all__ = ["ARInference", "chunk_distributions"]
