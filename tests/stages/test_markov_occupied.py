"""InputPriority on the occupied states only (``at_states``) gives what the dense window path gives."""

from __future__ import annotations

import numpy as np
import pytest

from stages.lib.markov import MarkovGridConfig, build_stencils, initial_state, kernels, psi_matrix
from stages.markov_prediction.chain import InputPriority, PriorityPropagator
from stages.markov_prediction.priority import combine_with_preference
from testkit.hybrid_chain import hybrid_chain_case

SMALL = MarkovGridConfig(v_max_mps=6.0, n_s_cells=30, n_steps=6, n_state_samples=5, n_input_samples=4, n_sub_times=4)


def test_occupied_states_path_equals_the_window_path():
    stencils = build_stencils(SMALL)
    rng = np.random.default_rng(7)
    n_pairs, n_in = 6, SMALL.n_inputs
    restriction = rng.uniform(0, 1, (n_pairs, n_in, SMALL.n_v_cells, SMALL.n_s_cells)).astype(np.float32)
    restriction[:, 4:, :, 10:] *= rng.random((n_pairs, 1, SMALL.n_v_cells, SMALL.n_s_cells - 10)) > 0.5  # braking only in places
    restriction[2, :, :, :] = 0.0  # a pair with every input forbidden everywhere
    prefs = [rng.dirichlet(np.ones(n_in), n_pairs).astype(np.float32) for _ in range(SMALL.n_steps)]
    dense = [InputPriority(weights=lambda lo, hi, q=q: combine_with_preference(restriction[..., lo:hi], q, 0.0)) for q in prefs]
    occupied = [InputPriority(weights=d.weights, at_states=lambda b, v, s, q=q: combine_with_preference(restriction[b, :, v, s], q[b], 0.0))
                for d, q in zip(dense, prefs)]
    p0 = initial_state(SMALL, s_m=rng.uniform(1, 8, n_pairs), v_mps=rng.uniform(0, 5, n_pairs), half_width_s_m=0.5, half_width_v_mps=0.5,
                       input_probs=rng.dirichlet(np.ones(n_in), n_pairs))
    psi = psi_matrix(SMALL.input_centres_mps2())
    a = PriorityPropagator(stencils, psi, kernel="scipy").run(p0, dense, with_interval=True, with_final_state=True)
    for kernel in ("scipy", *(["numba"] if kernels.available() else [])):  # numba: the compiled occupied-state kernels
        b = PriorityPropagator(stencils, psi, kernel=kernel).run(p0, occupied, with_interval=True, with_final_state=True)
        for name in ("position_probs", "velocity_probs", "interval_position_probs", "outside_mass", "pruned_mass", "final_state"):
            np.testing.assert_allclose(getattr(b, name), getattr(a, name), atol=1e-6, err_msg=f"{kernel}: {name}")
        assert b.mass_error.max() <= 1e-5


@pytest.mark.skipif(not kernels.available(), reason="numba does not import")
@pytest.mark.parametrize("forbid_threshold", [0.0, 0.25])
def test_compiled_priority_at_states_equals_combine_with_preference(forbid_threshold):
    """kernels.priority_at_states (the hybrid mode's at_states when numba imports) is combine_with_preference, bit for bit."""
    rng = np.random.default_rng(3)
    n_pairs, n_in, n_v, n_s = 5, 10, 7, 9
    weights = np.float32([0.2, 0.3, 0.5])  # a restriction is a sum of lateral-acceleration weights, as speed_restriction makes it
    cuts = rng.integers(0, n_in + 1, (3, n_pairs, n_v, n_s))
    restriction = sum(w * (np.arange(n_in)[None, :, None, None] < c[:, None]) for w, c in zip(weights, cuts)).astype(np.float32)
    restriction[1, :, 2, :] = 0.0  # every input forbidden
    restriction[2] = rng.uniform(0, 1, restriction[2].shape)  # and arbitrary values
    preference = rng.uniform(0, 1, (n_pairs, n_in)).astype(np.float32)
    preference /= preference.max(axis=1, keepdims=True)
    b, v, s = (rng.integers(0, n, 400) for n in (n_pairs, n_v, n_s))
    expected = combine_with_preference(restriction[b, :, v, s], preference[b], forbid_threshold)
    got = kernels.priority_at_states(restriction, preference, b, v, s, forbid_threshold)
    assert got.dtype == np.float32 and got.shape == expected.shape
    np.testing.assert_array_equal(got, expected)
    assert np.any(got[:, 0] == 1.0) and np.any(got[:, 0] < 1.0)


