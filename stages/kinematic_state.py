"""Kinematic state of every track from its positions, causally: ``KinematicEstimator``.

Why: a tracker's reported velocities are one tracker's convention. Seen so far:
scaled (a TAF-BW recording whose ``vx, vy`` are about half the speed its
positions imply), zero for the first frames of a track while the car already
moves at 10-19 m/s, pointing backwards (k733_2018-05-02), lagging. Positions
are the one field every tracker gets right to within its noise, so every
stage takes speed, velocity and acceleration from this estimator, and the
reported velocity is only evidence that is checked (``velocity_inconsistent``).

Per track, a constant-velocity Kalman filter on x and y (white-noise
acceleration of spectral density ``accel_noise_m2ps3``) whose measurement
noise is estimated online from its own innovations (an exponentially weighted
mean of the squared innovation less the predicted position variance, floored
at ``min_position_noise_m``²). That one adaptive filter follows K729's clean
positions closely and smooths K733's sample-and-hold positions (the tracker
repeats a position for several frames, then jumps) without a per-recording
setting. Chosen by the constant-speed displacement error at 1-4 s on both
development locations (``bench/state_estimator.py``): a fixed linear fit over
the last 0.6 s was best on K733 and 35 % worse than the reported speed on
K729; a quadratic fit the reverse; the adaptive filter is within 6 % of the
best of the candidates on each location (the figures are in README.md).

- The first sample of a track gives position only: its speed is the reported
  one if finite (``source = "reported"``), else unknown (NaN). From the
  second sample on the state is the filter's (``source = "positions"``).
- Standstill dead band: a track stands (speed 0, acceleration 0) when, over
  the last ``standstill_window_s``, the median position of the newer half of
  its samples lies within ``standstill_radius_m`` of the older half's (a car
  below about 0.5 m/s): position jitter, and the single glitches of K733's
  tracker, never become a creeping speed.
- Acceleration: the slope of a least-squares line through the filtered speed
  over the last ``accel_window_s`` (0 when standing or with too few samples).
- A position more than ``jump_m`` off the filter's prediction (and more than
  five of its standard deviations) restarts the track at the new position
  (issue ``position_jump``); so does a gap longer than ``max_gap_s`` between
  two samples (a re-used track id, issue ``track_restarted``).
- Consistency: once a track has ``consistency_min_samples`` samples where the
  estimated speed is at least ``consistency_min_speed_mps`` (after its first
  second), the median of reported / estimated speed and the median cosine
  between the two velocity vectors decide it: a factor outside
  ``[1 / factor_tolerance, factor_tolerance]`` or a cosine below 0.5 is one
  ``velocity_inconsistent`` issue for that track (once per track). The
  per-stream summary (``consistency()``) counts the tracks checked and
  inconsistent, with the median factor and cosine, and ``warning()`` returns
  one line once, when enough tracks disagree.

Pure: numpy and the standard library; time comes from the frames' stamps.
"""

from __future__ import annotations

import collections
import math
from dataclasses import dataclass, field

import numpy as np

from stages._core import ConfigMixin, Issue, check_ranges

_NS = 1e-9


@dataclass(frozen=True, kw_only=True)
class EstimatorConfig(ConfigMixin):
    """Parameters of ``KinematicEstimator`` (module docstring)."""

    accel_noise_m2ps3: float = 10.0
    initial_position_noise_m: float = 0.1
    min_position_noise_m: float = 0.02
    noise_adaptation: float = 0.05
    initial_speed_sigma_mps: float = 10.0
    standstill_radius_m: float = 0.25
    standstill_window_s: float = 1.0
    accel_window_s: float = 1.0
    jump_m: float = 5.0
    max_gap_s: float = 1.0
    consistency_min_speed_mps: float = 2.0
    consistency_min_samples: int = 10
    factor_tolerance: float = 1.25
    warn_min_tracks: int = 3
    warn_share: float = 0.3

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
class _Track:
    t_ns: int
    x: list[float]  # [position, velocity] along x
    y: list[float]
    p: list[float]  # shared covariance [p00, p01, p11] (same H and dt for both axes)
    r: float  # measurement noise variance, adapted
    n: int = 1
    first_ns: int = 0
    recent: collections.deque = field(default_factory=collections.deque)  # (t_ns, x, y, speed)
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


