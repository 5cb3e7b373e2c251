"""Dense traffic from real tracks: superimpose time-shifted copies of recordings of one map (``iamp data superimpose``).

A *layer* is one source sequence of an INTERACTION-format recording (TAF-BW)
shifted in time by ``shift_s``: its row at time t is written at
(t − shift) mod D_seq + m·D_seq for every m that lands in [0, D) — the
sequence is played circularly and tiled over the output's duration D, so
every layer contributes over the whole output. ``build_dense`` stacks whole
layers while their mean vehicles per frame fit under the target, then one
partial layer (``Layer.share``: whole tracks of one more copy, picked by a
hash of their ids, until their rows reach the share) tops the mean up to
the target. Each (layer, tile, source
track) gets a fresh track id (a track cut by the wrap becomes two tracks:
one leaving at the end, one entering at the start, as tracks do at a
recording's edges). The default shift step is the signal cycle
(``estimate_cycle_s`` finds it from the tracks: the autocorrelation of the
number of moving vehicles), so that the copies start in phase with the
lights; but the wrap and the tiling are over the sequence's length, which is
not a multiple of the cycle, so the rows a copy wraps round (and every tile
after the first) are out of phase with the others (K733's 244.1 s over an
89.2 s cycle: about 66 s). The output is meant for load (how many vehicles
and pairs a frame holds), not for traffic: copies do not see each other, so
cars of two copies drive through one another, and standing cars of two
copies can stand on the same spot (at 18 vehicles some 500 pairs of
vehicles closer than 1 m over 1 in 10 frames, against 9 in the source).

"Vehicles" are the rows whose ``agent_type`` is a vehicle type (car, truck,
bus, motorcycle, as the stages count them): K729's vehicle track files hold
pedestrians too, which are copied but not counted.

The output folder is laid out like the TAF-BW data: ``maps/<name>.osm`` (a
copy of the source map), ``recorded_trackfiles/<name>/meta_data.csv`` (one
sequence ``000``, the source's origin, frame rate, location and speed limit)
and ``vehicle_tracks_000.csv`` [+ ``pedestrian_tracks_000.csv``], plus the
source's LICENSE and an ATTRIBUTION.md saying what was derived from what
(TAF-BW is CC BY-NC-SA 4.0: the derived recording carries the same licence).
It is written whole into a temporary folder inside the output folder and moved
into place only when complete (``superimpose``): a failure or Ctrl-C leaves an
earlier recording of that name as it was. The output may not be, hold or lie
in the source recording's folder, nor hold its map (``check_out_apart``).

Pure: the standard library's csv and numpy; rows are copied as text except
the track id and the timestamp (and ``frame_id``, renumbered from the new
timestamp), so positions and velocities are the source's bit for bit.
"""

from __future__ import annotations

import csv
import dataclasses
import fnmatch
import math
import os
import shutil
import tempfile
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from stages.lib.datasets.interaction import META_FILE, TRACK_FILE_RE
from stages.lib.datasets.loader import MAPS_DIR, TRACKS_DIR, find_recording
from stages.lib.datasets.model import FORMAT_INTERACTION, DatasetError, RecordingRef, agent_type_from_name

#: Columns written, in this order, when the sources have them (``time`` of K729 is left out: it would be wrong).
COLUMNS = ("track_id", "frame_id", "timestamp_ms", "agent_type", "x", "y", "vx", "vy", "psi_rad", "length", "width")
#: Limits of a request, so that a slip of the finger (``--vehicles 1e6``, ``--duration-s 1e9``) is refused at once
#: and does not run for hours or out of memory: the output holds about vehicles x duration x frame rate rows (some
#: 550 bytes of memory each while it is built: 2 million vehicle-seconds at 10 Hz are some 11 GB and 2 minutes).
MAX_VEHICLES = 1000
MAX_DURATION_S = 86_400.0  # a day
MAX_SHIFT_S = 86_400.0  # a longer one only wraps round the sequences again (and round x shift must stay finite)
MAX_VEHICLE_SECONDS = 2_000_000.0  # a day of 23 vehicles, 1000 vehicles for 2000 s
META_COLUMNS = ("id", "frameRate_hz", "locationId", "speedLimit_kmh", "date", "weekDay", "startTime", "duration",
                "originLat", "originLon", "spatAvailable", "simulated", "tracking", "timeZone")


