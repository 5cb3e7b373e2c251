"""Binding of the grid_fusion stage: ports and ``main``; the stage is documented in ``stages/grid_fusion/__init__.py``."""

from __future__ import annotations

from bus_schemas import CorridorPredictions, MotionGrid, NodeStats
from stages.grid_fusion import MAX_SHARDS, GridFusionConfig, make
from stages.lib.grid_fusion import check_shard_sources
from stages.runtime import NodeContext, Port, StageSpec, run_stage

INPUTS = {
    **{f"grid_{i}": Port(MotionGrid, latest=True, optional=True) for i in range(MAX_SHARDS)},
    **{f"predictions_{i}": Port(CorridorPredictions, latest=True, optional=True) for i in range(MAX_SHARDS)},
    # every node's NodeStats (each node sends them every --stats-period): a clock tick, so that a frame that waits
    # for a shard that died is published after shard_timeout_s even when no other shard sends anything
    "tick": Port(NodeStats, pattern="_stats/*"),
}
OUTPUTS = {"motion_grid": Port(MotionGrid), "corridor_predictions": Port(CorridorPredictions)}


def make_core(config: GridFusionConfig, ctx: NodeContext):
    return make(config, ctx.input_keys, ctx.node_id)


SPEC = StageSpec(stage="stages.grid_fusion", config_cls=GridFusionConfig, make_core=make_core, inputs=INPUTS, outputs=OUTPUTS,
                 check_sources=check_shard_sources)


def main(argv: list[str] | None = None) -> int:
    return run_stage(SPEC, argv)


if __name__ == "__main__":
    raise SystemExit(main())
