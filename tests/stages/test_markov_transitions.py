"""Offline Markov stencils, their sparse/convolution forms, the cache and the batched propagation."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from stages.lib.markov import (
    InputMatrix,
    InputPerState,
    InputReplaced,
    MarkovGridConfig,
    MarkovPropagator,
    TransitionKind,
    build_stencils,
    gamma_from_priority,
    initial_state,
    load_or_build_stencils,
    psi_matrix,
)
from stages.lib.markov.transitions import cache_path, integrate_saturated, load_stencils, save_stencils
from stages.lib.markov import kernels

KINDS = list(TransitionKind)

# A small grid for the tests that do not need the default one.
SMALL = MarkovGridConfig(v_max_mps=6.0, n_s_cells=30, n_steps=6, n_state_samples=5, n_input_samples=4, n_sub_times=4)


def _with(config, **change):
    """``config`` with some parameters changed."""
    params = {k: v for k, v in config.params().items() if k != "model_version"}
    params.update(change)
    return MarkovGridConfig(**params)


@pytest.fixture(scope="module")
def default_stencils():
    return build_stencils(MarkovGridConfig())


@pytest.fixture(scope="module")
def small_stencils():
    return build_stencils(SMALL)


# ---------------------------------------------------------------------------
# Continuous model and stencils
# ---------------------------------------------------------------------------


def test_integrate_saturated_matches_fine_euler():
    s0 = np.array([0.3, 0.3, 0.3, 0.0])
    v0 = np.array([1.0, 19.5, 10.0, 0.0])
    accel = np.array([-3.0, 2.0, 0.5, -1.0])
    s, v = s0.copy(), v0.copy()
    dt = 1e-5
    for _ in range(int(round(0.4 / dt))):
        v_next = np.clip(v + accel * dt, 0.0, 20.0)
        s += 0.5 * (v + v_next) * dt
        v = v_next
    s_exact, v_exact = integrate_saturated(s0, v0, accel, 0.4, 20.0)
    np.testing.assert_allclose(s_exact, s, atol=1e-6)
    np.testing.assert_allclose(v_exact, v, atol=1e-9)
    # Stopped after 1/3 s, frozen there; capped at v_max after 0.25 s.
    assert v_exact[0] == 0.0 and s_exact[0] == pytest.approx(0.3 + 1.0 / 6.0)
    assert v_exact[1] == 20.0
    assert s_exact[3] == 0.0


@pytest.mark.parametrize("kind", KINDS)
def test_every_stencil_column_sums_to_one(default_stencils, kind):
    sums = default_stencils.column_sums(kind)
    assert sums.shape == (10, 40)
    np.testing.assert_allclose(sums, 1.0, atol=1e-12)
    assert np.all(default_stencils.kernel(kind) >= 0)


def test_default_grid_sizes(default_stencils):
    # docs/method.md §3.3 [M]: nnz(Υ(τ)) ≈ 1.7e5, nnz(Υ([0, τ])) ≈ 4.5e5 on the default grid.
    point = default_stencils.expand_sparse(TransitionKind.TIME_POINT)
    interval = default_stencils.expand_sparse(TransitionKind.TIME_INTERVAL)
    assert point.shape == (40_001, 40_001)
    assert 1.5e5 < point.nnz < 1.9e5
    assert 4.0e5 < interval.nnz < 5.0e5
    assert default_stencils.n_offsets == 9  # 0 … ⌈v_max·τ/Δs⌉


@pytest.mark.parametrize("kind", KINDS)
def test_expanded_matrix_is_column_stochastic_with_absorbing_outside(small_stencils, kind):
    n_s = 12
    matrix = small_stencils.expand_sparse(kind, n_s).toarray()
    n_states = SMALL.n_inputs * SMALL.n_v_cells * n_s
    assert matrix.shape == (n_states + 1, n_states + 1)
    np.testing.assert_allclose(matrix.sum(axis=0), 1.0, atol=1e-12)
    outside_column = np.zeros(n_states + 1)
    outside_column[-1] = 1.0
    np.testing.assert_array_equal(matrix[:, -1], outside_column)
    # Mass reaches the outside cell only from the last D-1 s-cells.
    s_of_state = np.arange(n_states) % n_s
    leaking = matrix[-1, :-1] > 0
    assert leaking.any()
    assert s_of_state[leaking].min() >= n_s - (small_stencils.n_offsets - 1)
    np.testing.assert_allclose(small_stencils.leak(kind, n_s).ravel(), matrix[-1, :-1], atol=1e-15)
    # Block-diagonal over α, and each block equals the per-α expansion.
    block = SMALL.n_v_cells * n_s
    for alpha in range(SMALL.n_inputs):
        own = slice(alpha * block, (alpha + 1) * block)
        per_alpha = small_stencils.expand_sparse(kind, n_s, alpha=alpha).toarray()
        np.testing.assert_array_equal(matrix[own, own], per_alpha[:-1, :-1])
        np.testing.assert_allclose(matrix[-1, own], per_alpha[-1, :-1], atol=1e-15)
        np.testing.assert_array_equal(np.delete(matrix[:-1, own], np.arange(own.start, own.stop), axis=0), 0.0)


@pytest.mark.parametrize("kind", KINDS)
def test_sparse_matrix_and_convolution_agree(small_stencils, kind):
    torch = pytest.importorskip("torch")
    n_s, n_in, n_v = 20, SMALL.n_inputs, SMALL.n_v_cells
    rng = np.random.default_rng(0)
    p = rng.random((n_in, n_v, n_s))
    p /= p.sum()
    moved = small_stencils.expand_sparse(kind, n_s) @ np.append(p.ravel(), 0.0)
    weight = torch.as_tensor(small_stencils.conv_weight(kind))
    x = torch.nn.functional.pad(torch.as_tensor(p.reshape(1, n_in * n_v, n_s)), (small_stencils.n_offsets - 1, 0))
    conv = torch.nn.functional.conv1d(x, weight, groups=n_in).numpy().ravel()
    np.testing.assert_allclose(conv, moved[:-1], atol=1e-14)
    assert moved[-1] > 0  # random mass near the end leaks out
    np.testing.assert_allclose(moved[-1], (small_stencils.leak(kind, n_s) * p).sum(), atol=1e-14)


@pytest.mark.parametrize("kind", KINDS)
def test_stencil_does_not_depend_on_s(small_stencils, kind):
    n_s = 30
    matrix = small_stencils.expand_sparse(kind, n_s).tocsc()
    n_v = SMALL.n_v_cells
    for alpha in (0, 4, 9):
        for v_cell in (0, 5, n_v - 1):
            col = (alpha * n_v + v_cell) * n_s
            a = matrix[:-1, col + 3].toarray().ravel().reshape(-1, n_s)
            b = matrix[:-1, col + 10].toarray().ravel().reshape(-1, n_s)
            np.testing.assert_array_equal(a[:, 3 : n_s - 7], b[:, 10:n_s])
            np.testing.assert_allclose(a.sum(), 1.0, atol=1e-12)


@pytest.mark.parametrize("kind", KINDS)
def test_standstill_keeps_mass_at_zero_speed(default_stencils, kind):
    # docs/method.md §3.2: a cell at v ∈ [0, 0.5] under [-3, -2.5] m/s² keeps all its mass at v = 0.
    ds_cells, v_targets, probs = default_stencils.stencil(kind, 0, 0)
    assert np.all(v_targets == 0)
    assert np.all(ds_cells >= 0)
    assert probs.sum() == pytest.approx(1.0, abs=1e-12)
    # The vehicle creeps at most v²/(2|a|) = 0.05 m before it stops.
    assert probs[ds_cells == 0].sum() >= 0.94


def test_standstill_over_a_full_run(default_stencils):
    cfg = default_stencils.config
    p0 = np.zeros((1, cfg.n_inputs, cfg.n_v_cells, cfg.n_s_cells), np.float32)
    p0[0, 0, 0, 5] = 1.0
    result = MarkovPropagator(default_stencils).run(p0, None, with_interval=True, with_final_state=True)
    assert result.final_state[0, :, 1:, :].sum() == 0.0
    np.testing.assert_allclose(result.velocity_probs[0, :, 0], 1.0, atol=1e-6)
    assert result.position_probs[0, :, :5].sum() == 0.0  # never backwards
    assert result.interval_position_probs[0, :, :5].sum() == 0.0
    assert result.position_probs[0, -1, 5:7].sum() == pytest.approx(1.0, abs=1e-6)


# ---------------------------------------------------------------------------
# Agreement with Monte Carlo (docs/method.md §3.5)
# ---------------------------------------------------------------------------


def _markov_moments(stencils, s_cell, v_cell, alpha):
    cfg = stencils.config
    p0 = np.zeros((1, cfg.n_inputs, cfg.n_v_cells, cfg.n_s_cells), np.float32)
    p0[0, alpha, v_cell, s_cell] = 1.0
    result = MarkovPropagator(stencils, prune_threshold=0.0).run(p0, None)  # Γ = identity
    probs = result.position_probs[0, -1].astype(np.float64)
    assert probs.sum() == pytest.approx(1.0, abs=1e-5)
    centres = cfg.s_centres_m()
    mean = float(probs @ centres)
    return mean, float(np.sqrt(probs @ (centres - mean) ** 2))


def _monte_carlo_moments(cfg, s_lo_m, v_lo_mps, alpha, n_samples=200_000, seed=7):
    """Uniform start in the cell; the acceleration is redrawn uniformly in the input cell every τ."""
    rng = np.random.default_rng(seed)
    s = s_lo_m + rng.random(n_samples) * cfg.ds_m
    v = v_lo_mps + rng.random(n_samples) * cfg.dv_mps
    lo, hi = cfg.input_edges()[alpha], cfg.input_edges()[alpha + 1]
    for _ in range(cfg.n_steps):
        s, v = integrate_saturated(s, v, lo + rng.random(n_samples) * (hi - lo), cfg.tau_s, cfg.v_max_mps)
    return float(s.mean()), float(s.std())


def test_monte_carlo_cruise(default_stencils):
    # s ∈ [1, 2) m, v ∈ [10, 10.5) m/s, a ∈ [-0.5, 0] m/s² for 4 s. Measured: Markov 40.500 ± 1.82,
    # MC 40.501 ± 0.77 (docs/method.md §3.5: 40.50 / 40.50, 1.82 / 0.77).
    markov_mean, markov_std = _markov_moments(default_stencils, 1, 20, 5)
    mc_mean, mc_std = _monte_carlo_moments(default_stencils.config, 1.0, 10.0, 5)
    assert markov_mean == pytest.approx(mc_mean, abs=0.05)
    assert markov_std >= mc_std  # numerical diffusion: the grid spreads, never sharpens


def test_monte_carlo_braking(default_stencils):
    # s ∈ [1, 2) m, v ∈ [4, 4.5) m/s, a ∈ [-3, -2.5] m/s²: stops after ~1.4 s. Measured: Markov 4.807, MC 4.791.
    markov_mean, markov_std = _markov_moments(default_stencils, 1, 8, 0)
    mc_mean, mc_std = _monte_carlo_moments(default_stencils.config, 1.0, 4.0, 0)
    assert markov_mean == pytest.approx(mc_mean, abs=0.05)
    assert markov_std >= mc_std


# ---------------------------------------------------------------------------
# Disk cache
# ---------------------------------------------------------------------------


def _assert_same(a, b):
    for kind in KINDS:
        np.testing.assert_array_equal(a.kernel(kind), b.kernel(kind))


def test_a_cache_folder_with_a_tilde_is_under_home(tmp_path, monkeypatch):
    """``stencil_cache_dir = "~/x"`` made a folder named "~" in the current one (the other path parameters expand it)."""
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    monkeypatch.chdir(tmp_path)
    assert cache_path(SMALL, "~/stencils").parent == tmp_path / "home" / "stencils"
    assert not (tmp_path / "~").exists()


def test_cache_second_build_loads_from_disk(tmp_path, monkeypatch):
    first = load_or_build_stencils(SMALL, cache_dir=tmp_path)
    path = cache_path(SMALL, tmp_path)
    assert path.exists() and path.suffix == ".npz"
    assert list(tmp_path.iterdir()) == [path]  # no temporary file left behind

    def fail(_config):
        raise AssertionError("rebuilt although a valid cache exists")

    monkeypatch.setattr("stages.lib.markov.transitions.build_stencils", fail)
    second = load_or_build_stencils(SMALL, cache_dir=tmp_path)
    _assert_same(first, second)
    # Plain arrays only: it loads without pickle and holds no object arrays.
    with np.load(path, allow_pickle=False) as npz:
        assert all(npz[name].dtype != object for name in npz.files)


def _corrupt_truncate(path):
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


def _corrupt_flip(path):
    data = bytearray(path.read_bytes())
    middle = len(data) // 2
    for i in range(middle, middle + 16):
        data[i] ^= 0xFF
    path.write_bytes(bytes(data))


def _corrupt_wrong_params(path):
    save_stencils(build_stencils(_with(SMALL, tau_s=0.5)), path)


def _corrupt_pickled(path):
    with np.load(path, allow_pickle=False) as npz:
        arrays = {name: npz[name] for name in npz.files}
    arrays["params_json"] = np.array([SMALL.params_json()], dtype=object)  # would need pickle to load
    with open(path, "wb") as handle:
        np.savez(handle, **arrays)


def _corrupt_column_sums(path):
    with np.load(path, allow_pickle=False) as npz:
        arrays = {name: npz[name] for name in npz.files}
    arrays["point_prob"] = arrays["point_prob"].copy()
    arrays["point_prob"][0] += 1e-6
    with open(path, "wb") as handle:
        np.savez(handle, **arrays)


@pytest.mark.parametrize(
    "corrupt, reason",
    [
        (_corrupt_truncate, "unreadable"),
        (_corrupt_flip, "unreadable"),
        (_corrupt_pickled, "unreadable"),
        (_corrupt_wrong_params, "parameters differ"),
        (_corrupt_column_sums, "column sums"),
    ],
)
def test_corrupt_cache_is_rebuilt_with_a_warning(tmp_path, caplog, corrupt, reason):
    reference = load_or_build_stencils(SMALL, cache_dir=tmp_path)
    path = cache_path(SMALL, tmp_path)
    corrupt(path)
    with pytest.raises(ValueError):
        load_stencils(path, SMALL)
    with caplog.at_level(logging.WARNING, logger="iamp.markov"):
        rebuilt = load_or_build_stencils(SMALL, cache_dir=tmp_path)
    warnings = [r for r in caplog.records if r.name == "iamp.markov" and r.levelno == logging.WARNING]
    assert len(warnings) == 1 and reason in warnings[0].getMessage()
    _assert_same(reference, rebuilt)
    _assert_same(reference, load_stencils(path, SMALL))  # the file was rewritten and is valid again


def test_config_rejects_bad_values():
    with pytest.raises(ValueError, match="integer"):
        MarkovGridConfig(v_max_mps=20.0, dv_mps=0.3)
    with pytest.raises(ValueError, match="increasing"):
        MarkovGridConfig(input_edges_mps2=(0.0, -1.0))
    with pytest.raises(ValueError, match="not implemented"):
        MarkovGridConfig(model_variant="power_limited")
    config = MarkovGridConfig.from_params({"ds_m": 0.5, "input_edges_mps2": [-6.0, -3.0, 0.0, 2.0]}, where="test")
    assert config.n_inputs == 3 and config.input_edges_mps2 == (-6.0, -3.0, 0.0, 2.0)


def test_cache_key_covers_every_parameter():
    keys = {SMALL.cache_key()}
    for change in ({"ds_m": 0.5}, {"tau_s": 0.2}, {"n_sub_times": 5}, {"n_input_samples": 5},
                   {"input_edges_mps2": (-6.0, -3.0, 0.0, 2.0)}, {"n_s_cells": 31}):
        keys.add(_with(SMALL, **change).cache_key())
    assert len(keys) == 7
    assert MarkovGridConfig().cache_key() == MarkovGridConfig().cache_key()


# ---------------------------------------------------------------------------
# Ψ and Γ
# ---------------------------------------------------------------------------


def test_psi_matches_method():
    psi = psi_matrix(MarkovGridConfig().input_centres_mps2())
    np.testing.assert_allclose(psi.sum(axis=0), 1.0)
    expected = [0.005, 0.008, 0.014, 0.032, 0.111, 0.665, 0.111, 0.032, 0.014, 0.008]
    np.testing.assert_allclose(psi[:, 5], expected, atol=6e-4)
    assert psi[0, 0] == pytest.approx(0.79, abs=0.01)


def test_gamma_from_priority_keeps_braking_when_all_forbidden():
    psi = psi_matrix(MarkovGridConfig().input_centres_mps2())
    lam = np.zeros((2, 3, 10))
    lam[0, 0, 4:7] = [0.2, 1.0, 0.5]
    gamma = gamma_from_priority(lam, psi)
    assert gamma.shape == (2, 3, 10, 10)
    np.testing.assert_allclose(gamma.sum(axis=-2), 1.0)
    assert np.all(gamma[0, 0, :4] == 0) and np.all(gamma[0, 0, 7:] == 0)
    np.testing.assert_array_equal(gamma[1, 2, 0], 1.0)  # every input forbidden → strongest braking
    np.testing.assert_array_equal(gamma[1, 2, 1:], 0.0)


# ---------------------------------------------------------------------------
# Propagation
# ---------------------------------------------------------------------------


def _batch(cfg, n_pairs=5, seed=3):
    rng = np.random.default_rng(seed)
    return initial_state(
        cfg,
        s_m=rng.uniform(2.0, 8.0, n_pairs),
        v_mps=rng.uniform(0.2, cfg.v_max_mps - 0.3, n_pairs),
        half_width_s_m=rng.uniform(0.5, 2.0, n_pairs),
        half_width_v_mps=rng.uniform(0.25, 1.0, n_pairs),
        input_probs=rng.dirichlet(np.ones(cfg.n_inputs), n_pairs),
    )


def _input_cases(cfg, n_pairs, seed=4):
    rng = np.random.default_rng(seed)
    psi = psi_matrix(cfg.input_centres_mps2())
    k_steps = cfg.n_steps
    replaced = [InputReplaced(probs=rng.dirichlet(np.ones(cfg.n_inputs), n_pairs)) for _ in range(k_steps)]
    matrix = [
        InputMatrix(gamma=gamma_from_priority(rng.uniform(0, 1, (n_pairs, cfg.n_inputs)), psi)) for _ in range(k_steps)
    ]
    lam = rng.uniform(0, 1, (n_pairs, cfg.n_v_cells, cfg.n_s_cells, cfg.n_inputs))
    lam[:, :, :, 3:] *= (rng.random((n_pairs, cfg.n_v_cells, cfg.n_s_cells, 1)) > 0.3)  # some states: braking only
    lam[:, 0, 0, :] = 0.0  # every input forbidden in one state
    per_state_gamma = np.moveaxis(gamma_from_priority(lam, psi), (1, 2), (3, 4))  # (B, M, M, N_v, N_s)
    per_state = [InputPerState(gamma=per_state_gamma) for _ in range(k_steps)]
    mixed = [replaced[0], None, matrix[2], per_state[3], replaced[4], matrix[5]][:k_steps]
    return {"identity": None, "replaced": replaced, "matrix": matrix, "per_state": per_state, "mixed": mixed}


_BACKENDS = [("numpy", "scipy"), *([("numpy", "numba")] if kernels.available() else []), ("torch", "auto")]


@pytest.mark.parametrize("case", ["identity", "replaced", "matrix", "per_state", "mixed"])
def test_numpy_and_torch_backends_agree(small_stencils, case):
    n_pairs = 5
    p0 = _batch(SMALL, n_pairs)
    inputs = _input_cases(SMALL, n_pairs)[case]
    results = {}
    for backend, kernel in _BACKENDS:  # numpy with the compiled kernels and with the scipy products, torch
        for crop in (True, False):
            propagator = MarkovPropagator(small_stencils, backend=backend, crop=crop, kernel=kernel)
            results[backend, kernel, crop] = propagator.run(p0, inputs, with_interval=True, with_final_state=True)
    reference = results["numpy", "scipy", False]
    for result in results.values():
        for name in ("position_probs", "velocity_probs", "interval_position_probs", "outside_mass",
                     "interval_outside_mass", "pruned_mass", "final_state"):
            np.testing.assert_allclose(getattr(result, name), getattr(reference, name), atol=2e-6, err_msg=name)
        # Mass is conserved: in the grid + outside = 1 (the pruned mass was put back).
        in_grid = result.final_state.sum(axis=(1, 2, 3), dtype=np.float64)
        np.testing.assert_allclose(in_grid + result.outside_mass[:, -1], 1.0, atol=1e-5)
        np.testing.assert_allclose(result.position_probs.sum(axis=2) + result.outside_mass, 1.0, atol=1e-5)
        interval_total = result.interval_position_probs.sum(axis=2) + result.interval_outside_mass
        np.testing.assert_allclose(interval_total, 1.0, atol=1e-5)
        np.testing.assert_allclose(result.velocity_probs.sum(axis=2) + result.outside_mass, 1.0, atol=1e-5)
        assert result.mass_error.max() <= 1e-5


@pytest.mark.parametrize("backend,kernel", _BACKENDS)
def test_pruned_mass_is_reported_and_accounted(small_stencils, backend, kernel):
    n_pairs = 4
    p0 = _batch(SMALL, n_pairs)
    inputs = _input_cases(SMALL, n_pairs)["replaced"]
    propagator = MarkovPropagator(small_stencils, backend=backend, prune_threshold=1e-4, renormalise_pruned=False, kernel=kernel)
    result = propagator.run(p0, inputs, with_final_state=True)
    assert result.pruned_mass.sum() > 1e-4  # a coarse threshold really prunes
    in_grid = result.final_state.sum(axis=(1, 2, 3), dtype=np.float64)
    np.testing.assert_allclose(in_grid + result.outside_mass[:, -1] + result.pruned_mass.sum(axis=1), 1.0, atol=1e-5)
    assert result.mass_error.max() <= 1e-5


def test_outside_mass_is_reported_not_renormalised(small_stencils):
    n_s = 12
    cfg = SMALL
    p_near_end = initial_state(
        _with(cfg, n_s_cells=n_s),
        s_m=[8.5, 1.5],
        v_mps=[5.0, 0.3],
        half_width_s_m=0.5,
        half_width_v_mps=0.25,
        input_probs=np.eye(cfg.n_inputs)[[6, 0]],
    )
    for backend in ("numpy", "torch"):
        propagator = MarkovPropagator(small_stencils, backend=backend, n_s_cells=n_s)
        result = propagator.run(p_near_end, None, with_interval=True)
        outside = result.outside_mass
        assert np.all(np.diff(outside[0]) >= -1e-7)  # absorbing: never decreases
        assert outside[0, -1] > 0.9  # 5 m/s for 2.4 s from 8.5 m leaves a 12 m window
        assert outside[1, -1] == 0.0  # the stopped car stays inside
        np.testing.assert_allclose(result.position_probs.sum(axis=2), 1.0 - outside, atol=1e-5)
        # The in-grid mass is not scaled back up to 1.
        assert result.position_probs[0, -1].sum() < 0.1
        assert np.all(result.interval_outside_mass[0] <= outside[0] + 1e-6)


def test_initial_state_box_and_dense_form_agree(small_stencils):
    cfg = SMALL
    state = initial_state(
        cfg, s_m=[3.0], v_mps=[2.1], half_width_s_m=1.0, half_width_v_mps=0.5, input_probs=np.eye(10)[4]
    )
    np.testing.assert_allclose(state.position_probs[0, 2:4], [0.5, 0.5])
    np.testing.assert_allclose(state.velocity_probs[0, 3:6], [0.4, 0.5, 0.1], atol=1e-6)
    joint = state.joint()
    assert joint.shape == (1, cfg.n_inputs, cfg.n_v_cells, cfg.n_s_cells)
    assert joint.sum() == pytest.approx(1.0, abs=1e-6)
    propagator = MarkovPropagator(small_stencils)
    a = propagator.run(state, None, with_interval=True)
    b = propagator.run(joint, None, with_interval=True)
    np.testing.assert_allclose(a.position_probs, b.position_probs, atol=1e-7)
    with pytest.raises(ValueError, match="does not intersect"):
        initial_state(cfg, s_m=[-5.0], v_mps=[2.0], half_width_s_m=1.0, half_width_v_mps=0.5, input_probs=np.eye(10)[4])


def test_boxes_outside_grid_are_exactly_the_boxes_initial_state_refuses():
    from stages.lib.markov.propagate import _overlaps, boxes_outside_grid

    cfg = SMALL
    rng = np.random.default_rng(7)
    s_edges, v_edges = cfg.s_edges_m(), cfg.v_edges_mps()
    # boxes ending on an edge, touching the grid from outside, tiny, huge, not finite, zero wide
    s = np.concatenate([rng.uniform(-10, s_edges[-1] + 10, 400), rng.choice(s_edges, 200) + rng.choice([-0.5, 0.0, 0.5], 200),
                        [s_edges[0] - 1.0, s_edges[-1] + 1.0, np.nan, 3.0, 3.0, np.inf]])
    hs = np.concatenate([rng.uniform(1e-12, 5, 400), rng.choice([0.5, 1e-300, 5e-324, 0.25], 200), [1.0, 1.0, 1.0, 0.0, -1.0, 1.0]])
    v = rng.uniform(-2, v_edges[-1] + 2, s.shape[0])
    hv = rng.choice([0.25, 1e-300, 0.5, 2.0], s.shape[0])
    s_out, v_out = boxes_outside_grid(cfg, s_m=s, v_mps=v, half_width_s_m=hs, half_width_v_mps=hv)
    with np.errstate(invalid="ignore"):  # the definition: a finite box of positive width with some overlap
        s_def = ~(np.isfinite(s) & np.isfinite(hs) & (hs > 0) & (_overlaps(s_edges, np.nan_to_num(s), hs).sum(axis=1) > 0))
        v_def = ~(np.isfinite(v) & np.isfinite(hv) & (hv > 0) & (_overlaps(v_edges, v, hv).sum(axis=1) > 0))
    np.testing.assert_array_equal(s_out, s_def)
    np.testing.assert_array_equal(v_out, v_def)
    assert s_out[-6:].tolist() == [True, True, True, True, True, True] and 0 < s_out[:600].sum() < 600
    for b in range(0, 600, 7):  # initial_state raises for exactly these
        args = dict(s_m=[s[b]], v_mps=[2.1], half_width_s_m=hs[b], half_width_v_mps=0.5, input_probs=np.eye(10)[4])
        if s_out[b]:
            with pytest.raises(ValueError, match="does not intersect"):
                initial_state(cfg, **args)
        else:
            initial_state(cfg, **args)


def test_callable_inputs_see_this_steps_marginals(small_stencils):
    seen = []

    def inputs(k, marginals):
        seen.append((k, np.asarray(marginals.position).sum(axis=1)))
        return InputReplaced(probs=np.tile(np.eye(10)[0], (2, 1)))

    result = MarkovPropagator(small_stencils).run(_batch(SMALL, 2), inputs)
    assert [k for k, _ in seen] == list(range(SMALL.n_steps))
    np.testing.assert_allclose(seen[-1][1], result.position_probs[:, -1].sum(axis=1))


def test_bad_input_transition_is_rejected(small_stencils):
    gamma = np.full((2, 10, 10), 0.2)  # columns sum to 2
    with pytest.raises(ValueError, match="must sum to 1"):
        MarkovPropagator(small_stencils).run(_batch(SMALL, 2), [InputMatrix(gamma=gamma)] * SMALL.n_steps)


@pytest.mark.parametrize("backend", ["numpy", "torch"])
def test_inputs_may_be_torch_tensors(small_stencils, backend):
    torch = pytest.importorskip("torch")
    n_pairs = 3
    p0 = _batch(SMALL, n_pairs)
    cases = _input_cases(SMALL, n_pairs)
    as_numpy = cases["mixed"]
    as_torch = [
        None if t is None else type(t)(**{name: torch.as_tensor(value) for name, value in vars(t).items()})
        for t in as_numpy
    ]
    propagator = MarkovPropagator(small_stencils, backend=backend)
    a = propagator.run(p0, as_numpy)
    b = propagator.run(p0, as_torch)
    np.testing.assert_allclose(a.position_probs, b.position_probs, atol=1e-6)
    bad = [InputReplaced(probs=torch.full((n_pairs, 10), 0.5))] * SMALL.n_steps
    with pytest.raises(ValueError, match="must sum to 1"):
        propagator.run(p0, bad)


@pytest.mark.parametrize("backend", ["numpy", "torch"])
@pytest.mark.parametrize("kind", list(TransitionKind))
def test_position_of_a_step_equals_the_position_of_the_full_step(small_stencils, backend, kind):
    """``transition_position`` (the interval's hot path) gives the s-marginal and leak of ``transition`` without its state."""
    if backend == "torch":
        pytest.importorskip("torch")
    n_pairs = 4
    propagator = MarkovPropagator(small_stencils, backend=backend)
    be = propagator._backend
    p0 = _batch(SMALL, n_pairs)
    for lo, hi in ((0, SMALL.n_s_cells), (3, 19), (SMALL.n_s_cells - 9, SMALL.n_s_cells)):
        slab = be.initial_slab(p0, lo, hi)
        moved, leaked = be.transition(kind, slab, lo, hi)
        position, leaked2 = be.transition_position(kind, slab, lo, hi)
        np.testing.assert_allclose(be.to_numpy(position), be.to_numpy(be.position(moved)), atol=1e-7)
        np.testing.assert_allclose(be.to_numpy(leaked2), be.to_numpy(leaked), atol=0)


def test_torch_on_cuda_agrees_with_numpy(small_stencils):
    """The CUDA path (backend torch, device cuda): skipped where no NVIDIA GPU is present."""
    torch = pytest.importorskip("torch")
    if not torch.cuda.is_available():
        pytest.skip("no CUDA device")
    n_pairs = 5
    p0 = _batch(SMALL, n_pairs)
    inputs = _input_cases(SMALL, n_pairs)["mixed"]
    reference = MarkovPropagator(small_stencils, backend="numpy").run(p0, inputs, with_interval=True)
    result = MarkovPropagator(small_stencils, backend="torch", device="cuda").run(p0, inputs, with_interval=True)
    for name in ("position_probs", "velocity_probs", "interval_position_probs", "outside_mass"):
        np.testing.assert_allclose(getattr(result, name), getattr(reference, name), atol=2e-6, err_msg=name)


@pytest.mark.skipif(not kernels.available(), reason="numba does not import")
@pytest.mark.parametrize("n_s", [30, 14])
def test_numba_kernel_equals_scipy_when_the_window_moves_and_mass_leaves(small_stencils, n_s):
    """Fast pairs: the cropped window moves forward every step (the fused step reads the previous window in place)
    and, with a short window, mass leaves it; the compiled path gives the scipy path's numbers."""
    cfg = _with(SMALL, n_s_cells=n_s)
    rng = np.random.default_rng(11)
    p0 = initial_state(cfg, s_m=rng.uniform(2.0, 4.0, 3), v_mps=rng.uniform(4.5, 5.5, 3), half_width_s_m=0.5,
                       half_width_v_mps=0.25, input_probs=rng.dirichlet(np.ones(cfg.n_inputs), 3))
    inputs = _input_cases(cfg, 3)["mixed"]
    runs = {kernel: MarkovPropagator(small_stencils, n_s_cells=n_s, crop_quantum_cells=1, kernel=kernel).run(
        p0, inputs, with_interval=True, with_final_state=True) for kernel in ("scipy", "numba")}
    assert runs["scipy"].position_probs[:, -1, :2].max() == 0.0  # the mass has left the first cells: the window moved
    if n_s == 14:
        assert runs["scipy"].outside_mass[:, -1].min() > 0.05  # and some left the window
    for name in ("position_probs", "velocity_probs", "interval_position_probs", "outside_mass", "interval_outside_mass",
                 "pruned_mass", "final_state", "mass_error"):
        np.testing.assert_allclose(getattr(runs["numba"], name), getattr(runs["scipy"], name), atol=1e-6, err_msg=name)


def test_iamp_eval_builds_its_stencils_in_the_folder_stencil_cache_dir_names(tmp_path, monkeypatch):
    """``iamp eval --set stencil_cache_dir=...`` was ignored: the evaluation loaded the stencils from the default folder."""
    from stages.offline import evaluation

    asked = []

    def record(config, cache_dir=None):
        asked.append(cache_dir)
        return load_or_build_stencils(config)  # (from the default folder, which the other tests fill: a build takes a minute)

    monkeypatch.setattr(evaluation, "load_or_build_stencils", record)
    evaluation.Evaluation(evaluation.EvalConfig(modes=("baseline",), params=(("stencil_cache_dir", str(tmp_path / "x")),), progress=False))
    assert asked == [str(tmp_path / "x")]
