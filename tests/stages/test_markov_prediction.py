"""The markov_prediction stage: λ pieces, the batched chain, the baselines, the motion grid and the messages."""

from __future__ import annotations

import math

import numpy as np
import pytest

import bus_schemas as bs
from stages.lib.markov import InputPerState, MarkovGridConfig, MarkovPropagator, build_stencils, gamma_from_priority, initial_state, psi_matrix
from stages.markov_prediction import CV_LINE_ID, RAW_GRIDS, MarkovPredictionConfig, MarkovPredictor
from stages.markov_prediction import core
from stages.markov_prediction import priority as pr
from stages.markov_prediction.chain import InputPriority, PriorityPropagator

STAMP = 1_000_000_000
#: The chain's unit tests run without an intentions stage: uniform corridor weights, measured initial boxes.
PLAIN = {"corridor_weights": "uniform", "initial_box": "measurement"}


# --------------------------------------------------------------------------- synthetic scenes


def _header(stamp: int = STAMP) -> bs.Header:
    return bs.Header(run_id="test", frame_index=0, stamp_ns=stamp, producer="test")


def _corridor(cid: int, *, vehicle_s: float = 5.0, length: float = 150.0, heading: float = 0.0, x0: float = 0.0,
              y0: float = 0.0, limit: float = 13.89, radius: float | None = None, d0: float = 0.0) -> bs.Corridor:
    """A straight corridor from (x0, y0) along ``heading``, or, with ``radius``, straight for 30 m then a left arc."""
    s = np.arange(0.0, length + 0.25, 0.5)
    if radius is None:
        heading_s = np.full(s.shape, heading)
        kappa = np.zeros(s.shape)
    else:
        kappa = np.where(s > 30.0, 1.0 / radius, 0.0)
        heading_s = heading + np.concatenate([[0.0], np.cumsum(kappa[1:] * np.diff(s))])
    x = x0 + np.concatenate([[0.0], np.cumsum(np.cos(heading_s[1:]) * np.diff(s))])
    y = y0 + np.concatenate([[0.0], np.cumsum(np.sin(heading_s[1:]) * np.diff(s))])
    return bs.Corridor(
        corridor_id=cid, lanelet_ids=np.array([1], np.int64), lanelet_start_s_m=np.array([0.0]), x_m=x, y_m=y, s_m=s,
        heading_rad=heading_s, curvature_1pm=kappa, width_m=np.full(s.shape, 3.5), extension_start_s_m=float(length),
        vehicle_s_m=vehicle_s, vehicle_d_m=d0, speed_limit_mps=limit,
    )


def _vehicle(track_id: int, speed: float, corridors) -> bs.VehicleCorridors:
    return bs.VehicleCorridors(
        track_id=track_id, agent_type=bs.AgentType.CAR, status=bs.MatchStatus.MATCHED, lanelet_id=1, match_distance_m=0.0,
        speed_mps=speed, corridors=tuple(corridors),
    )


def _corridor_set(*vehicles, stamp: int = STAMP) -> bs.CorridorSet:
    return bs.CorridorSet(header=_header(stamp), scene_id="test", vehicles=tuple(vehicles))


def _relation(track_id: int, cid: int, *, leader: int = -1, gap: float = math.nan, leader_speed: float = math.nan,
              conflict: dict | None = None) -> bs.CorridorRelations:
    e, ei = np.zeros(0), np.zeros(0, np.int64)
    n = 1 if conflict else 0
    c = conflict or {}

    def f(key):
        return np.array([c.get(key, 0.0)] * n, dtype=np.float64)

    return bs.CorridorRelations(
        track_id=track_id, corridor_id=cid, object_track_ids=ei, object_types=np.zeros(0, np.uint8), object_s_m=e,
        object_d_m=e, object_gap_m=e, object_speed_mps=e, leader_track_id=leader, leader_gap_m=gap,
        leader_speed_mps=leader_speed, intersection_ids=ei, intersection_entry_s_m=e, intersection_exit_s_m=e,
        intersection_distance_m=e, intersection_entry_lanelet_ids=ei,
        conflict_track_ids=np.array([c.get("track", 0)] * n, np.int64),
        conflict_corridor_ids=np.array([c.get("corridor", 0)] * n, np.int64), conflict_kinds=np.ones(n, np.uint8),
        conflict_s_m=f("s"), conflict_other_s_m=f("other_s"), conflict_x_m=f("x"), conflict_y_m=f("y"),
        conflict_distance_m=f("distance"), conflict_other_distance_m=f("other_distance"),
        conflict_other_speed_mps=f("other_speed"), conflict_time_s=f("t"), conflict_other_time_s=f("other_t"),
        conflict_priority=np.array([-1] * n, np.int8), influencing_index=0 if n else -1,
        influencing_rule="priority_other" if n else "none",
    )


def _relation_set(*relations, stamp: int = STAMP) -> bs.RelationSet:
    return bs.RelationSet(header=_header(stamp), scene_id="test", relations=tuple(relations))


@pytest.fixture(scope="module")
def baseline() -> MarkovPredictor:
    return MarkovPredictor(MarkovPredictionConfig(**PLAIN))


@pytest.fixture(scope="module")
def stencils(baseline):
    return baseline.stencils


@pytest.fixture(scope="module")
def baseline_torch(baseline) -> MarkovPredictor:
    return MarkovPredictor(MarkovPredictionConfig(backend="torch", **PLAIN), stencils=baseline.stencils)


def _mean_speed(prediction, b: int, predictor: MarkovPredictor) -> np.ndarray:
    vel = prediction.velocity_probs[b]
    return (vel @ predictor.v_centres) / vel.sum(axis=1)


def _leader_scene(with_leader: bool):
    """A follower at 10 m/s, 15 m (bumper to bumper) behind a leader at 2 m/s, on one straight road."""
    cs = _corridor_set(_vehicle(1, 10.0, [_corridor(7)]), _vehicle(2, 2.0, [_corridor(8, vehicle_s=5.0 + 15.0 + 4.5)]))
    rel = _relation(1, 7, leader=2, gap=15.0, leader_speed=2.0) if with_leader else _relation(1, 7)
    return cs, _relation_set(rel, _relation(2, 8))


def _conflict_scene():
    """Ego at 8 m/s, 25 m before a crossing; the priority vehicle creeps at 1.5 m/s, 4 m before it on its own road."""
    ego = _corridor(7)
    other = _corridor(9, heading=math.pi / 2, x0=25.0, y0=-20.0)  # crosses the ego's road at x = 25 (ego s = 30)
    cs = _corridor_set(_vehicle(1, 8.0, [ego]), _vehicle(3, 1.5, [other]))
    conflict = dict(track=3, corridor=9, s=30.0, other_s=9.0, distance=25.0, other_distance=4.0, other_speed=1.5)
    return cs, _relation_set(_relation(1, 7, conflict=conflict), _relation(3, 9))


