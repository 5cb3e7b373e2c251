"""Readers for a recording's signal side: the signal-phase CSV and the KML lane file.

TAF-BW layout, beside the tracks of a recording folder:

- ``signal_phases_NNN.csv``: one row per signal group and time,
  ``signal_group_id, timestamp_ms, movement_state`` (J2735 names:
  ``STOP_AND_REMAIN``, ``PRE_MOVEMENT``, ``PERMISSIVE_MOVEMENT_ALLOWED``,
  ``PERMISSIVE_CLEARANCE``, ``DARK``), ``timestamp_ms`` on the tracks' clock
  (0 at the recording's start). Read by header name.
- ``*.kml``: a MAP-style lane file: one ``Placemark`` per lane with a WGS84
  ``LineString`` (lon, lat, alt) that starts at the lane's stop line, and
  ``ExtendedData`` ``Source`` (lane id), ``Sink`` (connected lane ids) and
  ``SignalGroup`` (the group of each connection, same order; empty for an
  unsignalised lane); a ``RefPoint`` Point. Read by element name (any
  namespace).

Meaning of the rows: a row's state holds from its time until the group's next
row; the group's last row holds until the last time of the file, after which
the state is unknown. A file of 100 ms samples and one that keeps only each
group's first row, its changes and its last row therefore give the same
states at every time. Bad rows are skipped and counted in a ``LoadReport``
(file, line), as for track rows; an unknown state name is kept as
``SignalPhase.UNKNOWN`` and counted.
"""

from __future__ import annotations

import math
import re
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from bus_schemas.signals import J2735_NAMES, SignalPhase

from stages.lib.datasets._rows import (
    MISSING_FIELD,
    NON_NUMERIC,
    TIME_BACKWARDS,
    DUPLICATE_FRAME,
    BadRow,
    display_path,
    field_int,
    field_text,
    open_table,
)
from stages.lib.datasets.model import DatasetError
from stages.lib.datasets.report import KEPT, SKIPPED, LoadReport, ReportBuilder

SIGNAL_FILE_RE = re.compile(r"^signal_phases_(\d+)\.csv$")
SIGNAL_REQUIRED = ("signal_group_id", "timestamp_ms", "movement_state")
# reasons
UNKNOWN_MOVEMENT_STATE = "unknown_movement_state"
BAD_LANE = "bad_lane"
BAD_CONNECTION = "bad_connection"


_RECORDING_NAME_RE = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]{0,199}")
MAX_LANE_FILE_BYTES = 16 * 1024 * 1024


def lane_file_for(data_dir: Path, recording: str) -> Path | None:
    """The one ``*.kml`` lane file of ``<data_dir>/recorded_trackfiles/<recording>/``, or None.

    ``recording`` comes from the bus (``SceneInfo.recording``): only a plain
    folder name is looked up (no path, no ``..``), inside the stage's own
    data folder, and a file over ``MAX_LANE_FILE_BYTES`` is not read.
    """
    if not isinstance(recording, str) or not _RECORDING_NAME_RE.fullmatch(recording) or ".." in recording:
        return None
    folder = Path(data_dir) / "recorded_trackfiles" / recording
    if not folder.is_dir():
        return None
    files = [p for p in sorted(folder.iterdir()) if p.is_file() and is_lane_file(p)]
    if len(files) != 1 or files[0].stat().st_size > MAX_LANE_FILE_BYTES:
        return None
    return files[0]


def is_signal_file(path: Path) -> bool:
    return SIGNAL_FILE_RE.match(path.name) is not None


