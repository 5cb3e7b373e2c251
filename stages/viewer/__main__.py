"""Binding of the viewer stage: ports and ``main``; the stage is documented in ``stages/viewer/__init__.py``."""

from __future__ import annotations

import dataclasses
import sys
from typing import Any

from bus_schemas import CorridorPredictions, CorridorSet, MotionGrid, NodeStats, SceneInfo, SchemaError, TrackFrame, keys
from stages.runtime import BusClient, NodeContext, Port, StageSpec, build_parser, run_stage
from stages.viewer.config import ViewerConfig
from stages.viewer.scene import StatsBoard, ViewerApp

# The results are "latched" inputs only to keep them out of the runtime's stamp join (16 stamps, 2 s): the
# predictions may lag the frames by more on a busy machine, and the join would then drop every frame. The core
# gets the latest of each with every frame and joins them to their frames by stamp itself (model.FrameHistory).
# HOOK(runtime): a Port option "not joined, latest value" (without the start-up query) would say this plainly.
INPUTS = {
    "track_frame": Port(TrackFrame),
    "scene": Port(SceneInfo, latched=True),
    "corridor_set": Port(CorridorSet, latched=True, optional=True),
    "corridor_predictions": Port(CorridorPredictions, latched=True, optional=True),
    "motion_grid": Port(MotionGrid, latched=True, optional=True),
}
OUTPUTS: dict[str, Port] = {}


def make_core(config: ViewerConfig, ctx: NodeContext, network: Any = None, opened: list | None = None) -> ViewerApp:
    """The viewer app, started; with ``network`` (the stage's network flags) also a bus session for the run's NodeStats.

    What it opens is appended to ``opened`` for ``main`` to close: an open
    second Zenoh session would keep the process from exiting.
    """
    opened = [] if opened is None else opened
    board = StatsBoard() if config.stats and network is not None else None
    if board is not None:  # the runtime has no port for the _stats/* wildcard
        bus = BusClient(mode=network.mode, connect=network.connect, config_file=network.config)
        opened.append(bus)
        bus.subscribe(keys.stats_pattern(ctx.run_id), lambda _key, data: _put_stats(board, data))
    app = ViewerApp(config, run_id=ctx.run_id, log=ctx.log, stats=board)
    opened.append(app)
    ctx.log.info("viewer: %s", app.start())
    return app


def _put_stats(board: StatsBoard, data: bytes) -> None:
    try:
        board.put(NodeStats.decode(data))
    except SchemaError:
        pass


SPEC = StageSpec(stage="stages.viewer", config_cls=ViewerConfig, make_core=make_core, inputs=INPUTS, outputs=OUTPUTS, restart_default=True)


def main(argv: list[str] | None = None) -> int:
    network = None
    args = sys.argv[1:] if argv is None else argv
    if not {"-h", "--help"} & set(args):
        try:  # the network flags, for the stats subscription; run_stage reports any bad flag itself
            network, _ = build_parser(SPEC).parse_known_args(args)
        except SystemExit:
            network = None
    opened: list = []
    spec = dataclasses.replace(SPEC, make_core=lambda config, ctx: make_core(config, ctx, network, opened))
    try:
        return run_stage(spec, argv)
    finally:
        for item in reversed(opened):
            item.close()


if __name__ == "__main__":
    raise SystemExit(main())