# --------------------------------------------------------------------------- λ pieces


def test_speed_restriction_forbids_accelerating_over_the_limit_and_before_a_curve():
    grid = MarkovGridConfig()
    v, a = grid.v_centres_mps(), grid.input_centres_mps2()
    s = np.arange(0.0, 200.0, 0.5)
    kappa = np.where(s > 100.0, 1.0 / 20.0, 0.0)  # a 20 m radius curve from s = 100
    adm = pr.admissible_speeds(s, kappa, 10.0, np.array([2.0]), 2.5, 0.0)
    cells = np.array([10.5, 99.5])
    lam = pr.speed_restriction(adm, s, cells, v, a, np.array([1.0]), 0.4)  # (M, N_v, 2)
    at_limit = int(np.argmin(np.abs(v - 9.75)))  # just below the limit
    slow = int(np.searchsorted(v, 5.0))
    assert np.all(lam[a > 0.5, at_limit, 0] == 0.0) and np.all(lam[a < -0.1, at_limit, 0] == 1.0)
    assert np.all(lam[:, slow, 0] == 1.0)  # far below the limit on the straight: everything allowed
    v_curve = math.sqrt(2.0 * 20.0)  # 6.3 m/s
    fast = int(np.searchsorted(v, 8.0))
    assert np.all(lam[a >= -0.25, fast, 1] == 0.0), "at 8 m/s just before a curve of 6.3 m/s the car may not keep its speed"
    assert adm[0, np.searchsorted(s, 150.0)] == pytest.approx(v_curve, rel=1e-6)


def test_preference_combination_carries_cut_preference_down_and_keeps_braking_when_all_forbidden():
    q = pr.normalised_preference((0.1, 0.2, 0.4, 0.3), 4)
    m = np.array([1.0, 1.0, 0.0, 0.0], np.float32).reshape(1, 4, 1, 1)
    r = pr.combine_with_preference(m, q, 1e-3)[0, :, 0, 0]
    assert r[2] == 0 and r[3] == 0 and r[1] == pytest.approx(1.0)  # the cut 0.75 + 1.0 of the top inputs lands on input 1
    dead = pr.combine_with_preference(np.full((1, 4, 1, 1), 1e-4, np.float32), q, 1e-3)[0, :, 0, 0]
    assert dead.tolist() == [1.0, 0.0, 0.0, 0.0]


def test_critical_gaps_grow_with_closing_speed():
    grid = MarkovGridConfig()
    gaps = pr.CriticalGaps.build(grid.v_centres_mps(), grid.input_centres_mps2(), 20.0, (1.6,), 6.0)
    zero = 5  # input cell [-0.5, 0]
    same = gaps.gaps_m[0, 20, zero, 20, zero]
    closing = gaps.gaps_m[0, 20, zero, 4, zero]  # follower 10.25 m/s, leader 2.25 m/s
    assert same < 0.5 < closing
    assert closing == pytest.approx((10.25 - 2.25) * 1.6 + (10.25**2 - 2.25**2) / 12.0, abs=1.0)


def test_a_close_slow_leader_shifts_mass_to_braking(baseline):
    free, _ = baseline.process(*_leader_scene(False))
    led, issues = baseline.process(*_leader_scene(True))
    assert not issues
    v_free, v_led = _mean_speed(free, 0, baseline), _mean_speed(led, 0, baseline)
    assert v_led[3] < v_free[3] - 1.0 and v_led[-1] < 3.5
    slow_cells = baseline.v_centres < 5.0
    assert led.velocity_probs[0, -1, slow_cells].sum() > 0.7 > free.velocity_probs[0, -1, slow_cells].sum()
    assert led.mean_s_m[0, -1] < free.mean_s_m[0, -1] - 8.0


def test_an_influencing_priority_vehicle_makes_the_vehicle_stop_before_the_conflict(baseline):
    free, _ = baseline.process(*_conflict_scene()[:1])
    yielding, issues = baseline.process(*_conflict_scene())
    assert not issues
    zone_start = 30.0 - 0.5 * (4.5 + 1.8)
    cells = yielding.pairs[0].s_first_m + np.arange(yielding.position_probs.shape[2]) + 0.5
    beyond = cells > zone_start
    assert free.position_probs[0, -1, beyond].sum() > 0.9
    assert yielding.position_probs[0, -1, beyond].sum() < 0.1
    assert _mean_speed(yielding, 0, baseline)[-1] < 2.0


# --------------------------------------------------------------------------- the chain


def test_input_priority_equals_the_explicit_per_state_gamma():
    cfg = MarkovGridConfig(v_max_mps=6.0, n_s_cells=30, n_steps=4, n_state_samples=5, n_input_samples=4, n_sub_times=4)
    stencils = build_stencils(cfg)
    psi = psi_matrix(cfg.input_centres_mps2())
    rng = np.random.default_rng(1)
    lam = rng.uniform(0.0, 1.0, (2, cfg.n_inputs, cfg.n_v_cells, cfg.n_s_cells)).astype(np.float32)
    lam[0, :, 3, 5] = 0.0  # an all-forbidden state keeps the strongest braking input
    lam_fixed = lam.copy()
    lam_fixed[0, 0, 3, 5] = 1.0
    gamma = np.moveaxis(gamma_from_priority(np.moveaxis(lam_fixed, 1, -1), psi), (-2, -1), (1, 2)).astype(np.float32)
    p0 = initial_state(cfg, s_m=np.array([3.0, 6.0]), v_mps=np.array([2.0, 4.0]), half_width_s_m=1.0, half_width_v_mps=0.5,
                       input_probs=np.full(cfg.n_inputs, 1.0 / cfg.n_inputs))
    reference = MarkovPropagator(stencils).run(p0, [InputPerState(gamma=gamma)] * 4, with_final_state=True)
    for backend in ("numpy", "torch"):
        ours = PriorityPropagator(stencils, psi, backend=backend).run(
            p0, [InputPriority(weights=lambda lo, hi: lam_fixed[..., lo:hi])] * 4, with_final_state=True
        )
        np.testing.assert_allclose(ours.final_state, reference.final_state, atol=2e-6)


