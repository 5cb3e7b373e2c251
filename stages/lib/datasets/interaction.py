"""Reader for INTERACTION-format recordings (TAF-BW is one).

Layout of a recording folder ``recorded_trackfiles/<recording>/``:
``meta_data.csv`` (one row per sequence) and ``vehicle_tracks_NNN.csv`` /
``pedestrian_tracks_NNN.csv`` (one sequence NNN may have both; they are read
into one ``Sequence``).

Quirks handled here, all by header name, never by position:

- Column order differs between recordings (k729 puts x, y last and adds a
  ``time`` column, which is not used).
- ``frame_id`` is global and inconsistent in TAF-BW, so the frame within the
  sequence is ``round(timestamp_ms * frameRate_hz / 1000)``; ``frame_id`` is
  optional and not read. ``timestamp_ms`` restarts at 0 in each sequence.
- Track ids are integers; INTERACTION pedestrian files use ``P<n>``, read as
  ``PREFIXED_TRACK_ID_OFFSET + n`` so they never collide with vehicle ids.
- ``vx``, ``vy``, ``psi_rad``, ``length``, ``width`` are optional columns
  (INTERACTION pedestrian files lack the last three): a missing value is
  derived from the positions or defaulted, and counted.
- ``meta_data.csv`` gives per sequence: ``frameRate_hz``, ``locationId``,
  ``speedLimit_kmh``, ``date``, ``startTime``, ``timeZone``, ``duration``,
  ``originLat``, ``originLon`` (x east, y north in metres from that origin).
  The meta file and each sequence's origin and frame rate are required.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path

from bus_schemas import AgentType

from stages.lib.datasets._rows import (
    NON_NUMERIC,
    UNKNOWN_AGENT_TYPE,
    BadRow,
    RowBuffer,
    display_path,
    field_float,
    measured_float,
    field_int,
    field_text,
    no_usable_row,
    open_table,
    optional_float,
    optional_text,
    skip_counts,
)
from stages.lib.datasets.kinematics import RepairRule
from stages.lib.datasets.model import FORMAT_INTERACTION, DatasetError, Sequence, agent_type_from_name
from stages.lib.datasets.report import KEPT, ReportBuilder

TRACK_FILE_RE = re.compile(r"^(vehicle|pedestrian)_tracks_(\d+)\.csv$")
META_FILE = "meta_data.csv"
PREFIXED_TRACK_ID_OFFSET = 1_000_000_000
"""Added to the number of a prefixed track id (``P12`` -> 1_000_000_012)."""

TRACK_REQUIRED = ("track_id", "timestamp_ms", "agent_type", "x", "y")
META_REQUIRED = ("id", "frameRate_hz", "originLat", "originLon")

FORMAT = FORMAT_INTERACTION


@dataclass(frozen=True, slots=True, kw_only=True)
class SequenceMeta:
    """One row of ``meta_data.csv``."""

    id: str
    frame_rate_hz: float
    location_id: str
    speed_limit_mps: float
    start_time: str
    duration_s: float
    origin_lat_deg: float
    origin_lon_deg: float


def sequence_id_of(path: Path) -> str | None:
    """``"013"`` for ``vehicle_tracks_013.csv``; None for other files."""
    m = TRACK_FILE_RE.match(path.name)
    return m.group(2) if m else None


def read_meta(path: Path) -> dict[str, SequenceMeta]:
    """Rows of ``meta_data.csv`` by sequence id; ``DatasetError`` when missing or unusable."""
    if not path.is_file():
        raise DatasetError(f"{path}: meta_data.csv is missing; it gives each sequence's frame rate and origin")
    out: dict[str, SequenceMeta] = {}
    with path.open(newline="", encoding="utf-8-sig") as handle:
        table = open_table(path, META_REQUIRED, handle)
        cols = table.columns
        for line, fields in table.rows:
            try:
                seq_id = field_text(fields, cols, "id")
                lat = _meta_float(fields, cols, "originLat")
                lon = _meta_float(fields, cols, "originLon")
                rate = _meta_float(fields, cols, "frameRate_hz")
            except BadRow as exc:
                raise DatasetError(f"{path}:{line}: {exc.detail} (origin and frame rate are required)") from None
            if not (-90 <= lat <= 90 and -180 <= lon <= 180):
                raise DatasetError(f"{path}:{line}: origin lat={lat} lon={lon} is not a geodetic position")
            if not rate > 0:
                raise DatasetError(f"{path}:{line}: frameRate_hz={rate} must be > 0")
            speed_kmh = optional_float(fields, cols, "speedLimit_kmh")
            out[seq_id] = SequenceMeta(
                id=seq_id,
                frame_rate_hz=rate,
                location_id=optional_text(fields, cols, "locationId"),
                speed_limit_mps=speed_kmh / 3.6 if speed_kmh > 0 else math.nan,
                start_time=_start_time(
                    optional_text(fields, cols, "date"),
                    optional_text(fields, cols, "startTime"),
                    optional_text(fields, cols, "timeZone"),
                ),
                duration_s=optional_float(fields, cols, "duration"),
                origin_lat_deg=lat,
                origin_lon_deg=lon,
            )
    if not out:
        raise DatasetError(f"{path}: no sequence rows")
    return out


def meta_for(metas: dict[str, SequenceMeta], seq_id: str, meta_path: Path) -> SequenceMeta:
    """The meta row of ``seq_id`` (also matching ``13`` to ``013``)."""
    if seq_id in metas:
        return metas[seq_id]
    for key, meta in metas.items():
        if key.isdigit() and seq_id.isdigit() and int(key) == int(seq_id):
            return meta
    raise DatasetError(f"{meta_path}: no row for sequence {seq_id}, so its origin is unknown")


def read_sequence(files: list[Path], meta: SequenceMeta, rule: RepairRule, display_root: Path | None = None) -> Sequence:
    """Read the track files of one sequence into a ``Sequence``.

    Raises ``DatasetError`` naming the file when a file lacks a required
    column or has no usable row.
    """
    report = ReportBuilder()
    buffer = RowBuffer(report)
    period_ms = 1000.0 / meta.frame_rate_hz
    for path in files:
        shown = display_path(path, display_root)
        kept_before = len(buffer)
        skipped_before = skip_counts(report)
        with path.open(newline="", encoding="utf-8-sig") as handle:
            table = open_table(path, TRACK_REQUIRED, handle)
            cols = table.columns
            for line, fields in table.rows:
                report.rows_read += 1
                try:
                    track_id = _track_id(field_text(fields, cols, "track_id"))
                    stamp_ms = field_int(fields, cols, "timestamp_ms")
                    type_name = field_text(fields, cols, "agent_type")
                    x = field_float(fields, cols, "x")
                    y = field_float(fields, cols, "y")
                    vx = measured_float(fields, cols, "vx")  # empty: derived from the positions, like NaN
                    vy = measured_float(fields, cols, "vy")
                    yaw = measured_float(fields, cols, "psi_rad")
                    length = measured_float(fields, cols, "length")  # empty: the type's default size
                    width = measured_float(fields, cols, "width")
                except BadRow as exc:
                    report.skip(exc.reason, shown, line, exc.detail)
                    continue
                agent_type = agent_type_from_name(type_name)
                kept = buffer.append(
                    file=shown,
                    line=line,
                    track_id=track_id,
                    frame_index=int(round(stamp_ms / period_ms)),
                    stamp_ns=stamp_ms * 1_000_000,
                    agent_type=agent_type,
                    x_m=x,
                    y_m=y,
                    vx_mps=vx,
                    vy_mps=vy,
                    yaw_rad=yaw,
                    length_m=length,
                    width_m=width,
                )
                if kept and agent_type is AgentType.UNKNOWN:
                    detail = f"track {track_id}: agent_type={type_name!r} kept as UNKNOWN"
                    report.add(UNKNOWN_AGENT_TYPE, KEPT, shown, line, detail)
        if len(buffer) == kept_before:
            raise no_usable_row(path, report, skipped_before)
    arrays = buffer.finish(rule)
    report.rows_kept = len(buffer)
    return Sequence(
        id=meta.id,
        start_time=meta.start_time,
        duration_s=meta.duration_s,
        frame_rate_hz=meta.frame_rate_hz,
        origin_lat_deg=meta.origin_lat_deg,
        origin_lon_deg=meta.origin_lon_deg,
        source_files=tuple(files),
        report=report.build(),
        **arrays,
    )


# --------------------------------------------------------------------------- helpers


def _track_id(text: str) -> int:
    try:
        return int(text)
    except ValueError:
        pass
    m = re.fullmatch(r"([A-Za-z]+)(\d+)", text)
    if m:
        return PREFIXED_TRACK_ID_OFFSET + int(m.group(2))
    raise BadRow(NON_NUMERIC, f"track_id={text!r} is neither an integer nor like P12")


def _meta_float(fields: list[str], cols: dict[str, int], name: str) -> float:
    value = field_float(fields, cols, name)
    if not math.isfinite(value):
        raise BadRow(NON_NUMERIC, f"{name}={value} is not a finite number")
    return value


def _start_time(date: str, time_of_day: str, zone: str) -> str:
    """ISO 8601 local time with offset (``2022-03-16T11:30:01.698+01:00``) where parseable."""
    m = re.fullmatch(r"(\d{1,2}):(\d{1,2}):(\d{1,2}(?:\.\d+)?)", time_of_day)
    d = re.fullmatch(r"\d{4}-\d{2}-\d{2}", date)
    if not (m and d):
        return " ".join(p for p in (date, time_of_day, zone) if p)
    h, mi, s = int(m.group(1)), int(m.group(2)), float(m.group(3))
    out = f"{date}T{h:02d}:{mi:02d}:{s:06.3f}"
    z = re.fullmatch(r"(?:GMT|UTC)\s*([+-])(\d{1,2})(?::?(\d{2}))?", zone.strip())
    if z:
        out += f"{z.group(1)}{int(z.group(2)):02d}:{int(z.group(3) or 0):02d}"
    return out
