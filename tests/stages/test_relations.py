"""Tests of the relations stage on the real K729 map and tracks (embedded sequence 013).

Real frames come from the dataset player and the corridors core run in-process
over the whole sequence (continuity state as on the bus). Scenes the
recording lacks (crossing traffic, pedestrians on a crosswalk, controlled
speeds) are built by placing objects on the real lanelets' centrelines and
running the corridors core on that one frame.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from bus_schemas import AgentType, ConflictKind, CorridorSet, Header, TrackFrame
from stages.corridors import CorridorBuilder, CorridorsConfig, SceneMaps
from stages.lib.datasets import DEFAULT_DATA_DIR
from stages.lib.maps import Projection, segment_intersections
from stages.relations import RelationExtractor, RelationsConfig, choose_influencing, most_influencing, rank_conflicts
from stages.tracks_source.core import TrackPlayer, TracksSourceConfig

pytestmark = pytest.mark.skipif(
    not (DEFAULT_DATA_DIR / "maps").is_dir(), reason=f"embedded TAF-BW data not found at {DEFAULT_DATA_DIR}"
)

# lanelets of the K729 map (stages.lib.maps computes their relations)
NORTH_LEFT_TURN = -335558  # from the north approach, turns left; yields to the oncoming straight lanes
ONCOMING_STRAIGHT_RIGHT_LANE = -335552  # from the south, straight, right lane
ONCOMING_STRAIGHT_LEFT_LANE = -335550  # from the south, straight, left lane
EAST_LEFT_TURN = -335540  # from the east, turns left; the north left turn has right of way over it


@pytest.fixture(scope="module")
def scene_maps() -> SceneMaps:
    return SceneMaps()


@pytest.fixture(scope="module")
def sequence(scene_maps):
    """Sequence 013: (track_frame, corridor_set) per frame, the scene, and one relation set per frame."""
    player = TrackPlayer.open(TracksSourceConfig(), run_id="test", producer="tracks")
    builder = CorridorBuilder(CorridorsConfig(), producer="corridors", scene_maps=scene_maps)
    extractor = RelationExtractor(RelationsConfig(), scene_maps=scene_maps)
    scene, frames, relation_sets = None, [], []
    for _stamp, result in player:
        scene = result.outputs.get("scene", scene)
        frame = result.outputs["track_frame"]
        corridor_set = builder.update({"track_frame": frame, "scene": scene}).outputs["corridor_set"]
        relations = extractor.update({"track_frame": frame, "corridor_set": corridor_set, "scene": scene})
        assert relations.issues == []
        frames.append((frame, corridor_set))
        relation_sets.append(relations.outputs["relation_set"])
    return {"scene": scene, "frames": frames, "relations": relation_sets, "road_map": builder.scene_map.road_map}


def _vehicle(corridor_set: CorridorSet, track_id: int):
    return next(v for v in corridor_set.vehicles if v.track_id == track_id)


def _row(frame: TrackFrame, track_id: int) -> int:
    return int(np.flatnonzero(frame.track_ids == track_id)[0])


def _relations_of(relation_set, track_id: int, lanelet_id: int | None = None, corridor_set: CorridorSet | None = None):
    """The relations of a track, only those whose corridor passes `lanelet_id` when given."""
    found = [r for r in relation_set.relations if r.track_id == track_id]
    if lanelet_id is not None:
        corridors = {c.corridor_id: c for c in _vehicle(corridor_set, track_id).corridors}
        found = [r for r in found if lanelet_id in corridors[r.corridor_id].lanelet_ids]
    return found


def _path_s_m(road_map, lanelet_ids, xy) -> float:
    """Arc length of a point on the lanelet path's own centreline (independent of the corridor)."""
    return float(road_map.path_centreline(lanelet_ids).project(np.asarray(xy, dtype=np.float64).reshape(1, 2)).s_m[0])


# --------------------------------------------------------------------------- built scenes


@dataclasses.dataclass
class Placed:
    track_id: int
    agent_type: AgentType
    xy: tuple[float, float]
    heading_rad: float
    speed_mps: float
    length_m: float = 4.6
    width_m: float = 2.0


def on_lanelet(road_map, track_id: int, lanelet_id: int, s_m: float, speed_mps: float) -> Placed:
    line = road_map.lanelet(lanelet_id).centreline
    x, y = line.to_xy(s_m)[0]
    return Placed(track_id, AgentType.CAR, (float(x), float(y)), float(np.atleast_1d(line.heading_at(s_m))[0]), speed_mps)


def build_frame(objects: list[Placed], scene, stamp_ns: int = 1_000_000_000) -> TrackFrame:
    return TrackFrame(
        header=Header(run_id="test", frame_index=0, stamp_ns=stamp_ns, producer="test"),
        scene_id=scene.scene_id,
        track_ids=np.array([o.track_id for o in objects], dtype=np.int64),
        agent_types=np.array([int(o.agent_type) for o in objects], dtype=np.uint8),
        x_m=np.array([o.xy[0] for o in objects]),
        y_m=np.array([o.xy[1] for o in objects]),
        vx_mps=np.array([o.speed_mps * math.cos(o.heading_rad) for o in objects]),
        vy_mps=np.array([o.speed_mps * math.sin(o.heading_rad) for o in objects]),
        yaw_rad=np.array([o.heading_rad for o in objects]),
        length_m=np.array([o.length_m for o in objects]),
        width_m=np.array([o.width_m for o in objects]),
    )


