"""The AR training set: (x, mask, y) windows from recordings, built with the online feature code (docs/method.md §8.1).

``build_dataset(config)`` plays every selected sequence through the
in-process chain of ``iamp eval`` (``stages.offline.chain.Chain``:
``TrackPlayer`` → ``CorridorBuilder`` → ``RelationExtractor``, fresh cores
per sequence, maps loaded once) and feeds every frame to one
``FeatureTracker``, exactly as the online stage does. The ground truth is
``stages.offline.truth``'s, the one ``iamp eval`` scores against. A sample is taken at a frame (every
``sample_stride``-th frame, default every frame) for each matched vehicle
that

- has a full 4 s true future: positions at t + 0.1 k s, k = 1..40 (±1 ms)
  with a finite target acceleration at each (else ``skipped.no_full_future``);
- followed one of its corridors (``stages.offline.truth.followed_corridor``):
  the corridor with the smallest maximum lateral distance |d| of the
  track's true positions over the next ``route_future_s`` 10 s (as far as
  the track goes; only positions whose projection falls within the
  corridor, at least the 40 of the 4 s future), at most
  ``max_route_error_m`` 2 m (else
  ``skipped.followed_no_corridor``). When another corridor holds them
  within ``route_tie_m`` 0.5 m as well (before a branch, when the track ends
  before the routes part) the route is undecided: the sample is dropped
  (``route_tied``, ``skip_tied`` true): a sample on an arbitrary one of
  the tied corridors carries the curvature of a route the car may not take,
  and keeping them made the nets worse (measured: docs/method.md §8.3).

Few cars give windows, most of them standing at a signal (docs/method.md
§8.3).

x and mask are ``FeatureTracker.batch`` for that (vehicle, corridor); y are
the vehicle's longitudinal accelerations at t + 0.1 … 4.0 s from its true
future, smoothed NON-causally: per track (split where stamps skip), the
velocity is the Savitzky–Golay derivative (degree 2) of x and y over
``target_window_s`` (15 samples, 1.4 s at 10 Hz), the speed its norm, and
the acceleration the Savitzky–Golay derivative of that speed over the same
window; the first and last ``target_edge_s`` 1.5 s of each track get none
(NaN: no window uses them). Why the edges: the K733 tracker settles at a
track's ends, and there the edges dominated the error; 15 samples is the
compromise between the noise on K733 and the detail lost on K729
(measured: docs/method.md §8.3).

Each sample carries (recording, sequence, track_id, corridor_id, stamp_ns) so
that splits can keep tracks together; ``sequence_spans`` gives each
sequence's first and last stamp for time splits.

Cache. Building all of TAF-BW takes about a minute on 2 cores, so
``build_dataset(..., cache_dir=...)`` keeps the arrays in
``<cache_dir>/ar_dataset_<key>.npz``, the key a hash of the data files'
contents (track files and maps of the selected recordings), the dataset and
feature config, ``FEATURE_NAMES`` and ``DATASET_VERSION``.
"""

from __future__ import annotations

from stages.lib.base import progress_bar

import dataclasses
import hashlib
import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from bus_schemas import MatchStatus
from stages.corridors import SceneMaps
from stages.lib.datasets import DEFAULT_DATA_DIR, DatasetError, Recording, default_recordings, discover, load_recording
from stages.offline.chain import Chain
from stages.offline.truth import (
    ACCEL_EDGE_S,
    ACCEL_WINDOW_S,
    ROUTE_MAX_ERROR_M,
    ROUTE_TIE_M,
    followed_corridor,
    future_accelerations,
    ground_truth,
    positions_after,
    route_decision,
    smoothed_acceleration,
)
from stages.tracks_source.core import file_sha256

from stages.lib.ar.features import ACCEL, FEATURE_NAMES, HISTORY_STEPS, HORIZON_STEPS, N_FEATURES, STEP_S, FeatureConfig, FeatureTracker

DATASET_VERSION = 3
"""Bump when the sample definition changes (invalidates caches)."""
_STEP_NS = int(round(STEP_S * 1e9))