def test_probability_is_conserved_for_every_pair(baseline):
    cs, rs = _conflict_scene()
    prediction, _ = baseline.process(cs, rs)
    total = prediction.position_probs.sum(axis=2) + prediction.outside_mass
    np.testing.assert_allclose(total, 1.0, atol=1e-5)
    np.testing.assert_allclose(prediction.velocity_probs.sum(axis=2), prediction.position_probs.sum(axis=2) + prediction.outside_mass, atol=1e-5)


def test_free_driving_on_a_straight_road_keeps_its_speed(baseline):
    prediction, _ = baseline.process(_corridor_set(_vehicle(1, 10.0, [_corridor(7)])))
    s_after = prediction.mean_s_m[0] - 5.0
    assert abs(s_after[-1] - 40.0) < 1.0
    np.testing.assert_allclose(prediction.mean_xy_m[0, -1], [5.0 + s_after[-1], 0.0], atol=1e-6)


def test_a_standing_vehicle_mostly_stays(baseline):
    prediction, _ = baseline.process(_corridor_set(_vehicle(1, 0.0, [_corridor(7)])))
    assert prediction.mean_s_m[0, -1] - 5.0 < 1.0  # the standstill part (80 % at 4 s) does not creep
    assert prediction.velocity_probs[0, -1, 0] > 0.8


def test_numpy_and_torch_cpu_agree(baseline, baseline_torch):
    cs, rs = _conflict_scene()
    cs = _corridor_set(*cs.vehicles, *_leader_scene(True)[0].vehicles[1:])
    for scene in ((cs, rs), _leader_scene(True)):
        a, _ = baseline.process(*scene)
        b, _ = baseline_torch.process(*scene)
        np.testing.assert_allclose(a.position_probs, b.position_probs, atol=1e-4)
        np.testing.assert_allclose(a.velocity_probs, b.velocity_probs, atol=1e-4)
        np.testing.assert_allclose(a.mean_xy_m, b.mean_xy_m, atol=1e-3)


# --------------------------------------------------------------------------- motion grid


def test_grid_sums_to_one_minus_outside_and_stays_on_the_road():
    predictor = MarkovPredictor(MarkovPredictionConfig(grid_distribution="point", **PLAIN, **RAW_GRIDS))  # the chain's own grids
    straight, curve = _corridor(7, length=60.0), _corridor(8, length=60.0, radius=25.0)
    prediction, issues = predictor.process(_corridor_set(_vehicle(1, 12.0, [straight, curve])))
    assert any(i.kind == "corridor_too_short" for i in issues), "60 m is too short for 12 m/s: reported"
    frame, grid = prediction.grid_frame, prediction.vehicle_grids[1]
    expected = (0.5 * (1.0 - prediction.outside_mass)).sum(axis=0)
    centres = []
    for k in range(prediction.step_times_s.shape[0]):
        cells, values = grid.step(k, frame.n_cells)
        assert values.sum() == pytest.approx(expected[k], abs=1e-3)
        rows, cols = np.divmod(cells[values > 1e-4], frame.n_cols)
        centres.append(np.column_stack([frame.origin_x_m + (cols + 0.5) * frame.cell_m, frame.origin_y_m + (rows + 0.5) * frame.cell_m]))
    points = np.concatenate(centres)
    lines = [np.column_stack([c.x_m, c.y_m]) for c in (straight, curve)]
    distance = np.min([np.min(np.hypot(*(points[:, None, :] - line[None]).transpose(2, 0, 1)), axis=1) for line in lines], axis=0)
    band = 1.75 + 1.0 + frame.cell_m  # half the lane, 2.5 σ, one cell
    assert distance.max() < band
    message = prediction.motion_grid(_header(), "test")
    assert len(message.steps) == 10 and all(np.all(s.values > 1e-5) for s in message.steps)
    assert bs.MotionGrid.decode(message.encode()).n_cols == frame.n_cols


# --------------------------------------------------------------------------- constant-velocity baselines


def test_cv_and_corridor_cv_are_exact_on_a_constant_velocity_track():
    t = 0.4 * np.arange(1, 11)
    heading = 0.3
    corridor = _corridor(7, heading=heading, x0=-5.0 * math.cos(heading), y0=-5.0 * math.sin(heading))
    cs = _corridor_set(_vehicle(1, 8.0, [corridor]))
    frame = bs.TrackFrame(
        header=_header(), scene_id="test", track_ids=np.array([1], np.int64), agent_types=np.array([1], np.uint8),
        x_m=np.array([0.0]), y_m=np.array([0.0]), vx_mps=np.array([8.0 * math.cos(heading)]),
        vy_mps=np.array([8.0 * math.sin(heading)]), yaw_rad=np.array([heading]), length_m=np.array([4.5]), width_m=np.array([1.8]),
    )
    truth = np.column_stack([8.0 * t * math.cos(heading), 8.0 * t * math.sin(heading)])
    for mode in ("cv", "corridor_cv"):
        prediction, issues = MarkovPredictor(MarkovPredictionConfig(mode=mode, **PLAIN)).process(cs, None, None, frame)
        assert not issues
        np.testing.assert_allclose(prediction.mean_xy_m[0], truth, atol=1e-6)
        assert prediction.pairs[0].corridor_id == (CV_LINE_ID if mode == "cv" else 7)
        np.testing.assert_allclose(prediction.position_probs[0].sum(axis=1) + prediction.outside_mass[0], 1.0, atol=1e-6)


# --------------------------------------------------------------------------- stage update and issues


def test_update_publishes_both_messages_and_reports_bad_inputs(baseline):
    cs = _corridor_set(
        _vehicle(1, 10.0, [_corridor(7)]),
        _vehicle(2, math.nan, [_corridor(8)]),
        _vehicle(4, 6.0, [_corridor(10, length=20.0)]),
    )
    rs = _relation_set(_relation(1, 7), _relation(1, 99), _relation(4, 10, leader=77, gap=math.nan))
    result = baseline.update({"corridor_set": cs, "relation_set": rs})
    kinds = {(i.kind, i.agent_id) for i in result.issues}
    assert {("nan_state", 2), ("unknown_corridor", 1), ("corridor_too_short", 4), ("nan_relation", 4)} <= kinds
    predictions = result.outputs["corridor_predictions"]
    assert [(p.track_id, p.corridor_id) for p in predictions.predictions] == [(1, 7), (4, 10)]
    decoded = bs.CorridorPredictions.decode(predictions.encode())
    first = decoded.predictions[0]
    assert first.s_probs.shape[0] == 10 and first.v_probs.shape == (10, 40)
    np.testing.assert_allclose(first.s_probs.sum(axis=1) + first.outside_mass, 1.0, atol=1e-5)
    assert result.outputs["motion_grid"].mode == "baseline"


