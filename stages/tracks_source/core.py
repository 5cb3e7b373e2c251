"""The dataset player's core: ``TrackPlayer`` and its config (documented in ``stages/tracks_source/__init__.py``)."""

from __future__ import annotations

import hashlib
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

from bus_schemas import Header, SceneInfo, SignalState, TrackFrame

from stages.lib.base import ConfigMixin, Issue, StageResult
from stages.lib.projections import published_projection
from stages.lib.datasets import (
    DEFAULT_DATA_DIR,
    DEFAULT_RECORDING,
    DEFAULT_SEQUENCE,
    KEPT,
    SKIPPED,
    DatasetError,
    LoadReport,
    Recording,
    Sequence,
    discover,
    load_recording,
)


@dataclass(frozen=True, kw_only=True)
class TracksSourceConfig(ConfigMixin):
    """What to play and how fast (see the module docstring)."""

    data: str = ""
    recording: str = ""
    sequences: tuple[str, ...] = ()
    speed: float | str = 1.0
    loop: bool = False
    projection: str = "auto"
    signals: bool = True  # publish signal_state when the recording has signal phases (False: play it without them)
    #: the frames' stamps: "recording" (the recording's own, from about 0) or "wall" (the same moved so that the first
    #: frame carries the wall clock (Unix ns) at which playback starts, as a live tracker stamps its frames)
    clock: str = "recording"

    def __post_init__(self) -> None:
        if isinstance(self.speed, str):
            if self.speed != "max":
                raise ValueError(f"speed = {self.speed!r}: expected a number > 0 or 'max'")
        elif isinstance(self.speed, bool) or not isinstance(self.speed, (int, float)):
            raise ValueError(f"speed = {self.speed!r}: expected a number > 0 or 'max'")
        elif not (math.isfinite(self.speed) and self.speed > 0):
            raise ValueError(f"speed = {self.speed!r}: must be > 0 (or 'max')")
        if not self.projection.strip():
            raise ValueError("projection must not be empty (use 'auto')")
        if any(not s.strip() for s in self.sequences):
            raise ValueError(f"sequences = {list(self.sequences)!r}: empty sequence id")
        if self.clock not in ("recording", "wall"):
            raise ValueError(f"clock = {self.clock!r}: expected \"recording\" or \"wall\"")


@dataclass(frozen=True, slots=True, kw_only=True)
class PlaybackSelection:
    """The data folder, recording and sequences a config resolves to (None: all sequences)."""

    data_dir: Path
    recording: str
    sequences: tuple[str, ...] | None


def resolve_selection(config: TracksSourceConfig) -> PlaybackSelection:
    """Apply the defaults of the module docstring; may list the folder (``DatasetError``)."""
    data_dir = Path(config.data).expanduser() if config.data else DEFAULT_DATA_DIR
    is_default_dir = data_dir.resolve() == DEFAULT_DATA_DIR.resolve()
    if config.recording:
        recording = config.recording
    elif is_default_dir:
        recording = DEFAULT_RECORDING
    else:
        recording = discover(data_dir)[0].name
    if config.sequences:
        sequences: tuple[str, ...] | None = tuple(config.sequences)
    elif is_default_dir and recording == DEFAULT_RECORDING:
        sequences = (DEFAULT_SEQUENCE,)
    else:
        sequences = None
    return PlaybackSelection(data_dir=data_dir, recording=recording, sequences=sequences)


