"""Reader for inD-format recordings (https://www.ind-dataset.com).

One inD recording ``XX`` is three files side by side: ``XX_tracks.csv`` (one
row per track and frame), ``XX_tracksMeta.csv`` (one row per track: class,
size, first and last frame) and ``XX_recordingMeta.csv`` (one row: frame rate,
location, speed limit, geo-reference). In our layout they live in
``recorded_trackfiles/<recording>/``; each ``XX`` there becomes one
``Sequence``. Other files (``XX_background.png`` ...) are ignored.

Conversions, by header name:

- ``xCenter``, ``yCenter`` are metres in inD's local frame, whose origin is
  (``xUtmOrigin``, ``yUtmOrigin``) in UTM; the frame is kept as is. The
  recording's origin lat/lon is ``latLocation``/``lonLocation`` (a reference
  point of the location; the exact frame origin is the UTM one, reported as
  ``Recording.utm_origin_x_m/utm_origin_y_m``).
- ``heading`` is in degrees: converted to radians in (-pi, pi].
- ``xVelocity``/``yVelocity`` m/s; ``width``/``length`` m (pedestrians have
  0: replaced by the type default and counted).
- ``frame`` is the frame index; ``stamp_ns = frame / frameRate``.
- The class comes from ``tracksMeta`` (car, truck_bus, pedestrian, bicycle);
  a track without a meta row, or of another class, is kept as UNKNOWN and
  counted as ``unknown_agent_type``.
- ``speedLimit`` is m/s in inD; a non-positive value means unknown (NaN).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path

from bus_schemas import AgentType

from stages.lib.datasets._rows import (
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
)
from stages.lib.datasets.kinematics import RepairRule
from stages.lib.datasets.model import FORMAT_IND, DatasetError, Sequence, agent_type_from_name
from stages.lib.datasets.report import KEPT, ReportBuilder

TRACKS_FILE_RE = re.compile(r"^(\d+)_tracks\.csv$")
TRACKS_REQUIRED = ("trackId", "frame", "xCenter", "yCenter")
TRACKS_META_REQUIRED = ("trackId", "class")
RECORDING_META_REQUIRED = ("frameRate", "latLocation", "lonLocation")

FORMAT = FORMAT_IND


@dataclass(frozen=True, slots=True, kw_only=True)
class RecordingMeta:
    """The one row of ``XX_recordingMeta.csv`` that we use."""

    id: str
    location_id: str
    frame_rate_hz: float
    speed_limit_mps: float
    start_time: str
    duration_s: float
    origin_lat_deg: float
    origin_lon_deg: float
    utm_origin_x_m: float
    utm_origin_y_m: float


def sequence_id_of(path: Path) -> str | None:
    """``"01"`` for ``01_tracks.csv``; None for other files."""
    m = TRACKS_FILE_RE.match(path.name)
    return m.group(1) if m else None


def companion_files(tracks_path: Path) -> tuple[Path, Path]:
    """(tracksMeta, recordingMeta) paths beside ``XX_tracks.csv``."""
    seq = sequence_id_of(tracks_path)
    return tracks_path.with_name(f"{seq}_tracksMeta.csv"), tracks_path.with_name(f"{seq}_recordingMeta.csv")


def read_recording_meta(path: Path) -> RecordingMeta:
    if not path.is_file():
        raise DatasetError(f"{path}: recordingMeta is missing; it gives the frame rate and the origin")
    with path.open(newline="", encoding="utf-8-sig") as handle:
        table = open_table(path, RECORDING_META_REQUIRED, handle)
        cols = table.columns
        for line, fields in table.rows:
            try:
                rate = field_float(fields, cols, "frameRate")
                lat = field_float(fields, cols, "latLocation")
                lon = field_float(fields, cols, "lonLocation")
            except BadRow as exc:
                raise DatasetError(f"{path}:{line}: {exc.detail} (origin and frame rate are required)") from None
            if not (math.isfinite(rate) and rate > 0):
                raise DatasetError(f"{path}:{line}: frameRate={rate} must be > 0")
            if not (math.isfinite(lat) and math.isfinite(lon) and -90 <= lat <= 90 and -180 <= lon <= 180):
                raise DatasetError(f"{path}:{line}: origin lat={lat} lon={lon} is not a geodetic position")
            speed = optional_float(fields, cols, "speedLimit")
            weekday = optional_text(fields, cols, "weekday")
            start = optional_text(fields, cols, "startTime")
            if start and re.fullmatch(r"\d+(\.0+)?", start):
                start = f"{int(float(start)):02d}:00"
            return RecordingMeta(
                id=optional_text(fields, cols, "recordingId") or sequence_id_of_meta(path),
                location_id=optional_text(fields, cols, "locationId"),
                frame_rate_hz=rate,
                speed_limit_mps=speed if speed > 0 else math.nan,
                start_time=" ".join(p for p in (weekday, start) if p),
                duration_s=optional_float(fields, cols, "duration"),
                origin_lat_deg=lat,
                origin_lon_deg=lon,
                utm_origin_x_m=optional_float(fields, cols, "xUtmOrigin"),
                utm_origin_y_m=optional_float(fields, cols, "yUtmOrigin"),
            )
    raise DatasetError(f"{path}: no data row")


def sequence_id_of_meta(path: Path) -> str:
    return path.name.split("_", 1)[0]


def read_tracks_meta(path: Path) -> dict[int, str]:
    """Class name of each track id in ``XX_tracksMeta.csv``."""
    if not path.is_file():
        raise DatasetError(f"{path}: tracksMeta is missing; it gives each track's class")
    out: dict[int, str] = {}
    with path.open(newline="", encoding="utf-8-sig") as handle:
        table = open_table(path, TRACKS_META_REQUIRED, handle)
        for _line, fields in table.rows:
            try:
                out[field_int(fields, table.columns, "trackId")] = field_text(fields, table.columns, "class")
            except BadRow:
                continue  # its rows then show up as unknown_agent_type
    return out


def read_sequence(tracks_path: Path, rule: RepairRule, display_root: Path | None = None) -> tuple[Sequence, RecordingMeta]:
    """Read one inD recording ``XX`` into a ``Sequence`` (plus its recording meta)."""
    tracks_meta_path, recording_meta_path = companion_files(tracks_path)
    meta = read_recording_meta(recording_meta_path)
    classes = read_tracks_meta(tracks_meta_path)
    report = ReportBuilder()
    buffer = RowBuffer(report)
    shown = display_path(tracks_path, display_root)
    with tracks_path.open(newline="", encoding="utf-8-sig") as handle:
        table = open_table(tracks_path, TRACKS_REQUIRED, handle)
        cols = table.columns
        for line, fields in table.rows:
            report.rows_read += 1
            try:
                track_id = field_int(fields, cols, "trackId")
                frame = field_int(fields, cols, "frame")
                x = field_float(fields, cols, "xCenter")
                y = field_float(fields, cols, "yCenter")
                vx = measured_float(fields, cols, "xVelocity")  # empty: derived from the positions, like NaN
                vy = measured_float(fields, cols, "yVelocity")
                heading_deg = measured_float(fields, cols, "heading")
                length = measured_float(fields, cols, "length")  # empty: the type's default size
                width = measured_float(fields, cols, "width")
            except BadRow as exc:
                report.skip(exc.reason, shown, line, exc.detail)
                continue
            class_name = classes.get(track_id)
            agent_type = agent_type_from_name(class_name) if class_name is not None else AgentType.UNKNOWN
            kept = buffer.append(
                file=shown,
                line=line,
                track_id=track_id,
                frame_index=frame,
                stamp_ns=int(round(frame * 1e9 / meta.frame_rate_hz)) if abs(frame) < 1e15 else 2**63,  # (too far: skipped)
                agent_type=agent_type,
                x_m=x,
                y_m=y,
                vx_mps=vx,
                vy_mps=vy,
                yaw_rad=_wrap(math.radians(heading_deg)) if math.isfinite(heading_deg) else math.nan,
                length_m=length,
                width_m=width,
            )
            if kept and agent_type is AgentType.UNKNOWN:
                why = f"class={class_name!r}" if class_name is not None else "no row in tracksMeta"
                report.add(UNKNOWN_AGENT_TYPE, KEPT, shown, line, f"track {track_id}: {why}, kept as UNKNOWN")
    if len(buffer) == 0:
        raise no_usable_row(tracks_path, report, {})
    arrays = buffer.finish(rule)
    report.rows_kept = len(buffer)
    seq = Sequence(
        id=sequence_id_of(tracks_path) or meta.id,
        start_time=meta.start_time,
        duration_s=meta.duration_s,
        frame_rate_hz=meta.frame_rate_hz,
        origin_lat_deg=meta.origin_lat_deg,
        origin_lon_deg=meta.origin_lon_deg,
        source_files=(tracks_path,),
        report=report.build(),
        **arrays,
    )
    return seq, meta


def _wrap(angle_rad: float) -> float:
    """Angle in (-pi, pi]."""
    wrapped = math.remainder(angle_rad, 2.0 * math.pi)
    return math.pi if wrapped == -math.pi else wrapped
