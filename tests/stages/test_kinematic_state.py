"""The causal state estimator: speed from positions, reported velocity as checked evidence.

Synthetic tracks for the rules, the embedded K729 sequence for the real thing,
and the corridors stage fed the same frames with scaled, zeroed and reversed
reported velocities.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from bus_schemas import Header, SceneInfo, TrackFrame
from stages.lib.base import ConfigError
from stages.corridors import CorridorBuilder, CorridorsConfig, SceneMaps
from stages.lib.datasets import DEFAULT_DATA_DIR, DEFAULT_RECORDING, load_recording
from stages.lib.kinematic_state import EstimatorConfig, KinematicEstimator

STEP_NS = 100_000_000


def _run(est, track_id, xs, ys, vxs, vys, start_ns=0):
    issues, states = [], []
    for k, (x, y, vx, vy) in enumerate(zip(xs, ys, vxs, vys)):
        states.append(est.update(track_id, start_ns + k * STEP_NS, float(x), float(y), float(vx), float(vy), issues))
    return states, issues


def _straight(n, speed, noise_m=0.0, seed=0, accel=0.0):
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 0.1
    s = speed * t + 0.5 * accel * t**2
    v = speed + accel * t
    x = s * math.cos(0.3) + rng.normal(0, noise_m, n)
    y = s * math.sin(0.3) + rng.normal(0, noise_m, n)
    return x, y, v * math.cos(0.3), v * math.sin(0.3)


def test_speed_comes_from_positions_whatever_the_tracker_reports():
    x, y, vx, vy = _straight(40, 12.0, noise_m=0.05)
    for factor in (1.0, 0.5, 2.0, 0.0, -1.0):
        states, _ = _run(KinematicEstimator(), 1, x, y, vx * factor, vy * factor)
        if factor == 0.0:  # a reported zero at birth is no speed at all
            assert states[0].source == "unknown" and math.isnan(states[0].speed_mps)
        else:
            assert states[0].source == "reported" and states[0].speed_mps == pytest.approx(12.0 * abs(factor))
        later = np.array([s.speed_mps for s in states[10:]])
        assert np.all(np.abs(later - 12.0) < 1.0), (factor, later)
        assert all(s.source == "positions" for s in states[1:])
        heading = np.array([s.heading_rad for s in states[10:]])
        np.testing.assert_allclose(heading, 0.3, atol=0.15)


def test_acceleration_is_estimated_and_braking_cars_slow_down():
    x, y, vx, vy = _straight(40, 14.0, accel=-3.0)
    states, _ = _run(KinematicEstimator(), 1, x, y, vx, vy)
    assert states[-1].accel_mps2 == pytest.approx(-3.0, abs=0.5)
    assert states[-1].speed_mps == pytest.approx(14.0 - 3.0 * 3.9, abs=0.8)


def test_scaled_velocities_are_one_counted_issue_per_track_and_one_warning_line():
    est = KinematicEstimator()
    issues = []
    for track_id in range(4):
        x, y, vx, vy = _straight(40, 10.0 + track_id, noise_m=0.03, seed=track_id)
        _, got = _run(est, track_id, x, y, vx * 0.5, vy * 0.5)
        issues += got
    kinds = [i.kind for i in issues]
    assert kinds.count("velocity_inconsistent") == 4
    assert {i.agent_id for i in issues if i.kind == "velocity_inconsistent"} == {0, 1, 2, 3}
    c = est.consistency()
    assert c.tracks_checked == 4 and c.tracks_inconsistent == 4
    assert c.median_factor == pytest.approx(0.5, abs=0.05) and c.median_cosine > 0.95
    line = est.warning()
    assert line is not None and "4 of 4 tracks" in line and "factor 0.50" in line
    assert est.warning() is None  # once


def test_a_calibrated_scale_is_undone_and_the_velocity_fused():
    est = KinematicEstimator()
    for track_id in range(3):
        x, y, vx, vy = _straight(40, 10.0 + track_id, noise_m=0.03, seed=track_id)
        _run(est, track_id, x, y, vx * 0.5, vy * 0.5)
    assert est.calibration.trusted and est.calibration.factor == pytest.approx(0.5, abs=0.02)
    x, y, vx, vy = _straight(30, 14.0, noise_m=0.03, seed=9)
    states, _ = _run(est, 9, x, y, vx * 0.5, vy * 0.5, start_ns=10**10)
    # the first sample answers with the calibrated report; from the second the filter fuses it
    assert states[0].source == "reported" and states[0].speed_mps == pytest.approx(14.0, abs=0.5)
    assert all(s.source == "fused" and abs(s.speed_mps - 14.0) < 1.0 for s in states[1:])


def _calibrated():
    est = KinematicEstimator()
    for track_id in range(3):
        x, y, vx, vy = _straight(40, 10.0, noise_m=0.03, seed=track_id)
        _run(est, track_id, x, y, vx, vy)
    assert est.calibration.trusted
    return est


def test_zero_at_birth_is_never_fused_and_counted_while_the_positions_move():
    est = _calibrated()
    x, y, vx, vy = _straight(30, 15.0, noise_m=0.03, seed=5)
    zero = np.where(np.arange(30) < 10, 0.0, 1.0)
    states, issues = _run(est, 5, x, y, vx * zero, vy * zero, start_ns=10**10)
    assert all(abs(s.speed_mps - 15.0) < 1.5 for s in states[2:])
    assert [s.source for s in states[1:10]] == ["positions"] * 9 and states[12].source == "fused"
    zero_issues = [k for k, _ in enumerate(issues) if issues[k].kind == "velocity_zero_while_moving"]
    assert len(zero_issues) >= 7 and {i.kind for i in issues} == {"velocity_zero_while_moving"}


def test_a_wrong_reported_velocity_is_gated_out_once_the_positions_show_motion():
    est = _calibrated()
    x, y, vx, vy = _straight(30, 15.0, noise_m=0.03, seed=5)
    slow = np.where(np.arange(30) < 10, 0.2, 1.0)  # the tracker starts at 3 m/s for a car at 15 m/s
    states, issues = _run(est, 5, x, y, vx * slow, vy * slow, start_ns=10**10)
    assert est.velocity_rejected > 0 and "velocity_rejected" in {i.kind for i in issues}
    assert all(abs(s.speed_mps - 15.0) < 1.5 for s in states[3:])


def test_reversed_velocities_are_inconsistent_by_direction():
    x, y, vx, vy = _straight(40, 10.0)
    est = KinematicEstimator()
    _, issues = _run(est, 7, x, y, -vx, -vy)
    assert [i.kind for i in issues] == ["velocity_inconsistent"]
    assert est.consistency().median_cosine < -0.9


def test_consistent_velocities_raise_nothing():
    x, y, vx, vy = _straight(60, 9.0, noise_m=0.03)
    est = KinematicEstimator()
    _, issues = _run(est, 3, x, y, vx, vy)
    assert issues == [] and est.consistency().tracks_checked == 1 and est.warning() is None


def test_standing_car_with_jitter_stays_standing():
    """3 cm of position jitter (and a tracker reporting noise as velocity): after the 1 s window it stands."""
    rng = np.random.default_rng(1)
    n = 60
    x, y = 5.0 + rng.normal(0, 0.03, n), -3.0 + rng.normal(0, 0.03, n)
    states, issues = _run(KinematicEstimator(), 1, x, y, rng.normal(0, 0.8, n), rng.normal(0, 0.8, n))
    assert issues == []
    later = states[11:]
    assert sum(s.standing for s in later) >= 0.9 * len(later)
    assert all(s.speed_mps == 0.0 and s.accel_mps2 == 0.0 for s in later if s.standing)
    assert np.mean([s.speed_mps for s in later]) < 0.1


def test_a_car_pulling_away_is_released_from_the_dead_band_within_half_a_second():
    t = np.arange(60) * 0.1
    s = np.where(t < 3.0, 0.0, 0.5 * 2.0 * (t - 3.0) ** 2)  # stands 3 s, then 2 m/s²
    states, _ = _run(KinematicEstimator(), 1, s, np.zeros(60), np.zeros(60), np.zeros(60))
    assert all(st.standing for st in states[12:30])
    first_moving = next(k for k in range(30, 60) if not states[k].standing)
    assert first_moving <= 35, first_moving


def test_a_jump_restarts_the_track_and_a_gap_too():
    x, y, vx, vy = _straight(30, 10.0)
    x = x.copy()
    x[20:] += 50.0
    est = KinematicEstimator()
    states, issues = _run(est, 1, x, y, vx, vy)
    assert [i.kind for i in issues] == ["position_jump"]
    assert states[20].source == "reported"
    assert states[-1].speed_mps == pytest.approx(10.0, abs=1.0)
    # the same id 3 s later, elsewhere: a new track
    later_issues = []
    est.update(1, 60 * STEP_NS, 500.0, 500.0, 0.0, 0.0, later_issues)
    assert [i.kind for i in later_issues] == ["track_restarted"]


def test_bad_configuration_is_a_config_error():
    with pytest.raises((ConfigError, ValueError)):
        EstimatorConfig(factor_tolerance=0.9)
    with pytest.raises(ConfigError):
        EstimatorConfig.from_params({"jump_m": "far"})


# --------------------------------------------------------------------------- real data


@pytest.fixture(scope="module")
def k729():
    rec = load_recording(DEFAULT_DATA_DIR, DEFAULT_RECORDING)
    return rec, rec.sequences[0]


def test_on_k729_positions_agree_with_the_trackers_good_velocities(k729):
    """K729's reported velocities are right (checked by hand): the estimate must agree where cars move."""
    _, seq = k729
    est = KinematicEstimator()
    issues = []
    ours, theirs = [], []
    first = {}
    for i in np.lexsort((seq.track_id, seq.stamp_ns)).tolist():
        tid = int(seq.track_id[i])
        first.setdefault(tid, int(seq.stamp_ns[i]))
        s = est.update(tid, int(seq.stamp_ns[i]), float(seq.x_m[i]), float(seq.y_m[i]), float(seq.vx_mps[i]), float(seq.vy_mps[i]), issues)
        reported = math.hypot(seq.vx_mps[i], seq.vy_mps[i])
        if seq.stamp_ns[i] - first[tid] >= 1_000_000_000 and reported > 3.0:
            ours.append(s.speed_mps)
            theirs.append(reported)
    diff = np.abs(np.array(ours) - np.array(theirs))
    assert len(ours) > 100
    assert np.median(diff) < 0.3, np.median(diff)
    assert "velocity_inconsistent" not in {i.kind for i in issues}
    assert est.consistency().tracks_checked >= 2


