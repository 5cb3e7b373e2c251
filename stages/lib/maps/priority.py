"""Right of way between two car lanelets (`RoadMap.priority`) and the turn of a lanelet.

`RightOfWay` reads the regulatory elements of the car lanelets once and
decides, for a pair, who goes first and by which `PriorityRule`; `RoadMap`
holds one and answers `priority` and `priority_with_rule` through it.

Right of way (`RoadMap.priority`), in this order
    1. Regulatory elements on the lanelet or its direct predecessors (approach
       lanelets): RightOfWay (right_of_way lanelets over yield lanelets), a
       TrafficSign stop or give-way sign (de205, de206, or a type naming stop or
       yield) against a lanelet without one, AllWayStop (equal).
    2. Geometry, from the approach heading (at s = 0) and the turn of each
       lanelet (heading change above 30 degrees):
       - oncoming lanelets (more than 135 degrees apart): a left turn yields to
         a lanelet that does not turn left, otherwise equal;
       - crossing lanelets (45 to 135 degrees): the major road first when both
         carry OSM tags that differ (priority_road=designated, then the highway
         class motorway > trunk > primary > secondary > tertiary > the rest),
         else right before left;
       - the same approach direction: the lanelet that turns less, by more than
         15 degrees, goes first; otherwise equal (0).
    Road tags are only compared between crossing roads because k733's tags come
    from OSM ways and differ between the two halves of one road. The TAF-BW
    maps have no regulatory elements, and both intersections are signalised,
    so this rule describes who yields under the same green phase.
"""

from __future__ import annotations

import enum
import math

from lanelet2 import core as ll_core

from stages.lib.maps.geometry import wrap_angle_rad

TURN_THRESHOLD_RAD = math.radians(30.0)
_HIGHWAY_RANK = {"motorway": 6, "trunk": 5, "primary": 4, "secondary": 3, "tertiary": 2}
_STOP_OR_YIELD_SIGNS = ("de205", "de206", "stop", "yield", "give_way")


class Turn(enum.Enum):
    UNKNOWN = 0
    STRAIGHT = 1
    LEFT = 2
    RIGHT = 3


class PriorityRule(enum.Enum):
    """Which rule decided `RoadMap.priority_with_rule`."""

    UNKNOWN = 0
    REGULATORY = 1
    ROAD_CLASS = 2
    ONCOMING_TURN = 3
    RIGHT_BEFORE_LEFT = 4
    LESS_TURNING = 5
    EQUAL = 6


def turn_of(turn_angle_rad: float) -> Turn:
    """LEFT, RIGHT or STRAIGHT for a heading change from a lanelet's start to its end, at 30 degrees."""
    if turn_angle_rad > TURN_THRESHOLD_RAD:
        return Turn.LEFT
    if turn_angle_rad < -TURN_THRESHOLD_RAD:
        return Turn.RIGHT
    return Turn.STRAIGHT