def test_config_names_what_to_fix():
    with pytest.raises(ValueError, match="mode = 'ar'"):
        MarkovPredictionConfig(mode="ar")
    with pytest.raises(ValueError, match="corridor_weights = 'dbn'"):
        MarkovPredictionConfig(corridor_weights="dbn")
    with pytest.raises(ValueError, match="initial_box"):
        MarkovPredictionConfig(initial_box="wide")
    with pytest.raises(ValueError, match="hybrid_input"):
        MarkovPredictionConfig(hybrid_input="rules")
    with pytest.raises(ValueError, match="numpy backend runs on cpu only"):
        MarkovPredictionConfig.from_params({"device": "cuda"})


def test_defaults_are_calibrated_grids_on_1_m_cells_sampled_every_half_cell():
    """The grids' defaults: the shipped spread table and the online spread on 1 m cells; ``grid_substeps`` 0 resolves
    to a footprint sample every half cell along (⌈2·ds/cell⌉) at construction, so every reader sees the number in use;
    RAW_GRIDS turns the spread off."""
    cfg = MarkovPredictionConfig()
    assert (cfg.spread_calibration, cfg.spread_online, cfg.grid_cell_m, cfg.grid_substeps) == ("shipped", True, 1.0, 2)
    assert MarkovPredictionConfig(grid_cell_m=0.5).grid_substeps == 4 and MarkovPredictionConfig(grid_cell_m=0.3).grid_substeps == 7
    assert MarkovPredictionConfig(grid_cell_m=4.0).grid_substeps == 1 and MarkovPredictionConfig(grid_substeps=3).grid_substeps == 3
    raw = MarkovPredictionConfig(**RAW_GRIDS)
    assert (raw.spread_calibration, raw.spread_online) == ("", False)
    with pytest.raises(ValueError, match="grid_substeps = -1"):
        MarkovPredictionConfig(grid_substeps=-1)


# --------------------------------------------------------------------------- intentions and hybrid inputs


def _belief(track_id: int, probs: dict[int, float], *, stamp: int = STAMP, s=None, v=None) -> bs.IntentionBelief:
    s = s or {}
    v = v or {}
    corridors = tuple(
        bs.CorridorBelief(
            corridor_id=c, probability=p, manoeuvre=bs.Manoeuvre.FOLLOW_LANE, particle_count=100,
            s_mean_m=s.get(c, (5.0, 0.1))[0], s_std_m=s.get(c, (5.0, 0.1))[1],
            v_mean_mps=v.get(c, (10.0, 0.1))[0], v_std_mps=v.get(c, (10.0, 0.1))[1],
            a_mean_mps2=0.0, a_std_mps2=0.3, p_stop=0.1, stop_distance_m=math.nan,
        )
        for c, p in probs.items()
    )
    vehicle = bs.VehicleBelief(
        track_id=track_id, corridors=corridors, p_stop=0.1, p_expected_stop=0.1, p_violation=0.0, p_lane_change=0.0,
        expected_manoeuvre=bs.Manoeuvre.FOLLOW_LANE, intersection_distance_m=math.nan, effective_sample_size=90.0,
        particle_count=100,
    )
    return bs.IntentionBelief(header=_header(stamp), scene_id="test", vehicles=(vehicle,))


def _profiles(track_id: int, cid: int, accel: float, *, sigma: float = 0.3, edges=None, stamp: int = STAMP) -> bs.AccelerationProfiles:
    from scipy.stats import norm

    edges = np.linspace(-3.0, 2.0, 11) if edges is None else edges
    cdf = norm.cdf((edges - accel) / sigma)
    cdf[0], cdf[-1] = 0.0, 1.0
    row = np.diff(cdf).astype(np.float32)
    profile = bs.AccelerationProfile(
        track_id=track_id, corridor_id=cid, history_steps=40, accel_mps2=np.full(40, accel, np.float32),
        chunk_mean_mps2=np.full(10, accel, np.float32), chunk_sigma_mps2=np.full(10, sigma, np.float32),
        input_probs=np.repeat(row[None] / row.sum(), 10, axis=0),
    )
    return bs.AccelerationProfiles(header=_header(stamp), scene_id="test", model="test", step_s=0.1, chunk_s=0.4,
                                   input_edges_mps2=np.asarray(edges, np.float64), profiles=(profile,))


def _drive_choice(predictor: MarkovPredictor, refs: dict[float, MarkovPredictor], value_attr: str, not_expected: tuple[str, ...],
                  scene_at, frames: int, scene: bs.SceneInfo | None = None) -> int | None:
    """``frames`` frames of ``scene_at(stamp, n)`` (a corridor set and a track frame of car 1 on corridor 7, AR profile 0)
    through ``predictor``, whose online choice keeps its value in ``value_attr``: no issue of the kinds ``not_expected``,
    and every frame's own prediction that of the fixed-value reference ``refs[value]`` of the value in use; returns the
    frame the value first changed at (None: never; tests/stages/test_accel_shift.py, test_speed_lead.py)."""
    switched_at = None
    for n in range(frames):
        stamp = STAMP + n * 100_000_000
        cs, frame = scene_at(stamp, n)
        value = getattr(predictor, value_attr)
        prediction, issues = predictor.process(cs, None, scene, frame, acceleration_profiles=_profiles(1, 7, 0.0, stamp=stamp))
        assert not [i for i in issues if i.kind in not_expected], issues
        if getattr(predictor, value_attr) != value and switched_at is None:
            switched_at = n
        ref, _ = refs[getattr(predictor, value_attr)].process(cs, None, scene, frame, acceleration_profiles=_profiles(1, 7, 0.0, stamp=stamp))
        np.testing.assert_array_equal(prediction.mean_s_m, ref.mean_s_m)  # the frame's own prediction: the value in use
        predictor.idle()
    return switched_at


