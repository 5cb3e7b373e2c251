"""Kinematic state of every track, causally: positions first, the tracker's velocity as checked evidence.

Why: a tracker's reported velocities are one tracker's convention. Seen so far:
scaled (a TAF-BW recording whose ``vx, vy`` are about half the speed its
positions imply), zero for the first frames of a track while the car already
moves at 10-19 m/s, pointing backwards (k733_2018-05-02), lagging. Positions
are the one field every tracker gets right to within its noise, so every
stage takes speed, velocity and acceleration from ``KinematicEstimator``
(the corridors stage runs it and publishes the state in ``CorridorSet``).

Per track, a constant-velocity Kalman filter on x and y (white-noise
acceleration of spectral density ``accel_noise_m2ps3``) whose position noise
is estimated online from its own innovations (an exponentially weighted mean
of the squared innovation less the predicted position variance, floored at
``min_position_noise_m``²): it follows K729's clean positions closely and
smooths K733's sample-and-hold positions (the tracker repeats a position for
several frames, then jumps) without a per-recording setting.

A bank of such filters: the noise estimate cannot tell a noisy tracker from a
car that accelerates, so every track runs one filter per value of
``accel_noise_bank`` (with ``accel_noise_m2ps3`` among them, the one published
first) on the same samples. Each sample keeps every filter's speed; once it
is ``bank_horizon_s`` old, each is scored by speed x elapsed time against the
distance the track covered since (squared, an exponentially weighted mean
over the stream with a memory of ``bank_memory`` samples; a track's first
second left out). After ``bank_min_samples`` scored samples the stream
publishes the filter with the lowest mean, switching when another is lower by
``bank_switch_gain``. Causal: a sample is judged only after its horizon, on
positions. ``backtest()`` reports the choice, the switches and each filter's
rms. A bank of one value is the single filter.

The reported velocity is checked against the positions and used only once
it has passed:

- Calibration (per stream, ``Calibration``): for every moving sample of a
  track at least 1 s old, the mean reported velocity over the last second is
  compared with the chord of the positions over the same second (factor of
  the lengths, cosine of the angle; the chord does not depend on the filter,
  so the check cannot confirm itself). Trusted when at least
  ``calibration_min_samples`` samples from ``calibration_min_tracks`` tracks
  agree: |median cosine| >= 0.9 and the factor's interquartile range within
  ``calibration_max_spread`` of its median. A trusted reported velocity is
  used as ``sign(cosine) · reported / factor``: a scale or a reversal is
  undone, not merely detected.
- Fusion: from a track's second sample on, the calibrated velocity is a
  measurement of the filter's velocity with its own noise, adapted like the
  position noise (``velocity_noise_adaptation``); a sample more than
  ``velocity_gate_sigma`` standard deviations (+ 1 m/s) off the filter's
  velocity is rejected (issue ``velocity_rejected``): a zero at birth while the
  positions move never pulls a track to a stop. ``fuse_reported = false``
  uses positions alone.
- A reported speed below 0.1 m/s is never fused: trackers report zero at a
  track's birth and on dropouts, and whether a car stands is for its
  positions (the dead band) to say; while the positions show it moving at
  2 m/s or more, each such sample is an issue ``velocity_zero_while_moving``.
- The first sample of a track has a position only: its speed is the
  calibrated reported one if trusted, else the reported one as given
  (``source = "reported"``); a reported zero there is unknown (NaN, ``source
  = "unknown"``: the corridors stage reports the track ``state_pending`` for
  that one frame) rather than a standing car that is not standing: a birth
  at speed 0 misleads the intentions filter's particles and the
  acceleration history (measured: docs/method.md §6.3).
  It is not fed to the filter.
- Per track, once it has ``consistency_min_samples`` such samples, the
  medians decide it: a factor outside ``[1 / factor_tolerance,
  factor_tolerance]`` or a cosine below 0.5 is one ``velocity_inconsistent``
  issue for that track. ``consistency()`` sums the decided tracks and
  ``warning()`` returns one line, once, when enough of them disagree.

Also:

- Standstill dead band: a track stands (speed 0, acceleration 0) when its
  filtered speed over the last 0.3 s is below ``standstill_max_speed_mps`` on
  average and, over the last
  ``standstill_window_s``, the median position of the newer half of its
  samples lies within ``standstill_radius_m`` of the older half's: position
  jitter, and the single glitches of K733's tracker, never become a creeping
  speed, and a car pulling away is released as soon as the filter sees it
  move.
- Acceleration: the slope of a least-squares line through the filtered speed
  over the last ``accel_window_s`` (0 when standing or with too few samples).
- A position more than ``jump_m`` off the filter's prediction (and more than
  five of its standard deviations) restarts the track at the new position
  (issue ``position_jump``); so does a gap longer than ``max_gap_s`` between
  two samples (a re-used track id, issue ``track_restarted``). ``started_ns``
  says at which sample a track's state (re)started: the corridors stage then
  drops what it kept of the car before.

Chosen by the constant-speed displacement error at 1/2/4 s on both
development locations (``bench/state_estimator.py``; figures in README.md,
"State from positions").

Pure: numpy and the standard library; time comes from the frames' stamps.
"""

