"""Parts shared by every message family: the header and agent types."""

from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import Annotated

from ._wire import Range

# Value ranges shared by the schemas (see ``_wire``: checked at decoding). Generous on
# purpose: they catch what no sensor or stage produces (inf, 1e308, negative sizes,
# stamps past int64), not what is merely unusual.
MAX_COORD_M = 1.0e6  # map-frame coordinates: a local frame spans kilometres, not 1,000 km
MAX_SPEED_MPS = 150.0  # 540 km/h
MAX_ACCEL_MPS2 = 100.0
INT64_MAX = 2**63 - 1
COORD = Range(-MAX_COORD_M, MAX_COORD_M, unit="m")
COORD_OR_NAN = Range(-MAX_COORD_M, MAX_COORD_M, nan=True, unit="m")
DIST_OR_NAN = Range(-MAX_COORD_M, MAX_COORD_M, nan=True, unit="m")
SPEED_OR_NAN = Range(0.0, 2 * MAX_SPEED_MPS, nan=True, unit="m/s")  # a norm of two components of up to MAX_SPEED_MPS
FINITE = Range()
FINITE_OR_NAN = Range(nan=True)
ANGLE_OR_NAN = Range(-100.0, 100.0, nan=True, unit="rad")
VEL_OR_NAN = Range(-MAX_SPEED_MPS, MAX_SPEED_MPS, nan=True, unit="m/s")
ACCEL_OR_NAN = Range(-MAX_ACCEL_MPS2, MAX_ACCEL_MPS2, nan=True, unit="m/s2")
PROB = Range(0.0, 1.0 + 1e-5)  # float32 sums may exceed 1 by rounding
PROB_OR_NAN = Range(0.0, 1.0 + 1e-5, nan=True)
NON_NEG_INT = Range(0, INT64_MAX)


@dataclass(frozen=True, slots=True, kw_only=True)
class Header:
    """Where a message comes from and which source frame it derives from.

    ``stamp_ns`` is the time of the source frame (recording time for a dataset,
    sensor time for a live tracker), not the wall clock; stages with several
    inputs join on it. ``frame_index`` counts source frames from 0.

    ``source_wall_ns`` is the wall clock (Unix ns) at which the source
    published the source frame this message derives from; every stage copies
    it from its input (a stage joining several inputs, from the source
    frame's) into its outputs, so that any node can measure end-to-end
    latency. 0: unknown (a recording made before the field existed, a
    message not derived from a source frame). Added in the header-v2 bump
    (``HEADER_WALL_UPGRADE``).
    """

    run_id: str
    frame_index: Annotated[int, NON_NEG_INT]
    stamp_ns: Annotated[int, NON_NEG_INT]
    producer: str
    source_wall_ns: Annotated[int, NON_NEG_INT] = 0


def _header_add_wall(body: object) -> object:
    """Body of a schema version from before ``Header.source_wall_ns``, made a body of the next one (wall stamp 0: unknown).

    Only a well-formed map with a header map is changed; anything else goes
    on unchanged, for the strict decoder to reject with its usual message.
    """
    if isinstance(body, dict):
        header = body.get("header")
        if isinstance(header, dict) and "source_wall_ns" not in header:
            return {**body, "header": {**header, "source_wall_ns": 0}}
    return body


HEADER_WALL_UPGRADE = _header_add_wall
"""``Message.UPGRADES`` entry of every schema whose only change in its bump was ``Header.source_wall_ns``."""


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
