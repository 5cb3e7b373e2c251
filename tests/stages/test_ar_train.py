"""Tests of the AR data set, model file and training (stages.offline.train.dataset, .model, .train, ``iamp train``).

A tiny data set from the first frames of the embedded sequence 013 keeps
these fast; nothing here asserts on wall-clock time.
"""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
import torch

from stages import cli
from bus_schemas import Header, TrackFrame
from stages.offline.train.dataset import (ARDataset, DatasetConfig, PositionNoise, build_dataset, dataset_key, corridor_errors, future_targets, route_weights,
                                          smoothed_acceleration)
from stages.lib.ar.features import ACCEL, FEATURE_NAMES, HISTORY_STEPS, HORIZON_STEPS
from stages.lib.ar.model import DEFAULT_MODEL_PATH, ARModel, ARNet, GRUNet, load_model, save_model
from stages.offline.train.fit import TrainConfig, _displacement, _loss, error_table, fit, split_samples
from stages.lib.datasets import DEFAULT_DATA_DIR

pytestmark = pytest.mark.skipif(not (DEFAULT_DATA_DIR / "maps").is_dir(), reason=f"embedded TAF-BW data not found at {DEFAULT_DATA_DIR}")

TINY = DatasetConfig(data_dir=DEFAULT_DATA_DIR, recordings=("k729_2022-03-16",), sequences=("013",), max_frames_per_sequence=300)


@pytest.fixture(scope="module")
def tiny() -> ARDataset:
    ds = build_dataset(TINY)
    assert len(ds) > 50
    return ds


@pytest.fixture(scope="module")
def tiny_model(tiny) -> ARModel:
    train, val, _ = split_samples(tiny, "time", 0.3, 0)
    model, _info = fit(TrainConfig(epochs=3, seed=0), tiny.subset(train), tiny.subset(val))
    return model


# --------------------------------------------------------------------------- data set


def test_dataset_shapes_and_provenance(tiny):
    n = len(tiny)
    assert tiny.x.shape == (n, HISTORY_STEPS, len(FEATURE_NAMES)) and tiny.x.dtype == np.float32
    assert tiny.mask.shape == (n, HISTORY_STEPS) and tiny.mask.dtype == bool and np.all(tiny.mask[:, -1])
    assert tiny.y.shape == (n, HORIZON_STEPS) and np.all(np.isfinite(tiny.y)) and np.all(np.isfinite(tiny.x))
    assert tiny.y_mask.shape == (n, HORIZON_STEPS) and tiny.y_mask.dtype == bool and np.all(tiny.y_mask.sum(axis=1) >= TINY.min_future_steps)
    assert np.all(tiny.y[~tiny.y_mask] == 0.0)
    assert tiny.weight.shape == (n,) and np.all((tiny.weight > 0) & (tiny.weight <= 1))
    assert tiny.recordings == ("k729_2022-03-16",) and tiny.sequences == ("k729_2022-03-16/013",)
    assert np.all(tiny.stamp_ns[1:] >= tiny.stamp_ns[:-1])
    assert tiny.counts["samples"] == n and tiny.counts.get("no_full_future", 0) > 0
    assert np.array_equal(tiny.last_acceleration, tiny.x[:, -1, ACCEL])


def test_targets_are_the_smoothed_acceleration_of_the_true_track(tiny):
    from stages.lib.datasets import load_recording

    seq = load_recording(DEFAULT_DATA_DIR, "k729_2022-03-16", ("013",)).sequences[0]
    full = tiny.y_mask.all(axis=1)
    k = int(np.argmax(np.where(full, np.abs(tiny.y).max(axis=1), -1.0)))  # the full-future sample with the most acceleration
    assert np.abs(tiny.y[k]).max() > 1.0
    rows = np.flatnonzero(seq.track_id == tiny.track_id[k])
    stamps, xy = seq.stamp_ns[rows], np.column_stack([seq.x_m[rows], seq.y_m[rows]])
    # independent: speed from central differences of positions, then a least-squares slope over ±0.7 s
    speed = np.hypot(*np.gradient(xy, 0.1, axis=0).T)
    i0 = int(np.searchsorted(stamps, tiny.stamp_ns[k]))
    slopes = []
    for j in range(i0 + 1, i0 + HORIZON_STEPS + 1):
        w = slice(max(j - 7, 0), j + 8)
        slopes.append(np.polyfit(stamps[w] * 1e-9, speed[w], 1)[0])
    assert np.corrcoef(slopes, tiny.y[k])[0, 1] > 0.9
    assert np.max(np.abs(np.asarray(slopes) - tiny.y[k])) < 0.5


