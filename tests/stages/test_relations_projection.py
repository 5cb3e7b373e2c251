"""relations' batched projection of objects onto corridors (branch and bound) against the per-corridor reference.

``_project_onto_corridors`` must give bit for bit what the dense projection
it replaced gave (``_dense`` below: every point against every segment) for
every (corridor, point) it projects (near a smooth corridor the same as
``maps.project_to_polyline`` within float rounding), and may leave NaN only where the point is farther
than ``radius_m`` from the corridor in |d| (the lateral test could not keep
it) or outside the reach box.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from stages.lib.maps.geometry import project_to_polyline
from stages.relations.core import _BLOCK, _project_onto_corridors


def _dense(points: np.ndarray, xy: np.ndarray, arc: np.ndarray):
    """The projection before the branch and bound (relations at b3e0b71), for one corridor: (s, d, heading)."""
    segment = np.diff(xy, axis=0)
    length2 = np.maximum((segment**2).sum(axis=1), 1e-18)
    lower, upper = np.zeros(len(segment)), np.ones(len(segment))
    lower[0], upper[-1] = -np.inf, np.inf
    rel = points[:, None, :] - xy[None, :-1, :]
    t = np.clip((rel * segment[None]).sum(axis=2) / length2[None], lower[None], upper[None])
    off = rel - t[..., None] * segment[None]
    j = (off**2).sum(axis=2).argmin(axis=1)
    c = np.arange(len(points))
    seg_len = np.sqrt(length2[j])
    ux, uy = segment[j, 0] / seg_len, segment[j, 1] / seg_len
    return arc[j] + t[c, j] * seg_len, ux * rel[c, j, 1] - uy * rel[c, j, 0], np.arctan2(uy, ux)


def _pair(g: int, xy: np.ndarray) -> SimpleNamespace:
    s = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(xy, axis=0).T))]) - 3.0  # a corridor starts behind s = 0
    return SimpleNamespace(g=g, xy=xy, corridor=SimpleNamespace(s_m=s))


def _corridors(rng: np.random.Generator) -> list[np.ndarray]:
    out = []
    for n in (2, 3, 5, _BLOCK + 2, 3 * _BLOCK + 1, 90, 200):  # 1 segment, 2, a few, block edges, long
        heading = rng.uniform(-np.pi, np.pi) + np.cumsum(rng.normal(0.0, 0.08, n - 1))
        steps = 0.5 * np.column_stack([np.cos(heading), np.sin(heading)])
        out.append(rng.uniform(-20, 20, 2) + np.concatenate([[[0.0, 0.0]], np.cumsum(steps, axis=0)]))
    zigzag = np.column_stack([np.arange(12.0), np.tile([0.0, 3.0], 6)])  # turns of ~110 deg: never pruned
    repeated = np.array([[0.0, 0.0], [0.0, 0.0], [1.0, 0.0], [2.0, 0.5]])  # a zero-length first segment: never pruned
    return [*out, zigzag, repeated]


def test_projection_is_the_reference_bit_for_bit_and_prunes_only_far_points():
    rng = np.random.default_rng(16)
    lines = _corridors(rng)
    pairs = [_pair(g, xy) for g, xy in enumerate(lines)]
    points = np.concatenate([rng.uniform(-60, 60, (300, 2)), np.concatenate(lines) + rng.normal(0, 1.0, (sum(map(len, lines)), 2))])
    radius = np.full(len(pairs), 2.5)
    s, d, heading = _project_onto_corridors(points, pairs, None, radius)
    s0, d0, h0 = _project_onto_corridors(points, pairs, None, None)
    assert np.isfinite(s0).all()  # no radius: every point projected
    pruned = 0
    for pair, xy in zip(pairs, lines):
        dense = _dense(points, xy, pair.corridor.s_m)
        for got, want in zip((s0[pair.g], d0[pair.g], h0[pair.g]), dense):
            np.testing.assert_array_equal(got, want)
        if len(xy) > 20:  # smooth: the same as the map library's projection, within rounding
            ref = project_to_polyline(points, xy, pair.corridor.s_m)
            near = np.abs(ref.d_m) < radius[pair.g]
            np.testing.assert_allclose(s0[pair.g][near], ref.s_m[near], rtol=0, atol=1e-9)
            np.testing.assert_allclose(d0[pair.g][near], ref.d_m[near], rtol=0, atol=1e-9)
        done = np.isfinite(s[pair.g])
        np.testing.assert_array_equal(s[pair.g][done], dense[0][done])
        np.testing.assert_array_equal(d[pair.g][done], dense[1][done])
        # a point left out is one the lateral test could not keep
        assert (np.abs(dense[1][~done]) > radius[pair.g]).all()
        pruned += int((~done).sum())
    assert pruned > len(points)  # the pruning does happen
    assert np.isfinite(s[len(lines) - 2]).all() and np.isfinite(s[len(lines) - 1]).all()  # zigzag, zero-length: all projected


def test_reach_box_leaves_far_points_nan_and_no_points_is_fine():
    xy = np.column_stack([np.linspace(0, 20, 41), np.zeros(41)])
    pairs = [_pair(0, xy)]
    points = np.array([[10.0, 1.0], [10.0, 40.0], [-50.0, 0.0]])
    s, d, _h = _project_onto_corridors(points, pairs, np.array([5.0]), None)
    assert np.isfinite(s[0, 0]) and np.isnan(s[0, 1:]).all()
    assert d[0, 0] == 1.0
    empty = _project_onto_corridors(np.zeros((0, 2)), pairs, np.array([5.0]), np.array([2.0]))
    assert all(a.shape == (1, 0) for a in empty)


def test_compiled_branch_and_bound_equals_the_numpy_one_bit_for_bit(monkeypatch):
    """The numba kernel (stages.lib.maps.kernels.project_polylines) gives the numpy code's values and NaNs exactly,
    with reach boxes and radius pruning, and a frame with a non-finite point goes to the numpy code."""
    import pytest

    from stages.lib.maps import kernels

    if not kernels.available():
        pytest.skip("numba not importable")
    used = []
    original = kernels.project_polylines
    monkeypatch.setattr(kernels, "project_polylines", lambda *a: used.append(original(*a)) or used[-1])
    rng = np.random.default_rng(23)
    for trial in range(12):
        lines = _corridors(rng)
        if trial % 4 == 3:
            lines = lines[:3]  # the longest corridor short: padded turns count as 1.0 in the numpy code
        elif trial % 4 == 2:
            lines = [lines[-3], lines[-2]]  # the longest corridor has no padding
        pairs = [_pair(g, xy) for g, xy in enumerate(lines)]
        points = np.concatenate([rng.uniform(-60, 60, (200, 2)), np.concatenate(lines) + rng.normal(0, 2.0, (sum(map(len, lines)), 2))])
        reach = rng.uniform(1.0, 30.0, len(pairs)) if trial % 2 else None
        radius = rng.uniform(0.5, 4.0, len(pairs)) if trial % 3 else None
        got = _project_onto_corridors(points, pairs, reach, radius)
        want = _project_onto_corridors(points, pairs, reach, radius, compiled=False)
        for a, b in zip(got, want):
            np.testing.assert_array_equal(a, b)
    assert len(used) == 12 and all(u is not None for u in used)
    points[3] = np.nan
    got = _project_onto_corridors(points, pairs, None, np.full(len(pairs), 2.0))
    assert len(used) == 12  # not called: the numpy code handles the frame
    assert np.isnan(got[0][:, 3]).all()
