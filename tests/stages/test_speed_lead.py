"""hybrid_speed_leads_s (curve_choice.OnlineLeadChoice): a moving pair's chain starts at v0 + L·a (a the corridors
stage's estimated acceleration), L chosen online by back testing the candidates on the cars the stage predicts."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest

import bus_schemas as bs
from stages.markov_prediction import MarkovPredictionConfig, MarkovPredictor
from stages.markov_prediction.curve_choice import OnlineLeadChoice
from tests.stages.test_markov_prediction import PLAIN, STAMP, _corridor, _corridor_set, _header, _drive_choice, _profiles, _vehicle, _with_failing_back_test

AR0 = {"hybrid_initial_input": "ar", "hybrid_curve_factors": (), **PLAIN}
OFF = {**AR0, "hybrid_speed_leads_s": ()}
LEADS = (0.0, 0.4, 0.8)


@pytest.fixture(scope="module")
def stencils():
    return MarkovPredictor(MarkovPredictionConfig(**PLAIN)).stencils


def test_config_checks():
    assert MarkovPredictionConfig().hybrid_speed_leads_s == (0.0, 0.2, 0.4, 0.8)  # on by default (docs/evaluation.md "Online speed lead")
    assert MarkovPredictor(MarkovPredictionConfig(mode="hybrid", hybrid_speed_leads_s=(), **PLAIN)).lead_choice is None
    assert MarkovPredictor(MarkovPredictionConfig(mode="baseline", **PLAIN)).lead_choice is None
    for bad in ((0.4,), (0.0, math.nan), (0.0, -0.2), (0.0, "x"), (0.0, True)):
        with pytest.raises(ValueError, match="hybrid_speed_leads_s"):
            MarkovPredictionConfig(mode="hybrid", hybrid_speed_leads_s=bad)
    with pytest.raises(ValueError, match="hybrid_speed_leads_s"):
        OnlineLeadChoice((0.0, math.inf), 0.4 * np.arange(1, 11))
    assert OnlineLeadChoice((0.4, 0.0), 0.4 * np.arange(1, 11)).factor == 0.0  # the estimate as it is until the evidence says


def _scene(stamp: int, s_now: float, speed: float, accel: float):
    """A car at ``speed`` (estimated acceleration ``accel``) at arc length ``s_now`` of a straight corridor (x = s)."""
    corridor = _corridor(7, vehicle_s=s_now, length=600.0, limit=20.0)
    vehicle = dataclasses.replace(_vehicle(1, speed, [corridor]), accel_mps2=accel)
    cs = _corridor_set(vehicle, stamp=stamp)
    frame = bs.TrackFrame(header=_header(stamp), scene_id="test", track_ids=np.array([1], np.int64), agent_types=np.array([1], np.uint8),
                          x_m=np.array([s_now]), y_m=np.array([0.0]), vx_mps=np.array([math.nan]), vy_mps=np.array([math.nan]),
                          yaw_rad=np.array([0.0]), length_m=np.array([4.5]), width_m=np.array([1.8]))
    return cs, frame


def _fixed(lead: float, stencils) -> MarkovPredictor:
    p = MarkovPredictor(MarkovPredictionConfig(mode="hybrid", **OFF), stencils=stencils)
    p.speed_lead = lead  # (no choice: the pairs get this lead on every frame)
    return p


def test_a_lead_moves_the_start_speed_by_lead_times_the_estimated_acceleration(stencils):
    """The chain of a car at 8 m/s estimated to accelerate at 1 m/s² with lead 0.8 s starts as the same car at 8.8 m/s
    without one; a car without an estimated acceleration, or a standing one, is not moved."""
    stamp = STAMP
    led, plain = _fixed(0.8, stencils), _fixed(0.0, stencils)
    cs, frame = _scene(stamp, 10.0, 8.0, 1.0)
    got, issues = led.process(cs, None, None, frame, acceleration_profiles=_profiles(1, 7, 0.0, stamp=stamp))
    assert not issues, issues
    cs_fast, _ = _scene(stamp, 10.0, 8.8, math.nan)
    want, _ = plain.process(cs_fast, None, None, frame, acceleration_profiles=_profiles(1, 7, 0.0, stamp=stamp))
    np.testing.assert_allclose(got.mean_s_m, want.mean_s_m, rtol=0, atol=1e-9)
    assert got.mean_s_m[0, -1] > plain.process(cs, None, None, frame, acceleration_profiles=_profiles(1, 7, 0.0, stamp=stamp))[0].mean_s_m[0, -1] + 2.5
    cs_none, _ = _scene(stamp, 10.0, 8.0, math.nan)  # no estimate: as without a lead
    a, _ = _fixed(0.8, stencils).process(cs_none, None, None, frame, acceleration_profiles=_profiles(1, 7, 0.0, stamp=stamp))
    b, _ = _fixed(0.0, stencils).process(cs_none, None, None, frame, acceleration_profiles=_profiles(1, 7, 0.0, stamp=stamp))
    np.testing.assert_array_equal(a.mean_s_m, b.mean_s_m)
    cs_stand, _ = _scene(stamp, 10.0, 0.0, 1.0)  # standing (the standstill mixture's): not led
    a, _ = _fixed(0.8, stencils).process(cs_stand, None, None, frame, acceleration_profiles=_profiles(1, 7, 0.0, stamp=stamp))
    b, _ = _fixed(0.0, stencils).process(cs_stand, None, None, frame, acceleration_profiles=_profiles(1, 7, 0.0, stamp=stamp))
    np.testing.assert_array_equal(a.mean_s_m, b.mean_s_m)


def _drive(predictor: MarkovPredictor, refs: dict[float, MarkovPredictor], true_accel: float, frames: int,
           scene: bs.SceneInfo | None = None) -> int | None:
    """A car whose estimated speed is 6 m/s and acceleration 1 m/s² at every frame, while it really drives at
    6 + ``true_accel`` m/s (the estimate lags by 1 s when ``true_accel`` is 1) and its AR profile says 0; every frame's
    prediction is checked against the fixed-lead reference of the lead in use; returns the frame the lead switched at."""
    v_true = 6.0 + true_accel

    def scene_at(stamp: int, n: int):
        # (positions a few cm off the line, as measured ones are: the back test's paired differences then vary)
        return _scene(stamp, 5.0 + v_true * 0.1 * n + 0.05 * math.sin(1.3 * n), 6.0, 1.0)

    return _drive_choice(predictor, refs, "speed_lead", ("speed_lead_failed", "scene_changed", "location_changed"), scene_at, frames, scene)


def test_a_lagging_estimate_makes_the_stage_lead_and_a_right_one_does_not(stencils):
    """The estimate says 6 m/s and 1 m/s² while the car holds 6.8 m/s: the back test finds lead 0.8 s closest to where it
    went and the stage switches to it; a car that holds the estimated 6 m/s leaves the lead at 0."""
    config = MarkovPredictionConfig(mode="hybrid", **{**AR0, "hybrid_speed_leads_s": LEADS})
    predictor = MarkovPredictor(config, stencils=stencils)
    assert predictor.lead_choice is not None and predictor.speed_lead == 0.0
    switched_at = _drive(predictor, {lead: _fixed(lead, stencils) for lead in LEADS}, 0.8, 140)
    summary = predictor.lead_choice.summary()
    assert switched_at is not None and summary["factor"] == 0.8, summary
    assert summary["mean_ade_m"][2] < summary["mean_ade_m"][1] < summary["mean_ade_m"][0]
    predictor.reset()
    assert predictor.lead_choice.factor == 0.8  # kept across sequences

    steady = MarkovPredictor(config, stencils=stencils)
    assert _drive(steady, {lead: _fixed(lead, stencils) for lead in LEADS}, 0.0, 140) is None
    summary = steady.lead_choice.summary()
    assert summary["samples"] >= 20 and summary["factor"] == 0.0, summary
    assert summary["mean_ade_m"][0] < summary["mean_ade_m"][1] < summary["mean_ade_m"][2]


def test_a_failing_back_test_costs_only_its_samples(stencils, monkeypatch):
    predictor = MarkovPredictor(MarkovPredictionConfig(mode="hybrid", **{**AR0, "hybrid_speed_leads_s": LEADS}), stencils=stencils)
    issues = _with_failing_back_test(predictor, _fixed(0.0, stencils), "speed_lead_s",
                                     lambda stamp, n: _scene(stamp, 5.0 + 0.6 * n, 6.0, 1.0), monkeypatch)
    assert [i.kind for i in issues] == ["speed_lead_failed"] and "boom" in issues[0].detail
    assert predictor.speed_lead == 0.0 and not predictor.lead_choice.pending


def test_forget_location_starts_the_learners_afresh_and_reset_keeps_them(stencils):
    """``reset`` (a new sequence) keeps what was learnt online; ``forget_location`` (another place) starts from nothing."""
    config = MarkovPredictionConfig(mode="hybrid", **{**AR0, "hybrid_speed_leads_s": LEADS, "hybrid_curve_factors": (0.0, 1.0, 2.0)})
    predictor = MarkovPredictor(config, stencils=stencils)
    _drive(predictor, {lead: _fixed(lead, stencils) for lead in LEADS}, 0.8, 140)
    learnt = predictor.learnt()
    assert set(learnt) == {"curve_choice", "speed_lead"} and learnt["speed_lead"]["factor"] == 0.8
    predictor.reset()
    assert predictor.speed_lead == 0.8 and predictor.lead_choice.summary()["samples"] == learnt["speed_lead"]["samples"]
    predictor.forget_location()
    assert predictor.speed_lead == 0.0 and predictor.curve_factor == 1.0
    assert predictor.learnt()["speed_lead"]["samples"] == 0 and predictor.learnt()["speed_lead"]["factor"] == 0.0
    assert predictor.learnt()["curve_choice"]["samples"] == 0


def _scene_info(scene_id: str, location_id: str) -> bs.SceneInfo:
    return bs.SceneInfo(header=_header(STAMP), scene_id=scene_id, recording="test", location_id=location_id, map_name="test.osm",
                        map_sha256="", projection="auto", origin_lat_deg=48.0, origin_lon_deg=9.0, frame_rate_hz=10.0,
                        speed_limit_mps=20.0, n_frames=0)


def test_the_streaming_stage_follows_the_scene(stencils):
    """On the bus nobody calls ``forget_location``: the stage does it itself when the latched scene names another
    location (a replay of another recording), and only ``reset``s (the tracks) on another scene of the same location;
    one issue each. A frame older than the new scene's first (``prepare`` ran ahead) is the old scene's: no change."""
    config = MarkovPredictionConfig(mode="hybrid", **{**AR0, "hybrid_speed_leads_s": LEADS})
    predictor = MarkovPredictor(config, stencils=stencils)
    here = _scene_info("k1/seq1", "k1")
    _drive(predictor, {lead: _fixed(lead, stencils) for lead in LEADS}, 0.8, 140, scene=here)
    assert predictor.speed_lead == 0.8 and 1 in predictor._history

    def frame_at(n: int, scene: bs.SceneInfo) -> list[str]:
        stamp = STAMP + n * 100_000_000
        cs, frame = _scene(stamp, 5.0 + 0.68 * n, 6.0, 1.0)
        _, issues = predictor.process(cs, None, scene, frame, acceleration_profiles=_profiles(1, 7, 0.0, stamp=stamp))
        predictor.idle()
        return [i.kind for i in issues if i.kind in ("scene_changed", "location_changed")]

    samples = predictor.lead_choice.summary()["samples"]
    assert frame_at(141, here) == []
    assert frame_at(142, _scene_info("k1/seq2", "k1")) == ["scene_changed"]  # the same place: tracks afresh, what was learnt kept
    assert len(predictor._history[1].samples) == 1 and predictor.speed_lead == 0.8
    assert predictor.lead_choice.summary()["samples"] >= samples
    assert frame_at(143, _scene_info("k1/seq2", "k1")) == []
    assert frame_at(144, _scene_info("k2/seq1", "k2")) == ["location_changed"]  # another place: from nothing
    assert predictor.speed_lead == 0.0 and predictor.learnt()["speed_lead"]["samples"] == 0
    assert frame_at(140, _scene_info("k1/seq2", "k1")) == []  # (older than the change: the old scene's last frame)
    assert frame_at(145, _scene_info("k2/seq1", "k2")) == []
    predictor.reset()  # the caller starts the next sequence itself (iamp eval): its scene comes without an issue
    assert frame_at(146, _scene_info("k2/seq2", "k2")) == []
    assert frame_at(147, _scene_info("k3/seq1", "k3")) == ["location_changed"]  # (a reset keeps the location)

    def kinds(n: int) -> list[str]:
        stamp = STAMP + n * 100_000_000
        cs, frame = _scene(stamp, 5.0 + 0.68 * n, 6.0, 1.0)
        _, issues = predictor.process(cs, None, _scene_info("k3/seq1", "k3"), frame, acceleration_profiles=_profiles(1, 7, 0.0, stamp=stamp))
        predictor.idle()
        return [i.kind for i in issues if i.kind in ("scene_changed", "location_changed", "stamp_went_back")]

    for n in range(148, 160):
        assert kinds(n) == []
    choice = predictor.lead_choice  # (a replay started again is the same place: what was learnt is kept)
    assert kinds(150) == []  # a frame a second back (prepare runs ahead, frames come late): within track_timeout_s
    assert len(predictor._history[1].samples) > 1
    assert kinds(100) == ["stamp_went_back"]  # 6 s back: the replay started again, the tracks afresh
    assert len(predictor._history[1].samples) == 1 and predictor.lead_choice is choice
    assert kinds(101) == []


def test_iamp_eval_starts_every_recording_afresh(monkeypatch):
    """Two recordings in one evaluation: the predictors forget what they learnt online between them (as two stages
    started on each would), and the report keeps what each recording learnt (``learnt_by_recording``)."""
    from stages.lib.datasets import DEFAULT_DATA_DIR, DEFAULT_RECORDING
    from stages.offline.evaluation import EvalConfig, Evaluation

    config = EvalConfig(data_dir=DEFAULT_DATA_DIR, recordings=(DEFAULT_RECORDING,), stride_s=0.4, max_frames_per_sequence=150,
                        progress=False, modes=("hybrid",))
    evaluation = Evaluation(config)
    real_load = evaluation._load

    def twice():
        (rec,) = real_load()
        return [rec, dataclasses.replace(rec, name=rec.name + "-again")]

    monkeypatch.setattr(evaluation, "_load", twice)
    forgotten = []
    predictor = evaluation.predictors["hybrid"]
    real_forget = predictor.forget_location
    monkeypatch.setattr(predictor, "forget_location", lambda: (forgotten.append(len(evaluation.recordings)), real_forget())[1])
    report = evaluation.run()
    assert forgotten == [1]  # once, after the first recording
    by_recording = report["modes"]["hybrid"]["learnt_by_recording"]
    assert list(by_recording) == [DEFAULT_RECORDING, DEFAULT_RECORDING + "-again"]
    # the same frames twice, each from nothing: the same samples learnt (not twice as many the second time)
    first, second = by_recording[DEFAULT_RECORDING], by_recording[DEFAULT_RECORDING + "-again"]
    assert first["speed_lead"]["samples"] > 0
    assert json.dumps(first, sort_keys=True) == json.dumps(second, sort_keys=True)
    assert report["modes"]["hybrid"]["speed_lead"] == by_recording[DEFAULT_RECORDING + "-again"]["speed_lead"]
