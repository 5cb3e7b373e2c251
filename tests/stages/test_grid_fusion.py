"""Sharded markov_prediction + grid fusion in-process: two shards fused give the one-process MotionGrid; a missing shard is counted."""

from __future__ import annotations

import numpy as np
import pytest

from bus_schemas import Header
from stages.ar_inference import ARInference, ARInferenceConfig
from stages.corridors import SceneMaps
from stages.intentions import IntentionsConfig
from stages.grid_fusion import GridFusion, GridFusionConfig
from stages.lib.datasets import DEFAULT_DATA_DIR, load_recording
from stages.lib.grid_fusion import fuse_motion_grids, parse_shard, shard_of
from stages.lib.markov import MarkovGridConfig, load_or_build_stencils
from stages.markov_prediction import MarkovPredictionConfig, MarkovPredictor
from stages.offline.chain import chain_frames

N_FRAMES = 3


def dense(grid):
    """{(k, x cell, y cell): value} of a MotionGrid, cells on the absolute lattice."""
    ox, oy = int(round(grid.origin_x_m / grid.cell_m)), int(round(grid.origin_y_m / grid.cell_m))
    return {(k, ox + int(c), oy + int(r)): float(v) for k, s in enumerate(grid.steps) for r, c, v in zip(s.rows, s.cols, s.values)}


@pytest.fixture(scope="module")
def frames():
    scene_maps = SceneMaps()
    recording = load_recording(DEFAULT_DATA_DIR, "k729_2022-03-16", ("019",))
    items = chain_frames(recording, recording.sequences[0], scene_maps, intentions=IntentionsConfig(), max_frames=58)
    ar = ARInference(ARInferenceConfig(), producer="ar_inference")
    out = []
    for n, item in enumerate(items):
        profiles = ar.process(item.corridor_set, item.relation_set, item.frame, item.scene)[0]
        shards = {shard_of(v.track_id, 2) for v in item.corridor_set.vehicles if v.corridors}
        if n >= 10 and shards == {0, 1}:  # frames with vehicles in both shards
            out.append((item, profiles))
        if len(out) == N_FRAMES:
            break
    assert len(out) == N_FRAMES
    return out


def _run(frames, shard: str):
    stencils = load_or_build_stencils(MarkovGridConfig())
    predictor = MarkovPredictor(MarkovPredictionConfig(mode="hybrid", shard=shard), stencils=stencils)
    grids, issues = [], []
    for item, profiles in frames:
        result = predictor.update({"corridor_set": item.corridor_set, "relation_set": item.relation_set, "scene": item.scene,
                                   "track_frame": item.frame, "intention_belief": item.belief, "acceleration_profiles": profiles})
        grids.append(result.outputs)
        issues += result.issues
    return grids, issues


def test_shard_parsing_and_hash_are_stable():
    assert parse_shard("") is None and parse_shard("1/2") == (1, 2)
    for bad in ("2/2", "-1/2", "a/b", "1", "0/0"):
        with pytest.raises(ValueError):
            parse_shard(bad)
    with pytest.raises(ValueError, match="i/n"):
        MarkovPredictionConfig(shard="3/2")
    assert [shard_of(t, 2) for t in (1, 2, 3, 4, 5)] == [shard_of(t, 2) for t in (1, 2, 3, 4, 5)]
    assert shard_of(17, 2) == __import__("zlib").crc32(b"17") % 2  # not Python's hash: stable across processes


def test_two_shards_fused_equal_one(frames):
    one, _ = _run(frames, "")
    a, issues_a = _run(frames, "0/2")
    b, issues_b = _run(frames, "1/2")
    assert not [i for i in issues_a + issues_b if i.kind == "unknown_corridor"]
    for full, x, y in zip(one, a, b):
        tracks = {p.track_id for p in full["corridor_predictions"].predictions}
        ta = {p.track_id for p in x["corridor_predictions"].predictions}
        tb = {p.track_id for p in y["corridor_predictions"].predictions}
        assert ta and tb and ta.isdisjoint(tb) and ta | tb == tracks  # each vehicle in exactly one shard
        # each message says whose vehicles it covers: the whole frame, or one shard's
        assert [(m["motion_grid"].shard, m["corridor_predictions"].shard) for m in (full, x, y)] == [("", ""), ("0/2", "0/2"), ("1/2", "1/2")]
        assert not any(m[o].missing_shards for m in (full, x, y) for o in ("motion_grid", "corridor_predictions"))
        g = full["motion_grid"]
        fused = fuse_motion_grids([x["motion_grid"], y["motion_grid"]], g.header)
        d1, d2 = dense(g), dense(fused)
        tolerance = 2 * g.min_value + 1e-6  # cells below a shard's min_value were not sent
        for key in set(d1) | set(d2):
            assert abs(d1.get(key, 0.0) - d2.get(key, 0.0)) <= tolerance, key
        assert len(set(d1) ^ set(d2)) <= 0.02 * len(d1)


