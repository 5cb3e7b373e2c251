"""Corridors, relations, intentions and ar_inference: one vehicle's exception costs only that vehicle, not the frame.

Real frames of the embedded K729 sequence 019 (frame 41: cars 5711, 5720,
5753, 5761). Each core runs over frames 0..41 twice, the second time with a
stand-in failure for car 5711 at frame 41; the other cars' outputs at frame
41 are those of the clean run, and the failure is an issue.
"""

from __future__ import annotations

import numpy as np
import pytest

from stages.corridors import CorridorBuilder, CorridorsConfig, SceneMaps
from stages.lib.datasets import DEFAULT_DATA_DIR, load_recording
from stages.intentions import IntentionFilter, IntentionsConfig
from stages.offline.intentions_eval import chain_frames
from stages.relations import RelationExtractor, RelationsConfig

pytestmark = pytest.mark.skipif(
    not (DEFAULT_DATA_DIR / "maps").is_dir(), reason=f"embedded TAF-BW data not found at {DEFAULT_DATA_DIR}"
)

FRAME = 41
FAILING = 5711
OTHERS = (5720, 5753, 5761)


class Boom(RuntimeError):
    """The stand-in failure."""


@pytest.fixture(scope="module")
def scene_maps():
    return SceneMaps()


@pytest.fixture(scope="module")
def frames(scene_maps):
    recording = load_recording(DEFAULT_DATA_DIR, "k729_2022-03-16", ("019",))
    return chain_frames(recording, recording.sequences[0], scene_maps)[: FRAME + 1]


def _kinds(issues, track_id):
    return [i.kind for i in issues if i.agent_id == track_id]


def test_corridors(frames, scene_maps):
    def run(patch):
        builder = CorridorBuilder(CorridorsConfig(), scene_maps=scene_maps)
        for item in frames[:FRAME]:
            builder.process(item.frame, item.scene)
        if patch:
            corridors, failing = builder._corridors, builder._tracks[FAILING]

            def bad(scene_map, track, *args):
                if track is failing:
                    raise Boom("stand-in failure while building corridors")
                return corridors(scene_map, track, *args)

            builder._corridors = bad
        return builder.process(frames[FRAME].frame, frames[FRAME].scene)

    (clean, _), (dirty, issues) = run(False), run(True)
    assert _kinds(issues, FAILING) == ["vehicle_failed"]
    by_id = {v.track_id: v for v in dirty.vehicles}
    assert by_id[FAILING].status.name == "BAD_STATE" and not by_id[FAILING].corridors
    for v in clean.vehicles:
        if v.track_id in OTHERS:
            w = by_id[v.track_id]
            assert (w.status, w.lanelet_id, [c.corridor_id for c in w.corridors]) == (v.status, v.lanelet_id, [c.corridor_id for c in v.corridors])
            for a, b in zip(v.corridors, w.corridors):
                np.testing.assert_array_equal(a.x_m, b.x_m)
                assert a.vehicle_s_m == b.vehicle_s_m


def test_relations(frames, scene_maps):
    item = frames[FRAME]
    clean, _ = RelationExtractor(RelationsConfig(), scene_maps=scene_maps).process(item.frame, item.corridor_set, item.scene)
    extractor = RelationExtractor(RelationsConfig(), scene_maps=scene_maps)
    lateral = extractor._lateral

    def bad(pair, *args):
        if pair.vehicle.track_id == FAILING:
            raise Boom("stand-in failure of one pair's lateral relation")
        return lateral(pair, *args)

    extractor._lateral = bad
    dirty, issues = extractor.process(item.frame, item.corridor_set, item.scene)
    n = len(next(v for v in item.corridor_set.vehicles if v.track_id == FAILING).corridors)
    assert _kinds(issues, FAILING) == ["pair_failed"] * n
    assert not any(r.track_id == FAILING for r in dirty.relations)
    others = [r for r in clean.relations if r.track_id != FAILING]
    assert len(others) == len(dirty.relations)
    for a, b in zip(others, dirty.relations):
        assert (a.track_id, a.corridor_id, a.leader_track_id, a.leader_gap_m) == (b.track_id, b.corridor_id, b.leader_track_id, b.leader_gap_m)
        np.testing.assert_array_equal(a.object_track_ids, b.object_track_ids)


def test_intentions(frames, scene_maps, monkeypatch):
    import stages.intentions.core as core

    def run():
        intentions = IntentionFilter(IntentionsConfig(), scene_maps=scene_maps)
        for item in frames[:FRAME]:
            intentions.process(item.frame, item.corridor_set, item.relation_set, item.scene)
        return intentions

    last = frames[FRAME]
    clean, _ = run().process(last.frame, last.corridor_set, last.relation_set, last.scene)
    intentions = run()
    build = core.build_tables

    def bad(inputs, *args, **kwargs):
        if any(i.track_id == FAILING for i in inputs):
            raise Boom("stand-in failure of the batched filter for one vehicle")
        return build(inputs, *args, **kwargs)

    monkeypatch.setattr(core, "build_tables", bad)
    dirty, issues = intentions.process(last.frame, last.corridor_set, last.relation_set, last.scene)
    assert _kinds(issues, FAILING) == ["vehicle_failed"]
    assert FAILING not in intentions.tracked_ids
    a = {v.track_id: v for v in clean.vehicles}
    b = {v.track_id: v for v in dirty.vehicles}
    assert set(b) == set(OTHERS)
    for track in OTHERS:
        assert [(c.corridor_id, c.probability, c.s_mean_m, c.v_mean_mps) for c in a[track].corridors] == \
               [(c.corridor_id, c.probability, c.s_mean_m, c.v_mean_mps) for c in b[track].corridors]


def test_ar_inference(frames, monkeypatch):
    import stages.lib.ar.features as features
    from stages.ar_inference import ARInference, ARInferenceConfig

    clean_core = ARInference(ARInferenceConfig())
    dirty_core = ARInference(ARInferenceConfig(), model=clean_core.model)
    for item in frames[:FRAME]:
        for core in (clean_core, dirty_core):
            core.observe(item.corridor_set, item.relation_set, item.frame)
    last = frames[FRAME]
    clean, _ = clean_core.process(last.corridor_set, last.relation_set, last.frame, last.scene)
    failing = {id(c) for v in last.corridor_set.vehicles if v.track_id == FAILING for c in v.corridors}
    compute = features.pair_features

    def bad(corridors, *args):  # the frame's batch fails while it holds the corridor; then each pair is computed alone
        if any(id(c) in failing for c in corridors):
            raise Boom("stand-in failure of one corridor's features")
        return compute(corridors, *args)

    monkeypatch.setattr(features, "pair_features", bad)
    dirty, issues = dirty_core.process(last.corridor_set, last.relation_set, last.frame, last.scene)
    assert _kinds(issues, FAILING) == ["pair_failed"] * len(failing)
    a = {(p.track_id, p.corridor_id): p for p in clean.profiles}
    b = {(p.track_id, p.corridor_id): p for p in dirty.profiles}
    others = [k for k in a if k[0] in OTHERS]
    assert others
    for key in others:
        np.testing.assert_array_equal(a[key].input_probs, b[key].input_probs)
