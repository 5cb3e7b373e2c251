"""Relations per vehicle and corridor (``iamp.RelationSet``): lateral, to intersections, to other corridors."""

from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import Annotated, ClassVar

import numpy as np

from ._wire import Array, Message, register
from .common import Header


class ConflictKind(enum.IntEnum):
    UNKNOWN = 0
    CROSSING = 1
    MERGE = 2


def _a(dtype: str, dim: str):
    return Annotated[np.ndarray, Array(dtype, (dim,))]


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
    times both vehicles need to reach it, and priority from this corridor's
    view (+1 this one has priority, -1 it must yield, 0 unknown/equal).
    ``influencing_*`` is the one conflict (index into the arrays, -1 if none)
    that the rules chose to influence this corridor, and ``influencing_rule``
    says which rule chose it.
    """

    track_id: int
    corridor_id: int
    object_track_ids: _a("int64", "o")
    object_types: _a("uint8", "o")
    object_s_m: _a("float64", "o")
    object_d_m: _a("float64", "o")
    object_gap_m: _a("float64", "o")
    object_speed_mps: _a("float64", "o")
    leader_track_id: int
    leader_gap_m: float
    leader_speed_mps: float
    intersection_ids: _a("int64", "q")
    intersection_entry_s_m: _a("float64", "q")
    intersection_exit_s_m: _a("float64", "q")
    intersection_distance_m: _a("float64", "q")
    intersection_entry_lanelet_ids: _a("int64", "q")
    conflict_track_ids: _a("int64", "c")
    conflict_corridor_ids: _a("int64", "c")
    conflict_kinds: _a("uint8", "c")
    conflict_s_m: _a("float64", "c")
    conflict_other_s_m: _a("float64", "c")
    conflict_x_m: _a("float64", "c")
    conflict_y_m: _a("float64", "c")
    conflict_time_s: _a("float64", "c")
    conflict_other_time_s: _a("float64", "c")
    conflict_priority: _a("int8", "c")
    influencing_index: int
    influencing_rule: str


@register
@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class RelationSet(Message):
    """Relations of every (vehicle, corridor) pair of one frame."""

    SCHEMA: ClassVar[str] = "iamp.RelationSet"
    VERSION: ClassVar[int] = 1

    header: Header
    scene_id: str
    relations: tuple[CorridorRelations, ...]