def relate(objects: list[Placed], scene, scene_maps, config: RelationsConfig | None = None):
    """Corridors then relations of one built frame: (frame, corridor_set, relation_set, issues)."""
    frame = build_frame(objects, scene)
    builder = CorridorBuilder(CorridorsConfig(), producer="corridors", scene_maps=scene_maps)
    corridor_set = builder.update({"track_frame": frame, "scene": scene}).outputs["corridor_set"]
    extractor = RelationExtractor(config or RelationsConfig(), scene_maps=scene_maps)
    result = extractor.update({"track_frame": frame, "corridor_set": corridor_set, "scene": scene})
    return frame, corridor_set, result.outputs.get("relation_set"), result.issues


@pytest.fixture(scope="module")
def crossing_scene(sequence, scene_maps):
    """A left turner from the north (ego, 5 m/s) and three cars crossing its path.

    B (oncoming, right lane, 1.5 m/s) and C (oncoming, left lane, 5 m/s) have
    right of way over the ego; D (left turner from the east, 4.6 m/s) yields
    to it and arrives at its conflict point at almost the ego's time.
    """
    road_map = sequence["road_map"]
    objects = [
        on_lanelet(road_map, 1, NORTH_LEFT_TURN, 8.0, 5.0),
        on_lanelet(road_map, 2, ONCOMING_STRAIGHT_RIGHT_LANE, 10.0, 1.5),
        on_lanelet(road_map, 3, ONCOMING_STRAIGHT_LEFT_LANE, 10.0, 5.0),
        on_lanelet(road_map, 4, EAST_LEFT_TURN, 5.0, 4.6),
    ]
    frame, corridor_set, relation_set, issues = relate(objects, sequence["scene"], scene_maps)
    assert issues == []
    return frame, corridor_set, relation_set


# --------------------------------------------------------------------------- lateral relation


def test_queued_car_has_the_car_in_front_as_leader_with_the_bumper_gap(sequence):
    # frames 321-710 of sequence 013: car 2686 waits behind car 2682 on the south approach
    k = 500
    frame, corridor_set = sequence["frames"][k]
    road_map = sequence["road_map"]
    follower, leader = 2686, 2682
    assert _vehicle(corridor_set, follower).speed_mps < 0.5 and _vehicle(corridor_set, leader).speed_mps < 0.5
    relations = _relations_of(sequence["relations"][k], follower)
    assert relations
    lengths = frame.length_m[_row(frame, follower)] + frame.length_m[_row(frame, leader)]
    for rel in relations:
        corridor = next(c for c in _vehicle(corridor_set, follower).corridors if c.corridor_id == rel.corridor_id)
        assert rel.leader_track_id == leader
        ids = [int(x) for x in corridor.lanelet_ids]
        s_follower = _path_s_m(road_map, ids, (frame.x_m[_row(frame, follower)], frame.y_m[_row(frame, follower)]))
        s_leader = _path_s_m(road_map, ids, (frame.x_m[_row(frame, leader)], frame.y_m[_row(frame, leader)]))
        expected_gap = s_leader - s_follower - 0.5 * lengths
        assert 1.0 < expected_gap < 5.0
        assert rel.leader_gap_m == pytest.approx(expected_gap, abs=0.5)
        assert abs(rel.leader_speed_mps) < 0.5
        k_leader = int(np.flatnonzero(rel.object_track_ids == leader)[0])
        assert rel.object_gap_m[k_leader] == rel.leader_gap_m
        assert abs(rel.object_d_m[k_leader]) < 1.0
    # and the follower is behind the leader, with the same gap negated
    for rel in _relations_of(sequence["relations"][k], leader):
        k_follower = np.flatnonzero(rel.object_track_ids == follower)
        assert len(k_follower) == 1
        assert rel.object_gap_m[k_follower[0]] == pytest.approx(-relations[0].leader_gap_m, abs=0.5)


def test_leader_is_the_nearest_object_ahead_in_every_relation_of_the_sequence(sequence):
    for (frame, _corridor_set), relation_set in zip(sequence["frames"][::10], sequence["relations"][::10]):
        for rel in relation_set.relations:
            assert np.all(np.diff(rel.object_s_m) >= 0.0)
            if rel.leader_track_id < 0:
                assert math.isnan(rel.leader_gap_m)
                continue
            k = int(np.flatnonzero(rel.object_track_ids == rel.leader_track_id)[0])
            ahead = rel.object_gap_m[rel.object_s_m > rel.object_s_m[k]]
            assert rel.leader_gap_m >= 0.0 and np.all(ahead >= rel.leader_gap_m)


