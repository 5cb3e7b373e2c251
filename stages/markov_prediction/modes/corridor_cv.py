"""Mode ``corridor_cv``: constant speed along each corridor, in closed form (no chain).

``constant_speed`` is also the loop's fallback for a pair a chain mode cannot
take (``MarkovPredictor._predict``), and the prediction of mode ``cv``.
"""

from __future__ import annotations

import numpy as np
from scipy.special import ndtr

from stages.markov_prediction.modes.base import InputModel, Pair, Predictor


class CorridorCV(InputModel):
    """Every acceleration input held at 0: the loop's ``constant_speed`` on one pair per corridor."""

    chain = False


def constant_speed(predictor: Predictor, pairs: list[Pair]) -> dict[str, np.ndarray]:
    """Constant speed along each corridor (or the cv line): exact means, Gaussian spreads for the grid.

    The position at t_k is s0 + v0·t_k; the grid spreads it with
    σ_s(t) = √(σ0² + (½σ_a t²)²) along the line and σ_v(t) = σ_a·t in
    speed (σ_a = ``cv_accel_sigma_mps2``, σ0 = ``init_sigma_s_m``), so
    that calibration metrics have something to measure.
    """
    cfg, grid, n_s = predictor.config, predictor.grid, predictor.n_s
    t = predictor.step_times_s
    n_b, n_k = len(pairs), t.shape[0]
    edges = grid.s_edges_m()[: n_s + 1]
    v_edges = grid.v_edges_mps()
    pos = np.zeros((n_b, n_k, n_s), np.float32)
    vel = np.zeros((n_b, n_k, grid.n_v_cells), np.float32)
    outside = np.zeros((n_b, n_k), np.float32)
    exact_s = np.zeros((n_b, n_k))
    sigma_s = np.sqrt(cfg.init_sigma_s_m**2 + (0.5 * cfg.cv_accel_sigma_mps2 * t**2) ** 2)
    sigma_v = np.maximum(cfg.cv_accel_sigma_mps2 * t, 1e-3)
    for b, p in enumerate(pairs):
        mean_w = p.s0_m - p.s_first_m + p.v0_mps * t  # window coordinates
        exact_s[b] = p.s0_m + p.v0_mps * t
        cdf = ndtr((edges[None, :] - mean_w[:, None]) / sigma_s[:, None])
        cdf[:, 0] = 0.0  # nothing behind the window's start (no reversing)
        pos[b] = np.diff(cdf, axis=1)
        outside[b] = 1.0 - cdf[:, -1]
        vcdf = ndtr((v_edges[None, :] - p.v0_mps) / sigma_v[:, None])
        vcdf[:, 0], vcdf[:, -1] = 0.0, 1.0
        vel[b] = np.diff(vcdf, axis=1)
    return {"position": pos, "interval": None, "velocity": vel, "outside": outside, "exact_s": exact_s}
