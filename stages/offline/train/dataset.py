"""The AR training set: (x, mask, y) windows from recordings, built with the online feature code (docs/method.md §8.1).

``build_dataset(config)`` plays every selected sequence through the
in-process chain of ``iamp eval`` (``stages.offline.chain.Chain``:
``TrackPlayer`` → ``CorridorBuilder`` → ``RelationExtractor``, fresh cores
per sequence, maps loaded once) and feeds every frame to one
``FeatureTracker``, exactly as the online stage does. The ground truth is
``stages.offline.truth``'s, the one ``iamp eval`` scores against. A sample is taken at a frame (every
``sample_stride``-th frame, default every frame) for each matched vehicle
that

- has at least ``min_future_steps`` (10, 1 s) known targets among the 40
  steps of its 4 s true future: a position at t + 0.1 k s (its row within 20 ms, `truth.STAMP_TOL_NS`) with a
  finite target acceleration there (``future_targets``; else
  ``no_full_future`` when none is known, ``short_future`` when too few).
  The unknown steps are masked (``y_mask`` false, y 0): the loss and the
  validation figures count the known steps only. A window whose future is
  cut by the track's end (or its first 1.5 s without a target) is kept
  (``partial_future`` counts them), and so is a window whose history is
  shorter than 4 s (the input ``mask``, as online);
- followed one of its corridors (``corridor_errors``, the rule of
  ``stages.offline.truth.followed_corridor``): the corridor with the
  smallest maximum lateral distance |d| of the track's true positions over
  the next ``route_future_s`` 10 s (as far as the track goes; only positions
  whose projection falls within the corridor, at least 40 of them or all
  there are), at most ``max_route_error_m`` 2 m (else
  ``followed_no_corridor``). Every corridor that holds them within
  ``route_tie_m`` 0.5 m of the best is tied with it (before a branch, when
  the track ends before the routes part): the route is undecided
  (``route_tied``) and ``tied_routes`` decides (``route_weights``):
  ``weight`` (default) makes one sample per tied corridor with weight 1/k,
  the probability of each route when the future cannot tell them apart (the
  online stage predicts on every corridor of a car, so the model learns
  each of them); ``drop`` drops the window (dataset version 3: that made
  the linear net better than ``first``, docs/method.md §8.3); ``first``
  keeps it on the best one. Each sample carries its ``weight`` (1 for a
  decided route), which the loss and the validation figures use.

Dataset version 3 asked for the whole 4 s future and dropped tied routes:
60 cars gave windows (K729's car tracks last 4.2 s at the median). With
partial futures and weighted routes every car with at least 1 s of known
future gives windows (counts: ``ARDataset.sizes``, docs/method.md §8.3).

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

Augmentation (``position_noise_m`` > 0, ``iamp train --position-noise M``):
``PositionNoise`` jitters each track's positions (white noise of a σ drawn
per track from [0, M] m) before the corridors and relations cores see the
frame, so the features are those of a noisier tracker; the targets, the
route and the windows' futures stay those of the true positions
(docs/method.md §8.3).

Each sample carries (recording, sequence, track_id, corridor_id, stamp_ns) so
that splits can keep tracks together; ``sequence_spans`` gives each
sequence's first and last stamp for time splits.

Cache. Building all of TAF-BW takes about a minute on 2 cores, so
``build_dataset(..., cache_dir=...)`` keeps the arrays in
``<cache_dir>/ar_dataset_<key>.npz``, the key a hash of the data files'
contents (track files and maps of the selected recordings), the dataset and
feature config, ``FEATURE_NAMES``, ``DATASET_VERSION`` and the fingerprint of
the project's code (``stages.lib.fingerprint``: any change to ``stages/`` or
``bus_schemas/`` builds the data set again rather than reading what older code
built).
"""

from __future__ import annotations

from stages.lib.base import atomic_write, progress_bar

import dataclasses
import hashlib
import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from bus_schemas import MatchStatus, TrackFrame
from stages.corridors import SceneMaps
from stages.lib.datasets import DEFAULT_DATA_DIR, DatasetError, Recording, default_recordings, discover, load_recording
from stages.lib.datasets.warp import time_warped
from stages.lib.fingerprint import code_fingerprint
from stages.offline.chain import Chain
from stages.offline.truth import (
    ACCEL_EDGE_S,
    ACCEL_WINDOW_S,
    ROUTE_MAX_ERROR_M,
    ROUTE_TIE_M,
    ground_truth,
    positions_after,
    rows_near,
    smoothed_acceleration,
)
from stages.lib.datasets.report import report_lines
from stages.lib.maps import project_to_polyline
from stages.tracks_source.core import file_sha256