def _scene(rec, seq) -> SceneInfo:
    return SceneInfo(
        header=Header(run_id="test", frame_index=0, stamp_ns=0, producer="test"),
        scene_id=f"{rec.name}/{seq.id}",
        recording=rec.name,
        location_id=rec.location_id,
        map_name=rec.map_path.name,
        map_sha256="",
        projection="auto",
        origin_lat_deg=seq.origin_lat_deg,
        origin_lon_deg=seq.origin_lon_deg,
        frame_rate_hz=seq.frame_rate_hz,
        speed_limit_mps=13.9,
        n_frames=seq.n_frames,
    )


def _speeds(rec, seq, scene_maps, n_frames, transform):
    builder = CorridorBuilder(CorridorsConfig(), scene_maps=scene_maps)
    scene = _scene(rec, seq)
    out = {}
    issues = []
    for k, view in enumerate(seq.frames()):
        if k >= n_frames:
            break
        vx, vy = transform(np.asarray(view.vx_mps), np.asarray(view.vy_mps), k)
        frame = TrackFrame(
            header=Header(run_id="test", frame_index=k, stamp_ns=int(view.stamp_ns), producer="test"),
            scene_id=scene.scene_id,
            track_ids=view.track_id,
            agent_types=view.agent_type,
            x_m=view.x_m,
            y_m=view.y_m,
            vx_mps=vx,
            vy_mps=vy,
            yaw_rad=view.yaw_rad,
            length_m=view.length_m,
            width_m=view.width_m,
        )
        cs, got = builder.process(frame, scene)
        issues += got
        for v in cs.vehicles:
            out[(k, v.track_id)] = (v.speed_mps, v.vx_mps, v.vy_mps)
    return out, issues


