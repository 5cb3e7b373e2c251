"""hybrid_accel_shifts (curve_choice.OnlineShiftChoice, modes.hybrid.shift_inputs): a constant added to the AR input
distributions' acceleration, chosen online by back testing the candidates on the cars the stage predicts."""

from __future__ import annotations

import math

import numpy as np
import pytest

import bus_schemas as bs
from stages.markov_prediction import MarkovPredictionConfig, MarkovPredictor
from stages.markov_prediction.curve_choice import OnlineShiftChoice
from stages.markov_prediction.modes.hybrid import cell_moments, shift_inputs
from tests.stages.test_markov_prediction import PLAIN, STAMP, _corridor, _corridor_set, _header, _drive_choice, _profiles, _vehicle, _with_failing_back_test

EDGES = np.linspace(-3.0, 2.0, 11)  # the default input cells: 0.5 m/s² wide
# λ(0) as the model gives it: with "adaptive" the blend learns against the shifted model in use, so a stage that
# switched later learns a slightly different weight than one shifted from the start (1e-6 of the positions here)
AR0 = {"hybrid_initial_input": "ar", **PLAIN}
SHIFTS = (0.0, 0.25, 0.5)  # off by default (docs/evaluation.md "Online acceleration shift"); the candidates it was measured with


@pytest.fixture(scope="module")
def stencils():
    return MarkovPredictor(MarkovPredictionConfig(**PLAIN)).stencils


def test_shift_inputs_moves_the_mean_keeps_the_mass_and_folds_the_tails():
    rng = np.random.default_rng(3)
    probs = np.zeros((4, 10))
    probs[:, 3:7] = rng.uniform(0.1, 1.0, (4, 4))
    probs /= probs.sum(axis=1, keepdims=True)
    for shift in (0.25, 0.5, -0.25, 0.1, -0.6):
        out = shift_inputs(probs, shift, EDGES)
        np.testing.assert_allclose(out.sum(axis=1), 1.0, atol=1e-12)
        assert np.all(out >= 0)
        for b in range(4):  # no mass reaches an end cell here: the mean moves by exactly the shift
            assert cell_moments(EDGES, out[b])[0] == pytest.approx(cell_moments(EDGES, probs[b])[0] + shift, abs=1e-12)
            np.testing.assert_allclose(shift_inputs(probs[b], shift, EDGES), out[b])  # one row as many
    np.testing.assert_array_equal(shift_inputs(probs, 0.0, EDGES), probs)
    top = np.zeros(10)
    top[8] = 1.0
    np.testing.assert_allclose(shift_inputs(top, 0.75, EDGES), np.eye(10)[9])  # beyond the last cell: folded into it
    np.testing.assert_allclose(shift_inputs(top, -5.0, EDGES), np.eye(10)[0])


def test_config_checks():
    assert MarkovPredictionConfig().hybrid_accel_shifts == ()
    assert MarkovPredictor(MarkovPredictionConfig(mode="hybrid", **PLAIN)).shift_choice is None
    for bad in ((0.5,), (0.0, math.nan), (0.0, "x"), (0.0, True)):
        with pytest.raises(ValueError, match="hybrid_accel_shifts"):
            MarkovPredictionConfig(mode="hybrid", hybrid_accel_shifts=bad)
    MarkovPredictionConfig(mode="hybrid", hybrid_accel_shifts=(-0.5, 0.0))  # any sign
    with pytest.raises(ValueError, match="hybrid_accel_shifts"):
        OnlineShiftChoice((0.0, math.inf), 0.4 * np.arange(1, 11))


def _straight_scene(stamp: int, s_now: float, speed: float):
    """A car at ``speed`` at arc length ``s_now`` of a straight corridor (x = s), with its position in a TrackFrame."""
    corridor = _corridor(7, vehicle_s=s_now, length=600.0, limit=20.0)
    cs = _corridor_set(_vehicle(1, speed, [corridor]), stamp=stamp)
    frame = bs.TrackFrame(header=_header(stamp), scene_id="test", track_ids=np.array([1], np.int64), agent_types=np.array([1], np.uint8),
                          x_m=np.array([s_now]), y_m=np.array([0.0]), vx_mps=np.array([math.nan]), vy_mps=np.array([math.nan]),
                          yaw_rad=np.array([0.0]), length_m=np.array([4.5]), width_m=np.array([1.8]))
    return cs, frame