from stages.lib.ar.features import ACCEL, FEATURE_NAMES, HISTORY_STEPS, HORIZON_STEPS, N_FEATURES, STEP_S, FeatureConfig, FeatureTracker

DATASET_VERSION = 5
"""Bump when the sample definition changes (invalidates caches). 5: a row within 20 ms of a step's time (was 1 ms)."""
_STEP_NS = int(round(STEP_S * 1e9))
TIED_ROUTES = ("weight", "drop", "first")
"""What a window whose route the future cannot decide gives (module docstring): one sample per tied corridor with
weight 1/k (``weight``, default), none (``drop``, version 3's behaviour) or one on the first tied corridor (``first``)."""


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
    tied_routes: str = "weight"
    min_future_steps: int = 10
    features: FeatureConfig = field(default_factory=FeatureConfig)
    #: Augmentation (``PositionNoise``): each track's positions jittered by white isotropic Gaussian noise of a σ drawn
    #: per track uniformly from [0, position_noise_m] m before the cores see them; targets and routes stay from the
    #: true positions. 0: off (the samples of the data set without it).
    position_noise_m: float = 0.0
    noise_seed: int = 0
    #: Augmentation (``stages.lib.datasets.warp.time_warped``): each sequence is also played at each of these speed
    #: factors (time scaled by 1/f, the whole scene together), its samples in the split of the sequence they come from
    #: and stamped in its time (stamp · f). (): off.
    speed_factors: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        if self.sample_stride < 1:
            raise ValueError(f"sample_stride = {self.sample_stride}: must be >= 1")
        if self.tied_routes not in TIED_ROUTES:
            raise ValueError(f"tied_routes = {self.tied_routes!r}: expected one of {', '.join(TIED_ROUTES)}")
        if not (1 <= self.min_future_steps <= HORIZON_STEPS):
            raise ValueError(f"min_future_steps = {self.min_future_steps}: must lie in [1, {HORIZON_STEPS}]")
        if self.max_frames_per_sequence < 0:
            raise ValueError(f"max_frames_per_sequence = {self.max_frames_per_sequence}: must be >= 0 (0: all)")
        if not (math.isfinite(self.target_edge_s) and self.target_edge_s >= 0):
            raise ValueError(f"target_edge_s = {self.target_edge_s!r}: must be >= 0")
        if not (math.isfinite(self.position_noise_m) and 0 <= self.position_noise_m <= 10):
            raise ValueError(f"position_noise_m = {self.position_noise_m!r}: must lie in [0, 10] m")
        factors = [float(f) for f in self.speed_factors]
        if any(not (math.isfinite(f) and 0.5 <= f <= 2.0) or f == 1.0 for f in factors) or len(set(factors)) != len(factors):
            raise ValueError(f"speed_factors = {self.speed_factors!r}: distinct factors in [0.5, 2], none 1 (the sequence as"
                             " recorded is always played)")
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
            "tied_routes": self.tied_routes,
            "min_future_steps": self.min_future_steps,
            "features": dataclasses.asdict(self.features),
            "feature_names": list(FEATURE_NAMES),
            "history": HISTORY_STEPS,
            "horizon": HORIZON_STEPS,
            "version": DATASET_VERSION,
            "code": code_fingerprint(),  # the code that builds the samples (corridors, relations, features): a change rebuilds
            # only when on, so that the keys (and caches) of data sets without it stay what they were
            **({"position_noise_m": self.position_noise_m, "noise_seed": self.noise_seed} if self.position_noise_m > 0 else {}),
            **({"speed_factors": [float(f) for f in self.speed_factors]} if self.speed_factors else {}),
        }


