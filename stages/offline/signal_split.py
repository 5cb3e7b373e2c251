"""The signal split of ``iamp eval`` (issue 17): each window's signal state at its start, ``by_signal.red|amber|green|unknown``.

A window's key is the phase, at the window's start, of the signal group of
the car's most probable corridor (the intentions' P(R = c); the first
corridor with a signalised stop line without beliefs), from the relations'
``signal_phase`` (RelationSet v2): ``red`` (red and red-amber), ``amber``,
``green``, or ``unknown`` (no stop line ahead, phase unknown or dark). Only
recordings with signal phases get the split (``--signals off``: none).
"""

from __future__ import annotations

from bus_schemas import IntentionBelief, RelationSet, SignalPhase

SIGNAL_KEYS = ("red", "amber", "green", "unknown")


def signal_keys(relation_set: RelationSet | None, belief: IntentionBelief | None) -> dict[int, str]:
    """Per track id, the key of its window (tracks without relations are absent: ``unknown``)."""
    if relation_set is None:
        return {}
    weights: dict[tuple[int, int], float] = {}
    if belief is not None:
        for v in belief.vehicles:
            for c in v.corridors:
                weights[(v.track_id, c.corridor_id)] = float(c.probability)
    best: dict[int, tuple[float, str]] = {}
    for rel in relation_set.relations:
        if rel.signal_group < 0:
            continue
        w = weights.get((rel.track_id, rel.corridor_id), 0.0)
        key = SignalPhase(int(rel.signal_phase)).summary
        if rel.track_id not in best or w > best[rel.track_id][0]:
            best[rel.track_id] = (w, key)
    return {t: k for t, (_, k) in best.items()}


__all__ = ["SIGNAL_KEYS", "signal_keys"]
