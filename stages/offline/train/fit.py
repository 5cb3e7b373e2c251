"""Training the AR acceleration model (``iamp train``, docs/method.md §8.1–8.5).

::

    iamp train [--data DIR] [--recording NAME ...] [--split sequence|recording|time] [--val-fraction 0.2]
               [--kind ar|gru] [--hidden 0|N] [--tied-routes weight|drop|first] [--min-future-steps 10] [--epochs 200] [--patience 20] [--folds 0] [--batch-size 256] [--lr 1e-3] [--seed 0] [--device cpu|cuda]
               [--out artefacts/ar_model.pt] [--json FILE] [--no-progress]

Data: ``stages.offline.train.dataset`` (the online ``FeatureTracker`` over the
in-process chain; targets from the true future, smoothed non-causally),
cached under ``artefacts/ar_cache``.

Splits (never neighbouring windows of one track on both sides):

- ``sequence`` (default): per recording, its sequences in a seeded random
  order, each going to validation when that brings the validation part
  nearer to ``val_fraction`` of the recording's samples (so every recording
  is in both parts, and K729's large sequence 013 is never the whole of it;
  docs/method.md §8.3). A recording
  with a single sequence (K733) is split by a time block instead: the
  stamp that leaves ``val_fraction`` of its windows after it is the cut,
  and the later part is validation (by time, not by samples). Windows near the cut are dropped:
  a training sample needs its 4 s future before the cut, a validation sample
  its 4 s history after it (``dropped_at_cut``).
- ``recording``: whole recordings; the set whose share of samples is
  closest to ``val_fraction`` (with two recordings: the smaller one).
  Needs at least two recordings with samples.
- ``time``: every sequence split by a time block as above.

Training: features z-scored with the training set's mean and std over real
steps (std floored at 1e-3 in the feature's units; a constant feature gets
std 1) and clipped to ±``z_clip`` 3; the net of ``kind``: ``ar``, ``ARNet``
(linear, or one ReLU layer of ``hidden`` units), or ``gru``, ``GRUNet``
(``hidden`` 32 units by default); Adam (``lr`` 1e-3, L2 ``weight_decay`` 0.3 for the
linear net, 0.1 with a hidden layer, 0.01 for the GRU, not tuned), loss MSE + MAE (m/s², mean over the
known target steps, each sample by its weight: 1/k on one of k tied routes; ``loss`` "displacement", ``--loss``:
of the along-track displacement, m, that the steps' accelerations integrate to, a step counted while every step up to
it is known), learning rate cosine-annealed with warm restarts every 10
epochs (``CosineAnnealingWarmRestarts`` T_0 = 10, stepped per batch), batches
of 256, at most 200 epochs, early stopping when the validation loss has not
improved for ``patience`` 20 epochs; the best epoch's weights are kept
(``patience`` 0: no early stopping, the last epoch's weights). With
``folds`` R >= 2 (``--folds``), ``fit_folds``: R nets on R repeated splits,
trained side by side, pick the epoch count by their mean validation loss,
and one net is trained on every sample for that many epochs.
Seeded: the same seed, data and machine give the same weights.

Why these: without regularisation the nets fit noise within a few epochs
(few cars against 38 440 weights); the weight decays and the z-clip are the
best of those measured on seeded sequence splits (docs/method.md §8.4).
The validation set also picks the epoch, so its figures are slightly
optimistic; a model trained on one location (``--recording``) and scored
on the other gives an unbiased, cross-location figure.

Report (printed; ``--json``; and in the weights file's ``metadata``):
validation MSE and MAE (known steps, weighted) of the model against "zero" (a = 0) and "last" (the
last observed causal acceleration feature held over 4 s), overall, per
0.4 s chunk and per recording, and on the windows with their whole 4 s
future (``validation_full_future``); the cars, windows and samples of the
data set (``sizes.dataset``); the model's inference time for one frame of
32 pairs (``inference_ms_per_frame``, median and minimum; a figure); ``sigma_res_chunks`` (the RMSE of the chunk
means, docs/method.md §8.5); the sizes; epochs, the best epoch, time.

Exit codes: 0 success, 2 bad command line, data or configuration (a
message says what to fix).
"""

from __future__ import annotations

from stages.lib.base import check_output, json_safe, progress_bar

import copy
import dataclasses
import datetime as _dt
import itertools
import json
import math
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from stages.offline.train.dataset import ARDataset, DatasetConfig, build_dataset
from stages.lib.ar.features import FEATURE_NAMES, HISTORY_STEPS, HORIZON_STEPS, STEP_S, FeatureConfig
from stages.lib.ar.model import CHUNK_STEPS, KINDS, N_CHUNKS, ARModel, chunk_means, make_net, save_model

from stages.offline.train import DEFAULT_CACHE_DIR, DEFAULT_OUT, LOSSES, SPLITS

SOURCE_DIR = Path(__file__).resolve().parents[3]  # the checkout this code runs from, for the model's provenance (git commit)

DEFAULT_DECAY_LINEAR = 0.3
DEFAULT_DECAY_HIDDEN = 0.1
DEFAULT_DECAY_GRU = 0.01
DEFAULT_HIDDEN_GRU = 32
INFERENCE_PAIRS = 32
"""Pairs per frame of the inference timing in the report (a busy K733 frame has about this many vehicle-corridor pairs)."""
_NS = 1e-9