def _with_failing_back_test(predictor: MarkovPredictor, reference: MarkovPredictor, field_name: str, scene_at, monkeypatch) -> list:
    """Two frames of ``scene_at(stamp, n)`` (a corridor set and a track frame of car 1 on corridor 7, AR profile 0) with
    the back test of the online choice on Pair ``field_name`` raising: each frame's prediction must equal
    ``reference``'s; returns the last frame's issues (tests/stages/test_accel_shift.py, test_speed_lead.py)."""
    real = predictor._back_test_choice

    def failing(choice, name, *args, **kwargs):
        if name == field_name:
            raise RuntimeError("boom")
        return real(choice, name, *args, **kwargs)

    monkeypatch.setattr(predictor, "_back_test_choice", failing)
    issues: list = []
    for n in range(2):
        stamp = STAMP + n * 100_000_000
        cs, frame = scene_at(stamp, n)
        prediction, issues = predictor.process(cs, None, None, frame, acceleration_profiles=_profiles(1, 7, 0.0, stamp=stamp))
        ref, _ = reference.process(cs, None, None, frame, acceleration_profiles=_profiles(1, 7, 0.0, stamp=stamp))
        np.testing.assert_array_equal(prediction.mean_s_m, ref.mean_s_m)
        predictor.idle()
    return issues


def test_intention_weights_replace_the_uniform_ones_and_missing_beliefs_fall_back(stencils):
    predictor = MarkovPredictor(MarkovPredictionConfig(mode="corridor_cv", corridor_weights="intentions", initial_box="measurement"), stencils=stencils)
    cs = _corridor_set(_vehicle(1, 10.0, [_corridor(7), _corridor(8, radius=20.0)]))
    prediction, issues = predictor.process(cs, intention_belief=_belief(1, {7: 0.2, 8: 0.6}))
    assert [round(p.probability, 6) for p in prediction.pairs] == [0.25, 0.75]
    prediction, issues = predictor.process(cs, intention_belief=None)
    assert [p.probability for p in prediction.pairs] == [0.5, 0.5] and any(i.kind == "no_intentions" for i in issues)
    prediction, issues = predictor.process(cs, intention_belief=_belief(1, {7: 1.0}))
    assert [p.probability for p in prediction.pairs] == [0.5, 0.5] and any(i.kind == "no_belief" for i in issues)
    prediction, issues = predictor.process(cs, intention_belief=_belief(1, {7: 0.2, 8: 0.6}, stamp=STAMP + 1))
    assert [p.probability for p in prediction.pairs] == [0.5, 0.5] and any(i.kind == "stamp_mismatch" for i in issues)


def test_particle_box_widens_the_initial_spread(stencils):
    cs = _corridor_set(_vehicle(1, 10.0, [_corridor(7)]))
    spreads = {}
    for box in ("measurement", "particles"):
        predictor = MarkovPredictor(MarkovPredictionConfig(mode="baseline", corridor_weights="intentions", initial_box=box), stencils=stencils)
        prediction, _ = predictor.process(cs, _relation_set(_relation(1, 7)), intention_belief=_belief(1, {7: 1.0}, s={7: (6.0, 2.0)}, v={7: (10.0, 1.0)}))
        probs = prediction.position_probs[0, 0]
        centres = prediction.pairs[0].s_first_m + (np.arange(probs.size) + 0.5) * prediction.ds_m
        mean = float(probs @ centres / probs.sum())
        spreads[box] = math.sqrt(float(probs @ (centres - mean) ** 2 / probs.sum()))
    assert spreads["particles"] > spreads["measurement"] + 0.5


def test_initial_box_default_is_per_mode_and_decides_where_the_chain_starts(stencils):
    # "auto" (the default) resolves to the mode's box: the measurement for hybrid and corridor_cv, the particles for baseline
    assert MarkovPredictionConfig().initial_box == "particles"  # baseline is the default mode
    assert {m: MarkovPredictionConfig(mode=m).initial_box for m in ("hybrid", "corridor_cv", "baseline", "cv")} == {
        "hybrid": "measurement", "corridor_cv": "measurement", "baseline": "particles", "cv": "measurement"}
    assert MarkovPredictionConfig(mode="hybrid", initial_box="particles").initial_box == "particles"  # an explicit box wins
    assert MarkovPredictionConfig.from_params({"mode": "corridor_cv", "initial_box": "auto"}).initial_box == "measurement"
    # the particles say 6 m/s at s = 9 m, the measurement 10 m/s at s = 5 m: the default box of each mode decides the start
    cs = _corridor_set(_vehicle(1, 10.0, [_corridor(7)]))
    belief = _belief(1, {7: 1.0}, s={7: (9.0, 0.1)}, v={7: (6.0, 0.1)})
    starts = {}
    for mode in ("hybrid", "corridor_cv", "baseline"):
        predictor = MarkovPredictor(MarkovPredictionConfig(mode=mode), stencils=stencils)
        prediction, _ = predictor.process(cs, _relation_set(_relation(1, 7)), intention_belief=belief,
                                          acceleration_profiles=_profiles(1, 7, 0.0) if mode == "hybrid" else None)
        starts[mode] = float(prediction.mean_s_m[0, -1])  # s at 4 s
    assert abs(starts["corridor_cv"] - (5.0 + 40.0)) < 1.0 and abs(starts["hybrid"] - (5.0 + 40.0)) < 2.0
    assert abs(starts["baseline"] - (9.0 + 24.0)) < 3.0


def test_hybrid_follows_the_ar_distributions(stencils):
    predictor = MarkovPredictor(MarkovPredictionConfig(mode="hybrid", **PLAIN), stencils=stencils)
    cs = _corridor_set(_vehicle(1, 10.0, [_corridor(7)]))
    ends = {}
    for accel in (-2.0, 0.0, 1.5):
        prediction, issues = predictor.process(cs, acceleration_profiles=_profiles(1, 7, accel))
        assert not issues
        ends[accel] = float(prediction.mean_s_m[0, -1]) - 5.0
        np.testing.assert_allclose(prediction.position_probs[0].sum(axis=1) + prediction.outside_mass[0], 1.0, atol=1e-5)
    # s(4 s) = 10·4 + ½·a·16 for a held acceleration; the chain's Ψ keeps part of the previous input, so only roughly
    assert ends[-2.0] < ends[0.0] < ends[1.5]
    assert abs(ends[0.0] - 40.0) < 1.5 and abs(ends[-2.0] - 24.0) < 4.0 and abs(ends[1.5] - 52.0) < 4.0
    direct = MarkovPredictor(MarkovPredictionConfig(mode="hybrid", hybrid_input="direct", **PLAIN), stencils=stencils)
    prediction, _ = direct.process(cs, acceleration_profiles=_profiles(1, 7, -2.0))
    assert abs(float(prediction.mean_s_m[0, -1]) - 5.0 - 24.0) < 4.0


