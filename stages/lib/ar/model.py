"""The AR-Net acceleration model and its weights file (docs/method.md §8.1–8.5).

Model kinds (``KINDS``, the file's ``kind``):

- ``ar``, ``ARNet``: y = W·[z(x) flattened, mask] + b, the AR-Net form
  (Triebe et al.) with the history of every feature as the lagged inputs:
  40 steps × F z-scored features plus the 40 mask values in, 40
  accelerations (m/s², at 0.1 … 4.0 s) out. ``hidden = 0`` is that linear
  map (the paper's model); ``hidden = N`` puts one ReLU layer of N units in
  between (a small MLP).
- ``gru``, ``GRUNet``: a one-layer GRU of ``hidden`` units reads the 40
  steps (F z-scores and the mask bit each); its last state goes through a
  linear map to the 40 accelerations, to which a linear map of the newest
  step's inputs is added.

``ARModel`` wraps a trained net with what it needs to be used: the per-
feature mean and std of the training set (over real steps) for the z-score
(clipped to ±``z_clip`` 3: the curvature and influencer features are mostly
0 with rare large values, and unclipped they cost validation MSE;
docs/method.md §8.2, §8.4),
the features it uses (``feature_names``, a subset of
``features.FEATURE_NAMES`` in that order; ``predict`` takes all of
``FEATURE_NAMES`` and selects them), ``sigma_res_chunks`` (10,) — the
validation RMSE of the 0.4 s chunk means per chunk k, the σ_res,k of
docs/method.md §8.5 — and ``metadata`` (what it was trained on and how well it
did, see ``stages.offline.train.fit``).

File format (``save_model``/``load_model``): a ``torch.save`` of a plain
dict, loadable with ``torch.load(weights_only=True)``: ``format`` =
``"hybrid-iamp/ar-model"``, ``version`` 2, ``kind`` (``KINDS``; a version 1
file has none and is read as ``ar``), ``hidden``, ``history_steps``,
``horizon_steps``, ``step_s``, ``feature_names`` (list of str), ``z_clip``,
``feature_mean``/``feature_std``/``sigma_res_chunks`` (float32 tensors),
``state_dict`` (str → tensor) and ``metadata_json`` (a JSON string). A
file that is missing, not a torch file, or lacks or mistypes any of these
gives a ``ValueError`` naming the file and the problem.

``DEFAULT_MODEL_PATH``: the shipped model, ``stages/lib/ar/weights/ar_taf_bw.pt``,
resolved from this module's location (works from any working directory).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch

from stages.lib.base import atomic_write, json_safe

from stages.lib.ar.features import FEATURE_NAMES, HISTORY_STEPS, HORIZON_STEPS, STEP_S

DEFAULT_MODEL_PATH = Path(__file__).resolve().parent / "weights" / "ar_taf_bw.pt"
"""The shipped model trained on all of TAF-BW."""

FILE_FORMAT = "hybrid-iamp/ar-model"
FILE_VERSION = 2
READ_VERSIONS = (1, 2)
KINDS = ("ar", "gru")
"""Model kinds: ``ar`` (``ARNet``: linear with ``hidden`` 0, an MLP with one ReLU layer of ``hidden`` units) and
``gru`` (``GRUNet``: a GRU of ``hidden`` units over the 40 steps)."""
N_CHUNKS = 10
CHUNK_STEPS = HORIZON_STEPS // N_CHUNKS


class ARNet(torch.nn.Module):
    """Linear (``hidden`` 0) or one-hidden-layer map from (B, 40·F + 40) to (B, 40)."""

    kind = "ar"

    def __init__(self, n_features: int, hidden: int = 0, history_steps: int = HISTORY_STEPS, horizon_steps: int = HORIZON_STEPS) -> None:
        super().__init__()
        if n_features < 1 or hidden < 0:
            raise ValueError(f"ARNet: n_features = {n_features} must be >= 1 and hidden = {hidden} >= 0")
        self.n_features = int(n_features)
        self.hidden = int(hidden)
        self.history_steps = int(history_steps)
        self.horizon_steps = int(horizon_steps)
        n_in = self.history_steps * (self.n_features + 1)
        if self.hidden:
            self.body = torch.nn.Sequential(
                torch.nn.Linear(n_in, self.hidden), torch.nn.ReLU(), torch.nn.Linear(self.hidden, self.horizon_steps)
            )
        else:
            self.body = torch.nn.Sequential(torch.nn.Linear(n_in, self.horizon_steps))

    def forward(self, z: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """z (B, 40, F) z-scored features, mask (B, 40) float → (B, 40) accelerations."""
        flat = torch.cat([z.reshape(z.shape[0], -1), mask.reshape(mask.shape[0], -1)], dim=1)
        return self.body(flat)


class GRUNet(torch.nn.Module):
    """A one-layer GRU of ``hidden`` units over the 40 history steps (z-scored features and the mask bit per step), its last
    state mapped linearly to the 40 accelerations, plus the linear AR map of the newest step's inputs (a skip path, so that
    the net starts from what the linear model sees most strongly)."""

    kind = "gru"

    def __init__(self, n_features: int, hidden: int = 32, history_steps: int = HISTORY_STEPS, horizon_steps: int = HORIZON_STEPS) -> None:
        super().__init__()
        if n_features < 1 or hidden < 1:
            raise ValueError(f"GRUNet: n_features = {n_features} must be >= 1 and hidden = {hidden} >= 1")
        self.n_features = int(n_features)
        self.hidden = int(hidden)
        self.history_steps = int(history_steps)
        self.horizon_steps = int(horizon_steps)
        self.gru = torch.nn.GRU(self.n_features + 1, self.hidden, batch_first=True)
        self.head = torch.nn.Linear(self.hidden, self.horizon_steps)
        self.skip = torch.nn.Linear(self.n_features + 1, self.horizon_steps)

    def forward(self, z: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """z (B, 40, F) z-scored features, mask (B, 40) float → (B, 40) accelerations."""
        seq = torch.cat([z, mask.unsqueeze(-1)], dim=2)
        _, h = self.gru(seq)
        return self.head(h[-1]) + self.skip(seq[:, -1])


def make_net(kind: str, n_features: int, hidden: int, history_steps: int = HISTORY_STEPS, horizon_steps: int = HORIZON_STEPS) -> torch.nn.Module:
    """The net of `kind` (``KINDS``); ValueError for an unknown kind."""
    if kind == "ar":
        return ARNet(n_features, hidden, history_steps, horizon_steps)
    if kind == "gru":
        return GRUNet(n_features, hidden, history_steps, horizon_steps)
    raise ValueError(f"model kind {kind!r}: expected one of {', '.join(KINDS)}")


@dataclass(eq=False)
class ARModel:
    """A trained net with its normalisation, σ_res per chunk and metadata (module docstring)."""

    net: torch.nn.Module
    feature_names: tuple[str, ...]
    feature_mean: np.ndarray
    feature_std: np.ndarray
    sigma_res_chunks: np.ndarray
    metadata: dict[str, Any] = field(default_factory=dict)
    z_clip: float = 3.0

    def __post_init__(self) -> None:
        unknown = [n for n in self.feature_names if n not in FEATURE_NAMES]
        if unknown:
            raise ValueError(f"ARModel: unknown feature(s) {unknown}; known: {', '.join(FEATURE_NAMES)}")
        f = len(self.feature_names)
        self.feature_mean = np.asarray(self.feature_mean, dtype=np.float32).reshape(-1)
        self.feature_std = np.asarray(self.feature_std, dtype=np.float32).reshape(-1)
        self.sigma_res_chunks = np.asarray(self.sigma_res_chunks, dtype=np.float32).reshape(-1)
        if self.feature_mean.shape != (f,) or self.feature_std.shape != (f,) or self.net.n_features != f:
            raise ValueError(f"ARModel: {f} features but mean {self.feature_mean.shape}, std {self.feature_std.shape}, net {self.net.n_features}")
        if not (math.isfinite(self.z_clip) and self.z_clip > 0):
            raise ValueError(f"ARModel: z_clip = {self.z_clip!r} must be > 0")
        if self.sigma_res_chunks.shape != (N_CHUNKS,):
            raise ValueError(f"ARModel: sigma_res_chunks must have shape ({N_CHUNKS},), got {self.sigma_res_chunks.shape}")
        self.columns = np.array([FEATURE_NAMES.index(n) for n in self.feature_names], dtype=np.int64)
        self.net.eval()

    @property
    def hidden(self) -> int:
        return self.net.hidden

    @property
    def kind(self) -> str:
        return self.net.kind

    def normalise(self, x: np.ndarray) -> np.ndarray:
        """(B, 40, len(FEATURE_NAMES)) raw features → (B, 40, F_model) z-scores clipped to ±``z_clip``, float32."""
        z = (np.asarray(x, dtype=np.float32)[:, :, self.columns] - self.feature_mean) / self.feature_std
        return np.clip(z, -self.z_clip, self.z_clip).astype(np.float32)

    def predict(self, x: np.ndarray, mask: np.ndarray, device: str | torch.device = "cpu", batch_size: int = 65536) -> np.ndarray:
        """Accelerations (B, 40) float32 at 0.1 … 4.0 s for features x (B, 40, F) and mask (B, 40), F = len(FEATURE_NAMES).

        No gradients (inference mode); the net is moved to `device` when it is not there from the last call.
        """
        x = np.asarray(x)
        mask = np.asarray(mask)
        if x.ndim != 3 or x.shape[1:] != (self.net.history_steps, len(FEATURE_NAMES)):
            raise ValueError(f"ARModel.predict: x must have shape (B, {self.net.history_steps}, {len(FEATURE_NAMES)}), got {x.shape}")
        if mask.shape != x.shape[:2]:
            raise ValueError(f"ARModel.predict: mask must have shape {x.shape[:2]}, got {mask.shape}")
        if x.shape[0] == 0:
            return np.zeros((0, self.net.horizon_steps), dtype=np.float32)
        dev = torch.device(device)
        if next(self.net.parameters()).device != dev:  # moved when elsewhere, not on every call
            self.net.to(dev)
        net = self.net
        out = []
        with torch.inference_mode():
            for a in range(0, x.shape[0], batch_size):
                z = torch.from_numpy(self.normalise(x[a : a + batch_size])).to(dev)
                m = torch.from_numpy(mask[a : a + batch_size].astype(np.float32)).to(dev)
                out.append(net(z, m).cpu().numpy())
        return np.concatenate(out).astype(np.float32)


# --------------------------------------------------------------------------- file


def chunk_means(a: np.ndarray) -> np.ndarray:
    """(B, 40) → (B, 10): the means of the 0.4 s chunks (steps 4k+1 … 4k+4)."""
    a = np.asarray(a)
    return a.reshape(a.shape[0], N_CHUNKS, CHUNK_STEPS).mean(axis=2)


def save_model(path: str | Path, model: ARModel) -> Path:
    """Write `model` to `path` (parent folders created) in the format of the module docstring."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    payload = {
        "format": FILE_FORMAT,
        "version": FILE_VERSION,
        "kind": str(model.net.kind),
        "hidden": int(model.net.hidden),
        "history_steps": int(model.net.history_steps),
        "horizon_steps": int(model.net.horizon_steps),
        "step_s": float(STEP_S),
        "feature_names": list(model.feature_names),
        "z_clip": float(model.z_clip),
        "feature_mean": torch.from_numpy(np.asarray(model.feature_mean, dtype=np.float32).copy()),
        "feature_std": torch.from_numpy(np.asarray(model.feature_std, dtype=np.float32).copy()),
        "sigma_res_chunks": torch.from_numpy(np.asarray(model.sigma_res_chunks, dtype=np.float32).copy()),
        "state_dict": {k: v.detach().cpu().clone() for k, v in model.net.state_dict().items()},
        "metadata_json": json.dumps(json_safe(model.metadata), sort_keys=True),
    }
    with atomic_write(path) as handle:
        torch.save(payload, handle)
    return path




