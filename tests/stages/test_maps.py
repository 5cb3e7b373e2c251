"""Tests of stages.lib.maps on the real TAF-BW maps and tracks (data beside the repository)."""

from __future__ import annotations

import csv
import math
import xml.etree.ElementTree as ElementTree
from pathlib import Path

import numpy as np
import pytest

from stages.lib.datasets import full_data_dir

from stages.lib.maps import (
    ConflictKind,
    MapProblemKind,
    PriorityRule,
    Projection,
    RoadMap,
    Turn,
    is_car_lanelet,
    load_map,
    projection_for_location,
)

DATA = full_data_dir() or Path("no-full-data")  # $IAMP_TAF_BW: the full TAF-BW recordings
RECORDINGS = {"k729": "k729_2022-03-16", "k733": "k733_2018-05-02"}

pytestmark = pytest.mark.skipif(
    not (DATA / "maps").is_dir(), reason="full TAF-BW data not found: set IAMP_TAF_BW to its folder"
)


def _map_path(recording: str) -> Path:
    return DATA / "maps" / f"{RECORDINGS[recording]}.osm"


def _meta(recording: str) -> dict[str, str]:
    with open(DATA / "recorded_trackfiles" / RECORDINGS[recording] / "meta_data.csv", newline="") as handle:
        return next(csv.DictReader(handle))


def _origin(recording: str) -> tuple[float, float]:
    meta = _meta(recording)
    return float(meta["originLat"]), float(meta["originLon"])


def _car_positions_m(recording: str) -> np.ndarray:
    """Every Car row of every sequence, read by column name (the order differs)."""
    rows = []
    for path in sorted((DATA / "recorded_trackfiles" / RECORDINGS[recording]).glob("vehicle_tracks_*.csv")):
        with open(path, newline="") as handle:
            rows.extend(
                (float(r["x"]), float(r["y"])) for r in csv.DictReader(handle) if r["agent_type"] == "Car"
            )
    return np.array(rows)


@pytest.fixture(scope="module")
def k729() -> RoadMap:
    road_map, problems = load_map(_map_path("k729"), *_origin("k729"), Projection.LOCAL_CARTESIAN)
    assert road_map is not None and problems == []
    return road_map


@pytest.fixture(scope="module")
def positions() -> dict[str, np.ndarray]:
    return {recording: _car_positions_m(recording) for recording in RECORDINGS}


# ----- car lanelets ---------------------------------------------------------


def test_car_lanelets_exclude_walkways_crosswalks_and_bike_lanes(k729):
    subtypes = {}
    for relation in ElementTree.parse(_map_path("k729")).getroot().iter("relation"):
        tags = {t.get("k"): t.get("v") for t in relation.iter("tag")}
        if tags.get("type") == "lanelet":
            subtypes[int(relation.get("id"))] = tags.get("subtype", "")
    not_for_cars = {i for i, s in subtypes.items() if s in ("walkway", "crosswalk", "bikelane")}
    unsubtyped = {i for i, s in subtypes.items() if s == ""}
    assert len(not_for_cars) == 37 and len(unsubtyped) == 32
    assert set(k729.lanelet_ids) == unsubtyped
    assert not_for_cars.isdisjoint(k729.lanelet_ids)
    assert not k729.build_problems


def test_car_lanelet_rule_on_tags():
    assert is_car_lanelet({"type": "lanelet"})
    assert is_car_lanelet({"type": "lanelet", "subtype": "road"})
    assert is_car_lanelet({"type": "lanelet", "highway": "primary", "oneway": "yes"})
    assert not is_car_lanelet({"type": "lanelet", "subtype": "walkway"})
    assert not is_car_lanelet({"type": "lanelet", "subtype": "bicycle_lane"})
    assert not is_car_lanelet({"type": "lanelet", "subtype": "road", "participant:vehicle": "no"})
    assert is_car_lanelet({"type": "lanelet", "subtype": "bus_lane", "participant:vehicle": "yes"})


def test_lanelet_geometry_and_speed_limits(k729):
    lanelet = k729.lanelet(-335529)
    assert 3.0 < lanelet.width_m < 3.6
    assert lanelet.length_m == pytest.approx(53.8, abs=0.5)
    assert lanelet.speed_limit_mps == pytest.approx(50.0 / 3.6)
    assert np.all(np.diff(lanelet.centreline.s_m) < 0.55)
    assert k729.lanelet(-335556).turn is Turn.LEFT
    assert k729.lanelet(-335531).turn is Turn.RIGHT
    k733, _ = load_map(_map_path("k733"), *_origin("k733"), Projection.SCALED_MERCATOR)
    tagged = {round(k733.lanelet(i).speed_limit_mps * 3.6) for i in k733.lanelet_ids}
    assert tagged == {50, 60}  # OSM maxspeed tags in k733


