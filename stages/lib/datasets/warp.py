"""A sequence played faster or slower: the time-warp augmentation of the AR training data.

``time_warped(seq, f)`` is ``seq`` with every track's time scaled by 1/f: each
object follows the same path, f times as fast (speeds × f, accelerations × f²),
and the whole scene together, so that leaders, queues and gaps stay
consistent. The tracks are resampled on the sequence's own frame period
(linear interpolation of position, velocity and yaw, unwrapped), each in its
stretches without a gap (a gap longer than 1.5 periods splits a track;
repeated stamps keep their first row). Reported velocities are scaled by f;
sizes and types are kept. The frame index is ``round(stamp · rate)`` as the
loaders make it. Used by ``iamp train --speed-factors`` (DatasetConfig
``speed_factors``): a location whose traffic is faster or slower than the
training location's is then not out of the model's range.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from stages.lib.datasets.kinematics import _wrap as wrap_angle
from stages.lib.datasets.model import ARRAY_FIELDS, Sequence

#: a gap between two rows of a track longer than this many frame periods splits it (nothing is invented across it)
MAX_GAP_PERIODS = 1.5


def time_warped(seq: Sequence, factor: float) -> Sequence:
    """``seq`` played ``factor`` times as fast (module docstring); ``factor`` 1 returns ``seq`` itself.
    ValueError for a factor that is not finite and positive."""
    if not (math.isfinite(factor) and factor > 0):
        raise ValueError(f"time_warped: factor {factor!r} must be finite and > 0")
    if factor == 1.0 or seq.n_rows == 0:
        return seq
    period = seq.period_ns
    cols: dict[str, list[np.ndarray]] = {name: [] for name in ARRAY_FIELDS}
    order = np.lexsort((seq.stamp_ns, seq.track_id))
    tracks = np.split(order, np.flatnonzero(np.diff(seq.track_id[order])) + 1)
    for rows in tracks:
        stamps = seq.stamp_ns[rows]
        keep = np.concatenate(([True], np.diff(stamps) > 0))  # a repeated stamp: its first row
        rows, stamps = rows[keep], stamps[keep]
        for piece in np.split(np.arange(rows.size), np.flatnonzero(np.diff(stamps) > MAX_GAP_PERIODS * period) + 1):
            r = rows[piece]
            t = stamps[piece].astype(np.float64) / factor
            first, last = math.ceil(t[0] / period - 1e-9), math.floor(t[-1] / period + 1e-9)
            if last < first:
                continue
            k = np.arange(first, last + 1, dtype=np.int64)
            new_t = (k * period).astype(np.float64)
            n = k.size
            cols["stamp_ns"].append(k * period)
            cols["frame_index"].append(np.rint(k * period * seq.frame_rate_hz / 1e9).astype(np.int64))
            cols["track_id"].append(np.full(n, seq.track_id[r[0]], np.int64))
            cols["agent_type"].append(np.full(n, seq.agent_type[r[0]], np.uint8))
            for name in ("x_m", "y_m"):
                cols[name].append(np.interp(new_t, t, getattr(seq, name)[r]))
            for name in ("vx_mps", "vy_mps"):
                cols[name].append(np.interp(new_t, t, getattr(seq, name)[r]) * factor)
            cols["yaw_rad"].append(wrap_angle(np.interp(new_t, t, np.unwrap(seq.yaw_rad[r]))))
            for name in ("length_m", "width_m"):
                cols[name].append(np.full(n, getattr(seq, name)[r[0]], np.float64))
    arrays = {name: (np.concatenate(parts).astype(ARRAY_FIELDS[name]) if parts else np.zeros(0, ARRAY_FIELDS[name]))
              for name, parts in cols.items()}
    by_frame = np.lexsort((arrays["track_id"], arrays["frame_index"]))
    arrays = {name: a[by_frame] for name, a in arrays.items()}
    duration = float((arrays["stamp_ns"][-1] - arrays["stamp_ns"][0]) / 1e9) if arrays["stamp_ns"].size else 0.0
    return dataclasses.replace(seq, id=f"{seq.id}@x{factor:g}", duration_s=duration, **arrays)
