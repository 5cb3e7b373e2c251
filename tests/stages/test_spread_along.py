"""``spread_shape = "along"``: the spread applied along each corridor (s) before rasterising, and across it per step."""

from __future__ import annotations

import json

import numpy as np
import pytest

from stages.lib.datasets import DEFAULT_DATA_DIR
from stages.lib.markov import MarkovGridConfig, frame_kernels, load_or_build_stencils
from stages.markov_prediction import RAW_GRIDS, MarkovPredictionConfig, MarkovPredictor
from stages.markov_prediction.rasterise import (
    Centrelines, GridFrame, cell_footprints_arrays, lateral_kernel, lateral_table, vehicle_grid, vehicle_grids,
)
from stages.markov_prediction.spread import SCHEMA, along_spread, blur_along, fold_behind


def _probs(rng, shape, density=0.3):
    return (rng.random(shape) * (rng.random(shape) < density)).astype(np.float32)


def test_blur_along_compiled_equals_the_numpy_definition(monkeypatch):
    rng = np.random.default_rng(1)
    probs = _probs(rng, (6, 8, 70))
    sigma = rng.uniform(0, 9, (6, 8))
    sigma[0] = 0.0
    sigma[1, 3] = np.nan  # not finite: as is
    sigma[2, 1] = 0.2  # narrower than a cell
    got = blur_along(probs, sigma)
    monkeypatch.setattr(frame_kernels, "numba", None)
    want = blur_along(probs, sigma)
    assert got.dtype == np.float32 and got.shape == probs.shape
    np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-12)
    np.testing.assert_array_equal(got[0], probs[0])
    np.testing.assert_array_equal(got[1, 3], probs[1, 3])
    with pytest.raises(ValueError, match="sigmas"):
        blur_along(probs, sigma[:3])


def test_blur_along_keeps_mass_and_mean_inside_and_drops_what_leaves_the_window():
    probs = np.zeros((1, 3, 100), np.float32)
    probs[0, :, 50] = 1.0  # a point in the middle
    probs[0, 2, 50] = 0.0
    probs[0, 2, 2] = 1.0  # a point near the start of the window
    sigma = np.array([[0.0, 5.0, 5.0]])
    out = blur_along(probs, sigma)
    np.testing.assert_array_equal(out[0, 0], probs[0, 0])
    cells = np.arange(100)
    assert out[0, 1].sum() == pytest.approx(1.0, abs=1e-4)  # the Gaussian's tail past 4σ and below 1e-6 only
    assert (out[0, 1] * cells).sum() / out[0, 1].sum() == pytest.approx(50.0, abs=1e-6)
    assert (out[0, 1] > 0).sum() > 30 and out[0, 1, 50] == out[0, 1].max()
    assert 0.6 < out[0, 2].sum() < 0.7  # about a third of the mass went behind the window's start: dropped
    assert np.all(out >= 0)


def _batch(rng, n_pairs, n_cells, offsets, weights):
    lines = []
    for b in range(n_pairs):
        m = int(rng.integers(3, 30))
        s = np.cumsum(rng.uniform(0.5, 3.0, m))
        heading = np.cumsum(rng.normal(0, 0.3, m)) + b
        lines.append((s, np.cumsum(np.cos(heading) * 2.0), np.cumsum(np.sin(heading) * 2.0), np.angle(np.exp(1j * heading))))
    packed = Centrelines(*[list(a) for a in zip(*lines)])
    lower = np.stack([s[0] - 3.0 + np.arange(n_cells, dtype=np.float64) for s, *_ in lines])
    return cell_footprints_arrays(packed, lower, 1.0, 4, offsets, weights)


