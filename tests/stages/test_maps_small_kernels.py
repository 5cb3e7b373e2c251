"""The small map kernels (`stages.lib.maps.kernels.unwrapped_interp`, `max_separation`) against the numpy code they
replace, bit for bit, on random and edge cases."""

from __future__ import annotations

import math

import numpy as np
import pytest

from stages.lib.maps import kernels
from stages.corridors.routes import max_separation_m


pytestmark = pytest.mark.skipif(not kernels.available(), reason="numba not importable")


def _same(a: float, b: float) -> bool:
    return (math.isnan(a) and math.isnan(b)) or np.float64(a).tobytes() == np.float64(b).tobytes()


def test_unwrapped_interp_is_numpy_interp_of_unwrap_bit_for_bit():
    rng = np.random.default_rng(7)
    checked = 0
    for case in range(400):
        m = int(rng.integers(2, 40))
        xp = np.cumsum(rng.uniform(0.01, 1.0, m)) - rng.uniform(0, 3)
        if case % 3 == 0:  # a corridor's wrapped heading through +-pi, with jumps of exactly pi now and then
            fp = (np.cumsum(rng.normal(0.0, 0.6, m)) + math.pi) % (2 * math.pi) - math.pi
            fp[rng.integers(0, m)] = math.pi
        else:
            fp = rng.uniform(-10, 10, m)
            if case % 7 == 0:
                fp[1:] = fp[:-1] + math.pi  # |dd| == pi exactly: numpy's boundary case
        for x in [*rng.uniform(xp[0] - 2, xp[-1] + 2, 8), xp[0], xp[-1], xp[m // 2], xp[0] - 1e-12]:
            want = float(np.interp(x, xp, np.unwrap(fp)))
            got = kernels.unwrapped_interp(float(x), xp, fp)
            assert got is not None and _same(got, want), (case, x)
            checked += 1
    assert checked == 400 * 12


def test_unwrapped_interp_declines_what_it_does_not_cover():
    xp, fp = np.arange(5.0), np.zeros(5)
    assert kernels.unwrapped_interp(math.nan, xp, fp) is None
    assert kernels.unwrapped_interp(1.0, np.array([0.0, 1.0, 1.0, 2.0]), np.zeros(4)) is None  # not strictly increasing
    assert kernels.unwrapped_interp(1.0, xp, np.array([0.0, np.nan, 0, 0, 0])) is None
    assert kernels.unwrapped_interp(1.0, xp.astype(np.float32), fp) is None  # another dtype: numpy


def test_max_separation_kernel_is_the_numpy_max_bit_for_bit(monkeypatch):
    from bus_schemas import Corridor

    rng = np.random.default_rng(3)

    def corridor(n, nan=False):
        x, y = rng.normal(0, 50, n), rng.normal(0, 50, n)
        if nan:
            x[rng.integers(0, n)] = np.nan
        z = np.zeros(n)
        return Corridor(corridor_id=1, lanelet_ids=np.zeros(1, np.int64), lanelet_start_s_m=np.zeros(1), x_m=x, y_m=y, s_m=z,
                        heading_rad=z, curvature_1pm=z, width_m=z, extension_start_s_m=0.0, vehicle_s_m=0.0, vehicle_d_m=0.0,
                        speed_limit_mps=10.0)

    cases = [(corridor(int(rng.integers(1, 30))), corridor(int(rng.integers(1, 30)), nan=k % 5 == 0), int(rng.integers(0, 35)))
             for k in range(300)]
    compiled = [max_separation_m(a, b, i) for a, b, i in cases]
    monkeypatch.setattr(kernels, "max_separation", lambda *args: None)
    reference = [max_separation_m(a, b, i) for a, b, i in cases]
    assert all(_same(x, y) for x, y in zip(compiled, reference))
    assert sum(math.isnan(x) for x in reference) > 10 and sum(x == 0.0 for x in reference) > 10