@dataclass(frozen=True, slots=True)
class SourceSequence:
    """One sequence's rows as read: header names, rows (lists of text), the meta row, and per row the time in ms."""

    id: str
    kind: str  # "vehicle" or "pedestrian"
    columns: tuple[str, ...]
    rows: tuple[tuple[str, ...], ...]
    meta: dict[str, str]
    time_ms: np.ndarray
    track_ids: np.ndarray  # text ids as read (object array)
    vehicle: np.ndarray  # per row: its agent_type is a vehicle type (``AgentType.is_vehicle``: what the stages predict)

    @property
    def duration_ms(self) -> int:
        """Length of the sequence: last stamp + one frame."""
        if not self.time_ms.size:
            return 0
        return int(self.time_ms.max()) + self.frame_ms

    @property
    def frame_ms(self) -> int:
        return int(round(1000.0 / float(self.meta.get("frameRate_hz") or 10)))

    def mean_per_frame(self) -> float:
        """Mean number of vehicles (rows of a vehicle type) per frame over the sequence's frames."""
        if not self.time_ms.size:
            return 0.0
        return float(np.count_nonzero(self.vehicle)) / (self.duration_ms / self.frame_ms)


@dataclass(frozen=True, slots=True)
class Layer:
    """One copy: source sequence index, its time shift in seconds and the share of its tracks written.

    ``share`` < 1 keeps whole source tracks, picked in a fixed pseudo-random order (a hash of the track id and
    the shift) until their rows reach ``share`` of the sequence's rows: the copy then adds about ``share`` times
    the sequence's mean vehicles per frame (``plan_layers`` tops the target up with one such partial copy).
    """

    source: int
    shift_s: float
    share: float = 1.0


@dataclass(frozen=True, slots=True)
class SuperimposeResult:
    """What was written: the folder, the recording name, and per-frame vehicle counts (mean, median, max)."""

    out_dir: Path
    name: str
    layers: tuple[Layer, ...]
    duration_s: float
    n_tracks: int
    n_rows: int
    vehicles_mean: float
    vehicles_median: float
    vehicles_max: int


def default_name(recording: str, target_vehicles: float) -> str:
    """``<recording>-dense<N>``, N as given (``0.5`` stays ``0.5``: rounding named it ``-dense0``; ``18.0`` is ``18``)."""
    return f"{recording}-dense{target_vehicles:.15g}"


def check_name(name: str, flag: str = "--name") -> None:
    """``DatasetError`` unless ``name`` is a plain folder name: it becomes ``recorded_trackfiles/<name>/`` and
    ``maps/<name>.osm`` under the output, so a separator or ``..`` would write elsewhere (``../../x``: outside the
    output) or into folders that do not exist (``a/b``), and a leading dot hides it (``.``, ``..``: the folders)."""
    bad = not name or name.startswith(".") or ".." in name or any(c in name for c in "/\\\0") or len(name.encode()) > 200
    if bad:
        raise DatasetError(f"{flag} {name!r}: give a plain folder name (not empty, at most 200 bytes, no '/', '\\' or '..', "
                           "not starting with '.')")


def check_out_apart(out_dir: str | Path, ref: RecordingRef, flag: str = "--out") -> None:
    """``DatasetError`` where the output folder is the source recording's folder, holds it or lies inside it, or holds
    its map: the new recording replaces files in the output (its recording folder, map, LICENSE), and the source is
    read from files that would be among them (``--out`` = ``--data`` and ``--name`` = ``--recording`` deleted the
    source's tracks)."""
    out = Path(out_dir).expanduser().resolve()
    folder = ref.folder.resolve()
    if out == folder or out in folder.parents:
        raise DatasetError(f"{flag} {out_dir}: holds the source recording {ref.name} ({folder}); write to another folder")
    if folder in out.parents:
        raise DatasetError(f"{flag} {out_dir}: lies in the source recording's folder {folder}; write to another folder")
    if ref.map_path is not None and out in ref.map_path.resolve().parents:
        raise DatasetError(f"{flag} {out_dir}: holds the source map {ref.map_path}; write to another folder")