def test_smoothed_acceleration_of_a_constant_acceleration_track():
    t = np.arange(60) * 0.1
    s = 2.0 * t + 0.5 * 1.5 * t**2
    xy = np.column_stack([s * math.cos(0.3), s * math.sin(0.3)])
    stamps = (t * 1e9).astype(np.int64)
    a = smoothed_acceleration(stamps, xy, 100_000_000, 15)
    assert np.all(np.isnan(a[:7])) and np.all(np.isnan(a[-7:]))  # the window would not be centred
    np.testing.assert_allclose(a[7:-7], 1.5, atol=1e-6)
    a = smoothed_acceleration(stamps, xy, 100_000_000, 15, edge_samples=15)
    assert np.isnan(a[14]) and np.isnan(a[-15]) and np.all(np.isfinite(a[15:-15]))
    gap = np.concatenate([stamps[:30], stamps[30:] + 500_000_000])  # a skip: two pieces, each long enough
    a = smoothed_acceleration(gap, xy, 100_000_000, 15, edge_samples=0)
    np.testing.assert_allclose(a, 1.5, atol=1e-6)
    assert np.all(np.isnan(smoothed_acceleration(stamps[:10], xy[:10], 100_000_000, 15)))


def test_dataset_cache_round_trip(tmp_path):
    cfg = DatasetConfig(data_dir=DEFAULT_DATA_DIR, recordings=("k729_2022-03-16",), sequences=("013",), max_frames_per_sequence=120)
    built = build_dataset(cfg, cache_dir=tmp_path)
    files = list(tmp_path.glob("ar_dataset_*.npz"))
    assert len(files) == 1 and built.key in files[0].name
    again = build_dataset(cfg, cache_dir=tmp_path)
    for name in ("x", "mask", "y", "y_mask", "weight", "track_id", "stamp_ns", "corridor_id"):
        assert np.array_equal(getattr(built, name), getattr(again, name))
    assert again.counts == built.counts and again.sequences == built.sequences


