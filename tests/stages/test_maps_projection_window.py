"""``project_to_polyline`` with hints measures only the segments within the window: the same result, bit for bit,
as measuring every segment and masking (the code before, ``_masked`` below), including the fallback to every
segment for a point whose window holds none."""

from __future__ import annotations

import numpy as np

from stages.lib.maps.geometry import project_to_polyline


def _masked(points, line, arc, hints, window):
    """Every segment measured, those outside each point's window masked (stages/lib/maps/geometry.py at b3e0b71)."""
    seg = np.diff(line, axis=0)
    seg_len = np.hypot(seg[:, 0], seg[:, 1])
    seg_len2 = np.maximum(seg_len**2, 1e-18)
    lower, upper = np.zeros(len(seg)), np.ones(len(seg))
    lower[0], upper[-1] = -np.inf, np.inf
    rel = points[:, None, :] - line[None, :-1, :]
    t = np.clip((rel * seg[None]).sum(axis=2) / seg_len2[None], lower[None], upper[None])
    foot = line[None, :-1, :] + t[..., None] * seg[None]
    dist2 = ((points[:, None, :] - foot) ** 2).sum(axis=2)
    h = hints[:, None]
    outside = (arc[None, 1:] < h - window) | (arc[None, :-1] > h + window)
    masked = np.where(outside, np.inf, dist2)
    usable = np.isfinite(masked).any(axis=1)
    j = np.where(usable[:, None], masked, dist2).argmin(axis=1)
    rows = np.arange(len(points))
    ux, uy = seg[j, 0] / np.sqrt(seg_len2[j]), seg[j, 1] / np.sqrt(seg_len2[j])
    return arc[j] + t[rows, j] * seg_len[j], ux * rel[rows, j, 1] - uy * rel[rows, j, 0], np.arctan2(seg[j, 1], seg[j, 0])


def _random_polyline(rng: np.random.Generator, n: int, *, wiggly: bool) -> tuple[np.ndarray, np.ndarray]:
    """A random 0.5 m-step polyline of ``n`` points (heading steps of sd 0.3 rad if ``wiggly``, else 0.05) and its arc
    lengths, shifted by a random offset in [0, 10) m."""
    heading = np.cumsum(rng.normal(0.0, 0.3 if wiggly else 0.05, n - 1))
    line = np.concatenate([[[0.0, 0.0]], np.cumsum(0.5 * np.column_stack([np.cos(heading), np.sin(heading)]), axis=0)])
    return line, np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(line, axis=0).T))]) - rng.uniform(0, 10)


def test_windowed_projection_equals_the_masked_dense_one():
    rng = np.random.default_rng(7)
    for trial in range(30):
        n = int(rng.integers(2, 400))
        line, arc = _random_polyline(rng, n, wiggly=trial % 3 == 0)
        k = int(rng.integers(1, 6))
        points = line[rng.integers(0, n, k)] + rng.normal(0, 2.0, (k, 2))
        hints = rng.uniform(arc[0] - 20, arc[-1] + 20, k) if trial % 4 == 0 else rng.uniform(arc[0], arc[-1], k)
        window = float(rng.choice([1.0, 5.0, 10.0]))
        got = project_to_polyline(points, line, arc, s_hint_m=hints, window_m=window)
        want = _masked(points, line, arc, hints, window)
        for a, b in zip((got.s_m, got.d_m, got.heading_rad), want):
            np.testing.assert_array_equal(a, b)


