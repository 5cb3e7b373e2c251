"""AR input features per vehicle and corridor, one row per 0.1 s step (docs/method.md §8.1).

``FeatureTracker`` keeps each vehicle's history and turns it into the AR
model's input. Training (``stages.offline.train.dataset``) and the online stage use this
one class, frame by frame, so the model sees online exactly what it was
trained on.

Features (``FEATURE_NAMES``; the paper's 22, then own speed):

====  ==========================  =====================================================================
#     name                        definition
====  ==========================  =====================================================================
0     ``accel_mps2``              longitudinal acceleration, CAUSAL: least-squares slope of the
                                  vehicle's speed (``VehicleCorridors.speed_mps``) over the last
                                  ``accel_window_s`` (default 1.0 s, 11 frames at 10 Hz); 0 with
                                  fewer than 3 samples or less than half the window; clipped to
                                  ±``accel_clip_mps2`` 8
1–12  ``curv_{pos,neg}_<a>_<b>m``  the corridor ahead of the vehicle's s in 6 segments of 10 m
                                  (``lookahead_m`` 60): ∫max(κ, 0) ds and ∫min(κ, 0) ds per segment,
                                  rad (κ positive to the left: a left turn gives ``pos`` > 0).
                                  Beyond the corridor's end κ = 0 (the corridors stage cuts a
                                  corridor v·4 s + 26 m ahead, so a slow car sees less than 60 m)
13    ``intersection_distance_m`` entry of the next intersection (smallest entry s among the
                                  relations' intersections, which holds only those not yet left)
                                  minus the vehicle's s, clipped to [−10, 100]; 100 without one
14    ``leader_gap_m``            the relations' bumper-to-bumper leader gap, clipped to [0, 100];
                                  100 without a leader
15    ``leader_speed_mps``        the leader's speed along the corridor; the own speed without one
16–18 ``infl1_*``                 the most influencing vehicle (``relations.most_influencing``):
                                  its distance to the conflict point (``conflict_other_distance_m``,
                                  clipped to [−10, 100]), its speed, and its priority
                                  (+1: it has right of way over the ego, −1: the ego has, i.e.
                                  ``-conflict_priority``); absent: 100 m, 0 m/s, 0
19–21 ``infl2_*``                 the second most influencing vehicle, likewise
22    ``speed_mps``               own speed (not in the paper's table; see "own speed" below)
====  ==========================  =====================================================================

Without a ``RelationSet`` (or one of another stamp, issue ``stamp_mismatch``)
the relation features 13–21 take their "absent" values (issue
``no_relations``).

Measured choices (``iamp train``, validation MSE; figures in
docs/method.md §8.1):

- Causal window 1.0 s: the nets rebuild what they need from the speed
  history, so the window does not matter to them; it matters to the "last
  value held" predictor, which it is. The K733 tracker's speeds jitter from
  frame to frame, mostly along the track, so a short slope there is noise;
  1.0 s is the compromise, and ``markov_prediction``'s ``accel_window_s``.
  Shrinking the slope by its standard error (``accel_shrink``) barely
  helped; off.
- Own speed (``speed_mps``, not in the paper's table): slightly better with
  it. Kept.
- The context features (1–21): the nets are clearly worse without them.

History. A vehicle's rows are kept per step index round(stamp / 0.1 s)
(a later frame in the same step replaces the earlier one; skipped stamps
leave steps empty); rows older than ``HISTORY_STEPS`` steps before the newest
are dropped and a vehicle unseen for more than ``track_timeout_s`` 1 s (by
stamps) is forgotten. A stamp going backwards resets everything (issue
``stamp_backwards``). A row holds the vehicle's acceleration and speed and,
when it was matched, the 21 corridor features of each of its corridors by
``corridor_id`` (ids are stable from frame to frame while the route
continues: ``stages.corridors`` inherits them). The rows live in ring
buffers of ``HISTORY_STEPS`` slots (slot = step mod 40), one for the vehicle
and one per corridor id, so ``batch`` gathers a pair's 40 steps by index
arrays. ``update`` computes the corridor features of all pairs of a frame
in one batch (``pair_features``: row p exactly what pair p alone gives);
when the batch raises, each pair is computed alone so that only the
failing ones lose their row (issue ``pair_failed``).

``batch(corridor_set)``: for each matched vehicle with at least one row and
each of its corridors, the 40 steps ending at the set's stamp, oldest first.
``mask`` is True where the vehicle has a row at that step. Steps without a
row (before the track began, skipped frames, a non-finite speed) repeat the
nearest real row: the previous one, else (leading padding) the oldest. A
corridor feature of a step whose row lacks that corridor id (the corridor
appeared later, or the vehicle was unmatched then) likewise repeats that
corridor's value at the nearest step that has it: the previous one, else the
oldest one (i.e. a new branch's past is its first value). A vehicle without
any row (non-finite speed at its first frame) is left out of the batch.

Bad values never raise: a non-finite speed gives issue ``nan_state`` and no
row; a non-finite corridor feature is replaced by its "absent"/0 value with
issue ``nan_feature``.
"""

