"""Parts shared by every message family: the header and agent types."""

from __future__ import annotations

import enum
from dataclasses import dataclass


@dataclass(frozen=True, slots=True, kw_only=True)
class Header:
    """Where a message comes from and which source frame it derives from.

    ``stamp_ns`` is the time of the source frame (recording time for a dataset,
    sensor time for a live tracker), not the wall clock; stages with several
    inputs join on it. ``frame_index`` counts source frames from 0.
    """

    run_id: str
    frame_index: int
    stamp_ns: int
    producer: str


class AgentType(enum.IntEnum):
    UNKNOWN = 0
    CAR = 1
    TRUCK = 2
    BUS = 3
    MOTORCYCLE = 4
    BICYCLE = 5
    PEDESTRIAN = 6

    @property
    def is_vehicle(self) -> bool:
        """Vehicles get corridors and Markov predictions; the rest are obstacles."""
        return self in (AgentType.CAR, AgentType.TRUCK, AgentType.BUS, AgentType.MOTORCYCLE)


VEHICLE_TYPE_VALUES = frozenset(int(t) for t in AgentType if t.is_vehicle)