@dataclass(frozen=True, eq=False)
class ARDataset:
    """Samples (N of them) and where each comes from.

    x (N, 40, F) float32 features (``FEATURE_NAMES``), mask (N, 40) bool,
    y (N, 40) float32 target accelerations (m/s²) at 0.1 … 4.0 s (0 where
    unknown), y_mask (N, 40) bool the known ones, weight (N,) float32 the
    sample's weight (1, or 1/k for one of k tied routes);
    recording/sequence (N,) int32 indices into ``recordings``/``sequences``
    (a sequence name is ``"<recording>/<id>"``), track_id, corridor_id,
    stamp_ns (N,) int64. ``sequence_spans`` (S, 2) int64: first and last
    stamp of each sequence (of the frames played). ``counts``: samples kept and windows skipped, by
    reason.
    """

    x: np.ndarray
    mask: np.ndarray
    y: np.ndarray
    y_mask: np.ndarray
    weight: np.ndarray
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
    def tracks(self) -> int:
        """How many cars (distinct sequence and track) give samples."""
        return len({(int(s), int(t)) for s, t in zip(self.sequence, self.track_id)})

    def sizes(self) -> dict[str, Any]:
        """Samples, windows (weighted: a tied window counts once), cars, and the full-future share, overall and per recording."""
        def one(sel: np.ndarray) -> dict[str, Any]:
            full = self.y_mask[sel].all(axis=1)
            return {"samples": int(sel.sum()), "windows": round(float(self.weight[sel].sum()), 3),
                    "cars": len({(int(s), int(t)) for s, t in zip(self.sequence[sel], self.track_id[sel])}),
                    "full_future_samples": int(full.sum()), "short_history_samples": int((~self.mask[sel].all(axis=1)).sum()),
                    "known_target_steps": int(self.y_mask[sel].sum())}
        every = np.ones(len(self), dtype=bool)
        return one(every) | {"by_recording": {name: one(self.recording == r) for r, name in enumerate(self.recordings)}}

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
            y_mask=self.y_mask[index],
            weight=self.weight[index],
            recording=self.recording[index],
            sequence=self.sequence[index],
            track_id=self.track_id[index],
            corridor_id=self.corridor_id[index],
            stamp_ns=self.stamp_ns[index],
        )

    def save(self, path: Path) -> None:
        with atomic_write(path) as handle:  # (two trainings building one cached data set at once: both succeed)
            self._write(handle)

    def _write(self, handle) -> None:
        np.savez_compressed(
            handle,
            x=self.x, mask=self.mask, y=self.y, y_mask=self.y_mask, weight=self.weight, recording=self.recording, sequence=self.sequence, track_id=self.track_id,
            corridor_id=self.corridor_id, stamp_ns=self.stamp_ns, sequence_spans=self.sequence_spans,
            meta=np.array(json.dumps({"recordings": self.recordings, "sequences": self.sequences, "counts": self.counts, "key": self.key})),
        )

    @classmethod
    def load(cls, path: Path) -> "ARDataset":
        with np.load(path, allow_pickle=False) as z:
            meta = json.loads(str(z["meta"]))
            return cls(
                x=z["x"], mask=z["mask"], y=z["y"], y_mask=z["y_mask"], weight=z["weight"], recording=z["recording"], sequence=z["sequence"], track_id=z["track_id"],
                corridor_id=z["corridor_id"], stamp_ns=z["stamp_ns"], sequence_spans=z["sequence_spans"],
                recordings=tuple(meta["recordings"]), sequences=tuple(meta["sequences"]), counts=dict(meta["counts"]), key=meta["key"],
            )


# --------------------------------------------------------------------------- targets
# ``smoothed_acceleration`` (the targets), the tracks, their futures and the followed corridor: ``stages.offline.truth``.


# --------------------------------------------------------------------------- targets and routes of one window


def future_targets(track, stamp_ns: int, step_ns: int, n_steps: int) -> tuple[np.ndarray, np.ndarray]:
    """(accelerations (n_steps,), known (n_steps,) bool) of the true track at t + k·step (its row within ``truth.STAMP_TOL_NS``), k = 1..n_steps.

    A step is known when the track has a row there with a finite target
    (``Track.accel_mps2``); unknown steps hold NaN. No track: nothing known.
    """
    accel = np.full(n_steps, np.nan)
    if track is None or track.stamps_ns.shape[0] == 0:
        return accel, np.zeros(n_steps, dtype=bool)
    i, found = rows_near(track.stamps_ns, int(stamp_ns) + int(step_ns) * np.arange(1, n_steps + 1))
    accel[found] = track.accel_mps2[i[found]]
    return accel, np.isfinite(accel)


