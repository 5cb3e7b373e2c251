"""Binding of the intentions stage: ports and ``main``; the stage is documented in ``stages/intentions/__init__.py``."""

from __future__ import annotations

from bus_schemas import CorridorSet, IntentionBelief, RelationSet, SceneInfo, TrackFrame
from stages.intentions.core import IntentionFilter, IntentionsConfig
from stages.runtime import NodeContext, Port, StageSpec, run_stage

INPUTS = {
    "track_frame": Port(TrackFrame),
    "corridor_set": Port(CorridorSet),
    "relation_set": Port(RelationSet),
    "scene": Port(SceneInfo, latched=True),
}
OUTPUTS = {"intention_belief": Port(IntentionBelief)}


def make_core(config: IntentionsConfig, ctx: NodeContext) -> IntentionFilter:
    return IntentionFilter(config, producer=ctx.node_id)


SPEC = StageSpec(stage="stages.intentions", config_cls=IntentionsConfig, make_core=make_core, inputs=INPUTS, outputs=OUTPUTS)


def main(argv: list[str] | None = None) -> int:
    return run_stage(SPEC, argv)


if __name__ == "__main__":
    raise SystemExit(main())
