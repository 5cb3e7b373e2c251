"""Signal state as evidence: what a driver does at a signalised stop line (intentions and markov_prediction).

Pure numpy. Distances are from the vehicle's front bumper to the stop line
along its corridor (negative: past it). The rules, all stated, none fitted
(the only data with signal phases has no tracks):

- red and red-amber: a driver who can stop with at most
  ``RED_MAX_DECEL_MPS2`` (5 m/s², hard but ordinary braking) stops; one who
  would need more runs it;
- amber: stops when at most ``AMBER_MAX_DECEL_MPS2`` (3 m/s², the comfortable
  deceleration German amber times are designed for) suffices, else goes;
- green: goes (the signal gives no reason to stop; conflicts still may);
- unknown, dark, or a stop line beyond the horizon's reach
  (v·``HORIZON_S`` + v²/(2·3 m/s²) + ``REACH_MARGIN_M``): no evidence.
- A queue at green starts with a start-up delay: ``STARTUP_DELAY_S`` (1.5 s)
  after green onset for the first car, plus ``STARTUP_PER_POSITION_S``
  (1.0 s) per car ahead of it, counted as the distance to the stop line over
  ``QUEUE_SPACING_M`` (7 m per car). Stated from the traffic-engineering
  start-up lost time (about 2 s for the first car, 1-1.5 s start-up wave
  per queued car), not measured here.
"""

from __future__ import annotations

import math

import numpy as np

from bus_schemas.signals import SignalPhase

RED_MAX_DECEL_MPS2 = 5.0
AMBER_MAX_DECEL_MPS2 = 3.0
HORIZON_S = 4.0
REACH_MARGIN_M = 10.0
STARTUP_DELAY_S = 1.5
STARTUP_PER_POSITION_S = 1.0
QUEUE_SPACING_M = 7.0
QUEUE_REACH_M = 60.0  # a standing car further than this from the stop line is not taken as queued at it
MIN_STOP_DISTANCE_M = 0.5
RUN_PROBABILITY = 0.05  # P(stop) of a driver who cannot stop comfortably at red/amber (some still do)


def required_decel_mps2(front_distance_m, speed_mps):
    """Deceleration (positive) that stops at the line: v² / (2 max(d, 0.5 m))."""
    d = np.maximum(np.asarray(front_distance_m, dtype=np.float64), MIN_STOP_DISTANCE_M)
    v = np.asarray(speed_mps, dtype=np.float64)
    return v * v / (2.0 * d)


def in_reach(front_distance_m, speed_mps):
    """Whether the stop line matters within the horizon (and is not behind the front by more than 1 m)."""
    d = np.asarray(front_distance_m, dtype=np.float64)
    v = np.maximum(np.asarray(speed_mps, dtype=np.float64), 0.0)
    reach = v * HORIZON_S + v * v / (2.0 * AMBER_MAX_DECEL_MPS2) + REACH_MARGIN_M
    return np.isfinite(d) & (d > -1.0) & (d <= reach)


def stop_probability(phase: int, front_distance_m, speed_mps):
    """P(the driver stops at the line | the signal), per element of distance/speed; NaN: no evidence."""
    phase = SignalPhase(int(phase))
    d = np.asarray(front_distance_m, dtype=np.float64)
    v = np.asarray(speed_mps, dtype=np.float64)
    shape = np.broadcast(d, v).shape
    out = np.full(shape, np.nan)
    reach = np.broadcast_to(in_reach(d, v), shape)
    if phase is SignalPhase.GREEN:
        out[reach] = 0.0
    elif phase in (SignalPhase.RED, SignalPhase.RED_AMBER, SignalPhase.AMBER):
        limit = AMBER_MAX_DECEL_MPS2 if phase is SignalPhase.AMBER else RED_MAX_DECEL_MPS2
        can = np.broadcast_to(required_decel_mps2(d, v) <= limit, shape)
        out[reach] = np.where(can[reach], 1.0, RUN_PROBABILITY)
    return out


def startup_delay_s(front_distance_m: float) -> float:
    """Seconds after green onset until a queued car at this distance from the line starts."""
    d = max(float(front_distance_m), 0.0) if math.isfinite(front_distance_m) else 0.0
    return STARTUP_DELAY_S + STARTUP_PER_POSITION_S * math.floor(d / QUEUE_SPACING_M)


__all__ = [
    "AMBER_MAX_DECEL_MPS2",
    "HORIZON_S",
    "QUEUE_REACH_M",
    "QUEUE_SPACING_M",
    "RED_MAX_DECEL_MPS2",
    "STARTUP_DELAY_S",
    "STARTUP_PER_POSITION_S",
    "in_reach",
    "required_decel_mps2",
    "startup_delay_s",
    "stop_probability",
]
