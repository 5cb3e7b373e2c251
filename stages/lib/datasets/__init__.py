"""Dataset readers: INTERACTION-format (TAF-BW) and inD-format recordings.

Pure: numpy and the standard library's csv, no bus. ``discover(data_dir)``
lists the recordings of a data folder, ``load_recording(data_dir, name)``
reads one into columnar arrays, with every skipped, flagged or repaired row
counted in a ``LoadReport``. ``kinematics`` derives velocities from positions
and repairs implausible reported values at track starts.
"""

from stages.lib.datasets.defaults import DEFAULT_DATA_DIR, DEFAULT_RECORDING, DEFAULT_SEQUENCE, FULL_DATA_ENV, default_recordings, full_data_dir
from stages.lib.datasets.kinematics import Kinematics, RepairRule, TrackRepair, derive_kinematics, repair_track
from stages.lib.datasets.loader import discover, find_recording, load_recording, load_ref
from stages.lib.datasets.model import (
    AGENT_TYPES_BY_NAME,
    DEFAULT_SIZES_M,
    FORMAT_IND,
    FORMAT_INTERACTION,
    DatasetError,
    FrameView,
    Recording,
    RecordingRef,
    Sequence,
    agent_type_from_name,
)
from stages.lib.datasets.report import KEPT, REPAIRED, SKIPPED, LoadReport, ProblemCount, ProblemExample

__all__ = [
    "AGENT_TYPES_BY_NAME",
    "DEFAULT_DATA_DIR",
    "FULL_DATA_ENV",
    "full_data_dir",
    "FULL_DATA_ENV",
    "full_data_dir",
    "DEFAULT_RECORDING",
    "DEFAULT_SEQUENCE",
    "default_recordings",
    "DEFAULT_SIZES_M",
    "FORMAT_IND",
    "FORMAT_INTERACTION",
    "KEPT",
    "REPAIRED",
    "SKIPPED",
    "DatasetError",
    "FrameView",
    "Kinematics",
    "LoadReport",
    "ProblemCount",
    "ProblemExample",
    "Recording",
    "RecordingRef",
    "RepairRule",
    "Sequence",
    "TrackRepair",
    "agent_type_from_name",
    "derive_kinematics",
    "discover",
    "find_recording",
    "load_recording",
    "load_ref",
    "repair_track",
]
