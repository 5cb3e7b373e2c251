"""hybrid_curve_factors (stages/markov_prediction/curve_choice.py): the curve factor of hybrid's speed restriction,
chosen online by back testing the candidates on the cars the stage predicts."""

from __future__ import annotations

import math

import numpy as np
import pytest

import bus_schemas as bs
from stages.markov_prediction import MarkovPredictionConfig, MarkovPredictor
from stages.markov_prediction.curve_choice import MIN_SAMPLES, OnlineCurveChoice, sampled
from tests.stages.test_markov_prediction import PLAIN, STAMP, _corridor, _corridor_set, _header, _profiles, _vehicle

NO_SHIFT = {"hybrid_accel_shifts": ()}  # the curve choice alone (the acceleration shift's own tests: test_accel_shift.py)

S = 1_000_000_000  # ns per s
STEPS = 0.4 * np.arange(1, 11)


@pytest.fixture(scope="module")
def stencils():
    return MarkovPredictor(MarkovPredictionConfig(**PLAIN)).stencils


def _sample_means(errors_m: list[float], truth: np.ndarray) -> np.ndarray:
    """(C, 1, K, 2): candidate c's means ``errors_m[c]`` to the side of ``truth`` (K, 2) at every step."""
    return np.stack([(truth + np.array([0.0, e]))[None] for e in errors_m])


def _feed(choice: OnlineCurveChoice, track: int, t0_s: float, errors_m: list[float], seen_s: float = 4.0) -> None:
    """One car on x = 10 t, seen every 0.1 s from t0 to t0 + ``seen_s``, and a sample of it at t0."""
    t = np.round(np.arange(0.0, seen_s + 1e-9, 0.1), 6)
    stamps = [int(round((t0_s + x) * S)) for x in t]
    for stamp, x in zip(stamps, t):
        choice.add_positions(stamp, [track], [10.0 * (t0_s + x)], [0.0])
    truth = np.column_stack([10.0 * (t0_s + STEPS), np.zeros(STEPS.size)])
    choice.record(track, int(round(t0_s * S)), _sample_means(errors_m, truth))


def test_a_candidate_replaces_the_default_only_when_it_is_better_by_three_standard_errors():
    rng = np.random.default_rng(0)
    choice = OnlineCurveChoice((0.0, 1.0, 2.0), STEPS)
    assert choice.default == 1.0 and choice.factor == 1.0
    for n in range(MIN_SAMPLES + 10):  # candidate 0 is 0.5 m better than the default, with 0.3 m of noise
        _feed(choice, n, 10.0 * n, [1.0 + rng.normal(0, 0.3), 1.5 + rng.normal(0, 0.3), 2.0])
        choice.resolve(int((10.0 * n + 5.0) * S))  # the horizon (4 s) and the lag (1 s) have passed
        if choice.samples < MIN_SAMPLES:
            assert choice.factor == 1.0, choice.samples
    assert choice.samples == MIN_SAMPLES + 10 and not choice.pending
    assert choice.factor == 0.0
    summary = choice.summary()
    assert summary["mean_ade_m"][0] < summary["mean_ade_m"][1] < summary["mean_ade_m"][2]
    assert summary["t_vs_default"][0] < -3 and summary["t_vs_default"][1] == 0.0 and summary["t_vs_default"][2] > 3

    noise = OnlineCurveChoice((0.0, 1.0, 2.0), STEPS)  # no real difference: the default stays
    for n in range(200):
        _feed(noise, n, 10.0 * n, [1.0 + rng.normal(0, 0.3), 1.0 + rng.normal(0, 0.3), 1.0 + rng.normal(0, 0.3)])
        noise.resolve(int((10.0 * n + 5.0) * S))
    assert noise.samples == 200 and noise.factor == 1.0


