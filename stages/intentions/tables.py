"""Per-frame tables of the intentions stage: every (vehicle, corridor) pair of a frame as flat numpy arrays.

`PairTables` concatenates the centrelines of all pairs (samples ``(T,)``)
with a per-pair key offset, so that the particles of every vehicle are
placed on their corridors by one ``searchsorted`` (`PairTables.locate`),
whatever their number. Per pair it also holds the admissible speed profile
of docs/method.md §4.2 (one row per lateral acceleration of the driver styles),
the next intersection entrance and the stop position, the start of the
vehicle's matched lanelet (route switching), and the conflicts with
priority vehicles that drive the expected manoeuvre E.

`corridor_manoeuvre` classifies a corridor (turn, straight, lane change,
follow lane) from the map; `map_corridors` maps the corridors of a
vehicle's previous update onto its new ones (same id, else the longest
common lanelet run). `corridors_ok` and `unwrap_parts` check and unwrap the
corridors of a whole frame at once, with exactly the per-corridor results of
`corridor_ok` and ``np.unwrap``. Pure: no bus, no clock.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np

from bus_schemas import Corridor, CorridorRelations, Manoeuvre
from stages.intentions import kernels
from stages.lib.maps import RoadMap, Turn

KEY_OFFSET_M = 1.0e6
"""Key spacing between pairs in `PairTables.key`: far more than any corridor's length."""

MIN_CURVATURE_1PM = 1e-4


def admissible_speeds(s_m, curvature_1pm, length, speed_limit_mps, lat_accels_mps2, brake_mps2: float, smoothing_m: float) -> np.ndarray:
    """v_adm(s) ``(J, G, M)`` per lateral acceleration for G padded profiles ``(G, M)`` (docs/method.md §4.2).

    Row g holds ``length[g]`` samples (the rest is padding). v_prof(s) =
    min(v_limit, √(a_lat / max(|κ(s)|, 1e-4))) with κ smoothed by a moving
    average over ``smoothing_m`` (lanelet joins give spikes; ends held),
    then the braking look-ahead v_adm(s) = min over s' ≥ s of √(v_prof(s')² +
    2b(s' − s)), a reverse cumulative minimum of v_prof² + 2b·s' along each
    row. Padding gets the last sample's value.
    """
    s = np.asarray(s_m, dtype=np.float64)
    n_rows, m = s.shape
    length = np.asarray(length, dtype=np.int64)
    col = np.arange(m)[None, :]
    valid = col < length[:, None]
    last = np.maximum(length - 1, 0)
    kappa = np.abs(np.asarray(curvature_1pm, dtype=np.float64))
    kappa = np.where(np.isfinite(kappa) & valid, kappa, 0.0)
    kappa = np.where(valid, kappa, kappa[np.arange(n_rows), last][:, None])
    step = np.where(length > 1, (s[np.arange(n_rows), last] - s[:, 0]) / np.maximum(last, 1), 1.0)
    half = np.clip(np.round(0.5 * smoothing_m / np.maximum(step, 1e-3)), 0, m).astype(np.int64)
    if smoothing_m > 0 and half.max() > 0:
        h = int(half.max())
        padded = np.concatenate([np.repeat(kappa[:, :1], h, axis=1), kappa, np.repeat(kappa[:, -1:], h + 1, axis=1)], axis=1)
        csum = np.concatenate([np.zeros((n_rows, 1)), np.cumsum(padded, axis=1)], axis=1)
        hi = col + h + half[:, None] + 1
        lo = col + h - half[:, None]
        kappa = (np.take_along_axis(csum, hi, axis=1) - np.take_along_axis(csum, lo, axis=1)) / (2 * half[:, None] + 1)
    a_lat = np.asarray(lat_accels_mps2, dtype=np.float64)[:, None, None]
    limit = np.asarray(speed_limit_mps, dtype=np.float64)[None, :, None]
    v_prof = np.minimum(limit, np.sqrt(a_lat / np.maximum(kappa[None], MIN_CURVATURE_1PM)))
    key = np.where(valid[None], v_prof**2 + 2.0 * brake_mps2 * s[None], np.inf)
    suffix_min = np.minimum.accumulate(key[..., ::-1], axis=-1)[..., ::-1]
    out = np.sqrt(np.maximum(suffix_min - 2.0 * brake_mps2 * s[None], 0.0))
    return np.where(valid[None], out, out[:, np.arange(n_rows), last][..., None])