class KinematicEstimator:
    """Causal per-track state from positions for one stream of frames (module docstring)."""

    def __init__(self, config: EstimatorConfig | None = None) -> None:
        self.config = config or EstimatorConfig()
        self._tracks: dict[int, _Track] = {}
        self._factors: list[float] = []
        self._cosines: list[float] = []
        self._warned = False

    def reset(self) -> None:
        """Forget every track and the consistency figures (a new scene)."""
        self.__init__(self.config)

    def forget(self, track_id: int) -> None:
        self._tracks.pop(int(track_id), None)

    def update(
        self, track_id: int, stamp_ns: int, x_m: float, y_m: float, vx_mps: float, vy_mps: float, issues: list[Issue]
    ) -> KinematicState:
        """The state of ``track_id`` after its sample at ``stamp_ns`` (positions must be finite)."""
        cfg = self.config
        reported = math.hypot(vx_mps, vy_mps) if math.isfinite(vx_mps) and math.isfinite(vy_mps) else math.nan
        track = self._tracks.get(track_id)
        if track is not None:
            dt = (stamp_ns - track.t_ns) * _NS
            if dt <= 0.0:
                return self._state(track, reported)  # the same stamp again: nothing new
            if dt > cfg.max_gap_s:
                issues.append(Issue("track_restarted", track_id, f"{dt:.1f} s since its last sample: state restarted"))
                track = None
        if track is None:
            return self._start(track_id, stamp_ns, x_m, y_m, vx_mps, vy_mps, reported)
        if not self._step(track, dt, x_m, y_m):
            issues.append(Issue("position_jump", track_id, f"position {math.hypot(x_m - track.x[0], y_m - track.y[0]):.1f} m off its prediction: state restarted"))
            return self._start(track_id, stamp_ns, x_m, y_m, vx_mps, vy_mps, reported)
        track.t_ns = stamp_ns
        track.n += 1
        state = self._state(track, reported, x_m, y_m)
        self._check(track_id, track, state, vx_mps, vy_mps, reported, issues)
        return state

    # ----- filter ----------------------------------------------------------------

    def _start(self, track_id: int, stamp_ns: int, x: float, y: float, vx: float, vy: float, reported: float) -> KinematicState:
        cfg = self.config
        r = cfg.initial_position_noise_m**2
        track = _Track(t_ns=stamp_ns, x=[x, 0.0], y=[y, 0.0], p=[r, 0.0, cfg.initial_speed_sigma_mps**2], r=r, first_ns=stamp_ns)
        track.recent.append((stamp_ns, x, y, math.nan))
        self._tracks[track_id] = track
        if math.isfinite(reported):
            return KinematicState(vx, vy, reported, 0.0, False, "reported", reported)
        return KinematicState(math.nan, math.nan, math.nan, math.nan, False, "unknown", reported)

    def _step(self, track: _Track, dt: float, zx: float, zy: float) -> bool:
        """Predict over ``dt`` and update with (zx, zy); False when the sample is a jump (track untouched)."""
        cfg = self.config
        q = cfg.accel_noise_m2ps3
        p00, p01, p11 = track.p
        # predict: F = [[1, dt], [0, 1]], Q = q [[dt³/3, dt²/2], [dt²/2, dt]]
        p00 = p00 + 2.0 * dt * p01 + dt * dt * p11 + q * dt**3 / 3.0
        p01 = p01 + dt * p11 + q * dt * dt / 2.0
        p11 = p11 + q * dt
        px = track.x[0] + dt * track.x[1]
        py = track.y[0] + dt * track.y[1]
        ix, iy = zx - px, zy - py
        innovation2 = 0.5 * (ix * ix + iy * iy)
        s = p00 + track.r
        if math.sqrt(2.0 * innovation2) > cfg.jump_m and innovation2 > 25.0 * s:
            return False
        # adapt the measurement noise to the innovations this track shows
        a = cfg.noise_adaptation
        r_obs = max(innovation2 - p00, cfg.min_position_noise_m**2)
        track.r = (1.0 - a) * track.r + a * r_obs
        s = p00 + track.r
        k0, k1 = p00 / s, p01 / s
        track.x = [px + k0 * ix, track.x[1] + k1 * ix]
        track.y = [py + k0 * iy, track.y[1] + k1 * iy]
        track.p = [(1.0 - k0) * p00, (1.0 - k0) * p01, p11 - k1 * p01]
        return True

    def _state(self, track: _Track, reported: float, x: float | None = None, y: float | None = None) -> KinematicState:
        cfg = self.config
        vx, vy = track.x[1], track.y[1]
        speed = math.hypot(vx, vy)
        recent = track.recent
        if x is not None:
            recent.append((track.t_ns, x, y, speed))
            keep_ns = round(max(cfg.standstill_window_s, cfg.accel_window_s) / _NS)
            while recent and track.t_ns - recent[0][0] > keep_ns:
                recent.popleft()
        standing = self._standing(track)
        if standing:
            return KinematicState(0.0, 0.0, 0.0, 0.0, True, "positions", reported)
        return KinematicState(vx, vy, speed, self._accel(track), False, "positions", reported)

    def _standing(self, track: _Track) -> bool:
        """The median position of the older half of the window is within the radius of the newer half's."""
        cfg = self.config
        t_now = track.recent[-1][0]
        span_ns = round(cfg.standstill_window_s / _NS)
        window = [(t, x, y) for t, x, y, _ in track.recent if t_now - t <= span_ns]
        if len(window) < 4 or t_now - window[0][0] < span_ns:
            return False
        half = len(window) // 2
        old = np.median(np.array([(x, y) for _, x, y in window[:half]]), axis=0)
        new = np.median(np.array([(x, y) for _, x, y in window[half:]]), axis=0)
        return float(np.hypot(*(new - old))) < cfg.standstill_radius_m

    def _accel(self, track: _Track) -> float:
        window_ns = round(self.config.accel_window_s / _NS)
        t_now = track.t_ns
        pts = [(t, v) for t, _, _, v in track.recent if t_now - t <= window_ns and math.isfinite(v)]
        if len(pts) < 3:
            return 0.0
        t = np.array([p[0] for p in pts], dtype=np.float64) * _NS
        v = np.array([p[1] for p in pts])
        t -= t.mean()
        denom = float(np.dot(t, t))
        return float(np.dot(t, v - v.mean()) / denom) if denom > 0 else 0.0

    # ----- reported velocity as evidence ------------------------------------------

    def _check(self, track_id: int, track: _Track, state: KinematicState, vx: float, vy: float, reported: float, issues: list[Issue]) -> None:
        cfg = self.config
        if track.decided or state.standing or not math.isfinite(reported):
            return
        if state.speed_mps < cfg.consistency_min_speed_mps or (track.t_ns - track.first_ns) * _NS < 1.0:
            return
        track.ratios.append(reported / state.speed_mps)
        track.cosines.append((vx * state.vx_mps + vy * state.vy_mps) / (max(reported, 1e-9) * state.speed_mps))
        if len(track.ratios) < cfg.consistency_min_samples:
            return
        track.decided = True
        factor = float(np.median(track.ratios))
        cosine = float(np.median(track.cosines))
        self._factors.append(factor)
        self._cosines.append(cosine)
        if not is_consistent(factor, cosine, cfg):
            issues.append(
                Issue("velocity_inconsistent", track_id, f"reported speed is {factor:.2f} x the position-implied speed, direction cosine {cosine:.2f}")
            )

    @property
    def decided(self) -> tuple[tuple[float, float], ...]:
        """(factor, cosine) of every track decided so far, in the order decided."""
        return tuple(zip(self._factors, self._cosines))

    def consistency(self) -> Consistency:
        """Reported vs position-implied velocity over the tracks decided so far."""
        return consistency_of(self.decided, self.config)

    def warning(self) -> str | None:
        """One line, returned once, when enough checked tracks disagree with their positions; else None."""
        if self._warned:
            return None
        line = disagreement_line(self.consistency(), self.config)
        self._warned = line is not None
        return line
