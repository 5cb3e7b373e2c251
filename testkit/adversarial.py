"""Adversarial recordings: real K729 traffic with one (or several) planted oddities.

Every recording is a short clip (``CLIP_DURATION_S``, default 18 s from
``CLIP_START_S`` = 70 s, the busiest part) of the embedded sequence 013 of
``stages/data/taf-bw`` (K729), written in the INTERACTION layout the loader reads::

    <out>/LICENSE, ATTRIBUTION.md, ADVERSARIAL.md   TAF-BW licence and attribution, what was changed
    <out>/manifest.json                             per recording: oddities, affected track ids, expected issue kinds
    <out>/maps/<name>.osm                           byte copy of the K729 map
    <out>/recorded_trackfiles/<name>/meta_data.csv  the sequence's meta row (start time and duration of the clip)
    <out>/recorded_trackfiles/<name>/vehicle_tracks_013.csv

The track files are rewritten from the *raw* CSV rows (not the loader's
repaired arrays), so the loader and every stage see the oddity as a tracker
would deliver it. ``timestamp_ms`` restarts at 0 at the clip start;
``frame_id`` and ``time`` are recomputed from it.

Oddities (``ODDITIES``; each has the issue kinds we expect some node to
count for it, any one of which is enough; where no stage names one yet, the
kind is the name we would expect, see ``kinds_not_emitted``):

===================  =========================================================================
vel_half             reported velocities x 0.5 (all tracks, or the picked ones)
vel_double           reported velocities x 2
vel_zero_start       reported velocity 0 for the first second of each track
vel_reversed         reported velocities negated
fast_car             a new car driving a real car's path at 30 m/s, then straight on off the map
starts_off_map       a real car's track with a straight approach prepended that starts >= 60 m outside
                     the map's car lanelets (beyond the corridors stage's 50 m entry extension)
wrong_way            a real car's track played backwards in time (against the lane direction; yaw + pi)
teleport             a real car's positions jump by 50 m halfway through its track
duplicate_id         two different cars carry the same id at the same time (the later car's id is set
                     to the earlier one's)
id_reused            a car's id is re-used 1 s after its last frame by another car elsewhere
one_frame_track      a track with a single row (a real row, re-timed, new id)
nan_position         x or y NaN/inf on some rows of one track
nan_velocity         vx or vy NaN/inf on some rows of one track
nan_yaw              psi_rad NaN/inf on some rows of one track
nan_size             length or width NaN/inf on some rows of one track
crowd_100            copies of real tracks, offset laterally (0.3-1 m) and in time (<= 4 s), clipped
                     to +-3 s (``crowd_half_span_s``) around the clip's middle, until that frame holds >= 100 vehicles
===================  =========================================================================

``STANDALONE`` names one recording per oddity (``adv_<oddity>``; the
velocity oddities apply to every track there) plus ``adv_clean`` (the clip
unchanged); ``COMBINED`` packs several oddities into one recording, each on
its own tracks (a velocity oddity on one picked track each), for the
integration test. Everything is seeded: same seed, same bytes.

    python -m testkit.adversarial OUT_DIR [--seed N] [--combined] [--only NAME ...]

The output is derived from TAF-BW (CC BY-NC-SA 4.0): ``LICENSE`` and the
attribution travel with it.
"""

from __future__ import annotations

import argparse
import csv
import datetime as _dt
import json
import math
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from stages.lib.datasets import DEFAULT_DATA_DIR

REPO = Path(__file__).resolve().parents[1]
SOURCE_DATA = DEFAULT_DATA_DIR  # the embedded K729 data
SOURCE_RECORDING = "k729_2022-03-16"
SOURCE_SEQUENCE = "013"
CLIP_START_S = 70.0
CLIP_DURATION_S = 18.0
PERIOD_MS = 100
COLUMNS = ("track_id", "frame_id", "timestamp_ms", "agent_type", "vx", "vy", "psi_rad", "length", "width", "time", "x", "y")
_FLOATS = ("vx", "vy", "psi_rad", "length", "width", "x", "y")
NEW_ID_BASE = 900_000
"""New track ids (synthetic cars, copies) start here, far above the real ids."""

# --------------------------------------------------------------------------- the table


@dataclass(slots=True)
class Table:
    """Rows of one sequence as columns: ints, floats and agent type names; ``serial`` keeps the write order."""

    track_id: np.ndarray
    timestamp_ms: np.ndarray
    agent_type: np.ndarray
    vx: np.ndarray
    vy: np.ndarray
    psi_rad: np.ndarray
    length: np.ndarray
    width: np.ndarray
    x: np.ndarray
    y: np.ndarray
    serial: np.ndarray

    def __len__(self) -> int:
        return int(self.track_id.shape[0])

    def take(self, index) -> "Table":
        return Table(**{k: getattr(self, k)[index].copy() for k in self.__slots__})

    def track_ids(self) -> list[int]:
        return sorted(set(self.track_id.tolist()))

    def rows_of(self, track_id: int) -> np.ndarray:
        """Row indices of one track in time order."""
        idx = np.flatnonzero(self.track_id == track_id)
        return idx[np.argsort(self.timestamp_ms[idx], kind="stable")]

    @staticmethod
    def concat(tables: list["Table"]) -> "Table":
        return Table(**{k: np.concatenate([getattr(t, k) for t in tables]) for k in Table.__slots__})

    @staticmethod
    def build(
        track_id, timestamp_ms, x, y, vx, vy, psi_rad, *, length=4.6, width=2.1, agent_type="Car", serial_start: int = 0
    ) -> "Table":
        n = len(timestamp_ms)
        full = lambda v, dt: np.full(n, v, dtype=dt) if np.ndim(v) == 0 else np.asarray(v, dtype=dt)  # noqa: E731
        return Table(
            track_id=full(track_id, np.int64),
            timestamp_ms=np.asarray(timestamp_ms, dtype=np.int64),
            agent_type=full(agent_type, object),
            vx=full(vx, np.float64),
            vy=full(vy, np.float64),
            psi_rad=full(psi_rad, np.float64),
            length=full(length, np.float64),
            width=full(width, np.float64),
            x=np.asarray(x, dtype=np.float64),
            y=np.asarray(y, dtype=np.float64),
            serial=np.arange(serial_start, serial_start + n, dtype=np.int64),
        )


