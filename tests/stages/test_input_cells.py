"""The chain's input (acceleration) cells: one source of the defaults, other ranges end to end, mismatches caught."""

from __future__ import annotations

import numpy as np
import pytest

from stages.ar_inference import ARInferenceConfig, chunk_distributions
from stages.lib.markov import MarkovGridConfig, load_or_build_stencils
from stages.lib.markov.grid import uniform_input_edges
from stages.markov_prediction import MarkovPredictionConfig, MarkovPredictor
from stages.markov_prediction import priority as pr
from stages.markov_prediction.config import DEFAULT_PREFERENCE
from stages.markov_prediction.core import grid_config

from tests.stages.test_markov_prediction import PLAIN, _corridor, _corridor_set, _profiles, _vehicle

WIDE = {"input_min_mps2": -3.0, "input_max_mps2": 3.0, "n_inputs": 12}


def test_ar_inference_and_markov_prediction_share_the_default_cells():
    grid = MarkovGridConfig().input_edges()
    np.testing.assert_array_equal(ARInferenceConfig().input_edges(), grid)
    np.testing.assert_array_equal(grid_config(MarkovPredictionConfig()).input_edges(), grid)
    np.testing.assert_array_equal(grid, np.arange(-3.0, 2.01, 0.5))  # the documented default: 10 cells of 0.5 on [-3, 2]
    wide = MarkovPredictionConfig(**WIDE)
    np.testing.assert_array_equal(ARInferenceConfig(**WIDE).input_edges(), grid_config(wide).input_edges())
    assert grid_config(wide).n_inputs == 12 and grid_config(wide).input_centres_mps2()[-1] == 2.75


@pytest.mark.parametrize("bad", [{"input_min_mps2": 2.0, "input_max_mps2": 2.0}, {"n_inputs": 1}, {"input_max_mps2": float("nan")}])
def test_bad_cells_are_a_config_error(bad):
    with pytest.raises(ValueError):
        MarkovPredictionConfig(**bad)
    with pytest.raises(ValueError):
        uniform_input_edges(bad.get("input_min_mps2", -3.0), bad.get("input_max_mps2", 2.0), bad.get("n_inputs", 10))


def test_default_preference_is_carried_over_to_other_cells():
    default = uniform_input_edges()
    np.testing.assert_array_equal(pr.preference_on_cells(DEFAULT_PREFERENCE, default, default), DEFAULT_PREFERENCE)
    wide = pr.preference_on_cells(DEFAULT_PREFERENCE, default, uniform_input_edges(-3.0, 3.0, 12))
    np.testing.assert_allclose(wide[:10], DEFAULT_PREFERENCE)  # the shared cells keep their values
    assert DEFAULT_PREFERENCE[-1] > wide[10] > wide[11] > 0  # beyond 2 m/s² ever less preferred
    coarse = pr.preference_on_cells(DEFAULT_PREFERENCE, default, uniform_input_edges(-3.0, 2.0, 5))
    np.testing.assert_allclose(coarse, np.asarray(DEFAULT_PREFERENCE).reshape(5, 2).mean(axis=1))
    with pytest.raises(ValueError):
        pr.preference_on_cells(DEFAULT_PREFERENCE[:-1], default, default)
    # a preference set by hand must match the cells
    with pytest.raises(ValueError):
        MarkovPredictor(MarkovPredictionConfig(free_driving_preference=(1.0,) * 10, **WIDE, **PLAIN))


def test_stencils_of_another_grid_are_refused():
    default = load_or_build_stencils(MarkovGridConfig())
    with pytest.raises(ValueError, match="another grid"):
        MarkovPredictor(MarkovPredictionConfig(mode="hybrid", **WIDE), stencils=default)


def test_wider_cells_let_hybrid_follow_a_strong_acceleration():
    """A car pulling away at 2.6 m/s²: on [-3, 2] the profile is folded into the top cell (1.75 m/s²), on [-3, 3] it
    is not, and the chain goes ~s = v·t + ½·2.6·t² instead of ½·1.75·t²."""
    cs = _corridor_set(_vehicle(1, 5.0, [_corridor(7)]))
    ends = {}
    for name, cells in (("default", {}), ("wide", WIDE)):
        config = MarkovPredictionConfig(mode="hybrid", hybrid_speed_restriction=False, **cells, **PLAIN)
        predictor = MarkovPredictor(config, stencils=load_or_build_stencils(grid_config(config)))
        edges = predictor.grid.input_edges()
        prediction, issues = predictor.process(cs, acceleration_profiles=_profiles(1, 7, 2.6, edges=edges))
        assert not [i for i in issues if i.kind == "bad_profile"], issues
        ends[name] = float(prediction.mean_s_m[0, -1]) - 5.0
        # the other stage's profiles over the other cells are refused with a counted issue, never an exception
        other = uniform_input_edges() if cells else uniform_input_edges(-3.0, 3.0, 12)
        _, issues = predictor.process(cs, acceleration_profiles=_profiles(1, 7, 2.6, edges=np.asarray(other)))
        assert any(i.kind == "bad_profile" for i in issues)
    assert ends["wide"] > ends["default"] + 3.0, ends
    assert abs(ends["wide"] - (20.0 + 0.5 * 2.6 * 16.0)) < 5.0, ends


def test_ar_distributions_over_wider_cells_keep_a_strong_acceleration():
    profile = np.full((1, 40), 2.6)
    sigma = np.full(10, 0.3)
    narrow = chunk_distributions(profile, 4, sigma, ARInferenceConfig().input_edges())[2]
    wide = chunk_distributions(profile, 4, sigma, ARInferenceConfig(**WIDE).input_edges())[2]
    assert narrow.shape[-1] == 10 and wide.shape[-1] == 12
    np.testing.assert_allclose(wide.sum(axis=-1), 1.0, atol=1e-6)
    assert narrow[..., -1].min() > 0.99  # all folded into the top cell [1.5, 2]
    assert wide[..., -2:].sum(axis=-1).min() > 0.9 and wide[..., -1].min() > 0.5  # mostly in [2.5, 3]


def test_eval_gives_ar_inference_the_chain_cells():
    from stages.lib.datasets import DEFAULT_RECORDING
    from stages.offline.evaluation import EvalConfig, Evaluation

    evaluation = Evaluation(EvalConfig(recordings=(DEFAULT_RECORDING,), modes=("hybrid", "baseline"), progress=False,
                                       params=tuple(WIDE.items())))
    np.testing.assert_array_equal(evaluation.ar_config.input_edges(), evaluation.predictors["hybrid"].grid.input_edges())
    assert evaluation.predictors["baseline"].grid.n_inputs == 12
    # --set-ar with other cells than the chain's: refused, as the launcher refuses such a pipeline (it used to run, every
    # profile ignored as a bad_profile, and score the stage's fallback as hybrid with exit 0)
    from stages.lib.base import ConfigError

    with pytest.raises(ConfigError, match="input cells differ from the chain's: n_inputs = 10"):
        Evaluation(EvalConfig(recordings=(DEFAULT_RECORDING,), modes=("hybrid",), progress=False, params=tuple(WIDE.items()),
                              ar_params=(("n_inputs", 10),)))
