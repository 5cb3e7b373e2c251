"""The data model shared by every dataset format: recordings, sequences, frames.

A ``Recording`` is one location and session (``k729_2022-03-16``, inD ``01``)
with its map. It holds ``Sequence``s: contiguous stretches of tracks, each
with columnar numpy arrays (one row per object and frame) sorted by
``(frame_index, track_id)``. Positions are metres in the recording's local
frame (x east, y north, origin at ``origin_lat_deg/origin_lon_deg`` for
INTERACTION-format data, at the UTM origin for inD), velocities m/s, yaw in
radians from the x axis.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import numpy as np

from bus_schemas import AgentType

from stages.lib.datasets.report import LoadReport

FORMAT_INTERACTION = "interaction"
FORMAT_IND = "ind"
FORMATS = (FORMAT_INTERACTION, FORMAT_IND)


class DatasetError(ValueError):
    """A data folder, recording or file that cannot be used at all.

    A ``ValueError`` so that ``runtime.run_stage`` maps it to exit code 2
    (bad configuration) when a source cannot open its data.
    """


AGENT_TYPES_BY_NAME: dict[str, AgentType] = {
    "car": AgentType.CAR,
    "van": AgentType.CAR,
    "truck": AgentType.TRUCK,
    "truck_bus": AgentType.TRUCK,
    "bus": AgentType.BUS,
    "bike": AgentType.BICYCLE,
    "bicycle": AgentType.BICYCLE,
    "motorcycle": AgentType.MOTORCYCLE,
    "motorbike": AgentType.MOTORCYCLE,
    "pedestrian": AgentType.PEDESTRIAN,
    # INTERACTION's pedestrian_tracks files do not tell walkers from cyclists;
    # both are vulnerable road users that are obstacles, not predicted vehicles.
    "pedestrian/bicycle": AgentType.PEDESTRIAN,
}
"""Agent type names of all supported formats, lower case. Anything else is UNKNOWN."""


def agent_type_from_name(name: str) -> AgentType:
    """``AgentType`` for a dataset's type name (case-insensitive); UNKNOWN if not known."""
    return AGENT_TYPES_BY_NAME.get(name.strip().lower(), AgentType.UNKNOWN)


DEFAULT_SIZES_M: dict[AgentType, tuple[float, float]] = {
    AgentType.UNKNOWN: (1.0, 1.0),
    AgentType.CAR: (4.5, 1.8),
    AgentType.TRUCK: (10.0, 2.5),
    AgentType.BUS: (12.0, 2.5),
    AgentType.MOTORCYCLE: (2.2, 0.8),
    AgentType.BICYCLE: (1.8, 0.7),
    AgentType.PEDESTRIAN: (1.0, 1.0),
}
"""(length_m, width_m) used where a file gives no usable size (TAF-BW pedestrians are 1 x 1)."""


@dataclass(frozen=True, slots=True, kw_only=True)
class RecordingRef:
    """A recording found by ``discover``: where its files are, nothing read yet.

    ``track_files`` holds every track file (INTERACTION: ``vehicle_tracks_NNN``
    and ``pedestrian_tracks_NNN``; inD: ``XX_tracks.csv``); ``meta_path`` the
    INTERACTION ``meta_data.csv`` or None for inD, whose meta files sit beside
    each tracks file. ``map_path`` is None when ``maps/<name>.osm`` is missing.
    """

    name: str
    format: str
    folder: Path
    map_path: Path | None
    track_files: tuple[Path, ...]
    meta_path: Path | None
    sequence_ids: tuple[str, ...]
    ignored_files: tuple[Path, ...] = ()
    signal_files: tuple[Path, ...] = ()  # signal_phases_NNN.csv beside the tracks (stages.lib.datasets.signals)
    lane_file: Path | None = None  # the *.kml lane file beside the tracks


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class FrameView:
    """The objects of one frame of a sequence: views (no copies) into its arrays.

    Every array has shape ``(n,)``; dtypes as in ``Sequence``.
    """

    frame_index: int
    stamp_ns: int
    track_id: np.ndarray
    agent_type: np.ndarray
    x_m: np.ndarray
    y_m: np.ndarray
    vx_mps: np.ndarray
    vy_mps: np.ndarray
    yaw_rad: np.ndarray
    length_m: np.ndarray
    width_m: np.ndarray

    def __len__(self) -> int:
        return int(self.track_id.shape[0])


