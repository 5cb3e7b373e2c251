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


def preflight(config: ARInferenceConfig) -> None:
    """The launcher's check before any node starts (``StageSpec.preflight``, and ``launch.py --check``): a ``model``
    that is no file, a folder, or not a whole weights file (``iamp train`` writes a zip archive; a truncated copy has
    no end record) stops the run at once with what to fix, not the node minutes later. Cheap: torch is not loaded."""
    import zipfile
    from pathlib import Path

    from stages.lib.base import ConfigError

    from stages.lib.ar.inference import check_device

    check_device(config.device)
    if not config.model:
        return  # the shipped weights
    path = Path(config.model).expanduser()
    if path.is_dir():
        raise ConfigError(f"model = {config.model!r}: is a folder; expected a weights file written by `iamp train --out FILE`")
    if not path.is_file():
        raise ConfigError(f"model = {config.model!r}: no such weights file (train one with `iamp train --out FILE`)")
    if not zipfile.is_zipfile(path):
        raise ConfigError(f"model = {config.model!r}: not a whole weights file (truncated, or not written by `iamp train`)")


SPEC = StageSpec(stage="stages.ar_inference", config_cls=ARInferenceConfig, make_core=make_core, inputs=INPUTS, outputs=OUTPUTS,
                 preflight=preflight)


def main(argv: list[str] | None = None) -> int:
    return run_stage(SPEC, argv)


if __name__ == "__main__":
    raise SystemExit(main())