def test_samples_wait_for_the_horizon_and_a_car_that_leaves_is_scored_on_what_was_seen():
    choice = OnlineCurveChoice((0.0, 1.0), STEPS)
    _feed(choice, 1, 10.0, [1.0, 3.0])
    choice.resolve(int(14.5 * S))  # horizon passed, the lag not yet
    assert choice.samples == 0 and len(choice.pending) == 1
    choice.resolve(int(15.0 * S))
    assert choice.samples == 1 and choice.summary()["mean_ade_m"] == pytest.approx([1.0, 3.0])
    _feed(choice, 2, 20.0, [2.0, 2.0], seen_s=2.05)  # seen for 5 of the 10 steps: scored on those
    _feed(choice, 3, 30.0, [2.0, 2.0], seen_s=1.9)  # 4 of 10: not scored
    choice.resolve(int(40.0 * S))
    assert choice.samples == 2 and choice.unresolved == 1
    assert not choice.positions  # nothing left to score: the positions are forgotten


def test_a_track_that_jumps_is_counted_and_not_scored():
    # a position far off (a tracker's glitch, a re-used id) within a sample's horizon: its error is not the candidates',
    # and one such sample swamped the run's means (a new-user probe: 1,155 m for the rest of the run); the samples
    # around it score as before
    choice = OnlineCurveChoice((0.0, 1.0), STEPS)
    _feed(choice, 1, 10.0, [1.0, 3.0])
    _feed(choice, 2, 20.0, [1.0, 3.0])
    choice.add_positions(int(22.0 * S), [2], [50_000.0], [50_000.0])  # (the same stamp as a kept one: kept once, not moved)
    choice.positions[2][20] = (int(22.0 * S), 50_000.0, 50_000.0)
    _feed(choice, 3, 30.0, [1.0, 3.0])
    choice.resolve(int(40.0 * S))
    assert choice.samples == 2 and choice.jumped == 1 and choice.unresolved == 0
    assert choice.summary()["mean_ade_m"] == pytest.approx([1.0, 3.0]) and choice.summary()["jumped"] == 1


def test_positions_in_any_order_and_reset_keeps_what_was_learnt():
    a, b = OnlineCurveChoice((0.0, 1.0), STEPS), OnlineCurveChoice((0.0, 1.0), STEPS)
    t = np.round(np.arange(0.0, 4.05, 0.1), 6)
    for stamp_s in t:
        a.add_positions(int(round((10 + stamp_s) * S)), [1], [10.0 * stamp_s], [0.0])
    for stamp_s in t[::-1]:  # the frames came the other way round (and one twice)
        b.add_positions(int(round((10 + stamp_s) * S)), [1], [10.0 * stamp_s], [0.0])
    b.add_positions(int(round(12 * S)), [1], [999.0], [0.0])
    truth = np.column_stack([10.0 * STEPS, np.zeros(STEPS.size)])
    for c in (a, b):
        c.record(1, 10 * S, _sample_means([0.5, 1.5], truth))
        c.resolve(16 * S)
    assert a.summary()["mean_ade_m"] == b.summary()["mean_ade_m"] == pytest.approx([0.5, 1.5])
    a.record(1, 20 * S, _sample_means([0.5, 1.5], truth))
    a.reset()
    assert a.samples == 1 and not a.pending and not a.positions
    with pytest.raises(ValueError, match="hybrid_curve_factors"):
        OnlineCurveChoice((1.0,), STEPS)
    with pytest.raises(ValueError, match="hybrid_curve_factors"):
        OnlineCurveChoice((1.0, math.nan), STEPS)
    assert OnlineCurveChoice((0.0, 2.0), STEPS).factor == 0.0  # without 1 among them: the first is the default
    with pytest.raises(ValueError, match="hybrid_curve_factors"):
        MarkovPredictionConfig(mode="hybrid", hybrid_curve_factors=(1.0, -1.0))


def test_the_sampled_vehicles_depend_on_the_stamp_alone_and_all_get_their_turn():
    ids = [7, 3, 11, 5]
    assert sampled(ids, 123 * S) == sampled(list(reversed(ids)), 123 * S)
    seen = {v for n in range(40) for v in sampled(ids, STAMP + n * 100_000_000)}
    assert seen == set(ids)
    assert sampled([], STAMP) == [] and len(sampled(ids, STAMP, n=2)) == 2
    stamps = [STAMP + n * 100_000_000 for n in range(600)]
    assert all(sampled(ids, t, pairs=16) for t in stamps)  # up to PAIRS_PER_TEST pairs: every frame
    busy = sum(bool(sampled(ids, t, pairs=48)) for t in stamps)  # 48 pairs: one frame in three
    assert 150 < busy < 250, busy