def test_hybrid_without_a_usable_profile_falls_back_and_says_so(stencils):
    predictor = MarkovPredictor(MarkovPredictionConfig(mode="hybrid", **PLAIN), stencils=stencils)
    cs = _corridor_set(_vehicle(1, 10.0, [_corridor(7)]))
    for profiles, kind in (
        (None, "no_acceleration_profiles"),
        (_profiles(1, 99, 0.0), "no_acceleration_profile"),
        (_profiles(1, 7, 0.0, edges=np.linspace(-6.0, 2.0, 11)), "bad_profile"),
        (_profiles(1, 7, 0.0, stamp=STAMP + 5), "stamp_mismatch"),
    ):
        prediction, issues = predictor.process(cs, acceleration_profiles=profiles)
        assert any(i.kind == kind for i in issues), (kind, issues)
        assert abs(float(prediction.mean_s_m[0, -1]) - 45.0) < 2.0  # measured acceleration 0 held: ~10 m/s for 4 s



def test_hybrid_speed_restriction_slows_for_a_curve_the_profile_ignores(stencils):
    cs = _corridor_set(_vehicle(1, 12.0, [_corridor(7, radius=15.0)]))  # 12 m/s, a 15 m radius curve 25 m ahead
    ends = {}
    for restricted in (False, True):
        predictor = MarkovPredictor(MarkovPredictionConfig(mode="hybrid", hybrid_speed_restriction=restricted, **PLAIN), stencils=stencils)
        prediction, _ = predictor.process(cs, acceleration_profiles=_profiles(1, 7, 0.5))
        ends[restricted] = float(prediction.mean_s_m[0, -1])
        np.testing.assert_allclose(prediction.position_probs[0].sum(axis=1) + prediction.outside_mass[0], 1.0, atol=1e-5)
    assert ends[True] < ends[False] - 3.0, ends


def test_hybrid_speed_restriction_without_curves_keeps_the_limit_and_leaves_the_curve_to_the_model(stencils):
    """hybrid_speed_restriction_curves = false: the curve ahead no longer slows the pair (the AR model reads the
    curvature itself), as without any restriction; the speed limit still cuts a profile that accelerates past it."""
    cs = _corridor_set(_vehicle(1, 12.0, [_corridor(7, radius=15.0)]))  # 12 m/s, a 15 m radius curve 25 m ahead
    ends = {}
    for name, extra in (("full", {}), ("no curves", {"hybrid_speed_restriction_curves": False}),
                        ("off", {"hybrid_speed_restriction": False})):
        predictor = MarkovPredictor(MarkovPredictionConfig(mode="hybrid", **PLAIN, **extra), stencils=stencils)
        prediction, _ = predictor.process(cs, acceleration_profiles=_profiles(1, 7, 0.5))
        ends[name] = float(prediction.mean_s_m[0, -1])
    # "off" a little further: the profile (12 m/s + 0.5 m/s²) passes the corridor's limit 13.89 m/s, which "no curves" keeps
    assert ends["full"] < ends["no curves"] - 3.0 and 0.0 <= ends["off"] - ends["no curves"] < 1.0, ends
    predictor = MarkovPredictor(MarkovPredictionConfig(mode="hybrid", hybrid_speed_restriction_curves=False, **PLAIN), stencils=stencils)
    for limited in (False, True):
        straight = _corridor_set(_vehicle(1, 12.0, [_corridor(7, limit=12.0 if limited else 19.0)]))
        prediction, _ = predictor.process(straight, acceleration_profiles=_profiles(1, 7, 1.5))
        ends[limited] = float(prediction.mean_s_m[0, -1])
    assert ends[True] < ends[False] - 3.0, ends


def test_hybrid_initial_input_measured_starts_moving_pairs_from_their_measured_acceleration(stencils):
    """hybrid_initial_input = "measured": λ(0) of a moving pair is its measured acceleration (0 here: no history),
    not the AR profile's first distribution, so a profile that brakes at -2.5 m/s² brakes one step later."""
    cs = _corridor_set(_vehicle(1, 10.0, [_corridor(7)]))
    ends = {}
    for initial in ("ar", "measured"):
        predictor = MarkovPredictor(MarkovPredictionConfig(mode="hybrid", hybrid_initial_input=initial, **PLAIN), stencils=stencils)
        prediction, _ = predictor.process(cs, acceleration_profiles=_profiles(1, 7, -2.5))
        ends[initial] = float(prediction.mean_s_m[0, 0])  # s after the first step
        np.testing.assert_allclose(prediction.position_probs[0].sum(axis=1) + prediction.outside_mass[0], 1.0, atol=1e-5)
    assert ends["measured"] > ends["ar"] + 0.1, ends
    with pytest.raises(ValueError, match="hybrid_initial_input"):
        MarkovPredictionConfig(mode="hybrid", hybrid_initial_input="maybe")


def test_precision_blend_weights_each_by_its_precision():
    from stages.markov_prediction.modes.hybrid import precision_blend

    assert precision_blend(-1.0, 0.5, 1.0, 0.5) == pytest.approx((0.0, 0.5 / math.sqrt(2.0)))  # equal σ: the midpoint
    mean, sigma = precision_blend(0.0, 1.0, 1.0, 2.0)  # weights 1 and 1/4: 0.8 on the model
    assert mean == pytest.approx(0.2) and sigma == pytest.approx(1.0 / math.sqrt(1.25))
    assert precision_blend(0.0, 1.0, 1.0, 1e-4)[0] == pytest.approx(1.0, abs=1e-6)


def test_cell_moments_include_the_width_of_the_cells():
    from stages.markov_prediction.modes.hybrid import cell_moments

    edges = np.linspace(-3.0, 2.0, 11)
    one = np.zeros(10)
    one[6] = 1.0  # all mass in [0, 0.5]
    assert cell_moments(edges, one) == pytest.approx((0.25, 0.5 / math.sqrt(12.0)))
    two = np.zeros(10)
    two[[4, 8]] = 0.5  # centres -0.75 and 1.25
    assert cell_moments(edges, two) == pytest.approx((0.25, math.sqrt(1.0 + 0.25 / 12.0)))