def _broken_numbers(payload: dict) -> str:
    """What makes a model file's numbers unusable ('' if nothing): non-finite weights or statistics, a feature scale
    or residual spread that is not positive (the features are divided by the scale)."""
    for name, tensor in payload["state_dict"].items():
        if isinstance(tensor, torch.Tensor) and tensor.is_floating_point() and not bool(torch.isfinite(tensor).all()):
            return f"weights {name!r} hold NaN or inf"
    for key in ("feature_mean", "feature_std", "sigma_res_chunks"):
        if not bool(torch.isfinite(payload[key]).all()):
            return f"{key} holds NaN or inf"
    if not bool((payload["feature_std"] > 0).all()):
        return "feature_std has a value <= 0 (the features are divided by it)"
    if not bool((payload["sigma_res_chunks"] >= 0).all()):
        return "sigma_res_chunks has a negative spread"
    return ""


def load_model(path: str | Path = DEFAULT_MODEL_PATH) -> ARModel:
    """Read a model written by ``save_model``; ``ValueError`` naming the file and the problem otherwise."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"AR model file {path}: does not exist")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises pickle, zip and runtime errors for damaged files
        # the first sentence of torch's message only: for a file that is not a weights file it goes on to suggest
        # weights_only=False, which would run whatever code the file holds; never do that for a model file
        first = str(exc).strip().splitlines()[0].split(". ")[0][:160] if str(exc).strip() else ""
        raise ValueError(f"AR model file {path}: not a readable torch weights file ({type(exc).__name__}: {first}); "
                         "expected a file written by `iamp train`") from None
    if not isinstance(payload, dict) or payload.get("format") != FILE_FORMAT:
        found = payload.get("format") if isinstance(payload, dict) else type(payload).__name__
        raise ValueError(f"AR model file {path}: not an AR model (format {found!r}, expected {FILE_FORMAT!r})")
    if payload.get("version") not in READ_VERSIONS:
        raise ValueError(f"AR model file {path}: format version {payload.get('version')!r}, this code reads {', '.join(map(str, READ_VERSIONS))}")
    if payload["version"] == 1:  # version 1 had no kind: always the AR-Net
        payload = payload | {"kind": "ar"}
    expected = {
        "kind": str, "hidden": int, "history_steps": int, "horizon_steps": int, "step_s": float, "feature_names": list, "z_clip": float,
        "feature_mean": torch.Tensor, "feature_std": torch.Tensor, "sigma_res_chunks": torch.Tensor, "state_dict": dict, "metadata_json": str,
    }
    for key, tp in expected.items():
        if not isinstance(payload.get(key), tp):
            raise ValueError(f"AR model file {path}: entry {key!r} missing or not a {tp.__name__}")
    if (payload["history_steps"], payload["horizon_steps"]) != (HISTORY_STEPS, HORIZON_STEPS) or not math.isclose(payload["step_s"], STEP_S):
        raise ValueError(
            f"AR model file {path}: history/horizon/step {payload['history_steps']}/{payload['horizon_steps']}/{payload['step_s']} s, "
            f"this code uses {HISTORY_STEPS}/{HORIZON_STEPS}/{STEP_S} s"
        )
    broken = _broken_numbers(payload)
    if broken:  # a diverged training, or a damaged file: every prediction would be NaN and the stages fall back silently
        raise ValueError(f"AR model file {path}: {broken}; retrain it (`iamp train`)")
    try:
        metadata = json.loads(payload["metadata_json"])
        names = tuple(str(n) for n in payload["feature_names"])
        net = make_net(payload["kind"], len(names), payload["hidden"], payload["history_steps"], payload["horizon_steps"])
        net.load_state_dict(payload["state_dict"])
        return ARModel(
            net=net,
            feature_names=names,
            feature_mean=payload["feature_mean"].numpy(),
            feature_std=payload["feature_std"].numpy(),
            sigma_res_chunks=payload["sigma_res_chunks"].numpy(),
            metadata=metadata if isinstance(metadata, dict) else {"metadata": metadata},
            z_clip=payload["z_clip"],
        )
    except (ValueError, RuntimeError, KeyError, TypeError) as exc:
        first = str(exc).strip().splitlines()[0][:200] if str(exc).strip() else type(exc).__name__  # (torch lists every key)
        raise ValueError(f"AR model file {path}: inconsistent contents ({first}); expected a file written by `iamp train`") from None


__all__ = ["ARModel", "ARNet", "GRUNet", "KINDS", "make_net", "CHUNK_STEPS", "DEFAULT_MODEL_PATH", "N_CHUNKS", "chunk_means", "load_model", "save_model"]
