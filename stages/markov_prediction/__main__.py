"""Binding of the markov_prediction stage: ports and ``main``; the stage is documented in ``stages/markov_prediction/__init__.py``."""

from __future__ import annotations

from bus_schemas import AccelerationProfiles, CorridorPredictions, CorridorSet, IntentionBelief, MotionGrid, RelationSet, SceneInfo, TrackFrame
from stages.markov_prediction.config import MarkovPredictionConfig
from stages.markov_prediction.core import MarkovPredictor
from stages.runtime import NodeContext, Port, StageSpec, run_stage

INPUTS = {
    "corridor_set": Port(CorridorSet),
    "relation_set": Port(RelationSet),
    "scene": Port(SceneInfo, latched=True),
    "track_frame": Port(TrackFrame, optional=True),  # sizes, and the velocity of mode "cv"
    # corridor_weights = "intentions" (P(R = c)), initial_box = "particles" and hybrid_stop_mixture (P(stop)) read the DBN's belief
    "intention_belief": Port(IntentionBelief, optional=True),
    # mode = "hybrid": λ_AR(k) of the ar_inference stage replace the rule-based λ (docs/method.md §8.5)
    "acceleration_profiles": Port(AccelerationProfiles, optional=True),
    # hybrid_profiles = "previous" with the frame's profiles off the join: bound here instead of acceleration_profiles
    # (pipelines/pipelined.toml), the newest profiles come as a latest value and no frame waits for its own
    "previous_profiles": Port(AccelerationProfiles, optional=True, latest=True),
}
# acceleration_profiles: published with hybrid_profiles = "inline" only (the profiles the stage computed itself,
# pipelines/inline.toml), so that the viewer and the recording keep them where no ar_inference stage runs
OUTPUTS = {"corridor_predictions": Port(CorridorPredictions), "motion_grid": Port(MotionGrid), "acceleration_profiles": Port(AccelerationProfiles)}


def make_core(config: MarkovPredictionConfig, ctx: NodeContext) -> MarkovPredictor:
    return MarkovPredictor(config, producer=ctx.node_id, log=ctx.log)


SPEC = StageSpec(
    stage="stages.markov_prediction", config_cls=MarkovPredictionConfig, make_core=make_core, inputs=INPUTS, outputs=OUTPUTS
)


def main(argv: list[str] | None = None) -> int:
    return run_stage(SPEC, argv)


if __name__ == "__main__":
    raise SystemExit(main())