def test_compiled_window_kernel_equals_the_numpy_window_path():
    """The numba kernel (stages.lib.maps.kernels) gives the numpy windowed path's values bit for bit, and leaves
    to the numpy paths (None) what they decide otherwise: non-finite hints or points, a decreasing arc, empty windows."""
    from stages.lib.maps import kernels
    from stages.lib.maps.geometry import _project_in_window

    if not kernels.available():
        import pytest

        pytest.skip("numba not importable")
    rng = np.random.default_rng(11)
    compared = 0
    for trial in range(200):
        n = int(rng.integers(2, 300))
        heading = np.cumsum(rng.normal(0.0, 0.5 if trial % 3 == 0 else 0.05, n - 1))
        step = rng.choice([0.5, 1.0]) * (np.where(rng.random(n - 1) < 0.05, 0.0, 1.0) if trial % 5 == 0 else np.ones(n - 1))  # some zero-length segments
        line = np.concatenate([[[0.0, 0.0]], np.cumsum(step[:, None] * np.column_stack([np.cos(heading), np.sin(heading)]), axis=0)])
        arc = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(line, axis=0).T))]) - rng.uniform(0, 10)
        k = int(rng.integers(1, 8))
        points = line[rng.integers(0, n, k)] + rng.normal(0, 3.0, (k, 2))
        if trial % 7 == 0:
            points[0] = line[int(rng.integers(0, n))]  # on a vertex: ties between two segments
        hints = rng.uniform(arc[0] - 20, arc[-1] + 20, k) if trial % 4 == 0 else rng.uniform(arc[0], arc[-1], k)
        window = float(rng.choice([0.2, 1.0, 5.0, 10.0]))
        given_heading = np.arctan2(np.gradient(line[:, 1]), np.gradient(line[:, 0])) if trial % 2 else None
        want = _project_in_window(points, line, arc, hints, window, given_heading, compiled=False)
        got = _project_in_window(points, line, arc, hints, window, given_heading, compiled=True)
        assert (got is None) == (want is None)
        if want is not None:
            compared += 1
            for a, b in zip((got.s_m, got.d_m, got.heading_rad), (want.s_m, want.d_m, want.heading_rad)):
                np.testing.assert_array_equal(a, b)
    assert compared > 100
    line = np.column_stack([np.arange(10.0), np.zeros(10)])
    arc = np.arange(10.0)
    assert kernels.project_window(np.array([[1.0, 1.0]]), line, arc, np.array([np.nan]), 2.0) is None
    assert kernels.project_window(np.array([[np.nan, 1.0]]), line, arc, np.array([3.0]), 2.0) is None
    assert kernels.project_window(np.array([[1.0, 1.0]]), line, arc[::-1].copy(), np.array([3.0]), 2.0) is None
    assert kernels.project_window(np.array([[1.0, 1.0]]), line, arc, np.array([30.0]), 2.0) is None  # nothing in the window
    s, d, seg = kernels.project_window(np.array([[2.5, 1.0], [-1.0, -2.0]]), line, arc, np.array([3.0, 0.0]), 2.0)
    np.testing.assert_array_equal(s, [2.5, -1.0])  # the first segment extended backwards
    np.testing.assert_array_equal(d, [1.0, -2.0])
    np.testing.assert_array_equal(seg, [2, 0])


def test_infinite_window_equals_the_projection_without_hints():
    """`project_in_window` with window = inf (the intentions stage's `_project`) gives `project_to_polyline`'s (s, d)
    without hints bit for bit: compiled, and through the numpy paths (NaN points, a decreasing arc, two points)."""
    from stages.lib.maps.geometry import project_in_window

    rng = np.random.default_rng(23)
    for trial in range(40):
        n = int(rng.integers(2, 300))
        line, arc = _random_polyline(rng, n, wiggly=trial % 3 == 0)
        if trial % 7 == 3:
            arc = arc[::-1].copy()  # decreasing: the kernel declines, the numpy paths answer
        k = int(rng.integers(1, 300))
        points = line[rng.integers(0, n, k)] + rng.normal(0, 3.0, (k, 2))
        points[rng.integers(0, k, 5 if trial % 5 == 0 else 0)] = np.nan
        want = project_to_polyline(points, line, arc)
        s, d = project_in_window(points, line, arc, 0.0, np.inf)
        np.testing.assert_array_equal(s, want.s_m)
        np.testing.assert_array_equal(d, want.d_m)