def corridor_ok(corridor: Corridor) -> str | None:
    """Why a corridor cannot carry particles, or None."""
    arrays = (corridor.x_m, corridor.y_m, corridor.s_m, corridor.heading_rad)
    if len(corridor.s_m) < 2 or any(len(a) != len(corridor.s_m) for a in arrays):
        return f"{len(corridor.s_m)} centreline points"
    if not np.isfinite(np.stack(arrays)).all():
        return "non-finite centreline"
    if not (np.diff(corridor.s_m) > 0.0).all():
        return "arc length not increasing"
    if not (math.isfinite(corridor.vehicle_s_m) and math.isfinite(corridor.vehicle_d_m)):
        return "non-finite vehicle s/d"
    return None


def corridors_ok(corridors: Sequence[Corridor]) -> list[str | None]:
    """`corridor_ok` of several corridors: the checks run on all of them at once, the reason is worded for the failing ones."""
    if not corridors:
        return []
    try:
        lengths = [len(c.s_m) for c in corridors]
        if min(lengths) >= 2 and all(len(a) == n for c, n in zip(corridors, lengths) for a in (c.x_m, c.y_m, c.heading_rad)):
            s = np.concatenate([c.s_m for c in corridors])
            finite = bool(np.isfinite(s).all()) and all(bool(np.isfinite(np.concatenate(parts)).all()) for parts in (
                [c.x_m for c in corridors], [c.y_m for c in corridors], [c.heading_rad for c in corridors]))
            ends = np.cumsum(lengths)[:-1]
            increasing = np.diff(s) > 0.0
            increasing[ends - 1] = True  # from one corridor's last sample to the next one's first: no step
            vehicle = np.array([(c.vehicle_s_m, c.vehicle_d_m) for c in corridors], dtype=np.float64)
            if finite and bool(increasing.all()) and bool(np.isfinite(vehicle).all()):
                return [None] * len(corridors)
    except (TypeError, ValueError):  # odd arrays: worded one by one below
        pass
    return [corridor_ok(c) for c in corridors]


@dataclass(frozen=True, slots=True)
class VehicleInput:
    """One vehicle to update: its corridors (all usable) and the lanelet it is matched to."""

    track_id: int
    corridors: tuple[Corridor, ...]
    lanelet_id: int


