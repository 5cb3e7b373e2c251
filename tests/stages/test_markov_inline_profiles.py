"""hybrid_profiles = "inline": markov_prediction runs the AR model itself (the ar_inference stage's core) on the frame's
corridor set, relation set and track frame, so that a pipeline needs no ar_inference stage (pipelines/inline.toml): the
same profiles, the same outputs, one process and one bus hop fewer."""

from __future__ import annotations

from pathlib import Path

import pytest

from stages.ar_inference import ARInference, ARInferenceConfig
from stages.corridors import SceneMaps
from stages.intentions import IntentionsConfig
from stages.lib.datasets import DEFAULT_DATA_DIR, DEFAULT_RECORDING, DEFAULT_SEQUENCE, load_recording
from stages.markov_prediction import MarkovPredictionConfig, MarkovPredictor
from stages.offline.chain import chain_frames

FRAMES = 30


@pytest.fixture(scope="module")
def frames():
    """The first frames of the embedded default scenario through the offline chain (corridors, relations, intentions)."""
    recording = load_recording(Path(DEFAULT_DATA_DIR), DEFAULT_RECORDING, (DEFAULT_SEQUENCE,))
    items = chain_frames(recording, recording.sequences[0], SceneMaps(data=Path(DEFAULT_DATA_DIR)), intentions=IntentionsConfig(), max_frames=FRAMES)
    assert len(items) == FRAMES and all(i.corridor_set is not None and i.relation_set is not None for i in items)
    return items


@pytest.fixture(scope="module")
def stencils():
    return MarkovPredictor(MarkovPredictionConfig(mode="hybrid")).stencils


def _inputs(item) -> dict:
    return {"corridor_set": item.corridor_set, "relation_set": item.relation_set, "scene": item.scene, "track_frame": item.frame,
            "intention_belief": item.belief}


def test_config_checks():
    assert MarkovPredictionConfig(hybrid_profiles="inline").hybrid_profiles == "inline"
    with pytest.raises(ValueError, match="frame, previous or inline"):
        MarkovPredictionConfig(hybrid_profiles="own")
    assert MarkovPredictor(MarkovPredictionConfig(mode="baseline", hybrid_profiles="inline"))._inline_ar is None  # hybrid only
    with pytest.raises(ValueError, match='ar_model.*"inline" only'):
        MarkovPredictionConfig(ar_model="weights.pt")  # read by nothing in the frame mode: said, not ignored
    with pytest.raises(Exception, match="no such weights file"):  # a bad path stops the stage at its start, with its name
        MarkovPredictor(MarkovPredictionConfig(mode="hybrid", hybrid_profiles="inline", ar_model="/nonexistent/w.pt"))


def test_inline_gives_the_outputs_of_the_ar_stage_and_markov_prediction_apart(frames, stencils, monkeypatch):
    """Frame by frame, on the bus's path (prepare with everything but the belief, then update): the inline stage's
    MotionGrid and CorridorPredictions are byte for byte those of the frame mode given the ar_inference stage's
    profiles of the same frames, its acceleration_profiles that stage's profiles (but for the producer), and the AR
    model runs once per frame."""
    ar = ARInference(ARInferenceConfig(), producer="markov_prediction")
    apart = MarkovPredictor(MarkovPredictionConfig(mode="hybrid"), stencils=stencils)
    inline = MarkovPredictor(MarkovPredictionConfig(mode="hybrid", hybrid_profiles="inline"), stencils=stencils)
    runs = []
    real = inline._inline_ar.process
    monkeypatch.setattr(inline._inline_ar, "process", lambda *a, **k: runs.append(1) or real(*a, **k))
    grids = 0
    for n, item in enumerate(frames):
        profiles, _ = ar.process(item.corridor_set, item.relation_set, item.frame)
        want = apart.update(dict(_inputs(item), acceleration_profiles=profiles))
        partial = {k: v for k, v in _inputs(item).items() if k != "intention_belief"}
        assert inline.prepare(partial, {"intention_belief"}) is True  # the chain (and the AR model) before the belief
        got = inline.update(_inputs(item))
        assert len(runs) == n + 1  # once per frame: update took the prepared chain
        for port in ("motion_grid", "corridor_predictions"):
            assert got.outputs[port].encode() == want.outputs[port].encode(), (n, port)
        mine = got.outputs["acceleration_profiles"]
        assert mine.header == profiles.header and mine.encode() == profiles.encode()
        assert [i.kind for i in got.issues] == [i.kind for i in want.issues]
        grids += bool(got.outputs["motion_grid"].steps)
    assert grids > FRAMES // 2  # vehicles were predicted
    assert "acceleration_profiles" not in want.outputs  # the frame mode publishes none