# ----- alignment of map and tracks -------------------------------------------


@pytest.mark.parametrize(
    ("recording", "projection", "threshold"),
    [
        ("k729", Projection.UTM, 0.98),  # measured 0.9944
        ("k729", Projection.LOCAL_CARTESIAN, 0.975),  # measured 0.9882
        ("k733", Projection.SCALED_MERCATOR, 0.82),  # measured 0.8360
        ("k733", Projection.LOCAL_CARTESIAN, 0.815),  # measured 0.8333
    ],
)
def test_car_positions_fall_inside_car_lanelets(positions, recording, projection, threshold):
    road_map, problems = load_map(_map_path(recording), *_origin(recording), projection)
    assert problems == []
    assert road_map.share_inside(positions[recording]) >= threshold


def test_k733_misses_lie_in_the_unmapped_lane(positions):
    """Most k733 misses fall in the 3 m gap between lanelets -103632 and -103634 (a lane missing from the map)."""
    road_map, _ = load_map(_map_path("k733"), *_origin("k733"), projection_for_location(_meta("k733")["locationId"]))
    points = positions["k733"]
    inside = road_map.inside_matrix(points).any(axis=1)
    strip = np.concatenate(
        [road_map.lanelet(-103632).right_bound_m, road_map.lanelet(-103634).left_bound_m[::-1]]
    )
    x0, y0 = strip[:, 0], strip[:, 1]
    x1, y1 = np.roll(x0, -1), np.roll(y0, -1)
    px, py = points[:, :1], points[:, 1:]
    with np.errstate(divide="ignore", invalid="ignore"):
        crossing = ((y0 > py) != (y1 > py)) & (px < x0 + (x1 - x0) * (py - y0) / (y1 - y0))
    in_strip = crossing.sum(axis=1) % 2 == 1
    assert (in_strip & ~inside).sum() >= 0.85 * (~inside).sum()
    assert (inside | in_strip).mean() >= 0.975  # measured 0.9865


def test_auto_projection_picks_the_best_aligned(positions):
    probes = positions["k729"][::5]
    road_map, problems = load_map(_map_path("k729"), *_origin("k729"), "auto", probe_positions_m=probes)
    assert problems == []
    shares = dict(road_map.projection_shares)
    assert set(shares) == {Projection.LOCAL_CARTESIAN, Projection.SCALED_MERCATOR, Projection.UTM}
    assert road_map.projection is max(shares, key=shares.get)
    assert projection_for_location("K729") is Projection.UTM


# ----- Frenet projection --------------------------------------------------------


@pytest.mark.parametrize("lanelet_id", [-335529, -335556, -335553])  # straight, left turn, tight right turn
def test_frenet_round_trip(k729, lanelet_id):
    centreline = k729.lanelet(lanelet_id).centreline
    rng = np.random.default_rng(7)
    s_m = rng.uniform(0.5, centreline.length_m - 0.5, 300)
    d_m = rng.uniform(-1.5, 1.5, 300)
    back = centreline.project(centreline.to_xy(s_m, d_m))
    # the normals of the smooth heading and of the polyline's segments differ slightly on curves
    np.testing.assert_allclose(back.s_m, s_m, atol=0.1)
    np.testing.assert_allclose(back.d_m, d_m, atol=0.01)
    hinted = centreline.project(centreline.to_xy(s_m, d_m), s_hint_m=s_m, window_m=2.0)
    np.testing.assert_allclose(hinted.s_m, s_m, atol=0.1)


def test_frenet_sign_and_extension(k729):
    centreline = k729.lanelet(-335529).centreline  # heading east
    start = centreline.points_m[0]
    heading = centreline.heading_rad[0]
    left = start + 2.0 * np.array([-math.sin(heading), math.cos(heading)])
    behind = start - 3.0 * np.array([math.cos(heading), math.sin(heading)])
    result = centreline.project(np.array([left, behind]))
    assert result.d_m[0] == pytest.approx(2.0, abs=1e-6)
    assert result.s_m[1] == pytest.approx(-3.0, abs=1e-6)