from __future__ import annotations

import bisect
import collections
import math
from dataclasses import dataclass, field

import numpy as np

from stages.lib.base import ConfigMixin, Issue, check_ranges

_NS = 1e-9
_ZERO_MPS = 0.1  # a reported speed below this counts as "reported zero"
#: decided tracks (reported against position-implied velocity) that the estimator's consistency and its warning are
#: judged on: the most recent ones (a recording holds a few hundred; a live stream adds thousands a day)
DECIDED_WINDOW = 1000


@dataclass(frozen=True, kw_only=True)
class EstimatorConfig(ConfigMixin):
    """Parameters of ``KinematicEstimator`` (module docstring)."""

    accel_noise_m2ps3: float = 10.0
    initial_position_noise_m: float = 0.1
    min_position_noise_m: float = 0.02
    noise_adaptation: float = 0.05
    initial_speed_sigma_mps: float = 10.0
    standstill_radius_m: float = 0.25
    standstill_max_speed_mps: float = 0.5
    standstill_window_s: float = 1.0
    accel_window_s: float = 1.0
    jump_m: float = 5.0
    max_gap_s: float = 1.0
    consistency_min_speed_mps: float = 2.0
    consistency_min_samples: int = 10
    factor_tolerance: float = 1.25
    warn_min_tracks: int = 3
    warn_share: float = 0.3
    fuse_reported: bool = True
    calibration_min_samples: int = 30
    calibration_min_tracks: int = 2
    calibration_max_spread: float = 0.3
    calibration_window: int = 500
    initial_velocity_noise_mps: float = 1.0
    min_velocity_noise_mps: float = 0.05
    velocity_noise_adaptation: float = 0.2
    velocity_gate_sigma: float = 3.0
    accel_noise_bank: tuple[float, ...] = (1.0, 3.0, 10.0)
    bank_horizon_s: float = 2.0
    bank_min_samples: int = 300
    bank_memory: int = 3000
    bank_switch_gain: float = 0.03

    def __post_init__(self) -> None:
        positive = ("accel_noise_m2ps3", "initial_position_noise_m", "min_position_noise_m", "initial_speed_sigma_mps",
                    "standstill_window_s", "accel_window_s", "jump_m", "max_gap_s", "consistency_min_speed_mps")
        non_negative = ("standstill_radius_m",)
        check_ranges(self, positive=positive, non_negative=non_negative)
        if not (0.0 < self.noise_adaptation <= 1.0):
            raise ValueError(f"noise_adaptation must be in (0, 1], got {self.noise_adaptation}")
        if self.factor_tolerance <= 1.0:
            raise ValueError(f"factor_tolerance must be > 1, got {self.factor_tolerance}")
        if self.consistency_min_samples < 1 or self.warn_min_tracks < 1 or not (0.0 < self.warn_share <= 1.0):
            raise ValueError("consistency_min_samples and warn_min_tracks must be >= 1, warn_share in (0, 1]")
        bank = tuple(self.accel_noise_bank)
        if not all(isinstance(q, (int, float)) and math.isfinite(q) and q > 0 for q in bank) or len(set(bank)) != len(bank):
            raise ValueError(f"accel_noise_bank must hold distinct finite values > 0, got {self.accel_noise_bank!r}")
        object.__setattr__(self, "accel_noise_bank", tuple(float(q) for q in bank))
        if not (self.bank_horizon_s > 0 and self.bank_min_samples >= 1 and self.bank_memory >= 1 and 0.0 <= self.bank_switch_gain < 1.0):
            raise ValueError("bank_horizon_s must be > 0, bank_min_samples and bank_memory >= 1, bank_switch_gain in [0, 1)")

    @property
    def filter_bank(self) -> tuple[float, ...]:
        """The accelerations noises the estimator runs, ascending: the bank with ``accel_noise_m2ps3`` (the start) in it."""
        return tuple(sorted({*self.accel_noise_bank, float(self.accel_noise_m2ps3)}))