@pytest.mark.parametrize(
    "name, transform, tolerance_mps",
    [
        # a scale or a sign is calibrated away exactly: the same figures to rounding
        ("scaled 0.5", lambda vx, vy, k: (vx * 0.5, vy * 0.5), 1e-9),
        ("scaled 2", lambda vx, vy, k: (vx * 2.0, vy * 2.0), 1e-9),
        ("reversed", lambda vx, vy, k: (-vx, -vy), 1e-9),
        # zeros are gated out or outweighed by the positions: close, not equal
        ("zero for 1 s", lambda vx, vy, k: (vx * 0.0, vy * 0.0) if k < 10 else (vx, vy), 0.5),
    ],
)
def test_corridor_speeds_do_not_depend_on_the_reported_velocity(k729, name, transform, tolerance_mps):
    rec, seq = k729
    maps = SceneMaps()
    base, _ = _speeds(rec, seq, maps, 300, lambda vx, vy, k: (vx, vy))
    other, _ = _speeds(rec, seq, maps, 300, transform)
    assert base.keys() == other.keys()
    first: dict[int, int] = {}
    for k, track_id in sorted(base):
        first.setdefault(track_id, k)
    compared = 0
    for key, (speed, vx, vy) in base.items():
        if key[0] == first[key[1]]:  # a track's first sample carries the reported speed
            continue
        o = other[key]
        if math.isfinite(vx) and (tolerance_mps < 1e-3 or key[0] >= 20):
            assert o[1] == pytest.approx(vx, abs=tolerance_mps) and o[0] == pytest.approx(speed, abs=tolerance_mps), (name, key)
            compared += 1
    assert compared > 100