@pytest.mark.skipif(not kernels.available(), reason="numba does not import")
def test_compiled_speed_restriction_equals_the_numpy_definition():
    """kernels.SpeedRestriction (the hybrid mode's λ_speed, filled on demand) is priority.speed_restriction per pair, bit
    for bit, in full and at listed states (through the priority): profiles of one knot, of repeated knots, of irregular
    knots, shorter and longer than the N_v·L queries, curves, queries on knots and past both ends."""
    from stages.markov_prediction import priority as pr

    grid = MarkovGridConfig()
    v, a = grid.v_centres_mps(), grid.input_centres_mps2()
    rng = np.random.default_rng(3)
    lat = np.array([3.0, 2.5, 2.0, 1.5])
    weights = np.array([0.1, 0.2, 0.4, 0.3])
    profiles, adms, cells = [], [], []
    for b, n in enumerate([1, 2, 7, 150, 300, 400, 5000]):
        s = np.cumsum(rng.uniform(0.2, 1.5, n) * (rng.random(n) < 0.8 if b == 4 else 1.0)) - rng.uniform(0, 20)  # irregular knots
        if b == 3:
            s = np.unique(np.round(s * 2) / 2)  # knots on the half metre: cell centres + v·τ land on them
        kappa = np.where((s > 30) & (s < 60), 1.0 / rng.uniform(8, 40), 0.0) + rng.normal(0, 1e-3, s.size)
        adm = pr.admissible_speeds(s, kappa, rng.uniform(8, 17), lat, 2.0, 4.0)
        profiles.append(s)
        adms.append(adm)
        cells.append(rng.uniform(-25, 10) + 0.5 + np.arange(grid.n_s_cells) * 1.0)
    cells = np.array(cells)
    cells[3, :20] = profiles[3][5:25] - v[0] * 0.4  # queries on knots
    want = np.stack([pr.speed_restriction(adms[b], profiles[b], cells[b], v, a, weights, 0.4) for b in range(len(profiles))])
    assert 0.05 < want.mean() < 0.95 and np.any(want == 0.0) and np.any(want == np.float32(1.0))  # the cases restrict something
    np.testing.assert_array_equal(kernels.speed_restriction(profiles, adms, cells, v, a, weights, 0.4), want)
    lazy = kernels.SpeedRestriction(profiles, adms, cells, v, a, weights, 0.4)
    pref = rng.dirichlet(np.ones(grid.n_inputs), len(profiles)).astype(np.float32)
    for _ in range(4):  # states in any order, repeated, some asked for again in a later call
        n = 3000
        b_idx, v_idx, s_idx = rng.integers(0, len(profiles), n), rng.integers(0, grid.n_v_cells, n), rng.integers(0, grid.n_s_cells, n)
        for threshold in (0.0, 0.25):
            got = lazy.priority_at_states(pref, b_idx, v_idx, s_idx, threshold)
            np.testing.assert_array_equal(got, combine_with_preference(want[b_idx, :, v_idx, s_idx], pref[b_idx], threshold))
    np.testing.assert_array_equal(lazy.full(), want)
    assert not kernels.SpeedRestriction.supports(np.array([0.0, 2.0, 1.0])) and not kernels.SpeedRestriction.supports(np.zeros(0))
    for bad in (np.array([0.0, 2.0, 1.0]), np.zeros(0), np.array([0.0, np.nan])):  # np.interp reads these otherwise: refused
        with pytest.raises(ValueError):
            kernels.SpeedRestriction([profiles[0], bad], [adms[0], np.ones((4, bad.size))], cells[:2], v, a, weights, 0.4)
    kernels.SpeedRestriction([np.array([5.0, 6.0]), np.array([0.0, 1.0])], [np.ones((4, 2))] * 2, cells[:2], v, a, weights, 0.4)  # a drop between pairs is fine


