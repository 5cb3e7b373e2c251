"""Calibrated spread of the grids: a Gaussian along the corridor added to each pair's s-distribution, per step and speed band.

``iamp calibrate`` (``stages.offline.calibrate``) fits, on the windows of one
location, the σ (m) per prediction step and start-speed band for which the
90 % region of each mode's grid holds the truth in 90 % of the windows, and
writes them to a JSON file; the stage reads it (``spread_calibration``) and
widens the distributions its grids are made of with ``widen``. The mean
positions (``CorridorPredictions`` means, mADE) are computed before and do
not change; a σ of 0 leaves a step as it is (the spread is never narrowed).

File layout (``SCHEMA``)::

    {"schema": "iamp-spread-calibration/1", "modes": {"hybrid": {"bands_mps": [0.5, 2.0],
     "sigma_s_m": [[...n_steps...], [...], [...]]}, ...}, "fitted_on": {...}}

``bands_mps`` are the upper start-speed edges of all bands but the last
(speed ≤ 0.5: standing, ≤ 2: slow, above: fast); ``sigma_s_m`` has one row
per band and one σ per step.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np

SCHEMA = "iamp-spread-calibration/1"
#: ``spread_calibration = "shipped"`` names this file
SHIPPED = Path(__file__).with_name("spread.json")


@dataclass(frozen=True)
class SpreadTable:
    """σ (m) per start-speed band (rows) and step (columns) of one mode."""

    bands_mps: tuple[float, ...]
    sigma_s_m: np.ndarray  # (len(bands_mps) + 1, n_steps)

    def band(self, speed_mps: float) -> int:
        return int(np.searchsorted(np.asarray(self.bands_mps), speed_mps, side="left"))

    def sigmas(self, speed_mps: float) -> np.ndarray:
        return self.sigma_s_m[self.band(speed_mps)]

    def as_dict(self) -> dict[str, Any]:
        return {"bands_mps": list(self.bands_mps), "sigma_s_m": np.round(self.sigma_s_m, 4).tolist()}


def resolve(path: str) -> Path:
    return SHIPPED if path == "shipped" else Path(path).expanduser()


def load_spread(path: str, mode: str, n_steps: int) -> SpreadTable | None:
    """The table of ``mode`` in the file ``path`` (None when the file has none for it); a bad file raises ValueError."""
    where = f"spread_calibration = {path!r}"
    file = resolve(path)
    try:
        data = json.loads(file.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ValueError(f"{where}: cannot read {file}: {exc}; write it with `iamp calibrate` or set spread_calibration = \"\"") from exc
    if not isinstance(data, dict) or data.get("schema") != SCHEMA or not isinstance(data.get("modes"), dict):
        raise ValueError(f"{where}: {file} is not a {SCHEMA} file (write it with `iamp calibrate`)")
    entry = data["modes"].get(mode)
    if entry is None:
        return None
    try:
        bands = tuple(float(b) for b in entry["bands_mps"])
        sigma = np.asarray(entry["sigma_s_m"], dtype=np.float64)
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"{where}: mode {mode}: expected bands_mps and sigma_s_m ({exc})") from exc
    if sigma.shape != (len(bands) + 1, n_steps) or not np.all(np.isfinite(sigma)) or np.any(sigma < 0) or list(bands) != sorted(bands):
        raise ValueError(f"{where}: mode {mode}: sigma_s_m must be {len(bands) + 1} x {n_steps} finite values >= 0 (one row per band,"
                         f" one per step) and bands_mps increasing; got shape {sigma.shape}")
    return SpreadTable(bands, sigma)


def write_spread(path: Path, tables: dict[str, SpreadTable], fitted_on: dict[str, Any]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    blob = {"schema": SCHEMA, "modes": {m: t.as_dict() for m, t in tables.items()}, "fitted_on": fitted_on}
    path.write_text(json.dumps(blob, indent=2) + "\n")


@lru_cache(maxsize=256)
def _kernel(n_cells: int, sigma_cells: float) -> np.ndarray:
    """(N, N) column-stochastic Gaussian: column j spreads cell j's mass over the window (none leaves it)."""
    idx = np.arange(n_cells, dtype=np.float64)
    k = np.exp(-0.5 * ((idx[:, None] - idx[None, :]) / sigma_cells) ** 2)
    return (k / k.sum(axis=0, keepdims=True)).astype(np.float32)


def widen(probs: np.ndarray, sigmas_m: np.ndarray, ds_m: float) -> np.ndarray:
    """(K, N) s-distributions of one pair, each step k convolved with a Gaussian of σ = ``sigmas_m[k]`` (m; 0: unchanged)."""
    out = np.array(probs, dtype=np.float32, copy=True)
    n = out.shape[1]
    for k, sigma in enumerate(np.asarray(sigmas_m, dtype=np.float64)):
        if sigma > 0 and math.isfinite(sigma):
            out[k] = _kernel(n, round(float(sigma) / ds_m, 3)) @ out[k]
    return out