def test_blend_initial_follows_the_more_precise_of_model_and_measurement():
    """A noisy measurement leaves ~the model's mean, a precise one ~the measurement; the spread is the model's."""
    from stages.markov_prediction.modes.hybrid import blend_initial, cell_moments, start_inputs

    edges = np.linspace(-3.0, 2.0, 11)
    lam0 = start_inputs(edges, -1.5, 0.4)
    mu_m, sigma_m = cell_moments(edges, lam0)
    issues: list = []
    noisy = blend_initial(edges, lam0, 1.5, 50.0, 1, issues)
    precise = blend_initial(edges, lam0, 1.0, 0.01, 1, issues)
    assert cell_moments(edges, noisy)[0] == pytest.approx(mu_m, abs=0.01)
    assert cell_moments(edges, precise)[0] == pytest.approx(1.0, abs=0.05)
    np.testing.assert_allclose(precise, start_inputs(edges, precision_blend_mean(mu_m, sigma_m, 1.0, 0.01), sigma_m))
    equal = blend_initial(edges, lam0, 0.5, sigma_m, 1, issues)  # equal precision: halfway
    assert cell_moments(edges, equal)[0] == pytest.approx(0.5 * (mu_m + 0.5), abs=0.05)
    assert issues == []
    for noisy_sum in (noisy, precise, equal):
        assert noisy_sum.sum() == pytest.approx(1.0) and np.all(noisy_sum >= 0)


def precision_blend_mean(mu_m, sigma_m, a, sigma_a):
    return (mu_m / sigma_m**2 + a / sigma_a**2) / (1.0 / sigma_m**2 + 1.0 / sigma_a**2)


def test_blend_initial_keeps_the_model_without_a_usable_measurement():
    """No measurement (NaN, NaN: a young track) keeps λ_AR(0) silently; a NaN acceleration or a standard error
    that is NaN, 0, negative or infinite keeps it with one counted issue each."""
    from stages.markov_prediction.modes.hybrid import blend_initial, start_inputs

    edges = np.linspace(-3.0, 2.0, 11)
    lam0 = start_inputs(edges, -1.5, 0.4)
    issues: list = []
    assert blend_initial(edges, lam0, math.nan, math.nan, 3, issues) is lam0 and issues == []
    for a, se in ((math.nan, 0.2), (0.5, math.nan), (0.5, 0.0), (0.5, -1.0), (0.5, math.inf), (math.inf, 0.2)):
        assert blend_initial(edges, lam0, a, se, 3, issues) is lam0
    assert [i.kind for i in issues] == ["bad_measured_acceleration"] * 6 and all(i.agent_id == 3 for i in issues)


def _accelerating_history(predictor, speed0: float, accel: float, jitter: float, n: int = 11) -> int:
    """Feed n frames 0.1 s apart of a car at speed0 + accel·t (± jitter alternating); returns the last stamp."""
    for i in range(n):
        stamp = STAMP + i * 100_000_000
        v = speed0 + accel * 0.1 * i + (jitter if i % 2 else -jitter)
        predictor.observe(_corridor_set(_vehicle(1, v, [_corridor(7)]), stamp=stamp))
    return stamp


def test_speed_lines_made_together_equal_the_numpy_code_vehicle_by_vehicle(stencils):
    """_fit_speed_lines (kernels.speed_lines: every vehicle's least-squares speed line in one compiled call) gives
    _speed_line's numpy numbers bit for bit: 0 to 64 samples in the window (below 3: None), irregular stamps (some
    outside the window, one after the frame's stamp), speeds that jitter or are constant, huge and tiny."""
    from stages.lib.markov import kernels

    if not kernels.available():
        pytest.skip("numba does not import")
    predictor = MarkovPredictor(MarkovPredictionConfig(**PLAIN, accel_window_s=6.4), stencils=stencils)
    rng = np.random.default_rng(5)
    stamp = 1_650_000_000_123_456_789  # an epoch stamp in ns: its float64 rounds
    sizes = [0, 1, 2, 3, 5, 7, 8, 9, 15, 16, 17, 31, 40, 64, 64] + rng.integers(8, 65, 40).tolist()
    for track, n in enumerate(sizes):
        gaps = rng.integers(20_000_000, 150_000_000, n)
        stamps = stamp + 300_000_000 - np.cumsum(gaps)[::-1]  # the newest may lie after the stamp
        scale = 1e6 if track == 9 else 1e-6 if track == 10 else 1.0
        for t in stamps.tolist():
            v = 5.0 if track == 11 else scale * float(rng.normal(8.0, 3.0))
            predictor._history.setdefault(track, core._SpeedHistory()).samples.append((int(t), v))
    tracks = list(range(len(sizes))) + [-1]  # (-1: no history)
    want = {t: predictor._speed_line(t, stamp) for t in tracks}
    predictor._fit_speed_lines(tracks, stamp)
    assert set(predictor._lines) == {(t, stamp) for t in tracks}
    assert sum(w is not None for w in want.values()) >= 40
    for t in tracks:
        got, expect = predictor._lines[(t, stamp)], want[t]
        assert (got is None) == (expect is None), t
        if expect is not None:
            assert got[0] == expect[0] and np.array(got[1:]).tobytes() == np.array(expect[1:]).tobytes(), (t, got, expect)
        assert predictor._speed_line(t, stamp) == expect
    predictor.observe(_corridor_set(_vehicle(1, 9.0, [_corridor(7)]), stamp=stamp + 1))  # a new speed: the kept lines go
    assert not predictor._lines


def test_speed_lines_do_not_depend_on_where_the_clock_starts(stencils):
    """The same speeds at the same intervals give the same line, bit for bit, whether the stamps start at 0 (a
    recording) or are wall-clock ns (a live tracker): the times are taken from the newest sample in integer ns before
    they become float64 (an epoch stamp as float64 loses its last 8 bits), in the numpy code and the compiled one."""
    rng = np.random.default_rng(11)
    gaps = rng.integers(60_000_000, 140_000_000, 30)
    speeds = rng.normal(8.0, 2.0, 30).tolist()
    lines = []
    for origin in (0, 1_796_510_259_325_833_659):
        predictor = MarkovPredictor(MarkovPredictionConfig(**PLAIN, accel_window_s=2.0), stencils=stencils)
        stamps = (origin + 5_000_000_000 + np.cumsum(gaps)).tolist()
        for t, v in zip(stamps, speeds):
            predictor._history.setdefault(1, core._SpeedHistory()).samples.append((int(t), v))
        numpy_line = predictor._speed_line(1, stamps[-1])
        predictor._fit_speed_lines([1], stamps[-1])
        lines.append((numpy_line, predictor._lines[(1, stamps[-1])]))
    (zero_numpy, zero_kept), (wall_numpy, wall_kept) = lines
    assert zero_numpy is not None and zero_numpy[0] >= 10
    assert np.array(zero_numpy).tobytes() == np.array(wall_numpy).tobytes(), (zero_numpy, wall_numpy)
    assert np.array(zero_kept).tobytes() == np.array(wall_kept).tobytes(), (zero_kept, wall_kept)