def test_fold_behind_moves_the_blurs_mass_ahead_of_the_start_and_keeps_the_chains_own():
    """What the blur carried behind a pair's start cell goes to the mirrored cell ahead of it; the chain's own mass
    behind the start (its measurement spread) stays; the total is kept where the mirror stays in the window."""
    rng = np.random.default_rng(3)
    before = np.zeros((3, 4, 40), np.float32)
    before[:, :, 10:13] = [0.2, 0.5, 0.3]  # each pair's own mass on cells 10..12, a little behind its start (11)
    out = blur_along(before, np.tile(rng.uniform(1.0, 6.0, (3, 1)), (1, 4)))
    start = np.array([11, 11, 38])  # (the third pair's mirrors fall past the window: that mass is dropped)
    folded = out.copy()
    fold_behind(folded, before, start)
    for b in range(3):
        j0 = start[b]
        assert np.all(folded[b, :, :j0] <= np.maximum(before[b, :, :j0], 0) + 1e-7), "behind the start: at most the chain's own"
        assert np.all(folded[b, :, :j0] >= np.minimum(out[b, :, :j0], before[b, :, :j0]) - 1e-7)
        moved = out[b, :, :j0] - folded[b, :, :j0]  # (K, j0)
        gained = folded[b, :, j0 + 1:] - out[b, :, j0 + 1:]
        if 2 * j0 < before.shape[2]:
            np.testing.assert_allclose(folded[b].sum(axis=1), out[b].sum(axis=1), rtol=1e-5)
            np.testing.assert_allclose(gained[:, :j0], moved[:, ::-1], atol=1e-7)  # cell j0 - d -> j0 + d
    np.testing.assert_array_equal(folded[:, :, 11], out[:, :, 11])  # the start cell itself is not touched
    unchanged = out.copy()
    fold_behind(unchanged, before, np.zeros(3, np.int64))  # nothing behind: nothing moves
    np.testing.assert_array_equal(unchanged, out)


@pytest.mark.parametrize("fold", [True, False])
def test_along_spread_compiled_equals_pad_blur_fold_and_cut(monkeypatch, fold):
    """along_spread's one compiled pass gives the numpy sequence (pad, blur_along, fold_behind, the cells past the end
    set to 0) bit for bit: rows without a σ, starts before, inside and past the window, ends inside it."""
    rng = np.random.default_rng(7)
    n_b, n_k, n_l, pad = 5, 6, 40, 9
    probs = _probs(rng, (n_b, n_k, n_l), density=0.5)
    sigma = rng.uniform(0.2, 2.0, (n_b, n_k))
    sigma[0] = 0.0  # as is (copied into the padded window)
    sigma[1, 2] = np.nan
    start = np.array([-3, 0, 12, 30, n_l + 2 * pad + 5]) if fold else None
    beyond = np.zeros((n_b, n_l + 2 * pad), np.bool_)
    beyond[2, 35:] = True
    beyond[4, 50:] = True
    got = along_spread(probs, sigma, pad, start, beyond)
    monkeypatch.setattr(frame_kernels, "numba", None)
    want = along_spread(probs, sigma, pad, start, beyond)
    assert got.dtype == want.dtype == np.float32 and got.shape == (n_b, n_k, n_l + 2 * pad)
    np.testing.assert_array_equal(got, want)
    padded = np.pad(probs, ((0, 0), (0, 0), (pad, pad)))
    by_hand = blur_along(padded, sigma)
    if fold:
        fold_behind(by_hand, padded, start)
    by_hand[beyond[:, None, :].repeat(n_k, axis=1)] = 0.0
    np.testing.assert_array_equal(want, by_hand)
    assert np.any(got[2, :, :35] > 0) and not np.any(got[2, :, 35:]) and not np.any(got[4, :, 50:])
    with pytest.raises(ValueError, match="sigmas"):
        along_spread(probs, sigma[:3], pad, start, beyond)


