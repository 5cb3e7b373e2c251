"""Corridors: the lanelet sequences each vehicle may follow (``iamp.CorridorSet``)."""

from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import Any, Annotated, ClassVar

import numpy as np

from ._wire import Array, Message, Range, register
from .common import HEADER_WALL_UPGRADE, ACCEL_OR_NAN, ANGLE_OR_NAN, COORD, DIST_OR_NAN, FINITE_OR_NAN, NON_NEG_INT, SPEED_OR_NAN, VEL_OR_NAN, AgentType, Header

PTS = Annotated[np.ndarray, Array("float64", ("m",))]
M = ("m",)


class MatchStatus(enum.IntEnum):
    """How a tracked object was matched to the map."""

    UNKNOWN = 0
    MATCHED = 1  # on (or near) a car lanelet with agreeing heading: has corridors
    OFF_MAP = 2  # no car lanelet near enough (parking lot, outside the map, wrong way)
    NOT_A_VEHICLE = 3  # pedestrians, cyclists: obstacles only, no corridors
    BAD_STATE = 4  # NaN/inf position or speed: skipped this frame


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class Corridor:
    """One possible route: a lanelet sequence with a resampled centreline.

    The centreline arrays all have shape ``(m,)`` and are sampled about every
    0.5 m; ``s_m`` is the arc length from the corridor's start, which lies a
    little behind the vehicle. ``lanelet_start_s_m[i]`` is where
    ``lanelet_ids[i]`` begins along the corridor. Past ``extension_start_s_m``
    the corridor is the last lanelet extended straight (the map ended).
    ``vehicle_s_m``/``vehicle_d_m`` are the vehicle's Frenet coordinates on it
    (d positive to the left).
    """

    corridor_id: Annotated[int, NON_NEG_INT]
    lanelet_ids: Annotated[np.ndarray, Array("int64", ("k",))]
    lanelet_start_s_m: Annotated[np.ndarray, Array("float64", ("k",)), DIST_OR_NAN]
    x_m: Annotated[np.ndarray, Array("float64", M), COORD]
    y_m: Annotated[np.ndarray, Array("float64", M), COORD]
    s_m: Annotated[np.ndarray, Array("float64", M), COORD]
    heading_rad: Annotated[np.ndarray, Array("float64", M), ANGLE_OR_NAN]
    curvature_1pm: Annotated[np.ndarray, Array("float64", M), FINITE_OR_NAN]
    width_m: Annotated[np.ndarray, Array("float64", M), Range(0.0, 1000.0, nan=True, unit="m")]
    extension_start_s_m: Annotated[float, DIST_OR_NAN]
    vehicle_s_m: Annotated[float, DIST_OR_NAN]
    vehicle_d_m: Annotated[float, DIST_OR_NAN]
    speed_limit_mps: Annotated[float, SPEED_OR_NAN]


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class VehicleCorridors:
    """The corridors of one tracked object (empty unless ``status`` is MATCHED).

    The kinematic state is estimated from the track's positions, causally
    (``stages.lib.kinematic_state``), never copied from the tracker: ``speed_mps``,
    the velocity ``vx_mps``/``vy_mps`` (m/s east/north) and the longitudinal
    ``accel_mps2``; ``standing`` inside the standstill dead band (then all
    three are 0). ``reported_speed_mps`` is the tracker's own figure, kept as
    evidence. At a track's first sample the speed is the reported one and the
    velocity the reported vector (NaN when unknown).
    """

    track_id: Annotated[int, NON_NEG_INT]
    agent_type: AgentType
    status: MatchStatus
    lanelet_id: int  # the matched lanelet, -1 if none
    match_distance_m: Annotated[float, Range(-1.0, 1.0e6, nan=True, unit="m")]  # -1: not matched
    speed_mps: Annotated[float, SPEED_OR_NAN]
    corridors: tuple[Corridor, ...]
    vx_mps: Annotated[float, VEL_OR_NAN] = float("nan")
    vy_mps: Annotated[float, VEL_OR_NAN] = float("nan")
    accel_mps2: Annotated[float, ACCEL_OR_NAN] = float("nan")
    standing: bool = False
    reported_speed_mps: Annotated[float, SPEED_OR_NAN] = float("nan")


@register
@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class CorridorSet(Message):
    """Every object of one frame with its corridors; the corridors stage never drops one.

    A vehicle with a value outside its schema range (see the fields) is
    dropped at decoding by the receiving stage (``DROP_ELEMENTS``) and
    recorded there, never passed to its core.
    """

    SCHEMA: ClassVar[str] = "iamp.CorridorSet"
    VERSION: ClassVar[int] = 3  # v3: Header.source_wall_ns; v2: VehicleCorridors carries the estimated state (vx, vy, accel, standing, reported speed)
    UPGRADES: ClassVar[dict[int, Any]] = {2: HEADER_WALL_UPGRADE}  # v2 reads as v3 with source_wall_ns 0 (unknown)
    # measured 3.5-4.8 kB per corridor (0.5 m centreline samples, 6 float64 arrays): 8 MiB is about 2,000 corridors
    MAX_BYTES: ClassVar[int] = 8 * 1024 * 1024
    DROP_ELEMENTS: ClassVar[tuple[str, ...]] = ("vehicles",)

    header: Header
    scene_id: str
    vehicles: tuple[VehicleCorridors, ...]
