"""Deterministic sample messages, one per registered schema (for golden payloads and round trips)."""

from __future__ import annotations

import numpy as np

import bus_schemas as bs


def header(frame_index: int = 7) -> bs.Header:
    return bs.Header(
        run_id="golden", frame_index=frame_index, stamp_ns=1_700_000_000_000_000_000 + frame_index * 100_000_000, producer="source",
        source_wall_ns=1_767_225_600_000_000_000 + frame_index * 100_000_000 + 123_456,
    )


def track_frame(n: int = 4) -> bs.TrackFrame:
    i = np.arange(n, dtype=np.float64)
    return bs.TrackFrame(
        header=header(),
        scene_id="0123456789abcdef",
        track_ids=np.arange(100, 100 + n, dtype=np.int64),
        agent_types=np.array([1, 1, 6, 5][:n] + [1] * max(0, n - 4), dtype=np.uint8),
        x_m=10.0 + i,
        y_m=-5.0 - 0.5 * i,
        vx_mps=np.full(n, 3.25),
        vy_mps=np.zeros(n),
        yaw_rad=np.linspace(-np.pi, np.pi, n),
        length_m=np.full(n, 4.5),
        width_m=np.full(n, 1.9),
    )


def scene_info() -> bs.SceneInfo:
    return bs.SceneInfo(
        header=header(0),
        scene_id="0123456789abcdef",
        recording="k729_2022-03-16",
        location_id="K729",
        map_name="k729_2022-03-16.osm",
        map_sha256="ab" * 32,
        projection="local_cartesian",
        origin_lat_deg=49.01160993928274,
        origin_lon_deg=8.43856470258739,
        frame_rate_hz=10.0,
        speed_limit_mps=13.88888888888889,
        n_frames=1177,
        clock="recording",
    )


def node_stats() -> bs.NodeStats:
    return bs.NodeStats(
        run_id="golden",
        node_id="corridors",
        stage="stages.corridors",
        pid=4242,
        uptime_s=12.5,
        counters={"received": 10, "processed": 9, "published": 18, "decode_errors": 1},
        issues_by_kind={"off_map": 2},
        errors_by_kind={"WrongVersion": 1},
        proc_ms_p50=1.5,
        proc_ms_p95=3.25,
        proc_ms_max=7.0,
        latency_ms_p50=2.0,
        latency_ms_p95=4.0,
        queue_depth=0,
        last_stamp_ns=1_700_000_000_700_000_000,
        e2e_ms_p50=21.5,
        e2e_ms_p95=48.25,
    )


def progress() -> bs.Progress:
    return bs.Progress(node_id="corridors", last_stamp_ns=1_700_000_000_700_000_000, last_frame_index=7, handled=8)


SAMPLES = {
    "iamp.TrackFrame": track_frame,
    "iamp.SceneInfo": scene_info,
    "iamp.NodeStats": node_stats,
    "iamp.Progress": progress,
}


def corridor_set() -> bs.CorridorSet:
    m = 6
    s = np.arange(m, dtype=np.float64) * 0.5
    cor = bs.Corridor(
        corridor_id=11,
        lanelet_ids=np.array([-1001, -1002], dtype=np.int64),
        lanelet_start_s_m=np.array([0.0, 1.5]),
        x_m=s.copy(),
        y_m=np.zeros(m),
        s_m=s,
        heading_rad=np.zeros(m),
        curvature_1pm=np.zeros(m),
        width_m=np.full(m, 3.25),
        extension_start_s_m=2.5,
        vehicle_s_m=0.75,
        vehicle_d_m=-0.25,
        speed_limit_mps=13.875,
    )
    return bs.CorridorSet(
        header=header(),
        scene_id="0123456789abcdef",
        vehicles=(
            bs.VehicleCorridors(
                track_id=100, agent_type=bs.AgentType.CAR, status=bs.MatchStatus.MATCHED, lanelet_id=-1001, match_distance_m=0.0, speed_mps=3.5, corridors=(cor,),
                vx_mps=2.5, vy_mps=2.449489742783178, accel_mps2=-0.5, standing=False, reported_speed_mps=1.75
            ),
            bs.VehicleCorridors(
                track_id=102, agent_type=bs.AgentType.PEDESTRIAN, status=bs.MatchStatus.NOT_A_VEHICLE, lanelet_id=-1, match_distance_m=-1.0, speed_mps=0.0, corridors=(),
                vx_mps=0.0, vy_mps=0.0, accel_mps2=0.0, standing=True, reported_speed_mps=1.25
            ),
        ),
    )