def test_lateral_spread_per_step_compiled_equals_vehicle_grid():
    """vehicle_grids(lateral=...) (compiled) gives vehicle_grid with the same per-step sample weights bit for bit; the
    steps left at the base σ have the plain grids' samples."""
    rng = np.random.default_rng(4)
    n_b, n_k, n_l = 7, 6, 30
    sig = np.full((n_b, n_k), 0.4)
    sig[:, 2:] = rng.uniform(0.4, 1.5, (n_b, n_k - 2))
    offsets, base, rows, table = lateral_table(sig, 0.4, 0.5)
    assert table is not None and (rows[:, :2] == -1).all() and (rows[:, 2:] >= 0).all()
    assert offsets.size > lateral_kernel(0.4, 0.5)[0].size
    batch = _batch(rng, n_b, n_l, offsets, base)
    probs = _probs(rng, (n_b, n_k, n_l), 0.5)
    weights = [float(w) for w in rng.uniform(0.2, 1.0, n_b)]
    members = [[0, 1], [2], [3, 4, 5], [6]]
    frame = GridFrame(float(np.nanmin(batch.x_m)) - 1.0, float(np.nanmin(batch.y_m)) - 1.0, 0.5, 400, 400)
    shifts = rng.normal(0, 0.3, (n_b, n_k))
    got = vehicle_grids(frame, batch, probs, weights, members, shifts, lateral=(rows, table))
    from stages.markov_prediction.rasterise import sample_weight_rows

    lat_rows, sample_w = sample_weight_rows(batch, (rows, table))  # pair b's (K, P) weights: sample_w[lat_rows[b]]
    for grid, m in zip(got, members):
        want = vehicle_grid(frame, [batch.pair(b) for b in m], [probs[b] for b in m], [weights[b] for b in m],
                            [shifts[b] for b in m], step_weights=[sample_w[lat_rows[b]] for b in m])
        np.testing.assert_array_equal(grid.keys, want.keys)
        np.testing.assert_array_equal(grid.values, want.values)
    # the steps at the base σ: the same cells and sums as the grids of the base kernel alone (its ±2.5σ samples)
    narrow = cell_footprints_arrays(Centrelines([np.array([0.0, 50.0])], [np.array([0.0, 50.0])], [np.array([0.0, 0.0])],
                                                [np.array([0.0, 0.0])]), np.arange(20.0)[None, :], 1.0, 4, *lateral_kernel(0.4, 0.5))
    wide = cell_footprints_arrays(Centrelines([np.array([0.0, 50.0])], [np.array([0.0, 50.0])], [np.array([0.0, 0.0])],
                                              [np.array([0.0, 0.0])]), np.arange(20.0)[None, :], 1.0, 4, offsets, base)
    p1 = _probs(rng, (1, n_k, 20), 0.5)
    f1 = GridFrame(-5.0, -5.0, 0.5, 40, 80)
    a = vehicle_grids(f1, narrow, p1, [1.0], [[0]])[0]
    b = vehicle_grids(f1, wide, p1, [1.0], [[0]], lateral=(np.full((1, n_k), -1, np.int64), table))[0]
    np.testing.assert_array_equal(a.keys, b.keys)
    np.testing.assert_allclose(a.values, b.values, rtol=1e-12)
    # a wider step holds more cells across the corridor and the same mass
    c = vehicle_grids(f1, wide, p1, [1.0], [[0]], lateral=(np.full((1, n_k), table.shape[0] - 1, np.int64), table))[0]
    assert c.keys.size > a.keys.size and c.values.sum() == pytest.approx(a.values.sum(), rel=1e-9)


