"""The corridors stage and a tracker's stamps (found by a new-user probe of the live input): stamps in milliseconds
(or microseconds) are named in one issue per frame, where every vehicle was lost downstream to out-of-range speeds in
silence; a frame that arrives after a newer one is skipped, where it reset every track."""

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


def test_a_frame_that_arrives_after_a_newer_one_is_skipped_and_the_tracks_go_on():
    # frames 0 1 2 4 3 5 on the bus: frame 3 arrived late. It gets no CorridorSet and one frame_late issue; the vehicles'
    # states are not reset (before: stamp_backwards, every track reset while the other stages kept theirs), so frame 5
    # gives byte for byte the CorridorSet of the frames 0 1 2 4 5 without frame 3. A step back of more than
    # LATE_FRAME_NS is a source that started over: reset, as before
    from stages.corridors.core import LATE_FRAME_NS

    scene, frames = real_frames(6, run_id="t", map_sha256=True)
    builder, skipped = CorridorBuilder(CorridorsConfig()), CorridorBuilder(CorridorsConfig())
    results = [builder.update({"track_frame": frames[k], "scene": scene}) for k in (0, 1, 2, 4, 3, 5)]
    late = results[4]
    assert "corridor_set" not in late.outputs and [i.kind for i in late.issues] == ["frame_late"], late.issues
    assert "frame 3 stamped 100 ms before the last one" in late.issues[0].detail
    assert not any(i.kind == "stamp_backwards" for r in results for i in r.issues)
    expected = [skipped.update({"track_frame": frames[k], "scene": scene}) for k in (0, 1, 2, 4, 5)][-1]
    assert results[-1].outputs["corridor_set"].encode() == expected.outputs["corridor_set"].encode()
    restart = dataclasses.replace(frames[0], header=dataclasses.replace(frames[0].header, stamp_ns=frames[5].header.stamp_ns - LATE_FRAME_NS - 1))
    assert any(i.kind == "stamp_backwards" for i in builder.update({"track_frame": restart, "scene": scene}).issues)
