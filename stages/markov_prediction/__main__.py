"""Binding of the markov_prediction stage: ports and ``main``; the stage is documented in ``stages/markov_prediction/__init__.py``."""

from __future__ import annotations

from bus_schemas import AccelerationProfiles, CorridorPredictions, CorridorSet, IntentionBelief, MotionGrid, RelationSet, SceneInfo, TrackFrame
from stages.markov_prediction.config import MarkovPredictionConfig
from stages.markov_prediction.core import MarkovPredictor, check_torch_device
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


def preflight(config: MarkovPredictionConfig) -> None:
    """The launcher's check before any node starts (``StageSpec.preflight``, and ``launch.py --check``): a device that is
    not here and a spread table that does not fit the horizon stopped the node at its start, after ``--check`` had
    called the pipeline valid. The core's own device check (``check_torch_device``), and its spread table's."""
    from stages.lib.base import ConfigError

    if config.backend == "cuda":
        from stages.lib.markov import cuda_chain

        if (reason := cuda_chain.unavailable_reason()) is not None:
            raise ConfigError(f"backend = 'cuda': {reason}; use backend = 'numpy'")
    check_torch_device(config)
    if config.spread_calibration:
        from stages.markov_prediction.spread import load_spread

        try:
            load_spread(config.spread_calibration, config.mode, config.n_steps, config.spread_shape)
        except ValueError as exc:
            raise ConfigError(str(exc)) from None


SPEC = StageSpec(
    stage="stages.markov_prediction", config_cls=MarkovPredictionConfig, make_core=make_core, inputs=INPUTS, outputs=OUTPUTS,
    preflight=preflight,
)


def main(argv: list[str] | None = None) -> int:
    return run_stage(SPEC, argv)


if __name__ == "__main__":
    raise SystemExit(main())