def corridor_errors(corridors, future_xy: np.ndarray, *, min_inside: int = 1) -> np.ndarray:
    """(len(corridors),) max |d| (m) of the future positions within each corridor; inf where fewer than `min_inside` fall in it.

    ``stages.offline.truth.followed_corridor``'s rule for every corridor (that one keeps the best two).
    """
    future_xy = np.asarray(future_xy, dtype=np.float64).reshape(-1, 2)
    need = max(int(min_inside), 1)
    errors = np.full(len(corridors), np.inf)
    if future_xy.shape[0] == 0:
        return errors
    for k, c in enumerate(corridors):
        proj = project_to_polyline(future_xy, np.column_stack([c.x_m, c.y_m]), c.s_m)
        inside = (proj.s_m >= c.s_m[0]) & (proj.s_m <= c.s_m[-1])
        if int(inside.sum()) >= need:
            errors[k] = float(np.max(np.abs(proj.d_m[inside])))
    return errors


def route_weights(errors: np.ndarray, max_error_m: float, tie_m: float, tied_routes: str) -> tuple[list[tuple[int, float]], str | None]:
    """The corridors a window is a sample on, with their weights, and why the route was not single (None when it was).

    The best corridor (smallest error, the first of equals) is followed when
    its error is at most `max_error_m` (else ``"followed_no_corridor"``, no
    sample). Every corridor within `tie_m` of it is tied with it (``"route_tied"``,
    ``stages.offline.truth.route_decision``'s rule); then `tied_routes`:
    ``weight``: each of the k tied corridors with weight 1/k (the future
    cannot tell them apart, so each is as probable); ``drop``: none;
    ``first``: the best one with weight 1.
    """
    errors = np.asarray(errors, dtype=np.float64)
    if errors.size == 0:
        return [], "followed_no_corridor"
    best = int(np.argmin(errors))
    if not errors[best] <= max_error_m:
        return [], "followed_no_corridor"
    tied = np.flatnonzero(errors - errors[best] < tie_m)
    if tied.size <= 1:
        return [(best, 1.0)], None
    if tied_routes == "drop":
        return [], "route_tied"
    if tied_routes == "first":
        return [(best, 1.0)], "route_tied"
    return [(int(i), 1.0 / tied.size) for i in tied], "route_tied"


# --------------------------------------------------------------------------- building


@dataclass(slots=True)
class _Collector:
    x: list[np.ndarray] = field(default_factory=list)
    mask: list[np.ndarray] = field(default_factory=list)
    y: list[np.ndarray] = field(default_factory=list)
    y_mask: list[np.ndarray] = field(default_factory=list)
    weight: list[float] = field(default_factory=list)
    recording: list[int] = field(default_factory=list)
    sequence: list[int] = field(default_factory=list)
    track_id: list[int] = field(default_factory=list)
    corridor_id: list[int] = field(default_factory=list)
    stamp_ns: list[int] = field(default_factory=list)
    counts: dict[str, int] = field(default_factory=dict)

    def count(self, reason: str, n: int = 1) -> None:
        self.counts[reason] = self.counts.get(reason, 0) + n


class PositionNoise:
    """A TrackFrame hook that jitters positions like a noisier tracker (``DatasetConfig.position_noise_m``).

    Each track id gets a σ drawn uniformly from [0, ``max_m``] when first seen (so the samples span trackers from
    clean to ``max_m``, not one noise level); every frame its x and y get independent N(0, σ²) noise. Reported
    velocities are left as they are (the stages derive speed from positions and check the reported one against
    them). Deterministic for a given ``seed`` (any ``np.random.default_rng`` seed) and frame order.
    """

    def __init__(self, max_m: float, seed) -> None:
        self.max_m = float(max_m)
        self._rng = np.random.default_rng(seed)
        self._sigma: dict[int, float] = {}

    def __call__(self, frame: TrackFrame) -> TrackFrame:
        n = len(frame)
        if n == 0 or self.max_m <= 0:
            return frame
        sigma = np.array([self._sigma.setdefault(int(t), float(self._rng.uniform(0.0, self.max_m))) for t in frame.track_ids])
        noise = self._rng.standard_normal((2, n)) * sigma
        return dataclasses.replace(frame, x_m=frame.x_m + noise[0], y_m=frame.y_m + noise[1])


