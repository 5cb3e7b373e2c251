"""Binding of the viewer stage: ports and ``main``; the stage is documented in ``stages/viewer/__init__.py``."""

from __future__ import annotations

from bus_schemas import AccelerationProfiles, CorridorPredictions, CorridorSet, IntentionBelief, MotionGrid, NodeStats, SceneInfo, SignalState, TrackFrame
from stages.runtime import NodeContext, Port, StageSpec, run_closing_stage
from stages.viewer.config import ViewerConfig
from stages.viewer.scene import StatsBoard, ViewerApp

# The results are latest-value inputs: not part of the runtime's stamp join (16 stamps, 2 s), which would drop
# every frame once the predictions lag the frames by more, as they do on a busy machine. The core gets the
# newest of each with every frame and joins them to their frames by stamp itself (model.FrameHistory).
# "stats" is a wildcard input: the newest NodeStats of every node of the run, {key: NodeStats}.
INPUTS = {
    "track_frame": Port(TrackFrame),
    "scene": Port(SceneInfo, latched=True),
    "corridor_set": Port(CorridorSet, latest=True, optional=True),
    "corridor_predictions": Port(CorridorPredictions, latest=True, optional=True),
    "motion_grid": Port(MotionGrid, latest=True, optional=True),
    # a second prediction mode on the same frames (pipelines/compare.toml), drawn over the first with the running mADE of each
    "compare_predictions": Port(CorridorPredictions, latest=True, optional=True),
    # the selected-vehicle panel: P(route), P(stop) and the AR acceleration distributions
    "intention_belief": Port(IntentionBelief, latest=True, optional=True),
    "acceleration_profiles": Port(AccelerationProfiles, latest=True, optional=True),
    "signal_state": Port(SignalState, latest=True, optional=True),  # colours the signalised stop lines (stages.viewer.signals)
    "stats": Port(NodeStats, pattern="_stats/*"),
}
OUTPUTS: dict[str, Port] = {}


def make_core(config: ViewerConfig, ctx: NodeContext, opened: list | None = None) -> ViewerApp:
    """The viewer app, started; it is appended to ``opened`` for ``main`` to close (its server and render thread)."""
    app = ViewerApp(config, run_id=ctx.run_id, log=ctx.log, stats=StatsBoard() if config.stats else None)
    if opened is not None:
        opened.append(app)
    ctx.log.info("viewer: %s", app.start())
    return app


SPEC = StageSpec(stage="stages.viewer", config_cls=ViewerConfig, make_core=make_core, inputs=INPUTS, outputs=OUTPUTS, restart_default=True,
                 nice_default=10)  # an observer: never ahead of the prediction stages for CPU (StageSpec)


def main(argv: list[str] | None = None) -> int:
    return run_closing_stage(SPEC, argv)


if __name__ == "__main__":
    raise SystemExit(main())