@pytest.mark.skipif(not kernels.available(), reason="numba does not import")
def test_speed_restriction_knot_buckets_equal_the_numpy_loop():
    """SpeedRestriction's compiled knot buckets (kernels._knot_buckets) are the numpy loop's: per pair of n > 1 knots
    over a span > 0, h = span / n, inv_h at its first knot 1 / h, bucket max(searchsorted(s, s_0 + h·k, "right") − 1, 0);
    zeros for a pair of one knot or of one repeated knot; repeated and irregular knots, knots on the query points."""
    rng = np.random.default_rng(11)
    profiles = [np.array([4.0]), np.array([2.0, 2.0, 2.0]), np.arange(0.0, 10.0, 0.5), np.array([0.0, 0.0, 1.0, 1.0, 1.0, 7.5])]
    profiles += [np.cumsum(rng.uniform(0.0, 2.0, n) * (rng.random(n) < 0.7)) - rng.uniform(0, 50) for n in (2, 3, 40, 333)]
    grid = MarkovGridConfig()
    lazy = kernels.SpeedRestriction(profiles, [np.ones((1, s.size)) for s in profiles], np.zeros((len(profiles), 4)),
                                    grid.v_centres_mps(), grid.input_centres_mps2(), np.ones(1), 0.4)
    xp, _, start, bucket, inv_h = lazy._args[:5]
    want_bucket, want_inv = np.zeros_like(bucket), np.zeros_like(inv_h)
    for b in range(len(profiles)):
        lo, hi = start[b], start[b + 1]
        s = xp[lo:hi]
        span = s[-1] - s[0]
        if hi - lo > 1 and span > 0:
            h = span / (hi - lo)
            want_inv[lo] = 1.0 / h
            want_bucket[lo:hi] = np.maximum(np.searchsorted(s, s[0] + h * np.arange(hi - lo), side="right") - 1, 0)
    np.testing.assert_array_equal(bucket, want_bucket)
    np.testing.assert_array_equal(inv_h, want_inv)
    assert want_bucket.max() > 0 and np.count_nonzero(want_inv) == 6  # the cases bucket something


