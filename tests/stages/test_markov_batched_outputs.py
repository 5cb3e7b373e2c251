"""The batched output helpers (one np.interp over every pair's centreline) give what one call per pair gives."""

from __future__ import annotations

import numpy as np
import pytest

from stages.markov_prediction.rasterise import Centrelines, cell_footprints, cell_footprints_batch, lateral_kernel


def _centrelines(rng, n):
    lines = []
    for b in range(n):
        m = int(rng.integers(2, 40))
        s = np.cumsum(rng.uniform(0.2, 3.0, m)) - rng.uniform(-50, 50)
        heading = np.cumsum(rng.normal(0, 0.4, m)) + 3.0 * b  # crosses ±π: unwrapped per pair
        heading = np.angle(np.exp(1j * heading))
        lines.append((s, rng.uniform(-100, 100) + np.cumsum(rng.normal(0, 1, m)), rng.uniform(-100, 100) + np.cumsum(rng.normal(0, 1, m)), heading))
    return lines


def _single_xy(s_m, x_m, y_m, heading_rad, q):
    s_in = np.clip(q, s_m[0], s_m[-1])
    h = np.interp(s_in, s_m, np.unwrap(heading_rad))
    return np.interp(s_in, s_m, x_m) + (q - s_in) * np.cos(h), np.interp(s_in, s_m, y_m) + (q - s_in) * np.sin(h), h


def test_centrelines_equal_one_interp_per_pair():
    rng = np.random.default_rng(3)
    lines = _centrelines(rng, 12)
    packed = Centrelines(*[list(a) for a in zip(*lines)])
    queries = np.stack([rng.uniform(s[0] - 20, s[-1] + 20, 37) for s, *_ in lines])  # inside, before and past each centreline
    queries[:, 0] = [s[0] for s, *_ in lines]  # the knots at both ends
    queries[:, 1] = [s[-1] for s, *_ in lines]
    x, y, h = packed.xy_heading(queries)
    for b, line in enumerate(lines):
        ex, ey, eh = _single_xy(*line, queries[b])
        np.testing.assert_allclose(x[b], ex, rtol=0, atol=1e-9)
        np.testing.assert_allclose(y[b], ey, rtol=0, atol=1e-9)
        np.testing.assert_allclose(h[b], eh, rtol=0, atol=1e-9)


def test_batched_footprints_equal_single():
    rng = np.random.default_rng(5)
    lines = _centrelines(rng, 7)
    packed = Centrelines(*[list(a) for a in zip(*lines)])
    lower = np.stack([s[0] - 5.0 + np.arange(30, dtype=np.float64) for s, *_ in lines])
    offsets, weights = lateral_kernel(0.8, 0.5)
    batch = cell_footprints_batch(packed, lower, 1.0, 3, offsets, weights)
    for b, line in enumerate(lines):
        one = cell_footprints(*line, lower[b], 1.0, 3, offsets, weights)
        for name in ("x_m", "y_m", "weights", "normal_x", "normal_y"):
            np.testing.assert_allclose(getattr(batch[b], name), getattr(one, name), rtol=0, atol=1e-9, err_msg=name)


