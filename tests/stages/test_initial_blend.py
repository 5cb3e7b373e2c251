"""hybrid_initial_input "adaptive" (stages/markov_prediction/initial_blend.py): the weight of the measured acceleration
in a moving pair's first input, learnt online from what the cars then did."""

from __future__ import annotations

import numpy as np
import pytest

from stages.markov_prediction import MarkovPredictionConfig, MarkovPredictor
from stages.markov_prediction.core import _SpeedHistory
from stages.markov_prediction.initial_blend import MIN_RECORDS, OnlineInitialBlend
from tests.stages.test_markov_prediction import PLAIN, _accelerating_history, _corridor, _corridor_set, _profiles, _vehicle

S = 1_000_000_000  # ns per s


@pytest.fixture(scope="module")
def stencils():
    return MarkovPredictor(MarkovPredictionConfig(**PLAIN)).stencils


def _history(speeds: list[tuple[float, float]]) -> _SpeedHistory:
    """(time s, speed m/s) samples as a speed history."""
    h = _SpeedHistory()
    for t, v in speeds:
        h.samples.append((int(round(t * S)), v))
    return h


def _learn(truth, n: int, rng, window_s: float = 1.0) -> OnlineInitialBlend:
    """n cars, each recorded at t0 = 10 s with a measured acceleration a ~ N(0, 1) and a model mean μ ~ N(0, 1), then
    driving on at the acceleration truth(a, μ) for 1.2 s (speeds every 0.1 s)."""
    learnt = OnlineInitialBlend(window_s)
    histories = {}
    for track in range(n):
        a, mu = rng.normal(0.0, 1.0, 2)
        r = truth(a, mu)
        learnt.record(track, 10 * S, float(a), float(mu))
        histories[track] = _history([(10.0 + 0.1 * i, 8.0 + r * 0.1 * i) for i in range(13)])
    learnt.resolve(histories, int(10.5 * S))  # no window has ended yet
    assert learnt.resolved == 0 and len(learnt.pending) == n
    learnt.resolve(histories, 11 * S)
    return learnt


def test_the_weight_is_the_least_squares_share_of_the_measurement_that_came_true():
    rng = np.random.default_rng(0)
    assert _learn(lambda a, mu: a, 80, rng).weight == pytest.approx(1.0)  # the measurement came true: all of it
    assert _learn(lambda a, mu: mu, 80, rng).weight == pytest.approx(0.0, abs=1e-9)  # the model did: none of it
    half = _learn(lambda a, mu: 0.5 * (a + mu), 80, rng)
    assert half.weight == pytest.approx(0.5) and half.resolved == 80 and not half.pending
    assert _learn(lambda a, mu: 2 * mu - a, 80, rng).weight == 0.0  # anti-predictive: clipped to 0 ...
    assert _learn(lambda a, mu: 2 * mu - a, 80, rng).summary()["raw_weight"] == pytest.approx(-1.0)  # ... what it measured
    few = _learn(lambda a, mu: a, MIN_RECORDS - 1, rng)  # too few records: the model's λ(0) (w = 0)
    assert few.weight == 0.0 and few.summary()["raw_weight"] == pytest.approx(1.0)


def test_records_without_speeds_after_them_are_counted_and_reset_keeps_what_was_learnt():
    rng = np.random.default_rng(1)
    learnt = _learn(lambda a, mu: a, 60, rng)
    learnt.record(100, 12 * S, 1.0, 0.0)  # a track whose history is gone by then
    learnt.record(101, 12 * S, 1.0, 0.0)  # one with a single speed after t0
    learnt.record(101, 12 * S, 1.0, 0.0)  # the same stamp again: kept once
    learnt.record(102, 12 * S, float("nan"), 0.0)  # not finite: not kept
    assert set(learnt.pending) == {100, 101}
    learnt.resolve({101: _history([(11.9, 5.0), (12.0, 5.0), (12.5, 6.0)])}, 13 * S)
    assert (learnt.resolved, learnt.unresolved, learnt.pending) == (60, 2, {})
    learnt.record(7, 14 * S, 1.0, 0.0)
    learnt.reset()
    assert not learnt.pending and learnt.weight == pytest.approx(1.0)
    with pytest.raises(ValueError, match="window_s"):
        OnlineInitialBlend(0.0)


def test_adaptive_starts_from_the_model_until_it_has_learnt_then_moves_towards_the_measurement(stencils):
    """A car that has accelerated at +1.5 m/s² with an AR profile of -2.5 m/s²: with nothing learnt yet "adaptive" is
    "ar" exactly (and records the car); with a learnt weight of 1 it starts as "measured", with 0.5 between the two."""
    ends = {}
    for initial, weight in (("ar", None), ("measured", None), ("adaptive", None), ("adaptive", 1.0), ("adaptive", 0.5)):
        predictor = MarkovPredictor(MarkovPredictionConfig(mode="hybrid", hybrid_initial_input=initial, **PLAIN), stencils=stencils)
        if weight is not None:  # as if MIN_RECORDS cars had shown it
            learnt = predictor.initial_blend
            learnt.sum_xx, learnt.sum_xy, learnt.resolved = 10.0, 10.0 * weight, MIN_RECORDS
        stamp = _accelerating_history(predictor, 8.5, 1.5, 0.0)
        prediction, issues = predictor.process(_corridor_set(_vehicle(1, 10.0, [_corridor(7)]), stamp=stamp),
                                               acceleration_profiles=_profiles(1, 7, -2.5, stamp=stamp))
        assert not [i for i in issues if i.kind == "bad_measured_acceleration"]
        ends[(initial, weight)] = float(prediction.mean_s_m[0, 0])
        if initial == "adaptive":
            assert [r[0] for r in predictor.initial_blend.pending[1]] == [stamp]  # the car recorded for later
        else:
            assert predictor.initial_blend is None
    assert ends[("adaptive", None)] == ends[("ar", None)]
    assert ends[("adaptive", 1.0)] == pytest.approx(ends[("measured", None)], abs=0.1)
    assert ends[("ar", None)] + 0.1 < ends[("adaptive", 0.5)] < ends[("adaptive", 1.0)] - 0.1, ends
    assert MarkovPredictionConfig(mode="hybrid").hybrid_initial_input == "adaptive"  # the default
