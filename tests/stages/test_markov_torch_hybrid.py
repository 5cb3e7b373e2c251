"""The hybrid chain on the torch backend (CPU here, CUDA where a GPU is present) gives the numpy backend's numbers on
real frames, with λ on the window built on the torch device from λ_speed moved there once per run
(``chain._PriorityBackend._torch_priority``) instead of built in numpy and copied every step."""

from __future__ import annotations

import numpy as np
import pytest

from stages.lib.markov import MarkovGridConfig, kernels, load_or_build_stencils
from stages.markov_prediction import MarkovPredictionConfig, MarkovPredictor
from stages.markov_prediction import priority
from testkit.chain_messages import dense_frames_with_profiles

torch = pytest.importorskip("torch")


@pytest.fixture(scope="module")
def frames(tmp_path_factory):
    """Frames of about 12 vehicles superimposed from the embedded K729 scenario, with their AR profiles."""
    return dense_frames_with_profiles(12, 16, tmp_path_factory.mktemp("dense"), lambda n: n >= 10 and n % 3 == 0)


def _predict(backend: str, device: str, frames, stencils):
    predictor = MarkovPredictor(MarkovPredictionConfig(mode="hybrid", backend=backend, device=device), stencils=stencils)
    out = []
    for item, profiles in frames:
        prediction, _issues = predictor.process(item.corridor_set, item.relation_set, item.scene, item.frame,
                                                intention_belief=item.belief, acceleration_profiles=profiles)
        out.append(prediction)
    return out


@pytest.mark.skipif(not kernels.available(), reason="numba does not import (the compiled λ_speed)")
@pytest.mark.parametrize("device", ["cpu", "cuda"])
def test_hybrid_on_torch_agrees_with_numpy_on_real_frames(frames, device, monkeypatch):
    if device == "cuda" and not torch.cuda.is_available():
        pytest.skip("no CUDA device here")
    stencils = load_or_build_stencils(MarkovGridConfig())
    reference = _predict("numpy", "cpu", frames, stencils)
    combined = []
    real = priority.combine_with_preference
    monkeypatch.setattr(priority, "combine_with_preference", lambda *a, **k: combined.append(1) or real(*a, **k))
    ours = _predict("torch", device, frames, stencils)
    assert not combined  # λ built on the torch device, not in numpy per step
    assert sum(p.position_probs.shape[0] for p in ours) > 3 * len(frames)  # several pairs per frame
    for a, b in zip(reference, ours):
        np.testing.assert_allclose(b.position_probs, a.position_probs, atol=2e-4)
        np.testing.assert_allclose(b.velocity_probs, a.velocity_probs, atol=2e-4)
        np.testing.assert_allclose(b.mean_xy_m, a.mean_xy_m, atol=2e-2)
