"""ar_inference stage: the AR-Net acceleration profiles of every vehicle-corridor pair (docs/method.md §8).

Consumes ``corridor_set`` (``CorridorSet``) and ``relation_set``
(``RelationSet``) of the same stamp, optionally ``track_frame``; produces
``acceleration_profiles`` (``AccelerationProfiles``). Run it alone with
``python -m stages.ar_inference``.

Per frame it adds the frame to every vehicle's 4 s feature history
(``stages.lib.ar.FeatureTracker``: the same code that built the training data),
runs the model (``model``, default the shipped ``stages/lib/ar/weights/ar_taf_bw.pt``)
once over all (vehicle, corridor) pairs of the frame, and turns each
40-step profile into 10 normal distributions over the chain's input cells
(docs/method.md §8.5, ``chunk_distributions``): μ_k the mean of chunk k's four
0.1 s values, σ_k² = var(chunk) + (``sigma_scale``·σ_res,k)² with σ_res,k
the validation RMSE of chunk means stored with the weights, floored at
``sigma_floor_mps2`` 0.25 m/s² (half a cell); tails beyond the outer edges
are folded into the end cells. The cells (``input_min_mps2``,
``input_max_mps2``, ``n_inputs``) must be markov_prediction's: both default
to ``stages.lib.markov.grid``'s, and profiles over other cells are ignored
there (issue ``bad_profile``). A vehicle seen for less than 4 s is predicted
from what there is (padding and mask; ``history_steps`` says how much).

``max_pairs`` 600: bounded work per frame (issue 13): beyond it whole
vehicles are kept in CorridorSet order while their corridors fit, the rest
are skipped this frame (``stages.lib.caps.cap_pairs``; one ``pairs_capped``
issue). TAF-BW frames (at most ~20 vehicles, ~2 corridors each) never are.

Issues: ``stamp_mismatch`` (relations of another stamp: ignored),
``nan_prediction`` (pair left out), and the feature tracker's: ``scene_changed``
(the CorridorSet names another scene than the last) and ``stamp_backwards``
(every vehicle's history starts afresh), ``nan_state`` …. A weights file that is missing or unreadable stops the stage at start
(exit 2) with a message naming the file.
"""

from __future__ import annotations

from stages.ar_inference.config import ARInferenceConfig
from stages.ar_inference.core import ARInference, chunk_distributions

__all__ = ["INPUTS", "OUTPUTS", "SPEC", "ARInference", "ARInferenceConfig", "chunk_distributions", "main"]

_BINDING = ("SPEC", "INPUTS", "OUTPUTS", "main", "make_core")


def __getattr__(name: str):
    """The binding lives in ``__main__.py``; importing it pulls in the runtime (zenoh) only when asked."""
    if name in _BINDING:
        from stages.ar_inference import __main__ as binding

        return getattr(binding, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
