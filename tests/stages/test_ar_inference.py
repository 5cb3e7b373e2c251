"""ar_inference: chunk distributions (docs/method.md §8.5), the core on real frames, the stage on the bus."""

from __future__ import annotations

import re
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


def test_the_features_are_computed_as_the_model_was_trained(tmp_path):
    """A model trained with ``iamp train --accel-window 2.0`` stores ``feature_config.accel_window_s = 2.0``; the
    inference built its feature tracker with the defaults (1 s) and fed the net features it never saw, without a word."""
    import copy

    from stages.ar_inference import ARInference, ARInferenceConfig
    from stages.lib.ar import DEFAULT_MODEL_PATH, load_model
    from stages.lib.base import ConfigError

    shipped = load_model(DEFAULT_MODEL_PATH)
    assert ARInference(ARInferenceConfig(), model=shipped).tracker.config.accel_window_s == 1.0
    wide = copy.deepcopy(shipped)
    wide.metadata = {**shipped.metadata, "feature_config": {**shipped.metadata["feature_config"], "accel_window_s": 2.0}}
    core = ARInference(ARInferenceConfig(), model=wide)
    assert core.tracker.config.accel_window_s == 2.0
    core.reset()  # a new scene: a fresh history, the same features
    assert core.tracker.config.accel_window_s == 2.0
    odd = copy.deepcopy(shipped)
    odd.metadata = {**shipped.metadata, "feature_config": {**shipped.metadata["feature_config"], "lane_width_m": 3.5}}
    with pytest.raises(ConfigError, match="lane_width_m"):
        ARInference(ARInferenceConfig(), model=odd)


def test_a_model_with_broken_numbers_is_refused_at_load_and_eval_says_so(tmp_path, capsys):
    """NaN weights (a diverged training), a NaN residual spread or a feature scale of 0 made every prediction NaN:
    `iamp eval` and `iamp calibrate` then scored the stages' fallback (the measured acceleration held) with exit 0."""
    import copy

    import torch

    from stages import cli
    from stages.lib.ar import DEFAULT_MODEL_PATH, load_model, save_model

    shipped = load_model(DEFAULT_MODEL_PATH)

    def broken(name: str, change) -> str:
        model = copy.deepcopy(shipped)
        change(model)
        return str(save_model(tmp_path / f"{name}.pt", model))

    def nan_weights(m) -> None:
        with torch.no_grad():
            next(m.net.parameters()).fill_(float("nan"))

    files = {
        "weights": broken("nanw", nan_weights),
        "sigma_res_chunks holds NaN": broken("nansig", lambda m: setattr(m, "sigma_res_chunks", m.sigma_res_chunks * float("nan"))),
        "feature_std has a value <= 0": broken("std0", lambda m: setattr(m, "feature_std", m.feature_std * 0.0)),
    }
    for says, path in files.items():
        with pytest.raises(ValueError, match=re.escape(says)):
            load_model(path)
    code = cli.main(["eval", "--model", files["weights"], "--mode", "hybrid", "--max-frames", "5", "--no-progress"])
    err = capsys.readouterr().err
    assert code == 2 and "hold NaN or inf" in err and "Traceback" not in err, err
    # input cells of the profiles that are not the chain's: the profiles were dropped as mismatched, the fallback scored
    assert cli.main(["eval", "--set-ar", "n_inputs=12", "--mode", "hybrid", "--max-frames", "5", "--no-progress"]) == 2
    assert "the AR profiles' input cells differ from the chain's: n_inputs = 12" in capsys.readouterr().err


def test_iamp_eval_names_hybrid_s_model_and_where_its_figures_are_in_sample(tmp_path, capsys):
    """`iamp eval --model M` on M's own training recording said nothing of it (the figures are in-sample), and the
    printed table never named the model."""
    import copy
    import json

    from stages import cli
    from stages.lib.ar import DEFAULT_MODEL_PATH, load_model, save_model

    other = copy.deepcopy(load_model(DEFAULT_MODEL_PATH))
    other.metadata = {**other.metadata, "recordings": ["k733_2018-05-02"]}
    held_out = str(save_model(tmp_path / "k733only.pt", other))
    for model, says, inside in ((None, "IN-SAMPLE on k729_2022-03-16", ["k729_2022-03-16"]), (held_out, "every scored recording held out", [])):
        out_json = tmp_path / "eval.json"
        args = ["eval", "--mode", "hybrid", "--max-frames", "5", "--no-progress", "--json", str(out_json)] + (["--model", model] if model else [])
        assert cli.main(args) == 0
        lines = capsys.readouterr().out.splitlines()
        # (other weights than the shipped ones: a warning first, that the default spread table belongs to those)
        assert all(line.startswith("WARNING: spread_calibration = shipped (the default)") for line in lines[: int(model is not None)]), lines[:2]
        first = lines[int(model is not None)]
        assert first.startswith("hybrid's model ") and says in first, first
        report = json.loads(out_json.read_text())
        assert report["model_in_sample"] == inside and report["model_name"].split("@")[0] in first


def test_a_folder_given_as_the_model_says_so(tmp_path):
    from stages.ar_inference import ARInference, ARInferenceConfig
    from stages.lib.base import ConfigError

    with pytest.raises(ConfigError, match="is a folder; expected a weights file"):
        ARInference(ARInferenceConfig(model=str(tmp_path)))
