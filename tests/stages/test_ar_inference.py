"""ar_inference: chunk distributions (METHOD.md §3.2), the core on real frames, the stage on the bus."""

from __future__ import annotations

import numpy as np
import pytest

from stages.ar_inference import chunk_distributions

EDGES = np.linspace(-3.0, 2.0, 11)


def test_chunk_distribution_matches_the_method_example():
    accel = np.full((1, 40), -0.2)
    mu, sigma, probs = chunk_distributions(accel, 4, np.full(10, 0.4), EDGES)
    np.testing.assert_allclose(mu, -0.2)
    np.testing.assert_allclose(sigma, 0.4)
    expected = [0, 0, 0.001, 0.022, 0.204, 0.465, 0.268, 0.039, 0.001, 0]
    np.testing.assert_allclose(probs[0, 0], expected, atol=1.5e-3)
    np.testing.assert_allclose(probs.sum(axis=-1), 1.0, atol=1e-12)


def test_chunk_spread_adds_within_chunk_variance_and_is_floored():
    accel = np.repeat(np.array([[0.0, 1.0, 0.0, 1.0]]), 10, axis=0).reshape(1, 40)
    _, sigma, _ = chunk_distributions(accel, 4, np.zeros(10), EDGES, sigma_floor=0.1)
    np.testing.assert_allclose(sigma, 0.5)  # var of {0, 1, 0, 1} = 0.25
    _, sigma, probs = chunk_distributions(np.zeros((2, 40)), 4, np.zeros(10), EDGES, sigma_floor=0.25)
    np.testing.assert_allclose(sigma, 0.25)
    assert np.all(probs.max(axis=-1) < 0.95), "no degenerate distribution"


def test_tails_fold_into_the_end_cells():
    _, _, probs = chunk_distributions(np.full((1, 40), -6.0), 4, np.full(10, 0.3), EDGES)
    assert probs[0, 0, 0] > 0.999
    _, _, probs = chunk_distributions(np.full((1, 40), 4.0), 4, np.full(10, 0.3), EDGES)
    assert probs[0, 0, -1] > 0.999


def test_chunk_distributions_refuse_bad_shapes():
    with pytest.raises(ValueError, match="chunks of 4"):
        chunk_distributions(np.zeros((1, 38)), 4, np.zeros(10), EDGES)
    with pytest.raises(ValueError, match="sigma_res"):
        chunk_distributions(np.zeros((1, 40)), 4, np.zeros(9), EDGES)
