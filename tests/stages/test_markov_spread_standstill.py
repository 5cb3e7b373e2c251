"""Calibrated spread (``spread_calibration``, ``iamp calibrate``) and the hybrid standstill rates from the scene."""

from __future__ import annotations

import hashlib
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from stages.markov_prediction import RAW_GRIDS, MarkovPredictionConfig, MarkovPredictor
from stages.markov_prediction.spread import BLUR_MIN_VALUE, SCHEMA, SpreadTable, blur_grid, load_spread, write_spread
from stages.offline.calibrate import smallest_sigma
from tests.stages.test_markov_prediction import PLAIN, STAMP, _corridor, _corridor_set, _profiles, _relation, _relation_set, _vehicle

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def stencils():
    return MarkovPredictor(MarkovPredictionConfig(**PLAIN)).stencils


def _spread_file(tmp_path: Path, mode: str, sigma: float) -> Path:
    path = tmp_path / "spread.json"
    write_spread(path, {mode: SpreadTable((0.5, 2.0), np.full((3, 10), sigma))}, {"test": True})
    return path


def test_blur_grid_keeps_mass_and_centre_and_widens():
    from stages.markov_prediction.rasterise import GridFrame, SparseGrid

    frame = GridFrame(0.0, 0.0, 0.5, 80, 80)
    centre = 40 * 80 + 40
    grid = SparseGrid(np.array([centre, frame.n_cells + centre], np.int64), np.array([0.7, 0.7]))
    out = blur_grid(frame, grid, np.array([0.0, 3.0]))
    cells0, values0 = out.step(0, frame.n_cells)
    np.testing.assert_array_equal(cells0, [centre])  # σ 0: unchanged
    cells1, values1 = out.step(1, frame.n_cells)
    # the mass, less the far tails below BLUR_MIN_VALUE (under 0.01 % here); every cell kept above it
    assert values1.sum() == pytest.approx(0.7, rel=1e-4) and values1.sum() <= 0.7
    assert values1.min() > BLUR_MIN_VALUE
    rows, cols = np.divmod(cells1, frame.n_cols)
    assert float(values1 @ rows / values1.sum()) == pytest.approx(40.0, abs=1e-3)  # (the cut tails: 1e-4 cells off)
    spread_m = 0.5 * math.sqrt(float(values1 @ (cols - 40.0) ** 2 / values1.sum()))
    assert spread_m == pytest.approx(3.0, abs=0.1)
    assert np.all(np.diff(out.keys) > 0)  # still sorted unique keys


def test_calibrate_scores_the_blocks_as_the_stage_blurs_the_grid():
    """iamp calibrate's coverage on the blurred blocks = the coverage of the grid the stage publishes (blur_grid)."""
    from stages.markov_prediction.rasterise import GridFrame, SparseGrid
    from stages.offline.calibrate import _truth_in_blurred, truth_in_region

    rng = np.random.default_rng(3)
    frame = GridFrame(0.0, 0.0, 0.5, 120, 150)
    cells = np.unique(rng.integers(50 * 150 + 40, 70 * 150 + 90, 60))
    values = rng.random(cells.size)
    values /= values.sum()
    grid = SparseGrid(cells.astype(np.int64), values)
    for sigma in (0.0, 0.7, 2.0, 5.0, 11.0):
        blurred = blur_grid(frame, grid, np.array([sigma]))
        for cell in rng.integers(0, frame.n_cells, 40).tolist() + cells[:10].tolist():
            row, col = divmod(int(cell), frame.n_cols)
            future = np.array([[(col + 0.5) * 0.5, (row + 0.5) * 0.5]])
            covered, value = truth_in_region(frame, blurred, future, 0.9)
            fast = _truth_in_blurred(frame, cells, values, int(cell), sigma, 0.9)
            assert fast[0] == bool(covered[0]) and fast[1] == pytest.approx(value[0], rel=1e-9, abs=1e-15), (sigma, cell)


def test_spread_file_is_checked_and_read_per_mode_and_band(tmp_path):
    path = _spread_file(tmp_path, "cv", 2.0)
    table = load_spread(str(path), "cv", 10)
    assert table.band(0.2) == 0 and table.band(1.0) == 1 and table.band(5.0) == 2
    assert load_spread(str(path), "hybrid", 10) is None  # no table for that mode: nothing widened
    with pytest.raises(ValueError, match="3 x 12 finite values"):
        load_spread(str(path), "cv", 12)
    (tmp_path / "bad.json").write_text(json.dumps({"schema": "other"}))
    with pytest.raises(ValueError, match=SCHEMA):
        MarkovPredictor(MarkovPredictionConfig(mode="cv", spread_calibration=str(tmp_path / "bad.json")))
    with pytest.raises(ValueError, match="iamp calibrate"):
        MarkovPredictor(MarkovPredictionConfig(mode="cv", spread_calibration=str(tmp_path / "missing.json")))