def relation_set() -> bs.RelationSet:
    def f(*v):
        return np.array(v, dtype=np.float64)

    rel = bs.CorridorRelations(
        track_id=100,
        corridor_id=11,
        object_track_ids=np.array([101], dtype=np.int64),
        object_types=np.array([1], dtype=np.uint8),
        object_s_m=f(20.0),
        object_d_m=f(0.25),
        object_gap_m=f(14.5),
        object_speed_mps=f(4.0),
        leader_track_id=101,
        leader_gap_m=14.5,
        leader_speed_mps=4.0,
        intersection_ids=np.array([0], dtype=np.int64),
        intersection_entry_s_m=f(30.0),
        intersection_exit_s_m=f(52.5),
        intersection_distance_m=f(29.25),
        intersection_entry_lanelet_ids=np.array([-1002], dtype=np.int64),
        conflict_track_ids=np.array([103], dtype=np.int64),
        conflict_corridor_ids=np.array([31], dtype=np.int64),
        conflict_kinds=np.array([1], dtype=np.uint8),
        conflict_s_m=f(40.0),
        conflict_other_s_m=f(12.5),
        conflict_x_m=f(40.0),
        conflict_y_m=f(0.5),
        conflict_distance_m=f(25.0),
        conflict_other_distance_m=f(7.5),
        conflict_other_speed_mps=f(3.0),
        conflict_time_s=f(8.0),
        conflict_other_time_s=f(2.5),
        conflict_priority=np.array([-1], dtype=np.int8),
        influencing_index=0,
        influencing_rule="priority_other",
        signal_group=4,
        signal_stop_s_m=27.5,
        signal_distance_m=26.75,
        signal_phase=bs.SignalPhase.RED,
        signal_held_s=12.5,
    )
    return bs.RelationSet(header=header(), scene_id="0123456789abcdef", relations=(rel,))


def signal_state() -> bs.SignalState:
    return bs.SignalState(
        header=header(),
        scene_id="0123456789abcdef",
        group_ids=np.array([1, 2, 4, 9], dtype=np.int64),
        phases=np.array([1, 3, 4, 5], dtype=np.uint8),
        held_s=np.array([12.5, 0.25, np.nan, 3.0]),
    )


SAMPLES.update({"iamp.CorridorSet": corridor_set, "iamp.RelationSet": relation_set, "iamp.SignalState": signal_state})


def corridor_predictions() -> bs.CorridorPredictions:
    k, w, nv = 3, 4, 5
    s_probs = np.array([[0.5, 0.5, 0.0, 0.0], [0.0, 0.25, 0.75, 0.0], [0.0, 0.0, 0.5, 0.375]], dtype=np.float32)
    v_probs = np.zeros((k, nv), dtype=np.float32)
    v_probs[:, 2] = s_probs.sum(axis=1)
    steps = np.array([0.4, 0.8, 1.2])
    pred = bs.CorridorPrediction(
        track_id=100,
        corridor_id=11,
        probability=0.5,
        vehicle_s_m=5.0,
        s_first_m=5.0,
        s_probs=s_probs,
        v_probs=v_probs,
        outside_mass=np.array([0.0, 0.0, 0.125], dtype=np.float32),
        mean_x_m=np.array([1.0, 2.25, 3.5]),
        mean_y_m=np.array([-0.5, -0.5, -0.25]),
        mean_s_m=np.array([6.0, 7.25, 8.5]),
        x_at_mean_s_m=np.array([1.0, 2.25, 3.5]),
        y_at_mean_s_m=np.array([-0.5, -0.5, -0.5]),
    )
    assert pred.s_probs.shape == (k, w)
    return bs.CorridorPredictions(
        header=header(), scene_id="0123456789abcdef", mode="baseline", step_times_s=steps, ds_m=1.0, dv_mps=0.5, predictions=(pred,),
        shard="0/2",  # a shard's own output (v3): only its vehicles
    )