from __future__ import annotations

import collections
import math
from dataclasses import dataclass, field
from typing import Iterable, Sequence

import numpy as np

from bus_schemas import AgentType, Corridor, CorridorRelations, CorridorSet, MatchStatus, RelationSet, TrackFrame
from stages.lib.base import ConfigMixin, Issue, check_ranges
from stages.lib.influence import most_influencing

HISTORY_STEPS = 40
"""Steps of history the model sees (4 s)."""
HORIZON_STEPS = 40
"""Accelerations the model predicts, at 0.1 … 4.0 s."""
STEP_S = 0.1
"""Step of both, s."""

N_SEGMENTS = 6
SEGMENT_M = 10.0

_SEGMENT_NAMES = tuple(f"{int(i * SEGMENT_M):02d}_{int((i + 1) * SEGMENT_M):02d}m" for i in range(N_SEGMENTS))
FEATURE_NAMES: tuple[str, ...] = (
    ("accel_mps2",)
    + tuple(f"curv_{sign}_{seg}" for seg in _SEGMENT_NAMES for sign in ("pos", "neg"))
    + ("intersection_distance_m", "leader_gap_m", "leader_speed_mps")
    + tuple(f"infl{k}_{what}" for k in (1, 2) for what in ("distance_m", "speed_mps", "priority"))
    + ("speed_mps",)
)
"""Column names of the feature axis of ``FeatureTracker.batch`` (module docstring table)."""

N_FEATURES = len(FEATURE_NAMES)
ACCEL = FEATURE_NAMES.index("accel_mps2")
SPEED = FEATURE_NAMES.index("speed_mps")
_VEHICLE_COLUMNS = np.array([ACCEL, SPEED])
_CORRIDOR_COLUMNS = np.array([i for i in range(N_FEATURES) if i not in (ACCEL, SPEED)])
_CORRIDOR_SLICE = slice(int(_CORRIDOR_COLUMNS[0]), int(_CORRIDOR_COLUMNS[-1]) + 1)  # the corridor columns are contiguous
assert np.array_equal(np.arange(N_FEATURES)[_CORRIDOR_SLICE], _CORRIDOR_COLUMNS)
_VEHICLE_TYPES = frozenset(int(t) for t in AgentType if t.is_vehicle)


def _is_vehicle(agent_type) -> bool:
    """``AgentType(agent_type).is_vehicle``, False for a value that is no AgentType."""
    try:
        return int(agent_type) in _VEHICLE_TYPES
    except ValueError:
        return False
N_CORRIDOR_FEATURES = len(_CORRIDOR_COLUMNS)
_NS = 1e-9


