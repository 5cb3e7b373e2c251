"""Binding of the ar_inference stage: ports and ``main``; the stage is documented in ``stages/ar_inference/__init__.py``."""

from __future__ import annotations

from bus_schemas import AccelerationProfiles, CorridorSet, RelationSet, TrackFrame
from stages.ar_inference.config import ARInferenceConfig
from stages.ar_inference.core import ARInference
from stages.runtime import NodeContext, Port, StageSpec, run_stage

INPUTS = {
    "corridor_set": Port(CorridorSet),
    "relation_set": Port(RelationSet),
    "track_frame": Port(TrackFrame, optional=True),
}
OUTPUTS = {"acceleration_profiles": Port(AccelerationProfiles)}


def make_core(config: ARInferenceConfig, ctx: NodeContext) -> ARInference:
    core = ARInference(config, producer=ctx.node_id)
    ctx.log.info("model loaded: %s (%d features, %d history steps)", core.model_name, len(core.feature_names), core.history_steps)
    return core


SPEC = StageSpec(stage="stages.ar_inference", config_cls=ARInferenceConfig, make_core=make_core, inputs=INPUTS, outputs=OUTPUTS)


def main(argv: list[str] | None = None) -> int:
    return run_stage(SPEC, argv)


if __name__ == "__main__":
    raise SystemExit(main())