@pytest.mark.parametrize("shape", ["isotropic", "along"])
@pytest.mark.parametrize("mode", ["baseline", "corridor_cv"])
def test_calibrated_spread_widens_the_grid_and_leaves_the_means(tmp_path, stencils, mode, shape):
    cs = _corridor_set(_vehicle(1, 8.0, [_corridor(7)]))
    plain = MarkovPredictor(MarkovPredictionConfig(mode=mode, **PLAIN, **RAW_GRIDS), stencils=stencils)
    wide = MarkovPredictor(MarkovPredictionConfig(mode=mode, spread_calibration=str(_spread_file(tmp_path, mode, 4.0)),
                                                  spread_online=False, spread_shape=shape, **PLAIN), stencils=stencils)
    a, _ = plain.process(cs, _relation_set(_relation(1, 7)))
    b, _ = wide.process(cs, _relation_set(_relation(1, 7)))
    np.testing.assert_array_equal(a.mean_xy_m, b.mean_xy_m)
    np.testing.assert_array_equal(a.position_probs, b.position_probs)  # the CorridorPredictions stay as they were
    for k in (0, 9):
        cells_a, values_a = a.vehicle_grids[1].step(k, a.grid_frame.n_cells)
        cells_b, values_b = b.vehicle_grids[1].step(k, b.grid_frame.n_cells)
        assert (values_b > 1e-4).sum() > (values_a > 1e-4).sum() + 10
        assert values_b.sum() == pytest.approx(values_a.sum(), rel=1e-2)


def test_smallest_sigma_interpolates_and_never_narrows():
    sig = np.array([0.0, 1.0, 2.0, 4.0])
    assert smallest_sigma(sig, np.array([0.95, 0.97, 0.98, 0.99]), 0.9) == 0.0
    assert smallest_sigma(sig, np.array([0.5, 0.7, 0.8, 1.0]), 0.9) == pytest.approx(3.0)
    assert smallest_sigma(sig, np.array([0.5, 0.6, 0.7, 0.8]), 0.9) == 4.0