def is_lane_file(path: Path) -> bool:
    return path.suffix.lower() == ".kml"


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class SignalPhases:
    """Every group's phase over time: per group, row times (ms, increasing) and phases (``SignalPhase`` values).

    ``end_ms`` is the last time of the file(s): after it every state is unknown.
    """

    group_ids: tuple[int, ...]
    times_ms: dict[int, np.ndarray]
    phases: dict[int, np.ndarray]
    end_ms: int
    run_start_ms: dict[int, np.ndarray] = field(default_factory=dict)  # per row: when its phase began (-1: before the first row)
    source_files: tuple[Path, ...] = ()
    report: LoadReport = field(default_factory=LoadReport)

    def state(self, group_id: int, stamp_ns: int) -> tuple[SignalPhase, float]:
        """(phase, held_s) of one group at ``stamp_ns``; (UNKNOWN, NaN) outside the file or for an unknown group.

        ``held_s`` is the time since the group's phase began, NaN when it
        began before the group's first row.
        """
        t = self.times_ms.get(int(group_id))
        if t is None or t.size == 0:
            return SignalPhase.UNKNOWN, math.nan
        ms = stamp_ns / 1e6
        if ms < t[0] or ms > self.end_ms:
            return SignalPhase.UNKNOWN, math.nan
        i = int(np.searchsorted(t, ms, side="right")) - 1
        start = int(self.run_start_ms[int(group_id)][i])
        held = (ms - start) / 1e3 if start >= 0 else math.nan
        return SignalPhase(int(self.phases[int(group_id)][i])), held

    def states(self, stamp_ns: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(group_ids int64, phases uint8, held_s float64) of every group at ``stamp_ns``."""
        ids = np.array(self.group_ids, dtype=np.int64)
        phases = np.zeros(ids.shape, dtype=np.uint8)
        held = np.full(ids.shape, np.nan)
        for k, g in enumerate(self.group_ids):
            ph, h = self.state(g, stamp_ns)
            phases[k], held[k] = int(ph), h
        return ids, phases, held

    def changes(self, group_id: int) -> list[tuple[int, SignalPhase]]:
        """(time_ms, phase) where the group's phase changes, its first row included."""
        t, p = self.times_ms[int(group_id)], self.phases[int(group_id)]
        keep = np.concatenate(([True], p[1:] != p[:-1]))
        return [(int(a), SignalPhase(int(b))) for a, b in zip(t[keep], p[keep])]


def read_signal_phases(paths: list[Path] | tuple[Path, ...], display_root: Path | None = None) -> SignalPhases:
    """Read one or more signal-phase CSV files (by header name) into ``SignalPhases``.

    Rows missing a value or with a non-integer group or time are skipped; a
    repeated (group, time) is skipped (``duplicate_frame``), a time earlier
    than the group's previous row is skipped (``time_backwards``); an unknown
    state name is kept as UNKNOWN (``unknown_movement_state``). A file with no
    usable row raises ``DatasetError``.
    """
    builder = ReportBuilder()
    rows: dict[int, list[tuple[int, int]]] = {}
    end_ms = -1
    for path in paths:
        shown = display_path(path, display_root)
        used = 0
        with path.open(newline="", encoding="utf-8-sig") as handle:
            table = open_table(path, SIGNAL_REQUIRED, handle)
            cols = table.columns
            for line, fields in table.rows:
                builder.rows_read += 1
                try:
                    group = field_int(fields, cols, "signal_group_id")
                    t_ms = field_int(fields, cols, "timestamp_ms")
                    name = field_text(fields, cols, "movement_state")
                    if group < 0:
                        raise BadRow(NON_NUMERIC, f"signal_group_id={group} is negative")
                except BadRow as bad:
                    builder.skip(bad.reason, shown, line, bad.detail)
                    continue
                phase = J2735_NAMES.get(name.strip().upper())
                if phase is None:
                    builder.add(UNKNOWN_MOVEMENT_STATE, KEPT, shown, line, f"movement_state={name!r}: kept as unknown")
                    phase = SignalPhase.UNKNOWN
                seq = rows.setdefault(group, [])
                if seq and t_ms == seq[-1][0]:
                    builder.skip(DUPLICATE_FRAME, shown, line, f"group {group} repeats timestamp_ms {t_ms}")
                    continue
                if seq and t_ms < seq[-1][0]:
                    builder.skip(TIME_BACKWARDS, shown, line, f"group {group}: timestamp_ms {t_ms} < {seq[-1][0]}")
                    continue
                seq.append((t_ms, int(phase)))
                builder.rows_kept += 1
                used += 1
                end_ms = max(end_ms, t_ms)
        if used == 0:
            raise DatasetError(f"{path}: no usable signal-phase row ({builder.build().summary()})")
    groups = tuple(sorted(rows))
    return SignalPhases(
        run_start_ms={g: _run_starts(rows[g]) for g in groups},
        group_ids=groups,
        times_ms={g: np.array([r[0] for r in rows[g]], dtype=np.int64) for g in groups},
        phases={g: np.array([r[1] for r in rows[g]], dtype=np.uint8) for g in groups},
        end_ms=int(end_ms),
        source_files=tuple(paths),
        report=builder.build(),
    )


def _run_starts(rows: list[tuple[int, int]]) -> np.ndarray:
    out = np.empty(len(rows), dtype=np.int64)
    start = -1
    for i, (t_ms, phase) in enumerate(rows):
        if i > 0 and phase != rows[i - 1][1]:
            start = t_ms
        out[i] = start
    return out


@dataclass(frozen=True, slots=True, kw_only=True)
class KmlConnection:
    """A lane's connection to a sink lane, with the signal group that controls it (None: unsignalised)."""

    sink_lane: int
    signal_group: int | None


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class KmlLane:
    """One lane of the lane file: id, WGS84 polyline (lat, lon in degrees; first point at the stop line), connections."""

    lane_id: int
    name: str
    lat_deg: np.ndarray
    lon_deg: np.ndarray
    connections: tuple[KmlConnection, ...]
    line: int = 0

    @property
    def signal_groups(self) -> tuple[int, ...]:
        return tuple(sorted({c.signal_group for c in self.connections if c.signal_group is not None}))

    @property
    def is_ingress(self) -> bool:
        """A lane with connections (it leads into the junction)."""
        return bool(self.connections)


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class KmlLanes:
    """The lanes of a lane file, by id, and its reference point (NaN when absent)."""

    lanes: tuple[KmlLane, ...]
    ref_lat_deg: float
    ref_lon_deg: float
    source_file: Path
    report: LoadReport = field(default_factory=LoadReport)

    def lane(self, lane_id: int) -> KmlLane | None:
        return next((l for l in self.lanes if l.lane_id == lane_id), None)


def _local(tag: str) -> str:
    return tag.rsplit("}", 1)[-1]


def _child(el: ET.Element, name: str) -> ET.Element | None:
    return next((c for c in el.iter() if _local(c.tag) == name), None)


def _int_list(text: str) -> list[int]:
    parts = [p.strip() for p in (text or "").replace(";", ",").split(",")]
    return [int(p) for p in parts if p]


def read_kml_lanes(path: Path, display_root: Path | None = None) -> KmlLanes:
    """Read a KML lane file by element name; a lane that cannot be used is skipped and counted (``bad_lane``).

    A ``Sink`` and ``SignalGroup`` list of different lengths keeps the
    connections without groups (``bad_connection``, kept). An unreadable XML
    file raises ``DatasetError``.
    """
    shown = display_path(path, display_root)
    text = path.read_text(encoding="utf-8-sig")
    try:
        root = ET.fromstring(text)
    except ET.ParseError as exc:
        raise DatasetError(f"{path}: unreadable KML: {exc}") from None
    # ElementTree keeps no line numbers: the n-th <Placemark start tag is the n-th Placemark element
    starts = [text.count("\n", 0, m.start()) + 1 for m in re.finditer(r"<(?:\w+:)?Placemark[\s>]", text)]
    builder = ReportBuilder()
    lanes: list[KmlLane] = []
    ref_lat = ref_lon = math.nan
    for n, pm in enumerate(el for el in root.iter() if _local(el.tag) == "Placemark"):
        line = starts[n] if n < len(starts) else 0
        name_el = _child(pm, "name")
        name = (name_el.text or "").strip() if name_el is not None else ""
        point = next((c for c in pm if _local(c.tag) == "Point"), None)
        if point is not None:
            coords = _child(point, "coordinates")
            try:
                lon, lat = [float(v) for v in (coords.text or "").strip().split(",")[:2]]
                if name.lower() == "refpoint":
                    ref_lat, ref_lon = lat, lon
            except (AttributeError, ValueError):
                builder.add(BAD_LANE, SKIPPED, shown, line, f"placemark {name!r}: unreadable point")
            continue
        builder.rows_read += 1
        ls = _child(pm, "LineString")
        coords = _child(ls, "coordinates") if ls is not None else None
        data = {(d.get("name") or "").strip(): (_child(d, "value").text if _child(d, "value") is not None else "") or ""
                for d in pm.iter() if _local(d.tag) == "Data"}
        try:
            if coords is None:
                raise ValueError("no LineString coordinates")
            pts = [tuple(float(v) for v in tok.split(",")[:2]) for tok in (coords.text or "").split()]
            if len(pts) < 2 or any(len(p) != 2 or not all(map(math.isfinite, p)) for p in pts):
                raise ValueError(f"{len(pts)} usable points, need 2 or more")
            if "Source" not in data:
                raise ValueError("no Source")
            lane_id = int(data["Source"].strip())
            sinks = _int_list(data.get("Sink", ""))
            groups = _int_list(data.get("SignalGroup", ""))
        except ValueError as exc:
            builder.add(BAD_LANE, SKIPPED, shown, line, f"placemark {name!r}: {exc}")
            continue
        if groups and len(groups) != len(sinks):
            builder.add(BAD_CONNECTION, KEPT, shown, line, f"lane {lane_id}: {len(sinks)} sinks but {len(groups)} signal groups: groups dropped")
            groups = []
        conns = tuple(KmlConnection(sink_lane=s, signal_group=(groups[i] if groups else None)) for i, s in enumerate(sinks))
        pts_a = np.array(pts, dtype=np.float64)
        lanes.append(KmlLane(lane_id=lane_id, name=name, lon_deg=pts_a[:, 0], lat_deg=pts_a[:, 1], connections=conns, line=line))
        builder.rows_kept += 1
    lanes = _near_lanes(lanes, builder, shown)
    if not lanes:
        raise DatasetError(f"{path}: no usable lane (Placemark with a LineString and a Source) ({builder.build().summary()})")
    return KmlLanes(lanes=tuple(lanes), ref_lat_deg=ref_lat, ref_lon_deg=ref_lon, source_file=path, report=builder.build())


# A lane file describes one junction: a lane with a point farther than this from the median of all the file's points
# is a typo (a latitude of 89.9 for 49.0, a digit lost), counted as a bad lane. Kept, such a lane of thousands of km
# was resampled every metre and matched against the whole map: `iamp signals` ran for minutes into gigabytes.
MAX_LANE_DISTANCE_M = 5000.0
_M_PER_DEG = 111_320.0


def _near_lanes(lanes: list[KmlLane], builder: ReportBuilder, shown: str) -> list[KmlLane]:
    """The lanes whose every point lies within ``MAX_LANE_DISTANCE_M`` of the median of the file's points (and on
    the globe); the others counted as ``bad_lane``."""
    if not lanes:
        return lanes
    lat0 = float(np.median(np.concatenate([l.lat_deg for l in lanes])))
    lon0 = float(np.median(np.concatenate([l.lon_deg for l in lanes])))
    kept = []
    for lane in lanes:
        on_globe = bool(np.all(np.abs(lane.lat_deg) <= 90.0) and np.all(np.abs(lane.lon_deg) <= 180.0))
        dist = np.hypot((lane.lat_deg - lat0) * _M_PER_DEG, (lane.lon_deg - lon0) * _M_PER_DEG * math.cos(math.radians(lat0))) if on_globe else None
        if dist is not None and float(dist.max()) <= MAX_LANE_DISTANCE_M:
            kept.append(lane)
            continue
        where = "a point off the globe" if dist is None else f"a point {float(dist.max()) / 1000:.0f} km from the file's other lanes"
        builder.add(BAD_LANE, SKIPPED, shown, lane.line, f"lane {lane.lane_id} ({lane.name!r}): {where} (a coordinate typo?)")
        builder.rows_kept -= 1
    return kept


__all__ = [
    "BAD_CONNECTION",
    "BAD_LANE",
    "KmlConnection",
    "KmlLane",
    "KmlLanes",
    "SignalPhases",
    "UNKNOWN_MOVEMENT_STATE",
    "is_lane_file",
    "lane_file_for",
    "is_signal_file",
    "read_kml_lanes",
    "read_signal_phases",
]