@dataclass(frozen=True, kw_only=True)
class TrainConfig:
    """Everything a training run depends on (module docstring)."""

    dataset: DatasetConfig = field(default_factory=DatasetConfig)
    split: str = "sequence"
    val_fraction: float = 0.2
    kind: str = "ar"
    hidden: int = 0
    epochs: int = 200
    batch_size: int = 256
    lr: float = 1e-3
    weight_decay: float | None = None
    z_clip: float = 3.0
    patience: int = 20
    folds: int = 0
    seed: int = 0
    device: str = "cpu"
    drop_features: tuple[str, ...] = ()
    #: what the loss compares (``LOSSES``): "accel" the accelerations of the 40 target steps; "displacement" the
    #: along-track displacement they integrate to (``_displacement``), the quantity mADE scores
    loss: str = "accel"
    progress: bool = False

    def __post_init__(self) -> None:
        if self.split not in SPLITS:
            raise ValueError(f"split = {self.split!r}: expected one of {', '.join(SPLITS)}")
        if not (0.0 < self.val_fraction < 1.0):
            raise ValueError(f"val_fraction = {self.val_fraction!r}: must lie in (0, 1)")
        if self.kind not in KINDS:
            raise ValueError(f"kind = {self.kind!r}: expected one of {', '.join(KINDS)}")
        if self.loss not in LOSSES:
            raise ValueError(f"loss = {self.loss!r}: expected one of {', '.join(LOSSES)}")
        if self.hidden < 0 or (self.kind == "gru" and self.hidden < 1):
            raise ValueError(f"hidden = {self.hidden}: must be 0 (linear) or a number of units (at least 1 for kind gru)")
        if self.folds < 0 or self.folds == 1:
            raise ValueError(f"folds = {self.folds}: must be 0 (one split, early stopping) or at least 2")
        if self.patience < 0:
            raise ValueError(f"patience = {self.patience}: must be >= 1, or 0 (no early stopping: the last epoch's weights)")
        for name in ("epochs", "batch_size"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} = {getattr(self, name)}: must be >= 1")
        if not (math.isfinite(self.lr) and self.lr > 0):
            raise ValueError(f"lr = {self.lr!r}: must be > 0")
        if self.weight_decay is not None and not (math.isfinite(self.weight_decay) and self.weight_decay >= 0):
            raise ValueError(f"weight_decay = {self.weight_decay!r}: must be >= 0")
        if not (math.isfinite(self.z_clip) and self.z_clip > 0):
            raise ValueError(f"z_clip = {self.z_clip!r}: must be > 0")
        unknown = [n for n in self.drop_features if n not in FEATURE_NAMES]
        if unknown:
            raise ValueError(f"drop_features {unknown}: not feature names; known: {', '.join(FEATURE_NAMES)}")
        if len(set(self.drop_features)) >= len(FEATURE_NAMES):
            raise ValueError("drop_features would drop every feature")
        if self.device not in ("cpu", "cuda") and not self.device.startswith("cuda:"):
            raise ValueError(f"device = {self.device!r}: expected cpu or cuda")
        if self.device.startswith("cuda") and not torch.cuda.is_available():
            raise ValueError(f"device = {self.device!r}: CUDA is not available on this machine (torch {torch.__version__}); use --device cpu")

    @property
    def decay(self) -> float:
        """The weight decay used: as given, else 0.3 for the linear net and 0.1 with a hidden layer (module docstring)."""
        if self.weight_decay is not None:
            return self.weight_decay
        if self.kind == "gru":
            return DEFAULT_DECAY_GRU
        return DEFAULT_DECAY_HIDDEN if self.hidden else DEFAULT_DECAY_LINEAR

    @property
    def reach(self) -> float:
        """How many times its length a window spans of a sequence's time (the largest speed factor, at least 1): the splits' ``reach``."""
        return max((1.0, *(float(f) for f in self.dataset.speed_factors)))

    @property
    def feature_names(self) -> tuple[str, ...]:
        return tuple(n for n in FEATURE_NAMES if n not in self.drop_features)


# --------------------------------------------------------------------------- splits


def _time_block(ds: ARDataset, index: np.ndarray, seq: int, val_fraction: float, reach: float = 1.0) -> tuple[np.ndarray, np.ndarray, int, int]:
    """Train/val indices of one sequence's samples `index` split in time so that the later part holds `val_fraction` of them.
    ``reach``: the history and the horizon span up to this many times their length of the sequence's time (the largest
    speed factor of time-warped samples, stamped in the source's time).

    Returns (train, val, dropped, cut stamp).
    """
    t = ds.stamp_ns[index]
    if t.size == 0:
        return index, index, 0, int(ds.sequence_spans[seq][1])
    cut = int(np.quantile(t, 1.0 - val_fraction, method="inverted_cdf"))
    horizon_ns = int(round(HORIZON_STEPS * STEP_S * 1e9 * reach))
    history_ns = int(round(HISTORY_STEPS * STEP_S * 1e9 * reach))
    train = index[t + horizon_ns <= cut]
    val = index[t - history_ns >= cut]
    return train, val, int(index.size - train.size - val.size), cut


