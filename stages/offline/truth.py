"""Ground truth of the offline tools: what the cars really did (``iamp eval``, ``iamp train``, the intentions evaluation).

One module for the three of them, so that the AR model is trained and
scored against the same truth:

- ``ground_truth(seq)``: per vehicle track of a sequence its stamps,
  positions, reported speed and the smoothed longitudinal acceleration (the
  AR training targets, ``smoothed_acceleration``);
- ``future_positions`` / ``future_accelerations``: the true positions
  (``positions_at``: a row at the time, or the line between the rows around
  it when they are at most 250 ms apart: jitter, one missing frame) and
  accelerations (the row within ``STAMP_TOL_NS``, 20 ms) at t + k·step, k = 1..K: all K or None, or the
  longest run from k = 1 (``future_run``); ``positions_after``: every
  position in (t, t + seconds];
- ``followed_corridor``: the corridor a car followed, by ONE rule: the
  corridor whose centreline holds the future positions best, i.e. with the
  smallest maximum lateral distance |d| over the positions whose projection
  falls within the corridor (its s range, which includes the corridor's own
  straight extension; positions before its start or beyond its end do not
  count). A corridor holding fewer than ``min_inside`` of the positions
  (default 1; ``iamp train`` asks for the 40 of the 4 s future out of its
  10 s) is not followed (distance inf). ``route_decision`` applies the two
  thresholds:
  above ``max_error_m`` the car followed none of them, and a runner-up
  within ``tie_m`` means the future cannot tell the routes apart;
- ``route_credit`` / ``route_top1``: whether the followed corridor got the
  highest score; a k-way tie for the highest score counts 1/k (the
  expectation of breaking the tie at random, without the randomness);
- ``manoeuvre_class``: what the true future of a window does (stands,
  turns, brakes, accelerates, keeps_speed), from positions only;
  ``along_track_directions``: the unit tangent of the true path at each
  future step, the along/cross-track split of ``iamp eval``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Iterable, NamedTuple, Sequence

import numpy as np
from scipy.signal import savgol_filter

from bus_schemas import AgentType
from stages.lib.maps import project_to_polyline

#: the followed corridor holds the future within this lateral distance (m) ...
ROUTE_MAX_ERROR_M = 2.0
#: ... and the runner-up is at least this much worse (m), else the future does not tell the routes apart.
ROUTE_TIE_M = 0.5
#: Savitzky-Golay window and cut track ends of the true acceleration (s), the AR training targets' definition.
ACCEL_WINDOW_S = 1.5
ACCEL_EDGE_S = 1.5
#: two scores within this are tied for the highest.
SCORE_TIE = 1e-9
_NS = 1e-9
_MS_NS = 1_000_000
# How far a row's stamp may be from the time it stands for: a tracker's stamps jitter by a few ms (a recording's
# stamps at exactly k·100 ms are the exception), and 20 ms is below half the period of 25 Hz data, so the nearest row
# within it is the one meant. Was 1 ms: a jitter of ±5 ms left nothing to score or train on.
STAMP_TOL_NS = 20_000_000
# Two rows at most this far apart are interpolated between (jitter, or one frame missing at 10 Hz: a tracker's
# dropout, which cost the whole 4 s window of every instant before it); further apart, the time is not known.
_INTERP_MAX_GAP_NS = 250_000_000


# --------------------------------------------------------------------------- tracks


@dataclass(frozen=True, slots=True, eq=False)
class Track:
    """One vehicle track of a sequence: stamps (n,) int64 sorted, positions (n, 2), reported speed (n,), acceleration (n,).

    ``accel_mps2`` is ``smoothed_acceleration`` of the positions (NaN where unknown).
    """

    stamps_ns: np.ndarray
    xy: np.ndarray
    speed_mps: np.ndarray
    accel_mps2: np.ndarray


def smoothed_acceleration(stamps_ns: np.ndarray, xy: np.ndarray, period_ns: int, window_samples: int, edge_samples: int | None = None) -> np.ndarray:
    """(n,) longitudinal acceleration of one track from its positions, non-causal; NaN where unknown.

    The track is cut where consecutive stamps are not one period apart; a
    piece shorter than the window gets NaN, and so do the first and last
    `edge_samples` (default window // 2, where the window would not be
    centred) of each piece. Velocity: the Savitzky-Golay derivative (degree
    2) of x and y; acceleration: that of the speed (``stages.offline.train.dataset``
    explains the choice).
    """
    n = stamps_ns.shape[0]
    out = np.full(n, np.nan)
    w = int(window_samples) | 1
    dt = period_ns * _NS
    cuts = np.flatnonzero(np.abs(np.diff(stamps_ns) - period_ns) > min(STAMP_TOL_NS, period_ns // 4)) + 1
    for a, b in zip(np.concatenate([[0], cuts]), np.concatenate([cuts, [n]])):
        if b - a < w:
            continue
        vx = savgol_filter(xy[a:b, 0], w, 2, deriv=1, delta=dt)
        vy = savgol_filter(xy[a:b, 1], w, 2, deriv=1, delta=dt)
        accel = savgol_filter(np.hypot(vx, vy), w, 2, deriv=1, delta=dt)
        edge = w // 2 if edge_samples is None else max(int(edge_samples), 0)
        if b - a > 2 * edge:
            out[a + edge : b - edge] = accel[edge : len(accel) - edge]
    return out


def ground_truth(seq, *, accel_window_s: float = ACCEL_WINDOW_S, accel_edge_s: float = ACCEL_EDGE_S) -> dict[int, Track]:
    """Per vehicle track (``AgentType.is_vehicle``) of a sequence (``stages.lib.datasets.Sequence``): its ``Track``."""
    out = {}
    period = seq.period_ns
    window = max(int(round(accel_window_s * 1e9 / period)), 3) | 1
    edge = int(round(accel_edge_s * 1e9 / period))
    order = np.lexsort((seq.stamp_ns, seq.track_id))
    ids = seq.track_id[order]
    bounds = np.flatnonzero(np.diff(ids)) + 1
    for a, b in zip(np.concatenate([[0], bounds]), np.concatenate([bounds, [len(ids)]])):
        if b <= a:
            continue
        rows = order[a:b]
        if not AgentType(int(seq.agent_type[rows[0]])).is_vehicle:
            continue
        stamps = seq.stamp_ns[rows]
        xy = np.column_stack([seq.x_m[rows], seq.y_m[rows]])
        speed = np.hypot(seq.vx_mps[rows], seq.vy_mps[rows])
        out[int(ids[a])] = Track(stamps, xy, speed, smoothed_acceleration(stamps, xy, period, window, edge))
    return out


def rows_near(stamps_ns: np.ndarray, want_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Row indices of the stamps (sorted) nearest each wanted time (a tie: the later), and whether each is within
    ``STAMP_TOL_NS``."""
    n = stamps_ns.shape[0]
    j = np.searchsorted(stamps_ns, want_ns)
    lo, hi = np.clip(j - 1, 0, n - 1), np.minimum(j, n - 1)
    i = np.where(np.abs(stamps_ns[hi] - want_ns) <= np.abs(stamps_ns[lo] - want_ns), hi, lo)
    return i, np.abs(stamps_ns[i] - want_ns) <= STAMP_TOL_NS