def test_sum_by_key_equals_unique_and_bincount():
    """kernels.sum_by_key (rasterise._reduce: grids and their fusion) gives np.unique + np.bincount's keys and sums bit
    for bit, call after call (its scratch table is left clean), and falls back above its key bound."""
    from stages.lib.markov import kernels

    rng = np.random.default_rng(5)
    for size, top in ((0, 10), (1, 10), (50, 7), (20000, 833_000), (5000, 3_000_000), (300, 2 * kernels.SUM_BY_KEY_MAX_KEY)):
        keys = rng.integers(0, top, size)
        keys = np.concatenate([keys, keys[: size // 2]])  # repeated keys, sums of several values
        values = rng.normal(0, 1, keys.size) * 10.0 ** rng.integers(-8, 3, keys.size)  # sums whose order shows in the bits
        unique, inverse = np.unique(keys, return_inverse=True)
        got_keys, got_sums = kernels.sum_by_key(keys, values)
        np.testing.assert_array_equal(got_keys, unique)
        np.testing.assert_array_equal(got_sums, np.bincount(inverse, weights=values, minlength=unique.size))
        assert got_keys.dtype == np.int64 and got_sums.dtype == np.float64


def test_vehicle_grids_in_one_call_equal_vehicle_grid_per_vehicle():
    """rasterise.vehicle_grids (every vehicle in one compiled call) gives vehicle_grid's keys and sums bit for bit:
    vehicles of one and of several corridors, numpy and Python weights (numpy promotes w·p differently), a zero
    weight, a pair below min_mass, lateral shifts, samples off the grid and not finite; and without shifts."""
    from stages.markov_prediction.rasterise import GridFrame, cell_footprints_arrays, vehicle_grid, vehicle_grids

    rng = np.random.default_rng(9)
    lines = _centrelines(rng, 9)
    packed = Centrelines(*[list(a) for a in zip(*lines)])
    lower = np.stack([s[0] - 5.0 + np.arange(40, dtype=np.float64) for s, *_ in lines])
    offsets, weights = lateral_kernel(0.4, 0.5)
    batch = cell_footprints_arrays(packed, lower, 1.0, 4, offsets, weights)
    batch.centre_x[batch.rows[3, 7], :1] = np.nan  # not finite: off the grid (the first sub-sample's lateral samples)
    batch.centre_y[batch.rows[5, 2], 1] = np.inf
    probs = (rng.dirichlet(np.ones(40), (9, 10)) * (rng.random((9, 10, 40)) < 0.6)).astype(np.float32)
    probs[4] *= 1e-10  # below min_mass everywhere
    probs[:3, :, 33:] = 0.0  # cells without mass at any step (no footprints in a batch of the used cells)
    corridor_weights = [np.float64(w) for w in rng.uniform(0.1, 1.0, 9)]
    corridor_weights[1], corridor_weights[2], corridor_weights[6] = 0.7, 0.0, 1.0  # Python floats, and a zero weight
    shifts = rng.normal(0, 0.8, (9, 10))
    members = [[0, 1, 2], [3], [4, 5], [6, 7, 8]]
    frame = GridFrame(float(np.nanmin(batch.x_m)) + 15.0, float(np.nanmin(batch.y_m)) + 10.0, 0.5, 300, 280)  # part off the grid
    some = cell_footprints_arrays(packed, lower, 1.0, 4, offsets, weights, used=probs.max(axis=1) > 0)  # cells with mass only
    assert some.rows[3, 7] >= 0 and some.rows[5, 2] >= 0 and (some.rows < 0).any()
    some.centre_x[some.rows[3, 7], :1] = np.nan
    some.centre_y[some.rows[5, 2], 1] = np.inf
    for with_shifts in (True, False):
        got = vehicle_grids(frame, batch, probs, corridor_weights, members, shifts if with_shifts else None)
        got_some = vehicle_grids(frame, some, probs, corridor_weights, members, shifts if with_shifts else None)
        for a, b in zip(got, got_some):
            np.testing.assert_array_equal(a.keys, b.keys)
            np.testing.assert_array_equal(a.values, b.values)
        for grid, m in zip(got, members):
            want = vehicle_grid(frame, [batch.pair(b) for b in m], [probs[b] for b in m], [corridor_weights[b] for b in m],
                                [shifts[b] for b in m] if with_shifts else None)
            np.testing.assert_array_equal(grid.keys, want.keys)
            np.testing.assert_array_equal(grid.values, want.values)
            assert grid.keys.dtype == np.int64 and grid.values.dtype == np.float64
        assert sum(g.keys.size for g in got) > 1000 and sum(g.keys.size > 0 for g in got) >= 3


def test_fuse_step_by_step_equals_the_product_over_every_key():
    """rasterise.fuse with the grid's n_cells (frame_kernels.fuse_sorted: per step, each cell's 1 − Π (1 − g) in vehicle
    order) gives the keys of numpy's reduction over every key exactly and its values to rounding; a cell of one
    vehicle keeps its value bit for bit; every value is the log-sum form's (−expm1 Σ log1p(−g)) to 1e-9 relative
    down to the MotionGrid's floor (1e-5); values are clipped to [0, 1 − 1e-7]; a NaN stays NaN; unsorted keys take
    numpy's path."""
    from stages.markov_prediction.rasterise import _CLIP, SparseGrid, fuse

    rng = np.random.default_rng(11)
    n_cells, n_k = 5000, 10
    grids = []
    for n in range(25):
        keys = np.unique(rng.integers(0, n_k * n_cells, int(rng.integers(0, 3000))))
        grids.append(SparseGrid(keys, rng.uniform(0, 1, keys.size) * 10.0 ** rng.integers(-6, 1, keys.size)))
    grids[3] = SparseGrid(grids[3].keys, np.where(np.arange(grids[3].keys.size) % 7 == 0, 1.0, grids[3].values))  # clipped below 1
    grids[5] = SparseGrid(grids[5].keys, np.where(np.arange(grids[5].keys.size) % 11 == 0, -0.5, grids[5].values))  # clipped to 0
    want = fuse(grids)
    got = fuse(grids, n_cells)
    np.testing.assert_array_equal(got.keys, want.keys)
    np.testing.assert_allclose(got.values, want.values, rtol=1e-13, atol=0)
    assert got.keys.size > 10000
    all_keys = np.concatenate([g.keys for g in grids])
    all_g = np.clip(np.concatenate([g.values for g in grids]), 0.0, 1.0 - _CLIP)
    unique, inverse, counts = np.unique(all_keys, return_inverse=True, return_counts=True)
    np.testing.assert_array_equal(got.keys, unique)
    single = counts[inverse] == 1
    assert single.any() and (~single).any()
    np.testing.assert_array_equal(got.values[inverse[single]], all_g[single])  # one vehicle: its own value
    log_form = -np.expm1(np.bincount(inverse, weights=np.log1p(-all_g)))
    floor = log_form >= 1e-5
    np.testing.assert_allclose(got.values[floor], log_form[floor], rtol=1e-9)
    np.testing.assert_allclose(got.values, log_form, rtol=1e-6, atol=1e-15)
    assert got.values.max() < 1.0 and got.values.min() >= 0.0  # (each term clipped below 1: no cell is certain)
    # a cell of many vehicles, by hand, in vehicle order
    many = [SparseGrid(np.array([7], np.int64), np.array([v])) for v in (0.3, 0.5, 0.25, 1e-8)]
    expect = 1.0 - (1.0 - 0.3) * (1.0 - 0.5) * (1.0 - 0.25) * (1.0 - 1e-8)
    assert fuse(many, n_cells).values[0] == expect
    nan = fuse([SparseGrid(np.array([1, 2], np.int64), np.array([np.nan, 0.5])), SparseGrid(np.array([1], np.int64), np.array([0.5]))], n_cells)
    assert np.isnan(nan.values[0]) and nan.values[1] == 0.5
    shuffled = [SparseGrid(g.keys[::-1].copy(), g.values[::-1].copy()) for g in grids[:2]]  # not sorted: numpy's path
    mixed = fuse(shuffled, n_cells)
    np.testing.assert_array_equal(mixed.keys, fuse(shuffled).keys)
    np.testing.assert_array_equal(mixed.values, fuse(shuffled).values)


def test_fuse_on_threads_gives_the_same_bytes(monkeypatch):
    """frame_kernels.fuse_sorted with its steps shared out between threads (ranges of about equal terms) gives the
    one-call fusion's keys and values bit for bit, also with empty grids and steps without terms; a run that is not
    sorted, or one with a key out of order across a thread's range, still gives None (numpy's path)."""
    from stages.lib.markov import frame_kernels
    from stages.markov_prediction.rasterise import _CLIP, SparseGrid, fuse

    if not frame_kernels.available():
        pytest.skip("numba is not importable here")
    monkeypatch.setattr(frame_kernels, "TERMS_PER_THREAD", 100)  # threads on small grids too
    rng = np.random.default_rng(5)
    n_cells, n_k = 3000, 12
    grids = [SparseGrid(np.zeros(0, np.int64), np.zeros(0))]
    for n in range(20):
        keys = np.unique(rng.integers(0, n_k * n_cells, int(rng.integers(0, 2500))))
        keys = keys[(keys // n_cells) != 4]  # a step without terms
        grids.append(SparseGrid(keys, rng.uniform(0, 1, keys.size) * 10.0 ** rng.integers(-6, 1, keys.size)))
    one = fuse(grids, n_cells, threads=1)
    assert one.keys.size > 5000
    for threads in (2, 3, 5):
        many = fuse(grids, n_cells, threads=threads)
        assert many.keys.tobytes() == one.keys.tobytes() and many.values.tobytes() == one.values.tobytes()
    flat_keys = [g.keys for g in grids]
    values = np.concatenate([g.values for g in grids])
    # vehicle_grids' arrays as they are (VehicleGrids.flat: no joining again), the same bytes
    from stages.markov_prediction.rasterise import VehicleGrids

    ptr = np.concatenate(([0], np.cumsum([k.size for k in flat_keys])))
    joined = VehicleGrids(grids)
    joined.flat = (np.concatenate(flat_keys), values, ptr)
    for threads in (1, 2):
        got = fuse(joined, n_cells, threads=threads)
        assert got.keys.tobytes() == one.keys.tobytes() and got.values.tobytes() == one.values.tobytes()
    assert frame_kernels.fuse_sorted(joined.flat[0], values, n_cells, 1.0 - _CLIP, ptr=ptr[:-1]) is None  # ptr not the arrays'
    assert frame_kernels.fuse_sorted(flat_keys, values, n_cells, 1.0 - _CLIP, threads=3) is not None
    swapped = [k.copy() for k in flat_keys]
    j = int(np.argmax([k.size for k in swapped]))
    mid = swapped[j].size // 2
    swapped[j][mid], swapped[j][mid + 1] = swapped[j][mid + 1], swapped[j][mid]  # one pair out of order
    assert frame_kernels.fuse_sorted(swapped, values, n_cells, 1.0 - _CLIP, threads=3) is None
    assert frame_kernels.fuse_sorted(swapped, values, n_cells, 1.0 - _CLIP, threads=1) is None
    negative = [k.copy() for k in flat_keys]
    negative[j][0] = -1
    assert frame_kernels.fuse_sorted(negative, values, n_cells, 1.0 - _CLIP, threads=2) is None
    far = [k.copy() for k in flat_keys]
    far[j][mid] = far[j][-1] + 5 * n_cells  # larger than the run's last key, in its middle
    assert frame_kernels.fuse_sorted(far, values, n_cells, 1.0 - _CLIP, threads=2) is None
    mixed = fuse([SparseGrid(s, values[:s.size]) for s in swapped[j:j + 1]], n_cells, threads=2)  # numpy's path
    want = fuse([SparseGrid(s, values[:s.size]) for s in swapped[j:j + 1]])
    np.testing.assert_array_equal(mixed.keys, want.keys)


def test_footprint_bounds_equal_min_max_of_used_samples():
    """FootprintBatch.bounds (compiled, no sample arrays) gives np.min / np.max over the used cells' samples; None
    without a used cell; a NaN sample gives numpy's answer (NaN)."""
    rng = np.random.default_rng(13)
    lines = _centrelines(rng, 6)
    packed = Centrelines(*[list(a) for a in zip(*lines)])
    lower = np.stack([s[0] - 5.0 + np.arange(30, dtype=np.float64) for s, *_ in lines])
    offsets, weights = lateral_kernel(0.4, 0.5)
    from stages.markov_prediction.rasterise import cell_footprints_arrays

    batch = cell_footprints_arrays(packed, lower, 1.0, 4, offsets, weights)
    used = rng.random((6, 30)) < 0.3
    used[2] = False
    x, y = batch.x_m, batch.y_m
    want = (np.min(x[used]), np.max(x[used]), np.min(y[used]), np.max(y[used]))
    assert batch.bounds(used) == want
    assert batch.bounds(np.zeros_like(used)) is None
    some = cell_footprints_arrays(packed, lower, 1.0, 4, offsets, weights, used=used)  # the used cells' footprints only
    assert some.bounds(used) == want and some.centre_x.shape == (int(used.sum()), 4)
    np.testing.assert_array_equal(some.x_m[used], x[used])
    assert np.isnan(some.x_m[~used]).all()
    b, i = np.argwhere(used)[0]
    batch.centre_y[batch.rows[b, i], 0] = np.nan
    assert np.isnan(batch.bounds(used)[2])
    # wide lateral kernels (the spread's, 31 offsets; read at each line's two ends) and many lines: still bit for bit
    for sigma in (0.4, 1.5):
        wide_offsets, wide_weights = lateral_kernel(sigma, 0.5)
        many = _centrelines(rng, 40)
        lower_many = np.stack([s[0] - 5.0 + 0.7 * np.arange(60, dtype=np.float64) for s, *_ in many])
        wide = cell_footprints_arrays(Centrelines(*[list(a) for a in zip(*many)]), lower_many, 0.7, 4, wide_offsets, wide_weights)
        used_many = rng.random((40, 60)) < 0.5
        xm, ym = wide.x_m, wide.y_m
        assert wide.bounds(used_many) == (np.min(xm[used_many]), np.max(xm[used_many]), np.min(ym[used_many]), np.max(ym[used_many]))


def test_admissible_speeds_of_many_profiles_equal_one_at_a_time():
    """priority.admissible_speeds_batch (profiles of different lengths padded into one array) gives each profile's
    admissible_speeds bit for bit: short and long profiles, non-finite curvature, uneven knots."""
    from stages.markov_prediction import priority as pr

    rng = np.random.default_rng(17)
    lat = np.array([3.0, 2.5, 2.0, 1.5])
    s_list, k_list, limits = [], [], []
    for b in range(12):
        n = int(rng.integers(1, 90))
        s = np.cumsum(rng.uniform(0.2, 1.5, n)) if b % 2 else rng.uniform(-20, 20) + 0.5 * np.arange(n)
        kappa = rng.normal(0, 0.05, n)
        if b % 5 == 0 and n > 3:
            kappa[1] = np.nan
        s_list.append(s)
        k_list.append(kappa)
        limits.append(float(rng.uniform(5, 20)))
    got = pr.admissible_speeds_batch(s_list, k_list, limits, lat, 2.5, 3.0)
    for b in range(12):
        want = pr.admissible_speeds(s_list[b], k_list[b], limits[b], lat, 2.5, 3.0)
        assert got[b].shape == (4, s_list[b].size)
        np.testing.assert_array_equal(got[b], want)
    assert pr.admissible_speeds_batch([], [], [], lat, 2.5, 3.0) == []


def test_compiled_admissible_speeds_equal_the_numpy_code(monkeypatch):
    """priority.admissible_speeds_batch through kernels.admissible_rows (compiled) gives the numpy code's numbers bit
    for bit: padded rows, a one-point profile, zero and non-finite curvature, NaN and infinite speed limits, a negative
    lateral acceleration (NaN speeds), a zero brake, s of both signs."""
    from stages.lib.markov import kernels
    from stages.markov_prediction import priority as pr

    if not kernels.available():
        import pytest

        pytest.skip("numba does not import")
    rng = np.random.default_rng(23)
    s_list, k_list, limits = [], [], []
    for b in range(14):
        n = 1 if b == 3 else int(rng.integers(2, 120))
        s = np.cumsum(rng.uniform(0.1, 1.5, n)) - rng.uniform(0, 40)
        kappa = np.zeros(n) if b == 5 else rng.normal(0, 0.08, n)
        if b % 4 == 0 and n > 4:
            kappa[2], kappa[-1] = np.nan, np.inf
        s_list.append(s)
        k_list.append(kappa)
        limits.append(np.nan if b == 7 else np.inf if b == 8 else float(rng.uniform(5, 20)))
    for lat, brake in ((np.array([3.0, 2.5, 2.0, 1.5]), 2.5), (np.array([2.0, -1.0, 0.0]), 0.0)):
        with np.errstate(invalid="ignore", divide="ignore"):
            got = pr.admissible_speeds_batch(s_list, k_list, limits, lat, brake, 3.0)
            monkeypatch.setattr(kernels, "available", lambda: False)
            want = pr.admissible_speeds_batch(s_list, k_list, limits, lat, brake, 3.0)
            monkeypatch.undo()
        for g, w in zip(got, want):
            np.testing.assert_array_equal(g, w)
            assert g.shape == w.shape and np.array_equal(np.signbit(g), np.signbit(w))
    assert any(np.isnan(w).any() for w in want) and any(np.isfinite(w[0]).all() and w.size > 3 for w in want)  # the cases reach both


def test_unwrap_each_equals_np_unwrap_of_each_array(monkeypatch):
    """rasterise.unwrap_each (np.unwrap's steps on all the arrays at once, the running sums compiled:
    frame_kernels.add_running_sums) gives np.unwrap of each array bit for bit, with the compiled step and without it:
    arrays of 0, 1, 2 and many points, jumps past ±π (and of exactly ±π), -0.0, NaN and inf."""
    from stages.lib.markov import frame_kernels
    from stages.markov_prediction.rasterise import unwrap_each

    rng = np.random.default_rng(31)
    arrays = [np.zeros(0), np.array([2.5]), np.array([3.0, -3.0]), np.array([-0.0, 0.0, np.pi, 0.0, -np.pi, 0.0])]
    for n in (3, 7, 8, 9, 50, 400):
        a = np.cumsum(rng.normal(0.0, 1.2, n))
        arrays.append(np.mod(a + np.pi, 2 * np.pi) - np.pi)  # wrapped: many jumps
    arrays[-2][5], arrays[-3][4] = np.nan, np.inf
    with np.errstate(invalid="ignore"):
        want = np.concatenate([np.unwrap(a) for a in arrays])
        got = unwrap_each(arrays)
        assert got.tobytes() == want.tobytes()
        if frame_kernels.available():
            monkeypatch.setattr(frame_kernels, "add_running_sums", lambda *args: False)  # the numpy loop
            assert unwrap_each(arrays).tobytes() == want.tobytes()