@pytest.mark.skipif(not kernels.available(), reason="numba does not import")
@pytest.mark.parametrize("n_pairs", [1, 2, 7, 19])  # 19: several blocks of 8, the last one partly empty
def test_one_call_speed_priority_run_equals_the_step_by_step_run(n_pairs, monkeypatch):
    """PriorityPropagator's one-call path (kernels.speed_priority_run: the hybrid mode's chain in blocks of pairs, each
    on its pairs' cells) gives the step-by-step numba run's numbers bit for bit (B > 1; B = 1 within float32 rounding of the
    renormalisation), and the scipy reference's within 1e-6; pairs near the window's end leak mass, one pair starts
    at rest, one has every input forbidden somewhere."""
    stencils = build_stencils(SMALL)
    case = hybrid_chain_case(SMALL, n_pairs, np.random.default_rng(11))
    p0, prefs = case.p0, list(case.preferences)
    psi = psi_matrix(SMALL.input_centres_mps2())

    def schedule(threshold, compiled):
        lazy = case.restriction(SMALL)
        steps = [InputPriority(weights=lambda lo, hi, q=q: combine_with_preference(lazy.full()[..., lo:hi], q, threshold),
                               at_states=lambda b, vv, s, q=q: lazy.priority_at_states(q, b, vv, s, threshold),
                               restriction=lazy if compiled else None, preference=q if compiled else None, forbid_threshold=threshold)
                 for q in prefs[:-1]]
        return steps + [None]

    calls = []
    real = kernels.speed_priority_run
    monkeypatch.setattr(kernels, "speed_priority_run", lambda *args, **kw: calls.append(1) or real(*args, **kw))
    for threshold in (0.0, 0.3):
        one = PriorityPropagator(stencils, psi, kernel="numba").run(p0, schedule(threshold, True), with_interval=True)
        assert len(calls) == 1
        calls.clear()
        steps = PriorityPropagator(stencils, psi, kernel="numba").run(p0, schedule(threshold, False), with_interval=True)
        ref = PriorityPropagator(stencils, psi, kernel="scipy").run(p0, schedule(threshold, False), with_interval=True)
        assert not calls
        assert one.outside_mass[:, -1].max() > 1e-3  # something leaked
        for name in ("position_probs", "velocity_probs", "interval_position_probs", "outside_mass", "interval_outside_mass", "pruned_mass"):
            if n_pairs > 1:
                np.testing.assert_array_equal(getattr(one, name), getattr(steps, name), err_msg=name)
            else:
                np.testing.assert_allclose(getattr(one, name), getattr(steps, name), rtol=1e-6, atol=2e-7, err_msg=name)  # pruned mass: totals near 1, one ulp
            np.testing.assert_allclose(getattr(one, name), getattr(ref, name), atol=1e-6, err_msg=name)
        np.testing.assert_allclose(one.mass_error, steps.mass_error, atol=1e-6)
        assert one.mass_error.max() <= 1e-5


@pytest.mark.skipif(not kernels.available(), reason="numba does not import")
def test_block_scratch_is_kept_per_thread_and_never_read_before_it_is_written():
    """speed_priority_run's blocks take their scratch arrays (the state, p⁻ and the per-state buffers) from the calling
    thread's workspace (kernels._block_workspace), made once per thread instead of on every call. What a call leaves
    there, or NaN in every cell, does not change the next call's numbers: every cell is written before it is read."""
    import threading

    stencils = build_stencils(SMALL)
    psi = psi_matrix(SMALL.input_centres_mps2())
    n_s, n_in, n_v = SMALL.n_s_cells, SMALL.n_inputs, SMALL.n_v_cells

    def run(n_pairs: int, seed: int):
        case = hybrid_chain_case(SMALL, n_pairs, np.random.default_rng(seed))
        lazy = case.restriction(SMALL)
        steps = [InputPriority(weights=None, at_states=lambda b, vv, s, q=q: lazy.priority_at_states(q, b, vv, s, 0.3),
                               restriction=lazy, preference=q, forbid_threshold=0.3) for q in list(case.preferences)[:-1]]
        out = PriorityPropagator(stencils, psi, kernel="numba").run(case.p0, steps + [None], with_interval=True)
        return [getattr(out, name).copy() for name in ("position_probs", "velocity_probs", "interval_position_probs", "outside_mass")]

    first = run(19, 11)
    mine = kernels._block_workspace(n_s, n_in, n_v)
    assert kernels._block_workspace(n_s, n_in, n_v) is mine  # the same arrays on this thread
    run(7, 5)  # another chain leaves its numbers in the scratch
    again = run(19, 11)
    for a in mine:
        a.fill(np.nan if a.dtype.kind == "f" else -(2**40))
    poisoned = run(19, 11)
    for a, b, c in zip(first, again, poisoned):
        np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(a, c)
    other = []
    t = threading.Thread(target=lambda: other.append(kernels._block_workspace(n_s, n_in, n_v)))
    t.start()
    t.join()
    assert other[0] is not mine and all(x is not y for x, y in zip(other[0], mine))