def _crosswalks_m(scene):
    """Crosswalk centrelines and polygons of the scene's map, in the recording's frame (UTM, like the map)."""
    from lanelet2 import core as ll_core
    from lanelet2 import io as ll_io
    from lanelet2 import projection as ll_projection

    projector = ll_projection.UtmProjector(ll_io.Origin(scene.origin_lat_deg, scene.origin_lon_deg))
    lanelet_map, _errors = ll_io.loadRobust(str(DEFAULT_DATA_DIR / "maps" / scene.map_name), projector)
    origin = projector.forward(ll_core.GPSPoint(scene.origin_lat_deg, scene.origin_lon_deg, 0.0))
    found = []
    for lanelet in lanelet_map.laneletLayer:
        if "subtype" in lanelet.attributes and lanelet.attributes["subtype"] == "crosswalk":
            centre = np.array([(p.x - origin.x, p.y - origin.y) for p in lanelet.centerline])
            polygon = np.array(
                [(p.x - origin.x, p.y - origin.y) for p in list(lanelet.leftBound) + list(lanelet.rightBound)[::-1]]
            )
            found.append((centre, polygon))
    return found


def _inside(polygon: np.ndarray, xy) -> bool:
    x, y = xy
    a, b = polygon, np.roll(polygon, -1, axis=0)
    straddle = (a[:, 1] > y) != (b[:, 1] > y)
    with np.errstate(divide="ignore", invalid="ignore"):
        cross_x = a[:, 0] + (y - a[:, 1]) * (b[:, 0] - a[:, 0]) / (b[:, 1] - a[:, 1])
    return bool(np.count_nonzero(straddle & (x < cross_x)) % 2)


def test_pedestrian_on_the_crosswalk_is_a_lateral_object_only_within_the_lane_margin(sequence, scene_maps):
    scene, road_map = sequence["scene"], sequence["road_map"]
    assert scene_maps.get(scene).projection is Projection.UTM
    car = on_lanelet(road_map, 1, ONCOMING_STRAIGHT_RIGHT_LANE, 2.0, 2.0)
    _frame, corridor_set, _rel, _issues = relate([car], scene, scene_maps)
    corridor = next(c for c in _vehicle(corridor_set, 1).corridors if ONCOMING_STRAIGHT_RIGHT_LANE in c.lanelet_ids)
    line = np.column_stack([corridor.x_m, corridor.y_m])
    crossings = []
    for centre, polygon in _crosswalks_m(scene):
        i, _j, t, _u = segment_intersections(line, centre)
        for seg, frac in zip(i, t):
            s = corridor.s_m[seg] + frac * (corridor.s_m[seg + 1] - corridor.s_m[seg])
            if s > corridor.vehicle_s_m + 3.0:
                crossings.append((float(s), polygon))
    assert crossings, "no crosswalk ahead of the car on its corridor"
    s_cross, polygon = min(crossings, key=lambda c: c[0])
    k = int(np.searchsorted(corridor.s_m, s_cross))
    heading = float(np.interp(s_cross, corridor.s_m, np.unwrap(corridor.heading_rad)))
    centre = np.array([np.interp(s_cross, corridor.s_m, corridor.x_m), np.interp(s_cross, corridor.s_m, corridor.y_m)])
    normal = np.array([-math.sin(heading), math.cos(heading)])
    limit = 0.5 * corridor.width_m[k] + RelationsConfig().lateral_margin_m
    walking = heading + 0.5 * math.pi
    offsets = {101: 0.0, 102: limit - 0.3, 103: -(limit + 0.5), 104: limit + 2.0}
    pedestrians = [
        Placed(pid, AgentType.PEDESTRIAN, tuple(centre + d * normal), walking, 1.3, 0.6, 0.6) for pid, d in offsets.items()
    ]
    assert _inside(polygon, pedestrians[0].xy)
    _frame, corridor_set, relation_set, issues = relate([car, *pedestrians], scene, scene_maps)
    assert issues == []
    rel = next(r for r in _relations_of(relation_set, 1, ONCOMING_STRAIGHT_RIGHT_LANE, corridor_set))
    listed = set(int(x) for x in rel.object_track_ids)
    assert listed == {101, 102}
    k101 = int(np.flatnonzero(rel.object_track_ids == 101)[0])
    assert rel.object_types[k101] == AgentType.PEDESTRIAN
    assert abs(rel.object_d_m[k101]) < 0.1
    assert rel.object_s_m[k101] == pytest.approx(s_cross, abs=0.3)
    assert abs(rel.object_speed_mps[k101]) < 0.1  # walking across the lane
    assert rel.leader_track_id == -1  # crossing pedestrians are listed, they do not lead


# --------------------------------------------------------------------------- corridor to intersection