def test_points_in_lanelets(k729):
    middle = k729.lanelet(-335529).centreline.to_xy(20.0)
    found = k729.lanelets_containing(np.vstack([middle, [[500.0, 500.0]]]))
    assert -335529 in found[0]
    assert found[1] == ()


# ----- conflicts, intersections, priority --------------------------------------


def _dense(points: np.ndarray, step_m: float = 0.02) -> np.ndarray:
    s = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(points, axis=0).T))])
    t = np.arange(0.0, s[-1], step_m)
    return np.column_stack([np.interp(t, s, points[:, 0]), np.interp(t, s, points[:, 1])])


def test_crossing_of_straight_and_oncoming_left_turn(k729):
    import lanelet2
    from lanelet2.projection import LocalCartesianProjector

    straight_id, left_id = -335559, -335554  # north approach straight on, south-east approach turning left
    conflict = k729.conflict(straight_id, left_id)
    assert conflict is not None and conflict.kind is ConflictKind.CROSSING
    assert len(conflict.points) == 1
    raw = lanelet2.io.load(str(_map_path("k729")), LocalCartesianProjector(lanelet2.io.Origin(*_origin("k729"))))
    lines = [np.array([(p.x, p.y) for p in raw.laneletLayer[i].centerline]) for i in (straight_id, left_id)]
    a, b = _dense(lines[0]), _dense(lines[1])
    gaps = np.hypot(a[:, None, 0] - b[None, :, 0], a[:, None, 1] - b[None, :, 1])
    i, j = np.unravel_index(gaps.argmin(), gaps.shape)
    assert gaps[i, j] < 0.05  # the raw centrelines really cross
    crossing_xy = 0.5 * (a[i] + b[j])
    point = conflict.first
    assert math.hypot(point.x_m - crossing_xy[0], point.y_m - crossing_xy[1]) < 0.3
    assert point.s_a_m == pytest.approx(0.02 * i, abs=0.3)
    assert point.s_b_m == pytest.approx(0.02 * j, abs=0.3)
    assert abs(point.angle_rad) > math.radians(100)
    reverse = k729.conflict(left_id, straight_id)
    assert reverse.first.s_a_m == point.s_b_m and reverse.first.angle_rad == -point.angle_rad


def test_merge_is_placed_at_merge_start_and_divergence_is_no_conflict(k729):
    merge = k729.conflict(-335536, -335531)  # straight on and right turn into the southbound exit -335532
    assert merge.kind is ConflictKind.MERGE
    assert 0.0 < merge.first.s_a_m < k729.lanelet(-335536).length_m - 1.0
    assert k729.conflict(-335533, -335531) is None  # both leave -335529
    assert k729.relation(-335533, -335531).kind is ConflictKind.DIVERGE


def test_one_intersection_at_k729(k729):
    (intersection,) = k729.intersections()
    assert {-335559, -335554, -335556, -335540, -335533, -335531} <= set(intersection.lanelet_ids)
    assert all(m.entry_s_m <= m.exit_s_m for m in intersection.members)
    assert k729.intersection_of(-335529) is None
    assert k729.intersection_of(-335559) is intersection


def test_priority_falls_back_to_geometry_without_regulatory_elements(k729):
    assert k729.priority_with_rule(-335559, -335554) == (1, PriorityRule.ONCOMING_TURN)
    assert k729.priority_with_rule(-335559, -335556) == (-1, PriorityRule.RIGHT_BEFORE_LEFT)
    for conflict in k729.conflicts():
        a, b = conflict.lanelet_a_id, conflict.lanelet_b_id
        value, rule = k729.priority_with_rule(a, b)
        assert rule is not PriorityRule.REGULATORY
        assert k729.priority(b, a) == -value


def test_priority_uses_a_right_of_way_element():
    import lanelet2
    from lanelet2.core import AttributeMap, RightOfWay, getId
    from lanelet2.projection import LocalCartesianProjector

    raw = lanelet2.io.load(str(_map_path("k729")), LocalCartesianProjector(lanelet2.io.Origin(*_origin("k729"))))
    straight, left = raw.laneletLayer[-335559], raw.laneletLayer[-335554]
    tags = AttributeMap({"type": "regulatory_element", "subtype": "right_of_way"})
    element = RightOfWay(getId(), tags, [left], [straight])
    straight.addRegulatoryElement(element)
    left.addRegulatoryElement(element)
    road_map = RoadMap(raw, projection=Projection.LOCAL_CARTESIAN)
    assert road_map.priority_with_rule(-335559, -335554) == (-1, PriorityRule.REGULATORY)
    assert road_map.priority_with_rule(-335554, -335559) == (1, PriorityRule.REGULATORY)