@dataclass(frozen=True, kw_only=True)
class DatasetConfig:
    """What to build from (module docstring). Empty ``recordings``/``sequences``: all."""

    data_dir: Path = DEFAULT_DATA_DIR
    recordings: tuple[str, ...] = ()
    sequences: tuple[str, ...] = ()
    max_frames_per_sequence: int = 0
    sample_stride: int = 1
    target_window_s: float = ACCEL_WINDOW_S
    target_edge_s: float = ACCEL_EDGE_S
    max_route_error_m: float = ROUTE_MAX_ERROR_M
    route_tie_m: float = ROUTE_TIE_M
    route_future_s: float = 10.0
    skip_tied: bool = True
    features: FeatureConfig = field(default_factory=FeatureConfig)

    def __post_init__(self) -> None:
        if self.sample_stride < 1:
            raise ValueError(f"sample_stride = {self.sample_stride}: must be >= 1")
        if self.max_frames_per_sequence < 0:
            raise ValueError(f"max_frames_per_sequence = {self.max_frames_per_sequence}: must be >= 0 (0: all)")
        if not (math.isfinite(self.target_edge_s) and self.target_edge_s >= 0):
            raise ValueError(f"target_edge_s = {self.target_edge_s!r}: must be >= 0")
        for name in ("target_window_s", "max_route_error_m", "route_tie_m", "route_future_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} = {value!r}: must be > 0")

    def key_dict(self) -> dict[str, Any]:
        """Everything but the data folder's location that decides the samples."""
        return {
            "recordings": list(self.recordings),
            "sequences": list(self.sequences),
            "max_frames_per_sequence": self.max_frames_per_sequence,
            "sample_stride": self.sample_stride,
            "target_window_s": self.target_window_s,
            "target_edge_s": self.target_edge_s,
            "max_route_error_m": self.max_route_error_m,
            "route_tie_m": self.route_tie_m,
            "route_future_s": self.route_future_s,
            "skip_tied": self.skip_tied,
            "features": dataclasses.asdict(self.features),
            "feature_names": list(FEATURE_NAMES),
            "history": HISTORY_STEPS,
            "horizon": HORIZON_STEPS,
            "version": DATASET_VERSION,
        }


@dataclass(frozen=True, eq=False)
class ARDataset:
    """Samples (N of them) and where each comes from.

    x (N, 40, F) float32 features (``FEATURE_NAMES``), mask (N, 40) bool,
    y (N, 40) float32 target accelerations (m/s²) at 0.1 … 4.0 s;
    recording/sequence (N,) int32 indices into ``recordings``/``sequences``
    (a sequence name is ``"<recording>/<id>"``), track_id, corridor_id,
    stamp_ns (N,) int64. ``sequence_spans`` (S, 2) int64: first and last
    stamp of each sequence (of the frames played). ``counts``: samples kept and windows skipped, by
    reason.
    """

    x: np.ndarray
    mask: np.ndarray
    y: np.ndarray
    recording: np.ndarray
    sequence: np.ndarray
    track_id: np.ndarray
    corridor_id: np.ndarray
    stamp_ns: np.ndarray
    recordings: tuple[str, ...]
    sequences: tuple[str, ...]
    sequence_spans: np.ndarray
    counts: dict[str, int]
    key: str = ""

    def __len__(self) -> int:
        return int(self.y.shape[0])

    @property
    def last_acceleration(self) -> np.ndarray:
        """(N,) the last observed causal acceleration feature (the "last value held" predictor)."""
        return self.x[:, -1, ACCEL]

    def subset(self, index: np.ndarray) -> "ARDataset":
        index = np.asarray(index, dtype=np.int64)
        return dataclasses.replace(
            self,
            x=self.x[index],
            mask=self.mask[index],
            y=self.y[index],
            recording=self.recording[index],
            sequence=self.sequence[index],
            track_id=self.track_id[index],
            corridor_id=self.corridor_id[index],
            stamp_ns=self.stamp_ns[index],
        )

    def save(self, path: Path) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp.npz")
        np.savez_compressed(
            tmp,
            x=self.x, mask=self.mask, y=self.y, recording=self.recording, sequence=self.sequence, track_id=self.track_id,
            corridor_id=self.corridor_id, stamp_ns=self.stamp_ns, sequence_spans=self.sequence_spans,
            meta=np.array(json.dumps({"recordings": self.recordings, "sequences": self.sequences, "counts": self.counts, "key": self.key})),
        )
        tmp.replace(path)

    @classmethod
    def load(cls, path: Path) -> "ARDataset":
        with np.load(path, allow_pickle=False) as z:
            meta = json.loads(str(z["meta"]))
            return cls(
                x=z["x"], mask=z["mask"], y=z["y"], recording=z["recording"], sequence=z["sequence"], track_id=z["track_id"],
                corridor_id=z["corridor_id"], stamp_ns=z["stamp_ns"], sequence_spans=z["sequence_spans"],
                recordings=tuple(meta["recordings"]), sequences=tuple(meta["sequences"]), counts=dict(meta["counts"]), key=meta["key"],
            )