class _Clock:
    def __init__(self):
        self.t = 0.0

    def __call__(self):
        return self.t


def test_fusion_waits_for_every_shard_and_degrades_when_one_is_down(frames):
    a, _ = _run(frames, "0/2")
    b, _ = _run(frames, "1/2")
    clock = _Clock()
    core = GridFusion(GridFusionConfig(shard_timeout_s=1.0), [0, 1], clock=clock)
    out = core.update({"grid_0": a[0]["motion_grid"]})
    assert "motion_grid" not in out.outputs  # shard 1 is up (start-up grace): wait for it
    out = core.update({"grid_0": a[0]["motion_grid"], "grid_1": b[0]["motion_grid"]})
    assert out.outputs["motion_grid"].header.stamp_ns == a[0]["motion_grid"].header.stamp_ns and not out.issues
    fused = out.outputs["motion_grid"]
    assert fused.shard == "" and fused.missing_shards == ()  # the whole frame: shard outputs fused
    # shard 1 goes quiet: after the timeout the frames come with shard 0's vehicles only, each counted
    clock.t = 0.5
    assert "motion_grid" not in core.update({"grid_0": a[1]["motion_grid"], "grid_1": b[0]["motion_grid"]}).outputs
    clock.t = 2.0
    out = core.update({"grid_0": a[2]["motion_grid"], "grid_1": b[0]["motion_grid"]})
    assert out.outputs["motion_grid"].header.stamp_ns == a[1]["motion_grid"].header.stamp_ns
    assert [i.kind for i in out.issues] == ["shard_missing"]
    # the message itself says so (a consumer cannot tell a missing shard from an empty road), and after a round trip
    fused = type(out.outputs["motion_grid"]).decode(out.outputs["motion_grid"].encode())
    assert fused.shard == "" and fused.missing_shards == ("1/2",)
    assert dense(out.outputs["motion_grid"]) == pytest.approx(dense(fuse_motion_grids([a[1]["motion_grid"]], a[1]["motion_grid"].header)))
    out = core.update({"grid_0": a[2]["motion_grid"]})
    assert out.outputs["motion_grid"].header.stamp_ns == a[2]["motion_grid"].header.stamp_ns
    assert [i.kind for i in out.issues] == ["shard_missing"]


def test_fused_predictions_and_grids_name_the_shards_they_lack(frames):
    """A shard whose grid cannot be fused, or whose predictions did not come, is named in ``missing_shards`` of that
    output; the labels are the shards' own ("i/n"), else i of the bound count for one never heard from."""
    import dataclasses

    a, _ = _run(frames, "0/3")
    grid0, preds0 = a[0]["motion_grid"], a[0]["corridor_predictions"]
    other = dataclasses.replace(grid0, cell_m=grid0.cell_m * 2, shard="1/3")  # a shard of another cell size
    core = GridFusion(GridFusionConfig(shard_timeout_s=1.0, max_pending_frames=1), [0, 1, 2], clock=_Clock())
    core._bound_predictions = frozenset({"predictions_0", "predictions_1", "predictions_2"})
    out = core.update({"grid_0": grid0, "predictions_0": preds0, "grid_1": other})
    assert "motion_grid" not in out.outputs  # shard 2 and shard 1's predictions still awaited
    later = dataclasses.replace(grid0, header=dataclasses.replace(grid0.header, stamp_ns=grid0.header.stamp_ns + 10**8))
    out = core.update({"grid_0": later})  # a newer frame waits beyond max_pending_frames: the first goes out as it is
    kinds = sorted(i.kind for i in out.issues)
    assert kinds == ["incompatible_grid", "shard_missing"]
    assert out.outputs["motion_grid"].missing_shards == ("1/3", "2/3")  # 1: its grid left out; 2: never heard from
    assert out.outputs["corridor_predictions"].missing_shards == ("1/3", "2/3")
    assert out.outputs["corridor_predictions"].shard == "" and out.outputs["motion_grid"].shard == ""
