"""Online curve factor: how strongly hybrid's speed restriction slows cars for the curves ahead, chosen by what the cars did.

``hybrid_curve_factors`` (hybrid mode, with ``hybrid_speed_restriction``).
The restriction cuts λ_AR(k) per state by the admissible speed of the road
ahead, √(a_lat / (f·κ)) with the curvature κ of the corridor: f = 1 is the
baseline's rule, f = 0 the speed limit alone (the curves switch
``hybrid_speed_restriction_curves = false``), f = 2 halves the lateral
accelerations. Which f is right depends on the location and on the model: the
AR model reads the curvature ahead too, and whether it has learnt to slow for
it depends on where it was trained. Leave one location out, seed 0 (docs/evaluation.md,
"Online curve factor"): the K733-trained model on K729 was best
without the cut (mADE 1.385 → 1.343 m, fast cars 2.66 → 2.41), the
K729-trained model on K733 best with a stronger one (f = 2: 2.741 → 2.719;
f = 0: 3.198).

So the stage chooses f online, on the recording it predicts, by causal back
testing: at each frame it takes at most ``PER_FRAME`` moving vehicles with a
curve ahead (chosen from the frame's stamp, so the choice does not depend on
the order frames are handled in; a frame of more than ``PAIRS_PER_TEST``
pairs only every ⌈pairs / ``PAIRS_PER_TEST``⌉-th frame), runs the chain of
their pairs for the other candidates in one batch (the factor in use gives
the frame's own rows, which are not touched), and keeps each candidate's
mean positions. ``lag_s`` after the horizon (so that frames handled out of order
have stored their positions), each candidate scores the vehicle's ADE as
``iamp eval``'s mADE counts it (the best of its corridors), over the step
times the vehicle was seen at, from the first on: at least half the horizon
(a car that leaves the scene within 2 s is not scored; many with a bend
ahead leave within 4 s). The factor used is ``default`` (1, the baseline's
rule, when it is a candidate) until the evidence says otherwise: of the
candidates whose ADE is lower than the default's on the same samples by
``MIN_T`` standard errors of the paired difference or more (after at least
``MIN_SAMPLES``), the one with the lowest mean. What it learnt is kept
across ``reset`` (it belongs to the location, the tracker and the model);
the pending samples and positions are not.
"""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass, field

import numpy as np

#: scored samples before a candidate may replace ``default``
MIN_SAMPLES = 20
#: how sure: a candidate replaces ``default`` when its mean ADE difference to it is below 0 by this many standard errors
#: (consecutive frames sample the same cars, so the errors are correlated: 3, not 2)
MIN_T = 3.0
#: vehicles back-tested per frame at most
PER_FRAME = 1
#: a frame with more pairs than this is back-tested only every ⌈pairs / PAIRS_PER_TEST⌉-th frame (by its stamp): at a
#: busy junction the samples come anyway, and the extra chain stays a small share of the frame's
PAIRS_PER_TEST = 16


@dataclass
class _Sample:
    stamp_ns: int
    track_id: int
    means: np.ndarray  # (C, P, K, 2): each candidate's mean positions of the vehicle's pairs