@dataclass(frozen=True, slots=True)
class KinematicState:
    """One track's state at one stamp. ``source``: "positions", "reported" (first sample) or "unknown"."""

    vx_mps: float
    vy_mps: float
    speed_mps: float
    accel_mps2: float
    standing: bool
    source: str
    reported_speed_mps: float

    @property
    def heading_rad(self) -> float:
        """Direction of the estimated velocity (NaN when standing or unknown)."""
        if self.standing or not (self.speed_mps > 0.0):
            return math.nan
        return math.atan2(self.vy_mps, self.vx_mps)


@dataclass(slots=True, eq=False)
class _Filter:
    """One constant-velocity Kalman filter of a track (one member of the bank)."""

    x: list[float]  # [position, velocity] along x
    y: list[float]
    p: list[float]  # shared covariance [p00, p01, p11] (same H and dt for both axes)
    r: float  # measurement noise variance, adapted
    rv: float = 1.0  # variance of the calibrated reported velocity, adapted


@dataclass(slots=True, eq=False)
class _Track:
    t_ns: int
    filters: list[_Filter]  # one per accel noise of the bank, in the estimator's order
    first_ns: int = 0
    recent: collections.deque = field(default_factory=collections.deque)  # (t_ns, x, y, speed, reported vx, reported vy)
    history: collections.deque = field(default_factory=collections.deque)  # (t_ns, x, y, speed of each filter): back test
    ratios: list[float] = field(default_factory=list)
    cosines: list[float] = field(default_factory=list)
    decided: bool = False


@dataclass(frozen=True, slots=True)
class Consistency:
    """Reported vs position-implied velocity over the tracks decided so far."""

    tracks_checked: int
    tracks_inconsistent: int
    median_factor: float
    median_cosine: float

    def as_dict(self) -> dict[str, float | int]:
        return {
            "tracks_checked": self.tracks_checked,
            "tracks_inconsistent": self.tracks_inconsistent,
            "median_factor": self.median_factor,
            "median_cosine": self.median_cosine,
        }


def is_consistent(factor: float, cosine: float, config: EstimatorConfig) -> bool:
    """A track's reported velocity agrees with its positions: factor within the tolerance, cosine >= 0.5."""
    return 1.0 / config.factor_tolerance <= factor <= config.factor_tolerance and cosine >= 0.5


def consistency_of(decided, config: EstimatorConfig) -> Consistency:
    """The summary of (factor, cosine) pairs of decided tracks (one estimator's, or several merged)."""
    decided = list(decided)
    factors = [f for f, _ in decided]
    cosines = [c for _, c in decided]
    return Consistency(
        tracks_checked=len(decided),
        tracks_inconsistent=sum(not is_consistent(f, c, config) for f, c in decided),
        median_factor=float(np.median(factors)) if factors else math.nan,
        median_cosine=float(np.median(cosines)) if cosines else math.nan,
    )


def disagreement_line(c: Consistency, config: EstimatorConfig) -> str | None:
    """One warning line when enough checked tracks disagree with their positions; else None."""
    if c.tracks_inconsistent < config.warn_min_tracks or c.tracks_inconsistent < config.warn_share * c.tracks_checked:
        return None
    return (
        f"reported velocities disagree with the positions: {c.tracks_inconsistent} of {c.tracks_checked} tracks checked, "
        f"median reported/position speed factor {c.median_factor:.2f}, median direction cosine {c.median_cosine:.2f}; "
        "speeds and accelerations come from the positions"
    )


_add_reduce = np.add.reduce


def _sorted_percentile(values: list[float], q: int, *, median: bool = False) -> float:
    """``np.percentile(values, q)`` (method linear) of sorted finite non-zero floats, or with `median` ``np.median``,
    with numpy's arithmetic: the virtual index (n − 1)·q/100, its floor and fraction t, then a + (b − a)·t, or for t >=
    0.5 b − (b − a)·(1 − t); the median the middle value or (a + b) / 2 (of non-zero b, numpy's mean of two)."""
    n = len(values)
    if median:
        half = n // 2
        return values[half] if n % 2 else (values[half - 1] + values[half]) / 2.0
    virtual = (n - 1) * (q / 100)
    if virtual >= n - 1:
        return values[-1]
    lo = math.floor(virtual)
    t = virtual - lo
    a, b = values[lo], values[lo + 1]
    diff = b - a
    return b - diff * (1.0 - t) if t >= 0.5 else a + diff * t


