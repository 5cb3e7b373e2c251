"""A synthetic hybrid-chain case for the kernels' tests: pairs on corridors with a bend, a speed restriction from
their admissible speeds, AR-like preferences and a start state with pairs near the window's end (mass leaks) and one
at rest. The draws come from ``rng`` in a fixed order, so a seed gives one case."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class HybridChainCase:
    profiles: list  # per pair, the arc lengths of its speed profile (m)
    admissible: list  # per pair, (J, n) admissible speeds (m/s)
    cells: np.ndarray  # (B, L) s-cell centres (m)
    weights: np.ndarray  # (J,) weights of the lateral accelerations
    preferences: np.ndarray  # (K, B, M) float32, each row's maximum 1
    p0: object  # stages.lib.markov.SeparableState

    def restriction(self, config):
        """A fresh ``kernels.SpeedRestriction`` of the case (it caches what it computes)."""
        from stages.lib.markov import kernels

        return kernels.SpeedRestriction(self.profiles, self.admissible, self.cells, config.v_centres_mps(), config.input_centres_mps2(),
                                        self.weights, config.tau_s)


def hybrid_chain_case(config, n_pairs: int, rng: np.random.Generator) -> HybridChainCase:
    """``n_pairs`` pairs on ``config``'s grid (a ``MarkovGridConfig`` with at least 28 m of window)."""
    from stages.lib.markov import initial_state
    from stages.markov_prediction import priority as pr

    n_in, k_steps = config.n_inputs, config.n_steps
    profiles, adms = [], []
    for _ in range(n_pairs):
        s = np.cumsum(rng.uniform(0.3, 1.2, 80)) - 5.0
        kappa = np.where((s > 8) & (s < 18), 1.0 / rng.uniform(3, 8), 0.0)
        profiles.append(s)
        adms.append(pr.admissible_speeds(s, kappa, rng.uniform(2, 6), np.array([3.0, 2.0, 1.0]), 2.0, 4.0))
    cells = 0.5 + np.arange(config.n_s_cells)[None, :] * config.ds_m + rng.uniform(-2, 2, (n_pairs, 1))
    prefs = np.stack([rng.dirichlet(np.ones(n_in), n_pairs).astype(np.float32) for _ in range(k_steps)])
    prefs = prefs / prefs.max(axis=2, keepdims=True)
    s0 = rng.uniform(1, 20, n_pairs)
    s0[: min(2, n_pairs)] = [24.0, 27.5][: min(2, n_pairs)]  # near the window's end: mass leaks
    v0 = rng.uniform(0, 5.5, n_pairs)
    v0[-1] = 0.0
    p0 = initial_state(config, s_m=s0, v_mps=v0, half_width_s_m=0.7, half_width_v_mps=0.6,
                       input_probs=rng.dirichlet(np.ones(n_in), n_pairs))
    return HybridChainCase(profiles, adms, cells, np.array([0.3, 0.5, 0.2]), prefs.astype(np.float32), p0)
