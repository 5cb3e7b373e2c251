"""The AR inference: CorridorSet + RelationSet (+ TrackFrame) -> AccelerationProfiles, for the ar_inference stage and for
markov_prediction's ``hybrid_profiles = "inline"`` (docs/method.md §8.5; the stage is documented in
``stages/ar_inference/__init__.py``).

``ARInferenceConfig`` holds every parameter with units and defaults; ``ARInference`` keeps every vehicle's feature
history (``stages.lib.ar.features.FeatureTracker``), runs the AR model once over all pairs of a frame and turns each
40-step profile into the chain's input distributions (``chunk_distributions``).
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from bus_schemas import AccelerationProfile, AccelerationProfiles, CorridorSet, Header, RelationSet, SceneInfo, TrackFrame
from stages.lib.base import ConfigError, ConfigMixin, Issue, StageResult, check_ranges
from stages.lib.caps import cap_pairs
from stages.lib.markov.grid import DEFAULT_INPUT_MAX_MPS2, DEFAULT_INPUT_MIN_MPS2, DEFAULT_N_INPUTS, uniform_input_edges


def model_feature_config(model: Any, name: str = "the model"):
    """The features' definitions the model was trained with (``feature_config`` in its metadata, written by ``iamp
    train``): the inference must compute them the same way (a net trained on a 2 s acceleration window, fed the default
    1 s one, ran on features it never saw). A model without it (older files): the defaults; one that does not read:
    ``ConfigError``."""
    import dataclasses

    from stages.lib.ar import FeatureConfig

    stored = (getattr(model, "metadata", {}) or {}).get("feature_config")
    if not stored:
        return FeatureConfig()
    known = {f.name for f in dataclasses.fields(FeatureConfig)}
    unknown = sorted(set(stored) - known)
    if unknown:
        raise ConfigError(f"{name}: its feature_config has keys this build does not know ({', '.join(unknown)}): a model of another version")
    try:
        return FeatureConfig(**stored)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{name}: its feature_config does not read: {exc}") from None


@dataclass(frozen=True, kw_only=True)
class ARInferenceConfig(ConfigMixin):
    """Parameters of the AR inference (the ar_inference stage's, documented in stages/ar_inference/__init__.py; docs/method.md §8.5)."""

    #: weights file; empty: the shipped ``stages/lib/ar/weights/ar_taf_bw.pt``
    model: str = ""
    #: torch device of the model ("cpu", "cuda", "cuda:0")
    device: str = "cpu"
    #: Markov step τ: one distribution per chunk of ``chunk_s`` / the profile's 0.1 s steps
    chunk_s: float = 0.4
    #: input cells of the chain: ``n_inputs`` equal cells on [input_min, input_max] m/s². Must be the markov_prediction
    #: stage's (same three parameters, same defaults from ``stages.lib.markov.grid``); profiles over other cells are
    #: ignored there with a ``bad_profile`` issue
    input_min_mps2: float = DEFAULT_INPUT_MIN_MPS2
    input_max_mps2: float = DEFAULT_INPUT_MAX_MPS2
    n_inputs: int = DEFAULT_N_INPUTS
    #: σ_k = max(floor, √(var(chunk) + (scale·σ_res,k)²)): ``sigma_scale`` multiplies the validation RMSE of the weights file
    sigma_scale: float = 1.0
    sigma_floor_mps2: float = 0.25
    #: vehicle-corridor pairs per frame; whole vehicles beyond, in CorridorSet order, are skipped (issue ``pairs_capped``)
    max_pairs: int = 600

    def __post_init__(self) -> None:
        check_ranges(self, positive=("chunk_s", "sigma_floor_mps2"), non_negative=("sigma_scale",))
        if not self.input_max_mps2 > self.input_min_mps2:
            raise ValueError(f"input_min_mps2 = {self.input_min_mps2}, input_max_mps2 = {self.input_max_mps2}: need min < max")
        if self.max_pairs < 1:
            raise ValueError(f"max_pairs = {self.max_pairs}: must be >= 1")
        if self.n_inputs < 2:
            raise ValueError(f"n_inputs = {self.n_inputs}: must be >= 2")
        if not (self.device == "cpu" or self.device.startswith("cuda")):
            raise ValueError(f"device = {self.device!r}: expected 'cpu' or 'cuda[:N]'")

    def input_edges(self):
        """Edges of the input cells, ``(n_inputs + 1,) float64`` m/s² (``stages.lib.markov.grid.uniform_input_edges``)."""
        return np.asarray(uniform_input_edges(self.input_min_mps2, self.input_max_mps2, self.n_inputs), dtype=np.float64)


def chunk_distributions(
    accel_mps2: np.ndarray, chunk_steps: int, sigma_res: np.ndarray, edges: np.ndarray, *, sigma_scale: float = 1.0, sigma_floor: float = 0.25
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """docs/method.md §8.5: per chunk k, μ_k = mean of its steps, σ_k² = var(chunk) + (scale·σ_res,k)², σ_k ≥ floor,
    and λ_α(k) = Φ((e_{α+1} − μ_k)/σ_k) − Φ((e_α − μ_k)/σ_k), the tails beyond the outer edges folded into the end cells.

    ``accel_mps2`` is (B, H) with H a multiple of ``chunk_steps``; ``sigma_res`` is (H / chunk_steps,);
    returns μ (B, K), σ (B, K) and λ (B, K, M), float64, every λ row summing to 1.
    """
    accel = np.asarray(accel_mps2, dtype=np.float64)
    n_b, n_h = accel.shape
    if n_h % chunk_steps:
        raise ValueError(f"chunk_distributions: {n_h} steps do not split into chunks of {chunk_steps}")
    n_k = n_h // chunk_steps
    res = np.asarray(sigma_res, dtype=np.float64)
    if res.shape != (n_k,):
        raise ValueError(f"chunk_distributions: sigma_res must be ({n_k},), got {res.shape}")
    chunks = accel.reshape(n_b, n_k, chunk_steps)
    mu = chunks.mean(axis=2)
    sigma = np.maximum(np.sqrt(chunks.var(axis=2) + (sigma_scale * res[None, :]) ** 2), sigma_floor)
    z = (np.asarray(edges, dtype=np.float64)[None, None, :] - mu[..., None]) / sigma[..., None]
    cdf = 0.5 * (1.0 + _erf(z / math.sqrt(2.0)))
    cdf[..., 0], cdf[..., -1] = 0.0, 1.0
    probs = np.diff(cdf, axis=-1)
    probs = np.clip(probs, 0.0, None)
    return mu, sigma, probs / probs.sum(axis=-1, keepdims=True)


def _erf(x: np.ndarray) -> np.ndarray:
    from scipy.special import erf

    return erf(x)


def check_device(device: str) -> None:
    """``device`` is one this machine has (torch is loaded only for another than "cpu"); ConfigError otherwise. The
    core's start and the launcher's preflight (``stages.ar_inference``) both ask."""
    if device != "cpu":
        import torch

        if not torch.cuda.is_available():
            raise ConfigError(f"device = {device!r}: no CUDA device here; use device = 'cpu'")


class ARInference:
    """The ar_inference core: keeps every vehicle's feature history, predicts every pair of a frame in one batch.

    ``model`` may be passed (an already loaded ``stages.lib.ar.ARModel``) to share it between cores (evaluation).
    """

    def __init__(self, config: ARInferenceConfig, *, producer: str = "ar_inference", model: Any = None) -> None:
        from stages.lib.ar import DEFAULT_MODEL_PATH, FeatureTracker, load_model
        from stages.lib.ar import kernels as ar_kernels

        self.config = config
        self.producer = producer
        path = Path(config.model) if config.model else Path(DEFAULT_MODEL_PATH)
        if model is None:
            if path.is_dir():
                raise ConfigError(f"model = {str(path)!r}: is a folder; expected a weights file written by `iamp train --out FILE`")
            if not path.is_file():
                raise ConfigError(f"model = {str(path)!r}: no such weights file (train one with `iamp train --out FILE`)")
            try:
                model = load_model(path)
            except ValueError as exc:
                raise ConfigError(f"model = {str(path)!r}: {exc}") from exc
            digest = hashlib.sha256(path.read_bytes()).hexdigest()[:12]
            self.model_name = f"{path.name}@{digest}"
        else:
            self.model_name = getattr(model, "name", None) or f"{path.name}"
        check_device(config.device)
        self.model = model
        self.feature_config = model_feature_config(model, self.model_name)
        self.tracker = FeatureTracker(self.feature_config)
        ar_kernels.warm_up()  # the compiled feature kernel loaded (or compiled) now, not on the first frame
        meta = getattr(model, "metadata", {}) or {}
        self.step_s = float(meta.get("step_s", 0.1))
        self.history_steps = int(meta.get("history_steps", 40))
        self.feature_names = tuple(meta.get("feature_names", ()))
        steps = config.chunk_s / self.step_s
        if abs(steps - round(steps)) > 1e-6 or round(steps) < 1:
            raise ConfigError(f"chunk_s = {config.chunk_s}: must be a multiple of the model's step {self.step_s} s")
        self.chunk_steps = int(round(steps))
        self.edges = config.input_edges()
        self.sigma_res = np.asarray(model.sigma_res_chunks, dtype=np.float64)

    # ----- entry points ---------------------------------------------------------

    def update(self, inputs: Mapping[str, object]) -> StageResult:
        corridor_set = inputs.get("corridor_set")
        relation_set = inputs.get("relation_set")
        frame = inputs.get("track_frame")
        if not isinstance(corridor_set, CorridorSet):
            return StageResult(issues=[Issue("no_input", -1, "update without a corridor_set")])
        profiles, issues = self.process(
            corridor_set,
            relation_set if isinstance(relation_set, RelationSet) else None,
            frame if isinstance(frame, TrackFrame) else None,
        )
        return StageResult(outputs={"acceleration_profiles": profiles}, issues=issues)

    def observe(self, corridor_set: CorridorSet, relation_set: RelationSet | None, frame: TrackFrame | None = None) -> list[Issue]:
        """Add a frame to the histories without predicting (the evaluation between its instants)."""
        issues: list[Issue] = []
        if relation_set is not None and int(relation_set.header.stamp_ns) != int(corridor_set.header.stamp_ns):
            issues.append(Issue("stamp_mismatch", -1, f"relation_set stamp {relation_set.header.stamp_ns} != corridor_set stamp {corridor_set.header.stamp_ns}: relations ignored"))
            relation_set = None
        if frame is not None and int(frame.header.stamp_ns) != int(corridor_set.header.stamp_ns):
            frame = None
        issues.extend(self.tracker.update(corridor_set, relation_set, frame) or [])
        return issues

    def process(
        self, corridor_set: CorridorSet, relation_set: RelationSet | None, frame: TrackFrame | None = None, scene: SceneInfo | None = None
    ) -> tuple[AccelerationProfiles, list[Issue]]:
        """The pure function behind ``update``: observe the frame, then predict every (vehicle, corridor) pair of it."""
        corridor_set, dropped = cap_pairs(corridor_set, self.config.max_pairs)
        issues = self.observe(corridor_set, relation_set, frame)
        if dropped:
            issues.append(Issue("pairs_capped", -1, f"{dropped} vehicle-corridor pairs beyond max_pairs = {self.config.max_pairs} (whole vehicles, in CorridorSet order): skipped this frame"))
        keys, x, mask = self.tracker.batch(corridor_set)
        profiles: list[AccelerationProfile] = []
        if keys:
            accel = np.asarray(self.model.predict(x, mask, device=self.config.device), dtype=np.float64)
            bad = ~np.all(np.isfinite(accel), axis=1)
            for b in np.flatnonzero(bad):
                issues.append(Issue("nan_prediction", int(keys[b][0]), f"corridor {keys[b][1]}: the model gave non-finite accelerations: pair left out"))
            mu, sigma, probs = chunk_distributions(
                np.where(np.isfinite(accel), accel, 0.0), self.chunk_steps, self.sigma_res, self.edges,
                sigma_scale=self.config.sigma_scale, sigma_floor=self.config.sigma_floor_mps2,
            )
            real = mask.sum(axis=1).tolist()
            # float32 once for all pairs; each profile holds its row (the values astype gives row by row)
            accel32, mu32, sigma32, probs32 = (a.astype(np.float32) for a in (accel, mu, sigma, probs))
            for b in np.flatnonzero(~bad).tolist():
                track_id, corridor_id = keys[b]
                profiles.append(
                    AccelerationProfile(
                        track_id=int(track_id), corridor_id=int(corridor_id), history_steps=real[b],
                        accel_mps2=accel32[b], chunk_mean_mps2=mu32[b], chunk_sigma_mps2=sigma32[b], input_probs=probs32[b],
                    )
                )
        h = corridor_set.header
        header = Header(run_id=h.run_id, frame_index=h.frame_index, stamp_ns=h.stamp_ns, producer=self.producer, source_wall_ns=h.source_wall_ns)
        message = AccelerationProfiles(
            header=header, scene_id=scene.scene_id if scene is not None else corridor_set.scene_id, model=self.model_name,
            step_s=self.step_s, chunk_s=self.config.chunk_s, input_edges_mps2=self.edges, profiles=tuple(profiles),
        )
        return message, issues

    def reset(self) -> None:
        """Forget every vehicle's history (the next frame's scene is taken as it comes, without an issue)."""
        from stages.lib.ar import FeatureTracker

        self.tracker = FeatureTracker(self.feature_config)
