"""Binding of the tracks_source stage: ports and ``main``; the stage is documented in ``stages/tracks_source/__init__.py``."""

from __future__ import annotations

from bus_schemas import SceneInfo, SignalState, TrackFrame
from stages.lib.base import ConfigError
from stages.lib.datasets import DatasetError, find_recording
from stages.lib.datasets.model import same_sequence_id
from stages.runtime import NodeContext, Port, StageSpec, run_stage
from stages.tracks_source.core import TrackPlayer, TracksSourceConfig, resolve_selection

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


def preflight(config: TracksSourceConfig) -> None:
    """The launcher's check before any node starts (``StageSpec.preflight``): the recording and its map are there
    (the folder is listed, no track is read)."""
    try:
        sel = resolve_selection(config)
        ref = find_recording(sel.data_dir, sel.recording)
    except DatasetError as exc:
        raise ConfigError(str(exc)) from None
    if ref.map_path is None:
        raise ConfigError(f"recording {ref.name} has no map: expected maps/{ref.name}.osm in {sel.data_dir}")
    for want in sel.sequences or ():
        if not any(same_sequence_id(s, want) for s in ref.sequence_ids):
            raise ConfigError(f"recording {ref.name}: no track file for sequence {want!r}; available: {', '.join(ref.sequence_ids)}")


SPEC = StageSpec(
    stage="stages.tracks_source",
    config_cls=TracksSourceConfig,
    make_core=make_core,
    inputs=INPUTS,
    outputs=OUTPUTS,
    kind="source",
    restart_default=False,
    preflight=preflight,
)


def main(argv: list[str] | None = None) -> int:
    return run_stage(SPEC, argv)


if __name__ == "__main__":
    raise SystemExit(main())
