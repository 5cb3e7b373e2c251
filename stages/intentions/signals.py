"""Signal state as evidence in the DBN (issue 17): red or amber ahead within braking reach makes E = stop likely,
green gives no signal reason to stop, unknown leaves the network as it was.

``with_signals(tables, vehicles, relations)`` adds to the frame's
``PairTables`` per pair the next signalised stop line and its phase from the
relations (``signal_*``, RelationSet v2); ``signal_stop_probability`` turns
them into P(E = stop | signal) per particle with the rules of
``stages.lib.signal_rules``, from the particle's own s and v. Where the phase
says stop the stop model brakes for the stop line (the centre of a
``HALF_LENGTH_M`` car standing just before it) instead of the
intersection entrance minus ``stop_offset_m``. Without signal fields (no
phases, ``--signals off``) the tables are returned unchanged, so the network
is exactly today's.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Mapping, Sequence

import numpy as np

from bus_schemas import CorridorRelations, SignalPhase
from stages.lib.signal_rules import stop_probability

HALF_LENGTH_M = 2.25  # the particles carry no size: half a default car
STOP_LINE_MARGIN_M = 0.5  # the front stands this far before the line


def with_signals(tables, vehicles: Sequence, relations: Mapping[tuple[int, int], CorridorRelations]):
    """``tables`` with ``signal_line_s_m`` and ``signal_phase`` (G,) filled, or ``tables`` itself when no pair has a phase."""
    line, phase = [], []
    for vehicle in vehicles:
        for corridor in vehicle.corridors:
            rel = relations.get((vehicle.track_id, corridor.corridor_id))
            known = (rel is not None and rel.signal_group >= 0 and math.isfinite(rel.signal_stop_s_m)
                     and SignalPhase(int(rel.signal_phase)) not in (SignalPhase.UNKNOWN, SignalPhase.DARK))
            line.append(float(rel.signal_stop_s_m) if known else math.nan)
            phase.append(int(rel.signal_phase) if known else int(SignalPhase.UNKNOWN))
    if not any(math.isfinite(x) for x in line):
        return tables
    line_a = np.asarray(line, dtype=np.float64)
    phase_a = np.asarray(phase, dtype=np.uint8)
    stop_phase = np.isin(phase_a, [int(SignalPhase.RED), int(SignalPhase.RED_AMBER), int(SignalPhase.AMBER)]) & np.isfinite(line_a)
    target = line_a - HALF_LENGTH_M - STOP_LINE_MARGIN_M
    stop_s = np.where(stop_phase, target, tables.stop_s_m)
    return dataclasses.replace(tables, stop_s_m=stop_s, signal_line_s_m=line_a, signal_phase=phase_a)


def signal_stop_probability(tables, g: np.ndarray, s_m: np.ndarray, v_mps: np.ndarray) -> np.ndarray | None:
    """P(E = stop | signal) per particle (NaN: no evidence), or None when the frame has no signal fields."""
    line = getattr(tables, "signal_line_s_m", None)
    if line is None:
        return None
    phases = tables.signal_phase[g]
    front = line[g] - (s_m + HALF_LENGTH_M)
    out = np.full(np.shape(s_m), np.nan)
    for ph in np.unique(phases):
        sel = phases == ph
        out[sel] = stop_probability(int(ph), front[sel], np.asarray(v_mps)[sel])
    return out


def combine(p_conflict: np.ndarray, p_signal: np.ndarray | None) -> np.ndarray:
    """P(E = stop) from the conflicts and the signal (independent reasons to stop); the conflicts alone without evidence."""
    if p_signal is None:
        return p_conflict
    evidence = np.isfinite(p_signal) & (np.nan_to_num(p_signal) > 0.0)  # green (0) leaves the conflicts' value exactly
    return np.where(evidence, 1.0 - (1.0 - p_conflict) * (1.0 - np.nan_to_num(p_signal)), p_conflict)


__all__ = ["HALF_LENGTH_M", "combine", "signal_stop_probability", "with_signals"]