def _median(values: list[float]) -> float:
    """``np.median`` of a few finite floats without an array: the middle value, or the mean of the middle two as
    numpy takes it ((a + b) / 2); NaN if any value is (numpy's answer then)."""
    if any(v != v for v in values):
        return math.nan
    ordered = sorted(values)
    n = len(ordered)
    return ordered[n // 2] if n % 2 else (ordered[n // 2 - 1] + ordered[n // 2]) / 2.0


class Calibration:
    """Reported velocity vs the positions' 1 s chord velocity over the stream's recent moving samples.

    ``factor`` the median of |mean reported velocity| / |chord velocity|,
    ``cosine`` the median cosine between the two; ``trusted`` when there are
    enough samples from enough tracks, the direction is consistently along or
    against the motion (|cosine| >= 0.9) and the factor's interquartile range
    is within ``calibration_max_spread`` of it. A trusted reported velocity is
    used as ``sign(cosine) * reported / factor``.
    """

    def __init__(self, config: EstimatorConfig) -> None:
        self.config = config
        # the window's (factor, cosine) rows in a ring (the medians and quartiles do not depend on the rows' order),
        # and its track ids with a count per id, so that a refresh neither copies the window nor rebuilds a set
        self._values = np.empty((config.calibration_window, 2))
        self._count = 0
        self._next = 0
        self._tracks: collections.deque = collections.deque(maxlen=config.calibration_window)
        self._per_track: dict[int, int] = {}
        # per column (factor, cosine): the window's finite non-zero values kept sorted, and a count of its others (NaN,
        # infinite, ±0.0): where there are none the quantiles are read off the sorted values (`_refresh`)
        self._sorted: tuple[list[float], list[float]] = ([], [])
        self._others = [0, 0]
        self._dirty = 0
        self.factor = math.nan
        self.cosine = math.nan
        self.trusted = False

    def add(self, track_id: int, factor: float, cosine: float) -> None:
        if not len(self._values):  # a window of 0 samples keeps none (and is never trusted)
            return
        if len(self._tracks) == self._tracks.maxlen:  # the oldest sample leaves the window
            leaving = self._tracks[0]
            self._per_track[leaving] -= 1
            if not self._per_track[leaving]:
                del self._per_track[leaving]
        self._tracks.append(track_id)
        self._per_track[track_id] = self._per_track.get(track_id, 0) + 1
        full = self._count == len(self._values)
        for column, value in enumerate((factor, cosine)):
            value = float(np.float64(value))  # as the window holds it
            if full:  # the slot's old value leaves the window
                self._forget(column, float(self._values[self._next, column]))
            if math.isfinite(value) and value != 0.0:
                bisect.insort(self._sorted[column], value)
            else:
                self._others[column] += 1
            self._values[self._next, column] = value
        self._next = (self._next + 1) % len(self._values)
        self._count = min(self._count + 1, len(self._values))
        self._dirty += 1
        if self._dirty >= 10 or not self.trusted:
            self._refresh()

    def _forget(self, column: int, value: float) -> None:
        if math.isfinite(value) and value != 0.0:
            values = self._sorted[column]
            del values[bisect.bisect_left(values, value)]  # an equal finite non-zero float: the same bits
        else:
            self._others[column] -= 1

    def _refresh(self) -> None:
        cfg = self.config
        self._dirty = 0
        if self._count < cfg.calibration_min_samples or len(self._per_track) < cfg.calibration_min_tracks:
            return
        arr = self._values[: self._count]
        if self._others[0]:  # NaN, inf or a signed zero among them: numpy decides
            q1, med, q3 = np.percentile(arr[:, 0], [25, 50, 75])
        else:
            q1, med, q3 = (_sorted_percentile(self._sorted[0], q) for q in (25, 50, 75))
        self.factor = float(med)
        self.cosine = float(np.median(arr[:, 1])) if self._others[1] else _sorted_percentile(self._sorted[1], 50, median=True)
        self.trusted = bool(0.2 <= med <= 5.0 and abs(self.cosine) >= 0.9 and (q3 - q1) <= cfg.calibration_max_spread * med)

    def apply(self, vx: float, vy: float) -> tuple[float, float] | None:
        """The calibrated reported velocity, or None when it is not trusted or not finite."""
        if not self.trusted or not (math.isfinite(vx) and math.isfinite(vy)):
            return None
        k = math.copysign(1.0, self.cosine) / self.factor
        return vx * k, vy * k


def _predict(kf: _Filter, q: float, dt: float) -> tuple[float, float, float, float, float]:
    """The filter's prediction over ``dt``: covariance (p00, p01, p11) and position (x, y)."""
    p00, p01, p11 = kf.p
    # F = [[1, dt], [0, 1]], Q = q [[dt³/3, dt²/2], [dt²/2, dt]]
    p00 = p00 + 2.0 * dt * p01 + dt * dt * p11 + q * dt**3 / 3.0
    p01 = p01 + dt * p11 + q * dt * dt / 2.0
    p11 = p11 + q * dt
    return p00, p01, p11, kf.x[0] + dt * kf.x[1], kf.y[0] + dt * kf.y[1]


def _correct(kf: _Filter, predicted: tuple[float, float, float, float, float], zx: float, zy: float, cfg: EstimatorConfig) -> None:
    """Update the filter with the position (zx, zy), adapting its measurement noise to the innovations it shows."""
    p00, p01, p11, px, py = predicted
    ix, iy = zx - px, zy - py
    innovation2 = 0.5 * (ix * ix + iy * iy)
    a = cfg.noise_adaptation
    kf.r = (1.0 - a) * kf.r + a * max(innovation2 - p00, cfg.min_position_noise_m**2)
    s = p00 + kf.r
    k0, k1 = p00 / s, p01 / s
    kf.x = [px + k0 * ix, kf.x[1] + k1 * ix]
    kf.y = [py + k0 * iy, kf.y[1] + k1 * iy]
    kf.p = [(1.0 - k0) * p00, (1.0 - k0) * p01, p11 - k1 * p01]


class KinematicEstimator:
    """Causal per-track state for one stream of frames (module docstring)."""

    def __init__(self, config: EstimatorConfig | None = None) -> None:
        self.config = config or EstimatorConfig()
        self._tracks: dict[int, _Track] = {}
        # the last DECIDED_WINDOW decided tracks' (factor, cosine): a live stream decides tracks for days, and the
        # warning is judged on them (at every newly decided track, not every frame)
        self._factors: collections.deque[float] = collections.deque(maxlen=DECIDED_WINDOW)
        self._cosines: collections.deque[float] = collections.deque(maxlen=DECIDED_WINDOW)
        self._decided_total = 0
        self._judged_at = 0
        self._warned = False
        self.calibration = Calibration(self.config)
        self._rv_stream = self.config.initial_velocity_noise_mps**2
        self.velocity_rejected = 0
        self._bank = self.config.filter_bank
        self.selected = self._bank.index(float(self.config.accel_noise_m2ps3))
        self._bt_mean = [0.0] * len(self._bank)  # exponentially weighted mean squared back-test error per filter
        self.backtest_samples = 0
        self.switches = 0

    @property
    def accel_noise(self) -> float:
        """The accel noise (m²/s³) of the filter whose state is published now."""
        return self._bank[self.selected]

    def backtest(self) -> dict[str, object]:
        """The bank's back test so far: per accel noise the rms error (m) of speed x horizon vs the distance covered."""
        return {
            "accel_noise_m2ps3": self.accel_noise,
            "samples": self.backtest_samples,
            "switches": self.switches,
            "rms_m": {f"{q:g}": (math.sqrt(m) if self.backtest_samples else math.nan) for q, m in zip(self._bank, self._bt_mean)},
        }

    def reset(self) -> None:
        """Forget every track and the consistency figures (a new scene)."""
        self.__init__(self.config)

    def forget(self, track_id: int) -> None:
        self._tracks.pop(int(track_id), None)

    def started_ns(self, track_id: int) -> int | None:
        """The stamp of the sample the track's state (re)started at (a new track, a jump, a gap), None for a track it
        does not hold."""
        track = self._tracks.get(int(track_id))
        return None if track is None else track.first_ns

    def update(
        self, track_id: int, stamp_ns: int, x_m: float, y_m: float, vx_mps: float, vy_mps: float, issues: list[Issue]
    ) -> KinematicState:
        """The state of ``track_id`` after its sample at ``stamp_ns`` (positions must be finite)."""
        cfg = self.config
        reported = math.hypot(vx_mps, vy_mps) if math.isfinite(vx_mps) and math.isfinite(vy_mps) else math.nan
        calibrated = self.calibration.apply(vx_mps, vy_mps) if cfg.fuse_reported else None
        track = self._tracks.get(track_id)
        if track is not None:
            dt = (stamp_ns - track.t_ns) * _NS
            if dt <= 0.0:
                return self._state(track, reported, "positions")  # the same stamp again: nothing new
            if dt > cfg.max_gap_s:
                issues.append(Issue("track_restarted", track_id, f"{dt:.1f} s since its last sample: state restarted"))
                track = None
        if track is None:
            return self._start(track_id, stamp_ns, x_m, y_m, vx_mps, vy_mps, reported, calibrated)
        if not self._step(track, dt, x_m, y_m):
            kf = track.filters[self.selected]
            issues.append(Issue("position_jump", track_id, f"position {math.hypot(x_m - kf.x[0], y_m - kf.y[0]):.1f} m off its prediction: state restarted"))
            return self._start(track_id, stamp_ns, x_m, y_m, vx_mps, vy_mps, reported, calibrated)
        fused = False
        # a reported zero is no evidence (trackers report it at a track's birth and on dropouts):
        # whether a car stands is for its positions to say
        if calibrated is not None and reported >= _ZERO_MPS:
            fused = self._fuse(track, calibrated)
            if not fused:
                kf = track.filters[self.selected]
                issues.append(Issue(
                    "velocity_rejected", track_id,
                    f"reported velocity ({calibrated[0]:.1f}, {calibrated[1]:.1f}) m/s calibrated is off the positions' "
                    f"({kf.x[1]:.1f}, {kf.y[1]:.1f}): not used",
                ))
        track.t_ns = stamp_ns
        if len(self._bank) > 1:
            self._backtest(track, x_m, y_m)
        state = self._state(track, reported, "fused" if fused else "positions", (x_m, y_m, vx_mps, vy_mps))
        if reported < _ZERO_MPS and state.speed_mps >= cfg.consistency_min_speed_mps:
            issues.append(Issue("velocity_zero_while_moving", track_id, f"reported speed {reported:.2f} m/s, positions say {state.speed_mps:.1f} m/s: ignored"))
        self._check(track_id, track, state, reported, issues)
        return state

    # ----- filter ----------------------------------------------------------------

    def _start(self, track_id, stamp_ns, x, y, vx, vy, reported, calibrated) -> KinematicState:
        cfg = self.config
        r = cfg.initial_position_noise_m**2
        filters = [_Filter(x=[x, 0.0], y=[y, 0.0], p=[r, 0.0, cfg.initial_speed_sigma_mps**2], r=r, rv=self._rv_stream) for _ in self._bank]
        track = _Track(t_ns=stamp_ns, filters=filters, first_ns=stamp_ns)
        track.recent.append((stamp_ns, x, y, math.nan, vx, vy))
        self._tracks[track_id] = track
        # the filter starts from the position alone: a first reported velocity (zero at a track's birth,
        # say) is never fed in without the positions to gate it; it is only this sample's answer
        if not (reported >= _ZERO_MPS):
            # a reported zero (or nothing) at a track's birth says nothing: the speed waits for the second position
            return KinematicState(math.nan, math.nan, math.nan, math.nan, False, "unknown", reported)
        if calibrated is not None:
            return KinematicState(calibrated[0], calibrated[1], math.hypot(*calibrated), 0.0, False, "reported", reported)
        return KinematicState(vx, vy, reported, 0.0, False, "reported", reported)

    def _step(self, track: _Track, dt: float, zx: float, zy: float) -> bool:
        """Predict every filter over ``dt`` and update it with the position (zx, zy); False when the published filter
        sees the sample as a jump (track untouched)."""
        cfg = self.config
        predicted = [_predict(kf, q, dt) for kf, q in zip(track.filters, self._bank)]
        p00, _, _, px, py = predicted[self.selected]
        kf = track.filters[self.selected]
        ix, iy = zx - px, zy - py
        innovation2 = 0.5 * (ix * ix + iy * iy)
        if math.sqrt(2.0 * innovation2) > cfg.jump_m and innovation2 > 25.0 * (p00 + kf.r):
            return False
        for kf, pred in zip(track.filters, predicted):
            _correct(kf, pred, zx, zy, cfg)
        return True

    def _fuse(self, track: _Track, velocity: tuple[float, float]) -> bool:
        """Update every filter with the calibrated reported velocity, gated; False when the published filter rejects it."""
        cfg = self.config
        out = False
        for k, kf in enumerate(track.filters):
            p00, p01, p11 = kf.p
            ix, iy = velocity[0] - kf.x[1], velocity[1] - kf.y[1]
            innovation2 = 0.5 * (ix * ix + iy * iy)
            gate = cfg.velocity_gate_sigma**2 * (p11 + kf.rv) + 1.0
            if innovation2 > gate:
                if k == self.selected:
                    self.velocity_rejected += 1
                continue
            a = cfg.velocity_noise_adaptation
            kf.rv = (1.0 - a) * kf.rv + a * max(innovation2 - p11, cfg.min_velocity_noise_mps**2)
            if k == self.selected:
                self._rv_stream = (1.0 - 0.25 * a) * self._rv_stream + 0.25 * a * kf.rv
                out = True
            s = p11 + kf.rv
            k0, k1 = p01 / s, p11 / s
            kf.x = [kf.x[0] + k0 * ix, kf.x[1] + k1 * ix]
            kf.y = [kf.y[0] + k0 * iy, kf.y[1] + k1 * iy]
            kf.p = [p00 - k0 * p01, p01 - k0 * p11, (1.0 - k1) * p11]
        return out

    def _backtest(self, track: _Track, x: float, y: float) -> None:
        """Score each filter's speed of ``bank_horizon_s`` ago against the distance the track has covered since, and
        publish the filter with the lowest error over the stream (causal: only past samples are judged)."""
        cfg = self.config
        history = track.history
        history.append((track.t_ns, x, y, [math.hypot(kf.x[1], kf.y[1]) for kf in track.filters]))
        horizon_ns = round(cfg.bank_horizon_s / _NS)
        a = 1.0 / cfg.bank_memory
        scored = False
        while history and track.t_ns - history[0][0] >= horizon_ns:
            t0, x0, y0, speeds = history.popleft()
            if (t0 - track.first_ns) * _NS < 1.0:
                continue  # a track's first second: every filter is still settling
            dt = (track.t_ns - t0) * _NS
            covered = math.hypot(x - x0, y - y0)
            self.backtest_samples += 1
            w = max(a, 1.0 / self.backtest_samples)  # a plain mean until the memory is full
            means = self._bt_mean
            for k, v in enumerate(speeds):
                e = v * dt - covered
                means[k] += w * (e * e - means[k])
            scored = True
        if scored and self.backtest_samples >= cfg.bank_min_samples:
            best = min(range(len(self._bank)), key=self._bt_mean.__getitem__)
            if best != self.selected and self._bt_mean[best] < (1.0 - cfg.bank_switch_gain) * self._bt_mean[self.selected]:
                self.selected = best
                self.switches += 1

    def _state(self, track: _Track, reported: float, source: str, sample: tuple | None = None) -> KinematicState:
        cfg = self.config
        kf = track.filters[self.selected]
        vx, vy = kf.x[1], kf.y[1]
        speed = math.hypot(vx, vy)
        recent = track.recent
        if sample is not None:
            recent.append((track.t_ns, sample[0], sample[1], speed, sample[2], sample[3]))
            keep_ns = round(max(cfg.standstill_window_s, cfg.accel_window_s, 1.0) / _NS)
            while recent and track.t_ns - recent[0][0] > keep_ns:
                recent.popleft()
        if self._standing(track):
            return KinematicState(0.0, 0.0, 0.0, 0.0, True, source, reported)
        return KinematicState(vx, vy, speed, self._accel(track), False, source, reported)

    def _standing(self, track: _Track) -> bool:
        """The median position of the older half of the window is within the radius of the newer half's."""
        cfg = self.config
        t_now = track.recent[-1][0]
        span_ns = round(cfg.standstill_window_s / _NS)
        window = [(t, x, y) for t, x, y, *_ in track.recent if t_now - t <= span_ns]
        if len(window) < 4 or t_now - window[0][0] < span_ns:
            return False
        # a car the filter sees move, sustained over the last 0.3 s, is released at once
        newest = [v for t, _, _, v, *_ in track.recent if t_now - t <= 300_000_000 and math.isfinite(v)]
        if newest and sum(newest) / len(newest) >= cfg.standstill_max_speed_mps:
            return False
        half = len(window) // 2
        old_x, old_y = _median([x for _, x, _ in window[:half]]), _median([y for _, _, y in window[:half]])
        new_x, new_y = _median([x for _, x, _ in window[half:]]), _median([y for _, _, y in window[half:]])
        return float(np.hypot(new_x - old_x, new_y - old_y)) < cfg.standstill_radius_m

    def _accel(self, track: _Track) -> float:
        window_ns = round(self.config.accel_window_s / _NS)
        t_now = track.t_ns
        pts = [(t, v) for t, _, _, v, *_ in track.recent if t_now - t <= window_ns and math.isfinite(v)]
        if len(pts) < 3:
            return 0.0
        n = len(pts)
        # times from the newest sample, taken in integer ns first: a live tracker's stamps (wall clock, ~1.8e18 ns) lose
        # their last 8 bits as float64, and the fit would depend on when the clock started
        t = np.array([p[0] - t_now for p in pts], dtype=np.float64) * _NS
        v = np.array([p[1] for p in pts])
        # x.mean() is add.reduce(x) / n (numpy's float64 mean: the pairwise sum, then one division), without its overhead
        t -= _add_reduce(t) / n
        denom = float(np.dot(t, t))
        return float(np.dot(t, v - _add_reduce(v) / n) / denom) if denom > 0 else 0.0

    # ----- reported velocity as evidence ------------------------------------------

    def _chord(self, track: _Track) -> tuple[float, float, float, float] | None:
        """(chord vx, vy over the last 1 s of positions, mean reported vx, vy over the same samples), or None."""
        t_now, x_now, y_now = track.recent[-1][:3]
        first = None
        for item in track.recent:
            if t_now - item[0] <= 1_000_000_000:
                first = item
                break
        if first is None or t_now - first[0] < 900_000_000:
            return None
        dt = (t_now - first[0]) * _NS
        reps = [(vx, vy) for t, _, _, _, vx, vy in track.recent if t >= first[0]]
        if not all(math.isfinite(vx) and math.isfinite(vy) for vx, vy in reps):
            return None
        if any(math.hypot(vx, vy) < _ZERO_MPS for vx, vy in reps):
            # a zero while the chord moves is the birth transient the gate rejects, not the tracker's scale
            return None
        mvx = sum(v[0] for v in reps) / len(reps)
        mvy = sum(v[1] for v in reps) / len(reps)
        return (x_now - first[1]) / dt, (y_now - first[2]) / dt, mvx, mvy

    def _check(self, track_id: int, track: _Track, state: KinematicState, reported: float, issues: list[Issue]) -> None:
        """Reported vs positions over the last second: feeds the calibration and decides the track once."""
        cfg = self.config
        if state.standing or not math.isfinite(reported) or (track.t_ns - track.first_ns) * _NS < 1.0:
            return
        chord = self._chord(track)
        if chord is None:
            return
        cvx, cvy, rvx, rvy = chord
        chord_speed, rep_speed = math.hypot(cvx, cvy), math.hypot(rvx, rvy)
        if chord_speed < cfg.consistency_min_speed_mps:
            return
        factor = rep_speed / chord_speed
        cosine = (cvx * rvx + cvy * rvy) / (chord_speed * max(rep_speed, 1e-9))
        self.calibration.add(track_id, factor, cosine)
        if track.decided:
            return
        track.ratios.append(factor)
        track.cosines.append(cosine)
        if len(track.ratios) < cfg.consistency_min_samples:
            return
        track.decided = True
        factor = float(np.median(track.ratios))
        cosine = float(np.median(track.cosines))
        self._factors.append(factor)
        self._cosines.append(cosine)
        self._decided_total += 1
        if not is_consistent(factor, cosine, cfg):
            issues.append(
                Issue("velocity_inconsistent", track_id, f"reported speed is {factor:.2f} x the position-implied speed, direction cosine {cosine:.2f}")
            )

    @property
    def decided(self) -> tuple[tuple[float, float], ...]:
        """(factor, cosine) of the tracks decided so far (the last ``DECIDED_WINDOW``), in the order decided."""
        return tuple(zip(self._factors, self._cosines))

    def consistency(self) -> Consistency:
        """Reported vs position-implied velocity over the tracks decided so far (the last ``DECIDED_WINDOW``)."""
        return consistency_of(self.decided, self.config)

    def warning(self) -> str | None:
        """One line, returned once, when enough checked tracks disagree with their positions; else None. Judged
        again only when a track has been decided since (a stage asks every frame)."""
        if self._warned or self._judged_at == self._decided_total:
            return None
        self._judged_at = self._decided_total
        line = disagreement_line(self.consistency(), self.config)
        self._warned = line is not None
        return line