def test_iamp_calibrate_writes_a_file_the_stage_reads(tmp_path):
    out = tmp_path / "cal" / "spread.json"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    run = subprocess.run([sys.executable, "-m", "stages.cli", "calibrate", "--mode", "cv", "corridor_cv", "--max-frames", "40",
                          "--stride", "0.8", "--no-progress", "--out", str(out)], cwd=ROOT, env=env, capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    assert "wrote" in run.stdout and out.is_file()
    data = json.loads(out.read_text())
    assert data["schema"] == SCHEMA and set(data["modes"]) == {"cv", "corridor_cv"}
    assert data["fitted_on"]["recordings"] and data["fitted_on"]["level"] == 0.9
    table = load_spread(str(out), "cv", 10)
    assert table.sigma_m.shape == (3, 10) and np.all(np.diff(table.sigma_m, axis=1) >= 0)
    assert table.speed_noise_gain == 1.0 and data["fitted_on"]["speed_noise_gain"] == 1.0  # the default gain is written
    from stages.lib.ar.model import DEFAULT_MODEL_PATH

    assert data["fitted_on"]["model_sha256"] == hashlib.sha256(DEFAULT_MODEL_PATH.read_bytes()).hexdigest()  # its weights
    MarkovPredictor(MarkovPredictionConfig(mode="cv", spread_calibration=str(out)))  # the stage takes it
    bad = subprocess.run([sys.executable, "-m", "stages.cli", "calibrate", "--mode", "cv", "--out", str(out), "--set",
                          f"spread_calibration={out}"], cwd=ROOT, env=env, capture_output=True, text=True)
    assert bad.returncode == 2 and "do not --set it" in bad.stderr


def _standing_scene(leader_speed: float | None):
    """A car standing on a straight road; a leader 6 m ahead standing or pulling away (or none)."""
    cs = _corridor_set(_vehicle(1, 0.0, [_corridor(7)]))
    rel = _relation(1, 7) if leader_speed is None else _relation(1, 7, leader=2, gap=6.0, leader_speed=leader_speed)
    return cs, _relation_set(rel)


def test_hybrid_standing_car_stays_unless_its_leader_pulls_away(stencils):
    """An AR profile that accelerates at 1.5 m/s²: a car behind a standing leader (or with none) stays within 0.3 m
    over 4 s with rates (0, 0, 1.5); behind a leader that drives off it starts; with () the fixed rate's mixture."""
    rates = {"hybrid_standstill_rates_hz": (0.0, 0.0, 1.5)}
    scene = MarkovPredictor(MarkovPredictionConfig(mode="hybrid", **rates, **PLAIN), stencils=stencils)
    plain = MarkovPredictor(MarkovPredictionConfig(mode="hybrid", hybrid_standstill_rates_hz=(), **PLAIN), stencils=stencils)
    moved = {}
    for leader in (None, 0.0, 3.0):
        cs, rs = _standing_scene(leader)
        prediction, issues = scene.process(cs, rs, acceleration_profiles=_profiles(1, 7, 1.5))
        moved[leader] = float(prediction.mean_s_m[0, -1]) - 5.0
        np.testing.assert_allclose(prediction.position_probs[0].sum(axis=1) + prediction.outside_mass[0], 1.0, atol=1e-5)
    assert abs(moved[None]) < 0.3 and abs(moved[0.0]) < 0.3, moved
    assert moved[3.0] > 5.0, moved
    old, _ = plain.process(*_standing_scene(0.0), acceleration_profiles=_profiles(1, 7, 1.5))
    assert float(old.mean_s_m[0, -1]) - 5.0 > 1.0  # the fixed rate 0.055 /s lets ~20 % start by 4 s
    with pytest.raises(ValueError, match="three rates"):
        MarkovPredictionConfig(mode="hybrid", hybrid_standstill_rates_hz=(0.1, 0.2))


def _at_intersection(rel, distance_m: float, length_m: float = 20.0):
    """``rel`` with one intersection whose entry lies ``distance_m`` ahead of the vehicle (negative: inside)."""
    import dataclasses

    entry = 5.0 + distance_m
    return dataclasses.replace(rel, intersection_ids=np.array([1], np.int64), intersection_entry_s_m=np.array([entry]),
                               intersection_exit_s_m=np.array([entry + length_m]), intersection_distance_m=np.array([distance_m]),
                               intersection_entry_lanelet_ids=np.array([1], np.int64))


def test_hybrid_standing_car_at_an_intersection_starts_with_the_fourth_rate(stencils):
    """A fourth rate is that of a car standing inside an intersection or within standstill_intersection_m of its entry
    (it waits for a gap); further back it stays; with three rates the intersection makes no difference."""
    from stages.markov_prediction.core import standstill_group

    four = MarkovPredictionConfig(mode="hybrid", hybrid_standstill_rates_hz=(0.0, 0.0, 1.5, 1.0), standstill_intersection_m=8.0, **PLAIN)
    three = MarkovPredictionConfig(mode="hybrid", hybrid_standstill_rates_hz=(0.0, 0.0, 1.5), **PLAIN)
    cs, _ = _standing_scene(None)
    near, inside, far, passed = (_at_intersection(_relation(1, 7), d) for d in (3.0, -5.0, 15.0, -30.0))
    standing_leader = _at_intersection(_relation(1, 7, leader=2, gap=6.0, leader_speed=0.0), 3.0)
    moving_leader = _at_intersection(_relation(1, 7, leader=2, gap=6.0, leader_speed=3.0), 3.0)
    assert [standstill_group(r, four) for r in (near, inside, far, passed, standing_leader, moving_leader)] == [3, 3, 0, 0, 3, 2]
    assert [standstill_group(r, three) for r in (near, inside, far, standing_leader)] == [0, 0, 0, 1]
    moved = {}
    for name, config in (("four", four), ("three", three)):
        predictor = MarkovPredictor(config, stencils=stencils)
        for where, rel in (("near", near), ("far", far)):
            prediction, _ = predictor.process(cs, _relation_set(rel), acceleration_profiles=_profiles(1, 7, 1.5))
            moved[name, where] = float(prediction.mean_s_m[0, -1]) - 5.0
    assert moved["four", "near"] > 4.0 and abs(moved["four", "far"]) < 0.3, moved
    assert abs(moved["three", "near"]) < 0.3, moved
    with pytest.raises(ValueError, match="three rates"):
        MarkovPredictionConfig(mode="hybrid", hybrid_standstill_rates_hz=(0.1, 0.2, 0.3, 0.4, 0.5))


def test_hybrid_start_accel_replaces_the_ar_inputs_of_standing_cars_only(stencils):
    """With hybrid_start_accel_mps2 the starting part of a standing car accelerates at that rate whatever the AR says
    (here -1 m/s²: it would not move); a moving car keeps its AR distributions."""
    rates = {"hybrid_standstill_rates_hz": (0.0, 0.0, 50.0)}  # behind a leader that pulls away: starts at once
    ar = MarkovPredictor(MarkovPredictionConfig(mode="hybrid", **rates, **PLAIN), stencils=stencils)
    start = MarkovPredictor(MarkovPredictionConfig(mode="hybrid", hybrid_start_accel_mps2=1.5, **rates, **PLAIN), stencils=stencils)
    cs, rs = _standing_scene(3.0)
    moved = {name: float(p.process(cs, rs, acceleration_profiles=_profiles(1, 7, -1.0))[0].mean_s_m[0, -1]) - 5.0
             for name, p in (("ar", ar), ("start", start))}
    assert moved["ar"] < 2.0 and 8.0 < moved["start"] < 14.0, moved  # ½·1.5·16 = 12 m
    moving = _corridor_set(_vehicle(1, 10.0, [_corridor(7)]))
    a = ar.process(moving, _relation_set(_relation(1, 7)), acceleration_profiles=_profiles(1, 7, -1.0))[0]
    b = start.process(moving, _relation_set(_relation(1, 7)), acceleration_profiles=_profiles(1, 7, -1.0))[0]
    np.testing.assert_allclose(a.mean_s_m, b.mean_s_m)


def test_speed_noise_widens_the_calibrated_spread_of_a_scattering_track_only(tmp_path, stencils):
    """With speed_noise_gain the σ of a vehicle whose speeds scatter grows by σ_v·t; a smooth track keeps the table's σ;
    the means never move; a file without the key (gain 0) ignores the scatter."""
    from stages.markov_prediction.core import SPEED_NOISE_CAP_MPS

    table = SpreadTable((0.5, 2.0), np.full((3, 10), 1.0), speed_noise_gain=1.0)
    t = (np.arange(10) + 1) * 0.4
    np.testing.assert_allclose(table.sigmas(8.0, 0.5, t), np.hypot(1.0, 0.5 * t))
    np.testing.assert_allclose(table.sigmas(8.0, 0.0, t), 1.0)
    path = tmp_path / "noise.json"
    write_spread(path, {"corridor_cv": table}, {"test": True})
    assert load_spread(str(path), "corridor_cv", 10).speed_noise_gain == 1.0
    plain_path = _spread_file(tmp_path, "corridor_cv", 1.0)
    assert load_spread(str(plain_path), "corridor_cv", 10).speed_noise_gain == 0.0

    def run(spread: Path, speeds) -> tuple:
        predictor = MarkovPredictor(MarkovPredictionConfig(mode="corridor_cv", spread_calibration=str(spread), spread_online=False, **PLAIN), stencils=stencils)
        for i, v in enumerate(speeds):  # 0.1 s apart; the last frame is predicted
            pred, _ = predictor.process(_corridor_set(_vehicle(1, v, [_corridor(7)]), stamp=STAMP + i * 100_000_000),
                                        _relation_set(_relation(1, 7), stamp=STAMP + i * 100_000_000))
        noise = predictor.speed_noise(1, STAMP + (len(speeds) - 1) * 100_000_000)
        cells, values = pred.vehicle_grids[1].step(9, pred.grid_frame.n_cells)
        return noise, int((values > 1e-4).sum()), pred.mean_xy_m

    smooth, scatter = [8.0] * 11, [8.0 + (1.5 if i % 2 else -1.5) for i in range(10)] + [8.0]
    n_smooth, cells_smooth, mean_smooth = run(path, smooth)
    n_scatter, cells_scatter, mean_scatter = run(path, scatter)
    assert n_smooth == pytest.approx(0.0, abs=1e-9) and 1.0 < n_scatter <= SPEED_NOISE_CAP_MPS
    assert cells_scatter > 2 * cells_smooth  # σ at 4 s √(1 + (1.6·4)²) ≈ 6.5 m against 1 m
    np.testing.assert_allclose(mean_scatter, mean_smooth)
    _, cells_plain, _ = run(plain_path, scatter)
    assert cells_plain == cells_smooth


def test_the_shipped_table_is_there_for_every_mode():
    """``spread_calibration = "shipped"``: the table of the shipped AR model, beside its weights and licence."""
    from stages.markov_prediction.spread import SHIPPED

    from stages.markov_prediction.spread import SHIPPED_BY_SHAPE

    attribution = (SHIPPED.parent / "ATTRIBUTION.md").read_text()
    assert (SHIPPED.parent / "LICENSE").is_file()
    for shape, file in SHIPPED_BY_SHAPE.items():  # one table per spread_shape, each attributed
        assert file.is_file() and file.parent == SHIPPED.parent and f"`{file.name}`" in attribution
        for mode in ("hybrid", "baseline", "corridor_cv", "cv"):
            table = load_spread("shipped", mode, 10, shape)
            assert table is not None and table.sigma_m.shape == (3, 10) and table.speed_noise_gain == 1.0
            if mode != "cv" or shape == "isotropic":
                assert table.shape == shape
    # the stage takes the one of its shape: "auto" is along for the corridor modes, round for cv
    assert MarkovPredictor(MarkovPredictionConfig(mode="corridor_cv", spread_calibration="shipped")).spread.shape == "along"
    assert MarkovPredictor(MarkovPredictionConfig(mode="cv", spread_calibration="shipped")).spread.shape == "isotropic"


def test_the_compiled_blur_gives_the_numpy_blurs_numbers():
    """``frame_kernels.blur_cells`` (one compiled call per step) = ``blur_step`` (np.bincount, scipy's gaussian_filter)
    then ``block_cells_sorted``, bit for bit: cells, values and their order; near the frame's edges too."""
    from stages.lib.markov import frame_kernels
    from stages.markov_prediction.rasterise import GridFrame
    from stages.markov_prediction.spread import block_cells_sorted, blur_step

    if not frame_kernels.available():
        pytest.skip("numba not importable")
    rng = np.random.default_rng(11)
    frame = GridFrame(0.0, 0.0, 0.5, 90, 130)
    for trial in range(40):
        centre_r, centre_c = rng.integers(0, frame.n_rows), rng.integers(0, frame.n_cols)  # edges included
        rows = np.clip(centre_r + rng.integers(-6, 7, 50), 0, frame.n_rows - 1)
        cols = np.clip(centre_c + rng.integers(-9, 10, 50), 0, frame.n_cols - 1)
        cells = np.unique(rows * frame.n_cols + cols).astype(np.int64)
        values = rng.random(cells.size) * 10.0 ** -rng.integers(0, 4)
        for sigma in (0.2, 0.7, 1.3, 3.0, 6.5, 11.0):
            s_cells = sigma / frame.cell_m
            want = block_cells_sorted(frame, *blur_step(frame, cells, values, sigma))
            got = frame_kernels.blur_cells(cells, values, frame.n_rows, frame.n_cols, s_cells, max(int(s_cells // 2.0), 1),
                                           int(np.ceil(3.0 * s_cells)), BLUR_MIN_VALUE)
            np.testing.assert_array_equal(got[0], want[0], err_msg=f"trial {trial}, sigma {sigma}")
            np.testing.assert_array_equal(got[1], want[1], err_msg=f"trial {trial}, sigma {sigma}")


def test_iamp_eval_warns_when_hybrid_s_spread_table_was_fitted_with_other_weights(tmp_path, capsys):
    """A table that `iamp calibrate` fitted for one model, read by `iamp eval` scoring another: applied without a word
    (hybrid's spread belongs to its model)."""
    from stages import cli
    from stages.lib.ar.model import DEFAULT_MODEL_PATH
    from stages.markov_prediction.spread import resolve

    data = json.loads(resolve("shipped", "along").read_text())
    assert "hybrid" in data["modes"]
    shipped_sha = hashlib.sha256(DEFAULT_MODEL_PATH.read_bytes()).hexdigest()
    for sha, warned in (("0" * 64, True), (shipped_sha, False)):
        table = tmp_path / f"spread_{sha[:4]}.json"
        table.write_text(json.dumps({**data, "fitted_on": {**data.get("fitted_on", {}), "model": "other.pt", "model_sha256": sha}}))
        assert cli.main(["eval", "--mode", "hybrid", "--max-frames", "5", "--no-progress", "--set", f"spread_calibration={table}"]) == 0
        out = capsys.readouterr().out
        assert ("WARNING: spread_calibration = " in out and "fitted with AR weights other.pt" in out) is warned, out[:600]
    # the default table (shipped) read while scoring weights of one's own: said too, with what to do
    import torch

    blob = torch.load(DEFAULT_MODEL_PATH, map_location="cpu", weights_only=False)
    own = tmp_path / "own.pt"
    torch.save({**blob, "note": "a copy saved again: other bytes"} if isinstance(blob, dict) else blob, own)
    assert hashlib.sha256(own.read_bytes()).hexdigest() != shipped_sha
    assert cli.main(["eval", "--mode", "hybrid", "--max-frames", "5", "--no-progress", "--model", str(own)]) == 0
    out = capsys.readouterr().out
    assert "WARNING: spread_calibration = shipped (the default): fitted with AR weights shipped" in out and "iamp calibrate --model" in out, out[:600]