# ----- routing ------------------------------------------------------------------


def test_lanelets_entering_the_intersection_have_successors(k729):
    (intersection,) = k729.intersections()
    members = set(intersection.lanelet_ids)
    approaches = {p for m in members for p in k729.predecessors(m)} - members
    assert len(approaches) >= 6
    for lanelet_id in approaches:
        assert k729.successors(lanelet_id)
        assert set(k729.successors(lanelet_id)) & members
    assert k729.neighbours(-335529).left_id == -335530


def test_possible_paths_contain_straight_and_turning_routes(k729):
    approach = -335529  # west approach: straight on or right
    paths = k729.possible_paths(approach, 50.0, start_s_m=k729.lanelet(approach).length_m)
    assert len(paths) >= 2
    turns = []
    for path in paths:
        assert path[0] == approach
        assert sum(k729.lanelet(i).length_m for i in path[1:]) >= 50.0
        line = k729.path_centreline(path)
        turns.append(math.degrees(abs(math.remainder(line.heading_rad[-1] - line.heading_rad[0], math.tau))))
    assert min(turns) < 30.0 and max(turns) > 45.0
    assert k729.possible_paths(approach, 10.0) == [(approach,)]


# ----- robustness ---------------------------------------------------------------


def test_missing_and_garbage_files_give_problems(tmp_path):
    road_map, problems = load_map(tmp_path / "missing.osm", 49.0, 8.4)
    assert road_map is None and [p.kind for p in problems] == [MapProblemKind.FILE_NOT_FOUND]

    garbage = tmp_path / "garbage.osm"
    garbage.write_text("this is not an OSM file")
    road_map, problems = load_map(garbage, 49.0, 8.4)
    assert problems and problems[0].kind in (MapProblemKind.UNREADABLE, MapProblemKind.PARSE_ERROR)

    broken = tmp_path / "broken.osm"
    broken.write_text(
        "<?xml version='1.0'?><osm><node id='1' lat='49.0' lon='8.4'/><way id='2'><nd ref='99'/></way>"
        "<relation id='3'><member type='way' ref='2' role='left'/><tag k='type' v='lanelet'/></relation></osm>"
    )
    road_map, problems = load_map(broken, 49.0, 8.4)
    assert road_map is not None and road_map.lanelet_ids == ()
    kinds = {p.kind for p in problems}
    assert MapProblemKind.PARSE_ERROR in kinds and MapProblemKind.NO_CAR_LANELETS in kinds

    wrong_extension = tmp_path / "map.txt"
    wrong_extension.write_text("x")
    assert load_map(wrong_extension, 49.0, 8.4)[1][0].kind is MapProblemKind.UNREADABLE


def test_bad_arguments_give_problems():
    path = _map_path("k729")
    assert load_map(path, float("nan"), 8.4)[1][0].kind is MapProblemKind.BAD_ARGUMENT
    assert load_map(path, 49.0, 8.4, "mercury")[1][0].kind is MapProblemKind.BAD_ARGUMENT
    assert load_map(path, 49.0, 8.4, Projection.AUTO)[1][0].kind is MapProblemKind.BAD_ARGUMENT


def test_speed_limit_from_a_regulatory_element():
    import lanelet2
    from lanelet2.core import AttributeMap, LineString3d, Point3d, SpeedLimit, TrafficSignsWithType, getId
    from lanelet2.projection import LocalCartesianProjector

    raw = lanelet2.io.load(str(_map_path("k729")), LocalCartesianProjector(lanelet2.io.Origin(*_origin("k729"))))
    sign = LineString3d(
        getId(), [Point3d(getId(), 0, 0, 0), Point3d(getId(), 1, 0, 0)], AttributeMap({"type": "traffic_sign", "subtype": "de274-30"})
    )
    tags = AttributeMap({"type": "regulatory_element", "subtype": "speed_limit"})
    raw.laneletLayer[-335529].addRegulatoryElement(SpeedLimit(getId(), tags, TrafficSignsWithType([sign])))
    road_map = RoadMap(raw, default_speed_limit_mps=15.0)
    assert road_map.lanelet(-335529).speed_limit_mps == pytest.approx(30.0 / 3.6)
    assert road_map.lanelet(-335530).speed_limit_mps == 15.0