def read_sources(data_dir: str | Path, recording: str, sequences: list[str] | None = None) -> tuple[Path | None, list[SourceSequence]]:
    """The map path and the selected sequences (default all) of an INTERACTION-format recording, as text rows."""
    ref = find_recording(data_dir, recording)
    if ref.format != FORMAT_INTERACTION:
        raise DatasetError(f"recording {recording}: superimpose reads INTERACTION-format recordings (TAF-BW) only, not {ref.format}")
    meta_path = ref.meta_path or (ref.folder / META_FILE)
    with open(meta_path, newline="", encoding="utf-8") as f:
        metas = {row["id"].strip(): row for row in csv.DictReader(f)}
    wanted = list(sequences) if sequences else list(ref.sequence_ids)
    twice = sorted({q for q in wanted if wanted.count(q) > 1})
    if twice:  # its copies would start at the same shifts: vehicle on vehicle under two ids
        raise DatasetError(f"--sequence {', '.join(twice)} given more than once; name each sequence once (the copies are made by --vehicles)")
    out = []
    for seq_id in wanted:
        files = sorted(p for p in ref.folder.iterdir() if (m := TRACK_FILE_RE.match(p.name)) and m.group(2) == seq_id)
        if not files:
            raise DatasetError(f"recording {recording}: no track file for sequence {seq_id!r}; available: {', '.join(ref.sequence_ids)}")
        meta = metas.get(seq_id) or metas.get(str(int(seq_id)).zfill(3))
        if meta is None:
            raise DatasetError(f"recording {recording}: {meta_path} has no row for sequence {seq_id}")
        for path in files:
            kind = TRACK_FILE_RE.match(path.name).group(1)
            with open(path, newline="", encoding="utf-8") as f:
                reader = csv.reader(f)
                header = tuple(h.strip() for h in next(reader))
                rows = tuple(tuple(r) for r in reader if r)
            for need in ("track_id", "timestamp_ms", "agent_type", "x", "y"):
                if need not in header:
                    raise DatasetError(f"{path}: no column {need!r}")
            it, ii, ia = header.index("timestamp_ms"), header.index("track_id"), header.index("agent_type")
            time_ms = np.array([int(round(float(r[it]))) for r in rows], dtype=np.int64)
            is_vehicle = {}  # per type name as written: a few names for the whole file
            vehicle = np.array([is_vehicle.setdefault(r[ia], agent_type_from_name(r[ia]).is_vehicle) for r in rows], dtype=np.bool_)
            out.append(SourceSequence(seq_id, kind, header, rows, dict(meta), time_ms,
                                      np.array([r[ii].strip() for r in rows], dtype=object), vehicle))
    return ref.map_path, out