def read_track_file(path: Path) -> Table:
    """The raw rows of an INTERACTION-format vehicle track file (by header name)."""
    with path.open(newline="", encoding="utf-8-sig") as fh:
        rows = list(csv.DictReader(fh))
    col = lambda name, conv: [conv(r[name]) for r in rows]  # noqa: E731
    return Table(
        track_id=np.asarray(col("track_id", int), dtype=np.int64),
        timestamp_ms=np.asarray(col("timestamp_ms", int), dtype=np.int64),
        agent_type=np.asarray(col("agent_type", str), dtype=object),
        **{k: np.asarray(col(k, float), dtype=np.float64) for k in _FLOATS},
        serial=np.arange(len(rows), dtype=np.int64),
    )


def _fmt(value: float) -> str:
    if math.isnan(value):
        return "nan"
    if math.isinf(value):
        return "inf" if value > 0 else "-inf"
    return repr(float(value))


def write_track_file(path: Path, table: Table, start: _dt.datetime, frame_id_base: int) -> None:
    """Rows sorted by (track_id, timestamp_ms, serial), as the TAF-BW files are (grouped by track)."""
    order = np.lexsort((table.serial, table.timestamp_ms, table.track_id))
    with path.open("w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(COLUMNS)
        for i in order.tolist():
            ts = int(table.timestamp_ms[i])
            when = (start + _dt.timedelta(milliseconds=ts)).strftime("%Y-%m-%d %H:%M:%S.%f")[:-3]
            w.writerow([
                int(table.track_id[i]), frame_id_base + ts // PERIOD_MS, ts, table.agent_type[i],
                _fmt(table.vx[i]), _fmt(table.vy[i]), _fmt(table.psi_rad[i]), _fmt(table.length[i]), _fmt(table.width[i]),
                when, _fmt(table.x[i]), _fmt(table.y[i]),
            ])


# --------------------------------------------------------------------------- context


@dataclass(slots=True)
class TrackInfo:
    track_id: int
    rows: int
    start_ms: int
    end_ms: int
    path_m: float
    mean_speed_mps: float
    start_speed_mps: float


class Context:
    """What an oddity may use: the clip, a seeded generator, track picking, new ids, the map."""

    def __init__(self, table: Table, rng: np.random.Generator, road_map, duration_ms: int, crowd_half_span_ms: int = 3000) -> None:
        self.table = table
        self.crowd_half_span_ms = crowd_half_span_ms
        self.rng = rng
        self.road_map = road_map
        self.duration_ms = duration_ms
        self.used: set[int] = set()
        self._next_id = NEW_ID_BASE
        self._next_serial = 10_000_000
        self.info = {t: self._info(t) for t in table.track_ids()}

    def _info(self, track_id: int) -> TrackInfo:
        t = self.table
        idx = t.rows_of(track_id)
        steps = np.hypot(np.diff(t.x[idx]), np.diff(t.y[idx]))
        speed = np.hypot(t.vx[idx], t.vy[idx])
        return TrackInfo(
            track_id=track_id, rows=int(idx.size), start_ms=int(t.timestamp_ms[idx[0]]), end_ms=int(t.timestamp_ms[idx[-1]]),
            path_m=float(steps.sum()), mean_speed_mps=float(speed.mean()), start_speed_mps=float(speed[:3].mean()),
        )

    def new_id(self) -> int:
        self._next_id += 1
        return self._next_id

    def serials(self, n: int) -> int:
        start = self._next_serial
        self._next_serial += n
        return start

    def pick(self, n: int = 1, *, min_path_m: float = 0.0, min_rows: int = 1, where: Callable[[TrackInfo], bool] | None = None,
             prefer: Callable[[TrackInfo], float] | None = None, mark: bool = True) -> list[int]:
        """``n`` real tracks not used by another oddity; random among those that qualify, or the best by ``prefer``."""
        cands = [i for i in self.info.values() if i.track_id not in self.used and i.track_id < NEW_ID_BASE
                 and i.path_m >= min_path_m and i.rows >= min_rows and (where is None or where(i))]
        if len(cands) < n:
            raise ValueError(f"only {len(cands)} unused tracks qualify, {n} wanted")
        if prefer is not None:
            cands.sort(key=lambda i: (-prefer(i), i.track_id))
            chosen = [c.track_id for c in cands[:n]]
        else:
            chosen = sorted(int(c) for c in self.rng.choice([c.track_id for c in cands], size=n, replace=False))
        if mark:
            self.used.update(chosen)
        return chosen

    def replace_track(self, track_id: int, new_rows: Table) -> None:
        keep = self.table.track_id != track_id
        self.table = Table.concat([self.table.take(keep), new_rows])

    def add(self, rows: Table) -> None:
        self.table = Table.concat([self.table, rows])

    def off_map(self, xy: np.ndarray) -> np.ndarray:
        """True where a point lies inside no car lanelet."""
        inside = self.road_map.inside_matrix(np.asarray(xy, dtype=np.float64).reshape(-1, 2))
        return ~inside.any(axis=1)


# --------------------------------------------------------------------------- oddities


@dataclass(frozen=True, slots=True)
class Oddity:
    name: str
    description: str
    expected_kinds: tuple[str, ...]
    """Issue kinds any one of which, counted by any node (or the eval's skips, see ``eval_kinds``), shows the
    oddity was noticed; empty: nothing to notice, the run must only survive it."""
    apply: Callable[[Context, bool], list[int]]
    """(context, all_tracks) -> affected track ids; all_tracks: the velocity oddities hit every track."""


def _velocity(ctx: Context, all_tracks: bool, fn: Callable[[Table, np.ndarray], None]) -> list[int]:
    ids = ctx.table.track_ids() if all_tracks else ctx.pick(1, min_path_m=20.0)
    for tid in ids:
        fn(ctx.table, ctx.table.rows_of(tid))
    return ids


def _scale(f: float):
    def fn(t: Table, idx: np.ndarray) -> None:
        t.vx[idx] *= f
        t.vy[idx] *= f
    return fn


def _zero_first_second(t: Table, idx: np.ndarray) -> None:
    first = idx[t.timestamp_ms[idx] < t.timestamp_ms[idx[0]] + 1000]
    t.vx[first] = 0.0
    t.vy[first] = 0.0


def _polyline(t: Table, idx: np.ndarray, min_step_m: float = 0.5) -> np.ndarray:
    pts = [np.array([t.x[idx[0]], t.y[idx[0]]])]
    for i in idx[1:].tolist():
        p = np.array([t.x[i], t.y[i]])
        if np.hypot(*(p - pts[-1])) >= min_step_m:
            pts.append(p)
    return np.asarray(pts)


def _along(poly: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points at arc lengths ``s`` along ``poly``, straight on past its ends; and the heading there."""
    seg = np.diff(poly, axis=0)
    cum = np.concatenate([[0.0], np.cumsum(np.hypot(seg[:, 0], seg[:, 1]))])
    k = np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(seg) - 1)
    u = seg[k] / np.hypot(seg[k, 0], seg[k, 1])[:, None]
    pts = poly[k] + u * (s - cum[k])[:, None]
    return pts, np.arctan2(u[:, 1], u[:, 0])


def _fast_car(ctx: Context, _all: bool) -> list[int]:
    (src,) = ctx.pick(1, prefer=lambda i: i.path_m, mark=False)
    poly = _polyline(ctx.table, ctx.table.rows_of(src))
    length = float(np.hypot(*np.diff(poly, axis=0).T).sum())
    speed = 30.0
    t0 = 2000
    n = int(math.ceil((length + 60.0) / speed / (PERIOD_MS / 1000.0))) + 1
    s = speed * np.arange(n) * PERIOD_MS / 1000.0
    pts, heading = _along(poly, s)
    tid = ctx.new_id()
    ts = t0 + PERIOD_MS * np.arange(n)
    keep = ts < ctx.duration_ms
    rows = Table.build(tid, ts[keep], pts[keep, 0], pts[keep, 1], speed * np.cos(heading[keep]), speed * np.sin(heading[keep]),
                       heading[keep], serial_start=ctx.serials(int(keep.sum())))
    if ctx.off_map(pts[keep]).all():
        raise ValueError("fast car never on the map")
    ctx.add(rows)
    return [tid]


OFF_MAP_MARGIN_M = 60.0
"""The off-map car starts this far (straight line) outside every car lanelet: the corridors stage matches cars
up to ``entry_extension_m`` (50 m) before a lane's start, so a few metres off would still match."""
APPROACH_MAX_SPEED_MPS = 14.0
APPROACH_DECEL_MPS2 = 1.5


def _starts_off_map(ctx: Context, _all: bool) -> list[int]:
    """The earliest car entering the clip (moving) gets a straight approach from off the map: at up to 14 m/s,
    slowing at 1.5 m/s^2 to its first real speed; the real track is delayed to follow it, cut at the clip's end."""
    (tid,) = ctx.pick(1, min_path_m=25.0, prefer=lambda i: -i.start_ms if i.start_ms > 0 and i.start_speed_mps >= 3.0 else -1e9)
    t = ctx.table
    idx = t.rows_of(tid)
    first = idx[0]
    p0 = np.array([t.x[first], t.y[first]])
    poly = _polyline(t, idx)
    heading = math.atan2(*(poly[1] - poly[0])[::-1]) if len(poly) > 1 else float(t.psi_rad[first])
    u = np.array([math.cos(heading), math.sin(heading)])
    dt = PERIOD_MS / 1000.0
    v = max(ctx.info[tid].start_speed_mps, 3.0)
    back_m, speeds, points, run_m = 0.0, [], [], 0.0
    while run_m < OFF_MAP_MARGIN_M:  # walk back in time from the first real row
        v = min(v + APPROACH_DECEL_MPS2 * dt, APPROACH_MAX_SPEED_MPS)
        back_m += v * dt
        pt = p0 - back_m * u
        run_m = run_m + v * dt if ctx.off_map(pt)[0] else 0.0
        speeds.append(v)
        points.append(pt)
        if len(points) > 2000:
            raise ValueError("could not find an off-map start")
    n_back = len(points)
    approach = np.asarray(points[::-1])
    speed = np.asarray(speeds[::-1])
    shift = max(0, (n_back + 1) * PERIOD_MS - int(t.timestamp_ms[first]))
    ts_real = t.timestamp_ms[idx] + shift
    keep = ts_real < ctx.duration_ms
    if np.count_nonzero(keep) < 10:
        raise ValueError("clip too short for the off-map approach and 1 s of the real track")
    real = t.take(idx[keep])
    real.timestamp_ms = ts_real[keep]
    ts_app = real.timestamp_ms[0] - PERIOD_MS * np.arange(n_back, 0, -1)
    lead = Table.build(tid, ts_app, approach[:, 0], approach[:, 1], speed * u[0], speed * u[1], heading,
                       length=float(t.length[first]), width=float(t.width[first]), serial_start=ctx.serials(n_back))
    ctx.replace_track(tid, Table.concat([lead, real]))
    return [tid]


def _wrong_way(ctx: Context, _all: bool) -> list[int]:
    (tid,) = ctx.pick(1, min_path_m=30.0, prefer=lambda i: i.path_m)
    t = ctx.table
    idx = t.rows_of(tid)
    rev = idx[::-1]
    new = t.take(idx)
    new.x, new.y = t.x[rev].copy(), t.y[rev].copy()
    new.vx, new.vy = -t.vx[rev], -t.vy[rev]
    new.psi_rad = np.arctan2(np.sin(t.psi_rad[rev] + math.pi), np.cos(t.psi_rad[rev] + math.pi))
    ctx.replace_track(tid, new)
    return [tid]


def _teleport(ctx: Context, _all: bool) -> list[int]:
    (tid,) = ctx.pick(1, min_path_m=20.0, min_rows=60)
    t = ctx.table
    idx = t.rows_of(tid)
    after = idx[idx.size // 2:]
    angle = float(ctx.rng.uniform(-math.pi, math.pi))
    t.x[after] += 50.0 * math.cos(angle)
    t.y[after] += 50.0 * math.sin(angle)
    return [tid]


def _overlap_ms(a: TrackInfo, b: TrackInfo) -> int:
    return min(a.end_ms, b.end_ms) - max(a.start_ms, b.start_ms)


def _duplicate_id(ctx: Context, _all: bool) -> list[int]:
    free = [i for i in ctx.info.values() if i.track_id not in ctx.used and i.rows >= 30]
    pairs = [(a, b) for a in free for b in free if a.track_id < b.track_id and _overlap_ms(a, b) >= 3000]
    if not pairs:
        raise ValueError("no two tracks overlap by 3 s")
    a, b = pairs[int(ctx.rng.integers(len(pairs)))]
    ctx.used.update((a.track_id, b.track_id))
    ctx.table.track_id[ctx.table.track_id == b.track_id] = a.track_id
    return [a.track_id, b.track_id]


def _id_reused(ctx: Context, _all: bool) -> list[int]:
    (c,) = ctx.pick(1, where=lambda i: i.end_ms <= ctx.duration_ms - 6000 and i.rows >= 20)
    t = ctx.table
    c_end = ctx.info[c].end_ms
    c_last = t.rows_of(c)[-1]
    end_xy = np.array([t.x[c_last], t.y[c_last]])

    def far(i: TrackInfo) -> bool:
        first = t.rows_of(i.track_id)[0]
        return i.rows >= 40 and np.hypot(t.x[first] - end_xy[0], t.y[first] - end_xy[1]) > 15.0

    (e,) = ctx.pick(1, where=far, mark=False)
    copy = t.take(t.rows_of(e))
    copy.timestamp_ms = copy.timestamp_ms - copy.timestamp_ms[0] + c_end + 1000
    copy = copy.take(copy.timestamp_ms < ctx.duration_ms)
    copy.track_id[:] = c
    copy.serial = np.arange(ctx.serials(len(copy)), ctx._next_serial)
    ctx.add(copy)
    return [c]


def _one_frame(ctx: Context, _all: bool) -> list[int]:
    (src,) = ctx.pick(1, min_path_m=10.0, mark=False)
    t = ctx.table
    idx = t.rows_of(src)
    row = t.take(idx[idx.size // 2: idx.size // 2 + 1])
    row.track_id[:] = tid = ctx.new_id()
    row.timestamp_ms[:] = (ctx.duration_ms // 2 // PERIOD_MS) * PERIOD_MS
    row.serial[:] = ctx.serials(1)
    ctx.add(row)
    return [tid]


_BAD = (math.nan, math.inf, -math.inf)


def _nan_fields(columns: tuple[str, ...]):
    def apply(ctx: Context, _all: bool) -> list[int]:
        (tid,) = ctx.pick(1, min_rows=20)
        t = ctx.table
        idx = t.rows_of(tid)
        rows = ctx.rng.choice(idx[1:], size=min(6, idx.size - 1), replace=False)
        for k, i in enumerate(sorted(rows.tolist())):
            col = columns[k % len(columns)]
            getattr(t, col)[i] = _BAD[k % len(_BAD)]
        return [tid]
    return apply


def _crowd(ctx: Context, _all: bool, target: int = 100) -> list[int]:
    t = ctx.table
    half_span_ms = ctx.crowd_half_span_ms
    mid = (ctx.duration_ms // 2 // PERIOD_MS) * PERIOD_MS
    present = lambda tab, ts: int(np.count_nonzero(tab.timestamp_ms == ts))  # noqa: E731
    sources = [i for i in ctx.info.values() if i.rows >= 20 and i.track_id not in ctx.used]  # untouched tracks only
    added: list[Table] = []
    ids: list[int] = []
    count = present(t, mid)
    while count < target:
        src = sources[int(ctx.rng.integers(len(sources)))]
        dt = int(ctx.rng.integers(-40, 41)) * PERIOD_MS
        if not (src.start_ms <= mid - dt <= src.end_ms):
            continue
        copy = t.take(t.rows_of(src.track_id))
        copy.timestamp_ms = copy.timestamp_ms + dt
        copy = copy.take((np.abs(copy.timestamp_ms - mid) <= half_span_ms) & (copy.timestamp_ms >= 0) & (copy.timestamp_ms < ctx.duration_ms))
        if not np.any(copy.timestamp_ms == mid):
            continue
        angle = float(ctx.rng.uniform(-math.pi, math.pi))
        offset = float(ctx.rng.uniform(0.3, 1.0))
        copy.x += offset * math.cos(angle)
        copy.y += offset * math.sin(angle)
        copy.track_id[:] = tid = ctx.new_id()
        copy.serial = np.arange(ctx.serials(len(copy)), ctx._next_serial)
        added.append(copy)
        ids.append(tid)
        count += 1
    ctx.add(Table.concat(added))
    return ids


# Where no stage counted an oddity when this was written, the kind is the name we would expect (issue 12);
# the integration test asserts them, so those assertions fail until a stage counts one of them.
VELOCITY_INCONSISTENT = "velocity_inconsistent"
ODDITIES: dict[str, Oddity] = {o.name: o for o in (
    Oddity("vel_half", "reported velocities x 0.5", (VELOCITY_INCONSISTENT,), lambda c, a: _velocity(c, a, _scale(0.5))),
    Oddity("vel_double", "reported velocities x 2", (VELOCITY_INCONSISTENT,), lambda c, a: _velocity(c, a, _scale(2.0))),
    Oddity("vel_zero_start", "reported velocity 0 for the first second of each track",
           ("velocity_zero_while_moving", "velocity_rejected", VELOCITY_INCONSISTENT), lambda c, a: _velocity(c, a, _zero_first_second)),
    Oddity("vel_reversed", "reported velocities negated",
           (VELOCITY_INCONSISTENT, "repaired_velocity_sign_flipped"), lambda c, a: _velocity(c, a, _scale(-1.0))),
    Oddity("fast_car", "a car at 30 m/s along a real path, then straight off the map",
           ("pair_fallback_speed_above_vmax", "speed_out_of_range"), _fast_car),
    Oddity("starts_off_map", "a car starting >= 60 m off the car lanelets and driving onto them", ("off_map",), _starts_off_map),
    Oddity("wrong_way", "a car driving against the lane direction (a real track played backwards)", ("off_map_heading", "wrong_way"),
           _wrong_way),
    Oddity("teleport", "a track whose positions jump 50 m halfway", ("position_jump", "teleport"), _teleport),
    Oddity("duplicate_id", "two different cars with the same id at the same time",
           ("bad_row_duplicate_frame", "duplicate_track"), _duplicate_id),
    Oddity("id_reused", "a track id re-used 1 s after its end by another car elsewhere", ("position_jump", "id_reused"),
           _id_reused),
    Oddity("one_frame_track", "a track with one row", (), _one_frame),
    Oddity("nan_position", "x/y NaN or inf on some rows of a track", ("bad_row_non_finite_position", "bad_state"),
           _nan_fields(("x", "y"))),
    Oddity("nan_velocity", "vx/vy NaN or inf on some rows of a track", ("repaired_velocity_nan_from_positions", "bad_state"),
           _nan_fields(("vx", "vy"))),
    Oddity("nan_yaw", "psi_rad NaN or inf on some rows of a track",
           ("repaired_yaw_from_motion", "repaired_yaw_from_neighbour", "repaired_yaw_defaulted", "bad_state"), _nan_fields(("psi_rad",))),
    Oddity("nan_size", "length/width NaN or inf on some rows of a track", ("repaired_size_defaulted", "bad_state"),
           _nan_fields(("length", "width"))),
    Oddity("crowd_100", ">= 100 vehicles in one frame (offset copies of real tracks)", (), _crowd),
)}
def kinds_not_emitted(kinds) -> list[str]:
    """Those of ``kinds`` that no stage source names (a quoted ``"kind"``, or a loader reason behind
    ``bad_row_``/``repaired_``): names we expect but nothing counts yet."""
    text = "".join(p.read_text(encoding="utf-8") for p in (REPO / "stages").rglob("*.py"))
    out = []
    for kind in kinds:
        bare = kind.removeprefix("bad_row_").removeprefix("repaired_")
        if f'"{kind}"' not in text and f'"{bare}"' not in text:
            out.append(kind)
    return out


STANDALONE: dict[str, tuple[str, ...]] = {"adv_clean": (), **{f"adv_{name}": (name,) for name in ODDITIES}}
COMBINED: dict[str, tuple[str, ...]] = {
    # velocity oddities on one picked track each, the NaN fields, a one-frame track
    "combo_state": ("vel_half", "vel_double", "vel_zero_start", "vel_reversed", "nan_position", "nan_velocity", "nan_yaw",
                    "nan_size", "one_frame_track"),
    # motion oddities (each on its own track) and the crowd
    "combo_motion": ("fast_car", "starts_off_map", "wrong_way", "teleport", "duplicate_id", "id_reused", "crowd_100"),
}

# --------------------------------------------------------------------------- writing


def _read_meta(path: Path, seq: str) -> tuple[list[str], dict[str, str]]:
    with path.open(newline="", encoding="utf-8-sig") as fh:
        reader = csv.DictReader(fh)
        rows = list(reader)
        header = list(reader.fieldnames or [])
    for r in rows:
        if r["id"] == seq:
            return header, r
    raise ValueError(f"{path}: no meta row {seq}")


def load_clip(source: Path = SOURCE_DATA, start_s: float = CLIP_START_S, duration_s: float = CLIP_DURATION_S) -> Table:
    """The raw rows of sequence 013 within [start_s, start_s + duration_s), stamps restarting at 0."""
    table = read_track_file(source / "recorded_trackfiles" / SOURCE_RECORDING / f"vehicle_tracks_{SOURCE_SEQUENCE}.csv")
    lo, hi = int(round(start_s * 1000)), int(round((start_s + duration_s) * 1000))
    clip = table.take((table.timestamp_ms >= lo) & (table.timestamp_ms < hi))
    clip.timestamp_ms -= lo
    return clip


def _road_map(source: Path, meta: dict[str, str]):
    from stages.lib.maps import load_map, projection_for_location

    road_map, problems = load_map(
        source / "maps" / f"{SOURCE_RECORDING}.osm", float(meta["originLat"]), float(meta["originLon"]),
        projection_for_location(meta.get("locationId", "")),
    )
    if road_map is None:
        raise ValueError(f"K729 map unusable: {problems}")
    return road_map


@dataclass(slots=True)
class Written:
    name: str
    oddities: dict[str, list[int]] = field(default_factory=dict)
    rows: int = 0
    tracks: int = 0
    max_vehicles_per_frame: int = 0


def write_recordings(
    out_dir: str | Path,
    recordings: dict[str, tuple[str, ...]] | None = None,
    *,
    seed: int = 0,
    source: str | Path = SOURCE_DATA,
    start_s: float = CLIP_START_S,
    duration_s: float = CLIP_DURATION_S,
    crowd_half_span_s: float = 3.0,
) -> dict[str, Written]:
    """Write ``recordings`` (name -> oddity names; default ``STANDALONE``) under ``out_dir``; returns what was planted.

    A recording whose oddities are all velocity oddities applied alone (``STANDALONE``) changes every track;
    with several oddities each takes its own tracks. ``manifest.json`` records the result.
    """
    out = Path(out_dir)
    source = Path(source)
    recordings = dict(STANDALONE if recordings is None else recordings)
    unknown = sorted({o for odd in recordings.values() for o in odd} - set(ODDITIES))
    if unknown:
        raise ValueError(f"unknown oddities: {', '.join(unknown)}; known: {', '.join(ODDITIES)}")
    meta_path = source / "recorded_trackfiles" / SOURCE_RECORDING / "meta_data.csv"
    header, meta = _read_meta(meta_path, SOURCE_SEQUENCE)
    road_map = _road_map(source, meta)
    clip = load_clip(source, start_s, duration_s)
    duration_ms = int(round(duration_s * 1000))
    start = _dt.datetime.strptime(f"{meta['date']} {meta['startTime']}", "%Y-%m-%d %H:%M:%S.%f") + _dt.timedelta(seconds=start_s)
    frame_id_base = 1_000_000 + int(round(start_s * 10))
    (out / "maps").mkdir(parents=True, exist_ok=True)
    for name in ("LICENSE", "ATTRIBUTION.md"):
        shutil.copyfile(source / name, out / name)
    (out / "ADVERSARIAL.md").write_text(_NOTICE.format(seq=SOURCE_SEQUENCE, start=start_s, dur=duration_s, seed=seed))
    written: dict[str, Written] = {}
    for k, (name, oddities) in enumerate(recordings.items()):
        rng = np.random.default_rng([seed, k, *[ord(c) for c in name]])
        ctx = Context(clip.take(slice(None)), rng, road_map, duration_ms, int(round(crowd_half_span_s * 1000)))
        w = Written(name)
        for odd in oddities:
            w.oddities[odd] = [int(i) for i in ODDITIES[odd].apply(ctx, len(oddities) == 1)]
        table = ctx.table
        w.rows, w.tracks = len(table), len(table.track_ids())
        w.max_vehicles_per_frame = int(np.bincount(table.timestamp_ms // PERIOD_MS).max())
        folder = out / "recorded_trackfiles" / name
        folder.mkdir(parents=True, exist_ok=True)
        for old in folder.glob("*.csv"):
            old.unlink()
        write_track_file(folder / f"vehicle_tracks_{SOURCE_SEQUENCE}.csv", table, start, frame_id_base)
        row = {**meta, "startTime": start.strftime("%H:%M:%S.%f")[:-3], "duration": f"{duration_s:.1f}"}
        with (folder / "meta_data.csv").open("w", newline="", encoding="utf-8") as fh:
            wr = csv.DictWriter(fh, fieldnames=header, lineterminator="\n")
            wr.writeheader()
            wr.writerow(row)
        shutil.copyfile(source / "maps" / f"{SOURCE_RECORDING}.osm", out / "maps" / f"{name}.osm")
        written[name] = w
    manifest_path = out / "manifest.json"
    manifest = json.loads(manifest_path.read_text()) if manifest_path.is_file() else {}
    manifest.setdefault("recordings", {})
    manifest.update({"seed": seed, "source": f"{SOURCE_RECORDING}/{SOURCE_SEQUENCE}", "clip_start_s": start_s, "clip_duration_s": duration_s,
                     "crowd_half_span_s": crowd_half_span_s})
    for name, w in written.items():
        manifest["recordings"][name] = {
            "oddities": {o: {"tracks": ids, "expected_kinds": list(ODDITIES[o].expected_kinds),
                             "description": ODDITIES[o].description} for o, ids in w.oddities.items()},
            "rows": w.rows, "tracks": w.tracks, "max_vehicles_per_frame": w.max_vehicles_per_frame,
        }
    manifest_path.write_text(json.dumps(manifest, indent=2, sort_keys=True) + "\n")
    return written


_NOTICE = """# Adversarial recordings derived from TAF-BW (K729)

Written by `testkit/adversarial.py` (seed {seed}) from sequence {seq} of the embedded
`stages/data/taf-bw` excerpt: a {dur:.0f} s clip from {start:.0f} s, **modified on purpose**
(velocities scaled or negated, tracks moved, re-timed, duplicated, fields set to NaN/inf,
synthetic cars added; `manifest.json` says what, per recording). These files are material
derived from TAF-BW by the FZI Research Center for Information Technology and are shared
under the same licence, CC BY-NC-SA 4.0 (`LICENSE`, `ATTRIBUTION.md`): non-commercial use
only. They are test inputs, not measurements: never use them as data.
"""


# --------------------------------------------------------------------------- running and reading

PROCESSING_NODES = ("corridors", "relations", "intentions", "ar_inference", "markov_prediction")
"""The processing stages of the default pipeline (``stages/pipelines/hybrid.toml``)."""
NODES = ("source", *PROCESSING_NODES, "recorder")


@dataclass(slots=True)
class LaunchResult:
    exit_code: int
    wall_s: float
    output: str


def run_pipeline(data_dir: str | Path, recording: str, mcap: str | Path, *, run_id: str = "adv", speed: str = "max",
                 extra: tuple[str, ...] = (), timeout_s: float = 600.0, cwd: str | Path | None = None) -> LaunchResult:
    """``python launch.py --data DIR --recording NAME --speed max --no-viewer --record MCAP`` (default pipeline), to the end.

    A launcher still running after ``timeout_s`` is stopped with SIGINT (then killed) and reported as exit code 124.
    """
    import signal
    import subprocess
    import sys
    import time

    cmd = [sys.executable, str(REPO / "launch.py"), "--data", str(data_dir), "--recording", recording, "--speed", speed,
           "--no-viewer", "--record", str(mcap), "--overwrite", "--run-id", run_id, *extra]  # (a --keep folder of an earlier run)
    t0 = time.monotonic()
    proc = subprocess.Popen(cmd, cwd=str(cwd or Path(mcap).resolve().parent), stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True, start_new_session=True)
    try:
        out, _ = proc.communicate(timeout=timeout_s)
        code = proc.returncode
    except subprocess.TimeoutExpired:
        proc.send_signal(signal.SIGINT)
        try:
            out, _ = proc.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            out, _ = proc.communicate()
        code = 124
    return LaunchResult(exit_code=code, wall_s=time.monotonic() - t0, output=out or "")


@dataclass(slots=True)
class RecordingSummary:
    """What one recorded run shows: frames, grids, and each node's last ``NodeStats``."""

    track_frames: int = 0
    motion_grids: int = 0
    frames_without_grid: list[int] = field(default_factory=list)
    grids_without_frame: int = 0
    truncated: bool = False
    last_frame_index: int | None = None
    stats: dict[str, dict] = field(default_factory=dict)
    """node -> {"counters", "issues_by_kind", "errors_by_kind"} of its last NodeStats."""

    def core_errors(self) -> dict[str, int]:
        return {n: int(s["counters"].get("core_errors", 0)) for n, s in self.stats.items()}

    def issues(self) -> dict[str, dict[str, int]]:
        return {n: dict(s["issues_by_kind"]) for n, s in self.stats.items() if s["issues_by_kind"]}

    def kind_total(self, kind: str) -> int:
        return sum(int(s["issues_by_kind"].get(kind, 0)) for s in self.stats.values())

    def to_json(self) -> dict:
        return {"track_frames": self.track_frames, "motion_grids": self.motion_grids,
                "frames_without_grid": self.frames_without_grid, "grids_without_frame": self.grids_without_frame,
                "truncated": self.truncated, "last_frame_index": self.last_frame_index,
                "core_errors": self.core_errors(), "issues_by_kind": self.issues(),
                "counters": {n: s["counters"] for n, s in self.stats.items()},
                "errors_by_kind": {n: s["errors_by_kind"] for n, s in self.stats.items() if s["errors_by_kind"]}}


def summarise(mcap: str | Path, run_id: str = "adv") -> RecordingSummary:
    """Read a recording with the project's reader (``stages.recorder.inspect.read_messages``, cut files included)."""
    import bus_schemas as bs
    from stages.recorder.inspect import ReadReport, read_messages

    report = ReadReport()
    frames: list[int] = []
    grids: set[int] = set()
    out = RecordingSummary()
    prefix = f"iamp/{run_id}/"
    for m in read_messages(str(mcap), report):
        if not m.topic.startswith(prefix):
            continue
        if m.schema == bs.TrackFrame.SCHEMA:
            frames.append(bs.TrackFrame.decode(m.data).header.frame_index)
        elif m.schema == bs.MotionGrid.SCHEMA:
            grids.add(bs.MotionGrid.decode(m.data).header.frame_index)
            out.motion_grids += 1
        elif m.schema == bs.NodeStats.SCHEMA:
            st = bs.NodeStats.decode(m.data)
            out.stats[st.node_id] = {"counters": dict(st.counters), "issues_by_kind": dict(st.issues_by_kind),
                                     "errors_by_kind": dict(st.errors_by_kind)}
    out.track_frames = len(frames)
    out.frames_without_grid = sorted(set(frames) - grids)
    out.grids_without_frame = len(grids - set(frames))
    out.truncated = report.truncated
    out.last_frame_index = max(frames) if frames else None
    return out


def run_eval(data_dir: str | Path, recording: str, *, modes: tuple[str, ...] | None = None, stride_s: float | None = None) -> dict:
    """``iamp eval --data DIR --recording NAME`` in-process: {"exit_code", "skipped", "windows", "instants", "error"}.

    A crash (an exception out of the command) is exit code 1, as ``iamp`` would exit.
    """
    import contextlib
    import io
    import tempfile
    import traceback

    from stages.cli import main as iamp

    with tempfile.TemporaryDirectory() as tmp:
        out_json = Path(tmp) / "eval.json"
        argv = ["eval", "--data", str(data_dir), "--recording", recording, "--no-progress", "--json", str(out_json)]
        if modes:
            argv += ["--mode", *modes]
        if stride_s is not None:
            argv += ["--stride", str(stride_s)]
        buf = io.StringIO()
        error = ""
        try:
            with contextlib.redirect_stdout(buf), contextlib.redirect_stderr(buf):
                code = int(iamp(argv))
        except Exception as exc:  # what would be a crash of `iamp eval`
            code = 1
            error = f"{type(exc).__name__}: {exc}"
            buf.write(traceback.format_exc())
        report = json.loads(out_json.read_text()) if out_json.is_file() else {}
    windows = {m: r["overall"]["windows"] for m, r in report.get("modes", {}).items()}
    if code != 0 and not error:
        error = buf.getvalue().strip().splitlines()[-1] if buf.getvalue().strip() else ""
    return {"exit_code": code, "skipped": report.get("skipped", {}), "windows": windows, "instants": report.get("instants"),
            "error": error, "output_tail": buf.getvalue()[-3000:] if code != 0 else ""}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description="Write adversarial INTERACTION-format recordings on the K729 map.")
    p.add_argument("out", type=Path, help="output data folder (created)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--combined", action="store_true", help="write the combined recordings of the integration test instead")
    p.add_argument("--only", nargs="+", default=None, help="recording names to write")
    p.add_argument("--start", type=float, default=CLIP_START_S, help=f"clip start in s (default {CLIP_START_S:g})")
    p.add_argument("--duration", type=float, default=CLIP_DURATION_S, help=f"clip length in s (default {CLIP_DURATION_S:g})")
    p.add_argument("--crowd-half-span", type=float, default=3.0, help="crowd copies live this long either side of the middle (s)")
    args = p.parse_args(argv)
    table = COMBINED if args.combined else STANDALONE
    if args.only:
        missing = [n for n in args.only if n not in table]
        if missing:
            p.error(f"unknown recordings {missing}; known: {', '.join(table)}")
        table = {n: table[n] for n in args.only}
    for name, w in write_recordings(args.out, table, seed=args.seed, start_s=args.start, duration_s=args.duration, crowd_half_span_s=args.crowd_half_span).items():
        print(f"{name}: rows={w.rows} tracks={w.tracks} max_vehicles_per_frame={w.max_vehicles_per_frame} "
              + " ".join(f"{o}={ids[:6]}{'...' if len(ids) > 6 else ''}" for o, ids in w.oddities.items()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
