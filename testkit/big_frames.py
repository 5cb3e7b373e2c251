"""Well-formed TrackFrames of many objects built from real embedded tracks (issue 13, item 3).

``big_frames(n_objects)`` plays K729 sequence 013 and overlays ``k`` time
offsets of it: big frame ``j`` holds the objects of real frames ``j + o`` for
offsets ``o`` spread over the sequence (0.3-0.7 s apart) (each copy with its own track ids,
``id * 1000 + copy``), until ``n_objects`` are collected. The copies are real
cars on real lanes at other instants, so the frame is plausible traffic, just
far denser than any recording (at most ~20 vehicles per frame in TAF-BW).
Used by ``bench/hostile.py --section big-frame`` and the cap tests.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from bus_schemas import Header, SceneInfo, TrackFrame
from stages.lib.datasets import DEFAULT_DATA_DIR, load_recording
from stages.tracks_source.core import TracksSourceConfig, TrackPlayer, file_sha256

RECORDING = "k729_2022-03-16"
SEQUENCE = "013"


def real_frames(limit: int | None = None, *, run_id: str = "big", producer: str = "source",
                map_sha256: bool = False) -> tuple[SceneInfo, list[TrackFrame]]:
    """The scene and the TrackFrames of K729 sequence 013 (the first ``limit``), as the dataset player publishes them
    in run ``run_id`` as node ``producer``; ``map_sha256``: the scene names its map's hash, as the player's on the bus
    (a stage loads the map only then)."""
    recording = load_recording(DEFAULT_DATA_DIR, RECORDING, (SEQUENCE,))
    one = dataclasses.replace(recording, sequences=(recording.sequences[0],))
    sha = file_sha256(recording.map_path) if map_sha256 else ""
    player = TrackPlayer(TracksSourceConfig(recording=recording.name), one, map_sha256=sha, run_id=run_id, producer=producer)
    scene, frames = None, []
    for _stamp, result in player:
        scene = result.outputs.get("scene", scene)
        frames.append(result.outputs["track_frame"])
        if limit is not None and len(frames) >= limit:
            break
    return scene, frames


def big_frames(n_objects: int, n_frames: int = 3, *, source: tuple[SceneInfo, list[TrackFrame]] | None = None):
    """The scene and ``n_frames`` consecutive TrackFrames of exactly ``n_objects`` objects each."""
    scene, frames = source or real_frames()
    usable = len(frames) - n_frames
    per_frame = max(1.0, float(np.mean([len(f) for f in frames])))
    step = max(1, min(7, int(usable * per_frame / (1.2 * n_objects))))  # up to 0.7 s apart: another traffic picture
    offsets = list(range(0, usable, step))
    out = []
    for j in range(n_frames):
        cols = {k: [] for k in ("track_ids", "agent_types", "x_m", "y_m", "vx_mps", "vy_mps", "yaw_rad", "length_m", "width_m")}
        count = 0
        for copy, o in enumerate(offsets):
            f = frames[o + j]
            take = min(len(f), n_objects - count)
            if take <= 0:
                break
            for name in cols:
                values = np.asarray(getattr(f, name))[:take]
                cols[name].append(values * 1000 + copy if name == "track_ids" else values)
            count += take
        if count < n_objects:
            raise ValueError(f"only {count} objects available, {n_objects} asked")
        base = frames[j]
        header = Header(run_id="big", frame_index=base.header.frame_index, stamp_ns=base.header.stamp_ns, producer="source")
        arrays = {k: np.concatenate(v) for k, v in cols.items()}
        arrays["track_ids"] = arrays["track_ids"].astype(np.int64)
        arrays["agent_types"] = arrays["agent_types"].astype(np.uint8)
        out.append(TrackFrame(header=header, scene_id=base.scene_id, **arrays))
    return scene, out