@dataclass(frozen=True, slots=True, eq=False)
class PairTables:
    """The pairs of one frame; G pairs, V vehicles, T centreline samples, J driver styles, C conflicts.

    Pairs of vehicle v are ``first_pair[v] : first_pair[v] + n_slots[v]``, in
    the order of its corridors. Samples of pair g are ``start[g] : end[g]``.
    """

    vehicle: np.ndarray  # (G,) int64
    first_pair: np.ndarray  # (V,) int64
    n_slots: np.ndarray  # (V,) int64
    start: np.ndarray  # (G,) int64
    end: np.ndarray  # (G,) int64
    key: np.ndarray  # (T,) s + g·KEY_OFFSET_M
    s_m: np.ndarray  # (T,)
    x_m: np.ndarray  # (T,)
    y_m: np.ndarray  # (T,)
    heading_rad: np.ndarray  # (T,), unwrapped within each pair
    v_adm_mps: np.ndarray  # (J, T)
    vehicle_s_m: np.ndarray  # (G,)
    vehicle_d_m: np.ndarray  # (G,)
    entry_s_m: np.ndarray  # (G,) next intersection entrance ahead of the vehicle, NaN if none
    stop_s_m: np.ndarray  # (G,) where the stop model brakes for: entrance − stop offset, NaN if none
    switch_s_m: np.ndarray  # (G,) start of the vehicle's matched lanelet on the corridor, NaN if absent
    conflict_s_m: np.ndarray  # (G, C) conflict points with priority corridors, NaN padding
    conflict_other_time_s: np.ndarray  # (G, C)
    conflict_weight: np.ndarray  # (G, C) P(R = the other corridor), 0 padding
    signal_line_s_m: np.ndarray | None = None  # (G,) next signalised stop line, NaN if none; None: no signal fields (stages.intentions.signals)
    signal_phase: np.ndarray | None = None  # (G,) uint8 SignalPhase of its group

    @property
    def n_pairs(self) -> int:
        return int(self.vehicle.shape[0])

    def locate(self, g: np.ndarray, s_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(segment start index i, fraction t) of arc lengths on pairs, any matching shape.

        t lies in [0, 1) inside the corridor and outside it beyond either end
        (the end segments extended straight).
        """
        s = np.clip(s_m, -kernels.S_CLIP_M, kernels.S_CLIP_M)
        i = np.searchsorted(self.key, s + g * KEY_OFFSET_M, side="right") - 1
        i = np.clip(i, self.start[g], self.end[g] - 2)
        t = (s - self.s_m[i]) / (self.s_m[i + 1] - self.s_m[i])
        return i, t

    def pose(self, g: np.ndarray, s_m: np.ndarray, d_m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """x, y and heading of Frenet points (s, d) on pairs g: X(s) + d·n(s), ψ(s) (compiled: `kernels.pose`, the same bits)."""
        found = kernels.pose(self, g, s_m, d_m, KEY_OFFSET_M)
        return found if found is not None else self.pose_numpy(g, s_m, d_m)

    def pose_numpy(self, g: np.ndarray, s_m: np.ndarray, d_m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """`pose` on numpy (where numba is missing)."""
        i, t = self.locate(g, s_m)
        x = self.x_m[i] + t * (self.x_m[i + 1] - self.x_m[i])
        y = self.y_m[i] + t * (self.y_m[i + 1] - self.y_m[i])
        tc = np.clip(t, 0.0, 1.0)
        heading = self.heading_rad[i] + tc * (self.heading_rad[i + 1] - self.heading_rad[i])
        return x - d_m * np.sin(heading), y + d_m * np.cos(heading), heading

    def admissible_speed(self, g: np.ndarray, s_m: np.ndarray, style: np.ndarray) -> np.ndarray:
        """v_adm of each particle's corridor and driver style at its s (held beyond the ends; compiled: `kernels.admissible_speed`)."""
        found = kernels.admissible_speed(self, g, s_m, style, KEY_OFFSET_M)
        return found if found is not None else self.admissible_speed_numpy(g, s_m, style)

    def admissible_speed_numpy(self, g: np.ndarray, s_m: np.ndarray, style: np.ndarray) -> np.ndarray:
        """`admissible_speed` on numpy (where numba is missing)."""
        i, t = self.locate(g, s_m)
        tc = np.clip(t, 0.0, 1.0)
        v0 = self.v_adm_mps[style, i]
        return v0 + tc * (self.v_adm_mps[style, i + 1] - v0)


def next_entry_s_m(relations: CorridorRelations | None, vehicle_s_m: float) -> float:
    """Arc length of the first intersection entrance ahead of the vehicle on a corridor, NaN if none."""
    if relations is None:
        return math.nan
    entries = np.asarray(relations.intersection_entry_s_m, dtype=np.float64).tolist()
    return min((e for e in entries if math.isfinite(e) and e > vehicle_s_m), default=math.nan)


def build_tables(
    vehicles: Sequence[VehicleInput],
    relations: Mapping[tuple[int, int], CorridorRelations],
    route_probabilities: Mapping[tuple[int, int], float],
    *,
    lat_accels_mps2: Sequence[float],
    brake_lookahead_mps2: float,
    curvature_smoothing_m: float,
    default_speed_limit_mps: float,
    stop_offset_m: float,
) -> PairTables:
    """The tables of one frame; `relations` keyed by (track_id, corridor_id), `route_probabilities` likewise (last beliefs)."""
    n_vehicles = len(vehicles)
    n_slots = np.array([len(v.corridors) for v in vehicles], dtype=np.int64)
    first_pair = np.concatenate([[0], np.cumsum(n_slots)[:-1]]).astype(np.int64) if n_vehicles else np.zeros(0, np.int64)
    pair_vehicle, s_parts, x_parts, y_parts, h_parts, k_parts, limits = [], [], [], [], [], [], []
    vehicle_s, vehicle_d, entry, switch = [], [], [], []
    conflicts: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    for v, vehicle in enumerate(vehicles):
        for corridor in vehicle.corridors:
            pair_vehicle.append(v)
            s_parts.append(np.asarray(corridor.s_m, dtype=np.float64))
            x_parts.append(np.asarray(corridor.x_m, dtype=np.float64))
            y_parts.append(np.asarray(corridor.y_m, dtype=np.float64))
            h_parts.append(np.asarray(corridor.heading_rad, dtype=np.float64))
            k_parts.append(np.asarray(corridor.curvature_1pm, dtype=np.float64))
            ok = math.isfinite(corridor.speed_limit_mps) and corridor.speed_limit_mps > 0
            limits.append(corridor.speed_limit_mps if ok else default_speed_limit_mps)
            vehicle_s.append(float(corridor.vehicle_s_m))
            vehicle_d.append(float(corridor.vehicle_d_m))
            rel = relations.get((vehicle.track_id, corridor.corridor_id))
            entry.append(next_entry_s_m(rel, float(corridor.vehicle_s_m)))
            ids = lanelet_ids_of(corridor)
            switch.append(float(corridor.lanelet_start_s_m[ids.index(vehicle.lanelet_id)]) if vehicle.lanelet_id in ids else math.nan)
            conflicts.append(_priority_conflicts(rel, route_probabilities))
    n_pairs = len(pair_vehicle)
    lengths = np.array([len(s) for s in s_parts], dtype=np.int64)
    start = np.concatenate([[0], np.cumsum(lengths)[:-1]]).astype(np.int64) if n_pairs else np.zeros(0, np.int64)
    s_all = np.concatenate(s_parts) if n_pairs else np.zeros(0)
    # s + g·offset per pair g (g·offset as the double Python's int * float gives, added sample by sample: the same sums)
    key = s_all + np.repeat(np.arange(n_pairs, dtype=np.int64) * KEY_OFFSET_M, lengths) if n_pairs else np.zeros(0)
    if n_pairs:
        k_all = np.concatenate(k_parts)
        v_adm = kernels.admissible_speeds(s_all, k_all, lengths, limits, lat_accels_mps2, brake_lookahead_mps2, curvature_smoothing_m,
                                          MIN_CURVATURE_1PM)  # compiled, the same bits; None: numpy
        if v_adm is None:
            width = int(lengths.max())
            s_pad = np.zeros((n_pairs, width))
            k_pad = np.zeros((n_pairs, width))
            valid = np.arange(width)[None, :] < lengths[:, None]
            s_pad[valid] = s_all
            k_pad[valid] = k_all
            v_adm = admissible_speeds(s_pad, k_pad, lengths, limits, lat_accels_mps2, brake_lookahead_mps2, curvature_smoothing_m)
            v_adm = v_adm[:, valid]
    else:
        v_adm = np.zeros((len(lat_accels_mps2), 0))
    n_conf = max((len(c[0]) for c in conflicts), default=0)
    conflict_s = np.full((n_pairs, max(n_conf, 1)), np.nan)
    conflict_t = np.full((n_pairs, max(n_conf, 1)), np.nan)
    conflict_w = np.zeros((n_pairs, max(n_conf, 1)))
    for k, (cs, ct, cw) in enumerate(conflicts):
        if len(cs):  # (an empty row stays padding)
            conflict_s[k, : len(cs)], conflict_t[k, : len(cs)], conflict_w[k, : len(cs)] = cs, ct, cw
    entry_s = np.asarray(entry, dtype=np.float64)
    cat = (lambda parts: np.concatenate(parts)) if n_pairs else (lambda parts: np.zeros(0))
    return PairTables(
        vehicle=np.asarray(pair_vehicle, dtype=np.int64),
        first_pair=first_pair,
        n_slots=n_slots,
        start=start,
        end=start + lengths,
        key=key,
        s_m=s_all,
        x_m=cat(x_parts),
        y_m=cat(y_parts),
        heading_rad=unwrap_parts(h_parts) if n_pairs else np.zeros(0),
        v_adm_mps=v_adm,
        vehicle_s_m=np.asarray(vehicle_s, dtype=np.float64),
        vehicle_d_m=np.asarray(vehicle_d, dtype=np.float64),
        entry_s_m=entry_s,
        stop_s_m=entry_s - stop_offset_m,
        switch_s_m=np.asarray(switch, dtype=np.float64),
        conflict_s_m=conflict_s,
        conflict_other_time_s=conflict_t,
        conflict_weight=conflict_w,
    )


def unwrap_parts(parts: Sequence[np.ndarray]) -> np.ndarray:
    """The arrays concatenated, each ``np.unwrap``-ped on its own (exactly): those without a jump of π or more between
    neighbours are what ``np.unwrap`` makes of them (unchanged, the samples after the first plus 0.0) in one pass."""
    flat = np.concatenate(parts)
    out = flat + 0.0
    lengths = np.array([len(p) for p in parts], dtype=np.int64)
    starts = np.concatenate([[0], np.cumsum(lengths)[:-1]])
    out[starts[lengths > 0]] = flat[starts[lengths > 0]]
    jump = ~(np.abs(np.diff(flat)) < np.pi)  # NaN counts as a jump
    jump[(starts + lengths - 1)[(lengths > 0) & (starts + lengths < flat.size)]] = False  # across two parts
    if jump.any():
        owner = np.searchsorted(starts, np.flatnonzero(jump), side="right") - 1
        for k in np.unique(owner).tolist():
            out[starts[k] : starts[k] + lengths[k]] = np.unwrap(parts[k])
    return out


_NO_CONFLICTS = tuple(np.zeros(0) for _ in range(3))
for _a in _NO_CONFLICTS:
    _a.flags.writeable = False


def _priority_conflicts(rel: CorridorRelations | None, route_probabilities: Mapping[tuple[int, int], float]):
    """(s*, T', P(R = other corridor)) of the conflicts where the other corridor has priority (c,) (read only when empty)."""
    if rel is None or not len(rel.conflict_priority):
        return _NO_CONFLICTS
    priority, s_star, t_other = rel.conflict_priority, rel.conflict_s_m, rel.conflict_other_time_s
    if len(priority) == len(s_star) == len(t_other):  # on Python numbers: few conflicts per pair
        keep = [k for k, (pr, s, t) in enumerate(zip(np.asarray(priority).tolist(), np.asarray(s_star, np.float64).tolist(),
                                                     np.asarray(t_other, np.float64).tolist())) if pr < 0 and math.isfinite(s) and math.isfinite(t)]
    else:  # numpy's broadcasting (or its error) as before
        keep = np.flatnonzero((np.asarray(priority) < 0) & np.isfinite(s_star) & np.isfinite(t_other)).tolist()
    if not keep:
        return _NO_CONFLICTS
    tracks, corridors = rel.conflict_track_ids, rel.conflict_corridor_ids
    if type(tracks) is np.ndarray and type(corridors) is np.ndarray and tracks.dtype.kind in "iu" and corridors.dtype.kind in "iu":
        tracks, corridors = tracks.tolist(), corridors.tolist()  # Python ints: what int() of each element gives
    weights = np.array([route_probabilities.get((int(tracks[k]), int(corridors[k])), 1.0) for k in keep], dtype=np.float64)
    index = np.asarray(keep, dtype=np.int64)
    return np.asarray(rel.conflict_s_m, np.float64)[index], np.asarray(rel.conflict_other_time_s, np.float64)[index], weights.reshape(-1)


# --------------------------------------------------------------------------- corridor changes


def common_run(old: Sequence[int], new: Sequence[int]) -> tuple[int, int]:
    """(length, lanelet) of the longest run of consecutive lanelets two corridors share; (0, 0) if none.

    The run is aligned where both hold one lanelet; the lanelet returned is
    the run's first (its start gives the arc-length shift between them).
    """
    best, lanelet = 0, 0
    for i, a in enumerate(old):
        for j, b in enumerate(new):
            if a != b:
                continue
            n = 0
            while i + n < len(old) and j + n < len(new) and old[i + n] == new[j + n]:
                n += 1
            if n > best:
                best, lanelet = n, int(a)
    return best, lanelet


def lanelet_ids_of(corridor: Corridor) -> list[int]:
    """The corridor's lanelet ids as Python ints."""
    ids = corridor.lanelet_ids
    return ids.tolist() if isinstance(ids, np.ndarray) else [int(x) for x in ids]


def lanelet_shift_m(old: Corridor, new: Corridor, lanelet_id: int, old_ids: list[int] | None = None, new_ids: list[int] | None = None) -> float:
    """s_new − s_old for a point on `lanelet_id`, which both corridors hold (their first entry of it); `old_ids`/`new_ids`:
    the corridors' lanelet ids when at hand."""
    i = (old_ids if old_ids is not None else lanelet_ids_of(old)).index(lanelet_id)
    j = (new_ids if new_ids is not None else lanelet_ids_of(new)).index(lanelet_id)
    return float(new.lanelet_start_s_m[j]) - float(old.lanelet_start_s_m[i])


def map_corridors(old: Sequence[Corridor], new: Sequence[Corridor]) -> list[tuple[int, float]]:
    """For every old corridor, (new slot, arc-length shift) or (-1, NaN) when it has no successor.

    The new corridor with the same id (shift from the first old lanelet the
    new one holds), else the one with the longest common lanelet run (ties:
    the first; shift from the run's first lanelet). An old corridor sharing
    no lanelet with any new one maps to -1: its particles are placed by
    projection (`IntentionFilter`).
    """
    out = []
    ids = {c.corridor_id: j for j, c in enumerate(new)}
    new_lanelets = [lanelet_ids_of(c) for c in new]
    for corridor in old:
        old_lanelets = lanelet_ids_of(corridor)
        j = ids.get(corridor.corridor_id, -1)
        if j >= 0:
            shared = set(new_lanelets[j])
            lanelet = next((x for x in old_lanelets if x in shared), None)
            out.append((j, math.nan if lanelet is None else lanelet_shift_m(corridor, new[j], lanelet, old_lanelets, new_lanelets[j])))
            continue
        runs = [common_run(old_lanelets, lanelets) for lanelets in new_lanelets]
        lengths = [n for n, _ in runs]
        if not lengths or max(lengths) == 0:
            out.append((-1, math.nan))
            continue
        j = int(np.argmax(lengths))
        out.append((j, lanelet_shift_m(corridor, new[j], runs[j][1], old_lanelets, new_lanelets[j])))
    return out


# --------------------------------------------------------------------------- manoeuvres


def corridor_manoeuvre(road_map: RoadMap | None, corridor: Corridor, lane_change_reach_m: float) -> tuple[Manoeuvre, bool]:
    """(manoeuvre, changes lane) of following a corridor, from the map.

    The next intersection ahead (the first run of member lanelets whose end
    lies ahead of the vehicle): TURN_LEFT/TURN_RIGHT when one of its member
    lanelets on the corridor turns (``LaneletInfo.turn``), else GO_STRAIGHT.
    Without an intersection ahead: LANE_CHANGE_LEFT/RIGHT when the corridor
    switches lane at a boundary less than `lane_change_reach_m` behind the
    vehicle or ahead of it (consecutive lanelets that are not successors),
    else FOLLOW_LANE. "Changes lane" is that switch, with or without a turn.
    UNKNOWN without a map.
    """
    if road_map is None:
        return Manoeuvre.UNKNOWN, False
    ids = lanelet_ids_of(corridor)
    starts = np.asarray(corridor.lanelet_start_s_m, dtype=np.float64)
    s_v = float(corridor.vehicle_s_m)
    known = [road_map.has_lanelet(x) for x in ids]
    change = None
    for k in range(1, len(ids)):
        if known[k - 1] and known[k] and ids[k] not in road_map.successors(ids[k - 1]) and starts[k] > s_v - lane_change_reach_m:
            change = _side(road_map, ids[k - 1], ids[k])
            break
    turn = None
    intersection = None
    for k, lanelet_id in enumerate(ids):
        if not known[k]:
            continue
        end = starts[k] + road_map.lanelet(lanelet_id).length_m
        found = road_map.intersection_of(lanelet_id)
        if found is None or end <= s_v:
            if intersection is not None:
                break
            continue
        if intersection is not None and found.intersection_id != intersection:
            break
        intersection = found.intersection_id
        info = road_map.lanelet(lanelet_id)
        if turn is None and info.turn in (Turn.LEFT, Turn.RIGHT):
            turn = Manoeuvre.TURN_LEFT if info.turn is Turn.LEFT else Manoeuvre.TURN_RIGHT
    if turn is not None:
        return turn, change is not None
    if intersection is not None:
        return Manoeuvre.GO_STRAIGHT, change is not None
    if change is not None:
        return change, True
    return Manoeuvre.FOLLOW_LANE, False


def _side(road_map: RoadMap, before: int, after: int) -> Manoeuvre:
    """LANE_CHANGE_LEFT/RIGHT for a switch from `before` into `after` (a neighbour of one of its successors)."""
    for succ in road_map.successors(before):
        neighbours = road_map.neighbours(succ)
        if neighbours.left_id == after:
            return Manoeuvre.LANE_CHANGE_LEFT
        if neighbours.right_id == after:
            return Manoeuvre.LANE_CHANGE_RIGHT
    a = road_map.lanelet(before).centreline
    b = road_map.lanelet(after).centreline
    heading = float(a.heading_rad[-1])
    dx, dy = b.points_m[0] - a.points_m[-1]
    return Manoeuvre.LANE_CHANGE_LEFT if math.cos(heading) * dy - math.sin(heading) * dx > 0 else Manoeuvre.LANE_CHANGE_RIGHT
