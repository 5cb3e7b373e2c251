"""A tracker that stamps its frames in milliseconds (or microseconds) hears it from the corridors stage, in one issue
per frame that names the unit, instead of losing every vehicle downstream to out-of-range speeds in silence (found by
a new-user probe of the live input)."""

from __future__ import annotations

import dataclasses

from stages.corridors import CorridorBuilder, CorridorsConfig
from stages.lib.datasets import DEFAULT_DATA_DIR, DEFAULT_RECORDING, load_recording
from stages.tracks_source.core import TrackPlayer, TracksSourceConfig, file_sha256


def _played(n: int):
    recording = load_recording(DEFAULT_DATA_DIR, DEFAULT_RECORDING, ["013"])
    player = TrackPlayer(TracksSourceConfig(recording=recording.name), recording, map_sha256=file_sha256(recording.map_path),
                         run_id="t", producer="source")
    scene, frames = None, []
    for _stamp, result in player:
        scene = result.outputs.get("scene", scene)
        frames.append(result.outputs["track_frame"])
        if len(frames) == n:
            return scene, frames
    raise AssertionError("the embedded sequence is too short")


def _issues(scene, frames, divide: int) -> list:
    builder = CorridorBuilder(CorridorsConfig())
    found = []
    for frame in frames:
        header = dataclasses.replace(frame.header, stamp_ns=frame.header.stamp_ns // divide)
        found.append(builder.process(dataclasses.replace(frame, header=header), scene)[1])
    return found


def test_stamps_in_milliseconds_are_named_once_per_frame_and_nanoseconds_are_not():
    scene, frames = _played(6)
    for divide in (1_000_000, 1_000):  # milliseconds, microseconds
        per_frame = [[i for i in issues if i.kind == "stamp_step_implausible"] for issues in _issues(scene, frames, divide)]
        assert [len(f) for f in per_frame] == [0] + [1] * (len(frames) - 1)
        message = per_frame[1][0].detail
        assert f"advance {100_000_000 // divide} ns" in message and "10 Hz (100,000,000 ns a frame)" in message, message
        assert "must be nanoseconds" in message
    assert not any(i.kind == "stamp_step_implausible" for issues in _issues(scene, frames, 1) for i in issues)
