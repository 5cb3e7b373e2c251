"""Intentions of every vehicle (``iamp.IntentionBelief``): the DBN's route, stop/go and manoeuvre beliefs (docs/method.md §7).

One ``VehicleBelief`` per vehicle the intentions stage updated at this stamp,
with one ``CorridorBelief`` per corridor of the CorridorSet of the same stamp
(same ``corridor_id``, same order). ``(track_id, corridor_id)`` names a
corridor; ``IntentionBelief.route_probabilities()`` gives P(R = c) keyed that
way, which is what the motion grid weights corridors by and what the
relations stage's influencing rule takes.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import Any, Annotated, ClassVar

from ._wire import Message, Range, register
from .common import HEADER_WALL_UPGRADE, ACCEL_OR_NAN, DIST_OR_NAN, NON_NEG_INT, PROB, SPEED_OR_NAN, Header

_STD = Range(0.0, 1.0e6, nan=True)
_COUNT = Range(0, 10_000_000)


class Manoeuvre(enum.IntEnum):
    """What a vehicle is expected to do next (the most probable manoeuvre)."""

    UNKNOWN = 0
    FOLLOW_LANE = 1  # no intersection ahead on the corridor and no lane change
    GO_STRAIGHT = 2  # through the next intersection without turning
    TURN_LEFT = 3
    TURN_RIGHT = 4
    LANE_CHANGE_LEFT = 5
    LANE_CHANGE_RIGHT = 6
    STOP = 7  # stop before the next intersection entrance


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class CorridorBelief:
    """The belief about one corridor of a vehicle.

    ``probability`` is P(R = corridor); over a vehicle's corridors they sum to
    1. ``manoeuvre`` is what following this corridor means (turn, straight,
    lane change, follow lane; never STOP). ``particle_count`` particles carry
    it; the means and standard deviations of arc length ``s`` (the corridor's
    own s of the CorridorSet of this stamp), speed and acceleration are
    weighted over those particles (the Markov chain's initial box), NaN
    without particles. ``p_stop`` is P(I = stop | R = corridor) and
    ``stop_distance_m`` the distance from the vehicle to the stop position
    the stop model brakes for on this corridor (NaN when no intersection lies
    ahead on it).
    """

    corridor_id: Annotated[int, NON_NEG_INT]
    probability: Annotated[float, PROB]
    manoeuvre: Manoeuvre
    particle_count: Annotated[int, _COUNT]
    s_mean_m: Annotated[float, DIST_OR_NAN]
    s_std_m: Annotated[float, _STD]
    v_mean_mps: Annotated[float, SPEED_OR_NAN]
    v_std_mps: Annotated[float, _STD]
    a_mean_mps2: Annotated[float, ACCEL_OR_NAN]
    a_std_mps2: Annotated[float, _STD]
    p_stop: Annotated[float, PROB]
    stop_distance_m: Annotated[float, DIST_OR_NAN]


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class VehicleBelief:
    """The DBN's belief about one vehicle at this stamp.

    ``p_stop``: P(I = stop), the vehicle intends to stop before the entrance
    of the next intersection (go otherwise); ``p_expected_stop``: P(E =
    stop), the rules and gaps expect it to stop/yield; ``p_violation``:
    P(I ≠ E); ``p_lane_change``: the probability of the corridors that change
    lane. ``expected_manoeuvre``: STOP when ``p_stop`` > 0.5 and an
    intersection lies ahead, else the manoeuvre of the most probable
    corridor. ``intersection_distance_m``: the distance from the vehicle to
    the next intersection entrance on the most probable corridor (NaN when
    none lies ahead). ``effective_sample_size`` is 1/Σw² of the particle
    weights after this update (before any resampling), out of
    ``particle_count`` particles.
    """

    track_id: Annotated[int, NON_NEG_INT]
    corridors: tuple[CorridorBelief, ...]
    p_stop: Annotated[float, PROB]
    p_expected_stop: Annotated[float, PROB]
    p_violation: Annotated[float, PROB]
    p_lane_change: Annotated[float, PROB]
    expected_manoeuvre: Manoeuvre
    intersection_distance_m: Annotated[float, DIST_OR_NAN]
    effective_sample_size: Annotated[float, Range(0.0, 10_000_000.0, nan=True)]
    particle_count: Annotated[int, _COUNT]


@register
@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class IntentionBelief(Message):
    """The beliefs of every vehicle the intentions stage updated at this stamp.

    Probabilities lie in [0, 1]; a vehicle with a value outside its range is
    dropped at decoding (``DROP_ELEMENTS``, recorded): it has no belief at
    this stamp, as if the intentions stage had not updated it.
    """

    SCHEMA: ClassVar[str] = "iamp.IntentionBelief"
    VERSION: ClassVar[int] = 2  # v2: Header.source_wall_ns
    UPGRADES: ClassVar[dict[int, Any]] = {1: HEADER_WALL_UPGRADE}  # v1 reads as v2 with source_wall_ns 0 (unknown)
    # measured 0.6-0.7 kB per vehicle: 2 MiB is about 3,000 vehicles
    MAX_BYTES: ClassVar[int] = 2 * 1024 * 1024
    DROP_ELEMENTS: ClassVar[tuple[str, ...]] = ("vehicles",)

    header: Header
    scene_id: str
    vehicles: tuple[VehicleBelief, ...]

    def vehicle(self, track_id: int) -> VehicleBelief | None:
        """The belief of one vehicle, None if it has none at this stamp."""
        return next((v for v in self.vehicles if v.track_id == track_id), None)

    def route_probabilities(self) -> dict[tuple[int, int], float]:
        """P(R = c) keyed by (track_id, corridor_id)."""
        return {(v.track_id, c.corridor_id): c.probability for v in self.vehicles for c in v.corridors}
