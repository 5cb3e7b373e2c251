"""ar_inference: chunk distributions (docs/method.md §8.5), the core on real frames, the stage on the bus."""

from __future__ import annotations

import sys
from pathlib import Path

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


# --------------------------------------------------------------------------- the core on the embedded scenario


@pytest.fixture(scope="module")
def chain():
    """The first 80 frames of the embedded K729 sequence through corridors and relations (in-process)."""
    from stages.corridors import CorridorBuilder, CorridorsConfig, SceneMaps
    from stages.lib.datasets import DEFAULT_DATA_DIR, DEFAULT_RECORDING, DEFAULT_SEQUENCE, load_recording
    from stages.relations import RelationExtractor, RelationsConfig
    from stages.tracks_source.core import TrackPlayer, TracksSourceConfig

    rec = load_recording(DEFAULT_DATA_DIR, DEFAULT_RECORDING, (DEFAULT_SEQUENCE,))
    player = TrackPlayer(TracksSourceConfig(recording=DEFAULT_RECORDING), rec, map_sha256="", run_id="t", producer="source")
    maps = SceneMaps()
    corridors, relations = CorridorBuilder(CorridorsConfig(), scene_maps=maps), RelationExtractor(RelationsConfig(), scene_maps=maps)
    scene, out = None, []
    for n, (_stamp, result) in enumerate(player):
        if n >= 80:
            break
        scene = result.outputs.get("scene", scene)
        frame = result.outputs["track_frame"]
        cs, _ = corridors.process(frame, scene)
        rs, _ = relations.process(frame, cs, scene)
        out.append((frame, cs, rs))
    return out


def test_every_pair_gets_a_profile_with_distributions_and_history_grows(chain):
    from stages.ar_inference import ARInference, ARInferenceConfig

    core = ARInference(ARInferenceConfig())
    history = {}
    for frame, cs, rs in chain:
        msg, issues = core.process(cs, rs, frame)
        assert not [i for i in issues if i.kind == "nan_prediction"]
        pairs = {(v.track_id, c.corridor_id) for v in cs.vehicles if v.status == 1 for c in v.corridors}
        assert {(p.track_id, p.corridor_id) for p in msg.profiles} == pairs
        for p in msg.profiles:
            assert p.accel_mps2.shape == (40,) and p.input_probs.shape == (10, 10)
            np.testing.assert_allclose(p.input_probs.sum(axis=1), 1.0, atol=1e-5)
            assert np.all(p.chunk_sigma_mps2 >= 0.25 - 1e-6) and np.all(np.isfinite(p.accel_mps2))
            assert 1 <= p.history_steps <= 40
            assert p.history_steps >= history.get(p.track_id, 0)
            history[p.track_id] = p.history_steps
    assert max(history.values()) == 40, "a vehicle seen for 4 s has a full history"
    decoded = type(msg).decode(msg.encode())
    assert decoded.model == core.model_name and decoded.by_pair().keys() == msg.by_pair().keys()


def test_another_scene_starts_every_history_afresh(chain):
    """The CorridorSet of another scene (a replay of another recording on a running pipeline, stamps going on):
    the histories start afresh, one ``scene_changed`` issue; a reset takes the next scene without one."""
    import dataclasses

    from stages.ar_inference import ARInference, ARInferenceConfig

    core = ARInference(ARInferenceConfig())
    for frame, cs, rs in chain[:50]:
        msg, issues = core.process(cs, rs, frame)
        assert "scene_changed" not in [i.kind for i in issues]
    assert max(p.history_steps for p in msg.profiles) > 20
    frame, cs, rs = chain[50]
    other = dataclasses.replace(cs, scene_id=cs.scene_id + "-other")
    msg, issues = core.process(other, rs, frame)
    assert [i.kind for i in issues].count("scene_changed") == 1
    assert max(p.history_steps for p in msg.profiles) == 1
    frame, cs, rs = chain[51]
    msg, issues = core.process(dataclasses.replace(cs, scene_id=other.scene_id), rs, frame)
    assert "scene_changed" not in [i.kind for i in issues] and max(p.history_steps for p in msg.profiles) == 2
    core.reset()
    frame, cs, rs = chain[52]
    msg, issues = core.process(cs, rs, frame)
    assert "scene_changed" not in [i.kind for i in issues]


def test_a_missing_or_corrupt_model_is_a_config_error(tmp_path):
    from stages.lib.base import ConfigError
    from stages.ar_inference import ARInference, ARInferenceConfig

    with pytest.raises(ConfigError, match="no such weights file"):
        ARInference(ARInferenceConfig(model=str(tmp_path / "none.pt")))
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a torch file")
    with pytest.raises(ConfigError, match="bad.pt"):
        ARInference(ARInferenceConfig(model=str(bad)))


def test_stage_exits_2_on_a_missing_model(tmp_path):
    import subprocess
    import sys

    from testkit.helpers import REPO, python_env

    proc = subprocess.run(
        [sys.executable, "-m", "stages.ar_inference", "--run-id", "t", "--params-json", f'{{"model": "{tmp_path / "none.pt"}"}}',
         "--input", "corridor_set=c/corridor_set", "--input", "relation_set=r/relation_set"],
        cwd=REPO, env=python_env(), capture_output=True, text=True, timeout=120,
    )
    assert proc.returncode == 2, proc.stderr
    assert "no such weights file" in proc.stderr
