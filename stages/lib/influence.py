"""Which conflicting corridor influences a corridor: the explicit rules of docs/method.md §5.

Pure functions on the conflict arrays of one corridor (the ``conflict_*``
arrays of a ``CorridorRelations``, shape ``(c,)``), so the relations core and
the later AR-feature code share one ordering.

Ordering. Conflicts are ranked by |T' − T| (the other vehicle's time to the
conflict point minus this vehicle's), smallest first; ties go to the smaller
T' (`rank_conflicts`).

The influencing corridor (`choose_influencing`). Among the conflicts whose
other vehicle has not cleared the point (the relations core only lists those),
whose T' is below the horizon (4 s + 2 s) and whose other corridor is likely
enough (route probability at least the minimum, once intentions exist), a
conflict is eligible by the first of these rules that holds:

- ``priority_other``: the other corridor has right of way (priority −1 from
  this corridor's view);
- ``merge_ahead_other``: a merge, whatever the right of way, where the other
  vehicle is nearer the merge point than this one (other distance < this
  distance): after the merge it drives in front;
- ``equal_first_other``: a crossing without right of way either way
  (priority 0) where the other vehicle arrives first (T' < T).

The chosen conflict is the first eligible one in the ordering; its rule is
recorded, ``none`` when nothing is eligible.

The two most influencing vehicles for the AR features (`most_influencing`):
the same ordering and horizon without the priority rules, best conflict per
other vehicle, the first ``n`` vehicles.
"""

from __future__ import annotations

import numpy as np

from bus_schemas import ConflictKind, CorridorRelations

PRIORITY_OTHER = "priority_other"
MERGE_AHEAD_OTHER = "merge_ahead_other"
EQUAL_FIRST_OTHER = "equal_first_other"
NO_INFLUENCE = "none"
RULES = (PRIORITY_OTHER, MERGE_AHEAD_OTHER, EQUAL_FIRST_OTHER, NO_INFLUENCE)
"""Every value `influencing_rule` can take."""


def rank_conflicts(time_s, other_time_s) -> np.ndarray:
    """Indices (c,) int64 ordering conflicts by |T' − T|, ties to the smaller T' (then the index)."""
    t = np.asarray(time_s, dtype=np.float64)
    t_other = np.asarray(other_time_s, dtype=np.float64)
    return np.lexsort((np.arange(len(t)), t_other, np.abs(t_other - t))).astype(np.int64)


def eligibility(kinds, priority, distance_m, other_distance_m, time_s, other_time_s) -> np.ndarray:
    """The rule (index into `RULES`) that makes each conflict eligible; (c,) int8, 3 (``none``) if none.

    Only the rules themselves: the horizon and route-probability filters are
    applied by `choose_influencing`.
    """
    kinds = np.asarray(kinds)
    priority = np.asarray(priority)
    rule = np.full(len(kinds), RULES.index(NO_INFLUENCE), dtype=np.int8)
    equal_first = (kinds == ConflictKind.CROSSING) & (priority == 0) & (np.asarray(other_time_s) < np.asarray(time_s))
    merge_ahead = (kinds == ConflictKind.MERGE) & (np.asarray(other_distance_m) < np.asarray(distance_m))
    rule[equal_first] = RULES.index(EQUAL_FIRST_OTHER)
    rule[merge_ahead] = RULES.index(MERGE_AHEAD_OTHER)
    rule[priority < 0] = RULES.index(PRIORITY_OTHER)
    return rule


def choose_influencing(
    kinds,
    priority,
    distance_m,
    other_distance_m,
    time_s,
    other_time_s,
    *,
    horizon_s: float,
    other_probability=None,
    min_probability: float = 0.0,
) -> tuple[int, str]:
    """(index, rule) of the conflict influencing this corridor; (-1, ``none``) if none.

    Arrays are the corridor's conflicts (c,). `horizon_s` bounds T' (docs/method.md
    §5: 4 s + 2 s). `other_probability` (c,), when given, is P(R = the other
    corridor) from the intentions; conflicts below `min_probability` are
    skipped.
    """
    index, rule = choose_influencing_grouped(
        np.zeros(len(np.asarray(kinds)), dtype=np.int64), 1, kinds, priority, distance_m, other_distance_m, time_s, other_time_s,
        horizon_s=horizon_s, other_probability=other_probability, min_probability=min_probability,
    )
    return int(index[0]), RULES[int(rule[0])]


def choose_influencing_grouped(
    group,
    n_groups: int,
    kinds,
    priority,
    distance_m,
    other_distance_m,
    time_s,
    other_time_s,
    *,
    horizon_s: float,
    other_probability=None,
    min_probability: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """`choose_influencing` of many corridors at once: (index, rule) per group, arrays (n_groups,).

    The conflicts of corridor g are those with ``group == g``, contiguous
    (``group`` non-decreasing, as the relations core lists them); ``index``
    counts from the group's first conflict (-1 where none is eligible) and
    ``rule`` indexes `RULES`. The ranking (`rank_conflicts`: |T' − T|, ties
    to the smaller T', then the order) and the filters are applied per
    element, so each group gets what `choose_influencing` on its own arrays
    gives.
    """
    group = np.asarray(group, dtype=np.int64)
    rule = eligibility(kinds, priority, distance_m, other_distance_m, time_s, other_time_s)
    t = np.asarray(time_s, dtype=np.float64)
    t_other = np.asarray(other_time_s, dtype=np.float64)
    ok = (rule != RULES.index(NO_INFLUENCE)) & (t_other < horizon_s)
    if other_probability is not None:
        ok &= np.asarray(other_probability, dtype=np.float64) >= min_probability
    index = np.full(n_groups, -1, dtype=np.int64)
    chosen_rule = np.full(n_groups, RULES.index(NO_INFLUENCE), dtype=np.int8)
    order = np.lexsort((np.arange(len(t)), t_other, np.abs(t_other - t), group))
    eligible = order[ok[order]]  # ranked within each group
    if len(eligible):
        first = np.concatenate([[True], group[eligible][1:] != group[eligible][:-1]])
        best = eligible[first]
        group_start = np.searchsorted(group, np.arange(n_groups))
        index[group[best]] = best - group_start[group[best]]
        chosen_rule[group[best]] = rule[best]
    return index, chosen_rule


def most_influencing(relations: CorridorRelations, n: int = 2, *, horizon_s: float = 6.0) -> np.ndarray:
    """Indices into the conflict arrays of the `n` most influencing vehicles, best first.

    Same ordering as the influencing rule (|T' − T|, ties to the smaller T'),
    with no priority filter, T' below `horizon_s`, and at most one conflict per
    other vehicle (its best). The AR features then read, per index k,
    ``conflict_other_distance_m[k]``, ``conflict_other_speed_mps[k]`` and
    ``conflict_priority[k]`` (priority is from this corridor's view: +1 means
    this vehicle has right of way, so the feature "other has priority" is
    ``-conflict_priority[k]``). Fewer than `n` entries when fewer vehicles
    conflict.
    """
    order = rank_conflicts(relations.conflict_time_s, relations.conflict_other_time_s)
    chosen: list[int] = []
    seen: set[int] = set()
    for k in order:
        track_id = int(relations.conflict_track_ids[k])
        if track_id in seen or not relations.conflict_other_time_s[k] < horizon_s:
            continue
        seen.add(track_id)
        chosen.append(int(k))
        if len(chosen) == n:
            break
    return np.asarray(chosen, dtype=np.int64)