# --------------------------------------------------------------------------- targets
# ``smoothed_acceleration`` (the targets), the tracks, their futures and the followed corridor: ``stages.offline.truth``.


# --------------------------------------------------------------------------- building


@dataclass(slots=True)
class _Collector:
    x: list[np.ndarray] = field(default_factory=list)
    mask: list[np.ndarray] = field(default_factory=list)
    y: list[np.ndarray] = field(default_factory=list)
    recording: list[int] = field(default_factory=list)
    sequence: list[int] = field(default_factory=list)
    track_id: list[int] = field(default_factory=list)
    corridor_id: list[int] = field(default_factory=list)
    stamp_ns: list[int] = field(default_factory=list)
    counts: dict[str, int] = field(default_factory=dict)

    def count(self, reason: str, n: int = 1) -> None:
        self.counts[reason] = self.counts.get(reason, 0) + n


def _sequence_samples(cfg: DatasetConfig, rec: Recording, seq, map_sha256: str, scene_maps: SceneMaps, rec_index: int,
                      seq_index: int, out: _Collector, bar) -> tuple[int, int]:
    """Adds the samples of one sequence to `out`; returns the first and last stamp played."""
    chain = Chain(rec, seq, scene_maps, max_frames=cfg.max_frames_per_sequence, map_sha256=map_sha256, run_id="ar-dataset")
    tracker = FeatureTracker(cfg.features)
    truth = ground_truth(seq, accel_window_s=cfg.target_window_s, accel_edge_s=cfg.target_edge_s)
    span: list[int] = []
    for item in chain:
        bar.update(1)
        stamp, frame, corridor_set, relation_set = item.stamp_ns, item.frame, item.corridor_set, item.relation_set
        span = [span[0] if span else stamp, stamp]
        for issue in tracker.update(corridor_set, relation_set, frame):
            out.count(f"issue_{issue.kind}")
        if item.index % cfg.sample_stride:
            continue
        wanted: dict[tuple[int, int], np.ndarray] = {}
        for vehicle in corridor_set.vehicles:
            if vehicle.status != MatchStatus.MATCHED or not vehicle.corridors:
                continue
            track = truth.get(vehicle.track_id)
            accel = future_accelerations(track, stamp, _STEP_NS, HORIZON_STEPS)
            if accel is None:  # not all 40 future stamps, or an acceleration unknown there
                out.count("no_full_future")
                continue
            followed = followed_corridor(vehicle.corridors, positions_after(track, stamp, cfg.route_future_s), min_inside=HORIZON_STEPS)
            why = route_decision(followed, cfg.max_route_error_m, cfg.route_tie_m)
            if why is not None:
                out.count(why)
                if why != "route_tied" or cfg.skip_tied:
                    continue
            wanted[(vehicle.track_id, int(vehicle.corridors[followed.index].corridor_id))] = accel
        if not wanted:
            continue
        keys, x, mask = tracker.batch(corridor_set, pairs=wanted)
        for k, key in enumerate(keys):
            out.x.append(x[k])
            out.mask.append(mask[k])
            out.y.append(wanted[key].astype(np.float32))
            out.recording.append(rec_index)
            out.sequence.append(seq_index)
            out.track_id.append(key[0])
            out.corridor_id.append(key[1])
            out.stamp_ns.append(int(stamp))
        out.count("no_feature_row", len(wanted) - len(keys))
    return (span[0], span[1]) if span else (0, 0)


