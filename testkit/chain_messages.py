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


def dense_frames_with_profiles(vehicles: int, max_frames: int, out_dir: str | Path, keep) -> list:
    """``(ChainFrame, AccelerationProfiles)`` of the frames ``n`` (play order) for which ``keep(n)`` holds, of a
    recording of about ``vehicles`` vehicles per frame superimposed from the embedded K729 scenario into ``out_dir``:
    every input of markov_prediction in mode hybrid (the profiles from the shipped AR model)."""
    from stages.ar_inference import ARInference, ARInferenceConfig
    from stages.corridors import SceneMaps
    from stages.intentions import IntentionsConfig
    from stages.lib.datasets import DEFAULT_DATA_DIR, load_recording
    from stages.lib.datasets.superimpose import build_dense
    from stages.offline.chain import chain_frames

    built = build_dense(DEFAULT_DATA_DIR, "k729_2022-03-16", vehicles, out_dir)
    recording = load_recording(Path(out_dir), built.name)
    items = chain_frames(recording, recording.sequences[0], SceneMaps(data=Path(out_dir)), intentions=IntentionsConfig(), max_frames=max_frames)
    ar = ARInference(ARInferenceConfig(), producer="ar_inference")
    out = []
    for n, item in enumerate(items):
        profiles = ar.process(item.corridor_set, item.relation_set, item.frame, item.scene)[0]  # every frame: the AR state
        if keep(n):
            out.append((item, profiles))
    return out