def split_samples(ds: ARDataset, split: str, val_fraction: float, seed: int, reach: float = 1.0) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """(train indices, validation indices, description) for the split of the module docstring; ValueError if impossible.
    ``reach``: as ``_time_block``'s (time splits; 1 without time-warped samples)."""
    rng = np.random.default_rng(seed)
    train_parts, val_parts = [], []
    info: dict[str, Any] = {"split": split, "val_fraction": val_fraction, "seed": seed, "dropped_at_cut": 0,
                            "val_sequences": [], "time_cuts": {}}

    def block(seq: int) -> None:
        index = np.flatnonzero(ds.sequence == seq)
        train, val, dropped, cut = _time_block(ds, index, seq, val_fraction, reach)
        train_parts.append(train)
        val_parts.append(val)
        info["dropped_at_cut"] += dropped
        info["time_cuts"][ds.sequences[seq]] = {"cut_stamp_s": cut * _NS, "span_s": [float(v) * _NS for v in ds.sequence_spans[seq]]}

    if split == "recording":
        present = [r for r in range(len(ds.recordings)) if np.any(ds.recording == r)]
        if len(present) < 2:
            raise ValueError(f"--split recording needs samples from at least two recordings; have {[ds.recordings[r] for r in present]}")
        counts = {r: int(np.sum(ds.recording == r)) for r in present}
        best = None
        for k in range(1, len(present)):
            for combo in itertools.combinations(present, k):
                share = sum(counts[r] for r in combo) / len(ds)
                score = (abs(share - val_fraction), combo)
                best = score if best is None or score < best else best
        val_recs = set(best[1])
        val_mask = np.isin(ds.recording, list(val_recs))
        info["val_recordings"] = [ds.recordings[r] for r in sorted(val_recs)]
        return np.flatnonzero(~val_mask), np.flatnonzero(val_mask), info
    for r in range(len(ds.recordings)):
        seqs = sorted({int(s) for s in np.unique(ds.sequence[ds.recording == r])})
        if not seqs:
            continue
        if split == "time" or len(seqs) == 1:
            for s in seqs:
                block(s)
            continue
        target = val_fraction * int(np.sum(ds.recording == r))
        sizes = {s: int(np.sum(ds.sequence == s)) for s in seqs}
        val_seqs: list[int] = []
        n_val = 0
        for s in [seqs[i] for i in rng.permutation(len(seqs))]:
            if len(val_seqs) < len(seqs) - 1 and abs(n_val + sizes[s] - target) < abs(n_val - target):
                val_seqs.append(s)
                n_val += sizes[s]
        if not val_seqs:  # every sequence alone overshoots the target twice: the smallest
            val_seqs.append(min(seqs, key=lambda s: (sizes[s], s)))
        for s in seqs:
            (val_parts if s in val_seqs else train_parts).append(np.flatnonzero(ds.sequence == s))
        info["val_sequences"] += [ds.sequences[s] for s in sorted(val_seqs)]
    train = np.sort(np.concatenate(train_parts)) if train_parts else np.zeros(0, np.int64)
    val = np.sort(np.concatenate(val_parts)) if val_parts else np.zeros(0, np.int64)
    return train, val, info


# --------------------------------------------------------------------------- metrics


def error_table(pred: np.ndarray, y: np.ndarray, known: np.ndarray | None = None, weight: np.ndarray | None = None) -> dict[str, Any]:
    """MSE and MAE (overall and per 0.4 s chunk) of predictions (B, 40) against targets (B, 40), and the chunk-mean RMSE.

    Only the `known` steps (B, 40) count (default all), each sample with its
    `weight` (B,) (default 1); the chunk-mean RMSE takes the chunks whose 4
    steps are all known.
    """
    err = np.asarray(pred, np.float64) - np.asarray(y, np.float64)
    nan = [math.nan] * N_CHUNKS
    if err.shape[0] == 0:
        return {"mse": math.nan, "mae": math.nan, "mse_chunks": nan, "mae_chunks": nan, "chunk_mean_rmse": nan}
    known = np.ones(err.shape, bool) if known is None else np.asarray(known, bool)
    w = np.ones(err.shape[0]) if weight is None else np.asarray(weight, np.float64)
    wk = known * w[:, None]
    err = np.where(known, err, 0.0)

    def mean(values: np.ndarray, weights: np.ndarray, axis) -> Any:
        total = weights.sum(axis=axis)
        return np.where(total > 0, (values * weights).sum(axis=axis) / np.where(total > 0, total, 1.0), np.nan)

    chunks, wchunks = err.reshape(err.shape[0], N_CHUNKS, CHUNK_STEPS), wk.reshape(err.shape[0], N_CHUNKS, CHUNK_STEPS)
    full = known.reshape(err.shape[0], N_CHUNKS, CHUNK_STEPS).all(axis=2) * w[:, None]
    return {
        "mse": float(mean(err**2, wk, None)),
        "mae": float(mean(np.abs(err), wk, None)),
        "mse_chunks": mean(chunks**2, wchunks, (0, 2)).tolist(),
        "mae_chunks": mean(np.abs(chunks), wchunks, (0, 2)).tolist(),
        "chunk_mean_rmse": np.sqrt(mean(chunk_means(err) ** 2, full, 0)).tolist(),
    }


