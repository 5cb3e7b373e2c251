"""Tests of the intentions stage on the real K729 map and tracks (embedded sequence 013).

Real frames come from the dataset player, and the corridors and relations
cores run in-process over the whole sequence (continuity state as on the
bus), as ``stages.offline.chain.chain_frames`` does. Cars named by
track id were picked from that sequence: 2688 turns right at the
intersection, 2690 brakes to a stop about 17 m before its entrance.
"""

from __future__ import annotations

import dataclasses
import math
import sys
from pathlib import Path

import numpy as np
import pytest

from bus_schemas import IntentionBelief, Manoeuvre
from stages.corridors import SceneMaps
from stages.lib.datasets import DEFAULT_DATA_DIR, load_recording
from stages.intentions import IntentionFilter, IntentionsConfig
from stages.offline.chain import chain_frames
from stages.offline.truth import route_credit, route_top1

pytestmark = pytest.mark.skipif(
    not (DEFAULT_DATA_DIR / "maps").is_dir(), reason=f"embedded TAF-BW data not found at {DEFAULT_DATA_DIR}"
)

TURNING_CAR = 2688  # turns right (lanelet -335553) while a straight corridor is still listed
STOPPING_CAR = 2690  # brakes from 5.6 m/s to a standstill at t = 52.1 s, 17 m before the entrance
WINDOW = slice(760, 820)  # 76.0 to 81.9 s: several cars with two to four corridors each, 2688 from 76.4 s


@pytest.fixture(scope="module")
def scene_maps() -> SceneMaps:
    return SceneMaps()


@pytest.fixture(scope="module")
def frames(scene_maps):
    """Sequence 013 through TrackPlayer → CorridorBuilder → RelationExtractor (ChainFrame per frame)."""
    recording = load_recording(DEFAULT_DATA_DIR, "k729_2022-03-16", ("013",))
    return chain_frames(recording, recording.sequences[0], scene_maps)


def run(frames, scene_maps, config: IntentionsConfig | None = None, edit=None):
    """(belief, issues) per frame of a fresh filter; `edit(k, frame, corridor_set, relation_set)` may change the inputs."""
    intentions = IntentionFilter(config or IntentionsConfig(), scene_maps=scene_maps)
    out = []
    for k, item in enumerate(frames):
        inputs = (item.frame, item.corridor_set, item.relation_set)
        if edit is not None:
            inputs = edit(k, *inputs)
        out.append(intentions.process(*inputs, item.scene))
    return out, intentions


@pytest.fixture(scope="module")
def sequence_run(frames, scene_maps):
    beliefs, _ = run(frames, scene_maps)
    return beliefs


def without_track(track_id: int, frame, corridor_set, relation_set):
    """The three inputs with one object removed, as if the sensors lost it."""
    keep = np.asarray(frame.track_ids) != track_id
    arrays = {f: getattr(frame, f)[keep] for f in ("track_ids", "agent_types", "x_m", "y_m", "vx_mps", "vy_mps", "yaw_rad", "length_m", "width_m")}
    return (
        dataclasses.replace(frame, **arrays),
        dataclasses.replace(corridor_set, vehicles=tuple(v for v in corridor_set.vehicles if v.track_id != track_id)),
        dataclasses.replace(relation_set, relations=tuple(r for r in relation_set.relations if r.track_id != track_id)),
    )


# --------------------------------------------------------------------------- the filter on the real sequence


def _frame_tables(items):
    """(vehicles with corridors, their PairTables) of each frame of ``items`` that has any, with fixed table parameters."""
    from stages.intentions.tables import VehicleInput, build_tables

    for item in items:
        vehicles = [VehicleInput(v.track_id, tuple(v.corridors), int(v.lanelet_id)) for v in item.corridor_set.vehicles if v.corridors]
        if vehicles:
            yield vehicles, build_tables(vehicles, {}, {}, lat_accels_mps2=(3.0, 2.0), brake_lookahead_mps2=2.5, curvature_smoothing_m=1.0,
                                         default_speed_limit_mps=13.9, stop_offset_m=14.0)


def test_same_input_gives_identical_beliefs_and_another_seed_differs(frames, scene_maps):
    part = frames[WINDOW]
    first, _ = run(part, scene_maps)
    again, _ = run(part, scene_maps)
    other, _ = run(part, scene_maps, IntentionsConfig(seed=1))
    encoded = [b.encode() for b, _ in first]
    assert encoded == [b.encode() for b, _ in again]
    assert sum(a != b.encode() for a, (b, _) in zip(encoded, other)) > len(part) // 2
    assert all(issues == [] for _, issues in first)