class RightOfWay:
    """The right-of-way rule of the module docstring over the car lanelets of one map.

    `lanelets` maps a car lanelet id to its lanelet2 lanelet, `predecessors` to
    its predecessor ids, `infos` to its `LaneletInfo` (heading and turn).
    """

    def __init__(self, lanelets, predecessors, infos) -> None:
        self._lanelets = lanelets
        self._predecessors = predecessors
        self._infos = infos
        self.lanelet_ids = tuple(infos)
        self._right_of_way: dict[int, set[int]] = {x: set() for x in self.lanelet_ids}
        self._yields_in: dict[int, set[int]] = {x: set() for x in self.lanelet_ids}
        self._all_way_stops: dict[int, set[int]] = {x: set() for x in self.lanelet_ids}
        self._has_stop_sign: dict[int, bool] = {x: False for x in self.lanelet_ids}
        self._has_regulation: dict[int, bool] = {x: False for x in self.lanelet_ids}
        for lanelet_id, lanelet in self._lanelets.items():
            for element in lanelet.regulatoryElements:
                if isinstance(element, ll_core.RightOfWay):
                    self._has_regulation[lanelet_id] = True
                    if any(x.id == lanelet_id for x in element.rightOfWayLanelets()):
                        self._right_of_way[lanelet_id].add(element.id)
                    if any(x.id == lanelet_id for x in element.yieldLanelets()):
                        self._yields_in[lanelet_id].add(element.id)
                elif isinstance(element, ll_core.AllWayStop):
                    self._has_regulation[lanelet_id] = True
                    self._all_way_stops[lanelet_id].add(element.id)
                elif isinstance(element, ll_core.TrafficSign):
                    sign_type = str(element.type()).lower()
                    if any(key in sign_type for key in _STOP_OR_YIELD_SIGNS):
                        self._has_regulation[lanelet_id] = True
                        self._has_stop_sign[lanelet_id] = True

    def priority_with_rule(self, lanelet_a_id: int, lanelet_b_id: int) -> tuple[int, PriorityRule]:
        """`priority` and the rule (module docstring) that decided it."""
        a, b = lanelet_a_id, lanelet_b_id
        if a == b:
            return 0, PriorityRule.EQUAL
        regulatory = self._regulatory_priority(a, b)
        if regulatory is not None:
            return regulatory, PriorityRule.REGULATORY
        info_a, info_b = self._infos[a], self._infos[b]
        approach = float(wrap_angle_rad(info_b.centreline.heading_rad[0] - info_a.centreline.heading_rad[0]))
        if abs(approach) >= math.radians(135.0):
            left_a, left_b = info_a.turn is Turn.LEFT, info_b.turn is Turn.LEFT
            if left_a != left_b:
                return (-1 if left_a else 1), PriorityRule.ONCOMING_TURN
            return 0, PriorityRule.EQUAL
        if abs(approach) > math.radians(45.0):
            rank_a, rank_b = self._road_rank(a), self._road_rank(b)
            if rank_a is not None and rank_b is not None and rank_a != rank_b:
                return (1 if rank_a > rank_b else -1), PriorityRule.ROAD_CLASS
            return (-1 if approach > 0.0 else 1), PriorityRule.RIGHT_BEFORE_LEFT
        turn_a, turn_b = abs(info_a.turn_angle_rad), abs(info_b.turn_angle_rad)
        if abs(turn_a - turn_b) > math.radians(15.0):
            return (1 if turn_a < turn_b else -1), PriorityRule.LESS_TURNING
        return 0, PriorityRule.EQUAL

    def _with_approaches(self, lanelet_id: int) -> tuple[int, ...]:
        return (lanelet_id,) + self._predecessors[lanelet_id]

    def _regulatory_priority(self, a: int, b: int) -> int | None:
        group_a, group_b = self._with_approaches(a), self._with_approaches(b)
        if not any(self._has_regulation[x] for x in group_a + group_b):
            return None
        row_a = set().union(*(self._right_of_way[x] for x in group_a))
        row_b = set().union(*(self._right_of_way[x] for x in group_b))
        yield_a = set().union(*(self._yields_in[x] for x in group_a))
        yield_b = set().union(*(self._yields_in[x] for x in group_b))
        if row_a & yield_b:
            return 1
        if row_b & yield_a:
            return -1
        stops_a = set().union(*(self._all_way_stops[x] for x in group_a))
        stops_b = set().union(*(self._all_way_stops[x] for x in group_b))
        if stops_a & stops_b:
            return 0
        sign_a = any(self._has_stop_sign[x] for x in group_a)
        sign_b = any(self._has_stop_sign[x] for x in group_b)
        if sign_a != sign_b:
            return -1 if sign_a else 1
        return None

    def _road_rank(self, lanelet_id: int) -> tuple[int, int] | None:
        tags = {str(k): str(v) for k, v in dict(self._lanelets[lanelet_id].attributes).items()}
        if "highway" not in tags and "priority_road" not in tags:
            return None
        highway = tags.get("highway", "").removesuffix("_link")
        designated = tags.get("priority_road", "").lower() in ("designated", "yes")
        return (int(designated), _HIGHWAY_RANK.get(highway, 1))