def compare(pred: np.ndarray, ds: ARDataset) -> dict[str, Any]:
    """The model's errors on `ds` next to the zero and last-value-held predictors (known steps, weighted)."""
    last = np.repeat(ds.last_acceleration[:, None], HORIZON_STEPS, axis=1)
    return {"samples": len(ds), "windows": float(ds.weight.sum()), "model": error_table(pred, ds.y, ds.y_mask, ds.weight),
            "zero": error_table(np.zeros_like(ds.y), ds.y, ds.y_mask, ds.weight), "last": error_table(last, ds.y, ds.y_mask, ds.weight)}


def compare_full(pred: np.ndarray, ds: ARDataset) -> dict[str, Any]:
    """``compare`` on the windows with their whole 4 s future known (the windows of dataset version 3's kind)."""
    sel = np.flatnonzero(ds.y_mask.all(axis=1))
    return compare(pred[sel], ds.subset(sel))


def inference_ms(model: ARModel, ds: ARDataset, pairs: int = INFERENCE_PAIRS, repeats: int = 50) -> dict[str, float]:
    """Median and minimum wall time (ms) of ``model.predict`` on `pairs` windows of `ds` (one frame's batch), CPU.

    A figure, not a check: on a shared machine the median moves with the
    load (torch's threads wait for cores), the minimum much less.
    """
    take = np.arange(pairs) % max(len(ds), 1)
    x, mask = ds.x[take], ds.mask[take]
    model.predict(x, mask)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        model.predict(x, mask)
        times.append(time.perf_counter() - t0)
    return {"median_ms": float(np.median(times) * 1e3), "min_ms": float(np.min(times) * 1e3)}


# --------------------------------------------------------------------------- training