def test_probabilities_sum_to_one_and_the_floor_keeps_every_corridor(sequence_run):
    config = IntentionsConfig()
    smallest = 1.0
    n_vehicles = 0
    for belief, issues in sequence_run:
        assert issues == []
        for vehicle in belief.vehicles:
            n_vehicles += 1
            p = np.array([c.probability for c in vehicle.corridors])
            assert abs(p.sum() - 1.0) < 1e-9
            assert (p > 0.0).all()
            smallest = min(smallest, float(p.min()))
            counts = [c.particle_count for c in vehicle.corridors]
            assert sum(counts) == vehicle.particle_count == config.particles_per_vehicle
            assert min(counts) >= min(config.floor_particles, config.particles_per_vehicle // len(counts))
            for value in (vehicle.p_stop, vehicle.p_expected_stop, vehicle.p_violation, vehicle.p_lane_change):
                assert 0.0 <= value <= 1.0
            assert 0.0 < vehicle.effective_sample_size <= vehicle.particle_count + 1e-9
    assert n_vehicles > 2000
    # corridors the measurements ruled out keep particles and a (tiny) probability: they could still recover
    assert smallest < 1e-6


def test_a_car_that_turns_gets_its_turning_corridor_once_past_the_branch(frames, sequence_run):
    checked = 0
    for item, (belief, _) in zip(frames, sequence_run):
        vehicle = belief.vehicle(TURNING_CAR)
        matched = next((v for v in item.corridor_set.vehicles if v.track_id == TURNING_CAR), None)
        if vehicle is None or matched is None or len(vehicle.corridors) < 2:
            continue
        corridors = {c.corridor_id: c for c in matched.corridors}
        turning = [c for c in vehicle.corridors if c.manoeuvre is Manoeuvre.TURN_RIGHT]
        straight = [c for c in vehicle.corridors if c.manoeuvre is Manoeuvre.GO_STRAIGHT]
        if len(turning) != 1 or not straight:
            continue
        # past the branch: the lanelet the car is on belongs to the turning corridor only
        if any(matched.lanelet_id in corridors[c.corridor_id].lanelet_ids for c in straight):
            continue
        assert matched.lanelet_id in corridors[turning[0].corridor_id].lanelet_ids
        assert turning[0].probability > 0.9
        assert vehicle.expected_manoeuvre is Manoeuvre.TURN_RIGHT
        checked += 1
    assert checked >= 5


def test_a_car_braking_to_a_stop_before_the_intersection_gets_p_stop_rising(frames, sequence_run):
    stamps = np.array([item.frame.header.stamp_ns for item in frames])
    standstill_ns = 52_100_000_000
    seen = [k for k, (belief, _) in enumerate(sequence_run) if belief.vehicle(STOPPING_CAR) is not None]
    first = seen[0]  # the track starts 2.7 s before the standstill, braking from 5.6 m/s
    assert (standstill_ns - stamps[first]) * 1e-9 > 2.5

    def belief_at(before_s: float):
        k = int(np.argmin(np.abs(stamps - (standstill_ns - before_s * 1e9))))
        return sequence_run[k][0].vehicle(STOPPING_CAR)

    far, near, stopped = sequence_run[first][0].vehicle(STOPPING_CAR), belief_at(1.0), belief_at(0.0)
    assert far.p_stop < 0.6 < 0.8 < near.p_stop and stopped.p_stop > 0.8
    assert 10.0 < stopped.intersection_distance_m < 25.0
    assert stopped.expected_manoeuvre is Manoeuvre.STOP
    best = max(near.corridors, key=lambda c: c.probability)
    assert best.a_mean_mps2 < -0.5 and best.v_mean_mps < 3.0 < far.corridors[0].v_mean_mps


def test_expected_manoeuvre_follows_the_gap_to_a_priority_vehicle(frames):
    from stages.intentions.model import expected_stop
    from stages.intentions.tables import VehicleInput, build_tables

    item = frames[WINDOW][10]
    vehicle = next(v for v in item.corridor_set.vehicles if v.track_id == TURNING_CAR)
    corridor = vehicle.corridors[0]
    relation = next(r for r in item.relation_set.relations if r.track_id == TURNING_CAR and r.corridor_id == corridor.corridor_id)
    s_star = corridor.vehicle_s_m + 20.0  # the ego needs T_e = 20 m / 5 m/s = 4 s

    def p_expected_stop(other_time_s: float, q: float = 1.0, priority: int = -1, s_particle: float = corridor.vehicle_s_m) -> float:
        one = lambda value, dtype=np.float64: np.array([value], dtype=dtype)  # noqa: E731
        conflict = dataclasses.replace(
            relation, conflict_track_ids=one(99, np.int64), conflict_corridor_ids=one(7, np.int64), conflict_kinds=one(1, np.uint8),
            conflict_s_m=one(s_star), conflict_other_s_m=one(10.0), conflict_x_m=one(0.0), conflict_y_m=one(0.0),
            conflict_distance_m=one(20.0), conflict_other_distance_m=one(10.0), conflict_other_speed_mps=one(5.0),
            conflict_time_s=one(4.0), conflict_other_time_s=one(other_time_s), conflict_priority=one(priority, np.int8),
        )
        tables = build_tables(
            [VehicleInput(TURNING_CAR, (corridor,), vehicle.lanelet_id)], {(TURNING_CAR, corridor.corridor_id): conflict}, {(99, 7): q},
            lat_accels_mps2=(2.0,), brake_lookahead_mps2=2.5, curvature_smoothing_m=1.0, default_speed_limit_mps=13.9, stop_offset_m=14.0,
        )
        params = IntentionsConfig().model_params()
        return float(expected_stop(tables, np.zeros((1, 1), np.int64), np.full((1, 1), s_particle), np.full((1, 1), 5.0), params)[0, 0])

    assert p_expected_stop(5.0) > 0.9  # the priority car arrives 1 s after the ego: gap rejected, yield
    assert p_expected_stop(12.0) < 0.05  # 8 s after: gap accepted
    assert p_expected_stop(1.0) < 0.1  # 3 s before the ego: it is gone by then
    assert abs(p_expected_stop(5.0, q=0.5) - 0.5 * p_expected_stop(5.0)) < 1e-9  # weighted by its route probability
    assert p_expected_stop(5.0, priority=1) == 0.0  # the ego has priority
    assert p_expected_stop(5.0, s_particle=s_star + 1.0) == 0.0  # past the conflict point


# --------------------------------------------------------------------------- vehicles coming and going


def test_a_vehicle_unseen_for_more_than_one_second_is_dropped(frames, scene_maps):
    start = next(k for k, item in enumerate(frames) if any(v.track_id == TURNING_CAR and v.corridors for v in item.corridor_set.vehicles))
    part = frames[start : start + 25]  # the car is seen at k = 0..9, gone at k = 10..21, back at k = 22

    def edit(k, frame, corridor_set, relation_set):
        return without_track(TURNING_CAR, frame, corridor_set, relation_set) if 10 <= k < 22 else (frame, corridor_set, relation_set)

    assert all(any(v.track_id == TURNING_CAR and v.corridors for v in item.corridor_set.vehicles) for item in part)
    intentions = IntentionFilter(IntentionsConfig(), scene_maps=scene_maps)
    tracked = []
    for k, item in enumerate(part):
        belief, _ = intentions.process(*edit(k, item.frame, item.corridor_set, item.relation_set), item.scene)
        tracked.append(TURNING_CAR in intentions.tracked_ids)
        if k == 22:
            reborn = belief.vehicle(TURNING_CAR)
    assert tracked[:20] == [True] * 20  # 1.0 s unseen at k = 19: still kept
    assert tracked[20] is False  # 1.1 s unseen: dropped
    assert tracked[22] is True and reborn is not None
    assert sum(c.particle_count for c in reborn.corridors) == IntentionsConfig().particles_per_vehicle


def test_a_corridor_set_change_keeps_the_belief(frames, scene_maps):
    part = frames[WINDOW]
    renamed_from = 20

    def rename(k, frame, corridor_set, relation_set):
        if k < renamed_from:
            return frame, corridor_set, relation_set
        vehicles = []
        for v in corridor_set.vehicles:
            if v.track_id == TURNING_CAR:
                v = dataclasses.replace(v, corridors=tuple(dataclasses.replace(c, corridor_id=c.corridor_id ^ 0x5A5A5A) for c in v.corridors))
            vehicles.append(v)
        relations = tuple(
            dataclasses.replace(r, corridor_id=r.corridor_id ^ 0x5A5A5A) if r.track_id == TURNING_CAR else r for r in relation_set.relations
        )
        return frame, dataclasses.replace(corridor_set, vehicles=tuple(vehicles)), dataclasses.replace(relation_set, relations=relations)

    plain, _ = run(part, scene_maps)
    renamed, _ = run(part, scene_maps, edit=rename)
    compared = 0
    for (a, _), (b, _) in zip(plain[renamed_from:], renamed[renamed_from:]):
        va, vb = a.vehicle(TURNING_CAR), b.vehicle(TURNING_CAR)
        if va is None:
            continue
        # every corridor got a new id, yet the particles followed their lanelets: the same belief
        assert [c.corridor_id ^ 0x5A5A5A for c in va.corridors] == [c.corridor_id for c in vb.corridors]
        np.testing.assert_allclose([c.probability for c in va.corridors], [c.probability for c in vb.corridors], rtol=0, atol=1e-9)
        compared += 1
    assert compared >= 10

    # a corridor that disappears hands its particles to the corridor sharing the most lanelets with it
    k = next(k for k in range(len(part)) if (v := plain[k][0].vehicle(TURNING_CAR)) is not None and len(v.corridors) >= 3)
    before = plain[k][0].vehicle(TURNING_CAR)
    dropped = before.corridors[-1]

    def drop(j, frame, corridor_set, relation_set):
        if j != k + 1:
            return frame, corridor_set, relation_set
        vehicles = tuple(
            dataclasses.replace(v, corridors=tuple(c for c in v.corridors if c.corridor_id != dropped.corridor_id))
            if v.track_id == TURNING_CAR else v
            for v in corridor_set.vehicles
        )
        return frame, dataclasses.replace(corridor_set, vehicles=vehicles), relation_set

    changed, _ = run(part[: k + 2], scene_maps, edit=drop)
    after = changed[k + 1][0].vehicle(TURNING_CAR)
    normal = plain[k + 1][0].vehicle(TURNING_CAR)
    assert dropped.corridor_id not in [c.corridor_id for c in after.corridors]
    assert abs(sum(c.probability for c in after.corridors) - 1.0) < 1e-9
    survivors = {c.corridor_id: c.probability for c in normal.corridors if c.corridor_id != dropped.corridor_id}
    for c in after.corridors:
        # the surviving routes keep (at least) their mass: not reset to a uniform prior
        assert c.probability >= survivors[c.corridor_id] - 0.05


def test_nan_state_is_an_issue_and_the_other_vehicles_are_processed(frames, scene_maps):
    part = frames[WINDOW]
    intentions = IntentionFilter(IntentionsConfig(), scene_maps=scene_maps)
    for item in part[:10]:
        intentions.process(item.frame, item.corridor_set, item.relation_set, item.scene)
    item = part[10]
    row = int(np.flatnonzero(item.frame.track_ids == TURNING_CAR)[0])
    x = item.frame.x_m.copy()
    x[row] = math.nan
    others = {v.track_id for v in item.corridor_set.vehicles if v.corridors} - {TURNING_CAR}
    belief, issues = intentions.process(dataclasses.replace(item.frame, x_m=x), item.corridor_set, item.relation_set, item.scene)
    assert [(i.kind, i.agent_id) for i in issues] == [("nan_state", TURNING_CAR)]
    assert {v.track_id for v in belief.vehicles} == others and others
    assert TURNING_CAR in intentions.tracked_ids  # kept, not updated: it dies only after 1 s unseen
    # a vehicle without any finite speed is still updated, without the speed term
    item = part[11]
    vehicles = tuple(dataclasses.replace(v, speed_mps=math.nan) if v.track_id == TURNING_CAR else v for v in item.corridor_set.vehicles)
    vx = item.frame.vx_mps.copy()
    vx[row] = math.nan
    belief, issues = intentions.process(
        dataclasses.replace(item.frame, vx_mps=vx), dataclasses.replace(item.corridor_set, vehicles=vehicles), item.relation_set, item.scene
    )
    assert [(i.kind, i.agent_id) for i in issues] == [("nan_velocity", TURNING_CAR)]
    assert belief.vehicle(TURNING_CAR) is not None
    # inputs of different stamps: an issue and no output
    late = dataclasses.replace(item.relation_set, header=dataclasses.replace(item.relation_set.header, stamp_ns=item.frame.header.stamp_ns + 1))
    result = intentions.update({"track_frame": item.frame, "corridor_set": item.corridor_set, "relation_set": late, "scene": item.scene})
    assert [i.kind for i in result.issues] == ["stamp_mismatch"] and result.outputs == {}


# --------------------------------------------------------------------------- configuration, evaluation helpers, binding


def test_config_rejects_unknown_keys_and_bad_values():
    from stages.lib.base import ConfigError

    assert IntentionsConfig.from_params({"particles_per_vehicle": 100}).floor_particles == 2
    with pytest.raises(ConfigError, match="known: "):
        IntentionsConfig.from_params({"particles": 100}, "hybrid.toml node intentions")
    with pytest.raises(ConfigError, match="position_sigma_m"):
        IntentionsConfig.from_params({"position_sigma_m": 0.0})


def test_route_top1_splits_ties():
    assert route_credit(np.array([0.2, 0.7, 0.1]), 1) == 1.0
    assert route_credit(np.array([0.2, 0.7, 0.1]), 0) == 0.0
    assert route_credit(np.ones(4), 2) == 0.25  # a k-way tie counts 1/k, the expectation of a random pick
    assert route_top1([np.ones(2)] * 2000, [0] * 2000) == 0.5
    assert route_top1([np.array([0.6, 0.4]), np.array([0.4, 0.6])], [0, 0]) == 0.5
    assert math.isnan(route_top1([], []))


def test_binding_declares_the_ports():
    from stages.intentions import INPUTS, OUTPUTS, SPEC

    assert set(INPUTS) == {"track_frame", "corridor_set", "relation_set", "scene"} and INPUTS["scene"].latched
    assert OUTPUTS["intention_belief"].schema is IntentionBelief and SPEC.stage == "stages.intentions"


# --------------------------------------------------------------------------- through the bus


def test_the_stage_on_the_bus_publishes_the_in_process_beliefs(frames, scene_maps, tmp_path):
    from testkit import helpers as h
    from stages.runtime import BusClient

    part = frames[760:780]
    expected = [b.encode() for b, _ in run(part, scene_maps)[0]]
    run_id = "intentbus"
    port = h.free_port()
    got: list[bytes] = []
    with BusClient(listen=[h.endpoint(port)]) as bus:
        bus.subscribe(f"iamp/{run_id}/intentions/intention_belief", lambda _k, data: got.append(data))
        stage = h.start_module(
            "stages.intentions",
            "--run-id", run_id,
            "--connect", h.endpoint(port),
            "--input", "track_frame=source/track_frame",
            "--input", "corridor_set=corridors/corridor_set",
            "--input", "relation_set=relations/relation_set",
            "--input", "scene=source/scene",
            log_dir=tmp_path,
        )
        try:
            h.wait_until(lambda: "intentions" in bus.alive_now(f"iamp/{run_id}/_alive/*", 0.5), 60, "intentions liveliness")
            put_scene = bus.publisher(f"iamp/{run_id}/source/scene")
            put_frame = bus.publisher(f"iamp/{run_id}/source/track_frame")
            put_corridors = bus.publisher(f"iamp/{run_id}/corridors/corridor_set")
            put_relations = bus.publisher(f"iamp/{run_id}/relations/relation_set")
            put_scene(part[0].scene.encode())
            for k, item in enumerate(part):
                put_frame(item.frame.encode())
                put_corridors(item.corridor_set.encode())
                put_relations(item.relation_set.encode())
                h.wait_until(lambda: len(got) > k, 60, f"the belief of frame {k}\n{h.output_of(stage)[-2000:]}")
            assert h.stop_process(stage) == 0
        finally:
            h.kill_all([stage])
    assert got == expected


def test_particles_that_lose_their_vehicle_are_born_again_at_the_measurement(frames, scene_maps):
    """An id switch (2686's id handed to car 2688 from frame 780 on): the particles are far from the
    new measurement; they are born again there (particles_lost once), not left where the old car was."""
    switch, old, new = 780, 2686, 2688

    def rename(k, frame, corridor_set, relation_set):
        if k < switch:
            return frame, corridor_set, relation_set
        frame, corridor_set, relation_set = without_track(old, frame, corridor_set, relation_set)
        ids = np.where(np.asarray(frame.track_ids) == new, old, np.asarray(frame.track_ids))
        return (
            dataclasses.replace(frame, track_ids=ids),
            dataclasses.replace(corridor_set, vehicles=tuple(dataclasses.replace(v, track_id=old) if v.track_id == new else v for v in corridor_set.vehicles)),
            dataclasses.replace(relation_set, relations=tuple(dataclasses.replace(r, track_id=old) if r.track_id == new else r for r in relation_set.relations)),
        )

    out, _ = run(frames[: switch + 10], scene_maps, edit=rename)
    lost = [(k, i) for k, (_, issues) in enumerate(out) for i in issues if i.kind == "particles_lost"]
    assert [(k, i.agent_id) for k, i in lost] == [(switch, old)]
    untouched, _ = run(frames[: switch + 10], scene_maps)
    assert not any(i.kind == "particles_lost" for _, issues in untouched for i in issues)
    belief = next(v for v in out[switch + 5][0].vehicles if v.track_id == old)
    corridor_set = rename(switch + 5, frames[switch + 5].frame, frames[switch + 5].corridor_set, frames[switch + 5].relation_set)[1]
    measured = {c.corridor_id: c.vehicle_s_m for v in corridor_set.vehicles if v.track_id == old for c in v.corridors}
    for c in belief.corridors:
        assert abs(c.s_mean_m - measured[c.corridor_id]) < 3.0


def test_batched_table_helpers_equal_their_one_corridor_forms(frames):
    """corridors_ok and unwrap_parts run on all of a frame's corridors at once; each answer is the one-corridor one exactly."""
    from stages.intentions.tables import corridor_ok, corridors_ok, unwrap_parts

    corridors = [c for item in frames[WINDOW] for v in item.corridor_set.vehicles for c in v.corridors]
    assert len(corridors) > 50
    assert corridors_ok(corridors) == [None] * len(corridors) == [corridor_ok(c) for c in corridors]

    def edited(c, **changes):
        return dataclasses.replace(c, **changes)

    c = corridors[0]
    odd = [
        edited(c, x_m=np.where(np.arange(len(c.x_m)) == 3, np.nan, c.x_m)),
        edited(c, s_m=c.s_m[::-1].copy()),
        edited(c, vehicle_d_m=math.inf),
        edited(c, y_m=c.y_m[:-1]),
        edited(c, s_m=c.s_m[:1], x_m=c.x_m[:1], y_m=c.y_m[:1], heading_rad=c.heading_rad[:1]),
    ]
    mixed = corridors[:5] + odd + corridors[5:9]
    found = corridors_ok(mixed)
    assert found == [corridor_ok(m) for m in mixed]
    assert all(f is None for f in found[:5] + found[-4:]) and all(f is not None for f in found[5:10])

    rng = np.random.default_rng(3)
    parts = [np.asarray(c.heading_rad, dtype=np.float64) for c in corridors[:20]]
    parts += [np.cumsum(rng.uniform(-4.0, 4.0, 30)), np.array([2.0]), np.array([0.5, np.nan, 0.7, 7.0]), np.array([-0.0, 3.0, -3.0])]
    rng.shuffle(parts)
    want = np.concatenate([np.unwrap(p) for p in parts])
    got = unwrap_parts(parts)
    assert np.array_equal(got, want, equal_nan=True)
    assert np.array_equal(np.signbit(got), np.signbit(want))  # even the sign of zeros


def test_particles_that_cannot_follow_their_corridors_are_born_again(frames, scene_maps, monkeypatch):
    """Corridors sharing no lanelet with the last ones: the particles are projected onto them; when that (or mapping the
    corridors) raises, only that vehicle's particles are born again (issue particles_reborn), the others are untouched."""
    import stages.intentions.core as core

    part, k = frames[WINDOW], 15
    assert all(any(v.track_id == TURNING_CAR and v.corridors for v in item.corridor_set.vehicles) for item in part[k - 1 : k + 1])
    marker = 0x5A5A5A

    def strange(j, frame, corridor_set, relation_set):  # at frame k the turning car's corridors hold lanelets never seen
        if j != k:
            return frame, corridor_set, relation_set
        vehicles = tuple(
            dataclasses.replace(v, corridors=tuple(
                dataclasses.replace(c, corridor_id=c.corridor_id ^ marker, lanelet_ids=np.asarray(c.lanelet_ids) + 2 * 10**9) for c in v.corridors))
            if v.track_id == TURNING_CAR else v for v in corridor_set.vehicles
        )
        relations = tuple(dataclasses.replace(r, corridor_id=r.corridor_id ^ marker) if r.track_id == TURNING_CAR else r for r in relation_set.relations)
        return frame, dataclasses.replace(corridor_set, vehicles=vehicles), dataclasses.replace(relation_set, relations=relations)

    def by_track(belief):
        return {v.track_id: v for v in belief.vehicles}

    projected, _ = run(part[: k + 1], scene_maps, edit=strange)
    belief, issues = projected[k]
    assert not [i for i in issues if i.kind == "particles_reborn"]
    car = by_track(belief)[TURNING_CAR]
    assert sum(c.particle_count for c in car.corridors) == IntentionsConfig().particles_per_vehicle

    real_project, real_map = core._project, core.map_corridors

    def unseen(corridors):
        return any(int(np.min(c.lanelet_ids)) >= 10**9 for c in corridors)

    def project_fails(p, v, before, old, slot, lost, corridors):
        if unseen(corridors):
            raise RuntimeError("stand-in projection failure")
        return real_project(p, v, before, old, slot, lost, corridors)

    calls = []

    def map_fails(old, new):
        if unseen(new):
            calls.append(len(new))
            raise RuntimeError("stand-in mapping failure")
        return real_map(old, new)

    for name, stand_in in (("_project", project_fails), ("map_corridors", map_fails)):
        with monkeypatch.context() as patch:
            patch.setattr(core, name, stand_in)
            failed, _ = run(part[: k + 1], scene_maps, edit=strange)
        belief_f, issues_f = failed[k]
        assert [(i.kind, i.agent_id) for i in issues_f if i.kind == "particles_reborn"] == [("particles_reborn", TURNING_CAR)], name
        reborn = by_track(belief_f)[TURNING_CAR]
        assert sum(c.particle_count for c in reborn.corridors) == IntentionsConfig().particles_per_vehicle
        assert reborn.corridors != car.corridors  # born at the measurement instead of projected
        others, others_f = by_track(belief), by_track(belief_f)
        assert set(others) == set(others_f)
        for track_id in set(others) - {TURNING_CAR}:
            assert repr(others_f[track_id]) == repr(others[track_id]), (name, track_id)  # repr: NaN fields compare equal
    assert calls  # the stand-in mapping ran


def test_compiled_pose_and_admissible_speed_equal_the_numpy_path(frames):
    """stages.intentions.kernels places particles on their corridors as PairTables' numpy path does, bit for bit (even
    the sign of zeros): inside, beyond either end, at the samples themselves, clipped far away, and NaN."""
    from stages.intentions import kernels
    from stages.intentions.tables import KEY_OFFSET_M

    if not kernels.available():
        pytest.skip("numba not importable")
    rng = np.random.default_rng(5)
    checked = 0
    for vehicles, tables in _frame_tables(frames[WINDOW][::6]):
        n = 400
        g = rng.integers(0, tables.n_pairs, (3, n))
        lo, hi = tables.s_m[tables.start[g]], tables.s_m[tables.end[g] - 1]
        s = rng.uniform(lo - 30.0, hi + 30.0)
        at_sample = rng.integers(tables.start[g], tables.end[g])
        s[0, :50] = tables.s_m[at_sample[0, :50]]  # exactly on samples: t = 0 (and the last one's t = 1)
        s[0, 50:60] = [np.nan, -0.0, 0.0, 2.0e4, -2.0e4, np.inf, -np.inf, 1.0e4, -1.0e4, 5e-324]
        d = rng.normal(0.0, 1.5, (3, n))
        d[1, :10] = [-0.0, 0.0, np.nan, 1e300, -1e300, 0.0, 0.0, 0.0, 0.0, 0.0]
        style = rng.integers(0, tables.v_adm_mps.shape[0], (3, n))
        with np.errstate(all="ignore"):
            got, want = tables.pose(g, s, d), tables.pose_numpy(g, s, d)
            for a, b in zip(got, want):
                assert np.array_equal(a, b, equal_nan=True) and np.array_equal(np.signbit(a), np.signbit(b))
            a, b = tables.admissible_speed(g, s, style), tables.admissible_speed_numpy(g, s, style)
        assert np.array_equal(a, b, equal_nan=True) and np.array_equal(np.signbit(a), np.signbit(b))
        checked += 1
    assert checked >= 5
    # signed zeros: a corridor starting at s = 0 with zero headings, particles at s = −0.0 (t = −0.0, clipped as numpy does)
    s_line = np.array([0.0, 1.0, 2.0, 0.0, 0.5])
    tiny = dataclasses.replace(
        tables, key=s_line + np.array([0.0, 0.0, 0.0, 1.0, 1.0]) * KEY_OFFSET_M, s_m=s_line, x_m=np.array([-0.0, 1.0, 2.0, 0.0, -0.0]),
        y_m=np.array([-0.0, -0.0, 0.0, 0.0, 1.0]), heading_rad=np.array([-0.0, -0.0, 0.5, 0.0, -0.0]),
        start=np.array([0, 3]), end=np.array([3, 5]), v_adm_mps=np.array([[-0.0, 1.0, 2.0, 0.0, 3.0]]))
    g = np.array([[0, 0, 0, 1, 1, 1, 0, 1]])
    s = np.array([[-0.0, 0.0, 2.0, -0.0, 0.5, 0.25, 1.0, 0.0]])
    d = np.array([[-0.0, 0.0, -0.0, 0.0, -0.0, 1.0, -0.0, -0.0]])
    style = np.zeros_like(g)
    for a, b in [*zip(tiny.pose(g, s, d), tiny.pose_numpy(g, s, d)), (tiny.admissible_speed(g, s, style), tiny.admissible_speed_numpy(g, s, style))]:
        assert np.array_equal(a, b, equal_nan=True) and np.array_equal(np.signbit(a), np.signbit(b))


def test_compiled_admissible_speeds_equal_the_numpy_profiles():
    """kernels.admissible_speeds gives tables.admissible_speeds' valid samples bit for bit: rows of many lengths (the
    padding width and the smoothing window the widest row's), non-finite curvatures, no smoothing, one sample."""
    from stages.intentions import kernels
    from stages.intentions.tables import MIN_CURVATURE_1PM, admissible_speeds

    if not kernels.available():
        pytest.skip("numba not importable")
    rng = np.random.default_rng(9)
    for trial in range(40):
        n_rows = int(rng.integers(1, 30))
        lengths = rng.integers(1 if trial % 5 == 0 else 2, 160, n_rows)
        step = rng.uniform(0.05, 2.0, n_rows) if trial % 3 else np.full(n_rows, 0.5)
        s_parts = [rng.uniform(-50, 50) + step[r] * np.arange(n) + rng.uniform(0, 1e-3, n) for r, n in enumerate(lengths)]
        k_parts = [rng.normal(0.0, 0.05, n) * (rng.random(n) < 0.7) for n in lengths]
        if trial % 4 == 0:
            k_parts[0][: min(3, lengths[0])] = [np.nan, np.inf, -np.inf][: min(3, lengths[0])]
        limits = rng.uniform(5.0, 20.0, n_rows)
        lat = tuple(rng.uniform(1.0, 3.5, int(rng.integers(1, 5))))
        brake = float(rng.uniform(0.5, 4.0))
        smoothing = float(rng.choice([0.0, 0.3, 1.0, 7.5]))
        width = int(lengths.max())
        valid = np.arange(width)[None, :] < lengths[:, None]
        s_pad, k_pad = np.zeros((n_rows, width)), np.zeros((n_rows, width))
        s_pad[valid], k_pad[valid] = np.concatenate(s_parts), np.concatenate(k_parts)
        want = admissible_speeds(s_pad, k_pad, lengths, limits, lat, brake, smoothing)[:, valid]
        got = kernels.admissible_speeds(np.concatenate(s_parts), np.concatenate(k_parts), lengths, limits, lat, brake, smoothing, MIN_CURVATURE_1PM)
        assert got.shape == want.shape
        assert np.array_equal(got, want, equal_nan=True) and np.array_equal(np.signbit(got), np.signbit(want))
    assert kernels.admissible_speeds(np.zeros(3), np.zeros(2), [3], [10.0], (2.0,), 2.5, 1.0, MIN_CURVATURE_1PM) is None


@pytest.mark.parametrize("relaxation_s", [0.0, 0.4])
def test_compiled_propagation_equals_the_numpy_one(frames, monkeypatch, relaxation_s):
    """model.propagate with the compiled intention and motion update (kernels.intend_and_move) moves every particle
    exactly as its numpy path does: the same stop draws, s, v, a, d and P(E = stop), bit for bit, with and without the
    acceleration state, for rows that are and are not active this step."""
    from stages.intentions import kernels, model
    from stages.intentions.model import PARTICLE_FIELDS, Particles
    from stages.intentions.tables import VehicleInput, build_tables

    if not kernels.available():
        pytest.skip("numba not importable")
    mp = IntentionsConfig(accel_relaxation_s=relaxation_s).model_params()
    rng = np.random.default_rng(13)
    checked = 0
    for item in frames[WINDOW][::10]:
        vehicles = [VehicleInput(v.track_id, tuple(v.corridors), int(v.lanelet_id)) for v in item.corridor_set.vehicles if v.corridors]
        relations = {(r.track_id, r.corridor_id): r for r in item.relation_set.relations} if item.relation_set is not None else {}
        if not vehicles:
            continue
        tables = build_tables(vehicles, relations, {}, lat_accels_mps2=(3.0, 2.0, 1.5), brake_lookahead_mps2=2.5, curvature_smoothing_m=1.0,
                              default_speed_limit_mps=13.9, stop_offset_m=14.0)
        n_rows, n = len(vehicles), 200
        route = rng.integers(0, tables.n_slots[:, None], (n_rows, n))
        g = tables.first_pair[:, None] + route
        start = Particles(
            route=route, s_m=tables.vehicle_s_m[g] + rng.normal(0.0, 20.0, (n_rows, n)), d_m=rng.normal(0.0, 0.5, (n_rows, n)),
            v_mps=np.maximum(rng.normal(6.0, 5.0, (n_rows, n)), 0.0), a_mps2=rng.normal(0.0, 1.5, (n_rows, n)),
            stop=rng.random((n_rows, n)) < 0.5, style=rng.integers(0, 3, (n_rows, n)), p_expected_stop=rng.random((n_rows, n)),
            weight=np.full((n_rows, n), 1.0 / n),
        )
        dt = rng.uniform(0.02, 0.1, n_rows)
        active = rng.random(n_rows) < 0.8
        draws = (rng.random((3, n_rows, n)), rng.standard_normal((2, n_rows, n)))
        runs = []
        for compiled in (True, False):
            monkeypatch.setattr(kernels, "available", lambda compiled=compiled: compiled)
            p = Particles(*(getattr(start, name).copy() for name in PARTICLE_FIELDS))
            model.propagate(p, tables, tables.first_pair, dt, active, draws, mp)
            runs.append(p)
        for name in PARTICLE_FIELDS:
            a, b = getattr(runs[0], name), getattr(runs[1], name)
            assert a.dtype == b.dtype and np.array_equal(a, b, equal_nan=True), name
            if a.dtype.kind == "f":
                assert np.array_equal(np.signbit(a), np.signbit(b)), name
        assert not np.array_equal(runs[0].s_m, start.s_m) and not np.array_equal(runs[0].stop, start.stop)
        checked += 1
    assert checked >= 3


def test_compiled_log_likelihood_equals_the_numpy_one(frames, monkeypatch):
    """model.log_likelihood with the compiled terms (kernels.gaussian_errors) gives its numpy path's values bit for bit
    (signs of zeros too): usable and unusable headings and speeds, NaN and infinite measurements and states."""
    from stages.intentions import kernels, model
    from stages.intentions.model import Particles

    if not kernels.available():
        pytest.skip("numba not importable")
    mp = IntentionsConfig().model_params()
    rng = np.random.default_rng(17)
    checked = 0
    for vehicles, tables in _frame_tables(frames[WINDOW][::10]):
        n_rows, n = len(vehicles), 150
        route = rng.integers(0, tables.n_slots[:, None], (n_rows, n))
        g = tables.first_pair[:, None] + route
        p = Particles(
            route=route, s_m=tables.vehicle_s_m[g] + rng.normal(0.0, 20.0, (n_rows, n)), d_m=rng.normal(0.0, 0.5, (n_rows, n)),
            v_mps=np.maximum(rng.normal(6.0, 5.0, (n_rows, n)), 0.0), a_mps2=np.zeros((n_rows, n)),
            stop=np.zeros((n_rows, n), bool), style=np.zeros((n_rows, n), np.int64), p_expected_stop=np.zeros((n_rows, n)),
            weight=np.full((n_rows, n), 1.0 / n),
        )
        p.v_mps[0, :6] = [np.nan, np.inf, -0.0, 0.0, 1e300, 5e-324]
        p.d_m[0, 6:9] = [np.nan, -np.inf, 1e300]
        x_obs = tables.x_m[tables.start[tables.first_pair]] + rng.normal(0.0, 3.0, n_rows)
        y_obs = tables.y_m[tables.start[tables.first_pair]] + rng.normal(0.0, 3.0, n_rows)
        heading_obs = rng.uniform(-4.0, 4.0, n_rows)
        speed_obs = rng.uniform(0.0, 15.0, n_rows)
        heading_ok, speed_ok = rng.random(n_rows) < 0.7, rng.random(n_rows) < 0.7
        if n_rows > 1:
            x_obs[1], heading_obs[1], speed_obs[1] = np.nan, np.inf, np.nan
            heading_ok[1] = speed_ok[1] = True
        z = (x_obs, y_obs, heading_obs, speed_obs, heading_ok, speed_ok)
        with np.errstate(all="ignore"):
            got = model.log_likelihood(p, tables, tables.first_pair, z, mp)
            monkeypatch.setattr(kernels, "gaussian_errors", lambda *args, **kwargs: None)
            want = model.log_likelihood(p, tables, tables.first_pair, z, mp)
            monkeypatch.undo()
        assert np.array_equal(got, want, equal_nan=True) and np.array_equal(np.signbit(got), np.signbit(want))
        assert np.isfinite(want).sum() > want.size // 2
        checked += 1
    assert checked >= 3


def test_compiled_route_switches_equal_the_numpy_ones(frames, monkeypatch):
    """model.switch_routes through kernels.switch_routes switches the same particles to the same corridors with the same
    s as its numpy path, bit for bit: frequent and rare switches, vehicles with one corridor, corridors without the
    vehicle's lanelet (NaN switch s), and none at all (the particles' arrays kept)."""
    from stages.intentions import kernels, model
    from stages.intentions.model import PARTICLE_FIELDS, Particles

    if not kernels.available():
        pytest.skip("numba not importable")
    rng = np.random.default_rng(19)
    checked = 0
    for vehicles, tables in _frame_tables(frames[WINDOW][::10]):
        if max(len(v.corridors) for v in vehicles) < 2:
            continue
        switch_s = tables.switch_s_m.copy()
        switch_s[rng.random(switch_s.size) < 0.2] = np.nan
        tables = dataclasses.replace(tables, switch_s_m=switch_s)
        n_rows, n = len(vehicles), 200
        route = rng.integers(0, tables.n_slots[:, None], (n_rows, n))
        for rate in (0.6, 0.005, 0.0):
            mp = dataclasses.replace(IntentionsConfig().model_params(), route_switch_per_step=rate)
            start = Particles(
                route=route.copy(), s_m=rng.normal(30.0, 20.0, (n_rows, n)), d_m=np.zeros((n_rows, n)), v_mps=np.zeros((n_rows, n)),
                a_mps2=np.zeros((n_rows, n)), stop=np.zeros((n_rows, n), bool), style=np.zeros((n_rows, n), np.int64),
                p_expected_stop=np.zeros((n_rows, n)), weight=np.full((n_rows, n), 1.0 / n),
            )
            dt = rng.uniform(0.02, 0.1, n_rows)
            u_switch, u_choice = rng.random((n_rows, n)), rng.random((n_rows, n))
            runs = []
            for compiled in (True, False):
                p = Particles(*(getattr(start, name).copy() for name in PARTICLE_FIELDS))
                if not compiled:
                    monkeypatch.setattr(kernels, "switch_routes", lambda *args, **kwargs: None)
                before = (p.route, p.s_m)
                model.switch_routes(p, tables, tables.first_pair, dt, u_switch, u_choice, mp)
                monkeypatch.undo()
                runs.append((p, before))
            (a, a_before), (b, b_before) = runs
            assert a.route.dtype == b.route.dtype and np.array_equal(a.route, b.route)
            assert np.array_equal(a.s_m, b.s_m, equal_nan=True) and np.array_equal(np.signbit(a.s_m), np.signbit(b.s_m))
            switched = not np.array_equal(b.route, start.route)
            if rate != 0.005:  # many switches at 0.6, none at 0 (at 0.005: a few or none)
                assert switched == (rate > 0.0)
            if not switched:  # nothing moved: the same arrays kept
                assert a.route is a_before[0] and a.s_m is a_before[1]
        checked += 1
    assert checked >= 3


def test_lost_rows_are_those_whose_median_exceeds_the_gate():
    """_lost_rows takes medians only where at least half of a row exceeds its gate: the rows and medians are those of
    np.median over every row (odd and even rows, exactly half above, ties at the gate, NaN, infinite and huge gates)."""
    from stages.intentions.core import _lost_rows

    rng = np.random.default_rng(31)
    for n in (1, 2, 7, 8, 300):
        gap = np.abs(rng.normal(0.0, 10.0, (400, n)))
        allowed = rng.uniform(0.0, 20.0, 400)
        for r in range(0, 400, 10):  # exactly half (or one more, one fewer) above the gate, and values at the gate
            k = n // 2 + (r // 10) % 3 - 1
            gap[r] = np.where(np.arange(n) < k, allowed[r] + rng.uniform(0.0, 1.0, n), allowed[r] - rng.uniform(0.0, 1.0, n))
            if r % 20 == 0:
                gap[r, 0] = allowed[r]
        gap[5, 0] = np.nan
        gap[6] = np.inf
        allowed[7:10] = [np.inf, 1e308, np.nan]
        gap[8] = 1e308
        with np.errstate(invalid="ignore", over="ignore"):
            median = np.median(gap, axis=1)
            want = np.flatnonzero(median > allowed)
            rows, distance = _lost_rows(gap, allowed)
        assert np.array_equal(rows, want) and np.array_equal(distance, median[want])
        assert 0 < len(rows) < 400


def test_compiled_pair_sums_equal_numpys_bincounts():
    """kernels.pair_sums (the beliefs' per-pair sums) gives np.bincount's weighted sums bit for bit (signs of zeros,
    NaN and infinities too, empty pairs), and leaves bins outside the pairs to numpy."""
    from stages.intentions import kernels

    if not kernels.available():
        pytest.skip("numba not importable")
    rng = np.random.default_rng(37)
    for n_pairs, n in ((1, 1), (5, 300), (40, 5400), (7, 0)):
        g = rng.integers(0, max(n_pairs - 1, 1), n).astype(np.int64)  # the last pair empty
        w = rng.random(n) ** 3
        values = [rng.normal(0.0, 10.0 ** rng.integers(-3, 4), n) for _ in range(3)]
        stop = rng.random(n) < 0.5
        if n > 10:
            w[:4] = [0.0, -0.0, 1e-300, 5e-324]
            values[0][:6] = [np.nan, np.inf, -np.inf, -0.0, 0.0, 1e300]
            values[1][4:8] = -0.0
        found = kernels.pair_sums(g, w, values, stop, n_pairs)
        if not n:  # no particles: numpy's bincount (int64 zeros even with weights)
            assert found is None
            continue
        with np.errstate(all="ignore"):
            want = (np.bincount(g, w, minlength=n_pairs), np.bincount(g, minlength=n_pairs),
                    [np.bincount(g, w * x, minlength=n_pairs) for x in values], [np.bincount(g, w * x * x, minlength=n_pairs) for x in values],
                    np.bincount(g, w * stop, minlength=n_pairs))
            for a, b in zip((found[0], found[1], *found[2], *found[3], found[4]), (want[0], want[1], *want[2], *want[3], want[4])):
                assert a.dtype == b.dtype and np.array_equal(a, b, equal_nan=True) and np.array_equal(np.signbit(a), np.signbit(b))
    assert kernels.pair_sums(np.array([0, 3]), np.ones(2), [np.ones(2)], np.zeros(2, bool), 3) is None  # a bin beyond the pairs


def test_beliefs_without_the_pair_sums_kernel_are_the_same(frames, scene_maps, monkeypatch):
    """The beliefs' numpy path (np.bincount field by field, where the kernel declines) publishes the same messages."""
    from stages.intentions import kernels

    part = frames[WINDOW][:12]
    compiled, _ = run(part, scene_maps)
    monkeypatch.setattr(kernels, "pair_sums", lambda *args, **kwargs: None)
    plain, _ = run(part, scene_maps)
    assert [b.encode() for b, _ in compiled] == [b.encode() for b, _ in plain]
    assert sum(len(b.vehicles) for b, _ in plain) > 10


def test_kernel_modules_name_the_numpy_rules_they_were_compiled_against():
    """numba's cache of a kernel module does not notice edits of stages/lib/numpy_rules.py, whose functions the kernels
    call: every module using it holds that file's digest, so that an edit there must edit (and so renew the cache of)
    each of them."""
    import hashlib

    import stages.lib.numpy_rules as rules
    from stages.intentions import kernels as intentions_kernels
    from stages.lib.ar import kernels as ar_kernels
    from stages.lib.markov import kernels as markov_kernels

    digest = hashlib.sha256(Path(rules.__file__).read_bytes()).hexdigest()[:16]
    for module in (intentions_kernels, ar_kernels, markov_kernels):
        assert module.NUMPY_RULES_SHA256 == digest, f"{module.__name__}: update NUMPY_RULES_SHA256 to {digest}"


def test_compiled_expected_stop_equals_the_numpy_one(frames):
    """model.expected_stop through kernels.conflict_stop (the conflicts ahead found and the products taken compiled, the
    sigmoids numpy's) gives the numpy path's P(E = stop) bit for bit, also with many conflicts per pair."""
    import dataclasses as dc

    from stages.intentions import kernels, model
    from stages.intentions.tables import VehicleInput, build_tables

    if not kernels.available():
        pytest.skip("numba not importable")
    mp = IntentionsConfig().model_params()
    rng = np.random.default_rng(29)
    conflicts = 0
    for item in frames[WINDOW][::5]:
        vehicles = [VehicleInput(v.track_id, tuple(v.corridors), int(v.lanelet_id)) for v in item.corridor_set.vehicles if v.corridors]
        relations = {(r.track_id, r.corridor_id): r for r in item.relation_set.relations} if item.relation_set is not None else {}
        if not vehicles:
            continue
        tables = build_tables(vehicles, relations, {}, lat_accels_mps2=(3.0,), brake_lookahead_mps2=2.5, curvature_smoothing_m=1.0,
                              default_speed_limit_mps=13.9, stop_offset_m=14.0)
        # and a denser copy: random conflicts on most pairs (up to 12 each, some behind, some NaN padding)
        n_c = 12
        dense_s = tables.vehicle_s_m[:, None] + rng.uniform(-20.0, 60.0, (tables.n_pairs, n_c))
        dense_s[rng.random(dense_s.shape) < 0.3] = np.nan
        dense = dc.replace(tables, conflict_s_m=dense_s, conflict_other_time_s=rng.uniform(-2.0, 8.0, dense_s.shape),
                           conflict_weight=rng.uniform(0.0, 1.0, dense_s.shape))
        for t in (tables, dense):
            n_rows, n = len(vehicles), 150
            g = t.first_pair[:, None] + rng.integers(0, t.n_slots[:, None], (n_rows, n))
            s = t.vehicle_s_m[g] + rng.normal(0.0, 15.0, (n_rows, n))
            v = np.maximum(rng.normal(5.0, 4.0, (n_rows, n)), 0.0)
            got = model.expected_stop(t, g, s, v, mp)
            want = model._expected_stop_numpy(t, g, s, v, mp)
            assert np.array_equal(got, want) and np.array_equal(np.signbit(got), np.signbit(want))
            conflicts += int(np.count_nonzero(want))
    assert conflicts > 1000


def test_cached_manoeuvres_equal_the_map_lookup_also_at_the_thresholds(frames, scene_maps):
    """`_manoeuvres_of` (cached) gives `corridor_manoeuvre`'s answer for every corridor of the sequence and for corridors
    whose vehicle sits one float step either side of each lanelet's lane-change reach and end; the cache mostly hits."""
    from stages.intentions.tables import corridor_manoeuvre, lanelet_ids_of

    config = IntentionsConfig()
    intentions = IntentionFilter(config, scene_maps=scene_maps)
    road_map = scene_maps.get(frames[0].scene, config.projection).road_map
    reach = config.lane_change_reach_m
    looked_up = 0
    for item in frames[::5]:
        corridors = [c for v in item.corridor_set.vehicles for c in v.corridors]
        moved = []
        for c in corridors[:3]:
            for start, lanelet in zip(np.asarray(c.lanelet_start_s_m, dtype=np.float64).tolist(), lanelet_ids_of(c)):
                if not road_map.has_lanelet(lanelet):
                    continue
                for edge in (start + reach, start + road_map.lanelet(lanelet).length_m):
                    moved += [dataclasses.replace(c, vehicle_s_m=float(np.nextafter(edge, toward))) for toward in (-np.inf, np.inf)]
                    moved.append(dataclasses.replace(c, vehicle_s_m=edge))
        corridors += moved
        expected = [corridor_manoeuvre(road_map, c, reach) for c in corridors]
        assert intentions._manoeuvres_of(corridors, road_map) == expected
        assert intentions._manoeuvres_of(corridors, road_map) == expected  # from the cache
        looked_up += len(corridors)
    assert looked_up > 1000
    assert len(intentions._manoeuvres) < looked_up // 4


@pytest.mark.parametrize("compiled", [True, False])
def test_streams_are_default_rngs_of_seed_frame_and_track(compiled, monkeypatch):
    """`Streams` gives every track the stream of ``np.random.default_rng([seed, frame, track])``, number for number, for
    edge entropies (0, 2**32 - 1, 2**32: one or two 32-bit words, 2**64 - 1, more than four words in all) and when its
    generators are reused for another frame; the Python loop (no numba) gives the same."""
    from stages.intentions import streams

    if not compiled:
        monkeypatch.setattr(streams, "_hash_rows_compiled", streams._hash_rows)
    make = streams.Streams()
    cases = [(0, 0, [0, 1, 2**32 - 1, 2**32, 2**64 - 1]), (3, 2**40 + 7, [12345, 7]), (2**70, 2**33, [5]), (0, 0, [])]
    for seed, frame, tracks in cases:
        generators = make(seed, frame, tracks)
        assert len(generators) == len(tracks)
        for generator, track in zip(generators, tracks):
            reference = np.random.default_rng([seed, frame, track])
            assert generator.random() == reference.random()
            assert np.array_equal(generator.standard_normal((4, 30)), reference.standard_normal((4, 30)))
            assert np.array_equal(generator.random((2, 3, 30)), reference.random((2, 3, 30)))