def _curve_scene(stamp: int, s_now: float, with_frame: bool = True):
    """A car at 10 m/s on a corridor that bends (radius 15 m) 30 m from its start; it is at arc length ``s_now``."""
    corridor = _corridor(7, vehicle_s=s_now, radius=15.0, length=300.0)
    cs = _corridor_set(_vehicle(1, 10.0, [corridor]), stamp=stamp)
    x = float(np.interp(s_now, corridor.s_m, corridor.x_m))
    y = float(np.interp(s_now, corridor.s_m, corridor.y_m))
    header = _header(stamp)
    frame = bs.TrackFrame(header=header, scene_id="test", track_ids=np.array([1], np.int64), agent_types=np.array([1], np.uint8),
                          x_m=np.array([x]), y_m=np.array([y]), vx_mps=np.array([math.nan]), vy_mps=np.array([math.nan]),
                          yaw_rad=np.array([0.0]), length_m=np.array([4.5]), width_m=np.array([1.8])) if with_frame else None
    return cs, frame


def test_a_car_that_takes_the_bend_at_speed_makes_the_stage_drop_the_curve_cut(stencils):
    """Every 0.1 s for 20 s a car at 10 m/s on a corridor that bends after 30 m (radius 15 m, round and round), taken
    without slowing (the AR profile says 0 m/s²):
    the back test finds the prediction without the curve cut (factor 0) closer to where the car went, and the stage
    switches to it; the frame's own prediction is the fixed rule's until then, and the factor 0's after."""
    config = MarkovPredictionConfig(mode="hybrid", hybrid_curve_factors=(0.0, 1.0, 2.0), **NO_SHIFT, **PLAIN)
    fixed = {f: MarkovPredictor(MarkovPredictionConfig(mode="hybrid", hybrid_curve_factors=(), hybrid_speed_restriction_curves=bool(f),
                                                        **NO_SHIFT, **PLAIN), stencils=stencils) for f in (0, 1)}
    predictor = MarkovPredictor(config, stencils=stencils)
    assert predictor.curve_choice is not None and predictor.curve_factor == 1.0
    switched_at = None
    for n in range(200):
        stamp = STAMP + n * 100_000_000
        s_now = 5.0 + n * 1.0
        cs, frame = _curve_scene(stamp, s_now)
        prediction, issues = predictor.process(cs, None, None, frame, acceleration_profiles=_profiles(1, 7, 0.0, stamp=stamp))
        assert not [i for i in issues if i.kind == "curve_choice_failed"], issues
        refs = {f: fixed[f].process(cs, None, None, frame, acceleration_profiles=_profiles(1, 7, 0.0, stamp=stamp))[0] for f in fixed}
        if switched_at is None and predictor.curve_factor == 0.0:
            switched_at = n
        # the frame's own prediction is that of the factor in use
        np.testing.assert_array_equal(prediction.mean_s_m, refs[1 if switched_at is None else 0].mean_s_m)
    summary = predictor.curve_choice.summary()
    assert switched_at is not None, summary
    assert summary["factor"] == 0.0 and summary["mean_ade_m"][0] < summary["mean_ade_m"][1] < summary["mean_ade_m"][2]
    predictor.reset()
    assert predictor.curve_choice.factor == 0.0  # kept across sequences