def _normalisation(x: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    real = x[mask] if mask.any() else x.reshape(-1, x.shape[-1])
    mean = real.mean(axis=0).astype(np.float64)
    std = real.std(axis=0).astype(np.float64)
    std = np.where(std < 1e-9, 1.0, np.maximum(std, 1e-3))
    return mean.astype(np.float32), std.astype(np.float32)


def _displacement(err: torch.Tensor, w: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(B, 40) acceleration errors of the target steps -> the along-track displacement errors they integrate to at the
    end of each step (each step's acceleration held over its 0.1 s: the speed error at its end plus the exact position
    term), with weights that keep a step only while every step up to it is known (a later displacement depends on the
    unknown ones); `w` (B, 40) = weight × known; steps of ``STEP_S`` (the features' 0.1 s)."""
    known = w > 0
    err = torch.where(known, err, torch.zeros_like(err))  # (the targets of unknown steps are not read)
    v_end = STEP_S * torch.cumsum(err, dim=1)
    disp = STEP_S * torch.cumsum(v_end - 0.5 * STEP_S * err, dim=1)  # Σ (v_start·dt + a·dt²/2), v_start = v_end − a·dt
    return disp, w * torch.cumprod(known.to(w.dtype), dim=1)


def _loss(pred: torch.Tensor, y: torch.Tensor, w: torch.Tensor, kind: str = "accel") -> torch.Tensor:
    """MSE + MAE over the known steps, each sample by its weight: `w` (B, 40) = weight × known; of the accelerations
    (``kind`` "accel", m/s²) or of the displacements they integrate to (``kind`` "displacement", m: ``_displacement``)."""
    err = pred - y
    if kind == "displacement":
        err, w = _displacement(err, w)
    total = w.sum().clamp_min(1e-9)
    return ((err * err) * w).sum() / total + (err.abs() * w).sum() / total


def _git_commit() -> str | None:
    try:
        out = subprocess.run(["git", "-C", str(SOURCE_DIR), "rev-parse", "HEAD"], capture_output=True, text=True, timeout=10)
        if out.returncode != 0:
            return None
        dirty = subprocess.run(["git", "-C", str(SOURCE_DIR), "status", "--porcelain", "--untracked-files=no"], capture_output=True, text=True, timeout=10)
        return out.stdout.strip() + ("-dirty" if dirty.returncode == 0 and dirty.stdout.strip() else "")
    except (OSError, subprocess.SubprocessError):
        return None


class _Trainer:
    """One net in training: its normalisation (from ``train``), Adam and the cosine schedule, one epoch per ``epoch()``."""

    def __init__(self, cfg: TrainConfig, train: ARDataset, val: ARDataset | None, seed: int) -> None:
        names = cfg.feature_names
        columns = np.array([FEATURE_NAMES.index(n) for n in names])
        mean, std = _normalisation(train.x[:, :, columns], train.mask)
        torch.manual_seed(seed)
        self.net = net = make_net(cfg.kind, len(names), cfg.hidden)
        self.model = ARModel(net=net, feature_names=names, feature_mean=mean, feature_std=std, sigma_res_chunks=np.zeros(N_CHUNKS),
                             z_clip=cfg.z_clip)
        self.device = torch.device(cfg.device)
        net.to(self.device)
        self.train_t = self._tensors(train)
        self.val_t = self._tensors(val) if val is not None and len(val) else None
        self.opt = torch.optim.Adam(net.parameters(), lr=cfg.lr, weight_decay=cfg.decay)
        self.sched = torch.optim.lr_scheduler.CosineAnnealingWarmRestarts(self.opt, T_0=10)
        self.gen = torch.Generator().manual_seed(seed)
        self.n = len(train)
        self.batch_size = cfg.batch_size
        self.iters = max(1, math.ceil(self.n / cfg.batch_size))
        self.epochs_done = 0
        self.loss = cfg.loss

    def _tensors(self, ds: ARDataset):
        w = ds.y_mask.astype(np.float32) * ds.weight.astype(np.float32)[:, None]
        return (torch.from_numpy(self.model.normalise(ds.x)).to(self.device), torch.from_numpy(ds.mask.astype(np.float32)).to(self.device),
                torch.from_numpy(ds.y.astype(np.float32)).to(self.device), torch.from_numpy(w).to(self.device))

    def epoch(self) -> tuple[float, float]:
        """Train one epoch; (approximate training loss, validation loss or NaN without validation data)."""
        zt, mt, yt, wt = self.train_t
        self.net.train()
        perm = torch.randperm(self.n, generator=self.gen).to(self.device)
        total = 0.0
        for i in range(self.iters):
            idx = perm[i * self.batch_size : (i + 1) * self.batch_size]
            self.opt.zero_grad()
            loss = _loss(self.net(zt[idx], mt[idx]), yt[idx], wt[idx], self.loss)
            loss.backward()
            self.opt.step()
            self.sched.step(self.epochs_done + (i + 1) / self.iters)
            total += float(loss.detach()) * idx.numel()  # per-batch loss × batch size: the epoch figure is approximate
        self.epochs_done += 1
        self.net.eval()
        val_loss = math.nan
        if self.val_t is not None:
            zv, mv, yv, wv = self.val_t
            with torch.no_grad():
                val_loss = float(_loss(self.net(zv, mv), yv, wv, self.loss))
        return total / self.n, val_loss

    def state(self) -> dict[str, Any]:
        return copy.deepcopy(self.net.state_dict())

    def finish(self, state: dict[str, Any] | None = None) -> ARModel:
        """The model with the weights ``state`` (default the current ones), on the CPU, in eval mode."""
        if state is not None:
            self.net.load_state_dict(state)
        self.net.to("cpu").eval()
        return self.model


def _epochs(cfg: TrainConfig, desc: str, step, snapshot) -> tuple[list[dict[str, Any]], float, int, Any]:
    """Up to ``cfg.epochs`` calls of ``step()`` (one epoch; returns its history row, whose ``val_loss`` is the
    criterion), stopping once it has not improved for ``cfg.patience`` epochs (0: never); ``snapshot()`` is taken
    at each improvement. Returns (history, best validation loss, its epoch, the snapshot taken then)."""
    best_loss, best_epoch, best, stale = math.inf, -1, None, 0
    history: list[dict[str, Any]] = []
    bar = progress_bar(cfg.epochs, cfg.progress, unit="epoch", desc=desc)
    try:
        for epoch in range(cfg.epochs):
            row = {"epoch": epoch, **step()}
            history.append(row)
            if row["val_loss"] < best_loss - 1e-6:
                best_loss, best_epoch, stale = row["val_loss"], epoch, 0
                best = snapshot()
            else:
                stale += 1
            bar.update(1)
            bar.set_postfix(val=f"{row['val_loss']:.3f}", best=f"{best_loss:.3f}@{best_epoch}")
            if cfg.patience and stale >= cfg.patience:
                break
    finally:
        bar.close()
    return history, best_loss, best_epoch, best


def fit(cfg: TrainConfig, train: ARDataset, val: ARDataset, log=None) -> tuple[ARModel, dict[str, Any]]:
    """Train on `train`, early-stop on `val`; the model (σ_res from `val`) and the training history."""
    say = log or (lambda msg: None)
    if len(train) == 0 or len(val) == 0:
        raise ValueError(f"no samples to train on ({len(train)} training, {len(val)} validation): use more data or another --split")
    run = _Trainer(cfg, train, val, cfg.seed)
    t0 = time.perf_counter()
    history, best_loss, best_epoch, best_state = _epochs(
        cfg, "iamp train", lambda: dict(zip(("train_loss", "val_loss"), run.epoch())),
        run.state if cfg.patience else (lambda: None))
    # patience 0: no snapshot, so the last epoch's weights (the validation loss is reported, not used)
    model = run.finish(best_state)
    seconds = time.perf_counter() - t0
    say(f"trained {len(history)} epochs in {seconds:.1f} s, best epoch {best_epoch} (validation loss {best_loss:.4f})"
        + ("" if cfg.patience else f"; kept the last epoch's weights (validation loss {history[-1]['val_loss']:.4f})"))
    pred_val = model.predict(val.x, val.mask)
    model.sigma_res_chunks = np.asarray(error_table(pred_val, val.y, val.y_mask, val.weight)["chunk_mean_rmse"], dtype=np.float32)
    return model, {"epochs_run": len(history), "best_epoch": best_epoch, "best_val_loss": best_loss, "train_seconds": seconds, "history": history}


def fold_seed(seed: int, fold: int) -> int:
    """The split seed of repeated split ``fold`` (0-based) of a run seeded ``seed`` (``--folds``)."""
    return seed * 1000 + 1 + fold


def fit_folds(cfg: TrainConfig, ds: ARDataset, log=None) -> tuple[ARModel, dict[str, Any], ARDataset, np.ndarray]:
    """``--folds R``: the epoch count chosen by R repeated validation splits, then one net trained on every sample.

    R nets (split seeds ``fold_seed(seed, r)``, each the configured ``split`` with ``val_fraction``; net r seeded
    ``fold_seed(seed, r)`` too) are trained side by side, epoch by epoch; the mean of their validation losses
    picks the epoch E (the best mean; stopping when it has not improved for ``patience`` epochs). A net seeded
    ``seed`` is then trained on all samples for E + 1 epochs (the same schedule, so it ends at the same point of the
    cosine cycle). Its σ_res comes from the R nets' out-of-fold predictions at epoch E (a sample in several
    validation parts counts once per part). Returns the model, the fitted figures, the out-of-fold validation set
    and its predictions (for the report)."""
    say = log or (lambda msg: None)
    splits = [split_samples(ds, cfg.split, cfg.val_fraction, fold_seed(cfg.seed, r), reach=cfg.reach) for r in range(cfg.folds)]
    for r, (tr, va, _info) in enumerate(splits):
        if tr.size == 0 or va.size == 0:
            raise ValueError(f"--folds {cfg.folds}: split {r} has {tr.size} training and {va.size} validation samples;"
                             " use more data, fewer folds or another --split")
    runs = [_Trainer(cfg, ds.subset(tr), ds.subset(va), fold_seed(cfg.seed, r)) for r, (tr, va, _info) in enumerate(splits)]
    def step() -> dict[str, Any]:
        losses = [run.epoch() for run in runs]
        return {"train_loss": float(np.mean([t for t, _v in losses])), "val_loss": float(np.mean([v for _t, v in losses])),
                "val_loss_by_split": [v for _t, v in losses]}

    t0 = time.perf_counter()
    history, best_loss, best_epoch, best_states = _epochs(cfg, f"iamp train ({cfg.folds} splits)", step,
                                                          lambda: [run.state() for run in runs])
    cv_seconds = time.perf_counter() - t0
    epochs = best_epoch + 1
    say(f"{cfg.folds} splits: {len(history)} epochs in {cv_seconds:.1f} s, best mean validation loss {best_loss:.4f} "
        f"after {epochs} epochs; training on all {len(ds)} samples for {epochs} epochs")
    oof_index = np.concatenate([va for _tr, va, _info in splits])
    oof_pred = np.concatenate([run.finish(state).predict(ds.x[va], ds.mask[va]) for run, state, (_tr, va, _info)
                               in zip(runs, best_states, splits)])
    oof = ds.subset(oof_index)
    final = _Trainer(cfg, ds, None, cfg.seed)
    t1 = time.perf_counter()
    for _ in range(epochs):
        final.epoch()
    model = final.finish()
    model.sigma_res_chunks = np.asarray(error_table(oof_pred, oof.y, oof.y_mask, oof.weight)["chunk_mean_rmse"], dtype=np.float32)
    seconds = time.perf_counter() - t0
    say(f"trained the final net {epochs} epochs in {time.perf_counter() - t1:.1f} s")
    best_by_split = [min(h["val_loss_by_split"][r] for h in history) for r in range(cfg.folds)]
    return model, {"epochs_run": epochs, "best_epoch": best_epoch, "best_val_loss": best_loss, "train_seconds": seconds,
                   "folds": {"count": cfg.folds, "split_seeds": [fold_seed(cfg.seed, r) for r in range(cfg.folds)],
                             "epochs_run": len(history), "chosen_epochs": epochs, "best_mean_val_loss": best_loss,
                             "val_loss_at_chosen_by_split": history[best_epoch]["val_loss_by_split"],
                             "best_val_loss_by_split": best_by_split, "seconds": cv_seconds,
                             "splits": [info for _tr, _va, info in splits]},
                   "history": history}, oof, oof_pred


def run_training(cfg: TrainConfig, *, cache_dir: Path | None = DEFAULT_CACHE_DIR, log=None) -> tuple[ARModel, dict[str, Any]]:
    """Build (or read) the data set, split, train, evaluate: (model with metadata, report)."""
    say = log or (lambda msg: None)
    t0 = time.perf_counter()
    ds = build_dataset(cfg.dataset, cache_dir=cache_dir, progress=cfg.progress, log=say)
    data_seconds = time.perf_counter() - t0
    if len(ds) == 0:
        raise ValueError(f"no training samples in {cfg.dataset.data_dir} ({ds.counts}): select recordings with vehicles that have a 4 s future")
    if cfg.folds:
        # every sample trains the final net; "validation" is the R splits' out-of-fold part, predicted by their nets
        model, fitted, val, pred_val = fit_folds(cfg, ds, log=say)
        train = ds
        split_info = {"split": "folds", "base_split": cfg.split, "val_fraction": cfg.val_fraction, "seed": cfg.seed,
                      "folds": cfg.folds, "dropped_at_cut": 0, "val_sequences": [], "time_cuts": {},
                      "fold_splits": fitted["folds"]["splits"]}
    else:
        train_idx, val_idx, split_info = split_samples(ds, cfg.split, cfg.val_fraction, cfg.seed, reach=cfg.reach)
        train, val = ds.subset(train_idx), ds.subset(val_idx)
        say(f"{len(train)} training and {len(val)} validation samples ({cfg.split} split)")
        if len(train) and not len(val) and len(ds):
            dropped = split_info.get("dropped_at_cut", 0) if isinstance(split_info, dict) else 0
            raise ValueError(
                f"no validation samples: the {cfg.split} split left none of the {len(ds)} samples for validation"
                + (f" ({dropped} dropped at a time cut: a validation sample needs its {HISTORY_STEPS * STEP_S:g} s history after the cut,"
                   " so the later part of a short sequence holds none)" if dropped else "")
                + f"; give more sequences, or a larger --val-fraction (now {cfg.val_fraction:g})")
        model, fitted = fit(cfg, train, val, log=say)
        pred_val = model.predict(val.x, val.mask)
    pred_train = model.predict(train.x, train.mask)
    by_recording = {}
    for r, name in enumerate(ds.recordings):
        sel = val.recording == r
        if sel.any():
            by_recording[name] = compare(pred_val[sel], val.subset(np.flatnonzero(sel)))
    report: dict[str, Any] = {
        "data": str(cfg.dataset.data_dir),
        "recordings": list(ds.recordings),
        # with --folds every sequence trained the final net: none is held out from it ("out_of_fold": the repeated splits' validation parts)
        "sequences": {"train": sorted({ds.sequences[s] for s in train.sequence}),
                      **({"val": [], "out_of_fold": sorted({ds.sequences[s] for s in val.sequence})} if cfg.folds
                         else {"val": sorted({ds.sequences[s] for s in val.sequence})})},
        "split": split_info,
        "sizes": {"samples": len(ds), "train": len(train), "val": len(val), "dropped_at_cut": split_info["dropped_at_cut"],
                  "train_tracks": train.tracks, "val_tracks": val.tracks,
                  "train_windows": float(train.weight.sum()), "val_windows": float(val.weight.sum()), "dataset": ds.sizes()},
        "dataset_counts": ds.counts,
        "dataset_key": ds.key,
        "dataset_seconds": data_seconds,
        "model": {"kind": cfg.kind, "hidden": cfg.hidden, "features": list(model.feature_names), "dropped_features": list(cfg.drop_features),
                  "parameters": int(sum(p.numel() for p in model.net.parameters()))},
        "training": {k: v for k, v in fitted.items() if k != "history"} | {
            "epochs_max": cfg.epochs, "batch_size": cfg.batch_size, "lr": cfg.lr, "weight_decay": cfg.decay, "z_clip": cfg.z_clip,
            "patience": cfg.patience, "folds": fitted.get("folds", cfg.folds), "seed": cfg.seed, "device": cfg.device, "loss": "mse + mae" if cfg.loss == "accel" else f"mse + mae of the {cfg.loss}",
            "schedule": "CosineAnnealingWarmRestarts(T_0=10), per batch"},
        "train_errors": {"model": error_table(pred_train, train.y, train.y_mask, train.weight)},
        "validation": compare(pred_val, val),
        "validation_full_future": compare_full(pred_val, val),
        "inference_ms_per_frame": {"pairs": INFERENCE_PAIRS, **inference_ms(model, val), "device": "cpu", "threads": torch.get_num_threads(),
                                   "note": "model.predict only, one frame's batch; measured while the machine may be shared"},
        "validation_by_recording": by_recording,
        "sigma_res_chunks": model.sigma_res_chunks.tolist(),
        "history": fitted["history"],
    }
    model.metadata = {
        "feature_names": list(model.feature_names),
        "all_feature_names": list(FEATURE_NAMES),
        "history_steps": HISTORY_STEPS,
        "horizon_steps": HORIZON_STEPS,
        "step_s": STEP_S,
        "feature_config": dataclasses.asdict(cfg.dataset.features),
        "dataset_config": {k: v for k, v in cfg.dataset.key_dict().items() if k not in ("features", "feature_names")},
        "data": report["data"],
        "recordings": report["recordings"],
        "sequences": report["sequences"],
        "split": split_info,
        "sizes": report["sizes"],
        "seed": cfg.seed,
        "kind": cfg.kind,
        "hidden": cfg.hidden,
        "training": report["training"],
        "validation": report["validation"],
        "validation_full_future": report["validation_full_future"],
        "validation_by_recording": by_recording,
        "sigma_res_chunks": report["sigma_res_chunks"],
        "git_commit": _git_commit(),
        "date_utc": _dt.datetime.now(_dt.timezone.utc).replace(microsecond=0).isoformat(),
        "torch": torch.__version__,
        "history": report["history"],  # the loss curve, with the weights it led to
    }
    for key in ("feature_config", "dataset_config", "seed", "git_commit", "date_utc", "torch"):  # the JSON says it too
        report.setdefault(key, model.metadata[key])
    return model, report


# --------------------------------------------------------------------------- printing and CLI


def format_report(report: dict[str, Any]) -> str:
    """The validation table: MSE and MAE of model, zero and last per chunk, and σ_res."""
    v = report["validation"]
    lines = [
        f"data {report['data']}: {', '.join(report['recordings'])}; split {report['split']['split']}; "
        f"{report['sizes']['train']} training / {report['sizes']['val']} validation samples "
        f"({report['sizes']['dropped_at_cut']} dropped at time cuts)",
        f"cars with samples: {report['sizes']['dataset']['cars']}; windows {report['sizes']['dataset']['windows']:g} "
        f"({report['sizes']['dataset']['samples']} samples, tied routes split by weight)",
        f"model kind={report['model']['kind']} hidden={report['model']['hidden']} parameters={report['model']['parameters']}; "
        f"{report['training']['epochs_run']} epochs, best {report['training']['best_epoch']}, "
        f"{report['training']['train_seconds']:.1f} s",
        "",
        f"{'validation':<12}{'MSE':>8}{'MAE':>8}   (m/s², m²/s⁴)",
    ]
    for name in ("model", "zero", "last"):
        lines.append(f"{name:<12}{v[name]['mse']:>8.3f}{v[name]['mae']:>8.3f}")
    for rec, sub in report.get("validation_by_recording", {}).items():
        lines.append(f"  {rec} ({sub['samples']}): " + ", ".join(f"{n} {sub[n]['mse']:.3f}/{sub[n]['mae']:.3f}" for n in ("model", "zero", "last")))
    lines += ["", "chunk (s)      " + "".join(f"{0.4 * (k + 1):>7.1f}" for k in range(N_CHUNKS))]
    for name in ("model", "zero", "last"):
        lines.append(f"MSE {name:<11}" + "".join(f"{e:>7.3f}" for e in v[name]["mse_chunks"]))
    for name in ("model", "zero", "last"):
        lines.append(f"MAE {name:<11}" + "".join(f"{e:>7.3f}" for e in v[name]["mae_chunks"]))
    lines.append("sigma_res      " + "".join(f"{e:>7.3f}" for e in report["sigma_res_chunks"]))
    full = report.get("validation_full_future")
    if full:
        lines.append(f"windows with their whole 4 s future ({full['samples']}): MSE/MAE " +
                     ", ".join(f"{n} {full[n]['mse']:.3f}/{full[n]['mae']:.3f}" for n in ("model", "zero", "last")))
    inf = report.get("inference_ms_per_frame")
    if inf:
        lines.append(f"inference: {inf['median_ms']:.2f} ms median, {inf['min_ms']:.2f} ms min per frame of {inf['pairs']} pairs (cpu)")
    return "\n".join(lines)


def weak_model_warning(report: dict[str, Any]) -> str:
    """'' unless the trained model predicts the validation accelerations worse than zero acceleration does (too little
    data, or a split that holds out another behaviour): hybrid with it would be worse than corridor_cv."""
    v = report.get("validation", {})
    model, zero = v.get("model", {}).get("mse", math.nan), v.get("zero", {}).get("mse", math.nan)
    if not (math.isfinite(model) and math.isfinite(zero)) or model <= zero:
        return ""
    return (f"the model's validation MSE {model:.3f} is worse than predicting zero acceleration ({zero:.3f}), with"
            f" {report['sizes']['train']} training samples from {report['sizes']['dataset']['cars']} cars: more data (more"
            " sequences or recordings), a smaller model (--kind ar, or a smaller --hidden) or fewer epochs; as it is, hybrid"
            " with it would predict worse than corridor_cv")


def run_from_args(args) -> int:
    """``iamp train``: the parsed arguments of ``stages.offline.train.cli.add_arguments`` → exit code."""
    try:
        check_output(args.out, "--out")  # the outputs' places first: a bad one must not cost the training
        check_output(args.json, "--json")
        features = FeatureConfig() if args.accel_window is None else FeatureConfig(accel_window_s=args.accel_window)
        cfg = TrainConfig(
            dataset=DatasetConfig(
                data_dir=args.data, recordings=tuple(args.recording), sequences=tuple(args.sequence),
                max_frames_per_sequence=args.max_frames, features=features, tied_routes=args.tied_routes,
                min_future_steps=args.min_future_steps, position_noise_m=args.position_noise, noise_seed=args.seed,
                speed_factors=tuple(args.speed_factors),
            ),
            split=args.split, val_fraction=args.val_fraction, kind=args.kind,
            hidden=DEFAULT_HIDDEN_GRU if args.hidden is None and args.kind == "gru" else (args.hidden or 0), epochs=args.epochs, batch_size=args.batch_size,
            lr=args.lr, weight_decay=args.weight_decay, z_clip=args.z_clip, patience=args.patience, folds=args.folds, seed=args.seed, device=args.device,
            drop_features=tuple(args.drop_feature), loss=args.loss, progress=not args.no_progress,
        )
        model, report = run_training(cfg, cache_dir=None if args.no_cache else args.cache_dir, log=lambda m: print(m, file=sys.stderr))
    except ValueError as exc:  # DatasetError, bad options, impossible splits
        sys.stderr.write(f"iamp train: error: {exc}\n")
        return 2
    print(format_report(report))
    weak = weak_model_warning(report)
    if weak:
        print(f"WARNING: {weak}", file=sys.stderr)
    try:
        path = save_model(args.out, model)
    except OSError as exc:  # (the folder was checked before the training: the disk, or a path the check cannot see)
        sys.stderr.write(f"iamp train: error: --out {args.out}: cannot write the weights ({exc.strerror or exc})\n")
        return 2
    print(f"wrote {path}")
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(json_safe(report), indent=2, allow_nan=False))
        print(f"wrote {args.json}")
    return 0



__all__ = ["DEFAULT_CACHE_DIR", "DEFAULT_OUT", "SPLITS", "TrainConfig", "compare", "error_table", "fit",
           "format_report", "run_from_args", "run_training", "split_samples"]