def test_a_vehicles_first_frame_observed_after_its_second_is_kept(stencils):
    """prepare may observe frame n + 1 before frame n is finished: a vehicle new in frame n then gets its frame n + 1
    speed first. Its frame n speed goes in front (it was dropped as "older than every sample kept", so the vehicle's
    measured acceleration differed from frames taken in order: found on a dense recording); the same stamp twice is
    kept once, and a full history still leaves out a stamp older than all it holds."""
    in_order, ahead = (MarkovPredictor(MarkovPredictionConfig(**PLAIN), stencils=stencils) for _ in range(2))
    speeds = {STAMP + i * 100_000_000: 5.0 + 0.3 * i for i in range(4)}
    stamps = sorted(speeds)
    for t in stamps:
        in_order.observe(_corridor_set(_vehicle(1, speeds[t], [_corridor(7)]), stamp=t))
    for t in (stamps[1], stamps[0], stamps[0], stamps[2], stamps[3]):  # its first frame second, and twice
        ahead.observe(_corridor_set(_vehicle(1, speeds[t], [_corridor(7)]), stamp=t))
    assert list(ahead._history[1].samples) == list(in_order._history[1].samples) == [(t, speeds[t]) for t in stamps]
    assert ahead.measured_acceleration(1, stamps[-1]) == in_order.measured_acceleration(1, stamps[-1])
    full = ahead._history[1].samples
    full.extend((stamps[-1] + (k + 1) * 100_000_000, 6.0) for k in range(full.maxlen))
    kept = list(full)
    ahead.observe(_corridor_set(_vehicle(1, 4.0, [_corridor(7)]), stamp=stamps[0]))  # older than a full history holds
    assert list(ahead._history[1].samples) == kept


def test_hybrid_initial_input_blend_follows_a_clean_measurement_and_ignores_a_noisy_one(stencils):
    """hybrid_initial_input = "blend": a car that has accelerated at +1.5 m/s² with clean speeds starts like
    "measured" (the first step further than the AR profile's -2.5 m/s²); with speeds jittering ±3 m/s the
    measurement's standard error is large and it starts like "ar"; without history it is "ar" exactly."""
    ends = {}
    for initial, jitter in (("ar", 0.0), ("measured", 0.0), ("blend", 0.0), ("blend", 3.0), ("blend", None)):
        predictor = MarkovPredictor(MarkovPredictionConfig(mode="hybrid", hybrid_initial_input=initial, **PLAIN), stencils=stencils)
        stamp = STAMP if jitter is None else _accelerating_history(predictor, 8.5, 1.5, jitter)
        speed = 10.0
        prediction, issues = predictor.process(_corridor_set(_vehicle(1, speed, [_corridor(7)]), stamp=stamp),
                                               acceleration_profiles=_profiles(1, 7, -2.5, stamp=stamp))
        assert not [i for i in issues if i.kind == "bad_measured_acceleration"]
        ends[(initial, jitter)] = float(prediction.mean_s_m[0, 0])
        np.testing.assert_allclose(prediction.position_probs[0].sum(axis=1) + prediction.outside_mass[0], 1.0, atol=1e-5)
    assert abs(ends[("blend", 0.0)] - ends[("measured", 0.0)]) < 0.1, ends
    assert ends[("blend", 0.0)] > ends[("ar", 0.0)] + 0.2, ends
    assert abs(ends[("blend", 3.0)] - ends[("ar", 0.0)]) < 0.1 < ends[("blend", 0.0)] - ends[("blend", 3.0)], ends
    assert ends[("blend", None)] == pytest.approx(ends[("ar", 0.0)], abs=1e-6), ends
    MarkovPredictionConfig(mode="hybrid", hybrid_initial_input="blend")  # a valid value


def test_hybrid_rules_keeps_the_leader_rule_that_plain_hybrid_leaves_to_the_model(stencils):
    """hybrid_rules: λ_AR(k) is only the preference inside the baseline's rules, so an AR profile that accelerates
    towards a slow leader 15 m ahead is cut by the leader rule; plain hybrid follows the profile."""
    cs, rs = _leader_scene(with_leader=True)
    ends = {}
    for rules in (False, True):
        predictor = MarkovPredictor(MarkovPredictionConfig(mode="hybrid", hybrid_rules=rules, **PLAIN), stencils=stencils)
        prediction, _ = predictor.process(cs, rs, acceleration_profiles=_profiles(1, 7, 1.5))
        i = next(k for k, p in enumerate(prediction.pairs) if p.track_id == 1)
        ends[rules] = float(prediction.mean_s_m[i, -1])
        np.testing.assert_allclose(prediction.position_probs[i].sum(axis=1) + prediction.outside_mass[i], 1.0, atol=1e-5)
    assert ends[True] < ends[False] - 5.0, ends
    with pytest.raises(ValueError, match="hybrid_rules_standing"):
        MarkovPredictionConfig(mode="hybrid", hybrid_rules=True, hybrid_rules_standing="maybe")


def test_hybrid_stop_mixture_brakes_by_the_intentions_p_stop(stencils):
    """hybrid_stop_mixture: a moving car with P(stop) 0.9 on its corridor and the stop position 20 m ahead is predicted
    to brake (mean at 4 s well short of the AR's constant speed), with P(stop) 0 as the AR says; off: P(stop) unused."""
    import dataclasses

    cs = _corridor_set(_vehicle(1, 8.0, [_corridor(7)]))

    def belief(p_stop: float) -> bs.IntentionBelief:
        b = _belief(1, {7: 1.0})
        c = dataclasses.replace(b.vehicles[0].corridors[0], p_stop=p_stop, stop_distance_m=20.0)
        return dataclasses.replace(b, vehicles=(dataclasses.replace(b.vehicles[0], corridors=(c,)),))

    ends = {}
    for mix in (False, True):
        predictor = MarkovPredictor(MarkovPredictionConfig(mode="hybrid", hybrid_stop_mixture=mix), stencils=stencils)
        for p in (0.0, 0.9):
            prediction, _ = predictor.process(cs, _relation_set(_relation(1, 7)), intention_belief=belief(p),
                                              acceleration_profiles=_profiles(1, 7, 0.0))
            ends[mix, p] = float(prediction.mean_s_m[0, -1]) - 5.0
    assert abs(ends[True, 0.0] - ends[False, 0.0]) < 1e-6 and abs(ends[False, 0.9] - ends[False, 0.0]) < 1e-6
    assert abs(ends[False, 0.0] - 32.0) < 2.0  # 8 m/s for 4 s
    assert ends[True, 0.9] < 26.0, ends  # braking at a = 8² / 40 = 1.6 m/s² with weight 0.9 stops after ~20 m
