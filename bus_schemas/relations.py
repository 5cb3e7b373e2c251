"""Relations per vehicle and corridor (``iamp.RelationSet``): lateral, to intersections, to other corridors."""

from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import Any, Annotated, ClassVar

import numpy as np

from ._wire import Array, Message, Range, register
from .common import HEADER_WALL_UPGRADE, COORD_OR_NAN, DIST_OR_NAN, INT64_MAX, NON_NEG_INT, VEL_OR_NAN, Header
from .signals import HELD_S, SignalPhase


class ConflictKind(enum.IntEnum):
    UNKNOWN = 0
    CROSSING = 1
    MERGE = 2


# per-object arrays: o = surrounding objects, q = intersections, c = conflicts
I64_O = Annotated[np.ndarray, Array("int64", ("o",)), NON_NEG_INT]
U8_O = Annotated[np.ndarray, Array("uint8", ("o",))]
F64_O = Annotated[np.ndarray, Array("float64", ("o",)), DIST_OR_NAN]
V_O = Annotated[np.ndarray, Array("float64", ("o",)), VEL_OR_NAN]
I64_Q = Annotated[np.ndarray, Array("int64", ("q",))]
F64_Q = Annotated[np.ndarray, Array("float64", ("q",)), DIST_OR_NAN]
I64_C = Annotated[np.ndarray, Array("int64", ("c",)), NON_NEG_INT]
U8_C = Annotated[np.ndarray, Array("uint8", ("c",))]
I8_C = Annotated[np.ndarray, Array("int8", ("c",)), Range(-1, 1)]
F64_C = Annotated[np.ndarray, Array("float64", ("c",)), DIST_OR_NAN]
XY_C = Annotated[np.ndarray, Array("float64", ("c",)), COORD_OR_NAN]
V_C = Annotated[np.ndarray, Array("float64", ("c",)), VEL_OR_NAN]
T_C = Annotated[np.ndarray, Array("float64", ("c",)), Range(-1.0e9, 1.0e9, nan=True, unit="s")]
ID_OR_NONE = Range(-1, INT64_MAX)


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class CorridorRelations:
    """What surrounds one vehicle on one of its corridors.

    Lateral relation, arrays ``(o,)``: every object whose projection onto the
    corridor lies within the lane (vehicles, pedestrians, cyclists), with its
    arc length, lateral offset, bumper-to-bumper gap along the corridor
    (negative: behind) and speed along the corridor. The leader is the nearest
    object ahead (``leader_track_id`` -1 and NaN gap when none).

    Corridor to intersection, arrays ``(q,)``: each intersection the corridor
    passes, with entry/exit arc lengths, the distance from the vehicle to the
    entry (negative once inside) and the lanelet through which it enters.

    Corridor to corridor, arrays ``(c,)``: conflict points with corridors of
    other vehicles, with the arc length on both, the point, the kind, the
    distances along each corridor from each vehicle to the point (negative:
    the vehicle's centre is past it), the other vehicle's speed, the times
    both vehicles need to reach it, and priority from this corridor's view
    (+1 this one has priority, -1 it must yield, 0 unknown/equal).
    ``influencing_*`` is the one conflict (index into the arrays, -1 if none)
    that the rules chose to influence this corridor, and ``influencing_rule``
    says which rule chose it.

    Corridor to signal (v2): the next signalised stop line on the corridor
    that the vehicle's front has not passed: its ``signal_group`` (-1: none,
    or the scene has no lane file), its arc length ``signal_stop_s_m``, the
    distance from the vehicle's centre to it ``signal_distance_m`` (NaN: no
    stop line), the group's ``signal_phase`` at this stamp (UNKNOWN when no
    ``SignalState`` of about this stamp was received) and how long it has
    shown it, ``signal_held_s`` (NaN: unknown).
    """

    track_id: Annotated[int, NON_NEG_INT]
    corridor_id: Annotated[int, NON_NEG_INT]
    object_track_ids: I64_O
    object_types: U8_O
    object_s_m: F64_O
    object_d_m: F64_O
    object_gap_m: F64_O
    object_speed_mps: V_O
    leader_track_id: Annotated[int, ID_OR_NONE]
    leader_gap_m: Annotated[float, DIST_OR_NAN]
    leader_speed_mps: Annotated[float, VEL_OR_NAN]
    intersection_ids: I64_Q
    intersection_entry_s_m: F64_Q
    intersection_exit_s_m: F64_Q
    intersection_distance_m: F64_Q
    intersection_entry_lanelet_ids: I64_Q
    conflict_track_ids: I64_C
    conflict_corridor_ids: I64_C
    conflict_kinds: U8_C
    conflict_s_m: F64_C
    conflict_other_s_m: F64_C
    conflict_x_m: XY_C
    conflict_y_m: XY_C
    conflict_distance_m: F64_C
    conflict_other_distance_m: F64_C
    conflict_other_speed_mps: V_C
    conflict_time_s: T_C
    conflict_other_time_s: T_C
    conflict_priority: I8_C
    influencing_index: Annotated[int, ID_OR_NONE]
    influencing_rule: str
    signal_group: Annotated[int, ID_OR_NONE] = -1
    signal_stop_s_m: Annotated[float, DIST_OR_NAN] = float("nan")
    signal_distance_m: Annotated[float, DIST_OR_NAN] = float("nan")
    signal_phase: SignalPhase = SignalPhase.UNKNOWN
    signal_held_s: Annotated[float, HELD_S] = float("nan")


@register
@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class RelationSet(Message):
    """Relations of every (vehicle, corridor) pair of one frame.

    v2: each pair's next signalised stop line (``signal_*``).
    """

    SCHEMA: ClassVar[str] = "iamp.RelationSet"
    VERSION: ClassVar[int] = 3  # v3: Header.source_wall_ns
    UPGRADES: ClassVar[dict[int, Any]] = {2: HEADER_WALL_UPGRADE}  # v2 reads as v3 with source_wall_ns 0 (unknown)
    # measured about 1 kB per (vehicle, corridor) pair with <= 5 objects; the arrays grow with objects and conflicts
    MAX_BYTES: ClassVar[int] = 8 * 1024 * 1024
    # a pair's relations with a value out of range are dropped (recorded): the pair has none at this stamp
    DROP_ELEMENTS: ClassVar[tuple[str, ...]] = ("relations",)

    header: Header
    scene_id: str
    relations: tuple[CorridorRelations, ...]