def test_distance_to_the_intersection_entry_decreases_while_a_car_approaches(sequence):
    # car 2713 drives north on the south approach's left lane into the intersection (frames ~761-791)
    track_id, entry_lanelet = 2713, ONCOMING_STRAIGHT_LEFT_LANE
    road_map = sequence["road_map"]
    intersection = road_map.intersection_of(entry_lanelet)
    distances, advances = [], []
    previous_xy = None
    for k in range(765, 786):
        frame, corridor_set = sequence["frames"][k]
        rels = _relations_of(sequence["relations"][k], track_id, entry_lanelet, corridor_set)
        assert rels, f"frame {k}: no corridor of {track_id} through {entry_lanelet}"
        rel = rels[0]
        q = int(np.flatnonzero(rel.intersection_entry_lanelet_ids == entry_lanelet)[0])
        assert rel.intersection_ids[q] == intersection.intersection_id
        distances.append(float(rel.intersection_distance_m[q]))
        xy = np.array([frame.x_m[_row(frame, track_id)], frame.y_m[_row(frame, track_id)]])
        if previous_xy is not None:
            advances.append(float(np.hypot(*(xy - previous_xy))))
        previous_xy = xy
        if k == 775:  # independent check: the entry point along the lanelet path minus the car's arc length
            corridor = next(c for c in _vehicle(corridor_set, track_id).corridors if c.corridor_id == rel.corridor_id)
            ids = [int(x) for x in corridor.lanelet_ids]
            line = road_map.path_centreline(ids)
            lanelet_start = _path_s_m(road_map, ids, road_map.lanelet(entry_lanelet).centreline.to_xy(0.0)[0])
            entry = lanelet_start + intersection.member(entry_lanelet).entry_s_m
            assert distances[-1] == pytest.approx(entry - float(line.project(xy.reshape(1, 2)).s_m[0]), abs=0.5)
    distances = np.array(distances)
    assert np.all(distances > 0.0) and distances[0] > 10.0
    assert np.all(np.diff(distances) < 0.0)
    # it shrinks by the distance driven, frame to frame
    assert np.abs(-np.diff(distances) - np.array(advances)).max() < 0.3


# --------------------------------------------------------------------------- corridor to corridor


def test_crossing_corridors_give_the_conflict_point_where_the_centrelines_cross(crossing_scene):
    _frame, corridor_set, relation_set = crossing_scene
    ego = next(r for r in _relations_of(relation_set, 1, NORTH_LEFT_TURN, corridor_set))
    ego_corridor = next(c for c in _vehicle(corridor_set, 1).corridors if c.corridor_id == ego.corridor_id)
    checked = 0
    for other in (2, 3, 4):
        for k in np.flatnonzero(ego.conflict_track_ids == other):
            if ego.conflict_kinds[k] != ConflictKind.CROSSING:
                continue
            other_corridor = next(
                c for c in _vehicle(corridor_set, other).corridors if c.corridor_id == ego.conflict_corridor_ids[k]
            )
            a = np.column_stack([ego_corridor.x_m, ego_corridor.y_m])
            b = np.column_stack([other_corridor.x_m, other_corridor.y_m])
            distance = np.hypot(a[:, None, 0] - b[None, :, 0], a[:, None, 1] - b[None, :, 1])
            i, j = np.unravel_index(distance.argmin(), distance.shape)
            closest = 0.5 * (a[i] + b[j])
            point = np.array([ego.conflict_x_m[k], ego.conflict_y_m[k]])
            assert distance[i, j] < 0.5
            assert np.hypot(*(point - closest)) < 0.5
            for corridor, s in ((ego_corridor, ego.conflict_s_m[k]), (other_corridor, ego.conflict_other_s_m[k])):
                on_line = np.array([np.interp(s, corridor.s_m, corridor.x_m), np.interp(s, corridor.s_m, corridor.y_m)])
                assert np.hypot(*(on_line - point)) < 0.5
            assert ego.conflict_distance_m[k] == pytest.approx(ego.conflict_s_m[k] - ego_corridor.vehicle_s_m)
            assert ego.conflict_other_distance_m[k] == pytest.approx(
                ego.conflict_other_s_m[k] - other_corridor.vehicle_s_m
            )
            # the other corridor lists the same point, seen from its side
            mirror = next(r for r in relation_set.relations if r.track_id == other and r.corridor_id == other_corridor.corridor_id)
            m = int(np.flatnonzero((mirror.conflict_track_ids == 1) & (mirror.conflict_corridor_ids == ego.corridor_id))[0])
            assert mirror.conflict_s_m[m] == pytest.approx(ego.conflict_other_s_m[k])
            assert mirror.conflict_priority[m] == -ego.conflict_priority[k]
            checked += 1
    assert checked >= 3


def test_influencing_corridor_is_the_prioritized_one_closest_in_arrival_time(crossing_scene, sequence):
    _frame, corridor_set, relation_set = crossing_scene
    road_map = sequence["road_map"]
    ego = next(r for r in _relations_of(relation_set, 1, NORTH_LEFT_TURN, corridor_set))
    by_track = {}
    for other, lanelet in ((2, ONCOMING_STRAIGHT_RIGHT_LANE), (3, ONCOMING_STRAIGHT_LEFT_LANE), (4, EAST_LEFT_TURN)):
        point = road_map.conflict(NORTH_LEFT_TURN, lanelet).first
        k = int(np.flatnonzero((ego.conflict_track_ids == other) & (np.abs(ego.conflict_distance_m - (point.s_a_m - 8.0)) < 0.5))[0])
        by_track[other] = k
        # times by hand: T = distance / max(v, 1) from the map's conflict arc lengths
        speed_other = {2: 1.5, 3: 5.0, 4: 4.6}[other]
        assert ego.conflict_time_s[k] == pytest.approx((point.s_a_m - 8.0) / 5.0, abs=0.1)
        s_other = {2: 10.0, 3: 10.0, 4: 5.0}[other]
        assert ego.conflict_other_time_s[k] == pytest.approx((point.s_b_m - s_other) / speed_other, abs=0.1)
        assert ego.conflict_priority[k] == road_map.priority(NORTH_LEFT_TURN, lanelet)
    assert ego.conflict_priority[by_track[2]] == -1 and ego.conflict_priority[by_track[3]] == -1
    assert ego.conflict_priority[by_track[4]] == 1
    gaps = {t: abs(ego.conflict_other_time_s[k] - ego.conflict_time_s[k]) for t, k in by_track.items()}
    assert gaps[4] < gaps[2] < gaps[3]  # D is closest in time but yields to the ego
    assert int(ego.conflict_track_ids[ego.influencing_index]) == 2
    assert ego.influencing_rule == "priority_other"
    # the two most influencing vehicles for the AR features: no priority filter, one entry per vehicle
    top = most_influencing(ego, 2)
    assert [int(ego.conflict_track_ids[k]) for k in top] == [4, 2]
    # and D, which must yield to the ego's corridor, is influenced by it
    d_rels = _relations_of(relation_set, 4, EAST_LEFT_TURN, corridor_set)
    assert any(int(r.conflict_track_ids[r.influencing_index]) in (1, 2, 3) for r in d_rels if r.influencing_index >= 0)