@dataclass
class OnlineCurveChoice:
    """The curve factor of hybrid's speed restriction, chosen online by back testing (module docstring)."""

    factors: tuple[float, ...]
    step_times_s: np.ndarray
    default: float = 1.0
    min_samples: int = MIN_SAMPLES
    lag_s: float = 1.0
    tolerance_s: float = 0.05
    sum_ade: np.ndarray = field(init=False)
    sum_diff2: np.ndarray = field(init=False)  # Σ (ADE − the default's ADE)² per candidate
    samples: int = 0
    unresolved: int = 0  # samples without positions over half the horizon (track ended, gaps)
    jumped: int = 0  # samples whose track moved faster than MAX_TRUTH_SPEED_MPS between two positions (not scored)
    pending: list[_Sample] = field(default_factory=list)
    positions: dict[int, list[tuple[int, float, float]]] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.factors = tuple(float(f) for f in self.factors)
        self._check()
        if self.default not in self.factors:
            self.default = self.factors[0]
        self.step_ns = np.round(np.asarray(self.step_times_s, dtype=np.float64) * 1e9).astype(np.int64)
        self.sum_ade = np.zeros(len(self.factors))
        self.sum_diff2 = np.zeros(len(self.factors))
        self._default_index = self.factors.index(self.default)

    def _check(self) -> None:
        if len(self.factors) < 2 or any(not (math.isfinite(f) and f >= 0) for f in self.factors):
            raise ValueError(f"hybrid_curve_factors = {self.factors!r}: need two or more finite factors >= 0")

    @property
    def factor(self) -> float:
        """Of the candidates better than ``default`` by ``MIN_T`` standard errors (``t_values``), the one with the
        lowest mean ADE; ``default`` when none is (or before ``min_samples``)."""
        t = self.t_values()
        better = [c for c in range(len(self.factors)) if t[c] < -MIN_T]
        if self.samples < self.min_samples or not better:
            return self.default
        return self.factors[min(better, key=lambda c: self.sum_ade[c])]

    def t_values(self) -> np.ndarray:
        """(C,) the paired t statistic of each candidate's ADE minus the default's (0 for the default; NaN below 2
        samples)."""
        n = self.samples
        if n < 2:
            return np.full(len(self.factors), np.nan)
        diff = (self.sum_ade - self.sum_ade[self._default_index]) / n
        var = np.maximum(self.sum_diff2 / n - diff**2, 0.0) * n / (n - 1)
        with np.errstate(invalid="ignore", divide="ignore"):
            t = np.where(var > 0, diff / np.sqrt(var / n), 0.0)
        return t

    def add_positions(self, stamp_ns: int, track_ids, xs, ys) -> None:
        """The vehicles' positions at ``stamp_ns`` (kept in stamp order whatever order frames come in)."""
        stamp = int(stamp_ns)
        for t, x, y in zip(track_ids, xs, ys):
            if not (math.isfinite(x) and math.isfinite(y)):
                continue
            kept = self.positions.setdefault(int(t), [])
            if not kept or stamp > kept[-1][0]:
                kept.append((stamp, float(x), float(y)))
                continue
            i = bisect.bisect_left(kept, (stamp,))
            if i < len(kept) and kept[i][0] == stamp:
                continue
            kept.insert(i, (stamp, float(x), float(y)))

    def record(self, track_id: int, stamp_ns: int, means: np.ndarray) -> None:
        self.pending.append(_Sample(int(stamp_ns), int(track_id), np.asarray(means, dtype=np.float64)))

    def resolve(self, now_ns: int) -> None:
        """Score every sample whose horizon ended ``lag_s`` or more before ``now_ns``; forget positions too old to
        score any sample still to come."""
        now = int(now_ns)
        horizon = int(self.step_ns[-1]) if self.step_ns.size else 0
        ready = now - horizon - int(round(self.lag_s * 1e9))
        keep = []
        for sample in self.pending:
            if sample.stamp_ns > ready:
                keep.append(sample)
                continue
            ade = self._score(sample)
            if ade is None or ade is JUMPED:
                self.unresolved += ade is None
                self.jumped += ade is JUMPED
                continue
            self.sum_ade += ade
            self.sum_diff2 += (ade - ade[self._default_index]) ** 2
            self.samples += 1
        self.pending = keep
        oldest = min([s.stamp_ns for s in keep], default=ready) - int(round(self.tolerance_s * 1e9))
        for track_id in list(self.positions):
            kept = self.positions[track_id]
            cut = bisect.bisect_left(kept, (min(oldest, ready),))
            if cut:
                del kept[:cut]
            if not kept:
                del self.positions[track_id]

    def _score(self, sample: _Sample) -> np.ndarray | object | None:
        """(C,) each candidate's ADE of the sample (the best of the vehicle's pairs) over the step times at which the
        vehicle was seen (within ``tolerance_s``), from the first on; None when that is less than half the horizon (a
        car that left soon after) or a candidate has no finite mean; ``JUMPED`` when its track jumped (``_jumped``)."""
        kept = self.positions.get(sample.track_id)
        if not kept:
            return None
        stamps = [p[0] for p in kept]
        tol = int(round(self.tolerance_s * 1e9))
        truth, last = [], -1
        for dt in self.step_ns.tolist():
            want = sample.stamp_ns + dt
            i = bisect.bisect_left(stamps, want - tol)
            if i >= len(stamps) or abs(stamps[i] - want) > tol:
                break
            truth.append(kept[i][1:])
            last = i
        n = len(truth)
        if n < max(1, -(-self.step_ns.size // 2)):
            return None
        if _jumped(kept, bisect.bisect_left(stamps, sample.stamp_ns - tol), last):
            # the track jumped (a re-used id, a tracker's glitch, a position far off the map): its error is not the
            # candidates', and one such sample would swamp every mean (a 70 km jump: mean ADE 1,155 m for the run)
            return JUMPED
        err = np.linalg.norm(sample.means[:, :, :n] - np.asarray(truth)[None, None], axis=3)  # (C, P, n)
        with np.errstate(invalid="ignore"):
            ade = err.mean(axis=2)  # (C, P): NaN where a step has no mean
        ade = np.where(np.isfinite(ade), ade, np.inf).min(axis=1)
        return ade if np.all(np.isfinite(ade)) else None

    def reset(self) -> None:
        """A new sequence: the pending samples and positions go, what was learnt stays."""
        self.pending.clear()
        self.positions.clear()

    def summary(self) -> dict[str, object]:
        mean = (self.sum_ade / self.samples).tolist() if self.samples else [math.nan] * len(self.factors)
        return {"factor": self.factor, "factors": list(self.factors), "samples": self.samples, "unresolved": self.unresolved,
                "jumped": self.jumped, "mean_ade_m": mean, "t_vs_default": self.t_values().tolist()}


@dataclass
class OnlineShiftChoice(OnlineCurveChoice):
    """Online acceleration shift (``hybrid_accel_shifts``): a constant added to every AR input distribution's
    acceleration (``Pair.accel_shift_mps2``, ``modes.hybrid.shift_inputs``), chosen as the curve factor is, by causal
    back testing on the recording (``OnlineCurveChoice``; here ``factors`` are the candidate shifts in m/s², any sign,
    and ``default`` is 0, the model's own distribution). Why: held out, the models under-predict the cars that
    accelerate at both locations (along-track error at 4 s −3.0 m over all K729 windows, −7.8 for those cars), but a
    fixed shift chosen on K729 costs more on the others than it gains there (docs/evaluation.md, "Online acceleration
    shift"); a recording whose drivers accelerate harder than the model's training location shows it in the back
    test, and one that does not keeps 0."""

    default: float = 0.0

    def _check(self) -> None:
        if len(self.factors) < 2 or any(not math.isfinite(f) for f in self.factors):
            raise ValueError(f"hybrid_accel_shifts = {self.factors!r}: need two or more finite shifts (m/s²)")


@dataclass
class OnlineLeadChoice(OnlineCurveChoice):
    """Online speed lead (``hybrid_speed_leads_s``): a moving pair's chain starts at v0 + L·a instead of v0, a the
    corridors stage's estimated acceleration (``Pair.speed_lead_s``, ``MarkovPredictor._boxes``), L chosen as the curve
    factor is, by causal back testing on the recording (``OnlineCurveChoice``; ``factors`` are the candidate leads in
    seconds, ``default`` 0, the estimate as it is). Why: the start speed is what is left of hybrid's error where the
    estimate lags (docs/evaluation.md, "How far perfect inputs go"), and whether the estimated acceleration carries on
    depends on the recording (K729: a fixed lead of 0.4 s takes hybrid's mADE from 1.366 to 1.228 m, chosen online
    1.250; K733, whose positions jitter in time, loses with any lead: docs/evaluation.md, "Online speed lead")."""

    default: float = 0.0

    def _check(self) -> None:
        if len(self.factors) < 2 or any(not (math.isfinite(f) and f >= 0) for f in self.factors):
            raise ValueError(f"hybrid_speed_leads_s = {self.factors!r}: need two or more finite leads (s, >= 0)")


#: ``_score``'s answer for a sample whose track jumped (counted as ``jumped``, not scored)
JUMPED = object()
#: a track that moved faster than this between two of its kept positions jumped: no car's motion (K733's fastest cars
#: are under 20 m/s; a glitch or a re-used id moves tens to thousands of metres in a frame)
MAX_TRUTH_SPEED_MPS = 70.0


def _jumped(kept: list[tuple[int, float, float]], first: int, last: int) -> bool:
    """Whether the positions ``kept[first..last]`` (stamp order; from the sample's own stamp on where it is kept) hold a
    step faster than ``MAX_TRUTH_SPEED_MPS``."""
    if last <= first:
        return False
    run = np.asarray(kept[max(first, 0): last + 1], dtype=np.float64)  # (n, 3): stamp, x, y
    dt = np.diff(run[:, 0]) * 1e-9
    step = np.hypot(np.diff(run[:, 1]), np.diff(run[:, 2]))
    return bool(np.any(step > MAX_TRUTH_SPEED_MPS * np.maximum(dt, 1e-3)))


def _stamp_hash(stamp_ns: int) -> int:
    """The stamp (µs, so any frame rate) hashed to 64 bits."""
    return ((int(stamp_ns) // 1000) * 0x9E3779B97F4A7C15) & 0xFFFFFFFFFFFFFFFF


def frame_tested(stamp_ns: int, pairs: int) -> bool:
    """Whether a frame of ``pairs`` pairs is back-tested: all of them up to ``PAIRS_PER_TEST`` pairs, else one in
    ⌈``pairs`` / ``PAIRS_PER_TEST``⌉, chosen by the stamp's hash."""
    return (_stamp_hash(stamp_ns) >> 16) % max(1, -(-int(pairs) // PAIRS_PER_TEST)) == 0


def sampled(track_ids: list[int], stamp_ns: int, n: int = PER_FRAME, pairs: int = 0) -> list[int]:
    """At most ``n`` of ``track_ids``, chosen from the stamp alone (a hash of it picks where to start in the sorted ids);
    none where the frame is not tested (``frame_tested`` with ``pairs``)."""
    ids = sorted(set(int(t) for t in track_ids))
    if not ids or n <= 0 or not frame_tested(stamp_ns, pairs):
        return []
    start = (_stamp_hash(stamp_ns) >> 32) % len(ids)
    return [ids[(start + i * max(1, len(ids) // n)) % len(ids)] for i in range(min(n, len(ids)))]


__all__ = ["MIN_SAMPLES", "MIN_T", "OnlineCurveChoice", "OnlineLeadChoice", "OnlineShiftChoice", "PAIRS_PER_TEST", "PER_FRAME", "frame_tested", "sampled"]
