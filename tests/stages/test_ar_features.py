"""Tests of the AR features (stages.lib.ar.features) on synthetic corridors and on real K729 frames.

Real frames: the first frames of the embedded sequence 013 through the
in-process chain (TrackPlayer → CorridorBuilder → RelationExtractor), fed to
one FeatureTracker as the online stage and the data set builder do. Every
expected value is computed here independently from the relations or the
corridor arrays.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from bus_schemas import AgentType, Corridor, CorridorSet, Header, MatchStatus, RelationSet, TrackFrame, VehicleCorridors
from stages.lib.ar.features import (
    ACCEL,
    FEATURE_NAMES,
    HISTORY_STEPS,
    SPEED,
    FeatureConfig,
    FeatureTracker,
    causal_acceleration,
    curvature_integrals,
    corridor_features,
    curvature_rows,
    pair_features,
)
from stages.corridors import CorridorBuilder, CorridorsConfig, SceneMaps
from stages.lib.datasets import DEFAULT_DATA_DIR
from stages.relations import RelationExtractor, RelationsConfig, most_influencing
from stages.tracks_source.core import TrackPlayer, TracksSourceConfig

F = {name: i for i, name in enumerate(FEATURE_NAMES)}
STEP_NS = 100_000_000
N_REAL_FRAMES = 400


# --------------------------------------------------------------------------- synthetic corridors


def corridor(corridor_id: int = 7, *, kappa=None, length_m: float = 80.0, vehicle_s_m: float = 5.0, step_m: float = 0.5) -> Corridor:
    """A corridor sampled every `step_m` whose curvature is kappa(s) (s from the corridor start), geometry integrated."""
    s = np.arange(0.0, length_m + 1e-9, step_m)
    k = np.zeros_like(s) if kappa is None else np.asarray(kappa(s), dtype=np.float64)
    heading = np.concatenate([[0.0], np.cumsum(0.5 * (k[1:] + k[:-1]) * np.diff(s))])
    x = np.concatenate([[0.0], np.cumsum(np.cos(heading[:-1]) * np.diff(s))])
    y = np.concatenate([[0.0], np.cumsum(np.sin(heading[:-1]) * np.diff(s))])
    return Corridor(
        corridor_id=corridor_id, lanelet_ids=np.array([1], np.int64), lanelet_start_s_m=np.array([0.0]),
        x_m=x, y_m=y, s_m=s, heading_rad=heading, curvature_1pm=k, width_m=np.full_like(s, 3.5),
        extension_start_s_m=float(s[-1]), vehicle_s_m=vehicle_s_m, vehicle_d_m=0.0, speed_limit_mps=13.9,
    )


def corridor_set(stamp_ns: int, vehicles) -> CorridorSet:
    return CorridorSet(header=Header(run_id="t", frame_index=0, stamp_ns=stamp_ns, producer="test"), scene_id="s", vehicles=tuple(vehicles))


def vehicle(track_id: int, speed: float, corridors=None, status=MatchStatus.MATCHED) -> VehicleCorridors:
    corridors = (corridor(),) if corridors is None else tuple(corridors)
    return VehicleCorridors(track_id=track_id, agent_type=AgentType.CAR, status=status, lanelet_id=1, match_distance_m=0.0,
                            speed_mps=speed, corridors=corridors)


def test_feature_names():
    assert len(FEATURE_NAMES) == 23 and len(set(FEATURE_NAMES)) == 23
    assert FEATURE_NAMES[0] == "accel_mps2" and FEATURE_NAMES[-1] == "speed_mps"
    assert sum(n.startswith("curv_") for n in FEATURE_NAMES) == 12


def test_curvature_integrals_of_circular_arcs():
    # vehicle at s = 5; a left arc of radius 20 m from 20 m to 40 m ahead, a right arc of radius 10 m from 45 to 50 m ahead
    left, right = 1 / 20.0, -1 / 10.0
    c = corridor(kappa=lambda s: np.where((s >= 25) & (s <= 45), left, 0.0) + np.where((s >= 50) & (s <= 55), right, 0.0), length_m=90.0)
    curv = curvature_integrals(c)
    half_sample = 0.5 * 0.5 * max(left, -right)  # the trapezoid ramps over one 0.5 m sample at each end of an arc
    expected_pos = [0.0, 0.0, 10 * left, 10 * left, 0.0, 0.0]
    expected_neg = [0.0, 0.0, 0.0, 0.0, 5 * right, 0.0]
    np.testing.assert_allclose(curv[:, 0], expected_pos, atol=half_sample + 1e-9)
    np.testing.assert_allclose(curv[:, 1], expected_neg, atol=half_sample + 1e-9)
    assert math.isclose(curv[:, 0].sum(), 20 * left, abs_tol=2 * half_sample)  # the whole arc: length / radius
    assert math.isclose(curv[:, 1].sum(), 5 * right, abs_tol=2 * half_sample)
    assert np.all(curv[:, 0] >= 0) and np.all(curv[:, 1] <= 0)


def test_curvature_beyond_the_corridor_end_is_zero():
    c = corridor(kappa=lambda s: np.full_like(s, 0.1), length_m=30.0, vehicle_s_m=5.0)  # 25 m ahead of the vehicle
    curv = curvature_integrals(c)
    np.testing.assert_allclose(curv[:, 0], [1.0, 1.0, 0.5, 0.0, 0.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(curv[:, 1], 0.0)


def test_curvature_features_in_batch_columns():
    c = corridor(kappa=lambda s: np.where(s >= 15, -0.05, 0.0), length_m=90.0, vehicle_s_m=5.0)
    tracker = FeatureTracker()
    tracker.update(corridor_set(0, [vehicle(1, 5.0, [c])]), None)
    _keys, x, _mask = tracker.batch(corridor_set(0, [vehicle(1, 5.0, [c])]))
    curv = curvature_integrals(c)
    for seg in range(6):
        name = f"{seg * 10:02d}_{(seg + 1) * 10:02d}m"
        assert x[0, -1, F[f"curv_pos_{name}"]] == pytest.approx(curv[seg, 0], abs=1e-6)
        assert x[0, -1, F[f"curv_neg_{name}"]] == pytest.approx(curv[seg, 1], abs=1e-6)
    assert x[0, -1, F["curv_neg_10_20m"]] == pytest.approx(-0.5, abs=0.02)


def _curvature_alone(c: Corridor, lookahead_m: float = 60.0, n_segments: int = 6) -> np.ndarray:
    """The integrals of one corridor written out directly (nan_to_num, trapezoid cumsum, np.interp at the bounds)."""
    s = np.asarray(c.s_m, dtype=np.float64)
    kappa = np.nan_to_num(np.asarray(c.curvature_1pm, dtype=np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    out = np.zeros((n_segments, 2))
    if s.size < 2 or not math.isfinite(c.vehicle_s_m):
        return out
    bounds = c.vehicle_s_m + np.linspace(0.0, lookahead_m, n_segments + 1)
    for col, part in enumerate((np.maximum(kappa, 0.0), np.minimum(kappa, 0.0))):
        cumulative = np.concatenate([[0.0], np.cumsum(0.5 * (part[1:] + part[:-1]) * np.diff(s))])
        out[:, col] = np.diff(np.interp(bounds, s, cumulative))
    return out


def test_curvature_rows_of_a_batch_are_exactly_each_corridor_alone():
    rng = np.random.default_rng(5)
    wavy = [corridor(k, kappa=lambda s, a=rng.normal(0, 0.05), f=rng.uniform(0.02, 0.3): a * np.sin(f * s),
                     length_m=float(rng.uniform(3.0, 120.0)), vehicle_s_m=float(rng.uniform(-5.0, 40.0)), step_m=float(rng.uniform(0.3, 1.5)))
            for k in range(12)]
    odd = corridor(90, kappa=lambda s: np.where(s > 10, np.nan, 0.05))
    odd.curvature_1pm[3] = np.inf
    one_sample = corridor(91, length_m=0.0)
    lost = corridor(92, kappa=lambda s: np.full_like(s, 0.03), vehicle_s_m=math.nan)
    corridors = [*wavy[:5], odd, one_sample, *wavy[5:], lost]
    rows = curvature_rows(corridors)
    assert rows.shape == (len(corridors), 6, 2)
    for c, row in zip(corridors, rows):
        assert np.array_equal(row, _curvature_alone(c)), c.corridor_id  # bit for bit: the batch changes no figure
    assert np.any(rows[0] != 0.0) and np.all(rows[corridors.index(lost)] == 0.0)


def test_pair_features_of_a_batch_equal_each_pair_alone(real):
    cfg = FeatureConfig()
    with_leaders = 0  # (the influencer columns from a batch: test_influencer_features_follow_most_influencing_in_a_crossing_scene)
    for cs, rs, _ in real[::4]:
        rel = {(r.track_id, r.corridor_id): r for r in rs.relations}
        pairs = [(c, rel.get((v.track_id, c.corridor_id)), float(v.speed_mps)) for v in cs.vehicles if v.status == MatchStatus.MATCHED for c in v.corridors]
        if not pairs:
            continue
        with_leaders += any(r is not None and r.leader_track_id >= 0 for _c, r, _s in pairs)
        batch = pair_features(*zip(*pairs), cfg)
        for row, (c, r, speed) in zip(batch, pairs):
            assert np.array_equal(row, pair_features([c], [r], [speed], cfg)[0])
            assert np.array_equal(row[:12].reshape(6, 2), _curvature_alone(c))
    assert with_leaders > 5


def test_a_mismatched_curvature_array_fails_only_its_pair():
    good, bad = corridor(7), corridor(8)
    bad = Corridor(**{**{f: getattr(bad, f) for f in bad.__dataclass_fields__}, "curvature_1pm": bad.curvature_1pm[:-3]})
    tracker = FeatureTracker()
    cs = corridor_set(0, [vehicle(1, 3.0, [good, bad]), vehicle(2, 4.0)])
    issues = tracker.update(cs, None)
    assert [(i.kind, i.agent_id) for i in issues if i.kind != "no_relations"] == [("pair_failed", 1)]
    assert tracker.batch(cs)[0] == [(1, 7), (2, 7)]


def test_a_row_replaced_within_its_step_drops_the_corridors_it_lacks():
    straight, turn = corridor(7), corridor(8, kappa=lambda s: np.full_like(s, 0.02))
    later_turn = corridor(8, kappa=lambda s: np.full_like(s, 0.04))
    tracker = FeatureTracker()
    tracker.update(corridor_set(0, [vehicle(1, 3.0, [straight, turn])]), None)
    tracker.update(corridor_set(STEP_NS // 3, [vehicle(1, 3.0, [straight])]), None)  # same step: replaces the row without 8
    cs = corridor_set(STEP_NS, [vehicle(1, 3.0, [straight, later_turn])])
    tracker.update(cs, None)
    keys, x, mask = tracker.batch(cs)
    assert keys == [(1, 7), (1, 8)] and mask[1, -2:].all()
    col = F["curv_pos_00_10m"]
    np.testing.assert_allclose(x[1, -2:, col], 0.4, atol=1e-6)  # step 0 holds no corridor 8 any more: back-filled from step 1


def test_rows_older_than_the_history_are_not_used():
    tracker = FeatureTracker()
    for k in range(0, 46, 9):  # rows at steps 0, 9, ..., 45 (gaps below the 1 s timeout)
        cs = corridor_set(k * STEP_NS, [vehicle(3, float(k))])
        tracker.update(cs, None)
    _keys, x, mask = tracker.batch(cs)
    assert np.flatnonzero(mask[0]).tolist() == [3, 12, 21, 30, 39]  # steps 9 .. 45 of the window 6 .. 45
    np.testing.assert_array_equal(x[0, :, SPEED], np.repeat(np.float32([9, 18, 27, 36, 45]), [12, 9, 9, 9, 1]))
    # an earlier frame's batch sees only the rows the track still keeps (steps after 45 - 40): step 9, not step 0
    _keys, x, mask = tracker.batch(corridor_set(10 * STEP_NS, [vehicle(3, 0.0)]))
    assert np.flatnonzero(mask[0]).tolist() == [38]
    np.testing.assert_array_equal(x[0, :, SPEED], 9.0)


# --------------------------------------------------------------------------- history, mask, issues


def test_short_history_is_padded_and_masked():
    tracker = FeatureTracker()
    for k in range(5):
        cs = corridor_set(k * STEP_NS, [vehicle(3, 2.0 + 0.1 * k)])
        assert [i.kind for i in tracker.update(cs, None)] == ["no_relations"]
    keys, x, mask = tracker.batch(cs)
    assert keys == [(3, 7)]
    assert x.shape == (1, HISTORY_STEPS, len(FEATURE_NAMES)) and x.dtype == np.float32 and mask.dtype == bool
    assert mask[0].tolist() == [False] * 35 + [True] * 5
    np.testing.assert_allclose(x[0, :36, SPEED], 2.0)  # padding repeats the oldest real row
    np.testing.assert_allclose(x[0, 35:, SPEED], [2.0, 2.1, 2.2, 2.3, 2.4], rtol=1e-6)


def test_first_frame_gives_one_real_step_and_zero_acceleration():
    tracker = FeatureTracker()
    cs = corridor_set(7 * STEP_NS, [vehicle(3, 4.0)])
    tracker.update(cs, None)
    _keys, x, mask = tracker.batch(cs)
    assert mask[0].sum() == 1 and mask[0, -1]
    assert np.all(x[0, :, ACCEL] == 0.0) and np.all(x[0, :, SPEED] == 4.0)


def test_nan_speed_gives_an_issue_not_an_exception():
    tracker = FeatureTracker()
    issues = tracker.update(corridor_set(0, [vehicle(1, math.nan), vehicle(2, 3.0)]), None)
    assert [i.kind for i in issues if i.agent_id == 1] == ["nan_state"]
    assert tracker.issue_counts["nan_state"] == 1
    keys, x, _mask = tracker.batch(corridor_set(0, [vehicle(1, math.nan), vehicle(2, 3.0)]))
    assert keys == [(2, 7)] and np.all(np.isfinite(x))  # no row at all: left out
    # with history, a NaN frame is a masked step filled from the previous row
    tracker.update(corridor_set(STEP_NS, [vehicle(2, 3.0)]), None)
    issues = tracker.update(corridor_set(2 * STEP_NS, [vehicle(2, math.inf)]), None)
    assert [i.kind for i in issues if i.agent_id == 2] == ["nan_state"]
    keys, x, mask = tracker.batch(corridor_set(2 * STEP_NS, [vehicle(2, math.inf)]))
    assert keys == [(2, 7)] and mask[0, -3:].tolist() == [True, True, False]
    assert x[0, -1, SPEED] == 3.0 and np.all(np.isfinite(x))


def test_a_corridor_in_no_row_takes_its_geometry_now_for_every_step():
    straight, turn = corridor(7), corridor(9, kappa=lambda s: np.full_like(s, 0.02))
    tracker = FeatureTracker()
    for k in range(3):
        tracker.update(corridor_set(k * STEP_NS, [vehicle(1, 2.0), vehicle(2, 3.0 + k)]), None)
    cs = corridor_set(3 * STEP_NS, [vehicle(1, 2.0), vehicle(2, math.nan, [turn, straight])])  # no row for 2 this frame
    tracker.update(cs, None)
    keys, x, mask = tracker.batch(cs)
    assert keys == [(1, 7), (2, 9), (2, 7)]
    expected = corridor_features(turn, None, 5.0, FeatureConfig())  # relations absent, the speed of its last row
    np.testing.assert_array_equal(x[1][:, 1:22], np.broadcast_to(expected.astype(np.float32), (HISTORY_STEPS, 21)))
    assert x[1, -1, F["curv_pos_00_10m"]] == pytest.approx(0.2, abs=1e-6)
    np.testing.assert_array_equal(x[2][:, 1:13], x[0][:, 1:13])  # 7 from its rows: the same straight corridor as vehicle 1's
    np.testing.assert_array_equal(x[2][:, F["leader_speed_mps"]], np.float32([3.0] * 37 + [4.0, 5.0, 5.0]))  # no leader: own speed
    assert mask[1].tolist() == mask[2].tolist() == [False] * 36 + [True] * 3 + [False]
    np.testing.assert_array_equal(x[1][:, SPEED], np.float32([3.0] * 37 + [4.0, 5.0, 5.0]))


def test_nan_corridor_values_give_an_issue():
    bad = corridor(kappa=lambda s: np.where(s > 20, np.nan, 0.0))
    tracker = FeatureTracker()
    tracker.update(corridor_set(0, [vehicle(1, 3.0, [bad])]), None)
    _keys, x, _mask = tracker.batch(corridor_set(0, [vehicle(1, 3.0, [bad])]))
    assert np.all(np.isfinite(x))  # NaN curvature counts as straight


def test_skipped_stamps_leave_masked_steps_and_acceleration_uses_stamps():
    tracker = FeatureTracker(FeatureConfig(accel_window_s=1.0))
    stamps = [0, 1, 2, 4, 5, 6, 7, 9, 10]  # steps 3 and 8 missing
    for k in stamps:
        cs = corridor_set(k * STEP_NS, [vehicle(1, 5.0 + 2.0 * 0.1 * k)])  # 2 m/s² in time, whatever the frame count
        tracker.update(cs, None)
    _keys, x, mask = tracker.batch(cs)
    real = mask[0, -11:]
    assert real.tolist() == [k in stamps for k in range(11)]
    assert x[0, -1, ACCEL] == pytest.approx(2.0, abs=1e-6)
    assert x[0, -3, SPEED] == pytest.approx(x[0, -4, SPEED])  # step 8 repeats step 7


def test_causal_acceleration():
    t = np.arange(0, 11) * STEP_NS
    assert causal_acceleration(t, 3.0 - 1.5 * t * 1e-9, 1.0) == pytest.approx(-1.5)
    assert causal_acceleration(t[:2], np.array([1.0, 2.0]), 1.0) == 0.0  # too few samples
    assert causal_acceleration(t[:4], np.array([1.0, 2.0, 3.0, 4.0]), 1.0) == 0.0  # 0.3 s < half the window
    noisy = 3.0 + 0.3 * t * 1e-9 + np.random.default_rng(0).normal(0.0, 1.0, t.size)
    assert abs(causal_acceleration(t, noisy, 1.0, shrink=True)) < abs(causal_acceleration(t, noisy, 1.0))


def test_features_are_causal():
    speeds = [4.0 + math.sin(0.3 * k) for k in range(60)]
    a, b = FeatureTracker(), FeatureTracker()
    for k in range(45):
        a.update(corridor_set(k * STEP_NS, [vehicle(1, speeds[k])]), None)
    for k in range(60):
        b.update(corridor_set(k * STEP_NS, [vehicle(1, speeds[k] if k < 45 else 0.0)]), None)
        if k == 44:
            np.testing.assert_array_equal(a.batch(corridor_set(k * STEP_NS, [vehicle(1, speeds[k])]))[1],
                                          b.batch(corridor_set(k * STEP_NS, [vehicle(1, speeds[k])]))[1])


def test_tracks_unseen_for_more_than_a_second_are_forgotten():
    tracker = FeatureTracker()
    tracker.update(corridor_set(0, [vehicle(1, 3.0), vehicle(2, 3.0)]), None)
    tracker.update(corridor_set(10 * STEP_NS, [vehicle(2, 3.0)]), None)
    assert tracker.tracked_ids == {1, 2}
    tracker.update(corridor_set(11 * STEP_NS, [vehicle(2, 3.0)]), None)
    assert tracker.tracked_ids == {2}
    issues = tracker.update(corridor_set(5 * STEP_NS, [vehicle(2, 3.0)]), None)
    assert "stamp_backwards" in [i.kind for i in issues]


def test_a_new_corridor_takes_its_first_value_for_the_past():
    straight = corridor(7)
    turn = corridor(8, kappa=lambda s: np.full_like(s, 0.02))
    tracker = FeatureTracker()
    for k in range(3):
        tracker.update(corridor_set(k * STEP_NS, [vehicle(1, 3.0, [straight])]), None)
    for k in range(3, 5):
        tracker.update(corridor_set(k * STEP_NS, [vehicle(1, 3.0, [straight, turn])]), None)
    keys, x, mask = tracker.batch(corridor_set(4 * STEP_NS, [vehicle(1, 3.0, [straight, turn])]))
    assert keys == [(1, 7), (1, 8)]
    assert mask[1, -5:].all()
    col = F["curv_pos_00_10m"]
    np.testing.assert_allclose(x[1, -5:, col], 0.2, atol=1e-6)  # back-filled from the turn's first row
    np.testing.assert_allclose(x[0, -5:, col], 0.0)


def test_pairs_restricts_the_batch():
    tracker = FeatureTracker()
    cs = corridor_set(0, [vehicle(1, 3.0, [corridor(7), corridor(8)]), vehicle(2, 3.0)])
    tracker.update(cs, None)
    assert tracker.batch(cs)[0] == [(1, 7), (1, 8), (2, 7)]
    assert tracker.batch(cs, pairs={(1, 8)})[0] == [(1, 8)]


# --------------------------------------------------------------------------- real frames


@pytest.fixture(scope="module")
def real_scene():
    """(scene, scene_maps, road_map) of sequence 013."""
    if not (DEFAULT_DATA_DIR / "maps").is_dir():
        pytest.skip("embedded TAF-BW data not found")
    scene_maps = SceneMaps()
    player = TrackPlayer.open(TracksSourceConfig(), run_id="test", producer="tracks")
    scene = next(iter(player))[1].outputs["scene"]
    return scene, scene_maps, scene_maps.get(scene).road_map


@pytest.fixture(scope="module")
def real():
    """(corridor_set, relation_set, batch) per frame of the first frames of sequence 013, one FeatureTracker throughout."""
    if not (DEFAULT_DATA_DIR / "maps").is_dir():
        pytest.skip("embedded TAF-BW data not found")
    scene_maps = SceneMaps()
    player = TrackPlayer.open(TracksSourceConfig(), run_id="test", producer="tracks")
    builder = CorridorBuilder(CorridorsConfig(), scene_maps=scene_maps)
    extractor = RelationExtractor(RelationsConfig(), scene_maps=scene_maps)
    tracker = FeatureTracker()
    scene, out = None, []
    for n, (_stamp, result) in enumerate(player):
        if n >= N_REAL_FRAMES:
            break
        scene = result.outputs.get("scene", scene)
        frame = result.outputs["track_frame"]
        cs, _ = builder.process(frame, scene)
        rs, _ = extractor.process(frame, cs, scene)
        assert tracker.update(cs, rs, frame) == []
        out.append((cs, rs, tracker.batch(cs)))
    return out


def _relation_pairs(real):
    for cs, rs, (keys, x, mask) in real:
        rel = {(r.track_id, r.corridor_id): r for r in rs.relations}
        speeds = {v.track_id: v.speed_mps for v in cs.vehicles}
        for b, key in enumerate(keys):
            yield rel[key], speeds[key[0]], x[b], mask[b]


def test_real_batches_are_finite_and_cover_every_matched_pair(real):
    for cs, _rs, (keys, x, mask) in real:
        expected = [(v.track_id, c.corridor_id) for v in cs.vehicles if v.status == MatchStatus.MATCHED for c in v.corridors]
        assert keys == expected
        assert np.all(np.isfinite(x)) and x.shape == (len(keys), HISTORY_STEPS, len(FEATURE_NAMES))
        assert np.all(mask[:, -1])


def test_leader_features_equal_the_relations(real):
    with_leader = without = 0
    for r, speed, x, _mask in _relation_pairs(real):
        if r.leader_track_id >= 0:
            with_leader += 1
            assert x[-1, F["leader_gap_m"]] == pytest.approx(min(max(r.leader_gap_m, 0.0), 100.0), abs=1e-4)
            assert x[-1, F["leader_speed_mps"]] == pytest.approx(r.leader_speed_mps, abs=1e-4)
        else:
            without += 1
            assert x[-1, F["leader_gap_m"]] == 100.0
            assert x[-1, F["leader_speed_mps"]] == pytest.approx(speed, abs=1e-4)
    assert with_leader > 0 and without > 0


def test_intersection_distance_equals_the_relations(real):
    seen = 0
    for r, _speed, x, _mask in _relation_pairs(real):
        if len(r.intersection_distance_m):
            seen += 1
            q = int(np.argmin(r.intersection_entry_s_m))
            assert x[-1, F["intersection_distance_m"]] == pytest.approx(np.clip(r.intersection_distance_m[q], -10, 100), abs=1e-4)
        else:
            assert x[-1, F["intersection_distance_m"]] == 100.0
    assert seen > 0


def test_influencer_features_are_absent_without_conflicts(real):
    # sequence 013 has no crossing conflicts within the horizon: every influencer is absent
    for r, _speed, x, _mask in _relation_pairs(real):
        if len(most_influencing(r, 2)) == 0:
            for k in (1, 2):
                assert (x[-1, F[f"infl{k}_distance_m"]], x[-1, F[f"infl{k}_speed_mps"]], x[-1, F[f"infl{k}_priority"]]) == (100.0, 0.0, 0.0)


NORTH_LEFT_TURN = -335558  # K729: from the north, turns left; yields to the oncoming straight lanes
ONCOMING_STRAIGHT_RIGHT_LANE = -335552
ONCOMING_STRAIGHT_LEFT_LANE = -335550
EAST_LEFT_TURN = -335540  # yields to the north left turn


def test_influencer_features_follow_most_influencing_in_a_crossing_scene(real_scene):
    """A left turner from the north and three crossing cars placed on the real lanelets (as in test_relations)."""
    scene, scene_maps, road_map = real_scene
    placed = [(1, NORTH_LEFT_TURN, 8.0, 5.0), (2, ONCOMING_STRAIGHT_RIGHT_LANE, 10.0, 1.5),
              (3, ONCOMING_STRAIGHT_LEFT_LANE, 10.0, 5.0), (4, EAST_LEFT_TURN, 5.0, 4.6)]
    rows = []
    for track_id, lanelet_id, s_m, speed in placed:
        line = road_map.lanelet(lanelet_id).centreline
        x, y = line.to_xy(s_m)[0]
        rows.append((track_id, float(x), float(y), float(np.atleast_1d(line.heading_at(s_m))[0]), speed))
    frame = TrackFrame(
        header=Header(run_id="t", frame_index=0, stamp_ns=1_000_000_000, producer="t"), scene_id=scene.scene_id,
        track_ids=np.array([r[0] for r in rows], np.int64), agent_types=np.full(len(rows), int(AgentType.CAR), np.uint8),
        x_m=np.array([r[1] for r in rows]), y_m=np.array([r[2] for r in rows]),
        vx_mps=np.array([r[4] * math.cos(r[3]) for r in rows]), vy_mps=np.array([r[4] * math.sin(r[3]) for r in rows]),
        yaw_rad=np.array([r[3] for r in rows]), length_m=np.full(len(rows), 4.6), width_m=np.full(len(rows), 2.0),
    )
    cs, _ = CorridorBuilder(CorridorsConfig(), scene_maps=scene_maps).process(frame, scene)
    rs, _ = RelationExtractor(RelationsConfig(), scene_maps=scene_maps).process(frame, cs, scene)
    tracker = FeatureTracker()
    assert tracker.update(cs, rs, frame) == []
    keys, x, _mask = tracker.batch(cs)
    relations = {(r.track_id, r.corridor_id): r for r in rs.relations}
    priorities = set()
    for b, key in enumerate(keys):
        r = relations[key]
        chosen = most_influencing(r, 2).tolist()
        for k in (1, 2):
            got = (x[b, -1, F[f"infl{k}_distance_m"]], x[b, -1, F[f"infl{k}_speed_mps"]], x[b, -1, F[f"infl{k}_priority"]])
            if len(chosen) >= k:
                c = chosen[k - 1]
                assert got[0] == pytest.approx(np.clip(r.conflict_other_distance_m[c], -10, 100), abs=1e-4)
                assert got[1] == pytest.approx(r.conflict_other_speed_mps[c], abs=1e-4)
                assert got[2] == -float(r.conflict_priority[c])  # +1: the other has right of way
                if key[0] == 1:
                    priorities.add(got[2])
            else:
                assert got == (100.0, 0.0, 0.0)
    assert 1.0 in priorities  # the oncoming straight traffic has right of way over the left turner


def test_relations_missing_gives_absent_values(real):
    cs, _rs, _batch = real[-1]
    tracker = FeatureTracker()
    issues = tracker.update(cs, None)
    assert [i.kind for i in issues] == ["no_relations"]
    _keys, x, _mask = tracker.batch(cs)
    assert np.all(x[:, -1, F["leader_gap_m"]] == 100.0) and np.all(x[:, -1, F["infl1_priority"]] == 0.0)
    issues = tracker.update(cs, RelationSet(header=Header(run_id="t", frame_index=0, stamp_ns=cs.header.stamp_ns + 1, producer="x"),
                                            scene_id="s", relations=()))
    assert [i.kind for i in issues] == ["stamp_mismatch"]


def test_compiled_curvature_rows_equal_the_numpy_rows():
    """stages.lib.ar.kernels gives _curvature_rows_numpy's integrals bit for bit (signs of zeros too): wavy and straight
    corridors, non-finite and −0.0 curvatures, the vehicle before, inside and past the corridor, bounds on the samples
    themselves; corridors whose arc length does not increase strictly are left to numpy (the result is the same)."""
    from dataclasses import replace

    from stages.lib.ar import kernels
    from stages.lib.ar.features import _curvature_rows_numpy, _segment_bounds

    if not kernels.available():
        pytest.skip("numba not importable")
    rng = np.random.default_rng(17)
    corridors = []
    for k in range(60):
        c = corridor(k, kappa=lambda s, a=rng.normal(0, 0.05), f=rng.uniform(0.02, 0.3): a * np.sin(f * s),
                     length_m=float(rng.uniform(0.0, 120.0)), vehicle_s_m=float(rng.choice([rng.uniform(-80.0, 130.0), 0.0, 10.0, 20.5])),
                     step_m=float(rng.choice([0.5, rng.uniform(0.3, 1.5)])))
        if k % 7 == 0:
            c.curvature_1pm[::3] = -0.0
        if k % 11 == 0 and len(c.s_m) > 4:
            c.curvature_1pm[:3] = [np.nan, np.inf, -np.inf]
        corridors.append(c)
    flat = corridor(70, kappa=lambda s: np.where(s < 20, -0.0, 0.0))
    stuck = corridor(71, kappa=lambda s: 0.02 * np.ones_like(s))
    stuck.s_m[5] = stuck.s_m[4]  # not strictly increasing: numpy's rows
    lost = corridor(72, vehicle_s_m=math.nan)
    corridors += [flat, stuck, lost, replace(flat, corridor_id=73, vehicle_s_m=-0.0)]
    s_parts = [np.asarray(c.s_m, np.float64) for c in corridors]
    k_parts = [np.asarray(c.curvature_1pm, np.float64) for c in corridors]
    vehicle_s = np.array([c.vehicle_s_m for c in corridors])
    got = np.zeros((len(corridors), 6, 2))
    done = kernels.curvature_rows(s_parts, k_parts, vehicle_s, _segment_bounds(60.0, 6), got)
    want = _curvature_rows_numpy(s_parts, k_parts, vehicle_s, 60.0, 6)
    assert not done[corridors.index(stuck)] and done.sum() == len(corridors) - 1
    assert np.array_equal(got[done], want[done]) and np.array_equal(np.signbit(got[done]), np.signbit(want[done]))
    rows = curvature_rows(corridors)  # the public function: kernel rows and numpy rows together
    assert np.array_equal(rows, want) and np.array_equal(np.signbit(rows), np.signbit(want))
    assert np.any(want[:60] != 0.0)


def test_compiled_causal_acceleration_equals_the_numpy_one(monkeypatch):
    """kernels.causal_slope (numpy's pairwise sums and means) gives causal_acceleration's numpy slope bit for bit: jittered
    and skipped stamps, histories shorter and longer than the window (up to the tracker's 64 samples), NaN speeds."""
    from stages.lib.ar import kernels

    if not kernels.available():
        pytest.skip("numba not importable")
    rng = np.random.default_rng(23)
    cases = []
    for trial in range(400):
        n = int(rng.integers(1, 65))
        stamps = np.cumsum(rng.choice([100_000_000, 100_000_000, 200_000_000, 99_999_000, 0], n)) + int(rng.integers(0, 10**12))
        speeds = rng.uniform(0.0, 15.0, n) + rng.normal(0, 0.3, n)
        if trial % 17 == 0:
            speeds[int(rng.integers(0, n))] = np.nan
        cases.append((stamps.astype(np.int64), speeds, float(rng.choice([1.0, 0.5, 2.0, 0.3]))))
    got = [causal_acceleration(t, v, w) for t, v, w in cases]
    monkeypatch.setattr(kernels, "causal_slope", lambda *args: None)
    want = [causal_acceleration(t, v, w) for t, v, w in cases]
    assert np.array_equal(np.array(got), np.array(want), equal_nan=True)
    assert sum(g != 0.0 for g in got) > 200