def test_the_choice_needs_no_track_frame_and_is_off_without_the_speed_restriction(stencils):
    predictor = MarkovPredictor(MarkovPredictionConfig(mode="hybrid", **PLAIN), stencils=stencils)
    assert predictor.curve_choice is not None and MarkovPredictionConfig().hybrid_curve_factors == (0.0, 1.0, 2.0)
    for n in range(3):
        stamp = STAMP + n * 100_000_000
        cs, _ = _curve_scene(stamp, 5.0 + n, with_frame=False)
        _prediction, issues = predictor.process(cs, acceleration_profiles=_profiles(1, 7, 0.0, stamp=stamp))
        assert not [i for i in issues if i.kind == "curve_choice_failed"]
    # each frame's back test runs off its path: the last one when the stage is idle (or first thing in the next frame)
    assert len(predictor.curve_choice.pending) == 2
    predictor.idle()
    assert len(predictor.curve_choice.pending) == 3 and not predictor.curve_choice.positions
    for off in ({"hybrid_speed_restriction": False}, {"hybrid_speed_restriction_curves": False}, {"hybrid_curve_factors": ()}):
        assert MarkovPredictor(MarkovPredictionConfig(mode="hybrid", **off, **PLAIN), stencils=stencils).curve_choice is None
    assert MarkovPredictor(MarkovPredictionConfig(mode="baseline", **PLAIN), stencils=stencils).curve_choice is None


def test_a_failing_back_test_costs_only_its_samples(stencils, monkeypatch):
    predictor = MarkovPredictor(MarkovPredictionConfig(mode="hybrid", **NO_SHIFT, **PLAIN), stencils=stencils)
    reference = MarkovPredictor(MarkovPredictionConfig(mode="hybrid", **NO_SHIFT, **PLAIN), stencils=stencils)
    monkeypatch.setattr(predictor, "_pair_means", lambda *a, **k: (_ for _ in ()).throw(RuntimeError("boom")))
    for n in range(2):
        stamp = STAMP + n * 100_000_000
        cs, frame = _curve_scene(stamp, 5.0 + n)
        prediction, issues = predictor.process(cs, None, None, frame, acceleration_profiles=_profiles(1, 7, 0.0, stamp=stamp))
        ref, _ = reference.process(cs, None, None, frame, acceleration_profiles=_profiles(1, 7, 0.0, stamp=stamp))
        np.testing.assert_array_equal(prediction.mean_s_m, ref.mean_s_m)
        if n == 0:  # the back test runs after the frame's outputs: its failure goes out with the next frame's issues
            assert issues == []
            predictor.idle()
    assert [i.kind for i in issues] == ["curve_choice_failed"] and "boom" in issues[0].detail
    assert predictor.curve_factor == 1.0 and not predictor.curve_choice.pending


def test_the_back_test_runs_off_the_frames_path_and_when_it_runs_changes_nothing(stencils):
    """The back test of a frame runs in ``idle`` (the runtime calls it once the frame's outputs are out and nothing
    waits), or first thing in the next frame when nothing called it: the frames' predictions, issues and the choice
    are the same either way, and a frame's own sample is recorded only once idle (or the next frame) has run."""
    config = MarkovPredictionConfig(mode="hybrid", **PLAIN)
    idle_each, never = MarkovPredictor(config, stencils=stencils), MarkovPredictor(config, stencils=stencils)
    for n in range(80):
        stamp = STAMP + n * 100_000_000
        cs, frame = _curve_scene(stamp, 5.0 + n * 1.0)
        got = [p.process(cs, None, None, frame, acceleration_profiles=_profiles(1, 7, 0.0, stamp=stamp)) for p in (idle_each, never)]
        np.testing.assert_array_equal(got[0][0].mean_s_m, got[1][0].mean_s_m)
        assert [i.kind for i in got[0][1]] == [i.kind for i in got[1][1]]
        assert idle_each.curve_factor == never.curve_factor
        before = len(idle_each.curve_choice.pending) + idle_each.curve_choice.samples
        idle_each.idle()
        assert len(idle_each.curve_choice.pending) + idle_each.curve_choice.samples == before + 1  # this frame's sample
        idle_each.idle()  # nothing left to do
        assert len(idle_each.curve_choice.pending) + idle_each.curve_choice.samples == before + 1
    never.idle()
    assert idle_each.curve_choice.summary() == never.curve_choice.summary()
    assert idle_each.curve_choice.samples > 0 and idle_each.curve_factor == 0.0  # it learnt (the bend is taken at speed)
