"""Binding of the corridors stage: ports and ``main``; the stage is documented in ``stages/corridors/__init__.py``."""

from __future__ import annotations

from bus_schemas import CorridorSet, SceneInfo, TrackFrame
from stages.corridors.core import CorridorBuilder, CorridorsConfig
from stages.runtime import NodeContext, Port, StageSpec, run_stage

INPUTS = {"track_frame": Port(TrackFrame), "scene": Port(SceneInfo, latched=True)}
OUTPUTS = {"corridor_set": Port(CorridorSet)}


def make_core(config: CorridorsConfig, ctx: NodeContext) -> CorridorBuilder:
    return CorridorBuilder(config, producer=ctx.node_id, log=ctx.log)


SPEC = StageSpec(stage="stages.corridors", config_cls=CorridorsConfig, make_core=make_core, inputs=INPUTS, outputs=OUTPUTS)


def main(argv: list[str] | None = None) -> int:
    return run_stage(SPEC, argv)


if __name__ == "__main__":
    raise SystemExit(main())