@dataclass(frozen=True, kw_only=True)
class FeatureConfig(ConfigMixin):
    """Feature definitions (module docstring); lengths in m, times in s."""

    accel_window_s: float = 1.0
    accel_clip_mps2: float = 8.0
    accel_shrink: bool = False
    lookahead_m: float = N_SEGMENTS * SEGMENT_M
    absent_distance_m: float = 100.0
    min_distance_m: float = -10.0
    track_timeout_s: float = 1.0

    def __post_init__(self) -> None:
        check_ranges(self, positive=("accel_window_s", "accel_clip_mps2", "lookahead_m", "absent_distance_m", "track_timeout_s"))
        if not (math.isfinite(self.min_distance_m) and self.min_distance_m <= 0):
            raise ValueError(f"min_distance_m = {self.min_distance_m!r}: must be <= 0")

    def absent_row(self) -> np.ndarray:
        """The corridor features (21,) of a pair with no relations: no intersection, leader or influencer."""
        row = np.zeros(N_CORRIDOR_FEATURES, dtype=np.float64)
        full = np.zeros(N_FEATURES)
        full[FEATURE_NAMES.index("intersection_distance_m")] = self.absent_distance_m
        full[FEATURE_NAMES.index("leader_gap_m")] = self.absent_distance_m
        full[FEATURE_NAMES.index("infl1_distance_m")] = self.absent_distance_m
        full[FEATURE_NAMES.index("infl2_distance_m")] = self.absent_distance_m
        row[:] = full[_CORRIDOR_COLUMNS]
        return row


# --------------------------------------------------------------------------- single features


def causal_acceleration(stamps_ns: np.ndarray, speeds_mps: np.ndarray, window_s: float, shrink: bool = False) -> float:
    """Least-squares slope (m/s²) of the speeds within `window_s` up to the newest stamp; 0 if too few.

    Too few: fewer than 3 samples, or spanning less than half the window.
    Without `shrink` the compiled `kernels.causal_slope` computes it (the
    numpy arithmetic below, bit for bit). With `shrink`, the slope is shrunk towards 0 by its standard error σ:
    slope·max(0, 1 − σ²/slope²) (as ``markov_prediction``'s a0).
    """
    t = np.asarray(stamps_ns, dtype=np.int64)
    if t.size < 3:
        return 0.0
    if not shrink:
        from stages.lib.ar import kernels  # numba loaded on first use

        found = kernels.causal_slope(t, np.asarray(speeds_mps, dtype=np.float64), window_s, _NS)  # the same bits
        if found is not None:
            return found
    keep = t >= t[-1] - int(round(window_s / _NS)) - 1_000_000
    t, v = (t[keep] - t[-1]) * _NS, np.asarray(speeds_mps, dtype=np.float64)[keep]
    if t.size < 3 or -t[0] < 0.5 * window_s - 1e-6:
        return 0.0
    t = t - t.mean()
    sxx = float((t * t).sum())
    slope = float((t * (v - v.mean())).sum() / sxx)
    if not shrink:
        return slope
    residual = v - v.mean() - slope * t
    sigma2 = float((residual**2).sum()) / max(t.size - 2, 1) / sxx
    return slope * max(0.0, 1.0 - sigma2 / max(slope * slope, 1e-12))


def curvature_integrals(corridor: Corridor, lookahead_m: float = N_SEGMENTS * SEGMENT_M, n_segments: int = N_SEGMENTS) -> np.ndarray:
    """(n_segments, 2): ∫max(κ, 0) ds and ∫min(κ, 0) ds (rad) over equal segments ahead of the vehicle's s.

    Trapezoidal integration on the corridor's samples; the corridor is
    straight (κ = 0) beyond its ends. One corridor of `curvature_rows`.
    """
    return curvature_rows([corridor], lookahead_m, n_segments)[0]


def curvature_rows(corridors: Sequence[Corridor], lookahead_m: float = N_SEGMENTS * SEGMENT_M, n_segments: int = N_SEGMENTS) -> np.ndarray:
    """`curvature_integrals` of several corridors at once: (P, n_segments, 2), float64.

    Each row is exactly what one corridor alone gives: computed by the
    compiled kernel (`stages.lib.ar.kernels`, one pass per corridor), else
    (no numba, or an arc length that does not increase strictly) by
    `_curvature_rows_numpy`. A corridor whose curvature and arc-length arrays
    differ in length raises ``ValueError`` (the caller isolates the pair).
    """
    n_rows = len(corridors)
    out = np.zeros((n_rows, n_segments, 2))
    s_parts = [np.asarray(c.s_m, dtype=np.float64) for c in corridors]
    k_parts = [np.asarray(c.curvature_1pm, dtype=np.float64) for c in corridors]
    for c, s, k in zip(corridors, s_parts, k_parts):
        if s.shape != k.shape or s.ndim != 1:
            raise ValueError(f"corridor {c.corridor_id}: curvature has {k.shape} samples, arc length {s.shape}")
    vehicle_s = np.array([float(c.vehicle_s_m) for c in corridors], dtype=np.float64)
    from stages.lib.ar import kernels  # numba loaded on first use: `import stages.lib.ar` stays light

    done = kernels.curvature_rows(s_parts, k_parts, vehicle_s, _segment_bounds(lookahead_m, n_segments), out)
    rest = np.arange(n_rows) if done is None else np.flatnonzero(~done)
    if rest.size:
        out[rest] = _curvature_rows_numpy([s_parts[r] for r in rest.tolist()], [k_parts[r] for r in rest.tolist()], vehicle_s[rest],
                                          lookahead_m, n_segments)
    return out


