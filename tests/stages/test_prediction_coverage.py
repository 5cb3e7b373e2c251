"""Whose vehicles a prediction covers, said where people read it: the message, the viewer's panel, Foxglove's log.

A fused MotionGrid with a shard missing used to look like an empty road: a planner could not tell "no vehicle
there" from "nobody predicted the vehicles there". Since MotionGrid and CorridorPredictions v3 a shard's own output
says ``shard = "i/n"`` and a fused frame lists the shards it lacks in ``missing_shards``
(tests/stages/test_grid_fusion.py and tests/integration/test_sharded_markov.py check grid_fusion and the shards
fill them in). Here: the words (``bus_schemas.coverage``), the viewer's status line and the Foxglove bridge's
``/<node>/coverage`` log, which says each change once, not each frame.
"""

from __future__ import annotations

import dataclasses

import pytest

import bus_schemas as bs
from testkit import samples
from stages.viewer.model import InputSet


def _grid(**kw) -> bs.MotionGrid:
    return dataclasses.replace(samples.motion_grid(), **{"shard": "", "missing_shards": (), **kw})


def test_the_words_for_a_whole_a_shards_and_a_partial_frame():
    assert bs.coverage(_grid()) == "" and bs.coverage(None) == ""
    assert bs.coverage(_grid(shard="0/2")) == "shard 0/2's vehicles only"
    assert bs.coverage(_grid(missing_shards=("2/3", "1/3"))) == "shard 1/3, 2/3 missing"
    preds = dataclasses.replace(samples.corridor_predictions(), shard="", missing_shards=("0/2",))
    assert bs.coverage(_grid(), preds) == "shard 0/2 missing"  # one frame's messages read together


def test_the_viewer_says_it_on_the_status_line():
    frame = samples.track_frame(3)
    whole = InputSet(stamp_ns=1, frame_index=0, track_frame=frame, grid=_grid())
    assert whole.coverage == ""
    partial = dataclasses.replace(whole, grid=_grid(missing_shards=("1/2",)))
    assert partial.coverage == "predictions: shard 1/2 missing: other vehicles not predicted"
    assert "0/2" in dataclasses.replace(whole, grid=_grid(shard="0/2")).coverage


def test_foxglove_logs_each_change_of_coverage_once(tmp_path):
    foxglove = pytest.importorskip("foxglove")
    from stages.foxglove_bridge.scene import FoxgloveScene

    context = foxglove.Context()
    writer = foxglove.open_mcap(str(tmp_path / "x.mcap"), context=context)
    try:
        scene = FoxgloveScene(context)
        sequence = [(), ("1/2",), ("1/2",), ("1/2",), (), ()]  # whole, a shard down for three frames, back
        for n, missing in enumerate(sequence):
            scene.add("iamp/r/fusion/motion_grid", _grid(missing_shards=missing), 10 + n)
    finally:
        writer.close()
    assert scene.counts.logged.get("/fusion/coverage") == 2  # the shard lost, then back: two lines, not one per frame
    assert scene.counts.logged.get("/fusion/motion_grid") == len(sequence)
