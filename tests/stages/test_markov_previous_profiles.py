"""hybrid_profiles = "previous": markov_prediction's chain reads the AR profiles of the frame before, so it can run
before the frame's own come (pipelines/pipelined.toml binds them as the latest value ``previous_profiles``)."""

from __future__ import annotations

import numpy as np
import pytest

from stages.markov_prediction import MarkovPredictionConfig, MarkovPredictor
from tests.stages.test_markov_prediction import PLAIN, STAMP, _corridor, _corridor_set, _profiles, _relation, _relation_set, _vehicle

DT = 100_000_000  # one frame at 10 Hz
ONE = {"hybrid_curve_factors": (), "hybrid_initial_input": "ar", **PLAIN}  # no online learning: frames comparable one by one


@pytest.fixture(scope="module")
def stencils():
    return MarkovPredictor(MarkovPredictionConfig(**PLAIN)).stencils


def _frame(n: int):
    stamp = STAMP + n * DT
    return stamp, _corridor_set(_vehicle(1, 8.0, [_corridor(7, vehicle_s=5.0 + 0.8 * n)]), stamp=stamp)


def test_config_checks():
    assert MarkovPredictionConfig().hybrid_profiles == "frame"
    with pytest.raises(ValueError, match="hybrid_profiles"):
        MarkovPredictionConfig(hybrid_profiles="last")
    for bad in (0.0, -1.0, float("nan")):
        with pytest.raises(ValueError, match="hybrid_previous_max_age_s"):
            MarkovPredictionConfig(hybrid_previous_max_age_s=bad)


def test_the_chain_reads_the_profiles_of_the_frame_before_within_the_age_limit(stencils):
    """Frame n's chain with "previous" is frame n's chain with "frame" given frame n-1's profiles; the first frame (none
    before) and a frame whose last profiles are older than hybrid_previous_max_age_s hold the measured acceleration,
    as "frame" without profiles does."""
    prev = MarkovPredictor(MarkovPredictionConfig(mode="hybrid", hybrid_profiles="previous", **ONE), stencils=stencils)
    frame = MarkovPredictor(MarkovPredictionConfig(mode="hybrid", **ONE), stencils=stencils)
    accels = [1.5, -2.0, 0.5]
    for n, accel in enumerate(accels):
        stamp, cs = _frame(n)
        got, issues = prev.process(cs, acceleration_profiles=_profiles(1, 7, accel, stamp=stamp))
        before = _profiles(1, 7, accels[n - 1], stamp=stamp) if n else None
        want, _ = frame.process(cs, acceleration_profiles=before)
        np.testing.assert_array_equal(got.mean_s_m, want.mean_s_m)
        assert not [i for i in issues if i.kind == "stamp_mismatch"], issues
    # differs from reading its own: the first frame's profile said +1.5, the second's -2
    own, _ = frame.process(_frame(1)[1], acceleration_profiles=_profiles(1, 7, -2.0, stamp=_frame(1)[0]))
    again, _ = MarkovPredictor(MarkovPredictionConfig(mode="hybrid", **ONE), stencils=stencils).process(
        _frame(1)[1], acceleration_profiles=_profiles(1, 7, 1.5, stamp=_frame(1)[0]))
    assert not np.allclose(own.mean_s_m, again.mean_s_m)
    # too old: 3 frames later (0.3 s > 0.25 s) the last profiles (of frame 2) are not read
    stamp, cs = _frame(5)
    got, _ = prev.process(cs, acceleration_profiles=None)
    want, _ = frame.process(cs, acceleration_profiles=None)
    np.testing.assert_array_equal(got.mean_s_m, want.mean_s_m)
    prev.reset()  # a new sequence forgets them
    assert not prev._recent_profiles


def _inputs(n: int, with_profiles: bool, port: str = "acceleration_profiles") -> dict:
    stamp, cs = _frame(n)
    out = {"corridor_set": cs, "relation_set": _relation_set(_relation(1, 7), stamp=stamp)}
    if with_profiles:
        out[port] = _profiles(1, 7, 0.5 * n, stamp=stamp)
    return out