def test_median_without_arrays_is_numpy_median_bit_for_bit():
    from stages.lib.kinematic_state import _median

    rng = np.random.default_rng(5)
    for n in range(1, 60):
        for _ in range(50):
            values = rng.normal(0.0, 500.0, n)
            if n % 3 == 0:
                values = np.round(values, 1)  # ties
            assert np.float64(_median(values.tolist())).tobytes() == np.float64(np.median(values)).tobytes()
    assert math.isnan(_median([1.0, math.nan, 2.0]))


def test_calibration_window_ring_gives_the_figures_of_the_last_samples_in_order():
    """The calibration keeps its window in a ring: after every sample (past the window's wrap-around) its factor,
    cosine and trust are those computed from the last `calibration_window` samples as a list."""
    from stages.lib.kinematic_state import Calibration

    config = EstimatorConfig(calibration_window=40, calibration_min_samples=10, calibration_min_tracks=2)
    calibration = Calibration(config)
    rng = np.random.default_rng(11)
    history = []
    trusted = kept = 0
    for k in range(300):
        track_id = int(rng.integers(0, 3)) if k < 150 else 7  # then one track only: too few tracks once the window is its
        factor, cosine = float(rng.lognormal(0.0, 0.05 if k % 50 < 40 else 1.0)), float(rng.choice([0.95, 0.99, -0.2]))
        before = (calibration.factor, calibration.cosine, calibration.trusted)
        calibration.add(track_id, factor, cosine)
        history.append((track_id, factor, cosine))
        window = history[-40:]
        if calibration._dirty == 0:  # refreshed on this sample: the figures of the window
            if len(window) >= 10 and len({t for t, _, _ in window}) >= 2:
                arr = np.array([(f, c) for _, f, c in window])
                q1, med, q3 = np.percentile(arr[:, 0], [25, 50, 75])
                assert calibration.factor == float(med) and calibration.cosine == float(np.median(arr[:, 1]))
                assert calibration.trusted == bool(0.2 <= med <= 5.0 and abs(calibration.cosine) >= 0.9
                                                   and (q3 - q1) <= config.calibration_max_spread * med)
                trusted += calibration.trusted
            else:  # too few samples or tracks in the window: the figures stay
                kept += 1
                assert (calibration.factor, calibration.cosine, calibration.trusted) == before or math.isnan(before[0])
    assert 0 < trusted and kept > 10
    assert Calibration(EstimatorConfig(calibration_window=0)).add(1, 1.0, 1.0) is None  # a window of none keeps nothing


def test_calibration_quantiles_from_its_sorted_window_are_numpys():
    """The calibration reads its quantiles off its window kept sorted (numpy only while NaN, infinite or signed-zero
    values are in it): after every sample, factor and cosine are np.percentile's and np.median's of the window bit for
    bit, through windows with and without such values, odd and even lengths, ties."""
    from stages.lib.kinematic_state import Calibration

    rng = np.random.default_rng(29)
    for window in (31, 40):
        config = EstimatorConfig(calibration_window=window, calibration_min_samples=5, calibration_min_tracks=1)
        calibration = Calibration(config)
        history = []
        sorted_path = numpy_path = 0
        for k in range(600):
            # wide magnitudes of both signs too: there the interpolation's rounding depends on numpy's formula
            factor = float(rng.lognormal(0.0, 0.3 if k % 3 else 3.0) * (1.0 if k % 5 else -1.0))
            cosine = float(rng.choice([0.95, 0.99, -0.2, 0.5])) if k % 7 else float(rng.lognormal(0.0, 3.0) * rng.choice([-1.0, 1.0]))
            if 200 <= k < 260 and k % 9 == 0:
                factor = float(rng.choice([np.nan, 0.0, -0.0, np.inf]))
                cosine = float(rng.choice([np.nan, 0.0, -0.0, -np.inf]))
            calibration._dirty = 10  # refresh on every sample
            calibration.add(1, factor, cosine)
            history.append((factor, cosine))
            arr = np.array(history[-window:])
            if len(arr) < 5:
                continue
            special = not (np.isfinite(arr).all() and (arr != 0.0).all())
            sorted_path += not special
            numpy_path += special
            with np.errstate(invalid="ignore"):
                q1, med, q3 = np.percentile(arr[:, 0], [25, 50, 75])
                cosine_median = np.median(arr[:, 1])
            assert np.float64(calibration.factor).tobytes() == np.float64(med).tobytes(), k
            assert np.float64(calibration.cosine).tobytes() == np.float64(cosine_median).tobytes(), k
            assert calibration.trusted == bool(0.2 <= med <= 5.0 and abs(cosine_median) >= 0.9 and (q3 - q1) <= config.calibration_max_spread * med)
        assert sorted_path > 300 and numpy_path > 40