def test_influencing_rule_ties_merges_horizon_and_route_probability():
    crossing, merge = int(ConflictKind.CROSSING), int(ConflictKind.MERGE)
    kinds = np.array([crossing, crossing, merge])
    priority = np.array([-1, -1, 0])
    distance = np.array([10.0, 10.0, 20.0])
    other_distance = np.array([12.0, 4.0, 5.0])
    t = np.array([2.0, 2.0, 4.0])
    # equal |T' - T| = 1: the smaller T' wins
    t_other = np.array([3.0, 1.0, 9.0])
    assert choose_influencing(kinds, priority, distance, other_distance, t, t_other, horizon_s=6.0) == (1, "priority_other")
    assert list(rank_conflicts(t, t_other)[:2]) == [1, 0]
    # a merge where the other is nearer the merge point influences whatever the priority
    t_other = np.array([3.0, 5.0, 4.5])
    assert choose_influencing(kinds, priority, distance, other_distance, t, t_other, horizon_s=6.0) == (2, "merge_ahead_other")
    # beyond the horizon nothing does
    assert choose_influencing(kinds, priority, distance, other_distance, t, t_other + 10.0, horizon_s=6.0) == (-1, "none")
    # an unlikely route is skipped
    chosen = choose_influencing(
        kinds, priority, distance, other_distance, t, t_other, horizon_s=6.0,
        other_probability=np.array([1.0, 1.0, 0.05]), min_probability=0.1,
    )
    assert chosen == (0, "priority_other")
    # equal priority at a crossing: the one who arrives first
    chosen = choose_influencing(
        np.array([crossing]), np.array([0]), np.array([10.0]), np.array([5.0]), np.array([3.0]), np.array([2.0]), horizon_s=6.0
    )
    assert chosen == (0, "equal_first_other")


def test_a_shared_lanelet_before_the_divergence_is_no_conflict(sequence, scene_maps):
    # two cars on the same oncoming lane: one will go straight, one turns right; they follow, never conflict
    road_map = sequence["road_map"]
    shared = road_map.predecessors(ONCOMING_STRAIGHT_RIGHT_LANE)[0]
    objects = [on_lanelet(road_map, 1, shared, 20.0, 3.0), on_lanelet(road_map, 2, shared, 35.0, 3.0)]
    _frame, corridor_set, relation_set, issues = relate(objects, sequence["scene"], scene_maps)
    assert issues == []
    for rel in relation_set.relations:
        assert len(rel.conflict_track_ids) == 0
    follower = _relations_of(relation_set, 1)
    assert follower and all(r.leader_track_id == 2 for r in follower)


# --------------------------------------------------------------------------- bad input


def _replace_frame(frame: TrackFrame, keep: np.ndarray, **columns) -> TrackFrame:
    fields = {
        name: np.asarray(getattr(frame, name))[keep].copy()
        for name in ("track_ids", "agent_types", "x_m", "y_m", "vx_mps", "vy_mps", "yaw_rad", "length_m", "width_m")
    }
    fields.update(columns)
    return TrackFrame(header=frame.header, scene_id=frame.scene_id, **fields)