def _future_rows(track: Track, stamp_ns: int, step_ns: int, n_steps: int) -> tuple[np.ndarray, np.ndarray]:
    """Row indices (n_steps,) of the stamps nearest t + k·step, and whether each is within ``STAMP_TOL_NS``."""
    return rows_near(track.stamps_ns, stamp_ns + int(step_ns) * np.arange(1, n_steps + 1))


def positions_at(track: Track, want_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Positions (k, 2) of the track at the wanted times, and whether each is known: a row whose stamp is the time
    gives its own position; a time between two rows at most ``_INTERP_MAX_GAP_NS`` apart (jittered stamps, or one
    missing frame at 10 Hz) the line between them; else the row within ``STAMP_TOL_NS`` as it is. A time the track
    holds none of these for (beyond its ends, or in a longer gap) is not known (NaN)."""
    stamps = track.stamps_ns
    n = stamps.shape[0]
    want_ns = np.asarray(want_ns, dtype=np.int64)
    xy = np.full((want_ns.shape[0], 2), np.nan)
    known = np.zeros(want_ns.shape[0], dtype=bool)
    if n == 0:
        return xy, known
    i, near = rows_near(stamps, want_ns)
    exact = stamps[i] == want_ns
    xy[exact], known[exact] = track.xy[i[exact]], True
    for k in np.flatnonzero(~exact).tolist():
        b = int(np.searchsorted(stamps, want_ns[k]))  # the first row after the time (none at it: not exact)
        a = b - 1
        if 0 <= a and b < n and 0 < stamps[b] - stamps[a] <= _INTERP_MAX_GAP_NS:
            f = float(want_ns[k] - stamps[a]) / float(stamps[b] - stamps[a])
            xy[k], known[k] = track.xy[a] + f * (track.xy[b] - track.xy[a]), True
        elif near[k]:
            xy[k], known[k] = track.xy[i[k]], True
    return xy, known


def future_positions(track: Track | None, stamp_ns: int, step_ns: int, n_steps: int) -> np.ndarray | None:
    """True positions (n_steps, 2) at t + k·step, k = 1..n_steps (``positions_at``), or None when one is not known."""
    if track is None or n_steps <= 0:
        return None
    xy, known = positions_at(track, stamp_ns + int(step_ns) * np.arange(1, n_steps + 1))
    return xy if known.all() else None


def future_accelerations(track: Track | None, stamp_ns: int, step_ns: int, n_steps: int) -> np.ndarray | None:
    """True accelerations (n_steps,) at t + k·step (the row within ``STAMP_TOL_NS``), or None when one is missing or unknown (NaN)."""
    if track is None or n_steps <= 0:
        return None
    i, found = _future_rows(track, stamp_ns, step_ns, n_steps)
    if not found.all():
        return None
    accel = track.accel_mps2[i]
    return accel if np.all(np.isfinite(accel)) else None


def future_run(track: Track, stamp_ns: int, step_ns: int, n_steps: int) -> np.ndarray:
    """True positions (k, 2) at t + j·step (as ``future_positions``), j = 1..k: the longest run up to n_steps (k may be 0)."""
    xy, known = positions_at(track, stamp_ns + int(step_ns) * np.arange(1, n_steps + 1))
    k = int(np.argmin(known)) if not known.all() else n_steps
    return xy[:k]


def positions_after(track: Track, stamp_ns: int, seconds: float) -> np.ndarray:
    """Positions (n, 2) of the track after `stamp_ns` up to `seconds` later."""
    a = np.searchsorted(track.stamps_ns, stamp_ns, side="right")
    b = np.searchsorted(track.stamps_ns, stamp_ns + int(round(seconds * 1e9)), side="right")
    return track.xy[a:b]


# --------------------------------------------------------------------------- the followed corridor


class Followed(NamedTuple):
    """The corridor the future followed best: its index, its max |d| (m) and the runner-up's (inf without one)."""

    index: int
    error_m: float
    runner_up_m: float


def followed_corridor(corridors: Sequence, future_xy: np.ndarray, *, min_inside: int = 1) -> Followed:
    """The corridor of `corridors` (``bus_schemas.Corridor``) the future positions (n, 2) follow best (module docstring).

    Only the positions whose projection falls within a corridor's s range
    count (a car standing at the start of its corridors jitters behind it);
    a corridor holding fewer than `min_inside` (at least 1) of them gets
    distance inf.
    """
    future_xy = np.asarray(future_xy, dtype=np.float64).reshape(-1, 2)
    need = max(int(min_inside), 1)
    errors = np.full(len(corridors), np.inf)
    for k, c in enumerate(corridors):
        proj = project_to_polyline(future_xy, np.column_stack([c.x_m, c.y_m]), c.s_m)
        inside = (proj.s_m >= c.s_m[0]) & (proj.s_m <= c.s_m[-1])
        if int(inside.sum()) >= need:
            errors[k] = float(np.max(np.abs(proj.d_m[inside])))
    order = np.argsort(errors, kind="stable")
    second = float(errors[order[1]]) if len(order) > 1 else math.inf
    return Followed(int(order[0]), float(errors[order[0]]), second)


def route_decision(followed: Followed, max_error_m: float = ROUTE_MAX_ERROR_M, tie_m: float = ROUTE_TIE_M) -> str | None:
    """None when `followed` singles out one corridor; else why not: ``"followed_no_corridor"`` or ``"route_tied"``."""
    if not followed.error_m <= max_error_m:
        return "followed_no_corridor"
    if followed.runner_up_m - followed.error_m < tie_m:
        return "route_tied"
    return None


# --------------------------------------------------------------------------- route_top1


def route_credit(scores: np.ndarray, truth: int) -> float:
    """1 when corridor `truth` has the highest score alone, 1/k when it is one of k tied for it, else 0."""
    scores = np.asarray(scores, dtype=np.float64)
    best = np.flatnonzero(scores >= scores.max() - SCORE_TIE)
    return 1.0 / best.size if int(truth) in best else 0.0


def route_top1(scores: Iterable[np.ndarray], truth: Iterable[int]) -> float:
    """Mean ``route_credit`` over windows (scores per corridor, the followed corridor's index); NaN without windows."""
    credits = [route_credit(s, t) for s, t in zip(scores, truth)]
    return float(np.mean(credits)) if credits else math.nan


# --------------------------------------------------------------------------- manoeuvre classes and the along-track direction

#: the classes of a window's true future, in priority order (the first that applies wins).
MANOEUVRES = ("stands", "turns", "brakes", "accelerates", "keeps_speed")
#: stands: no true future position is this far (m) from the start position.
STAND_MAX_DISPLACEMENT_M = 1.0
#: turns: the heading of the true path at the end differs from that at the start by more than this (degrees).
TURN_MIN_HEADING_DEG = 30.0
#: the headings are those of chords of at least this length (m): start → first position this far away, and last
#: position this far from the end → end (tracker jitter makes shorter steps' directions meaningless).
HEADING_CHORD_M = 1.0
#: brakes / accelerates: |v_end − v_start| exceeds min(SPEED_CHANGE_ABS_MPS, SPEED_CHANGE_REL · max(v_start, v_end)),
#: but at least SPEED_CHANGE_MIN_MPS (m/s) ...
SPEED_CHANGE_ABS_MPS = 2.0
SPEED_CHANGE_REL = 0.30
SPEED_CHANGE_MIN_MPS = 1.0
#: ... the speeds being the mean speeds over the first and the last this many steps of the horizon (chord / time).
SPEED_WINDOW_STEPS = 2
#: the along-track direction at a step: the central difference of the true positions; when that moves less than this
#: (m), the direction from the start position; when that too moves less, none (the error counts as cross-track only).
TANGENT_MIN_MOVE_M = 0.2


def _path(start_xy, future_xy) -> np.ndarray:
    start = np.asarray(start_xy, dtype=np.float64).reshape(1, 2)
    return np.vstack([start, np.asarray(future_xy, dtype=np.float64).reshape(-1, 2)])


def manoeuvre_class(start_xy, future_xy: np.ndarray, step_s: float) -> str:
    """The manoeuvre of a window's true future: one of ``MANOEUVRES``.

    `start_xy` is the true position at the instant, `future_xy` (K, 2) the
    true positions at t + k·`step_s`, k = 1..K. Speeds and headings come from
    these positions only (never from the tracker's reported velocity).
    In priority order:

    - ``stands``: no future position is ``STAND_MAX_DISPLACEMENT_M`` (1 m)
      or more from the start;
    - ``turns``: the heading of the path at the end differs from that at the
      start by more than ``TURN_MIN_HEADING_DEG`` (30°); the start heading is
      that of the chord from the start to the first position at least
      ``HEADING_CHORD_M`` (1 m) away, the end heading that of the chord from
      the last position at least 1 m before the end to the end (no such
      chord: not a turn);
    - ``brakes`` / ``accelerates`` (starting included): the speed at the
      end, v_end, is below / above the speed at the start, v_start, by more
      than min(``SPEED_CHANGE_ABS_MPS`` = 2 m/s, ``SPEED_CHANGE_REL`` = 30 %
      of max(v_start, v_end)), and by at least ``SPEED_CHANGE_MIN_MPS`` =
      1 m/s (below 3.3 m/s the relative threshold would be tracker jitter);
      v_start and v_end are the mean speeds (chord length over time) over the
      first and the last ``SPEED_WINDOW_STEPS`` (2, 0.8 s) steps;
    - ``keeps_speed`` otherwise.

    The thresholds were chosen by looking at the true futures of the
    embedded K729 recording only (step speeds of standing cars below
    0.2 m/s in 99 % of the steps, step-to-step speed changes of moving
    cars up to ~1.6 m/s over 0.4 s, hence the two-step speeds and the 1 m/s
    floor), not tuned against any evaluation result.
    """
    p = _path(start_xy, future_xy)
    k = p.shape[0] - 1
    if k < 1 or not np.all(np.isfinite(p)):
        raise ValueError("manoeuvre_class: needs a finite start and at least one future position")
    from_start = np.hypot(*(p - p[0]).T)
    if not from_start.max() >= STAND_MAX_DISPLACEMENT_M:
        return "stands"
    to_end = np.hypot(*(p - p[-1]).T)
    first = int(np.argmax(from_start >= HEADING_CHORD_M))
    before_end = np.flatnonzero(to_end >= HEADING_CHORD_M)
    if before_end.size:
        a, b = p[first] - p[0], p[-1] - p[before_end[-1]]
        change = math.degrees(abs(math.remainder(math.atan2(b[1], b[0]) - math.atan2(a[1], a[0]), 2 * math.pi)))
        if change > TURN_MIN_HEADING_DEG:
            return "turns"
    w = max(min(int(SPEED_WINDOW_STEPS), k), 1)
    v_start = float(np.hypot(*(p[w] - p[0]))) / (w * step_s)
    v_end = float(np.hypot(*(p[-1] - p[-1 - w]))) / (w * step_s)
    threshold = max(min(SPEED_CHANGE_ABS_MPS, SPEED_CHANGE_REL * max(v_start, v_end)), SPEED_CHANGE_MIN_MPS)
    if v_end < v_start - threshold:
        return "brakes"
    if v_end > v_start + threshold:
        return "accelerates"
    return "keeps_speed"


def along_track_directions(start_xy, future_xy: np.ndarray) -> np.ndarray:
    """(K, 2) unit vectors of the true direction of travel at each future step; NaN rows where there is none.

    The tangent of the true path at step k: the central difference
    p[k+1] − p[k−1] (p[0] the start position), at the last step the
    backward difference p[K] − p[K−1]. Where that moves less than
    ``TANGENT_MIN_MOVE_M`` (0.2 m: the car stands around that time) the
    direction from the start, p[k] − p[0]; where that too is shorter, NaN
    (``iamp eval`` then counts the whole error as cross-track and the step
    not at all in the along-track figures).
    """
    p = _path(start_xy, future_xy)
    k = p.shape[0] - 1
    out = np.full((k, 2), np.nan)
    for j in range(1, k + 1):
        for d in (p[min(j + 1, k)] - p[j - 1], p[j] - p[0]):
            n = float(np.hypot(*d))
            if n >= TANGENT_MIN_MOVE_M:
                out[j - 1] = d / n
                break
    return out


__all__ = [
    "ACCEL_EDGE_S", "MANOEUVRES", "STAND_MAX_DISPLACEMENT_M", "TURN_MIN_HEADING_DEG", "HEADING_CHORD_M", "SPEED_CHANGE_ABS_MPS",
    "SPEED_CHANGE_REL", "SPEED_CHANGE_MIN_MPS", "SPEED_WINDOW_STEPS", "TANGENT_MIN_MOVE_M", "along_track_directions", "manoeuvre_class", "ACCEL_WINDOW_S", "Followed", "ROUTE_MAX_ERROR_M", "ROUTE_TIE_M", "Track", "followed_corridor",
    "future_accelerations", "future_positions", "future_run", "ground_truth", "positions_after", "route_credit", "rows_near", "positions_at", "STAMP_TOL_NS",
    "route_decision", "route_top1", "smoothed_acceleration",
]