def estimate_cycle_s(source: SourceSequence, *, low_s: float = 40.0, high_s: float = 150.0) -> float:
    """The signal cycle (s): the lag in [low_s, high_s] of the highest autocorrelation of the number of vehicles moving faster than 3 m/s."""
    cols = source.columns
    if "vx" not in cols or "vy" not in cols:
        raise DatasetError(f"sequence {source.id}: no vx/vy columns to estimate the signal cycle from; give --shift-s")
    ivx, ivy = cols.index("vx"), cols.index("vy")
    speed = np.array([math.hypot(float(r[ivx]), float(r[ivy])) for r in source.rows])
    frame = (source.time_ms // source.frame_ms).astype(np.int64)
    moving = np.zeros(int(frame.max()) + 1 if frame.size else 1)
    np.add.at(moving, frame, ((speed > 3.0) & source.vehicle).astype(float))
    x = moving - moving.mean()
    ac = np.correlate(x, x, "full")[x.size - 1 :]
    lags_s = np.arange(ac.size) * source.frame_ms / 1000.0
    sel = (lags_s >= low_s) & (lags_s <= high_s)
    if not np.any(sel):
        raise DatasetError(f"sequence {source.id} ({source.duration_ms / 1000:.0f} s) is too short to estimate a signal cycle; give --shift-s")
    return float(lags_s[sel][int(np.argmax(ac[sel]))])


def plan_layers(sources: list[SourceSequence], target_vehicles: float, *, shift_s: float, duration_s: float) -> list[Layer]:
    """Layers whose mean vehicles per frame add up to ``target_vehicles`` (at least one).

    The sources are taken in turn (all of them with shift 0 first, then again
    shifted by ``shift_s``, 2·``shift_s``, ...), each contributing its mean
    number of vehicles per frame (the sequence is tiled over ``duration_s``),
    whole while they fit; the rest of the target is one partial copy of the
    next (``Layer.share``: a share of its tracks), so that N = 18 gives about
    18, not the 19.8 of four whole K733 copies.
    """
    vehicle_sources = [i for i, s in enumerate(sources) if s.kind == "vehicle" and s.time_ms.size]
    if not vehicle_sources:
        raise DatasetError("no vehicle tracks to superimpose")
    layers: list[Layer] = []
    total = 0.0
    round_no = 0
    while round_no <= 10_000:
        for i in vehicle_sources:
            mean = sources[i].mean_per_frame()
            if total + mean > target_vehicles * (1.0 + 1e-9):
                rest = (target_vehicles - total) / mean if mean > 0 else 0.0
                if rest >= 0.02 or not layers:  # a sliver under 2 % of a copy is left out
                    layers.append(Layer(i, round_no * shift_s, share=min(max(rest, 0.02), 1.0)))
                return layers
            layers.append(Layer(i, round_no * shift_s))
            total += mean
        round_no += 1
    return layers


def _kept_rows(src: SourceSequence, layer: Layer) -> np.ndarray | None:
    """Which of the source's rows a partial layer writes (``Layer.share``: whole tracks, in the order of a hash of
    their ids, until their vehicle rows reach the share); None: all of them."""
    if layer.share >= 1.0:
        return None
    names = src.track_ids.astype(str)
    ids, inverse = np.unique(names, return_inverse=True)
    rows = np.bincount(inverse, weights=src.vehicle, minlength=ids.size).astype(np.int64)  # vehicle rows per track
    order = sorted(range(ids.size), key=lambda k: zlib.crc32(f"{ids[k]}@{layer.shift_s:.3f}".encode()))
    goal, kept, n = layer.share * float(rows.sum()), [], 0
    for k in order:
        if n >= goal:
            break
        kept.append(ids[k])
        n += int(rows[k])
    return np.isin(names, kept)


def superimpose(
    sources: list[SourceSequence],
    layers: list[Layer],
    out_dir: str | Path,
    name: str,
    *,
    duration_s: float,
    map_path: Path | None,
    licence_dir: Path | None = None,
    description: str = "",
) -> SuperimposeResult:
    """Write the superimposed recording ``name`` under ``out_dir`` (module docstring); returns what was written.

    Everything is written into a temporary folder inside ``out_dir`` first and moved into place when complete
    (``_commit``): the work takes seconds to minutes, and a failure or Ctrl-C on the way must leave an earlier
    recording of that name whole (deleting its tracks first left meta_data.csv without tracks) and nothing behind.
    """
    out_dir = Path(out_dir)
    check_name(name, "name")
    if not layers:
        raise DatasetError("superimpose: no layers")
    first = sources[layers[0].source]
    origin = (first.meta.get("originLat"), first.meta.get("originLon"))
    for layer in layers:
        meta = sources[layer.source].meta
        if (meta.get("originLat"), meta.get("originLon")) != origin:
            raise DatasetError(f"superimpose: sequence {sources[layer.source].id} has another origin than {first.id}: not the same map frame")
    frame_ms = first.frame_ms
    duration_ms = int(round(duration_s * 1000.0 / frame_ms)) * frame_ms
    if duration_ms <= 0:
        raise DatasetError(f"duration {duration_s:g} s: shorter than one frame ({frame_ms} ms); give a longer --duration-s")
    for layer in layers:
        if layer.shift_s != 0 and int(round(layer.shift_s * 1000.0 / frame_ms)) == 0:
            raise DatasetError(f"shift {layer.shift_s:g} s: shorter than one frame ({frame_ms} ms), the copies would coincide; "
                               "give a longer --shift-s")
    _check_distinct(sources, layers, frame_ms)
    track_dir = out_dir / TRACKS_DIR / name
    if track_dir.exists() and not track_dir.is_dir():
        raise DatasetError(f"superimpose: {track_dir} is a file, not a recording folder")
    if map_path is not None and (out_dir / MAPS_DIR / f"{name}.osm").resolve() == Path(map_path).resolve():
        raise DatasetError(f"superimpose: the map {map_path} would be written over itself; write to another folder")
    out_dir.mkdir(parents=True, exist_ok=True)
    _check_writable(out_dir, name)
    # a hidden folder beside maps/ and recorded_trackfiles/ (not in them: a reader listing recordings would see it),
    # on the output's file system, so that the moves into place are renames
    stage = Path(tempfile.mkdtemp(prefix=f".{name}.", suffix=".superimpose.tmp", dir=out_dir))
    try:
        result = _write(sources, layers, stage, name, first=first, frame_ms=frame_ms, duration_ms=duration_ms,
                        map_path=map_path, licence_dir=licence_dir, description=description)
        _commit(stage, out_dir, name)
    finally:  # also on KeyboardInterrupt: no temporary folder is left behind
        shutil.rmtree(stage, ignore_errors=True)
    return dataclasses.replace(result, out_dir=out_dir)


def _check_writable(out_dir: Path, name: str) -> None:
    """``DatasetError`` before the work where ``_commit`` could not move the new files into place: the output folder,
    its ``maps/`` and ``recorded_trackfiles/`` (where they exist) and an old recording folder of that name (moved aside:
    a folder moved to another parent needs write access to itself) must be writable folders."""
    need = [out_dir, out_dir / MAPS_DIR, out_dir / TRACKS_DIR, out_dir / TRACKS_DIR / name]
    for folder in need:
        if not folder.exists():
            continue
        if not folder.is_dir():
            raise DatasetError(f"{folder} is a file, not a folder; remove it or write to another --out")
        if not os.access(folder, os.W_OK | os.X_OK):
            raise DatasetError(f"{folder} is not writable: the new recording could not be moved into place; "
                               "make it writable or write to another --out")


def _shift_ms(layer: Layer, frame_ms: int, period_ms: int) -> int:
    """A layer's circular shift in ms: whole frames, modulo the source's length."""
    return (int(round(layer.shift_s * 1000.0 / frame_ms)) * frame_ms) % period_ms


def _check_distinct(sources: list[SourceSequence], layers: list[Layer], frame_ms: int) -> None:
    """``DatasetError`` where two layers copy one sequence with the same circular shift: their rows would coincide,
    vehicle on vehicle under two ids (shift 0, a shift that is a multiple of the sequence's length, or more rounds of
    a short sequence than it has frames)."""
    seen: dict[tuple[int, int], int] = {}
    for k, layer in enumerate(layers):
        src = sources[layer.source]
        if src.duration_ms <= 0:
            continue
        key = (layer.source, _shift_ms(layer, frame_ms, src.duration_ms))
        if key in seen:
            j = seen[key]
            raise DatasetError(
                f"copies {j} and {k} of sequence {src.id} would coincide (shifts {layers[j].shift_s:g} s and "
                f"{layer.shift_s:g} s are equal modulo its {src.duration_ms / 1000:g} s); give another --shift-s, fewer "
                "--vehicles or longer sequences")
        seen[key] = k


def _write(
    sources: list[SourceSequence],
    layers: list[Layer],
    out_dir: Path,
    name: str,
    *,
    first: SourceSequence,
    frame_ms: int,
    duration_ms: int,
    map_path: Path | None,
    licence_dir: Path | None,
    description: str,
) -> SuperimposeResult:
    """The recording's files under ``out_dir`` (a fresh folder: ``superimpose``'s temporary one)."""
    track_dir = out_dir / TRACKS_DIR / name
    track_dir.mkdir(parents=True)
    (out_dir / MAPS_DIR).mkdir()
    if map_path is not None:
        shutil.copyfile(map_path, out_dir / MAPS_DIR / f"{name}.osm")
    next_id = {"vehicle": 1, "pedestrian": 1}
    written: dict[str, list[tuple[int, int, list[str], bool]]] = {"vehicle": [], "pedestrian": []}  # (ms, id, values, vehicle)
    for layer in layers:
        src = sources[layer.source]
        period = src.duration_ms
        if period <= 0:
            continue
        shift_ms = _shift_ms(layer, frame_ms, period)
        local = np.mod(src.time_ms - shift_ms, period)
        wrapped = (src.time_ms - shift_ms) < 0  # rows moved to the end by the circular shift: another track part
        row_kept = _kept_rows(src, layer)
        cols = src.columns
        idx = {c: cols.index(c) for c in COLUMNS if c in cols}
        n_tiles = -(-duration_ms // period)
        ids: dict[tuple[int, bool, str], int] = {}
        for tile in range(n_tiles):
            t_out = local + tile * period
            keep = np.flatnonzero(t_out < duration_ms)
            if row_kept is not None:
                keep = keep[row_kept[keep]]
            for r in keep:
                key = (tile, bool(wrapped[r]), src.track_ids[r])
                new = ids.get(key)
                if new is None:
                    new = ids[key] = next_id[src.kind]
                    next_id[src.kind] += 1
                row = src.rows[r]
                values = []
                for c in COLUMNS:
                    if c not in idx:
                        continue
                    if c == "track_id":
                        values.append(f"P{new}" if src.kind == "pedestrian" else str(new))
                    elif c == "timestamp_ms":
                        values.append(str(int(t_out[r])))
                    elif c == "frame_id":
                        values.append(str(int(t_out[r]) // frame_ms))
                    else:
                        values.append(row[idx[c]])
                written[src.kind].append((int(t_out[r]), new, values, bool(src.vehicle[r])))
    n_rows = 0
    header = [c for c in COLUMNS if any(c in sources[layer.source].columns for layer in layers)]
    for kind, rows in written.items():
        if not rows:
            continue
        rows.sort(key=lambda x: (x[1], x[0]))
        cols_by_layer_ok = all(all(c in sources[layer.source].columns for c in header) for layer in layers if sources[layer.source].kind == kind)
        if not cols_by_layer_ok:
            raise DatasetError(f"superimpose: the {kind} sources have different columns; superimpose sequences of one recording")
        with open(track_dir / f"{kind}_tracks_000.csv", "w", newline="", encoding="utf-8") as f:
            w = csv.writer(f, lineterminator="\n")
            w.writerow(header)
            for _t, _id, values, _vehicle in rows:
                w.writerow(values)
        n_rows += len(rows)
    meta = {c: first.meta.get(c, "") for c in META_COLUMNS}
    meta["spatAvailable"] = first.meta.get("spatAvailable", first.meta.get("spatAvailible", "no"))
    meta.update(id="000", duration=f"{duration_ms / 1000:.1f}", simulated="superimposed")
    with open(track_dir / META_FILE, "w", newline="", encoding="utf-8") as f:
        w = csv.DictWriter(f, fieldnames=list(META_COLUMNS), lineterminator="\n")
        w.writeheader()
        w.writerow(meta)
    if licence_dir is not None and (licence_dir / "LICENSE").is_file():
        shutil.copyfile(licence_dir / "LICENSE", out_dir / "LICENSE")
    # vehicles per frame: rows of a vehicle type, of any file (K729's vehicle files hold pedestrians too)
    vehicle_times = np.array([t for rows in written.values() for t, _i, _v, vehicle in rows if vehicle], dtype=np.int64)
    n_frames = duration_ms // frame_ms
    counts_all = np.zeros(n_frames)
    if vehicle_times.size:
        frames, c = np.unique(vehicle_times // frame_ms, return_counts=True)
        counts_all[frames[frames < n_frames]] = c[frames < n_frames]
    lines = [
        f"# {name}: superimposed from TAF-BW tracks",
        "",
        "Derived data: the tracks of the sequences below, time-shifted (circularly, tiled over the duration) and",
        "superimposed with fresh track ids by `iamp data superimpose` (stages/lib/datasets/superimpose.py).",
        "Source: TAF-BW dataset, Karlsruhe Institute of Technology / FZI, CC BY-NC-SA 4.0 (see LICENSE);",
        "the derived recording is under the same licence, for non-commercial use.",
        "",
        description,
        "",
        "| layer | source sequence | shift s | share of its tracks |",
        "|---|---|---|---|",
    ]
    lines += [f"| {k} | {sources[l.source].id} | {l.shift_s:.1f} | {l.share:.2f} |" for k, l in enumerate(layers)]
    (out_dir / "ATTRIBUTION.md").write_text("\n".join(lines) + "\n", encoding="utf-8")
    return SuperimposeResult(
        out_dir=out_dir,
        name=name,
        layers=tuple(layers),
        duration_s=duration_ms / 1000.0,
        n_tracks=sum(v - 1 for v in next_id.values()),
        n_rows=n_rows,
        vehicles_mean=float(counts_all.mean()),
        vehicles_median=float(np.median(counts_all)),
        vehicles_max=int(counts_all.max()),
    )


def _commit(stage: Path, out_dir: Path, name: str) -> None:
    """Move what ``_write`` wrote into ``stage`` into ``out_dir``: first the recording folder, by renaming the old one
    aside and the new one in its place, then the map, LICENSE and ATTRIBUTION.md by renaming over the old ones (where
    the map cannot be moved, the old recording folder is put back: no recording without its map). The files of
    an old recording folder that are neither track files nor meta_data.csv (signal phases, a KML lane file) are
    copied into the new one first: the command always replaced only those (``the recording's files``)."""
    (out_dir / MAPS_DIR).mkdir(exist_ok=True)
    (out_dir / TRACKS_DIR).mkdir(exist_ok=True)
    new_dir, old_dir = stage / TRACKS_DIR / name, out_dir / TRACKS_DIR / name
    if old_dir.is_dir():
        for entry in old_dir.iterdir():
            if fnmatch.fnmatch(entry.name, "*_tracks_*.csv") or entry.name == META_FILE:
                continue
            if entry.is_dir() and not entry.is_symlink():
                shutil.copytree(entry, new_dir / entry.name, symlinks=True)
            else:
                shutil.copy2(entry, new_dir / entry.name, follow_symlinks=False)
    aside = stage / "replaced"
    if old_dir.is_dir():
        os.rename(old_dir, aside)
        try:
            os.rename(new_dir, old_dir)
        except BaseException:
            os.rename(aside, old_dir)
            raise
    else:
        os.rename(new_dir, old_dir)
    try:  # the map after the recording: where it cannot be moved, the recording goes back as it was (no new recording
        for path in sorted((stage / MAPS_DIR).iterdir()):  # beside an old map, nor a new map without its recording)
            os.replace(path, out_dir / MAPS_DIR / path.name)
    except BaseException:
        os.rename(old_dir, new_dir)
        if aside.is_dir():
            os.rename(aside, old_dir)
        raise
    for file in ("LICENSE", "ATTRIBUTION.md"):
        if (stage / file).is_file():
            os.replace(stage / file, out_dir / file)


def check_request(target_vehicles: float, *, shift_s: float | None = None, duration_s: float | None = None) -> None:
    """``DatasetError`` naming the flag where a number of a request is out of range (None: not given, not checked):
    vehicles in (0, ``MAX_VEHICLES``], shift in (0, ``MAX_SHIFT_S``] (0 stacks the rounds' copies of a sequence on one
    another), duration in (0, ``MAX_DURATION_S``], and vehicles x duration at most ``MAX_VEHICLE_SECONDS``."""
    numbers = [v for v in (target_vehicles, shift_s, duration_s) if v is not None]
    if not all(math.isfinite(v) for v in numbers):
        raise DatasetError("--vehicles, --shift-s and --duration-s must be finite numbers")
    if not 0 < target_vehicles <= MAX_VEHICLES:
        raise DatasetError(f"--vehicles {target_vehicles:g}: give a mean number of vehicles per frame above 0 and at most {MAX_VEHICLES}")
    if shift_s is not None and not 0 < shift_s <= MAX_SHIFT_S:
        raise DatasetError(f"--shift-s {shift_s:g}: give a shift above 0 s (0 stacks the copies of a sequence on one another) "
                           f"and at most {MAX_SHIFT_S:.0f} s")
    if duration_s is not None and not 0 < duration_s <= MAX_DURATION_S:
        raise DatasetError(f"--duration-s {duration_s:g}: give a duration above 0 s and at most {MAX_DURATION_S:.0f} s (a day)")
    if duration_s is not None and target_vehicles * duration_s > MAX_VEHICLE_SECONDS:
        raise DatasetError(f"--vehicles {target_vehicles:g} x --duration-s {duration_s:g} = {target_vehicles * duration_s:.3g} "
                           f"vehicle-seconds: at most {MAX_VEHICLE_SECONDS:.0f} (the rows are built in memory); give fewer vehicles or a shorter duration")


def build_dense(
    data_dir: str | Path,
    recording: str,
    target_vehicles: float,
    out_dir: str | Path,
    *,
    name: str | None = None,
    sequences: list[str] | None = None,
    shift_s: float | None = None,
    duration_s: float | None = None,
) -> SuperimposeResult:
    """``target_vehicles`` (mean per frame) superimposed from ``recording`` into ``out_dir`` (module docstring).

    ``shift_s`` default: the signal cycle estimated on the longest source
    sequence; ``duration_s`` default: the longest selected sequence; ``name``
    default: ``default_name``. A request out of range (``check_request``), a
    name that is not a plain folder name (``check_name``) or an output that
    overlaps the source (``check_out_apart``) raises ``DatasetError`` before
    anything is written.
    """
    check_request(target_vehicles, shift_s=shift_s, duration_s=duration_s)
    if name is not None:
        check_name(name)
    check_out_apart(out_dir, find_recording(data_dir, recording))
    map_path, sources = read_sources(data_dir, recording, sequences)
    vehicles = [s for s in sources if s.kind == "vehicle" and s.time_ms.size]
    if not vehicles:
        raise DatasetError(f"recording {recording}: no vehicle tracks")
    longest = max(vehicles, key=lambda s: s.duration_ms)
    if shift_s is None:
        shift_s = estimate_cycle_s(longest)
    if duration_s is None:
        duration_s = longest.duration_ms / 1000.0
    check_request(target_vehicles, shift_s=shift_s, duration_s=duration_s)  # the defaults too: the size of the output
    layers = plan_layers(sources, target_vehicles, shift_s=shift_s, duration_s=duration_s)
    name = default_name(recording, target_vehicles) if name is None else name
    description = (f"Target: {target_vehicles:g} vehicles per frame on average; shift step {shift_s:.1f} s"
                   f" (multiples of it per round over the sequences); duration {duration_s:.1f} s.")
    return superimpose(sources, layers, out_dir, name, duration_s=duration_s, map_path=map_path,
                       licence_dir=Path(data_dir), description=description)


__all__ = ["MAX_DURATION_S", "MAX_SHIFT_S", "MAX_VEHICLES", "MAX_VEHICLE_SECONDS", "Layer", "SourceSequence", "SuperimposeResult",
           "build_dense", "check_name", "check_out_apart", "check_request", "default_name", "estimate_cycle_s", "plan_layers",
           "read_sources", "superimpose"]