def test_bad_input_becomes_issues_and_the_other_vehicles_are_still_processed(sequence, scene_maps):
    k = 500
    frame, corridor_set = sequence["frames"][k]
    scene = sequence["scene"]
    extractor = RelationExtractor(RelationsConfig(), scene_maps=scene_maps)
    with_corridors = [v.track_id for v in corridor_set.vehicles if v.corridors]
    assert 2682 in with_corridors and 2686 in with_corridors and len(with_corridors) >= 3
    # the leader 2682 is missing from the TrackFrame
    keep = frame.track_ids != 2682
    result = extractor.update({"track_frame": _replace_frame(frame, keep), "corridor_set": corridor_set, "scene": scene})
    assert [(i.kind, i.agent_id) for i in result.issues] == [("missing_track", 2682)]
    relations = result.outputs["relation_set"].relations
    assert {r.track_id for r in relations} == set(with_corridors) - {2682}
    assert all(r.leader_track_id != 2682 for r in relations)
    # a NaN position: that vehicle is skipped, not an obstacle either
    x = np.asarray(frame.x_m).copy()
    x[_row(frame, 2682)] = math.nan
    result = extractor.update(
        {"track_frame": _replace_frame(frame, np.ones(len(frame), bool), x_m=x), "corridor_set": corridor_set, "scene": scene}
    )
    assert ("nan_state", 2682) in [(i.kind, i.agent_id) for i in result.issues]
    assert {r.track_id for r in result.outputs["relation_set"].relations} == set(with_corridors) - {2682}
    # a corridor of length 0
    vehicles = list(corridor_set.vehicles)
    i = next(n for n, v in enumerate(vehicles) if v.track_id == 2686)
    c = vehicles[i].corridors[0]
    flat = dataclasses.replace(c, x_m=np.full(3, c.x_m[0]), y_m=np.full(3, c.y_m[0]), s_m=np.zeros(3),
                               heading_rad=np.zeros(3), curvature_1pm=np.zeros(3), width_m=np.full(3, 3.5))
    vehicles[i] = dataclasses.replace(vehicles[i], corridors=(flat, *vehicles[i].corridors[1:]))
    broken = dataclasses.replace(corridor_set, vehicles=tuple(vehicles))
    result = extractor.update({"track_frame": frame, "corridor_set": broken, "scene": scene})
    assert [(i.kind, i.agent_id) for i in result.issues] == [("bad_corridor", 2686)]
    n_before = len(sequence["relations"][k].relations)
    assert len(result.outputs["relation_set"].relations) == n_before - 1
    # messages of different stamps: an issue and no output
    late = dataclasses.replace(corridor_set, header=dataclasses.replace(corridor_set.header, stamp_ns=frame.header.stamp_ns + 1))
    result = extractor.update({"track_frame": frame, "corridor_set": late, "scene": scene})
    assert [i.kind for i in result.issues] == ["stamp_mismatch"] and result.outputs == {}
    # no scene yet: the lateral relation still works
    result = extractor.update({"track_frame": frame, "corridor_set": corridor_set})
    assert [i.kind for i in result.issues] == ["no_map"]
    follower = [r for r in result.outputs["relation_set"].relations if r.track_id == 2686]
    assert follower and all(r.leader_track_id == 2682 and len(r.intersection_ids) == 0 for r in follower)


def test_config_rejects_unknown_keys_and_bad_values():
    from stages.lib.base import ConfigError

    assert RelationsConfig.from_params({"lateral_margin_m": 0.75}).lateral_margin_m == 0.75
    with pytest.raises(ConfigError, match="known: "):
        RelationsConfig.from_params({"lateral_margin": 0.75}, "hybrid.toml node relations")
    with pytest.raises(ConfigError, match="horizon_s"):
        RelationsConfig.from_params({"horizon_s": -1.0})


def test_binding_declares_the_ports():
    from stages.relations import INPUTS, OUTPUTS, SPEC

    assert set(INPUTS) == {"track_frame", "corridor_set", "scene", "signal_state"} and INPUTS["scene"].latched
    assert INPUTS["signal_state"].latest and INPUTS["signal_state"].optional  # not joined: a recording without phases never sends it
    assert set(OUTPUTS) == {"relation_set"} and SPEC.stage == "stages.relations"


def test_relation_set_round_trips_on_the_wire(crossing_scene):
    from bus_schemas import RelationSet

    _frame, _corridor_set, relation_set = crossing_scene
    decoded = RelationSet.decode(relation_set.encode())
    assert len(decoded.relations) == len(relation_set.relations)
    for a, b in zip(decoded.relations, relation_set.relations):
        assert a.influencing_rule == b.influencing_rule
        np.testing.assert_array_equal(a.conflict_s_m, b.conflict_s_m)


def test_batched_lateral_relations_equal_the_pair_by_pair_ones_bit_for_bit(sequence, scene_maps, crossing_scene, monkeypatch):
    """`_lateral_batched` and `_conflict_owners` (every pair at once) give the messages of `_lateral` and `_relations`
    pair by pair (their fallbacks), every frame, with and without route probabilities."""
    batched = RelationExtractor(RelationsConfig(), scene_maps=scene_maps)
    calls = []
    original = RelationExtractor._lateral_batched

    def counted(self, *args):
        calls.append(1)
        return original(self, *args)

    monkeypatch.setattr(RelationExtractor, "_lateral_batched", counted)
    per_pair = RelationExtractor(RelationsConfig(), scene_maps=scene_maps)
    monkeypatch.setattr(per_pair, "_lateral_batched", lambda *args: (_ for _ in ()).throw(RuntimeError("off")))
    monkeypatch.setattr(per_pair, "_conflict_owners", lambda *args: (_ for _ in ()).throw(RuntimeError("off")))
    rng = np.random.default_rng(3)
    leaders = influenced = 0
    for n, (frame, corridor_set) in enumerate(sequence["frames"]):
        probabilities = None
        if n % 2:
            probabilities = {(v.track_id, c.corridor_id): float(rng.choice([0.05, 0.5, 1.0])) for v in corridor_set.vehicles for c in v.corridors}
        a, issues_a = batched.process(frame, corridor_set, sequence["scene"], route_probabilities=probabilities)
        b, issues_b = per_pair.process(frame, corridor_set, sequence["scene"], route_probabilities=probabilities)
        assert issues_a == issues_b == []
        assert a.encode() == b.encode()
        leaders += sum(r.leader_track_id >= 0 for r in a.relations)
        influenced += sum(r.influencing_index >= 0 for r in a.relations)
    frame, corridor_set, _relation_set = crossing_scene  # conflicts and influencing choices (sequence 013 has none)
    for probabilities in (None, {(v.track_id, c.corridor_id): p for v in corridor_set.vehicles for c, p in zip(v.corridors, (0.05, 1.0, 0.3))}):
        a, _ = batched.process(frame, corridor_set, sequence["scene"], route_probabilities=probabilities)
        b, _ = per_pair.process(frame, corridor_set, sequence["scene"], route_probabilities=probabilities)
        assert a.encode() == b.encode()
        influenced += sum(r.influencing_index >= 0 for r in a.relations)
    assert influenced >= 4
    with_pairs = sum(any(v.corridors for v in corridor_set.vehicles) for _frame, corridor_set in sequence["frames"])
    assert len(calls) == with_pairs + 2 > 1000 and leaders > 100


