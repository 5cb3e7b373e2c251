"""Signal state in the Markov prediction (issue 17): the stop chain brakes to a red stop line, a queue at green starts.

``apply_signals(predictor, pairs, issues)`` runs after the pairs got their
relations and before the chain, and changes only pairs whose relation names
a signalised stop line with a known phase (RelationSet v2 ``signal_*``);
without signal phases (``--signals off``, the development data) nothing
changes and the prediction is byte-for-byte today's. Per pair, with the
rules of ``stages.lib.signal_rules`` (d = distance from the front bumper
to the line):

- moving, and the driver is expected to stop (red/red-amber with at most
  5 m/s², amber with at most 3 m/s² needed): the stop line becomes a
  standing leader at gap d − ``LINE_MARGIN_M`` (unless a real leader is
  nearer), so the baseline's leader rule (critical gaps) brakes the chain
  to it; and the pair's input distributions λ(0..K−1) become a braking
  profile to the line (N(−v²/2d, ``BRAKE_SIGMA_MPS2``²) until the planned
  stop, then N(0, ``HOLD_SIGMA_MPS2``²)), which the hybrid mode uses in
  place of the AR profile; and its centre does not pass the line
  (``stop_line_wall``: position mass beyond the line, after the chain, is
  put at the line, standing);
- standing within ``QUEUE_REACH_M`` of the line at a stop phase: held (start
  rate ``HOLD_RATE_HZ``, the standstill mixture keeps it in place);
- standing within that reach at green: starts after the start-up delay
  (1.5 s + 1 s per car ahead, less the time green has held, when known):
  in the baseline, start rate 1 / (remaining delay + ``START_SPREAD_S``),
  replacing the mode's constant rate (0.055 Hz: a car waiting 18 s on
  average); in the hybrid mode (the AR model has never seen a green light)
  start rate 1 / ``START_SPREAD_S`` and inputs that hold until the delay,
  then ``LAUNCH_MPS2`` (``launch_profile``);
- green and moving, or no evidence: unchanged (a car at green is not slowed).

``cv`` and ``corridor_cv`` run no chain and are never changed: they remain
the references.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from bus_schemas import SignalPhase
from stages.lib.base import Issue
from stages.lib.signal_rules import QUEUE_REACH_M, startup_delay_s, stop_probability

LINE_MARGIN_M = 0.5
VIRTUAL_LEADER_ID = 2**62  # no track has it: the baseline takes it as a constant-speed (standing) point
BRAKE_SIGMA_MPS2 = 0.5
HOLD_SIGMA_MPS2 = 0.3
HOLD_RATE_HZ = 1e-6
START_SPREAD_S = 0.5
MAX_BRAKE_MPS2 = 8.0
LAUNCH_MPS2 = 2.0  # stated: a typical first-car start-up acceleration from a queue (1.5-2.5 m/s² in the literature), not measured


def _normal_over_bins(mean: float, sigma: float, edges: np.ndarray) -> np.ndarray:
    from math import erf, sqrt

    cdf = np.array([0.5 * (1.0 + erf((e - mean) / (sigma * sqrt(2.0)))) for e in edges])
    cdf[0], cdf[-1] = 0.0, 1.0  # the outer bins take the tails
    p = np.diff(cdf)
    return p / p.sum()


def braking_profile(v0_mps: float, gap_m: float, n_steps: int, tau_s: float, edges: np.ndarray) -> np.ndarray:
    """(K, M) inputs that stop a car at ``v0_mps`` within ``gap_m``: constant deceleration, then hold at zero."""
    a = min(v0_mps * v0_mps / (2.0 * max(gap_m, 0.5)), MAX_BRAKE_MPS2)
    t_stop = v0_mps / a if a > 0 else 0.0
    out = np.empty((n_steps, len(edges) - 1))
    for k in range(n_steps):
        braking = k * tau_s < t_stop
        out[k] = _normal_over_bins(-a if braking else 0.0, BRAKE_SIGMA_MPS2 if braking else HOLD_SIGMA_MPS2, edges)
    return out


def launch_profile(n_steps: int, tau_s: float, delay_s: float, edges: np.ndarray) -> np.ndarray:
    """(K, M) inputs of a car pulling away from a queue: N(0, ``HOLD_SIGMA_MPS2``²) until ``delay_s``, then
    N(``LAUNCH_MPS2``, ``BRAKE_SIGMA_MPS2``²)."""
    hold = _normal_over_bins(0.0, HOLD_SIGMA_MPS2, edges)
    go = _normal_over_bins(LAUNCH_MPS2, BRAKE_SIGMA_MPS2, edges)
    return np.stack([hold if (k + 1) * tau_s <= delay_s else go for k in range(n_steps)])


def apply_signals(predictor, pairs: list, issues: list[Issue]) -> dict[tuple[int, int], float]:
    """Change the pairs facing a known signal phase (module docstring).

    Returns the stop walls: per (track_id, corridor_id) of a moving pair
    expected to stop, the arc length its centre does not pass
    (``stop_line_wall``); empty without signal phases.
    """
    walls: dict[tuple[int, int], float] = {}
    if not predictor.model.chain:
        return walls
    cfg = predictor.config
    changed = 0
    for p in pairs:
        rel = p.relation
        if rel is None or rel.signal_group < 0 or not math.isfinite(rel.signal_distance_m):
            continue
        phase = SignalPhase(int(rel.signal_phase))
        if phase in (SignalPhase.UNKNOWN, SignalPhase.DARK):
            continue
        front = float(rel.signal_distance_m) - 0.5 * p.length_m
        if p.start_rate_hz > 0:  # standing
            if not (-1.0 < front <= QUEUE_REACH_M):
                continue
            if phase.means_stop:
                p.start_rate_hz = HOLD_RATE_HZ
            elif phase is SignalPhase.GREEN:
                held = float(rel.signal_held_s) if math.isfinite(rel.signal_held_s) else 0.0
                remaining = max(startup_delay_s(front) - held, 0.0)
                if getattr(cfg, "mode", "") == "hybrid":  # the delay in the inputs: still until it, then launching
                    p.start_rate_hz = 1.0 / START_SPREAD_S
                    p.input_probs = launch_profile(cfg.n_steps, cfg.tau_s, remaining, predictor.grid.input_edges())
                else:  # the delay in the standstill mixture's start rate; the mode's own inputs after it
                    p.start_rate_hz = 1.0 / (remaining + START_SPREAD_S)
            changed += 1
            continue
        if not phase.means_stop:
            continue
        if float(stop_probability(phase, front, p.v0_mps)) < 0.5:
            continue
        gap = max(front - LINE_MARGIN_M, 0.0)
        if rel.leader_track_id < 0 or not math.isfinite(rel.leader_gap_m) or rel.leader_gap_m > gap:
            p.relation = dataclasses.replace(rel, leader_track_id=VIRTUAL_LEADER_ID, leader_gap_m=gap, leader_speed_mps=0.0)
        p.input_probs = braking_profile(p.v0_mps, gap, cfg.n_steps, cfg.tau_s, predictor.grid.input_edges())
        walls[(p.track_id, p.corridor_id)] = float(rel.signal_stop_s_m) - 0.5 * p.length_m - LINE_MARGIN_M
        changed += 1
    if changed:
        issues.append(Issue("signal_evidence", -1, f"{changed} vehicle-corridor pairs follow their signal (stop line or queue start)"))
    return walls


def stop_line_wall(pairs: list, walls: dict[tuple[int, int], float], ds_m: float, pos, vel, interval, outside):
    """The chain's distributions with the stop walls applied: for a pair expected to stop, the position mass beyond
    its wall (window cells past the wall's cell, and the mass that left the window ahead) is put in the wall's cell and
    that share of the speed mass in the standing cell. Arrays (B, K, ·) as ``MarkovPredictor._markov`` holds them."""
    if not walls:
        return pos, vel, interval, outside
    pos, vel, outside = pos.copy(), vel.copy(), outside.copy()
    interval = None if interval is None else interval.copy()
    n_s = pos.shape[2]
    for b, p in enumerate(pairs):
        wall = walls.get((p.track_id, p.corridor_id))
        if wall is None:
            continue
        cell = int(math.floor((wall - p.s_first_m) / ds_m))
        if cell < 0 or cell >= n_s - 1:
            continue
        beyond = pos[b, :, cell + 1 :].sum(axis=1) + outside[b]
        pos[b, :, cell + 1 :] = 0.0
        pos[b, :, cell] += beyond
        outside[b] = 0.0
        total = np.maximum(vel[b].sum(axis=1), 1e-12)
        share = np.clip(beyond / total, 0.0, 1.0).astype(vel.dtype)
        vel[b] = vel[b] * (1.0 - share)[:, None]
        vel[b, :, 0] += share * total
        if interval is not None:
            moved = interval[b, :, cell + 1 :].sum(axis=1)
            interval[b, :, cell + 1 :] = 0.0
            interval[b, :, cell] += moved
    return pos, vel, interval, outside


__all__ = ["VIRTUAL_LEADER_ID", "apply_signals", "braking_profile", "stop_line_wall"]
