"""Binding of the tracks_source stage: ports and ``main``; the stage is documented in ``stages/tracks_source/__init__.py``."""

from __future__ import annotations

from bus_schemas import SceneInfo, SignalState, TrackFrame
from stages.runtime import NodeContext, Port, StageSpec, run_stage
from stages.tracks_source.core import TrackPlayer, TracksSourceConfig

INPUTS: dict[str, Port] = {}
OUTPUTS = {"scene": Port(SceneInfo, latched=True), "track_frame": Port(TrackFrame), "signal_state": Port(SignalState)}


def make_core(config: TracksSourceConfig, ctx: NodeContext) -> TrackPlayer:
    player = TrackPlayer.open(config, run_id=ctx.run_id, producer=ctx.node_id)
    rec = player.recording
    ctx.log.info(
        "recording loaded: recording=%s format=%s sequences=%s frames=%d %s",
        rec.name,
        rec.format,
        ",".join(s.id for s in rec.sequences),
        player.n_frames_per_pass,
        rec.report.summary(),
    )
    return player


SPEC = StageSpec(
    stage="stages.tracks_source",
    config_cls=TracksSourceConfig,
    make_core=make_core,
    inputs=INPUTS,
    outputs=OUTPUTS,
    kind="source",
    restart_default=False,
)


def main(argv: list[str] | None = None) -> int:
    return run_stage(SPEC, argv)


if __name__ == "__main__":
    raise SystemExit(main())
