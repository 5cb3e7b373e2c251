"""A tracker that stamps its frames in milliseconds (or microseconds) hears it from the corridors stage, in one issue
per frame that names the unit, instead of losing every vehicle downstream to out-of-range speeds in silence (found by
a new-user probe of the live input)."""

from __future__ import annotations

import dataclasses

from stages.corridors import CorridorBuilder, CorridorsConfig
from testkit.big_frames import real_frames


def _issues(scene, frames, divide: int) -> list:
    builder = CorridorBuilder(CorridorsConfig())
    found = []
    for frame in frames:
        header = dataclasses.replace(frame.header, stamp_ns=frame.header.stamp_ns // divide)
        found.append(builder.process(dataclasses.replace(frame, header=header), scene)[1])
    return found


def test_stamps_in_milliseconds_are_named_once_per_frame_and_nanoseconds_are_not():
    scene, frames = real_frames(6, run_id="t", map_sha256=True)
    for divide in (1_000_000, 1_000):  # milliseconds, microseconds
        per_frame = [[i for i in issues if i.kind == "stamp_step_implausible"] for issues in _issues(scene, frames, divide)]
        assert [len(f) for f in per_frame] == [0] + [1] * (len(frames) - 1)
        message = per_frame[1][0].detail
        assert f"advance {100_000_000 // divide} ns" in message and "10 Hz (100,000,000 ns a frame)" in message, message
        assert "must be nanoseconds" in message
    assert not any(i.kind == "stamp_step_implausible" for issues in _issues(scene, frames, 1) for i in issues)