def _curvature_rows_numpy(s_parts: list[np.ndarray], k_parts: list[np.ndarray], vehicle_s: np.ndarray, lookahead_m: float,
                          n_segments: int) -> np.ndarray:
    """`curvature_rows` on numpy: the element-wise work and the cumulative sums on all corridors together (rows padded
    to the longest), then each row its own ``np.interp``, so every row is exactly what one corridor alone gives."""
    n_rows = len(s_parts)
    out = np.zeros((n_rows, n_segments, 2))
    lengths = np.array([s.size for s in s_parts], dtype=np.int64)
    usable = (lengths >= 2) & np.isfinite(vehicle_s)
    if not usable.any():
        return out
    width = int(lengths.max())
    valid = np.arange(width)[None, :] < lengths[:, None]
    s = np.zeros((n_rows, width))
    kappa = np.zeros((n_rows, width))
    s[valid] = np.concatenate(s_parts)
    kappa[valid] = np.concatenate(k_parts)
    kappa = np.where(np.isfinite(kappa), kappa, 0.0)  # as np.nan_to_num(nan=0, posinf=0, neginf=0)
    ds = np.diff(s, axis=1)
    parts = np.stack([np.maximum(kappa, 0.0), np.minimum(kappa, 0.0)])  # (2, P, W)
    cumulative = np.zeros(parts.shape)
    np.cumsum(0.5 * (parts[..., 1:] + parts[..., :-1]) * ds, axis=-1, out=cumulative[..., 1:])  # sequential: per row as alone
    bounds = vehicle_s[:, None] + _segment_bounds(lookahead_m, n_segments)[None, :]
    at = np.zeros((2, n_rows, n_segments + 1))
    for row in np.flatnonzero(usable).tolist():
        n = int(lengths[row])
        for col in (0, 1):
            at[col, row] = np.interp(bounds[row], s[row, :n], cumulative[col, row, :n])
    out[usable] = np.moveaxis(np.diff(at, axis=-1), 0, -1)[usable]
    return out


_BOUNDS: dict[tuple[float, int], np.ndarray] = {}


def _segment_bounds(lookahead_m: float, n_segments: int) -> np.ndarray:
    """``np.linspace(0, lookahead_m, n_segments + 1)``, computed once per (lookahead, segments)."""
    key = (float(lookahead_m), int(n_segments))
    found = _BOUNDS.get(key)
    if found is None:
        found = _BOUNDS[key] = np.linspace(0.0, lookahead_m, n_segments + 1)
        found.flags.writeable = False
    return found


_INTERSECTION = FEATURE_NAMES.index("intersection_distance_m")
_LEADER_GAP = FEATURE_NAMES.index("leader_gap_m")
_LEADER_SPEED = FEATURE_NAMES.index("leader_speed_mps")
_INFLUENCER = tuple(
    (FEATURE_NAMES.index(f"infl{k}_distance_m"), FEATURE_NAMES.index(f"infl{k}_speed_mps"), FEATURE_NAMES.index(f"infl{k}_priority")) for k in (1, 2)
)


def corridor_features(corridor: Corridor, relations: CorridorRelations | None, speed_mps: float, config: FeatureConfig) -> np.ndarray:
    """The 21 corridor features (FEATURE_NAMES without accel and speed) of one pair at one frame, float64."""
    return pair_features([corridor], [relations], [speed_mps], config)[0]