def _sequence_samples(cfg: DatasetConfig, rec: Recording, seq, map_sha256: str, scene_maps: SceneMaps, rec_index: int,
                      seq_index: int, out: _Collector, bar, factor: float = 1.0) -> tuple[int, int]:
    """Adds the samples of one sequence to `out`; returns the first and last stamp played. ``factor`` != 1: ``seq`` is
    the time-warped copy of sequence ``seq_index`` at that speed factor; its samples are stamped in the source's time."""
    salt = (cfg.noise_seed, rec_index, seq_index) if factor == 1.0 else (cfg.noise_seed, rec_index, seq_index, int(round(factor * 1000)))
    noise = PositionNoise(cfg.position_noise_m, salt) if cfg.position_noise_m > 0 else None
    chain = Chain(rec, seq, scene_maps, max_frames=cfg.max_frames_per_sequence, map_sha256=map_sha256, run_id="ar-dataset",
                  frame_hook=noise)
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
        wanted: dict[tuple[int, int], tuple[np.ndarray, np.ndarray, float]] = {}
        for vehicle in corridor_set.vehicles:
            if vehicle.status != MatchStatus.MATCHED or not vehicle.corridors:
                continue
            track = truth.get(vehicle.track_id)
            accel, known = future_targets(track, stamp, _STEP_NS, HORIZON_STEPS)
            n_known = int(known.sum())
            if n_known < cfg.min_future_steps:  # too little of the 4 s future has a target
                out.count("no_full_future" if n_known == 0 else "short_future")
                continue
            future = positions_after(track, stamp, cfg.route_future_s)
            errors = corridor_errors(vehicle.corridors, future, min_inside=min(HORIZON_STEPS, max(len(future), 1)))
            chosen, why = route_weights(errors, cfg.max_route_error_m, cfg.route_tie_m, cfg.tied_routes)
            if why is not None:
                out.count(why)
            if not chosen:
                continue
            if n_known < HORIZON_STEPS:
                out.count("partial_future")
            for index, weight in chosen:
                wanted[(vehicle.track_id, int(vehicle.corridors[index].corridor_id))] = (accel, known, weight)
        if not wanted:
            continue
        keys, x, mask = tracker.batch(corridor_set, pairs=wanted)
        for k, key in enumerate(keys):
            out.x.append(x[k])
            out.mask.append(mask[k])
            accel, known, weight = wanted[key]
            out.y.append(np.where(known, accel, 0.0).astype(np.float32))
            out.y_mask.append(known.copy())
            out.weight.append(weight)
            out.recording.append(rec_index)
            out.sequence.append(seq_index)
            out.track_id.append(key[0])
            out.corridor_id.append(key[1])
            out.stamp_ns.append(int(stamp) if factor == 1.0 else int(round(stamp * factor)))
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
        for line in report_lines(rec.name, rec.report.as_dict()):  # rows the loader left out or changed: fewer samples
            say(line)
    plays = 1 + len(cfg.speed_factors)  # (a warped copy has about n_frames / f frames: the bar's total is a guess)
    total = plays * sum(min(s.n_frames, cfg.max_frames_per_sequence) if cfg.max_frames_per_sequence else s.n_frames for r in recordings for s in r.sequences)
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
                for factor in cfg.speed_factors:
                    _sequence_samples(cfg, rec, time_warped(seq, float(factor)), sha, scene_maps, r, len(seq_names) - 1, out, bar,
                                      factor=float(factor))
    finally:
        bar.close()
    n = len(out.y)
    out.count("samples", n)
    ds = ARDataset(
        x=np.stack(out.x) if n else np.zeros((0, HISTORY_STEPS, N_FEATURES), np.float32),
        mask=np.stack(out.mask) if n else np.zeros((0, HISTORY_STEPS), bool),
        y=np.stack(out.y) if n else np.zeros((0, HORIZON_STEPS), np.float32),
        y_mask=np.stack(out.y_mask) if n else np.zeros((0, HORIZON_STEPS), bool),
        weight=np.asarray(out.weight, dtype=np.float32),
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




__all__ = ["ARDataset", "DATASET_VERSION", "DatasetConfig", "PositionNoise", "build_dataset", "dataset_key", "smoothed_acceleration"]