def test_the_inline_model_predicts_over_the_stages_own_input_cells(frames):
    """A stage with other input cells than the defaults gets profiles over its cells (the ar_inference stage must be
    told them; inline they are the stage's own): no bad_profile."""
    cells = {"input_min_mps2": -4.0, "input_max_mps2": 3.0, "n_inputs": 14}
    inline = MarkovPredictor(MarkovPredictionConfig(mode="hybrid", hybrid_profiles="inline", **cells))
    out = inline.update(_inputs(frames[10]))
    profiles = out.outputs["acceleration_profiles"]
    assert len(profiles.input_edges_mps2) == 15 and profiles.input_edges_mps2[0] == -4.0 and profiles.profiles
    assert "bad_profile" not in [i.kind for i in out.issues]


def test_given_profiles_are_read_and_the_model_is_not_run(frames, stencils):
    """A set that holds the frame's profiles (iamp eval, whose AR stage sees every frame; a pipeline that binds them)
    is predicted from those, as the frame mode does: the stage's own AR model does not run and publishes nothing."""
    item = frames[0]
    profiles, _ = ARInference(ARInferenceConfig()).process(item.corridor_set, item.relation_set, item.frame)
    inline = MarkovPredictor(MarkovPredictionConfig(mode="hybrid", hybrid_profiles="inline"), stencils=stencils)
    out = inline.update(dict(_inputs(item), acceleration_profiles=profiles))
    assert inline._inline_last is None and "acceleration_profiles" not in out.outputs
    frame = MarkovPredictor(MarkovPredictionConfig(mode="hybrid"), stencils=stencils).update(dict(_inputs(item), acceleration_profiles=profiles))
    assert out.outputs["motion_grid"].encode() == frame.outputs["motion_grid"].encode()


def test_a_failing_ar_model_costs_the_frame_its_profiles_only(frames, stencils, monkeypatch):
    inline = MarkovPredictor(MarkovPredictionConfig(mode="hybrid", hybrid_profiles="inline"), stencils=stencils)

    def boom(*_a, **_k):
        raise RuntimeError("weights gone")

    monkeypatch.setattr(inline._inline_ar, "process", boom)
    out = inline.update(_inputs(frames[5]))
    kinds = [i.kind for i in out.issues]
    assert kinds.count("inline_ar_failed") == 1 and "weights gone" in next(i.detail for i in out.issues if i.kind == "inline_ar_failed")
    assert "motion_grid" in out.outputs and "acceleration_profiles" not in out.outputs
    inline.reset()
    assert inline._inline_last is None


def test_the_inline_pipeline_predicts_every_frame_on_the_bus(tmp_path):
    """pipelines/inline.toml: no ar_inference stage; markov_prediction predicts every frame in mode hybrid and
    publishes the profiles it computed, one message per frame."""
    import bus_schemas as bs
    from stages.recorder.inspect import read_messages
    from tests.integration.test_launch_run import _last_stats, run_pipeline_k729

    rec, counts = run_pipeline_k729("inline", "inl", tmp_path)
    assert counts["iamp/inl/markov_prediction/acceleration_profiles"] == counts["iamp/inl/source/track_frame"], counts
    assert not [t for t in counts if "/ar_inference/" in t], counts
    profiles = [bs.decode(m.data) for m in read_messages(str(rec)) if m.topic == "iamp/inl/markov_prediction/acceleration_profiles"]
    assert sum(len(p.profiles) for p in profiles) > 0
    st = _last_stats(rec, "markov_prediction")
    assert st.counters["core_errors"] == 0 and st.counters["prepared"] > 0, st.counters
    assert "inline_ar_failed" not in st.issues_by_kind, st.issues_by_kind
