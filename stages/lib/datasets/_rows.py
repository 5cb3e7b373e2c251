"""Row checks and array building shared by the format readers.

A format reader parses its CSV by header name and hands every row that has
usable values to ``RowBuffer.append`` in file order. The buffer skips
duplicated (track, frame) rows and rows whose time goes backwards within a
track; ``RowBuffer.finish`` then fills in default sizes, derives kinematics
per track, takes the sequence-level decisions (``velocity_sign_inverted``,
``yaw_modulo_pi``), repairs each track (``kinematics.repair_track``), counts
every change in the report and returns the arrays sorted by
(frame_index, track_id).
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np

from bus_schemas import AgentType

from stages.lib.datasets.kinematics import RepairRule, derive_kinematics, repair_track, velocity_sign_inverted, yaw_modulo_pi
from stages.lib.datasets.model import DEFAULT_SIZES_M, DatasetError
from stages.lib.datasets.report import REPAIRED, ReportBuilder

# reasons a row is skipped
MISSING_FIELD = "missing_field"
NON_NUMERIC = "non_numeric"
NON_FINITE_POSITION = "non_finite_position"
DUPLICATE_FRAME = "duplicate_frame"
TIME_BACKWARDS = "time_backwards"
TIME_OUT_OF_RANGE = "time_out_of_range"
# reason a row is kept but flagged
UNKNOWN_AGENT_TYPE = "unknown_agent_type"
# repairs
VELOCITY_SIGN_FLIPPED = "velocity_sign_flipped"
YAW_FLIPPED = "yaw_flipped"
VELOCITY_NAN = "velocity_nan_from_positions"
START_VELOCITY = "start_velocity_from_positions"
YAW_FROM_MOTION = "yaw_from_motion"
YAW_FROM_NEIGHBOUR = "yaw_from_neighbour"
YAW_DEFAULTED = "yaw_defaulted"
SIZE_DEFAULTED = "size_defaulted"

# the largest |time| a row may have: int64 nanoseconds, with room for the sums of later steps (about 146 years)
MAX_STAMP_NS = 2**62

SKIP_REASONS = (MISSING_FIELD, NON_NUMERIC, NON_FINITE_POSITION, DUPLICATE_FRAME, TIME_BACKWARDS, TIME_OUT_OF_RANGE)
REPAIR_REASONS = (
    VELOCITY_SIGN_FLIPPED,
    YAW_FLIPPED,
    VELOCITY_NAN,
    START_VELOCITY,
    YAW_FROM_MOTION,
    YAW_FROM_NEIGHBOUR,
    YAW_DEFAULTED,
    SIZE_DEFAULTED,
)


class BadRow(Exception):
    """Raised by the field parsers; caught per row and counted as ``reason``."""

    def __init__(self, reason: str, detail: str) -> None:
        super().__init__(detail)
        self.reason = reason
        self.detail = detail


@dataclass(frozen=True, slots=True)
class CsvTable:
    """A CSV file opened for reading by header name."""

    path: Path
    columns: dict[str, int]
    rows: Iterator[tuple[int, list[str]]]


def open_table(path: Path, required: tuple[str, ...], handle) -> CsvTable:
    """Read the header of ``path`` (an open text ``handle``) and check ``required`` columns.

    Column names are stripped of blanks and a byte-order mark. Yields
    ``(line, fields)`` with the 1-based physical line number; blank lines
    are passed over.
    """
    reader = csv.reader(handle)
    try:
        header = next(reader)
    except StopIteration:
        raise DatasetError(f"{path}: empty file, expected a header row") from None
    except csv.Error as exc:
        raise DatasetError(f"{path}: unreadable CSV header: {exc}") from None
    columns: dict[str, int] = {}
    for i, name in enumerate(header):
        name = name.strip().lstrip("\ufeff").strip()
        if name and name not in columns:
            columns[name] = i
    missing = [c for c in required if c not in columns]
    if missing:
        raise DatasetError(
            f"{path}: missing column(s) {', '.join(missing)}; the header has: {', '.join(columns) or '(nothing)'}"
        )

    def rows() -> Iterator[tuple[int, list[str]]]:
        line = reader.line_num
        while True:
            try:
                fields = next(reader)
            except StopIteration:
                return
            except csv.Error as exc:
                raise DatasetError(f"{path}:{reader.line_num}: unreadable CSV: {exc}") from None
            line = reader.line_num
            if not fields or all(not f.strip() for f in fields):
                continue
            yield line, fields

    return CsvTable(path=path, columns=columns, rows=rows())


def field_text(fields: list[str], columns: dict[str, int], name: str) -> str:
    """The stripped text of column ``name``; ``BadRow(missing_field)`` if absent or empty."""
    i = columns[name]
    text = fields[i].strip() if i < len(fields) else ""
    if not text:
        raise BadRow(MISSING_FIELD, f"no value for {name}")
    return text


def field_float(fields: list[str], columns: dict[str, int], name: str) -> float:
    """Column ``name`` as float (NaN/inf allowed); NaN if the column does not exist."""
    if name not in columns:
        return math.nan
    text = field_text(fields, columns, name)
    try:
        return float(text)
    except ValueError:
        raise BadRow(NON_NUMERIC, f"{name}={text!r} is not a number") from None


def measured_float(fields: list[str], columns: dict[str, int], name: str) -> float:
    """An optional measured column (velocity, heading, size) as float: NaN where the column or its value is missing,
    to be derived from the positions or defaulted like a NaN; text that is no number is a bad row."""
    if name not in columns:
        return math.nan
    i = columns[name]
    if i >= len(fields) or not fields[i].strip():
        return math.nan
    return field_float(fields, columns, name)


def field_int(fields: list[str], columns: dict[str, int], name: str) -> int:
    """Column ``name`` as an integer (``"12"`` or ``"12.0"``)."""
    text = field_text(fields, columns, name)
    try:
        return int(text)
    except ValueError:
        pass
    try:
        value = float(text)
    except ValueError:
        raise BadRow(NON_NUMERIC, f"{name}={text!r} is not an integer") from None
    if not math.isfinite(value) or value != int(value):
        raise BadRow(NON_NUMERIC, f"{name}={text!r} is not an integer")
    return int(value)


def optional_float(fields: list[str], columns: dict[str, int], name: str) -> float:
    """Column ``name`` as float, NaN when the column, the value or the number is missing."""
    try:
        return field_float(fields, columns, name)
    except BadRow:
        return math.nan


def optional_text(fields: list[str], columns: dict[str, int], name: str) -> str:
    """Column ``name`` as stripped text, empty when the column or the value is missing."""
    if name not in columns:
        return ""
    try:
        return field_text(fields, columns, name)
    except BadRow:
        return ""


def display_path(path: Path, root: Path | None) -> str:
    """``path`` relative to ``root`` where possible (for report examples)."""
    if root is not None:
        try:
            return str(path.relative_to(root))
        except ValueError:
            pass
    return str(path)


def no_usable_row(path: Path, report: ReportBuilder, skipped_before: dict[str, int]) -> DatasetError:
    """The error for a file none of whose rows could be used, with the skip counts of that file."""
    rep = report.build()
    parts = [
        f"{p.reason}={p.count - skipped_before.get(p.reason, 0)}"
        for p in rep.problems
        if p.action == "skipped" and p.count > skipped_before.get(p.reason, 0)
    ]
    return DatasetError(f"{path}: no usable row ({'skipped ' + ', '.join(parts) if parts else 'no data rows'})")


def skip_counts(report: ReportBuilder) -> dict[str, int]:
    return {p.reason: p.count for p in report.build().problems if p.action == "skipped"}


class RowBuffer:
    """Accepted rows of one sequence, in file order, plus the per-track checks."""

    def __init__(self, report: ReportBuilder) -> None:
        self.report = report
        self._cols: dict[str, list] = {k: [] for k in _COLUMNS}
        self._frames_seen: dict[int, set[int]] = {}
        self._last_stamp: dict[int, int] = {}

    def __len__(self) -> int:
        return len(self._cols["track_id"])

    def append(
        self,
        *,
        file: str,
        line: int,
        track_id: int,
        frame_index: int,
        stamp_ns: int,
        agent_type: AgentType,
        x_m: float,
        y_m: float,
        vx_mps: float,
        vy_mps: float,
        yaw_rad: float,
        length_m: float,
        width_m: float,
    ) -> bool:
        """Add one parsed row; False (and counted) if it is a duplicate, goes back in time or has a time that no
        array of nanoseconds holds."""
        if not -MAX_STAMP_NS <= stamp_ns <= MAX_STAMP_NS:  # a corrupt value, or not milliseconds (microseconds since 1970)
            self.report.skip(TIME_OUT_OF_RANGE, file, line, f"track {track_id}: time {stamp_ns / 1e9:.3g} s is beyond ±{MAX_STAMP_NS / 1e9 / 3.156e7:.0f} years"
                             " (a corrupt value, or a time not in the format's unit)")
            return False
        if not (math.isfinite(x_m) and math.isfinite(y_m)):
            self.report.skip(NON_FINITE_POSITION, file, line, f"track {track_id}: x={x_m} y={y_m}")
            return False
        seen = self._frames_seen.setdefault(track_id, set())
        if frame_index in seen:
            self.report.skip(DUPLICATE_FRAME, file, line, f"track {track_id} frame {frame_index} again")
            return False
        last = self._last_stamp.get(track_id)
        if last is not None and stamp_ns < last:
            self.report.skip(
                TIME_BACKWARDS, file, line, f"track {track_id}: stamp {stamp_ns / 1e6:.0f} ms after {last / 1e6:.0f} ms"
            )
            return False
        seen.add(frame_index)
        self._last_stamp[track_id] = stamp_ns
        c = self._cols
        c["file"].append(file)
        c["line"].append(line)
        c["track_id"].append(track_id)
        c["frame_index"].append(frame_index)
        c["stamp_ns"].append(stamp_ns)
        c["agent_type"].append(int(agent_type))
        c["x_m"].append(x_m)
        c["y_m"].append(y_m)
        c["vx_mps"].append(vx_mps)
        c["vy_mps"].append(vy_mps)
        c["yaw_rad"].append(yaw_rad)
        c["length_m"].append(length_m)
        c["width_m"].append(width_m)
        return True

    def finish(self, rule: RepairRule) -> dict[str, np.ndarray]:
        """Sizes and kinematics repaired, arrays sorted by (frame_index, track_id)."""
        c = self._cols
        files = c["file"]
        lines = c["line"]
        arr = {k: np.asarray(c[k], dtype=_COLUMNS[k]) for k in _COLUMNS if k not in ("file", "line")}
        n = arr["track_id"].shape[0]

        # sizes: non-finite or non-positive -> default of the agent type (one repair per row)
        bad_length = ~np.isfinite(arr["length_m"]) | (arr["length_m"] <= 0)
        bad_width = ~np.isfinite(arr["width_m"]) | (arr["width_m"] <= 0)
        for i in np.flatnonzero(bad_length | bad_width).tolist():
            default_length, default_width = DEFAULT_SIZES_M[AgentType(int(arr["agent_type"][i]))]
            old = f"{arr['length_m'][i]} x {arr['width_m'][i]}"
            if bad_length[i]:
                arr["length_m"][i] = default_length
            if bad_width[i]:
                arr["width_m"][i] = default_width
            new = f"{arr['length_m'][i]} x {arr['width_m'][i]}"
            self._repair(SIZE_DEFAULTED, files[i], lines[i], f"track {arr['track_id'][i]}: {old} -> {new} m")

        # kinematics, per track in time order: derive, decide per sequence, repair
        order = np.lexsort((arr["stamp_ns"], arr["track_id"]))
        segments = np.split(order, np.flatnonzero(np.diff(arr["track_id"][order])) + 1) if n else []
        derived = [
            derive_kinematics(arr["stamp_ns"][seg] * 1e-9, arr["x_m"][seg], arr["y_m"][seg], half_window=rule.half_window)
            for seg in segments
        ]
        dvx = np.full(n, np.nan)
        dvy = np.full(n, np.nan)
        for seg, kin in zip(segments, derived):
            dvx[seg], dvy[seg] = kin.vx_mps, kin.vy_mps
        flip_velocity = rule.repair_velocity and velocity_sign_inverted(arr["vx_mps"], arr["vy_mps"], dvx, dvy, rule)
        resolve_yaw = yaw_modulo_pi(arr["yaw_rad"], dvx, dvy, rule)
        for seg, kin in zip(segments, derived):
            old_vx, old_vy, old_yaw = arr["vx_mps"][seg], arr["vy_mps"][seg], arr["yaw_rad"][seg]
            rep = repair_track(
                arr["stamp_ns"][seg] * 1e-9,
                arr["x_m"][seg],
                arr["y_m"][seg],
                old_vx,
                old_vy,
                old_yaw,
                rule,
                derived=kin,
                flip_velocity=flip_velocity,
                resolve_yaw=resolve_yaw,
            )
            for reason, mask, what in (
                (VELOCITY_SIGN_FLIPPED, rep.velocity_sign_flipped, "velocity"),
                (VELOCITY_NAN, rep.velocity_nan, "velocity"),
                (START_VELOCITY, rep.start_velocity, "velocity"),
                (YAW_FROM_MOTION, rep.yaw_from_motion, "yaw"),
                (YAW_FROM_NEIGHBOUR, rep.yaw_from_neighbour, "yaw"),
                (YAW_DEFAULTED, rep.yaw_defaulted, "yaw"),
                (YAW_FLIPPED, rep.yaw_flipped, "yaw"),
            ):
                for j in np.flatnonzero(mask).tolist():
                    i = int(seg[j])
                    if what == "velocity":
                        detail = (
                            f"track {arr['track_id'][i]}: v=({old_vx[j]:.2f}, {old_vy[j]:.2f}) "
                            f"-> ({rep.vx_mps[j]:.2f}, {rep.vy_mps[j]:.2f}) m/s"
                        )
                    else:
                        detail = f"track {arr['track_id'][i]}: yaw={old_yaw[j]:.3f} -> {rep.yaw_rad[j]:.3f} rad"
                    self._repair(reason, files[i], lines[i], detail)
            arr["vx_mps"][seg] = rep.vx_mps
            arr["vy_mps"][seg] = rep.vy_mps
            arr["yaw_rad"][seg] = rep.yaw_rad

        final = np.lexsort((arr["track_id"], arr["frame_index"]))
        return {k: np.ascontiguousarray(v[final]) for k, v in arr.items()}

    def _repair(self, reason: str, file: str, line: int, detail: str) -> None:
        self.report.add(reason, REPAIRED, file, line, detail)


_COLUMNS: dict[str, object] = {
    "file": object,
    "line": np.int64,
    "track_id": np.int64,
    "frame_index": np.int64,
    "stamp_ns": np.int64,
    "agent_type": np.uint8,
    "x_m": np.float64,
    "y_m": np.float64,
    "vx_mps": np.float64,
    "vy_mps": np.float64,
    "yaw_rad": np.float64,
    "length_m": np.float64,
    "width_m": np.float64,
}