def _many_tracks(est, n_tracks, make, n=120):
    """Feed ``n_tracks`` tracks one after the other (ids 1..), each from ``make(seed) -> x, y``; reported zero."""
    for k in range(n_tracks):
        x, y = make(k)
        _run(est, k + 1, x, y, np.zeros(n), np.zeros(n), start_ns=k * n * STEP_NS)


def test_the_filter_bank_picks_a_smoother_filter_for_a_noisy_tracker_and_keeps_the_quick_one_for_a_clean_one():
    """Back test: each filter's speed 2 s ago against the distance covered since. Noisy positions of steady cars
    want a smooth filter; clean positions of cars that brake and accelerate want the quick default."""
    def noisy(seed):
        x, y, _, _ = _straight(120, 9.0, noise_m=0.4, seed=seed)
        return x, y

    def clean_varying(seed):
        t = np.arange(120) * 0.1
        s = 8.0 * t + 6.0 * np.sin(0.9 * t + seed)  # speed 8 ± 5.4 m/s
        return s * math.cos(0.3), s * math.sin(0.3)

    est = KinematicEstimator(EstimatorConfig(fuse_reported=False))
    _many_tracks(est, 12, noisy)
    report = est.backtest()
    assert est.accel_noise == 1.0 and report["samples"] >= 300 and report["switches"] >= 1, report
    assert report["rms_m"]["1"] < report["rms_m"]["10"]
    est = KinematicEstimator(EstimatorConfig(fuse_reported=False))
    _many_tracks(est, 12, clean_varying)
    report = est.backtest()
    assert est.accel_noise == 10.0 and report["samples"] >= 300 and report["switches"] == 0, report
    assert report["rms_m"]["10"] < report["rms_m"]["1"]


def test_a_bank_of_one_is_the_single_filter_and_the_bank_is_validated():
    x, y, vx, vy = _straight(60, 11.0, noise_m=0.2, seed=3)
    one, _ = _run(KinematicEstimator(EstimatorConfig(accel_noise_bank=(10.0,))), 1, x, y, vx, vy)
    bank, _ = _run(KinematicEstimator(), 1, x, y, vx, vy)  # too few samples to judge: the default filter is published
    assert [s.speed_mps for s in one] == [s.speed_mps for s in bank]
    assert EstimatorConfig(accel_noise_m2ps3=5.0).filter_bank == (1.0, 3.0, 5.0, 10.0)
    for bad in ((), (1.0, 1.0), (0.0, 2.0), (float("nan"),)):
        if bad == ():
            assert EstimatorConfig(accel_noise_bank=bad).filter_bank == (10.0,)
            continue
        with pytest.raises(ValueError, match="accel_noise_bank"):
            EstimatorConfig(accel_noise_bank=bad)


def test_a_long_live_stream_keeps_the_last_decided_tracks_and_still_warns_when_its_tracker_turns_bad(monkeypatch):
    """A live tracker's stream decides thousands of tracks a day: the estimator kept every one and judged the warning
    on all of them at every frame (its cost grew all day). It keeps the last ``DECIDED_WINDOW``; a tracker whose
    velocities go bad after a good spell is still told, once, from the recent tracks."""
    from stages.lib import kinematic_state

    monkeypatch.setattr(kinematic_state, "DECIDED_WINDOW", 8)
    est = KinematicEstimator()
    x, y, vx, vy = _straight(30, 10.0, noise_m=0.03)
    for track_id in range(12):  # good velocities
        _run(est, track_id, x, y, vx, vy, start_ns=track_id * 40 * STEP_NS)
        assert est.warning() is None
    assert len(est.decided) == 8 and est.consistency().tracks_checked == 8
    for track_id in range(12, 20):  # the tracker's velocities halve: the 8 kept tracks are all bad ones
        _run(est, track_id, x, y, vx * 0.5, vy * 0.5, start_ns=track_id * 40 * STEP_NS)
    line = est.warning()
    assert line is not None and "8 of 8 tracks" in line
    assert est.warning() is None  # once