def test_two_trainings_writing_one_cached_dataset_at_once_both_succeed(tiny, tmp_path, monkeypatch):
    """Two ``iamp train`` runs that build the same cached data set (bench/generalisation.py's directions in parallel)
    both write it; once both have written, both rename: each from a file of its own (a shared temporary name had the
    second rename fail with FileNotFoundError), and the cache holds the data set, nothing else."""
    import threading

    both_written = threading.Barrier(2, timeout=30)
    real_write = ARDataset._write

    def write_then_wait(self, handle):
        real_write(self, handle)
        both_written.wait()

    monkeypatch.setattr(ARDataset, "_write", write_then_wait)
    path = tmp_path / f"ar_dataset_{tiny.key}.npz"
    errors: list[BaseException] = []

    def save() -> None:
        try:
            tiny.save(path)
        except BaseException as exc:  # noqa: BLE001 - reported below
            errors.append(exc)

    threads = [threading.Thread(target=save) for _ in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert errors == []
    assert [p.name for p in tmp_path.iterdir()] == [path.name]
    assert np.array_equal(ARDataset.load(path).x, tiny.x)


def test_position_noise_jitters_the_features_not_the_targets(tiny):
    noisy_cfg = dataclasses.replace(TINY, position_noise_m=0.5, noise_seed=3)
    assert dataset_key(noisy_cfg) != dataset_key(TINY)
    assert "position_noise_m" not in TINY.key_dict()  # data sets without it keep their keys (and caches)
    noisy = build_dataset(noisy_cfg)
    again = build_dataset(noisy_cfg)
    assert np.array_equal(noisy.x, again.x)  # deterministic for a seed
    # the same windows where matching and routes did not change: the true futures' targets are the clean ones
    clean = {(int(t), int(c), int(s)): i for i, (t, c, s) in enumerate(zip(tiny.track_id, tiny.corridor_id, tiny.stamp_ns))}
    common = [(i, clean[(int(t), int(c), int(s))]) for i, (t, c, s) in enumerate(zip(noisy.track_id, noisy.corridor_id, noisy.stamp_ns))
              if (int(t), int(c), int(s)) in clean]
    assert len(common) > 0.8 * len(tiny)
    a, b = np.array([i for i, _ in common]), np.array([j for _, j in common])
    assert np.array_equal(noisy.y[a], tiny.y[b]) and np.array_equal(noisy.y_mask[a], tiny.y_mask[b])
    speed = FEATURE_NAMES.index("speed_mps")
    assert not np.allclose(noisy.x[a][..., speed], tiny.x[b][..., speed])  # the speed read from jittered positions differs
    with pytest.raises(ValueError, match="position_noise_m"):
        dataclasses.replace(TINY, position_noise_m=-1.0)


def test_position_noise_draws_one_sigma_per_track_within_the_bound():
    frame = TrackFrame(header=Header(run_id="t", frame_index=0, stamp_ns=1, producer="t"), scene_id="s",
                       track_ids=np.arange(400, dtype=np.int64), agent_types=np.zeros(400, np.uint8),
                       x_m=np.zeros(400), y_m=np.zeros(400), vx_mps=np.ones(400), vy_mps=np.zeros(400), yaw_rad=np.zeros(400),
                       length_m=np.full(400, 4.0), width_m=np.full(400, 2.0))
    hook = PositionNoise(0.5, 7)
    first, second = hook(frame), hook(frame)
    sigma = np.array([hook._sigma[i] for i in range(400)])
    assert np.all((sigma >= 0) & (sigma <= 0.5)) and 0.2 < sigma.mean() < 0.3
    assert not np.array_equal(first.x_m, second.x_m)  # fresh noise each frame, the same σ per track
    assert np.array_equal(first.vx_mps, frame.vx_mps) and np.array_equal(first.track_ids, frame.track_ids)
    z = np.concatenate([first.x_m, second.x_m, first.y_m, second.y_m]) / np.tile(np.maximum(sigma, 1e-9), 4)
    assert 0.85 < z.std() < 1.15
    assert PositionNoise(0.0, 7)(frame) is frame


def test_partial_futures_short_histories_and_tied_routes_give_samples(tiny):
    """Version 4 of the data set: windows with part of their future, with less than 4 s of history, on every tied route."""
    assert np.any(~tiny.y_mask.all(axis=1)) and np.any(tiny.y_mask.all(axis=1))
    assert np.any(~tiny.mask.all(axis=1))  # a history shorter than 4 s (masked)
    partial = ~tiny.y_mask.all(axis=1)  # counted once per window (a tied window is several samples)
    assert tiny.counts.get("partial_future", 0) == len(set(zip(tiny.stamp_ns[partial].tolist(), tiny.track_id[partial].tolist())))
    # a tied window is one sample per tied corridor, at the same stamp and track, weights summing to 1
    windows: dict[tuple[int, int], float] = {}
    for t, tid, w in zip(tiny.stamp_ns.tolist(), tiny.track_id.tolist(), tiny.weight.tolist()):
        windows[(t, tid)] = windows.get((t, tid), 0.0) + w
    assert np.allclose(list(windows.values()), 1.0, atol=1e-5)
    assert np.any(tiny.weight < 1) and tiny.counts.get("route_tied", 0) > 0
    sizes = tiny.sizes()
    assert sizes["windows"] == pytest.approx(len(windows), abs=1e-3) and sizes["samples"] == len(tiny)
    assert sizes["cars"] == tiny.tracks > 0 and sizes["by_recording"]["k729_2022-03-16"]["samples"] == len(tiny)
    old = build_dataset(dataclasses.replace(TINY, tied_routes="drop", min_future_steps=HORIZON_STEPS))
    assert len(old) < len(tiny) and old.y_mask.all() and np.all(old.weight == 1)
    assert old.tracks < tiny.tracks


def test_future_targets_mask_missing_and_unknown_steps():
    from stages.offline.truth import Track

    stamps = np.arange(0, 30) * 100_000_000
    accel = np.linspace(-1, 1, 30)
    accel[:5] = np.nan
    track = Track(stamps.astype(np.int64), np.zeros((30, 2)), np.zeros(30), accel)
    a, known = future_targets(track, 0, 100_000_000, HORIZON_STEPS)
    assert known.tolist() == [False] * 4 + [True] * 25 + [False] * 11
    np.testing.assert_allclose(a[known], accel[5:30])
    a, known = future_targets(None, 0, 100_000_000, HORIZON_STEPS)
    assert not known.any() and np.all(np.isnan(a))


def test_route_weights_split_tied_routes():
    assert route_weights(np.array([0.3, 1.5, np.inf]), 2.0, 0.5, "weight") == ([(0, 1.0)], None)
    assert route_weights(np.array([2.5, 3.0]), 2.0, 0.5, "weight") == ([], "followed_no_corridor")
    assert route_weights(np.array([], float), 2.0, 0.5, "weight") == ([], "followed_no_corridor")
    tied = np.array([0.9, 0.3, 0.6, 5.0])
    assert route_weights(tied, 2.0, 0.5, "weight") == ([(1, 0.5), (2, 0.5)], "route_tied")
    assert route_weights(tied, 2.0, 0.5, "drop") == ([], "route_tied")
    assert route_weights(tied, 2.0, 0.5, "first") == ([(1, 1.0)], "route_tied")
    assert route_weights(np.array([0.1, 0.2, 0.3]), 2.0, 0.5, "weight")[0] == [(0, 1 / 3), (1, 1 / 3), (2, 1 / 3)]


def test_corridor_errors_is_the_followed_corridor_rule():
    from types import SimpleNamespace

    from stages.offline.truth import followed_corridor

    s = np.linspace(0, 50, 51)
    straight = SimpleNamespace(x_m=s, y_m=np.zeros_like(s), s_m=s)
    offset = SimpleNamespace(x_m=s, y_m=np.full_like(s, 1.0), s_m=s)
    short = SimpleNamespace(x_m=s[:5], y_m=np.zeros(5), s_m=s[:5])
    future = np.column_stack([np.linspace(10, 20, 11), np.full(11, 0.2)])
    errors = corridor_errors([straight, offset, short], future, min_inside=5)
    np.testing.assert_allclose(errors[:2], [0.2, 0.8], atol=1e-9)
    assert errors[2] == np.inf
    followed = followed_corridor([straight, offset, short], future, min_inside=5)
    assert followed.index == 0 and followed.error_m == pytest.approx(errors[0]) and followed.runner_up_m == pytest.approx(errors[1])
    assert np.all(np.isinf(corridor_errors([straight], np.zeros((0, 2)))))


# --------------------------------------------------------------------------- splits


def test_time_split_keeps_windows_apart(tiny):
    train, val, info = split_samples(tiny, "time", 0.3, 0)
    cut = info["time_cuts"]["k729_2022-03-16/013"]["cut_stamp_s"] * 1e9
    assert len(train) and len(val)
    assert np.all(tiny.stamp_ns[train] + 4e9 <= cut + 1) and np.all(tiny.stamp_ns[val] - 4e9 >= cut - 1)
    assert info["dropped_at_cut"] == len(tiny) - len(train) - len(val) > 0


def test_sequence_split_never_shares_a_sequence():
    rng = np.random.default_rng(0)
    n = 400
    ds = ARDataset(
        x=np.zeros((n, HISTORY_STEPS, len(FEATURE_NAMES)), np.float32), mask=np.ones((n, HISTORY_STEPS), bool),
        y=np.zeros((n, HORIZON_STEPS), np.float32), y_mask=np.ones((n, HORIZON_STEPS), bool), weight=np.ones(n, np.float32), recording=np.repeat([0, 1], n // 2).astype(np.int32),
        sequence=np.concatenate([rng.integers(0, 8, n // 2), np.full(n // 2, 8)]).astype(np.int32),
        track_id=rng.integers(0, 20, n), corridor_id=np.zeros(n, np.int64), stamp_ns=np.sort(rng.integers(0, 100_000_000_000, n)),
        recordings=("a", "b"), sequences=tuple(f"a/{i}" for i in range(8)) + ("b/0",),
        sequence_spans=np.array([[0, 100_000_000_000]] * 9), counts={},
    )
    train, val, info = split_samples(ds, "sequence", 0.2, 3)
    a_train = set(ds.sequence[train][ds.recording[train] == 0].tolist())
    a_val = set(ds.sequence[val][ds.recording[val] == 0].tolist())
    assert a_train and a_val and not (a_train & a_val)
    assert "b/0" in info["time_cuts"]  # the single-sequence recording is split by time
    assert np.all(ds.stamp_ns[train][ds.recording[train] == 1] <= info["time_cuts"]["b/0"]["cut_stamp_s"] * 1e9 - 4e9 + 1)
    train_r, val_r, info_r = split_samples(ds, "recording", 0.2, 0)
    assert set(ds.recording[train_r]) .isdisjoint(set(ds.recording[val_r]))
    assert split_samples(ds, "sequence", 0.2, 3)[1].tolist() == val.tolist()  # seeded


# --------------------------------------------------------------------------- model


def test_same_seed_gives_identical_weights(tiny):
    train, val, _ = split_samples(tiny, "time", 0.3, 0)
    weights = []
    for seed in (5, 5, 6):
        model, _ = fit(TrainConfig(epochs=2, seed=seed, hidden=8), tiny.subset(train), tiny.subset(val))
        weights.append({k: v.clone() for k, v in model.net.state_dict().items()})
    assert all(torch.equal(weights[0][k], weights[1][k]) for k in weights[0])
    assert not all(torch.equal(weights[0][k], weights[2][k]) for k in weights[0])


def test_displacement_loss_integrates_the_acceleration_errors_exactly():
    # a constant acceleration error a over t s is a displacement error a·t²/2 at every step's end
    err = torch.full((1, HORIZON_STEPS), 1.5)
    disp, w = _displacement(err, torch.ones(1, HORIZON_STEPS))
    t = 0.1 * torch.arange(1, HORIZON_STEPS + 1, dtype=torch.float32)
    assert torch.allclose(disp[0], 1.5 * t**2 / 2, atol=1e-5) and torch.equal(w, torch.ones(1, HORIZON_STEPS))
    # an error only in the first step: a·dt²/2 after it, then a·dt·(t − dt/2): early errors weigh most
    one = torch.zeros(1, HORIZON_STEPS)
    one[0, 0] = 2.0
    disp, _ = _displacement(one, torch.ones(1, HORIZON_STEPS))
    assert torch.allclose(disp[0], 2.0 * 0.1 * (t - 0.05), atol=1e-5)
    # a step is kept only while every step up to it is known, with the sample's weight; unknown targets are not read
    w = torch.full((2, HORIZON_STEPS), 0.5)
    w[1, 10] = 0.0
    y = torch.zeros(2, HORIZON_STEPS)
    y[1, 10] = float("nan")
    disp, kept = _displacement(torch.ones(2, HORIZON_STEPS) - y, w)
    assert torch.equal(kept[0], w[0]) and torch.all(kept[1, :10] == 0.5) and torch.all(kept[1, 10:] == 0)
    assert torch.all(torch.isfinite(disp))
    loss = _loss(torch.ones(2, HORIZON_STEPS), y, w, "displacement")
    assert torch.isfinite(loss) and float(loss) > float(_loss(torch.ones(2, HORIZON_STEPS), torch.zeros(2, HORIZON_STEPS), w, "accel")) > 0
    assert float(_loss(torch.zeros(2, HORIZON_STEPS), torch.zeros(2, HORIZON_STEPS), w, "displacement")) == 0.0


def test_displacement_loss_trains_its_own_weights(tiny):
    train, val, _ = split_samples(tiny, "time", 0.3, 0)
    fits = [fit(TrainConfig(epochs=2, seed=5, hidden=8, loss=loss), tiny.subset(train), tiny.subset(val)) for loss in ("accel", "displacement")]
    (a, info_a), (d, info_d) = fits
    assert not all(torch.equal(a.net.state_dict()[k], d.net.state_dict()[k]) for k in a.net.state_dict())
    # the validation loss is of the displacement (m) there: not the acceleration loss of the same net
    assert math.isfinite(info_d["best_val_loss"]) and info_d["best_val_loss"] != info_a["best_val_loss"]
    with pytest.raises(ValueError, match="loss"):
        TrainConfig(loss="position")


def test_predict_shapes_and_save_load_round_trip(tiny, tiny_model, tmp_path):
    tiny_model.metadata = {"note": "test", "values": [1.0, 2.0]}
    pred = tiny_model.predict(tiny.x, tiny.mask)
    assert pred.shape == (len(tiny), HORIZON_STEPS) and pred.dtype == np.float32 and np.all(np.isfinite(pred))
    assert tiny_model.predict(tiny.x[:0], tiny.mask[:0]).shape == (0, HORIZON_STEPS)
    with pytest.raises(ValueError, match="x must have shape"):
        tiny_model.predict(tiny.x[:, :, :5], tiny.mask)
    with pytest.raises(ValueError, match="mask must have shape"):
        tiny_model.predict(tiny.x, tiny.mask[:, :5])
    path = save_model(tmp_path / "sub" / "m.pt", tiny_model)
    loaded = load_model(path)
    np.testing.assert_array_equal(loaded.predict(tiny.x, tiny.mask), pred)
    np.testing.assert_array_equal(loaded.sigma_res_chunks, tiny_model.sigma_res_chunks)
    assert loaded.metadata == {"note": "test", "values": [1.0, 2.0]} and loaded.feature_names == FEATURE_NAMES
    assert torch.load(path, weights_only=True)["format"] == "hybrid-iamp/ar-model"


def test_model_without_a_feature_selects_its_columns(tiny):
    train, val, _ = split_samples(tiny, "time", 0.3, 0)
    model, _ = fit(TrainConfig(epochs=1, drop_features=("speed_mps",)), tiny.subset(train), tiny.subset(val))
    assert "speed_mps" not in model.feature_names and model.net.n_features == len(FEATURE_NAMES) - 1
    changed = tiny.x.copy()
    changed[:, :, FEATURE_NAMES.index("speed_mps")] += 5.0
    np.testing.assert_array_equal(model.predict(changed, tiny.mask), model.predict(tiny.x, tiny.mask))


def test_bad_model_files_give_a_value_error_naming_the_file(tiny_model, tmp_path):
    missing = tmp_path / "missing.pt"
    with pytest.raises(ValueError, match="missing.pt.*does not exist"):
        load_model(missing)
    garbage = tmp_path / "garbage.pt"
    garbage.write_bytes(b"this is not a torch file")
    with pytest.raises(ValueError, match="garbage.pt.*not a readable torch weights file") as raised:
        load_model(garbage)
    # one line, and not torch's advice to load it with weights_only=False (which would run the file's code)
    assert "\n" not in str(raised.value) and "weights_only" not in str(raised.value)
    good = save_model(tmp_path / "good.pt", tiny_model)
    truncated = tmp_path / "truncated.pt"
    truncated.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    with pytest.raises(ValueError, match="truncated.pt"):
        load_model(truncated)
    other = tmp_path / "other.pt"
    torch.save({"weights": torch.zeros(3)}, other)
    with pytest.raises(ValueError, match="other.pt.*not an AR model"):
        load_model(other)
    payload = torch.load(good, weights_only=True)
    payload["state_dict"] = {"body.0.weight": torch.zeros(2, 2)}
    broken = tmp_path / "broken.pt"
    torch.save(payload, broken)
    with pytest.raises(ValueError, match="broken.pt.*inconsistent"):
        load_model(broken)
    payload = torch.load(good, weights_only=True)
    del payload["sigma_res_chunks"]
    torch.save(payload, broken)
    with pytest.raises(ValueError, match="sigma_res_chunks"):
        load_model(broken)


def test_arnet_forms():
    linear, hidden, gru = ARNet(23), ARNet(23, hidden=16), GRUNet(23, hidden=8)
    assert sum(p.numel() for p in linear.parameters()) == (40 * 24) * 40 + 40
    z, m = torch.zeros(2, 40, 23), torch.ones(2, 40)
    assert linear(z, m).shape == (2, 40) and hidden(z, m).shape == (2, 40) and gru(z, m).shape == (2, 40)
    assert (linear.kind, hidden.kind, gru.kind) == ("ar", "ar", "gru")
    z2 = z.clone()
    z2[0, 5, 3] = 1.0  # the GRU reads the whole history, not only the newest step
    assert not torch.equal(gru(z2, m)[0], gru(z, m)[0]) and torch.equal(gru(z2, m)[1], gru(z, m)[1])
    with pytest.raises(ValueError):
        GRUNet(23, hidden=0)


def test_gru_model_trains_saves_and_loads_with_its_kind(tiny, tmp_path):
    train, val, _ = split_samples(tiny, "time", 0.3, 0)
    model, info = fit(TrainConfig(epochs=2, seed=0, kind="gru", hidden=8), tiny.subset(train), tiny.subset(val))
    assert model.kind == "gru" and info["epochs_run"] == 2
    path = save_model(tmp_path / "gru.pt", model)
    assert torch.load(path, weights_only=True)["kind"] == "gru"
    loaded = load_model(path)
    assert loaded.kind == "gru" and isinstance(loaded.net, GRUNet)
    np.testing.assert_array_equal(loaded.predict(tiny.x, tiny.mask), model.predict(tiny.x, tiny.mask))
    with pytest.raises(ValueError, match="kind"):
        TrainConfig(kind="transformer")
    with pytest.raises(ValueError, match="hidden"):
        TrainConfig(kind="gru", hidden=0)


def test_version_1_files_still_load_as_ar_nets(tiny_model, tmp_path):
    payload = torch.load(save_model(tmp_path / "new.pt", tiny_model), weights_only=True)
    assert payload["version"] == 2 and payload["kind"] == "ar"
    del payload["kind"]
    payload["version"] = 1
    torch.save(payload, tmp_path / "v1.pt")
    old = load_model(tmp_path / "v1.pt")
    assert old.kind == "ar" and old.hidden == tiny_model.hidden
    x, mask = np.zeros((3, HISTORY_STEPS, len(FEATURE_NAMES)), np.float32), np.ones((3, HISTORY_STEPS), bool)
    np.testing.assert_array_equal(old.predict(x, mask), tiny_model.predict(x, mask))
    payload["version"] = 3
    torch.save(payload, tmp_path / "v3.pt")
    with pytest.raises(ValueError, match="v3.pt.*format version 3"):
        load_model(tmp_path / "v3.pt")
    payload["version"], payload["kind"] = 2, "transformer"
    torch.save(payload, tmp_path / "bad_kind.pt")
    with pytest.raises(ValueError, match="bad_kind.pt.*transformer"):
        load_model(tmp_path / "bad_kind.pt")


def test_error_table_chunks():
    y = np.zeros((2, 40))
    pred = np.zeros((2, 40))
    pred[:, :4] = 1.0
    table = error_table(pred, y)
    assert table["mse"] == pytest.approx(0.1) and table["mse_chunks"][0] == 1.0 and table["mse_chunks"][1] == 0.0
    assert table["chunk_mean_rmse"][0] == 1.0
    # unknown steps do not count, and each sample counts by its weight
    known = np.ones((2, 40), bool)
    known[0, :4] = False
    pred[0, 4:8] = 3.0  # sample 0 is wrong in chunk 1, sample 1 in chunk 0
    masked = error_table(pred, y, known, np.array([1.0, 1.0]))
    assert masked["mse_chunks"][0] == 1.0 and masked["mse_chunks"][1] == pytest.approx(4.5)
    assert masked["mse"] == pytest.approx((4 * 9 + 4 * 1) / 76)
    assert masked["chunk_mean_rmse"][0] == pytest.approx(1.0)  # only sample 1 has chunk 0 whole
    weighted = error_table(pred, y, known, np.array([1.0, 0.0]))
    assert weighted["mse_chunks"][1] == pytest.approx(9.0) and math.isnan(weighted["mse_chunks"][0])


def test_shipped_model_loads_and_predicts(tiny):
    if not DEFAULT_MODEL_PATH.is_file():
        pytest.skip(f"no shipped model at {DEFAULT_MODEL_PATH}")
    model = load_model()
    assert model.feature_names == FEATURE_NAMES and model.sigma_res_chunks.shape == (10,)
    assert np.all(model.sigma_res_chunks > 0)
    pred = model.predict(tiny.x, tiny.mask)
    assert np.all(np.isfinite(pred))
    for key in ("feature_names", "recordings", "split", "seed", "validation", "date_utc", "git_commit"):
        assert key in model.metadata


# --------------------------------------------------------------------------- iamp train


def test_cli_bad_arguments_exit_2(tmp_path, capsys):
    assert cli.main(["train", "--bogus"]) == 2
    assert cli.main(["train", "--val-fraction", "1.5", "--no-progress", "--no-cache", "--out", str(tmp_path / "m.pt")]) == 2
    assert "val_fraction" in capsys.readouterr().err
    assert cli.main(["train", "--data", str(tmp_path / "nothing"), "--no-progress", "--out", str(tmp_path / "m.pt")]) == 2
    assert cli.main(["train", "--drop-feature", "nope", "--no-progress", "--out", str(tmp_path / "m.pt")]) == 2
    assert cli.main(["train", "--kind", "gru", "--hidden", "0", "--no-progress", "--out", str(tmp_path / "m.pt")]) == 2
    assert cli.main(["train", "--loss", "jerk", "--no-progress", "--out", str(tmp_path / "m.pt")]) == 2
    assert "hidden" in capsys.readouterr().err
    assert cli.main(["train", "--min-future-steps", "41", "--no-progress", "--out", str(tmp_path / "m.pt")]) == 2
    assert "min_future_steps" in capsys.readouterr().err
    assert cli.main(["train", "--split", "recording", "--sequence", "013", "--max-frames", "100", "--no-progress", "--no-cache",
                     "--out", str(tmp_path / "m.pt")]) == 2
    assert "two recordings" in capsys.readouterr().err
    if not torch.cuda.is_available():
        assert cli.main(["train", "--device", "cuda", "--no-progress", "--out", str(tmp_path / "m.pt")]) == 2
        assert "CUDA is not available" in capsys.readouterr().err
    assert not (tmp_path / "m.pt").exists()


def test_cli_trains_writes_weights_and_report(tmp_path, capsys):
    out, report = tmp_path / "m.pt", tmp_path / "r.json"
    argv = ["train", "--sequence", "013", "--max-frames", "300", "--split", "time", "--val-fraction", "0.3", "--epochs", "3",
            "--no-progress", "--no-cache", "--out", str(out), "--json", str(report)]
    assert cli.main(argv) == 0
    printed = capsys.readouterr().out
    assert "sigma_res" in printed and "zero" in printed and "last" in printed
    data = json.loads(report.read_text())
    for name in ("model", "zero", "last"):
        assert len(data["validation"][name]["mse_chunks"]) == 10
    assert data["sizes"]["train"] > 0 and data["sizes"]["val"] > 0 and len(data["sigma_res_chunks"]) == 10
    assert data["sizes"]["dataset"]["cars"] > 0 and data["inference_ms_per_frame"]["median_ms"] > 0
    assert data["model"]["kind"] == "ar" and load_model(out).kind == "ar"
    model = load_model(out)
    assert model.metadata["split"]["split"] == "time" and model.metadata["seed"] == 0
    assert model.metadata["sequences"]["val"] == ["k729_2022-03-16/013"]


def test_folds_choose_the_epochs_by_the_mean_of_repeated_splits_then_train_on_every_sample(tiny):
    from stages.offline.train.fit import _Trainer, fit_folds, fold_seed

    cfg = TrainConfig(epochs=6, patience=2, folds=2, seed=4, hidden=8, split="time", val_fraction=0.3)
    model, fitted, oof, oof_pred = fit_folds(cfg, tiny)
    history = fitted["history"]
    means = [h["val_loss"] for h in history]
    assert all(len(h["val_loss_by_split"]) == 2 for h in history)
    assert means == pytest.approx([float(np.mean(h["val_loss_by_split"])) for h in history])
    assert fitted["best_epoch"] == int(np.argmin(means)) and fitted["epochs_run"] == fitted["best_epoch"] + 1
    assert fitted["folds"]["split_seeds"] == [fold_seed(4, 0), fold_seed(4, 1)] and fold_seed(4, 0) != fold_seed(5, 0)
    # early stopping on the mean: it ran `patience` epochs past its best, or to the end
    assert len(history) == min(cfg.epochs, fitted["best_epoch"] + 1 + cfg.patience)
    # the out-of-fold part: each split's validation samples, predicted by its own net
    assert len(oof) == oof_pred.shape[0] == sum(len(split_samples(tiny, "time", 0.3, fold_seed(4, r))[1]) for r in range(2))
    assert np.isfinite(model.sigma_res_chunks).all() and (model.sigma_res_chunks > 0).all()
    # the final net: seeded `seed`, trained on every sample for the chosen number of epochs
    again = _Trainer(cfg, tiny, None, cfg.seed)
    for _ in range(fitted["epochs_run"]):
        assert math.isnan(again.epoch()[1])
    ref = again.finish().net.state_dict()
    assert all(torch.equal(ref[k], v) for k, v in model.net.state_dict().items())
    with pytest.raises(ValueError, match="folds"):
        TrainConfig(folds=1)


def test_cli_folds_writes_a_model_trained_on_every_sample(tmp_path, capsys):
    out, report = tmp_path / "m.pt", tmp_path / "r.json"
    argv = ["train", "--sequence", "013", "--max-frames", "300", "--split", "time", "--val-fraction", "0.3", "--epochs", "3",
            "--folds", "2", "--no-progress", "--no-cache", "--out", str(out), "--json", str(report)]
    assert cli.main(argv) == 0
    assert "split folds" in capsys.readouterr().out
    data = json.loads(report.read_text())
    assert data["split"]["split"] == "folds" and data["split"]["folds"] == 2 and len(data["split"]["fold_splits"]) == 2
    assert data["sizes"]["train"] == data["sizes"]["samples"]  # every sample trains the final net
    assert 1 <= data["training"]["folds"]["chosen_epochs"] == data["training"]["epochs_run"] <= 3
    meta = load_model(out).metadata
    assert meta["split"]["split"] == "folds"
    assert meta["sequences"]["val"] == [] and meta["sequences"]["out_of_fold"] == meta["sequences"]["train"] == ["k729_2022-03-16/013"]
    assert cli.main(["train", "--folds", "1", "--no-progress", "--out", str(tmp_path / "x.pt")]) == 2
    assert "folds" in capsys.readouterr().err


def test_patience_0_trains_every_epoch_and_keeps_the_last_weights(tiny):
    from stages.offline.train.fit import _Trainer

    train, val, _ = split_samples(tiny, "time", 0.3, 0)
    cfg = TrainConfig(epochs=4, patience=0, seed=2, hidden=8)
    model, info = fit(cfg, tiny.subset(train), tiny.subset(val))
    assert info["epochs_run"] == len(info["history"]) == 4
    again = _Trainer(cfg, tiny.subset(train), tiny.subset(val), 2)
    for _ in range(4):
        again.epoch()
    last = again.finish().net.state_dict()
    assert all(torch.equal(last[k], v) for k, v in model.net.state_dict().items())
    with pytest.raises(ValueError, match="patience"):
        TrainConfig(patience=-1)


def test_a_split_that_leaves_no_validation_sample_says_why(tmp_path, capsys):
    """One sequence, its last 2 % (2.3 s) for validation: the time cut leaves nothing after it with a sample's 4 s
    history. It said only "no samples to train on (N training, 0 validation)"."""
    from stages import cli

    code = cli.main(["train", "--recording", "k729_2022-03-16", "--sequence", "013", "--val-fraction", "0.02", "--epochs", "1", "--no-cache",
                     "--out", str(tmp_path / "m.pt"), "--no-progress"])
    err = capsys.readouterr().err
    assert code == 2 and "no validation samples: the sequence split left none of the" in err and "larger --val-fraction" in err, err
    assert not (tmp_path / "m.pt").exists()


def test_a_model_worse_than_zero_acceleration_on_validation_is_warned_about():
    """4 cars, 107 samples: a 38,440-parameter net whose validation MSE (0.96) was worse than predicting 0 (0.50),
    written with exit 0 and no word."""
    from stages.offline.train.fit import weak_model_warning

    report = {"validation": {"model": {"mse": 0.962}, "zero": {"mse": 0.499}}, "sizes": {"train": 107, "dataset": {"cars": 4}}}
    said = weak_model_warning(report)
    assert "worse than predicting zero acceleration (0.499)" in said and "107 training samples from 4 cars" in said
    report["validation"]["model"]["mse"] = 0.28
    assert weak_model_warning(report) == ""
    report["validation"]["model"]["mse"] = float("nan")  # no validation window: nothing to compare
    assert weak_model_warning(report) == ""


def test_iamp_train_writes_its_provenance_into_both_outputs(tmp_path):
    """The weights file had the git commit, date and configs but not the loss curve; the JSON the curve but not the
    commit, date, seed or configs: a researcher needed both files to know what a model was."""
    import json as _json

    from stages import cli
    from stages.lib.ar import load_model

    out, js = tmp_path / "m.pt", tmp_path / "m.json"
    assert cli.main(["train", "--sequence", "019", "002", "--max-frames", "60", "--epochs", "2", "--no-progress", "--no-cache",
                     "--accel-window", "2.0", "--out", str(out), "--json", str(js)]) == 0
    report, meta = _json.loads(js.read_text()), load_model(out).metadata
    for key in ("git_commit", "date_utc", "seed", "feature_config", "dataset_config", "torch", "history"):
        assert key in report and key in meta, key
    assert report["feature_config"]["accel_window_s"] == meta["feature_config"]["accel_window_s"] == 2.0
    assert meta["history"] == report["history"] and len(report["history"]) >= 1
    assert meta["sequences"] and len(meta["sequences"]) == 2  # both sequences given in one --sequence
