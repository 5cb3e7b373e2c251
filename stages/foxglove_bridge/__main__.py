"""Binding of the live Foxglove bridge: ports and ``main``; the stage is documented in ``stages/foxglove_bridge/__init__.py``."""

from __future__ import annotations

from bus_schemas import CorridorPredictions, CorridorSet, IntentionBelief, MotionGrid, NodeStats, SceneInfo, TrackFrame
from stages.foxglove_bridge.config import FoxgloveConfig
from stages.foxglove_bridge.core import FoxgloveBridge
from stages.runtime import NodeContext, Port, StageSpec, run_closing_stage

# As the viewer: the results are latest-value inputs (never joined, never holding a frame back); "stats" is the
# wildcard input of every node's NodeStats.
INPUTS = {
    "track_frame": Port(TrackFrame),
    "scene": Port(SceneInfo, latched=True),
    "corridor_set": Port(CorridorSet, latest=True, optional=True),
    "corridor_predictions": Port(CorridorPredictions, latest=True, optional=True),
    "motion_grid": Port(MotionGrid, latest=True, optional=True),
    "intention_belief": Port(IntentionBelief, latest=True, optional=True),
    "compare_predictions": Port(CorridorPredictions, latest=True, optional=True),  # a second mode (compare.toml): /<its node>/means
    "stats": Port(NodeStats, pattern="_stats/*"),
}
OUTPUTS: dict[str, Port] = {}


def make_core(config: FoxgloveConfig, ctx: NodeContext, opened: list | None = None) -> FoxgloveBridge:
    bridge = FoxgloveBridge(config, run_id=ctx.run_id, node_id=ctx.node_id, log=ctx.log, topic_keys=ctx.input_keys)
    if opened is not None:
        opened.append(bridge)
    ctx.log.info("foxglove: %s", bridge.start())
    return bridge


SPEC = StageSpec(stage="stages.foxglove_bridge", config_cls=FoxgloveConfig, make_core=make_core, inputs=INPUTS, outputs=OUTPUTS, restart_default=True,
                 nice_default=10)  # an observer: never ahead of the prediction stages for CPU (StageSpec)


def main(argv: list[str] | None = None) -> int:
    return run_closing_stage(SPEC, argv)


if __name__ == "__main__":
    raise SystemExit(main())
