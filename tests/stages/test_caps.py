"""Bounded work per message (issue 13, item 3): caps on objects and pairs per frame.

A well-formed 1,000-object TrackFrame (copies of real K729 sequence 013
cars, ``testkit/big_frames.py``) through corridors and relations in-process:
each finishes, returns outputs for the objects within the cap (nearest to
the map's centre) and counts one ``objects_capped`` issue. The real
sequence itself is never capped, and the distance pruning of the relations'
projection changes nothing. No wall-clock or RSS assertions (the figures are
in ``bench/hostile.py --section big-frame``).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from bus_schemas import MatchStatus
from stages.lib.caps import keep_nearest
from stages.corridors import CorridorBuilder, CorridorsConfig, SceneMaps
from stages.lib.datasets import DEFAULT_DATA_DIR
from stages.relations import RelationExtractor, RelationsConfig
from stages.relations import core as relations_core
from testkit.big_frames import big_frames, real_frames

pytestmark = pytest.mark.skipif(
    not (DEFAULT_DATA_DIR / "maps").is_dir(), reason=f"embedded TAF-BW data not found at {DEFAULT_DATA_DIR}"
)

N = 1000


@pytest.fixture(scope="module")
def source():
    return real_frames()


@pytest.fixture(scope="module")
def scene_maps():
    return SceneMaps()


@pytest.fixture(scope="module")
def big(source, scene_maps):
    scene, frames = big_frames(N, 2, source=source)
    builder = CorridorBuilder(CorridorsConfig(), scene_maps=scene_maps)
    results = [builder.process(f, scene) for f in frames]
    return scene, frames, results


def test_keep_nearest_rule():
    xy = np.array([[10.0, 0.0], [1.0, 0.0], [np.nan, 0.0], [2.0, 0.0], [1.0, 0.0]])
    kept, dropped = keep_nearest(xy, np.zeros(2), 3)
    assert dropped == 2 and kept.tolist() == [False, True, False, True, True]
    kept, dropped = keep_nearest(xy, np.zeros(2), 5)
    assert dropped == 0 and kept.all()


def test_corridors_big_frame_capped(big):
    scene, frames, results = big
    cap = CorridorsConfig().max_objects
    corridor_set, issues = results[-1]
    assert len(corridor_set.vehicles) == N  # one entry per object, in frame order, never dropped
    capped = [i for i in issues if i.kind == "objects_capped"]
    assert len(capped) == 1 and capped[0].detail.startswith(f"{N - cap} of {N} objects")
    with_corridors = [v for v in corridor_set.vehicles if v.corridors]
    assert 0 < len(with_corridors) <= cap
    matched = sum(v.status is MatchStatus.MATCHED for v in corridor_set.vehicles)
    assert matched == len(with_corridors)
    # the dropped ones are the farthest from the map's centre: BAD_STATE without corridors
    assert sum(v.status is MatchStatus.BAD_STATE and not v.corridors for v in corridor_set.vehicles) >= N - cap
    assert all(len(v.corridors) <= CorridorsConfig().max_corridors_per_vehicle for v in corridor_set.vehicles)


def test_relations_big_frame_capped(big, scene_maps):
    scene, frames, results = big
    extractor = RelationExtractor(RelationsConfig(), scene_maps=scene_maps)
    relation_set, issues = extractor.process(frames[-1], results[-1][0], scene)
    kinds = [i.kind for i in issues]
    assert kinds.count("objects_capped") == 1
    assert "pair_failed" not in kinds and "conflicts_failed" not in kinds
    pairs = sum(len(v.corridors) for v in results[-1][0].vehicles)
    assert 0 < len(relation_set.relations) <= min(pairs, RelationsConfig().max_pairs)
    related = {r.track_id for r in relation_set.relations}
    with_corridors = {v.track_id for v in results[-1][0].vehicles if v.corridors}
    assert related <= with_corridors


def test_relations_pairs_cap(big, scene_maps):
    scene, frames, results = big
    extractor = RelationExtractor(RelationsConfig(max_pairs=50), scene_maps=scene_maps)
    relation_set, issues = extractor.process(frames[-1], results[-1][0], scene)
    assert [i.kind for i in issues].count("pairs_capped") == 1
    assert 0 < len(relation_set.relations) <= 50


def test_real_sequence_never_capped_and_pruning_changes_nothing(source, scene_maps, monkeypatch):
    scene, frames = source
    frames = frames[:150]
    builder = CorridorBuilder(CorridorsConfig(), scene_maps=scene_maps)
    sets = []
    for f in frames:
        corridor_set, issues = builder.process(f, scene)
        assert not [i for i in issues if i.kind.endswith("_capped")]
        sets.append(corridor_set)

    def run():
        extractor = RelationExtractor(RelationsConfig(), scene_maps=scene_maps)
        out = []
        for f, corridor_set in zip(frames, sets):
            relation_set, issues = extractor.process(f, corridor_set, scene)
            assert not [i for i in issues if i.kind.endswith("_capped")]
            out.append(relation_set.encode())
        return out

    pruned = run()
    monkeypatch.setattr(RelationExtractor, "_reach", lambda self, pairs: None)  # project every object on every corridor
    assert run() == pruned
    monkeypatch.setattr(relations_core, "_CHUNK_ELEMENTS", 1 << 10)  # many small chunks (projection and conflict lookups)
    assert run() == pruned
    monkeypatch.setattr(relations_core, "_CHUNK_ELEMENTS", 1)  # one row per block
    assert run() == pruned


@pytest.fixture(scope="module")
def big_relations(big, scene_maps):
    scene, frames, results = big
    extractor = RelationExtractor(RelationsConfig(), scene_maps=scene_maps)
    return extractor.process(frames[-1], results[-1][0], scene)[0]


def test_intentions_pairs_cap(big, big_relations, scene_maps):
    from stages.intentions import IntentionFilter, IntentionsConfig

    scene, frames, results = big
    belief, issues = IntentionFilter(IntentionsConfig(max_pairs=30), scene_maps=scene_maps).process(frames[-1], results[-1][0], big_relations, scene)
    assert [i.kind for i in issues].count("pairs_capped") == 1
    assert 0 < len(belief.vehicles) <= 30  # at least one corridor per vehicle: at most 30 vehicles


def test_ar_inference_pairs_cap(big, big_relations):
    from stages.ar_inference import ARInference, ARInferenceConfig

    scene, frames, results = big
    profiles, issues = ARInference(ARInferenceConfig(max_pairs=30)).process(results[-1][0], big_relations, frames[-1], scene)
    assert [i.kind for i in issues].count("pairs_capped") == 1
    assert 0 < len(profiles.profiles) <= 30


def test_markov_prediction_pairs_cap(big, big_relations):
    from stages.markov_prediction import MarkovPredictionConfig, MarkovPredictor

    scene, frames, results = big
    predictor = MarkovPredictor(MarkovPredictionConfig(max_pairs=20, corridor_weights="uniform", initial_box="measurement"))
    prediction, issues = predictor.process(results[-1][0], big_relations, scene, frames[-1])
    kinds = [i.kind for i in issues]
    assert kinds.count("pairs_capped") == 1 and "unknown_corridor" not in kinds
    assert 0 < len({(p.track_id, p.corridor_id) for p in prediction.pairs}) <= 20
    assert "grid_capped" not in kinds


def test_markov_prediction_grid_cap(big, big_relations):
    from bus_schemas import Header
    from stages.markov_prediction import MarkovPredictionConfig, MarkovPredictor

    scene, frames, results = big
    config = MarkovPredictionConfig(max_pairs=20, grid_max_cells_per_step=50, corridor_weights="uniform", initial_box="measurement")
    prediction, issues = MarkovPredictor(config).process(results[-1][0], big_relations, scene, frames[-1])
    assert [i.kind for i in issues].count("grid_capped") == 1
    header = Header(run_id="t", frame_index=0, stamp_ns=0, producer="markov_prediction")
    over = prediction.grid_cells_over_cap()
    grid = prediction.motion_grid(header, scene.scene_id)
    assert all(len(step.values) <= 50 for step in grid.steps) and any(len(step.values) == 50 for step in grid.steps)
    # the cells above the floor are found once per prediction: cutting one message leaves them as they were
    assert prediction.motion_grid(header, scene.scene_id).encode() == grid.encode()
    assert prediction.grid_cells_over_cap() == over > 0


def test_max_corridors_per_vehicle_enforced(source, scene_maps):
    scene, frames = source
    builder = CorridorBuilder(CorridorsConfig(max_corridors_per_vehicle=1), scene_maps=scene_maps)
    truncated = 0
    for f in frames[:100]:
        corridor_set, issues = builder.process(f, scene)
        assert all(len(v.corridors) <= 1 for v in corridor_set.vehicles)
        truncated += sum(i.kind == "corridors_truncated" for i in issues)
    assert truncated > 0  # K729 013 has cars with two or more corridors