ARRAY_FIELDS: dict[str, str] = {
    "frame_index": "int64",
    "stamp_ns": "int64",
    "track_id": "int64",
    "agent_type": "uint8",
    "x_m": "float64",
    "y_m": "float64",
    "vx_mps": "float64",
    "vy_mps": "float64",
    "yaw_rad": "float64",
    "length_m": "float64",
    "width_m": "float64",
}
"""The columnar arrays of a ``Sequence`` and their dtypes (all of shape ``(n_rows,)``)."""


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class Sequence:
    """One stretch of tracks (a TAF-BW ``vehicle_tracks_NNN`` file, an inD recording).

    Arrays, all ``(n_rows,)`` and read-only, sorted by ``(frame_index, track_id)``:

    - ``frame_index`` int64: frame number within the sequence. INTERACTION
      format: ``round(timestamp_ms * frame_rate_hz / 1000)``; the files'
      ``frame_id`` is global and inconsistent in TAF-BW (the same timestamp
      carries several frame_ids and a track repeats a frame_id), so it is not
      used. inD: the ``frame`` column.
    - ``stamp_ns`` int64: time within the sequence (``timestamp_ms`` · 1e6;
      inD ``frame / frameRate``).
    - ``track_id`` int64, ``agent_type`` uint8 (``AgentType`` values),
    - ``x_m``, ``y_m``, ``vx_mps``, ``vy_mps``, ``yaw_rad``, ``length_m``,
      ``width_m`` float64, all finite.

    ``source_files`` are the track files read; ``report`` what was skipped,
    flagged or repaired in them.
    """

    id: str
    start_time: str
    duration_s: float
    frame_rate_hz: float
    origin_lat_deg: float
    origin_lon_deg: float
    source_files: tuple[Path, ...]
    frame_index: np.ndarray
    stamp_ns: np.ndarray
    track_id: np.ndarray
    agent_type: np.ndarray
    x_m: np.ndarray
    y_m: np.ndarray
    vx_mps: np.ndarray
    vy_mps: np.ndarray
    yaw_rad: np.ndarray
    length_m: np.ndarray
    width_m: np.ndarray
    report: LoadReport = field(default_factory=LoadReport)

    def __post_init__(self) -> None:
        n = None
        for name, dtype in ARRAY_FIELDS.items():
            arr = getattr(self, name)
            if not isinstance(arr, np.ndarray) or arr.dtype != np.dtype(dtype) or arr.ndim != 1:
                raise TypeError(f"Sequence {self.id}: {name} must be a 1-d {dtype} array")
            if n is None:
                n = arr.shape[0]
            elif arr.shape[0] != n:
                raise ValueError(f"Sequence {self.id}: {name} has {arr.shape[0]} rows, frame_index has {n}")
            arr.setflags(write=False)

    @property
    def n_rows(self) -> int:
        return int(self.frame_index.shape[0])

    @property
    def n_frames(self) -> int:
        """Number of distinct frames that have at least one object."""
        if self.n_rows == 0:
            return 0
        return int(np.count_nonzero(np.diff(self.frame_index)) + 1)

    @property
    def n_tracks(self) -> int:
        return int(np.unique(self.track_id).shape[0])

    @property
    def period_ns(self) -> int:
        return int(round(1e9 / self.frame_rate_hz))

    def tracks_by_type(self) -> dict[AgentType, int]:
        """Number of distinct tracks per agent type (a track's first type counts)."""
        ids, first = np.unique(self.track_id, return_index=True)
        types, counts = np.unique(self.agent_type[first], return_counts=True)
        return {AgentType(int(t)): int(c) for t, c in zip(types, counts)}

    def frames(self) -> Iterator[FrameView]:
        """Yield the frames in order, each as views into the arrays."""
        if self.n_rows == 0:
            return
        bounds = np.flatnonzero(np.diff(self.frame_index)) + 1
        starts = np.concatenate(([0], bounds))
        stops = np.concatenate((bounds, [self.n_rows]))
        for a, b in zip(starts.tolist(), stops.tolist()):
            s = slice(a, b)
            yield FrameView(
                frame_index=int(self.frame_index[a]),
                stamp_ns=int(self.stamp_ns[a]),
                track_id=self.track_id[s],
                agent_type=self.agent_type[s],
                x_m=self.x_m[s],
                y_m=self.y_m[s],
                vx_mps=self.vx_mps[s],
                vy_mps=self.vy_mps[s],
                yaw_rad=self.yaw_rad[s],
                length_m=self.length_m[s],
                width_m=self.width_m[s],
            )


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class Recording:
    """A loaded recording: metadata, map path and its sequences.

    ``origin_lat_deg/origin_lon_deg``, ``frame_rate_hz`` and
    ``speed_limit_mps`` (NaN when unknown) come from the first loaded sequence;
    each ``Sequence`` carries its own origin and frame rate too. For inD,
    ``utm_origin_x_m/utm_origin_y_m`` give the UTM coordinates of the local
    frame's origin (the origin lat/lon is inD's ``latLocation/lonLocation``,
    a reference point of the location, not the exact frame origin); they are
    None for INTERACTION-format data. ``report`` merges the sequences' reports
    and lists ignored files. ``signal_phases`` and ``kml_lanes`` hold the
    recording's signal side when its folder has it (None otherwise).
    """

    name: str
    format: str
    location_id: str
    map_path: Path | None
    origin_lat_deg: float
    origin_lon_deg: float
    frame_rate_hz: float
    speed_limit_mps: float
    sequences: tuple[Sequence, ...]
    report: LoadReport
    utm_origin_x_m: float | None = None
    utm_origin_y_m: float | None = None
    signal_phases: object | None = None  # stages.lib.datasets.signals.SignalPhases when the folder has signal_phases_*.csv
    kml_lanes: object | None = None  # stages.lib.datasets.signals.KmlLanes when the folder has a *.kml lane file

    def sequence(self, sequence_id: str) -> Sequence:
        """The sequence with this id; raises ``DatasetError`` naming the loaded ones."""
        for seq in self.sequences:
            if same_sequence_id(seq.id, sequence_id):
                return seq
        raise DatasetError(
            f"recording {self.name}: no sequence {sequence_id!r}; loaded: {', '.join(s.id for s in self.sequences) or '(none)'}"
        )

    @property
    def n_frames(self) -> int:
        return sum(s.n_frames for s in self.sequences)


def same_sequence_id(a: str, b: str) -> bool:
    """Sequence ids match exactly or as numbers (``"13"`` matches ``"013"``)."""
    a, b = str(a).strip(), str(b).strip()
    if a == b:
        return True
    return a.isdigit() and b.isdigit() and int(a) == int(b)