def test_batched_corridor_checks_equal_the_corridor_by_corridor_ones(sequence, scene_maps):
    """`_checked_corridors` (every corridor of a frame at once) gives `_corridor_problem`'s verdicts and messages, the
    table indices and the lanelet-succession flag of each corridor, for sound and broken corridors side by side."""
    from stages.relations.core import SceneTables, _checked_corridors, _corridor_problem

    tables = SceneTables(sequence["road_map"])
    frame, corridor_set = max(sequence["frames"], key=lambda fc: sum(len(v.corridors) for v in fc[1].vehicles))
    sound = [c for v in corridor_set.vehicles for c in v.corridors]
    c = sound[0]
    s_back = c.s_m.copy()
    s_back[5] = s_back[3]
    broken = [
        dataclasses.replace(c, x_m=np.where(np.arange(len(c.x_m)) == 4, np.nan, c.x_m)),
        dataclasses.replace(c, width_m=np.full(len(c.x_m), np.inf)),
        dataclasses.replace(c, s_m=s_back),
        dataclasses.replace(c, s_m=np.zeros(len(c.s_m))),
        dataclasses.replace(c, vehicle_s_m=math.nan),
        dataclasses.replace(c, lanelet_start_s_m=c.lanelet_start_s_m[:-1]),
        dataclasses.replace(c, lanelet_start_s_m=np.full(len(c.lanelet_ids), np.nan)),
        dataclasses.replace(c, x_m=c.x_m[:1], y_m=c.y_m[:1], s_m=c.s_m[:1], heading_rad=c.heading_rad[:1], width_m=c.width_m[:1]),
        dataclasses.replace(c, y_m=c.y_m[:-1]),
        dataclasses.replace(c, lanelet_ids=np.array([999, *c.lanelet_ids[::-1]], dtype=np.int64), lanelet_start_s_m=np.zeros(len(c.lanelet_ids) + 1)),
        dataclasses.replace(c, lanelet_ids=np.zeros(0, np.int64), lanelet_start_s_m=np.zeros(0)),
    ]
    mixed = []
    for k, corridor in enumerate(sound):
        mixed.append(corridor)
        if k < len(broken):
            mixed.append(broken[k])
    mixed.extend(broken[len(sound):])
    vehicle = dataclasses.replace(corridor_set.vehicles[0], corridors=tuple(mixed))
    checked = _checked_corridors(dataclasses.replace(corridor_set, vehicles=(vehicle,)), tables)
    problems = 0
    for corridor in mixed:
        problem, index, follows = checked[id(corridor)]
        assert problem == _corridor_problem(corridor)
        if problem is None:
            want = tables.indices(corridor.lanelet_ids)
            np.testing.assert_array_equal(index, want)
            assert follows == bool(tables.is_successor[want[:-1], want[1:]].all())
        problems += problem is not None
    assert problems == 9
    assert not checked[id(broken[-2])][2] and checked[id(broken[-1])][2]  # unknown and reversed lanelets do not follow; none do
    # only sound corridors (nothing non-finite, no step back anywhere: the checks' short cuts) give the same answers
    checked = _checked_corridors(corridor_set, tables)
    for corridor in sound:
        problem, index, follows = checked[id(corridor)]
        want = tables.indices(corridor.lanelet_ids)
        assert problem is None and np.array_equal(index, want)
        assert follows == bool(tables.is_successor[want[:-1], want[1:]].all())


def _one_corridor_choice(kinds, priority, distance_m, other_distance_m, time_s, other_time_s, *, horizon_s, other_probability, min_probability):
    """The influencing choice for one corridor as `choose_influencing` made it before the grouped form: rank, then the first eligible."""
    from stages.lib.influence import NO_INFLUENCE, RULES, eligibility

    rule = eligibility(kinds, priority, distance_m, other_distance_m, time_s, other_time_s)
    ok = (rule != RULES.index(NO_INFLUENCE)) & (np.asarray(other_time_s, np.float64) < horizon_s)
    if other_probability is not None:
        ok &= np.asarray(other_probability, np.float64) >= min_probability
    for k in rank_conflicts(time_s, other_time_s):
        if ok[k]:
            return int(k), RULES[int(rule[k])]
    return -1, NO_INFLUENCE


