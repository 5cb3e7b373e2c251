"""Binding of the relations stage: ports and ``main``; the stage is documented in ``stages/relations/__init__.py``."""

from __future__ import annotations

from bus_schemas import CorridorSet, RelationSet, SceneInfo, SignalState, TrackFrame
from stages.relations.core import RelationExtractor, RelationsConfig
from stages.runtime import NodeContext, Port, StageSpec, run_stage

INPUTS = {
    "track_frame": Port(TrackFrame),
    "corridor_set": Port(CorridorSet),
    "scene": Port(SceneInfo, latched=True),
    "signal_state": Port(SignalState, latest=True, optional=True),  # not joined: the newest, used when within 0.5 s
}
OUTPUTS = {"relation_set": Port(RelationSet)}


def make_core(config: RelationsConfig, ctx: NodeContext) -> RelationExtractor:
    return RelationExtractor(config, producer=ctx.node_id)


SPEC = StageSpec(stage="stages.relations", config_cls=RelationsConfig, make_core=make_core, inputs=INPUTS, outputs=OUTPUTS)


def main(argv: list[str] | None = None) -> int:
    return run_stage(SPEC, argv)


if __name__ == "__main__":
    raise SystemExit(main())
