"""The time-warp augmentation (stages/lib/datasets/warp.py, ``iamp train --speed-factors``)."""

from __future__ import annotations

import numpy as np
import pytest

from stages.lib.datasets.model import Sequence
from stages.lib.datasets.warp import time_warped
from stages.offline.train.dataset import DatasetConfig

PERIOD_NS = 100_000_000


def _sequence(rows: list[tuple[int, int, float, float, float]]) -> Sequence:
    """rows (track, frame, x, y, yaw) at 10 Hz, each track moving along x."""
    rows = sorted(rows, key=lambda r: (r[1], r[0]))
    a = np.array(rows, dtype=np.float64)
    n = len(rows)
    return Sequence(
        id="007", start_time="", duration_s=float(a[:, 1].max() - a[:, 1].min()) / 10.0, frame_rate_hz=10.0,
        origin_lat_deg=0.0, origin_lon_deg=0.0, source_files=(),
        frame_index=a[:, 1].astype(np.int64), stamp_ns=(a[:, 1] * PERIOD_NS).astype(np.int64), track_id=a[:, 0].astype(np.int64),
        agent_type=np.ones(n, np.uint8), x_m=a[:, 2], y_m=a[:, 3], vx_mps=np.full(n, 10.0), vy_mps=np.zeros(n),
        yaw_rad=a[:, 4], length_m=np.full(n, 4.5), width_m=np.full(n, 1.8),
    )


def _speeds(seq: Sequence) -> np.ndarray:
    order = np.lexsort((seq.stamp_ns, seq.track_id))
    same = np.diff(seq.track_id[order]) == 0
    step = np.hypot(np.diff(seq.x_m[order]), np.diff(seq.y_m[order]))[same]
    return step / (np.diff(seq.stamp_ns[order])[same] / 1e9)


def test_a_warped_sequence_follows_the_same_paths_faster_with_the_whole_scene_together() -> None:
    # two cars at 10 m/s and 5 m/s, 4 s each, yaw across ±π (unwrapped before it is interpolated)
    rows = [(1, k, 10.0 * k / 10, 0.0, np.pi - 0.01 + 0.001 * k) for k in range(41)]
    rows += [(2, k, 5.0 * k / 10, 3.0, 0.0) for k in range(10, 51)]
    seq = _sequence(rows)
    fast = time_warped(seq, 1.25)
    assert fast.id == "007@x1.25"
    np.testing.assert_allclose(_speeds(fast), np.concatenate([np.full(int(4.0 / 1.25 * 10), 12.5), np.full(int(4.0 / 1.25 * 10), 6.25)]))
    # every frame on the sequence's period, sorted by (frame, track), the frame index that of the stamp
    assert np.all(np.diff(np.unique(fast.stamp_ns)) == PERIOD_NS)
    np.testing.assert_array_equal(fast.frame_index, fast.stamp_ns // PERIOD_NS)
    assert np.all(np.diff(fast.frame_index) >= 0)
    # the same path: every warped position lies on the original track's line, first and last included
    car = fast.track_id == 1
    assert fast.x_m[car].min() == 0.0 and fast.x_m[car].max() == 40.0 and np.all(fast.y_m[car] == 0.0)
    # the second car starts 1 s after the first, 0.8 s in the warped scene: the scene is warped together
    assert fast.stamp_ns[fast.track_id == 2].min() == 8 * PERIOD_NS
    np.testing.assert_allclose(fast.vx_mps, 12.5)
    assert np.all(np.abs(fast.yaw_rad) <= np.pi)
    assert time_warped(seq, 1.0) is seq


def test_a_track_with_a_gap_is_not_bridged_and_a_repeated_stamp_keeps_its_first_row() -> None:
    rows = [(1, k, float(k), 0.0, 0.0) for k in range(0, 10)] + [(1, k, float(k), 0.0, 0.0) for k in range(20, 30)]
    seq = _sequence(rows + [(1, 5, 99.0, 0.0, 0.0)])  # frame 5 twice: the second row is a tracker's repeat
    slow = time_warped(seq, 0.8)
    stamps = slow.stamp_ns / 1e9
    assert not np.any((stamps > 9 / 0.8 + 1e-9) & (stamps < 20 / 0.8 - 1e-9))  # nothing invented in the gap
    assert slow.x_m.max() < 30 and np.all(np.abs(np.diff(slow.x_m)[np.diff(stamps) < 0.15] - 0.8) < 1e-9)


def test_bad_factors_are_refused_with_a_message() -> None:
    seq = _sequence([(1, k, float(k), 0.0, 0.0) for k in range(5)])
    with pytest.raises(ValueError, match="finite and > 0"):
        time_warped(seq, 0.0)
    for factors in ((1.0,), (0.8, 0.8), (3.0,), (float("nan"),)):
        with pytest.raises(ValueError, match="speed_factors"):
            DatasetConfig(speed_factors=factors)
    assert "speed_factors" not in DatasetConfig().key_dict()  # off: the keys (and caches) of data sets without it unchanged
    assert DatasetConfig(speed_factors=(0.8, 1.25)).key_dict()["speed_factors"] == [0.8, 1.25]


def test_a_time_split_widens_its_margins_by_the_largest_speed_factor() -> None:
    """A warped window stamped in its source's time spans 4·F s of it: with reach F no training window's future and no
    validation window's history crosses the cut, whatever the factor of the sample."""
    from stages.lib.ar.features import FEATURE_NAMES, HISTORY_STEPS, HORIZON_STEPS
    from stages.offline.train.dataset import ARDataset
    from stages.offline.train.fit import split_samples

    n = 600
    stamps = np.arange(n, dtype=np.int64) * PERIOD_NS
    ds = ARDataset(
        x=np.zeros((n, HISTORY_STEPS, len(FEATURE_NAMES)), np.float32), mask=np.ones((n, HISTORY_STEPS), bool),
        y=np.zeros((n, HORIZON_STEPS), np.float32), y_mask=np.ones((n, HORIZON_STEPS), bool), weight=np.ones(n, np.float32),
        recording=np.zeros(n, np.int32), sequence=np.zeros(n, np.int32), track_id=np.arange(n) % 7, corridor_id=np.zeros(n, np.int64),
        stamp_ns=stamps, recordings=("a",), sequences=("a/0",), sequence_spans=np.array([[0, stamps[-1]]]), counts={},
    )
    plain_train, plain_val, info = split_samples(ds, "time", 0.3, 0)
    train, val, info_wide = split_samples(ds, "time", 0.3, 0, reach=1.25)
    cut = info_wide["time_cuts"]["a/0"]["cut_stamp_s"] * 1e9
    assert info["time_cuts"]["a/0"]["cut_stamp_s"] * 1e9 == cut
    assert np.all(ds.stamp_ns[train] + 1.25 * 4e9 <= cut + 1) and np.all(ds.stamp_ns[val] - 1.25 * 4e9 >= cut - 1)
    assert len(train) == len(plain_train) - 10 and len(val) == len(plain_val) - 10  # 1 s more on each side, 10 windows at 10 Hz