def motion_grid() -> bs.MotionGrid:
    def step(rows, cols, values):
        return bs.GridStep(
            rows=np.array(rows, dtype=np.int32), cols=np.array(cols, dtype=np.int32), values=np.array(values, dtype=np.float32)
        )

    return bs.MotionGrid(
        header=header(),
        scene_id="0123456789abcdef",
        mode="baseline",
        distribution="interval",
        origin_x_m=-20.0,
        origin_y_m=-10.5,
        cell_m=0.5,
        n_rows=40,
        n_cols=80,
        min_value=1e-5,
        step_times_s=np.array([0.4, 0.8]),
        steps=(step([20, 20, 21], [41, 42, 42], [0.5, 0.25, 0.125]), step([20], [45], [0.75])),
        missing_shards=("1/2",),  # a fused frame that lacks a shard's vehicles (v3)
    )


SAMPLES.update({"iamp.CorridorPredictions": corridor_predictions, "iamp.MotionGrid": motion_grid})


def intention_belief() -> bs.IntentionBelief:
    def corridor(corridor_id, probability, manoeuvre, count, s, v, p_stop, stop_distance):
        return bs.CorridorBelief(
            corridor_id=corridor_id,
            probability=probability,
            manoeuvre=manoeuvre,
            particle_count=count,
            s_mean_m=s,
            s_std_m=0.25,
            v_mean_mps=v,
            v_std_mps=0.5,
            a_mean_mps2=-0.75,
            a_std_mps2=0.5,
            p_stop=p_stop,
            stop_distance_m=stop_distance,
        )

    vehicle = bs.VehicleBelief(
        track_id=100,
        corridors=(
            corridor(11, 0.75, bs.Manoeuvre.TURN_LEFT, 200, 5.25, 3.5, 0.5, 24.0),
            corridor(12, 0.25, bs.Manoeuvre.GO_STRAIGHT, 100, 5.0, 4.0, 0.25, float("nan")),
        ),
        p_stop=0.4375,
        p_expected_stop=0.125,
        p_violation=0.375,
        p_lane_change=0.0,
        expected_manoeuvre=bs.Manoeuvre.TURN_LEFT,
        intersection_distance_m=24.0,
        effective_sample_size=212.5,
        particle_count=300,
    )
    return bs.IntentionBelief(header=header(), scene_id="0123456789abcdef", vehicles=(vehicle,))


SAMPLES.update({"iamp.IntentionBelief": intention_belief})


def acceleration_profiles() -> bs.AccelerationProfiles:
    edges = np.linspace(-3.0, 2.0, 11)
    probs = np.zeros((10, 10), dtype=np.float32)
    probs[:, 5] = 0.75
    probs[:, 4] = 0.25
    profile = bs.AccelerationProfile(
        track_id=7,
        corridor_id=2,
        history_steps=23,
        accel_mps2=np.linspace(-0.5, 0.25, 40).astype(np.float32),
        chunk_mean_mps2=np.linspace(-0.45, 0.2, 10).astype(np.float32),
        chunk_sigma_mps2=np.linspace(0.3, 1.0, 10).astype(np.float32),
        input_probs=probs,
    )
    return bs.AccelerationProfiles(
        header=header(), scene_id="0123456789abcdef", model="ar_taf_bw.pt@0123456789ab", step_s=0.1, chunk_s=0.4,
        input_edges_mps2=edges, profiles=(profile,),
    )


SAMPLES.update({"iamp.AccelerationProfiles": acceleration_profiles})