def file_sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with path.open("rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def scene_id_of(map_sha256: str, projection: str, origin_lat_deg: float, origin_lon_deg: float) -> str:
    """Short content hash naming a scene: map file, projection and origin (16 hex digits)."""
    key = f"{map_sha256}|{projection}|{origin_lat_deg!r}|{origin_lon_deg!r}"
    return hashlib.sha256(key.encode()).hexdigest()[:16]


def report_issues(report: LoadReport) -> list[Issue]:
    """One ``Issue`` per reason of a load report, with its count and first example."""
    issues = []
    for p in report.problems:
        if p.action == SKIPPED:
            kind = f"bad_row_{p.reason}"
        elif p.action == KEPT:
            kind = p.reason
        else:
            kind = f"repaired_{p.reason}"
        first = f" first={p.examples[0]}" if p.examples else ""
        issues.append(Issue(kind=kind, agent_id=-1, detail=f"count={p.count}{first}"))
    return issues


class TrackPlayer:
    """Plays the sequences of a loaded recording back to back as bus messages.

    Iterating yields ``(stamp_ns, StageResult)`` with outputs ``track_frame``
    (every frame) and ``scene`` (first frame, and whenever the scene changes).
    Each iteration starts the run afresh; with ``config.loop`` it never ends.
    """

    def __init__(
        self, config: TracksSourceConfig, recording: Recording, *, map_sha256: str, run_id: str, producer: str
    ) -> None:
        if recording.map_path is None:
            raise DatasetError(f"recording {recording.name} has no map: expected maps/{recording.name}.osm in its data folder")
        if not recording.sequences:
            raise DatasetError(f"recording {recording.name}: no sequence to play")
        self.config = config
        self.recording = recording
        self.map_path: Path = recording.map_path
        self.map_sha256 = map_sha256
        self.run_id = run_id
        self.producer = producer
        self.n_frames_per_pass = sum(s.n_frames for s in recording.sequences)

    @classmethod
    def open(cls, config: TracksSourceConfig, *, run_id: str, producer: str) -> "TrackPlayer":
        """Resolve the config's defaults, load the recording and hash its map."""
        sel = resolve_selection(config)
        recording = load_recording(sel.data_dir, sel.recording, sel.sequences)
        if recording.map_path is None:
            raise DatasetError(
                f"recording {recording.name} has no map: expected {sel.data_dir / 'maps' / (recording.name + '.osm')}"
            )
        return cls(config, recording, map_sha256=file_sha256(recording.map_path), run_id=run_id, producer=producer)

    def scene_for(self, seq: Sequence, frame_index: int, stamp_ns: int) -> SceneInfo:
        """The ``SceneInfo`` of a sequence (map name and sha256, projection and the sequence's origin; never a path)."""
        rec = self.recording
        return SceneInfo(
            header=Header(run_id=self.run_id, frame_index=frame_index, stamp_ns=stamp_ns, producer=self.producer),
            scene_id=scene_id_of(self.map_sha256, self.config.projection, seq.origin_lat_deg, seq.origin_lon_deg),
            recording=rec.name,
            location_id=rec.location_id,
            map_name=self.map_path.name,
            map_sha256=self.map_sha256,
            projection=published_projection(self.config.projection, rec.location_id),
            origin_lat_deg=seq.origin_lat_deg,
            origin_lon_deg=seq.origin_lon_deg,
            frame_rate_hz=seq.frame_rate_hz,
            speed_limit_mps=rec.speed_limit_mps,
            n_frames=self.n_frames_per_pass,
            clock=self.config.clock,  # "recording" or "wall": what the frames' stamps count
        )

    def signal_state_at(self, sequence_stamp_ns: int, stamp_ns: int, frame_index: int, scene_id: str) -> SignalState | None:
        """Every signal group's state at a frame (None: no signal phases, or ``signals`` off).

        The phase file's clock is the recording's own (``timestamp_ms`` of the
        tracks, 0 at its start), so it is read at the sequence's own stamp;
        the message carries the run's stamp.
        """
        phases = self.recording.signal_phases
        if phases is None or not self.config.signals:
            return None
        ids, states, held = phases.states(int(sequence_stamp_ns))
        return SignalState(
            header=Header(run_id=self.run_id, frame_index=frame_index, stamp_ns=stamp_ns, producer=self.producer),
            scene_id=scene_id, group_ids=ids, phases=states, held_s=held,
        )

    def __iter__(self) -> Iterator[tuple[int, StageResult]]:
        frame_index = 0
        last_stamp: int | None = None
        scene_id = ""
        pending_issues = report_issues(self.recording.report)
        while True:
            for seq in self.recording.sequences:
                if seq.n_rows == 0:
                    continue
                first_stamp = int(seq.stamp_ns[0])
                if last_stamp is None:  # the first frame: the recording's own stamp, or the wall clock now (clock "wall")
                    offset = time.time_ns() - first_stamp if self.config.clock == "wall" else 0
                else:
                    offset = last_stamp + seq.period_ns - first_stamp
                for k, view in enumerate(seq.frames()):
                    stamp = view.stamp_ns + offset
                    outputs: dict[str, object] = {}
                    if k == 0:
                        scene = self.scene_for(seq, frame_index, stamp)
                        if scene.scene_id != scene_id:
                            outputs["scene"] = scene
                            scene_id = scene.scene_id
                    outputs["track_frame"] = TrackFrame(
                        header=Header(run_id=self.run_id, frame_index=frame_index, stamp_ns=stamp, producer=self.producer),
                        scene_id=scene_id,
                        track_ids=view.track_id,
                        agent_types=view.agent_type,
                        x_m=view.x_m,
                        y_m=view.y_m,
                        vx_mps=view.vx_mps,
                        vy_mps=view.vy_mps,
                        yaw_rad=view.yaw_rad,
                        length_m=view.length_m,
                        width_m=view.width_m,
                    )
                    signal_state = self.signal_state_at(view.stamp_ns, stamp, frame_index, scene_id)
                    if signal_state is not None:
                        outputs["signal_state"] = signal_state
                    yield stamp, StageResult(outputs=outputs, issues=pending_issues)
                    pending_issues = []
                    frame_index += 1
                    last_stamp = stamp
            if not self.config.loop:
                return