def dataset_key(cfg: DatasetConfig) -> str:
    """Hash of the selected recordings' files (contents) and the config (module docstring), 16 hex digits."""
    digest = hashlib.sha256(json.dumps(cfg.key_dict(), sort_keys=True).encode())
    refs = discover(cfg.data_dir)
    names = set(cfg.recordings) or set(default_recordings(cfg.data_dir, [ref.name for ref in refs]))
    for ref in refs:
        if names and ref.name not in names:
            continue
        digest.update(ref.name.encode())
        for path in sorted(ref.track_files) + ([ref.meta_path] if ref.meta_path else []) + ([ref.map_path] if ref.map_path else []):
            digest.update(path.name.encode())
            digest.update(file_sha256(path).encode())
    return digest.hexdigest()[:16]


def build_dataset(cfg: DatasetConfig, *, cache_dir: Path | None = None, progress: bool = False, log=None) -> ARDataset:
    """The samples of the module docstring; read from / written to the cache when `cache_dir` is given.

    Raises ``DatasetError`` (a ValueError) for a missing folder or recording.
    """
    say = log or (lambda msg: None)
    key = dataset_key(cfg)
    cached = cache_dir / f"ar_dataset_{key}.npz" if cache_dir is not None else None
    if cached is not None and cached.is_file():
        try:
            ds = ARDataset.load(cached)
            say(f"data set from cache {cached} ({len(ds)} samples)")
            return ds
        except (OSError, ValueError, KeyError) as exc:
            say(f"cache {cached} unreadable ({exc}); rebuilding")
    t0 = time.perf_counter()
    names = list(cfg.recordings) or default_recordings(cfg.data_dir, [ref.name for ref in discover(cfg.data_dir)])
    recordings = [load_recording(cfg.data_dir, name, tuple(cfg.sequences) or None) for name in names]
    for rec in recordings:
        if rec.map_path is None:
            raise DatasetError(f"recording {rec.name} has no map: expected maps/{rec.name}.osm in {cfg.data_dir}")
    total = sum(min(s.n_frames, cfg.max_frames_per_sequence) if cfg.max_frames_per_sequence else s.n_frames for r in recordings for s in r.sequences)
    bar = progress_bar(total, progress, unit="frame", desc="iamp train: features")
    out = _Collector()
    scene_maps = SceneMaps(data=cfg.data_dir)
    seq_names: list[str] = []
    spans: list[tuple[int, int]] = []
    try:
        for r, rec in enumerate(recordings):
            sha = file_sha256(rec.map_path)
            for seq in rec.sequences:
                seq_names.append(f"{rec.name}/{seq.id}")
                spans.append(_sequence_samples(cfg, rec, seq, sha, scene_maps, r, len(seq_names) - 1, out, bar))
    finally:
        bar.close()
    n = len(out.y)
    out.count("samples", n)
    ds = ARDataset(
        x=np.stack(out.x) if n else np.zeros((0, HISTORY_STEPS, N_FEATURES), np.float32),
        mask=np.stack(out.mask) if n else np.zeros((0, HISTORY_STEPS), bool),
        y=np.stack(out.y) if n else np.zeros((0, HORIZON_STEPS), np.float32),
        recording=np.asarray(out.recording, dtype=np.int32),
        sequence=np.asarray(out.sequence, dtype=np.int32),
        track_id=np.asarray(out.track_id, dtype=np.int64),
        corridor_id=np.asarray(out.corridor_id, dtype=np.int64),
        stamp_ns=np.asarray(out.stamp_ns, dtype=np.int64),
        recordings=tuple(names),
        sequences=tuple(seq_names),
        sequence_spans=np.asarray(spans, dtype=np.int64).reshape(-1, 2),
        counts=dict(sorted(out.counts.items())),
        key=key,
    )
    say(f"data set built in {time.perf_counter() - t0:.1f} s: {n} samples")
    if cached is not None:
        ds.save(cached)
        say(f"cached in {cached}")
    return ds




__all__ = ["ARDataset", "DATASET_VERSION", "DatasetConfig", "build_dataset", "dataset_key", "smoothed_acceleration"]