def _drive(predictor: MarkovPredictor, refs: dict[float, MarkovPredictor], accel: float, frames: int) -> int | None:
    """Feed a car that starts at 2 m/s and accelerates at ``accel`` while its AR profile says 0 m/s²; check every
    frame's own prediction against the fixed-shift reference of the shift in use; returns the frame it switched at."""

    def scene_at(stamp: int, n: int):
        t = 0.1 * n
        return _straight_scene(stamp, 5.0 + 2.0 * t + 0.5 * accel * t * t, 2.0 + accel * t)

    return _drive_choice(predictor, refs, "accel_shift", ("accel_shift_failed",), scene_at, frames)


def _fixed(shift: float, stencils) -> MarkovPredictor:
    p = MarkovPredictor(MarkovPredictionConfig(mode="hybrid", hybrid_accel_shifts=(), **AR0), stencils=stencils)
    p.accel_shift = shift  # (no choice: the pairs get this shift on every frame)
    return p


def test_a_car_that_accelerates_past_its_profile_makes_the_stage_shift_and_one_that_keeps_it_does_not(stencils):
    """A car that accelerates at 0.5 m/s² while the AR model says 0: the back test finds the +0.5 shift closest to
    where it went and the stage switches to it; a car that keeps 0 leaves the shift at 0 (the model's own). Every
    frame's prediction is that of the shift in use."""
    config = MarkovPredictionConfig(mode="hybrid", hybrid_accel_shifts=SHIFTS, **AR0)
    predictor = MarkovPredictor(config, stencils=stencils)
    assert predictor.shift_choice is not None and predictor.accel_shift == 0.0
    refs = {s: _fixed(s, stencils) for s in config.hybrid_accel_shifts}
    switched_at = _drive(predictor, refs, 0.5, 140)
    summary = predictor.shift_choice.summary()
    assert switched_at is not None and summary["factor"] == 0.5, summary
    assert summary["mean_ade_m"][2] < summary["mean_ade_m"][1] < summary["mean_ade_m"][0]
    predictor.reset()
    assert predictor.shift_choice.factor == 0.5  # kept across sequences (it belongs to the location, tracker and model)

    steady = MarkovPredictor(config, stencils=stencils)
    assert _drive(steady, {s: _fixed(s, stencils) for s in config.hybrid_accel_shifts}, 0.0, 140) is None
    summary = steady.shift_choice.summary()
    assert summary["samples"] >= 20 and summary["factor"] == 0.0, summary
    assert summary["mean_ade_m"][0] < summary["mean_ade_m"][1] < summary["mean_ade_m"][2]


def test_a_failing_back_test_costs_only_its_samples_and_off_means_off(stencils, monkeypatch):
    predictor = MarkovPredictor(MarkovPredictionConfig(mode="hybrid", hybrid_curve_factors=(), hybrid_accel_shifts=SHIFTS, **AR0),
                                stencils=stencils)
    issues = _with_failing_back_test(predictor, _fixed(0.0, stencils), "accel_shift_mps2",
                                     lambda stamp, n: _straight_scene(stamp, 5.0 + 0.2 * n, 2.0), monkeypatch)
    assert [i.kind for i in issues] == ["accel_shift_failed"] and "boom" in issues[0].detail
    assert predictor.accel_shift == 0.0 and not predictor.shift_choice.pending
    assert MarkovPredictor(MarkovPredictionConfig(mode="hybrid", hybrid_accel_shifts=(), **PLAIN), stencils=stencils).shift_choice is None
    assert MarkovPredictor(MarkovPredictionConfig(mode="baseline", **PLAIN), stencils=stencils).shift_choice is None