def test_lateral_spread_per_step_on_two_threads_gives_the_same_grids():
    """vehicle_grids(threads=2) splits the vehicles into runs (at least PAIRS_PER_THREAD pairs each); the per-step
    lateral rows are indexed by the pair, so every run gives the grids one thread gives."""
    rng = np.random.default_rng(8)
    n_b, n_k, n_l = 48, 5, 25
    sig = rng.uniform(0.4, 1.5, (n_b, n_k))
    sig[::3, :2] = 0.4
    offsets, base, rows, table = lateral_table(sig, 0.4, 0.5)
    batch = _batch(rng, n_b, n_l, offsets, base)
    probs = _probs(rng, (n_b, n_k, n_l), 0.5)
    weights = [float(w) for w in rng.uniform(0.2, 1.0, n_b)]
    members = [[2 * i, 2 * i + 1] for i in range(n_b // 2)]
    frame = GridFrame(float(np.nanmin(batch.x_m)) - 1.0, float(np.nanmin(batch.y_m)) - 1.0, 0.5, 500, 500)
    one = vehicle_grids(frame, batch, probs, weights, members, None, threads=1, lateral=(rows, table))
    two = vehicle_grids(frame, batch, probs, weights, members, None, threads=2, lateral=(rows, table))
    assert sum(g.keys.size for g in one) > 1000
    for a, b in zip(one, two):
        np.testing.assert_array_equal(a.keys, b.keys)
        np.testing.assert_array_equal(a.values, b.values)


def test_the_shape_and_the_cap_are_checked_and_resolved():
    for mode in ("hybrid", "baseline", "corridor_cv"):  # "auto": along the map corridors
        assert MarkovPredictionConfig(mode=mode).spread_shape == "along"
    assert MarkovPredictionConfig(mode="cv").spread_shape == "isotropic"  # a straight ray: round
    assert MarkovPredictionConfig(mode="cv").spread_online_max_mps == 1.5
    assert MarkovPredictionConfig(spread_shape="isotropic").spread_online_max_mps == 1.5
    assert MarkovPredictionConfig(spread_shape="along").spread_online_max_mps == 3.0
    assert MarkovPredictionConfig(spread_shape="along", spread_online_max_mps=2.0).spread_online_max_mps == 2.0
    with pytest.raises(ValueError, match="spread_shape"):
        MarkovPredictionConfig(spread_shape="round")
    with pytest.raises(ValueError, match="spread_lateral_ratio"):
        MarkovPredictionConfig(spread_lateral_ratio=-0.1)


def test_iamp_calibrate_fits_a_table_for_the_along_shape(tmp_path, capsys):
    """With spread_shape "along" (auto for the corridor modes) every candidate is scored on the vehicle's grid rebuilt
    along its corridors, and the table says so; the stage warns when a table's shape is not the one it applies."""
    import argparse
    import logging

    from stages.markov_prediction.spread import load_spread
    from stages.offline.calibrate import add_arguments, run_cli

    parser = argparse.ArgumentParser()
    add_arguments(parser)
    out = tmp_path / "s.json"
    args = parser.parse_args(["--data", str(DEFAULT_DATA_DIR), "--out", str(out), "--mode", "corridor_cv", "cv", "--max-frames", "60",
                              "--stride", "0.8", "--no-progress"])  # spread_shape "auto": along for corridor_cv, round for cv
    assert run_cli(args) == 0, capsys.readouterr().err
    table = load_spread(str(out), "corridor_cv", MarkovPredictionConfig().n_steps)
    assert table.shape == "along" and json.loads(out.read_text())["modes"]["corridor_cv"]["shape"] == "along"
    assert load_spread(str(out), "cv", MarkovPredictionConfig().n_steps).shape == "isotropic"
    assert np.all(np.diff(table.sigma_m, axis=1) >= 0)

    class Catch(logging.Handler):
        def __init__(self):
            super().__init__()
            self.said = []

        def emit(self, record):
            self.said.append(record.getMessage())

    catch = Catch()
    log = logging.getLogger("test.spread_shape")
    log.addHandler(catch)
    MarkovPredictor(MarkovPredictionConfig(mode="corridor_cv", spread_calibration=str(out), spread_shape="isotropic"), log=log)  # warned
    MarkovPredictor(MarkovPredictionConfig(mode="corridor_cv", spread_calibration=str(out)), log=log)  # auto: along
    assert len(catch.said) == 1 and "fitted for spread_shape 'along'" in catch.said[0]
    bad = json.loads(out.read_text())
    bad["modes"]["corridor_cv"]["shape"] = "square"
    out.write_text(json.dumps(bad))
    with pytest.raises(ValueError, match="shape"):
        load_spread(str(out), "corridor_cv", MarkovPredictionConfig().n_steps)


def test_in_the_stage_the_along_spread_keeps_means_and_mass_with_fewer_cells(frames, tmp_path):
    n_steps = MarkovPredictionConfig().n_steps
    table = tmp_path / "spread.json"
    sigma = [[0.3] * n_steps, [1.0] * n_steps, [0.5 + 0.6 * k for k in range(n_steps)]]  # standing, slow, fast
    table.write_text(json.dumps({"schema": SCHEMA, "modes": {"corridor_cv": {"bands_mps": [0.5, 2.0], "sigma_m": sigma}}}))
    stencils = load_or_build_stencils(MarkovGridConfig())
    make = lambda **kw: MarkovPredictor(MarkovPredictionConfig(mode="corridor_cv", **kw), stencils=stencils)  # noqa: E731
    plain, iso, along = make(**RAW_GRIDS), make(spread_calibration=str(table), spread_online=False, spread_shape="isotropic"), \
        make(spread_calibration=str(table), spread_online=False)
    last = max(frames, key=lambda f: sum(v.speed_mps > 3.0 for v in f["corridor_set"].vehicles if v.corridors))
    args = (last["corridor_set"], last["relation_set"], last["scene"], last["track_frame"])
    p0, p_iso, p_along = (m.process(*args, intention_belief=last["intention_belief"])[0] for m in (plain, iso, along))
    np.testing.assert_array_equal(p_along.mean_xy_m, p0.mean_xy_m)  # the means (and mADE) do not move
    np.testing.assert_array_equal(p_along.position_probs, p0.position_probs)
    moving = [t for t, v in p_along.start_speeds_mps.items() if v > 2.0]
    assert moving, "no moving vehicle in the frame"
    p_sym = make(spread_calibration=str(table), spread_online=False, spread_fold_start=False).process(*args, intention_belief=last["intention_belief"])[0]
    for t in moving:
        g0, gi, ga, gs = p0.vehicle_grids[t], p_iso.vehicle_grids[t], p_along.vehicle_grids[t], p_sym.vehicle_grids[t]
        assert g0.keys.size < ga.keys.size < gi.keys.size  # wider than none, fewer cells than the round blur
        assert ga.keys.size <= gs.keys.size  # folded ahead of the start: no more cells than the symmetric blur
        n_cells = p_along.grid_frame.n_cells
        last_k = n_steps - 1
        for g, frame in ((ga, p_along.grid_frame), (gs, p_sym.grid_frame)):
            assert g.step(last_k, frame.n_cells)[1].sum() == pytest.approx(g0.step(last_k, p0.grid_frame.n_cells)[1].sum(), rel=0.02)


def test_regrid_gives_the_stages_own_along_grid(frames, tmp_path):
    """FramePrediction.regrid (iamp calibrate's candidates) rebuilds a vehicle's grid as the stage makes it with a table
    of that σ: the same mass per map cell (the two grids' frames differ: compared by cell position)."""
    n_steps = MarkovPredictionConfig().n_steps
    sigma = [0.4 + 0.5 * k for k in range(n_steps)]
    table = tmp_path / "spread.json"
    table.write_text(json.dumps({"schema": SCHEMA, "modes": {"corridor_cv": {"bands_mps": [0.5, 2.0], "sigma_m": [sigma] * 3,
                                                                             "shape": "along"}}}))
    stencils = load_or_build_stencils(MarkovGridConfig())
    stage = MarkovPredictor(MarkovPredictionConfig(mode="corridor_cv", spread_calibration=str(table), spread_shape="along"), stencils=stencils)
    # iamp calibrate widens the grid's margin so that no candidate's blur leaves it; so does this one
    keeper = MarkovPredictor(MarkovPredictionConfig(mode="corridor_cv", grid_margin_m=40.0), stencils=stencils)
    keeper.keep_geometry = True
    last = max(frames, key=lambda f: sum(v.speed_mps > 3.0 for v in f["corridor_set"].vehicles if v.corridors))
    args = (last["corridor_set"], last["relation_set"], last["scene"], last["track_frame"])
    a = stage.process(*args, intention_belief=last["intention_belief"])[0]
    b = keeper.process(*args, intention_belief=last["intention_belief"])[0]
    assert a.regrid is None and b.regrid is not None

    def by_position(frame, grid):
        k, cell = np.divmod(grid.keys, frame.n_cells)
        row, col = np.divmod(cell, frame.n_cols)
        x = np.round(frame.origin_x_m + col * frame.cell_m, 6)
        y = np.round(frame.origin_y_m + row * frame.cell_m, 6)
        return dict(zip(zip(k.tolist(), x.tolist(), y.tolist()), grid.values.tolist()))

    assert a.vehicle_grids
    for track, grid in a.vehicle_grids.items():
        want = by_position(a.grid_frame, grid)
        got = by_position(b.grid_frame, b.regrid(track, np.asarray(sigma)))
        inside = {key: v for key, v in got.items() if key in want}
        assert sum(got.values()) - sum(inside.values()) < 1e-6  # nothing where the stage has no cell (its frame holds all)
        assert set(want) == set(inside)
        np.testing.assert_allclose([inside[key] for key in want], list(want.values()), rtol=1e-9, atol=1e-15)