def test_grouped_influencing_choice_equals_the_choice_per_corridor():
    """`choose_influencing_grouped` (every corridor's conflicts at once) picks per group what `choose_influencing` picks
    on the group's own arrays, with ties in |T' - T|, NaN times, the horizon and route probabilities."""
    from stages.lib.influence import RULES, choose_influencing_grouped

    rng = np.random.default_rng(5)
    sizes = rng.integers(0, 7, 300)
    group = np.repeat(np.arange(len(sizes)), sizes)
    n = len(group)
    kinds = rng.choice([int(ConflictKind.CROSSING), int(ConflictKind.MERGE)], n).astype(np.uint8)
    priority = rng.integers(-1, 2, n).astype(np.int8)
    time_s = rng.choice([0.5, 1.0, 2.0, 3.0, np.nan, 9.0], n)
    other_time_s = rng.choice([0.5, 1.0, 2.5, 3.0, 7.0, np.nan], n)
    distance = rng.uniform(-2, 30, n)
    other_distance = rng.uniform(-2, 30, n)
    probability = rng.choice([0.05, 0.5, 1.0], n)
    for prob in (None, probability):
        index, rule = choose_influencing_grouped(group, len(sizes), kinds, priority, distance, other_distance, time_s, other_time_s,
                                                 horizon_s=6.0, other_probability=prob, min_probability=0.1)
        chosen = 0
        for g in range(len(sizes)):
            span = group == g
            args = (kinds[span], priority[span], distance[span], other_distance[span], time_s[span], other_time_s[span])
            want = _one_corridor_choice(*args, horizon_s=6.0, other_probability=None if prob is None else prob[span], min_probability=0.1)
            assert (int(index[g]), RULES[int(rule[g])]) == want
            assert choose_influencing(*args, horizon_s=6.0, other_probability=None if prob is None else prob[span], min_probability=0.1) == want
            chosen += want[0] >= 0
        assert 50 < chosen < len(sizes)


def test_lane_change_refinement_in_one_kernel_call_equals_the_call_per_corridor(scene_maps, monkeypatch):
    """`_refine` projects the conflict points of every lane-change corridor in one `kernels.project_window_groups` call;
    with the kernel declining (each corridor through `project_in_window`, the reference) every call over the embedded
    K729 sequences gives the same arc lengths bit for bit (hundreds of them moved by the refinement), and every frame
    the same RelationSet bytes and issues."""
    from stages.lib.datasets import load_recording
    from stages.lib.maps import kernels

    if not kernels.available():
        pytest.skip("numba not importable")
    name = "k729_2022-03-16"
    recording = load_recording(DEFAULT_DATA_DIR, name)
    player = TrackPlayer(TracksSourceConfig(recording=name), recording, map_sha256="", run_id="test", producer="tracks")
    builder = CorridorBuilder(CorridorsConfig(), producer="corridors", scene_maps=scene_maps)
    inputs, scene = [], None
    for _stamp, result in player:
        scene = result.outputs.get("scene", scene)
        frame = result.outputs["track_frame"]
        inputs.append((frame, builder.process(frame, scene)[0], scene))
    grouped_kernel = kernels.project_window_groups
    original = RelationExtractor._refine
    moved = []

    def compared(self, pairs, tables, point, g, s):
        given, reference = s.copy(), s.copy()
        monkeypatch.setattr(kernels, "project_window_groups", lambda *args: None)
        original(self, pairs, tables, point, g, reference)
        monkeypatch.setattr(kernels, "project_window_groups", grouped_kernel)
        original(self, pairs, tables, point, g, s)
        assert s.tobytes() == reference.tobytes()
        moved.append(int((s != given).sum()))

    def run():
        extractor = RelationExtractor(RelationsConfig(), scene_maps=scene_maps)
        return [extractor.process(frame, corridor_set, scene) for frame, corridor_set, scene in inputs]

    monkeypatch.setattr(RelationExtractor, "_refine", compared)
    grouped = run()
    assert sum(moved) > 100, moved
    monkeypatch.setattr(RelationExtractor, "_refine", original)
    monkeypatch.setattr(kernels, "project_window_groups", lambda *args: None)
    reference = run()
    assert len(grouped) == len(reference) > 1000
    for (a, issues_a), (b, issues_b) in zip(grouped, reference):
        assert a.encode() == b.encode() and issues_a == issues_b


def test_scene_tables_sorted_lookup_gives_the_indices_of_the_lookup_id_by_id(sequence):
    from stages.relations.core import SceneTables

    tables = SceneTables(sequence["road_map"])
    ids = np.array(sequence["road_map"].lanelet_ids, dtype=np.int64)
    rng = np.random.default_rng(2)
    query = np.concatenate([rng.permutation(ids), [0, -1, ids.min() - 1, ids.max() + 1, np.iinfo(np.int64).max], ids[:3]])
    by_array = tables.indices(query)
    by_id = tables.indices(query.tolist())  # a list: id by id
    assert by_array.dtype == by_id.dtype == np.int64 and by_array.tolist() == by_id.tolist()
    assert by_array[: len(ids)].tolist() == [tables._index[int(x)] for x in query[: len(ids)]]
    assert (by_array[len(ids) : len(ids) + 5] == tables.n_lanelets).all()
