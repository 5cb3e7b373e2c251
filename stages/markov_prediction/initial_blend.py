"""Online initial blend: how much of a moving car's measured acceleration its first input takes, learnt from the cars.

``hybrid_initial_input = "adaptive"`` (hybrid mode). The chain's first input
λ(0) of a moving pair is the normal of the AR model's spread σ_m at

    μ_m + w · (a − μ_m),

μ_m the mean of the model's λ(0), a the measured acceleration (the
least-squares slope of the car's speeds over the last ``accel_window_s``,
``MarkovPredictor.measured_acceleration``). The weight w is learnt here, on
the recording being predicted, from what the cars then did: for each moving
pair the stage records (t0, a, μ_m); at the first frame whose stamp is
``accel_window_s`` or more later the car's realised acceleration r is the
slope of its speeds over (t0, t0 + ``accel_window_s``] (samples after t0
only, so r shares no sample with a),
and w is the least-squares weight of the two predictors,

    w = Σ (r − μ_m)(a − μ_m) / Σ (a − μ_m)²,   clipped to [0, 1],

the convex combination of the two with the smallest squared error against
what followed. Noise in r (the tracker's) does not bias w; noise in a
lowers it, which is what it should do. Why: the precision blend
(``"blend"``, the slope's own standard error against σ_m) gained on K729,
whose tracker is smooth (held out, K733-trained model: mADE 1.55 → 1.34 m),
and lost on K733, whose speeds jitter by ±3 m/s (2.76 → 2.85 m): the slope's
standard error does not say how well the slope predicts the next seconds
there. Here the recording says it.

Until ``MIN_RECORDS`` pairs are resolved w = 0 (λ(0) of the model, the
``"ar"`` default). One record per vehicle and frame (μ_m the mean over its
pairs); standing vehicles are not recorded (their λ(0) is the start model).
What it learnt is kept across ``reset`` (it belongs to the location and the
tracker); the pending records are not. Counted for the log and the tests:
``resolved``, ``weight``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from stages.lib.ar.features import causal_acceleration

#: resolved records before the learnt weight is used (before: w = 0, the model's λ(0)); set before any run
MIN_RECORDS = 50


@dataclass
class OnlineInitialBlend:
    """The weight w of the measured acceleration in a moving pair's first input, learnt online (module docstring)."""

    window_s: float
    min_records: int = MIN_RECORDS
    #: per track: (t0 ns, measured a, model's mean μ_m) waiting for the car's next ``window_s``
    pending: dict[int, list[tuple[int, float, float]]] = field(default_factory=dict)
    sum_xy: float = 0.0  # Σ (r − μ)(a − μ)
    sum_xx: float = 0.0  # Σ (a − μ)²
    resolved: int = 0
    unresolved: int = 0  # records whose window had too few speeds (track ended, gaps)

    def __post_init__(self) -> None:
        if not (math.isfinite(self.window_s) and self.window_s > 0):
            raise ValueError(f"window_s = {self.window_s!r}: must be > 0 (accel_window_s)")

    @property
    def weight(self) -> float:
        """w in [0, 1]; 0 until ``min_records`` records are resolved."""
        if self.resolved < self.min_records or self.sum_xx <= 0.0:
            return 0.0
        return float(min(max(self.sum_xy / self.sum_xx, 0.0), 1.0))

    def record(self, track_id: int, stamp_ns: int, a_mps2: float, mu_mps2: float) -> None:
        """Keep (t0, a, μ_m) of one vehicle at one frame (once: a second record of the same stamp is ignored)."""
        if not (math.isfinite(a_mps2) and math.isfinite(mu_mps2)):
            return
        kept = self.pending.setdefault(int(track_id), [])
        if kept and kept[-1][0] >= stamp_ns:
            return
        kept.append((int(stamp_ns), float(a_mps2), float(mu_mps2)))

    def resolve(self, histories, now_ns: int) -> None:
        """Resolve every record whose window ended by ``now_ns`` from ``histories`` (track id -> object with
        ``samples``: (stamp ns, speed m/s) in stamp order); records of tracks without a history are dropped."""
        window = int(round(self.window_s * 1e9))
        for track_id in list(self.pending):
            kept = self.pending[track_id]
            hist = histories.get(track_id)
            if hist is None:
                self.unresolved += len(kept)
                del self.pending[track_id]
                continue
            while kept and kept[0][0] + window <= now_ns:
                t0, a, mu = kept.pop(0)
                r = _slope([(t, v) for t, v in hist.samples if t0 < t <= t0 + window], self.window_s)
                if r is None:
                    self.unresolved += 1
                    continue
                self.sum_xy += (r - mu) * (a - mu)
                self.sum_xx += (a - mu) ** 2
                self.resolved += 1
            if not kept:
                del self.pending[track_id]

    def reset(self) -> None:
        """A new sequence: the pending records go, what was learnt stays."""
        self.pending.clear()

    def summary(self) -> dict[str, object]:
        return {"resolved": self.resolved, "unresolved": self.unresolved, "weight": self.weight,
                "raw_weight": (self.sum_xy / self.sum_xx) if self.sum_xx > 0 else math.nan}


def _slope(points: list[tuple[int, float]], window_s: float) -> float | None:
    """The least-squares slope (m/s²) of the speeds ``points`` ((stamp ns, speed), in stamp order, all within one
    ``window_s``): ``causal_acceleration``'s, the ar features' and the measured acceleration's rule; None where that
    rule has none (fewer than 3 samples, a span below half the window) or a speed is not finite."""
    if len(points) < 3 or (points[-1][0] - points[0][0]) * 1e-9 < 0.5 * window_s - 1e-6:
        return None
    v = np.array([p[1] for p in points], dtype=np.float64)
    if not np.all(np.isfinite(v)):
        return None
    return causal_acceleration(np.array([p[0] for p in points], dtype=np.int64), v, window_s)


__all__ = ["MIN_RECORDS", "OnlineInitialBlend"]