def pair_features(
    corridors: Sequence[Corridor], relations: Sequence[CorridorRelations | None], speeds_mps: Sequence[float], config: FeatureConfig
) -> np.ndarray:
    """`corridor_features` of several pairs at once: (P, 21) float64, row p exactly what pair p alone gives."""
    full = np.zeros((len(corridors), N_FEATURES))
    full[:, 1 : 1 + 2 * N_SEGMENTS] = curvature_rows(corridors, config.lookahead_m).reshape(len(corridors), -1)
    absent, lo = config.absent_distance_m, config.min_distance_m
    full[:, _INTERSECTION] = absent
    full[:, _LEADER_GAP] = absent
    full[:, _LEADER_SPEED] = speeds_mps
    full[:, _INFLUENCER[0][0]] = absent
    full[:, _INFLUENCER[1][0]] = absent
    for row, rel in enumerate(relations):
        if rel is None:
            continue
        entry = np.asarray(rel.intersection_entry_s_m, dtype=np.float64).tolist()
        if entry:
            ahead = [e if math.isfinite(e) else math.inf for e in entry]
            q = ahead.index(min(ahead))  # the first smallest, as np.argmin
            full[row, _INTERSECTION] = _clip(float(rel.intersection_distance_m[q]), lo, absent)
        if rel.leader_track_id >= 0 and math.isfinite(rel.leader_gap_m):
            full[row, _LEADER_GAP] = _clip(float(rel.leader_gap_m), 0.0, absent)
            if math.isfinite(rel.leader_speed_mps):
                full[row, _LEADER_SPEED] = rel.leader_speed_mps
        if len(rel.conflict_time_s):  # most_influencing of no conflicts: none
            for (distance, speed, priority), c in zip(_INFLUENCER, most_influencing(rel, 2).tolist()):
                full[row, distance] = _clip(float(rel.conflict_other_distance_m[c]), lo, absent)
                full[row, speed] = rel.conflict_other_speed_mps[c]
                full[row, priority] = -float(rel.conflict_priority[c])
    return full[:, _CORRIDOR_COLUMNS]


def _clip(x: float, lo: float, hi: float) -> float:
    """``np.clip`` of one number, in Python (NaN stays NaN; a bound is taken unless x is strictly inside, as numpy does)."""
    if math.isnan(x):
        return x
    x = x if x > lo else lo
    return x if x < hi else hi


# --------------------------------------------------------------------------- the tracker


_NO_STEP = np.iinfo(np.int64).min


@dataclass(slots=True)
class _Ring:
    """Rows by step in ``HISTORY_STEPS`` slots: slot ``k % HISTORY_STEPS`` holds the row of step ``step[slot]`` (``_NO_STEP``: none)."""

    step: np.ndarray  # (HISTORY_STEPS,) int64
    values: np.ndarray  # (HISTORY_STEPS, width) float64

    @classmethod
    def empty(cls, width: int) -> "_Ring":
        return cls(np.full(HISTORY_STEPS, _NO_STEP, dtype=np.int64), np.zeros((HISTORY_STEPS, width)))


@dataclass(slots=True)
class _Track:
    """One vehicle's history: its rows (accel, speed) and, per corridor id, the corridor features of the rows that hold it.

    A row of step k is kept while k lies in (last_step − HISTORY_STEPS, last_step]; a corridor ring's slot holds a
    step only if that step's row holds the corridor (a row replaced within its step clears the corridors it lacks).
    """

    last_stamp_ns: int
    last_step: int = _NO_STEP
    stamps: collections.deque = field(default_factory=lambda: collections.deque(maxlen=64))
    speeds: collections.deque = field(default_factory=lambda: collections.deque(maxlen=64))
    vehicle: _Ring = field(default_factory=lambda: _Ring.empty(len(_VEHICLE_COLUMNS)))
    corridors: dict[int, _Ring] = field(default_factory=dict)

    def put(self, step: int, accel: float, speed: float, rows: dict[int, np.ndarray]) -> None:
        """The row of `step` (replacing one of the same step): vehicle values and the corridor features by id."""
        slot = step % HISTORY_STEPS
        self.last_step = step
        self.vehicle.step[slot] = step
        self.vehicle.values[slot] = (accel, speed)
        for cid in list(self.corridors):
            if cid not in rows:
                ring = self.corridors[cid]
                ring.step[slot] = _NO_STEP
                if int(ring.step.max()) <= step - HISTORY_STEPS:  # in no kept row any more
                    del self.corridors[cid]
        for cid, row in rows.items():
            ring = self.corridors.get(cid)
            if ring is None:
                ring = self.corridors[cid] = _Ring.empty(N_CORRIDOR_FEATURES)
            ring.step[slot] = step
            ring.values[slot] = row