def test_prepare_runs_the_chain_before_the_frames_profiles_and_once(stencils, monkeypatch):
    """On the bus: with "previous" the chain of a frame runs as soon as everything but the belief and the profiles is
    in; the frame's profiles coming after do not run it again, and update takes it."""
    prev = MarkovPredictor(MarkovPredictionConfig(mode="hybrid", hybrid_profiles="previous", **ONE), stencils=stencils)
    plain = MarkovPredictor(MarkovPredictionConfig(mode="hybrid", **ONE), stencils=stencils)
    calls = []
    real = prev._chain_phase
    monkeypatch.setattr(prev, "_chain_phase", lambda *a, **k: calls.append(1) or real(*a, **k))
    prev.update(_inputs(0, True))
    assert len(calls) == 1
    partial = _inputs(1, False)
    plain_calls = []
    plain_real = plain._chain_phase
    monkeypatch.setattr(plain, "_chain_phase", lambda *a, **k: plain_calls.append(1) or plain_real(*a, **k))
    plain.prepare(partial, {"intention_belief", "acceleration_profiles"})
    assert plain_calls == []  # "frame": the pairs only, the chain waits for the frame's profiles
    assert prev.prepare(partial, {"intention_belief", "acceleration_profiles"}) is True
    full = dict(partial, acceleration_profiles=_profiles(1, 7, 0.5, stamp=_frame(1)[0]))
    assert prev.prepare(full, {"intention_belief"}) is False  # (already run)
    result = prev.update(full)
    assert len(calls) == 2 and "motion_grid" in result.outputs
    reference = MarkovPredictor(MarkovPredictionConfig(mode="hybrid", **ONE), stencils=stencils)
    want, _ = reference.process(partial["corridor_set"], partial["relation_set"], acceleration_profiles=_profiles(1, 7, 0.0, stamp=_frame(1)[0]))
    got = result.outputs["corridor_predictions"]
    assert got.header.stamp_ns == _frame(1)[0]
    np.testing.assert_allclose(np.asarray(got.predictions[0].mean_s_m, np.float64), want.mean_s_m[0], rtol=1e-6)


def test_the_latest_value_port_feeds_previous_and_is_said_unused_otherwise(stencils):
    prev = MarkovPredictor(MarkovPredictionConfig(mode="hybrid", hybrid_profiles="previous", **ONE), stencils=stencils)
    prev.update(_inputs(0, True, port="previous_profiles"))
    assert list(prev._recent_profiles) == [_frame(0)[0]]
    frame = MarkovPredictor(MarkovPredictionConfig(mode="hybrid", **ONE), stencils=stencils)
    kinds = [[i.kind for i in frame.update(_inputs(n, True, port="previous_profiles")).issues] for n in range(3)]
    assert [k.count("profiles_port_unused") for k in kinds] == [1, 0, 0]  # said once
    assert not frame._recent_profiles


def test_iamp_eval_feeds_the_chain_the_frame_befores_profiles():
    """With hybrid_profiles "previous" the evaluation runs the AR stage at every frame (as on the bus) and each
    instant's chain reads the frame before's profiles: only an instant with no frame before it goes without."""
    from stages.lib.datasets import DEFAULT_DATA_DIR, DEFAULT_RECORDING, DEFAULT_SEQUENCE
    from stages.offline.evaluation import EvalConfig, Evaluation

    def run(params):
        config = EvalConfig(data_dir=DEFAULT_DATA_DIR, recordings=(DEFAULT_RECORDING,), sequences=(DEFAULT_SEQUENCE,), stride_s=0.8,
                            max_frames_per_sequence=300, progress=False, modes=("hybrid",), params=params)
        evaluation = Evaluation(config)
        return evaluation.run()["modes"]["hybrid"], evaluation.predictors["hybrid"]

    prev, predictor = run((("hybrid_profiles", "previous"),))
    frame, _ = run(())
    assert prev["overall"]["windows"] == frame["overall"]["windows"] > 0
    assert prev["overall"]["mADE_m"] != frame["overall"]["mADE_m"]
    assert prev["issues"].get("no_acceleration_profiles", 0) <= 1 and "no_acceleration_profiles" not in frame["issues"]
    assert predictor.previous_profiles and predictor._recent_profiles  # kept from the frames between the instants too


def test_the_pipelined_pipeline_predicts_every_frame_on_the_bus(tmp_path):
    """pipelines/pipelined.toml: markov_prediction with previous_profiles as a latest value predicts every frame
    (none waits for, or is lost for want of, its own profiles), in mode hybrid, with no issue of the binding."""
    import bus_schemas as bs
    from stages.recorder.inspect import read_messages
    from tests.integration.test_launch_run import _last_stats, run_pipeline_k729

    rec, _counts = run_pipeline_k729("pipelined", "pipe", tmp_path)
    grids = [bs.decode(m.data) for m in read_messages(str(rec)) if m.topic == "iamp/pipe/markov_prediction/motion_grid"]
    assert {g.mode for g in grids} == {"hybrid"}
    st = _last_stats(rec, "markov_prediction")
    assert st.counters["join_drops"] == 0 and st.counters["core_errors"] == 0, st.counters
    assert "profiles_port_unused" not in st.issues_by_kind and st.counters["prepared"] > 0, (st.issues_by_kind, st.counters)
