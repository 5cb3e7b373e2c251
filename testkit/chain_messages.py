"""Real bus messages made by the offline chain, for codec tests and ``bench/codec.py``.

``chain_messages`` plays a recording through ``stages.offline.chain.Chain``
(source, corridors, relations, intentions) and returns, in play order, every
message the cores published: SceneInfo, TrackFrame, SignalState (where the
recording has phases), CorridorSet, RelationSet and IntentionBelief.
``dense_messages`` does so on a recording of N vehicles per frame built by
the dense data builder.
"""

from __future__ import annotations

from pathlib import Path

from bus_schemas import Message


def chain_messages(data_dir: str | Path, recording_name: str, *, max_frames: int, sequences: tuple[str, ...] | None = None) -> list[Message]:
    """The messages of the first ``max_frames`` frames of the recording's first (or only given) sequence."""
    from stages.corridors import SceneMaps
    from stages.intentions import IntentionsConfig
    from stages.lib.datasets import load_recording
    from stages.offline.chain import Chain

    recording = load_recording(Path(data_dir), recording_name, sequences)
    out: list[Message] = []
    scene = None
    for item in Chain(recording, recording.sequences[0], SceneMaps(data=Path(data_dir)), intentions=IntentionsConfig(), max_frames=max_frames):
        if item.scene is not scene:
            scene = item.scene
            out.append(scene)
        out += [m for m in (item.frame, item.signal_state, item.corridor_set, item.relation_set, item.belief) if m is not None]
    return out


def dense_messages(vehicles: int, max_frames: int, out_dir: str | Path, *, data_dir: str | Path | None = None, recording: str = "k729_2022-03-16") -> list[Message]:
    """``chain_messages`` of a recording of about ``vehicles`` vehicles per frame superimposed into ``out_dir``.

    From ``recording`` of ``data_dir`` (default the embedded data: its K729
    sequences, so it runs on a fresh checkout) by the dense data builder
    (``stages.lib.datasets.superimpose.build_dense``, as ``bench/dense.py``).
    """
    from stages.lib.datasets import DEFAULT_DATA_DIR
    from stages.lib.datasets.superimpose import build_dense

    built = build_dense(data_dir if data_dir is not None else DEFAULT_DATA_DIR, recording, vehicles, out_dir)
    return chain_messages(out_dir, built.name, max_frames=max_frames)
