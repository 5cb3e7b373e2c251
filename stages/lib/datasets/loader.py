"""Find recordings in a data folder and load them, whatever their format.

A data folder is laid out like the TAF-BW subset::

    <data>/maps/<recording>.osm
    <data>/recorded_trackfiles/<recording>/
        meta_data.csv + vehicle_tracks_NNN.csv [+ pedestrian_tracks_NNN.csv]   (INTERACTION format)
        [signal_phases_NNN.csv] [<lanes>.kml]                                  (signal side, either format)
        XX_tracks.csv + XX_tracksMeta.csv + XX_recordingMeta.csv               (inD format)

Files that belong to neither format are ignored and logged at debug level. A
folder under ``recorded_trackfiles`` with no track file is not a recording.
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path
from typing import Iterable

from stages.lib.datasets import ind, interaction, signals
from stages.lib.datasets._rows import display_path
from stages.lib.datasets.kinematics import RepairRule
from stages.lib.datasets.model import FORMAT_IND, FORMAT_INTERACTION, DatasetError, Recording, RecordingRef, Sequence, same_sequence_id
from stages.lib.datasets.report import ReportBuilder

log = logging.getLogger("iamp.datasets")

TRACKS_DIR = "recorded_trackfiles"
MAPS_DIR = "maps"

_LAYOUT_HINT = (
    "expected maps/<rec>.osm and recorded_trackfiles/<rec>/ holding meta_data.csv + vehicle_tracks_NNN.csv "
    "(INTERACTION format) or XX_tracks.csv + XX_tracksMeta.csv + XX_recordingMeta.csv (inD format)"
)


def discover(data_dir: str | Path) -> list[RecordingRef]:
    """Recordings under ``data_dir``, sorted by name; nothing is read yet.

    Raises ``DatasetError`` when the folder does not exist or holds no
    recording.
    """
    root = Path(data_dir).expanduser()
    if not root.is_dir():
        what = "is a file, not a folder" if root.exists() else "does not exist"
        raise DatasetError(f"data folder {root} {what} ({_LAYOUT_HINT})")
    tracks_root = root / TRACKS_DIR
    refs: list[RecordingRef] = []
    if tracks_root.is_dir():
        for folder in sorted(p for p in tracks_root.iterdir() if p.is_dir()):
            ref = _recording_ref(root, folder)
            if ref is not None:
                refs.append(ref)
    if not refs:
        raise DatasetError(f"no recordings under {root}: {_LAYOUT_HINT}")
    return refs


def _recording_ref(root: Path, folder: Path) -> RecordingRef | None:
    files = sorted(p for p in folder.iterdir() if p.is_file())
    inter_tracks = [p for p in files if interaction.sequence_id_of(p) is not None]
    ind_tracks = [p for p in files if ind.sequence_id_of(p) is not None]
    if inter_tracks and ind_tracks:
        raise DatasetError(f"{folder}: mixes INTERACTION-format and inD-format track files; put them in separate recordings")
    if inter_tracks:
        fmt = FORMAT_INTERACTION
        meta = folder / interaction.META_FILE
        known = set(inter_tracks) | {meta}
        seq_ids = tuple(sorted({interaction.sequence_id_of(p) for p in inter_tracks}))
        tracks = tuple(inter_tracks)
        meta_path: Path | None = meta if meta.is_file() else None
    elif ind_tracks:
        fmt = FORMAT_IND
        known = set(ind_tracks)
        for p in ind_tracks:
            known.update(ind.companion_files(p))
        seq_ids = tuple(sorted(ind.sequence_id_of(p) for p in ind_tracks))
        tracks = tuple(ind_tracks)
        meta_path = None
    else:
        log.debug("not a recording (no track file): folder=%s", folder)
        return None
    signal_files = tuple(p for p in files if signals.is_signal_file(p))
    lane_files = [p for p in files if signals.is_lane_file(p)]
    if len(lane_files) > 1:
        raise DatasetError(f"{folder}: {len(lane_files)} KML lane files ({', '.join(p.name for p in lane_files)}); keep one")
    known.update(signal_files, lane_files)
    ignored = tuple(p for p in files if p not in known)
    for p in ignored:
        log.debug("ignored file: path=%s recording=%s", p, folder.name)
    map_path = root / MAPS_DIR / f"{folder.name}.osm"
    if not map_path.is_file():
        log.debug("recording without map: recording=%s expected=%s", folder.name, map_path)
    return RecordingRef(
        name=folder.name,
        format=fmt,
        folder=folder,
        map_path=map_path if map_path.is_file() else None,
        track_files=tracks,
        meta_path=meta_path,
        sequence_ids=seq_ids,
        ignored_files=ignored,
        signal_files=signal_files,
        lane_file=lane_files[0] if lane_files else None,
    )


def find_recording(data_dir: str | Path, name: str) -> RecordingRef:
    """The recording called ``name`` under ``data_dir``; ``DatasetError`` naming those there are."""
    refs = discover(data_dir)
    for ref in refs:
        if ref.name == name:
            return ref
    raise DatasetError(f"no recording {name!r} under {Path(data_dir)}; found: {', '.join(r.name for r in refs)}")


def load_recording(
    data_dir: str | Path, name: str, sequences: Iterable[str] | None = None, *, rule: RepairRule = RepairRule()
) -> Recording:
    """Load recording ``name`` of ``data_dir``, all its sequences or those listed.

    Only sequences with a track file are loaded (a ``meta_data.csv`` may list
    more). Bad rows are skipped and counted in the report; an unusable file
    or a missing meta file or origin raises ``DatasetError``.
    """
    return load_ref(find_recording(data_dir, name), sequences, rule=rule, display_root=Path(data_dir))


def load_ref(
    ref: RecordingRef, sequences: Iterable[str] | None = None, *, rule: RepairRule = RepairRule(), display_root: Path | None = None
) -> Recording:
    """Load a discovered recording (see ``load_recording``)."""
    wanted = _select(ref, sequences)
    builder = ReportBuilder()
    builder.extend_ignored(display_path(p, display_root) for p in ref.ignored_files)
    loaded: list[Sequence] = []
    location_id = ""
    speed_limit_mps = float("nan")
    utm_x = utm_y = None
    if ref.format == FORMAT_INTERACTION:
        meta_path = ref.meta_path or (ref.folder / interaction.META_FILE)
        metas = interaction.read_meta(meta_path)
        for seq_id in wanted:
            files = [p for p in ref.track_files if interaction.sequence_id_of(p) == seq_id]
            meta = interaction.meta_for(metas, seq_id, meta_path)
            seq = interaction.read_sequence(files, meta, rule, display_root)
            loaded.append(seq)
            if not location_id:
                location_id, speed_limit_mps = meta.location_id, meta.speed_limit_mps
    else:
        for seq_id in wanted:
            path = next(p for p in ref.track_files if ind.sequence_id_of(p) == seq_id)
            seq, meta = ind.read_sequence(path, rule, display_root)
            loaded.append(seq)
            if not location_id:
                location_id, speed_limit_mps = meta.location_id, meta.speed_limit_mps
                utm_x, utm_y = meta.utm_origin_x_m, meta.utm_origin_y_m
    for seq in loaded:
        builder.add_report(seq.report)
        log.debug("sequence loaded: recording=%s sequence=%s %s", ref.name, seq.id, seq.report.summary())
    first = loaded[0]
    # the signal side is optional: a file of it that cannot be used is counted and the tracks play without it (as with
    # `iamp eval --signals off`), never the recording lost
    phases = _signal_side(ref.signal_files, lambda: signals.read_signal_phases(ref.signal_files, display_root), "signal phases",
                          ref.name, builder, display_root)
    lanes = _signal_side((ref.lane_file,) if ref.lane_file is not None else (), lambda: signals.read_kml_lanes(ref.lane_file, display_root),
                         "its lane file's signals", ref.name, builder, display_root)
    return Recording(
        name=ref.name,
        format=ref.format,
        location_id=location_id or ref.name,
        map_path=ref.map_path,
        origin_lat_deg=first.origin_lat_deg,
        origin_lon_deg=first.origin_lon_deg,
        frame_rate_hz=first.frame_rate_hz,
        speed_limit_mps=speed_limit_mps,
        sequences=tuple(loaded),
        report=builder.build(),
        utm_origin_x_m=utm_x,
        utm_origin_y_m=utm_y,
        signal_phases=phases,
        kml_lanes=lanes,
    )


def _signal_side(files, read, what: str, name: str, builder: ReportBuilder, display_root: Path | None):
    """``read()`` of a recording's signal-side files (None without any): on a ``DatasetError`` the first file is listed
    as ignored with the reason and the recording plays without ``what``; its findings go into ``builder``."""
    if not files:
        return None
    try:
        out = read()
    except DatasetError as exc:
        builder.ignore_file(f"{display_path(files[0], display_root)} (not used: {exc}; played without {what})")
        log.warning("%s not used: recording=%s reason=%s", what, name, exc)
        return None
    builder.add_report(dataclasses.replace(out.report, rows_read=0, rows_kept=0))  # rows_read counts track rows
    log.debug("%s loaded: recording=%s %s", what, name, out.report.summary())
    return out


def _select(ref: RecordingRef, sequences: Iterable[str] | None) -> list[str]:
    if sequences is None:
        return list(ref.sequence_ids)
    if isinstance(sequences, str):
        sequences = [sequences]
    wanted: list[str] = []
    for want in sequences:
        match = next((s for s in ref.sequence_ids if same_sequence_id(s, want)), None)
        if match is None:
            raise DatasetError(
                f"recording {ref.name}: no track file for sequence {want!r}; available: {', '.join(ref.sequence_ids)}"
            )
        if match not in wanted:
            wanted.append(match)
    if not wanted:
        raise DatasetError(f"recording {ref.name}: empty sequence selection; available: {', '.join(ref.sequence_ids)}")
    return wanted