def _fill_source(present: np.ndarray) -> np.ndarray:
    """For each position, the index of the nearest present one: the previous, else the first. (..., n) int, per row."""
    n = present.shape[-1]
    idx = np.where(present, np.arange(n), -1)
    idx = np.maximum.accumulate(idx, axis=-1)
    first = np.argmax(present, axis=-1)
    return np.where(idx < 0, np.expand_dims(first, -1), idx)


class FeatureTracker:
    """Per-vehicle feature history over frames (module docstring); the same for training and online.

    Call ``update`` once per frame (stamps increasing), then ``batch`` for
    the model input of that frame.
    """

    def __init__(self, config: FeatureConfig | None = None) -> None:
        self.config = config or FeatureConfig()
        self._tracks: dict[int, _Track] = {}
        self._last_stamp_ns: int | None = None
        self._scene_id = ""  # the scene of the last frame (another one starts every history afresh)
        self._step_ns = int(round(STEP_S / _NS))
        self.issue_counts: collections.Counter[str] = collections.Counter()

    @property
    def tracked_ids(self) -> frozenset[int]:
        return frozenset(self._tracks)

    def reset(self) -> None:
        self._tracks.clear()
        self._last_stamp_ns = None
        self._scene_id = ""

    def step_index(self, stamp_ns: int) -> int:
        return int(round(int(stamp_ns) / self._step_ns))

    def update(self, corridor_set: CorridorSet, relation_set: RelationSet | None, track_frame: TrackFrame | None = None) -> list[Issue]:
        """Add one frame. `track_frame` is accepted for the online stage's convenience and not used.

        The speed is ``VehicleCorridors.speed_mps``: the frame's reported
        speed, or the corridors stage's position-derived one where that is
        not finite. Returns the issues (also counted in ``issue_counts``).
        """
        cfg = self.config
        issues: list[Issue] = []
        stamp = int(corridor_set.header.stamp_ns)
        scene_id = corridor_set.scene_id
        if scene_id and self._scene_id and scene_id != self._scene_id:  # (a replay of another recording: other track ids)
            issues.append(Issue("scene_changed", -1, f"scene {self._scene_id!r} -> {scene_id!r}: feature history reset"))
            self._tracks.clear()
        elif self._last_stamp_ns is not None and stamp < self._last_stamp_ns:
            issues.append(Issue("stamp_backwards", -1, f"stamp {stamp} < {self._last_stamp_ns}: feature history reset"))
            self._tracks.clear()
        self._scene_id = scene_id or self._scene_id
        self._last_stamp_ns = stamp
        timeout_ns = int(round(cfg.track_timeout_s / _NS))
        for track_id in [k for k, t in self._tracks.items() if stamp - t.last_stamp_ns > timeout_ns]:
            del self._tracks[track_id]
        relations: dict[tuple[int, int], CorridorRelations] = {}
        if relation_set is None:
            issues.append(Issue("no_relations", -1, "no relation set: leader, intersection and influencer features absent"))
        elif int(relation_set.header.stamp_ns) != stamp:
            issues.append(Issue("stamp_mismatch", -1, f"relation set stamp {relation_set.header.stamp_ns} != corridor set {stamp}: relations ignored"))
        else:
            relations = {(r.track_id, r.corridor_id): r for r in relation_set.relations}
        step = self.step_index(stamp)
        entries: list[tuple] = []  # (vehicle, speed or None when not finite), in the set's order
        pairs: list[tuple] = []  # (corridor, relations, speed) of the matched vehicles' corridors
        for vehicle in corridor_set.vehicles:
            if not _is_vehicle(vehicle.agent_type) or vehicle.status in (MatchStatus.NOT_A_VEHICLE, MatchStatus.BAD_STATE):
                continue
            speed = float(vehicle.speed_mps)
            if not math.isfinite(speed):
                entries.append((vehicle, None))
                continue
            entries.append((vehicle, speed))
            if vehicle.status == MatchStatus.MATCHED:
                pairs.extend((c, relations.get((vehicle.track_id, c.corridor_id)), speed) for c in vehicle.corridors)
        features, failures = self._pair_features(pairs)
        finite_rows = np.isfinite(features).all(axis=1).tolist()  # the rows to look into for non-finite features
        k = 0
        for vehicle, speed in entries:
            if speed is None:
                issues.append(Issue("nan_state", vehicle.track_id, f"speed {vehicle.speed_mps}: no feature row this frame"))
                continue
            track = self._tracks.get(vehicle.track_id)
            if track is None:
                track = self._tracks[vehicle.track_id] = _Track(last_stamp_ns=stamp)
            track.last_stamp_ns = stamp
            track.stamps.append(stamp)
            track.speeds.append(speed)
            t = np.fromiter(track.stamps, dtype=np.int64, count=len(track.stamps))
            v = np.fromiter(track.speeds, dtype=np.float64, count=len(track.speeds))
            accel = _clip(float(causal_acceleration(t, v, cfg.accel_window_s, cfg.accel_shrink)), -cfg.accel_clip_mps2, cfg.accel_clip_mps2)
            rows: dict[int, np.ndarray] = {}
            if vehicle.status == MatchStatus.MATCHED:
                for corridor in vehicle.corridors:
                    failure, row, finite = failures.get(k), features[k], finite_rows[k]
                    k += 1
                    if failure is not None:
                        issues.append(Issue("pair_failed", vehicle.track_id, f"corridor {corridor.corridor_id}: features raised {type(failure).__name__}: {failure}: no row"))
                        continue
                    if not finite:
                        bad = ~np.isfinite(row)
                        names = [FEATURE_NAMES[int(i)] for i in _CORRIDOR_COLUMNS[bad]]
                        issues.append(Issue("nan_feature", vehicle.track_id, f"corridor {corridor.corridor_id}: non-finite {', '.join(names)}; absent value used"))
                        row[bad] = cfg.absent_row()[bad]
                    rows[int(corridor.corridor_id)] = row
            track.put(step, accel, speed, rows)
        self.issue_counts.update(i.kind for i in issues)
        return issues

    def _pair_features(self, pairs: list[tuple]) -> tuple[np.ndarray, dict[int, Exception]]:
        """(P, 21) corridor features of the pairs (corridor, relations, speed) in one batch, and the failed pairs' exceptions
        by index: when the batch raises, each pair is computed alone so that only the failing ones lose their row."""
        if not pairs:
            return np.zeros((0, N_CORRIDOR_FEATURES)), {}
        corridors, relations, speeds = zip(*pairs)
        try:
            return pair_features(corridors, relations, speeds, self.config), {}
        except Exception:  # noqa: BLE001 - found pair by pair below
            pass
        out = np.zeros((len(pairs), N_CORRIDOR_FEATURES))
        failures: dict[int, Exception] = {}
        for k, (corridor, rel, speed) in enumerate(pairs):
            try:
                out[k] = pair_features([corridor], [rel], [speed], self.config)[0]
            except Exception as exc:  # noqa: BLE001 - one corridor's failure costs only its row (no profile for it)
                failures[k] = exc
        return out, failures

    def batch(
        self, corridor_set: CorridorSet, pairs: Iterable[tuple[int, int]] | None = None
    ) -> tuple[list[tuple[int, int]], np.ndarray, np.ndarray]:
        """(keys, x [B, 40, F] float32, mask [B, 40] bool) for the matched pairs of `corridor_set`, newest step last.

        keys are (track_id, corridor_id) in the set's order; `pairs`, when
        given, restricts the batch to those keys.
        """
        wanted = None if pairs is None else set(pairs)
        anchor = self.step_index(int(corridor_set.header.stamp_ns))
        steps = np.arange(anchor - HISTORY_STEPS + 1, anchor + 1)
        slots = steps % HISTORY_STEPS
        empty = [], np.zeros((0, HISTORY_STEPS, N_FEATURES), np.float32), np.zeros((0, HISTORY_STEPS), bool)
        chosen = []  # (vehicle, track, corridor ids) of the matched vehicles with rows, in the set's order
        for vehicle in corridor_set.vehicles:
            if vehicle.status != MatchStatus.MATCHED or not vehicle.corridors:
                continue
            track = self._tracks.get(vehicle.track_id)
            if track is None or track.last_step == _NO_STEP:
                continue
            ids = [int(c.corridor_id) for c in vehicle.corridors]
            if wanted is not None:
                ids = [c for c in ids if (vehicle.track_id, c) in wanted]
                if not ids:
                    continue
            chosen.append((vehicle, track, ids))
        if not chosen:
            return empty
        # every chosen vehicle's 40 steps at once (each row what that vehicle alone gives)
        last = np.fromiter((track.last_step for _v, track, _i in chosen), dtype=np.int64, count=len(chosen))
        kept = (steps[None, :] > (last - HISTORY_STEPS)[:, None]) & (steps[None, :] <= last[:, None])  # the rows each track keeps
        present = (np.stack([track.vehicle.step for _v, track, _i in chosen])[:, slots] == steps) & kept
        fill = slots[_fill_source(present)]
        vehicle_values = np.stack([track.vehicle.values for _v, track, _i in chosen])[np.arange(len(chosen))[:, None], fill]
        usable = present.any(axis=1).tolist()  # a vehicle without a row in the window: left out
        pairs_at: list[tuple[int, int, _Ring | None]] = []  # (vehicle, corridor id, its ring) of the usable vehicles
        rings: list[_Ring] = []
        ring_vehicle: list[int] = []
        for v, (_vehicle, track, ids) in enumerate(chosen):
            if not usable[v]:
                continue
            for cid in ids:
                ring = track.corridors.get(cid)
                pairs_at.append((v, cid, ring))
                if ring is not None:
                    rings.append(ring)
                    ring_vehicle.append(v)
        if rings:  # where each ring holds a kept row of its vehicle
            has = (np.stack([ring.step for ring in rings])[:, slots] == steps) & kept[ring_vehicle]
            has_any = has.any(axis=1).tolist()
        keys: list[tuple[int, int]] = []
        key_vehicle: list[int] = []
        from_rings: list[int] = []  # pairs whose corridor is in some row: their batch rows, their rings
        ring_rows: list[int] = []
        now: dict[int, np.ndarray] = {}  # the other pairs (corridor in no row): geometry now, relations absent
        r = 0
        by_id: dict | None = None
        by_id_of = -1
        for v, cid, ring in pairs_at:
            if ring is not None and has_any[r]:
                from_rings.append(len(keys))
                ring_rows.append(r)
            else:
                if by_id_of != v:
                    by_id, by_id_of = {c.corridor_id: c for c in chosen[v][0].corridors}, v
                try:
                    now[len(keys)] = corridor_features(by_id[cid], None, float(vehicle_values[v, -1, 1]), self.config)
                except Exception:  # noqa: BLE001 - its row failed in update (issue pair_failed): no profile for it
                    r += ring is not None
                    continue
            r += ring is not None
            keys.append((chosen[v][0].track_id, cid))
            key_vehicle.append(v)
        if not keys:
            return empty
        x = np.empty((len(keys), HISTORY_STEPS, N_FEATURES), dtype=np.float32)  # float64 values rounded as by astype
        x[:, :, _VEHICLE_COLUMNS] = vehicle_values[key_vehicle]
        if from_rings:  # each pair's 40 steps from its ring, all pairs in one gather
            source = slots[_fill_source(has[ring_rows])]
            x[from_rings, :, _CORRIDOR_SLICE] = np.stack([rings[k].values for k in ring_rows])[np.arange(len(from_rings))[:, None], source]
        for b, row in now.items():
            x[b, :, _CORRIDOR_SLICE] = row
        return keys, x, present[key_vehicle]


__all__ = [
    "ACCEL",
    "FEATURE_NAMES",
    "HISTORY_STEPS",
    "HORIZON_STEPS",
    "N_FEATURES",
    "SPEED",
    "STEP_S",
    "FeatureConfig",
    "FeatureTracker",
    "causal_acceleration",
    "corridor_features",
    "curvature_integrals",
]
