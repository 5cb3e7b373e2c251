"""bench/oracle_profiles.py: the true future acceleration put in place of the AR model's, the true start speed in place
of the estimate, and the run that scores hybrid with them (issue 15's decomposition: how far perfect inputs go)."""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from bus_schemas import AccelerationProfile, AccelerationProfiles, AgentType, CorridorSet, Header, MatchStatus, VehicleCorridors
from stages.lib.ar.inference import chunk_distributions
from stages.offline.truth import Track

REPO = Path(__file__).resolve().parents[1]
_spec = importlib.util.spec_from_file_location("oracle_profiles", REPO / "bench" / "oracle_profiles.py")
oracle = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(oracle)

PERIOD = 100_000_000


def _track(n: int, speed: float = 5.0, accel: np.ndarray | None = None) -> Track:
    stamps = np.arange(n, dtype=np.int64) * PERIOD
    x = speed * stamps * 1e-9
    a = np.full(n, np.nan) if accel is None else accel
    return Track(stamps, np.column_stack([x, np.zeros(n)]), np.full(n, speed), a)


def test_true_accelerations_hold_the_last_known_value_past_the_track():
    accel = np.full(30, np.nan)
    accel[:20] = np.linspace(-1.0, 1.0, 20)
    got = oracle.true_accelerations(_track(30, accel=accel), 10 * PERIOD, PERIOD, 40)
    assert got.shape == (40,)
    np.testing.assert_allclose(got[:9], accel[11:20])  # steps 1..9 are rows 11..19
    assert np.all(got[9:] == accel[19])  # unknown from row 20 on, and no row past 29: the last known held
    assert oracle.true_accelerations(None, 0, PERIOD, 40) is None
    assert np.all(oracle.true_accelerations(_track(5), 0, PERIOD, 4) == 0.0)  # none known at all: 0


def test_oracle_profiles_replace_the_mean_and_keep_the_spread_recipe():
    edges = np.linspace(-4.0, 4.0, 11)
    accel = np.concatenate([np.full(25, 1.5), np.full(25, -0.5)])
    truth = {7: _track(50, accel=accel)}
    h = Header(run_id="t", frame_index=0, stamp_ns=0, producer="t", source_wall_ns=0)
    learned = AccelerationProfile(track_id=7, corridor_id=1, history_steps=40, accel_mps2=np.zeros(40, np.float32),
                                  chunk_mean_mps2=np.zeros(10, np.float32), chunk_sigma_mps2=np.full(10, 0.5, np.float32),
                                  input_probs=np.full((10, 10), 0.1, np.float32))
    other = AccelerationProfile(track_id=8, corridor_id=1, history_steps=40, accel_mps2=np.zeros(40, np.float32),
                                chunk_mean_mps2=np.zeros(10, np.float32), chunk_sigma_mps2=np.full(10, 0.5, np.float32),
                                input_probs=np.full((10, 10), 0.1, np.float32))
    msg = AccelerationProfiles(header=h, scene_id="s", model="m", step_s=0.1, chunk_s=0.4, input_edges_mps2=edges, profiles=(learned, other))
    sigma_res = np.full(10, 0.3)
    out, n = oracle.oracle_profiles(msg, truth, 0, sigma_res, sigma_scale=1.0, sigma_floor=0.25)
    assert n == 1  # track 8 has no truth: kept as it was
    mine, kept = out.profiles
    assert kept is other
    np.testing.assert_allclose(mine.accel_mps2, accel[1:41], rtol=1e-6)
    mu, sigma, probs = chunk_distributions(accel[None, 1:41], 4, sigma_res, edges)
    np.testing.assert_allclose(mine.chunk_mean_mps2, mu[0], rtol=1e-6)
    np.testing.assert_allclose(mine.chunk_sigma_mps2, sigma[0], rtol=1e-6)
    np.testing.assert_allclose(mine.input_probs, probs[0], rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(mine.input_probs.sum(axis=1), 1.0, rtol=1e-5)
    AccelerationProfiles.decode(out.encode())  # still a valid message


def test_true_speed_from_positions_and_only_inside_a_whole_window():
    track = _track(40, speed=6.0)
    assert oracle.true_speed(track, 20 * PERIOD, PERIOD) == pytest.approx(6.0, rel=1e-9)
    assert oracle.true_speed(track, 2 * PERIOD, PERIOD) is None  # the 1.5 s window does not fit before it
    assert oracle.true_speed(track, 38 * PERIOD, PERIOD) is None  # nor after it
    assert oracle.true_speed(track, 20 * PERIOD + PERIOD // 2, PERIOD) is None  # no row at that stamp
    gap = Track(np.concatenate([track.stamps_ns[:21], track.stamps_ns[21:] + PERIOD]), track.xy, track.speed_mps, track.accel_mps2)
    assert oracle.true_speed(gap, 20 * PERIOD, PERIOD) is None  # a gap inside the window


def test_with_true_speeds_replaces_only_vehicles_with_a_true_speed():
    h = Header(run_id="t", frame_index=0, stamp_ns=20 * PERIOD, producer="t", source_wall_ns=0)

    def vehicle(track_id: int) -> VehicleCorridors:
        return VehicleCorridors(track_id=track_id, agent_type=AgentType.CAR, status=MatchStatus.MATCHED, lanelet_id=-1,
                                match_distance_m=0.0, speed_mps=1.0, corridors=())

    cs = CorridorSet(header=h, scene_id="s", vehicles=(vehicle(1), vehicle(2)))
    out, n = oracle.with_true_speeds(cs, {1: _track(40, speed=6.0)}, 20 * PERIOD, PERIOD)
    assert n == 1
    assert out.vehicles[0].speed_mps == pytest.approx(6.0) and out.vehicles[1].speed_mps == 1.0


def test_the_bench_scores_each_variant_on_the_embedded_scenario(tmp_path):
    out = tmp_path / "oracle.json"
    env = {k: v for k, v in os.environ.items() if k != "IAMP_TAF_BW"}
    env["OMP_NUM_THREADS"] = "1"
    r = subprocess.run([sys.executable, str(REPO / "bench" / "oracle_profiles.py"), "--mode", "hybrid", "corridor_cv", "--no-progress",
                        "--max-frames", "60", "--oracle", "none", "profiles", "speed", "--json", str(out)],
                       cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    report = json.loads(out.read_text())
    variants = report["variants"]
    assert variants["none"]["oracle"]["profiles_replaced"] == 0 and variants["none"]["oracle"]["speeds_replaced"] == 0
    assert variants["profiles"]["oracle"]["profiles_replaced"] > 0 and variants["profiles"]["oracle"]["speeds_replaced"] == 0
    assert variants["speed"]["oracle"]["speeds_replaced"] > 0 and variants["speed"]["oracle"]["profiles_replaced"] == 0
    s = report["summary"]
    # the profiles reach hybrid only; the true speeds reach every mode
    assert s["profiles"]["corridor_cv"]["mADE_m"] == s["none"]["corridor_cv"]["mADE_m"]
    assert s["profiles"]["hybrid"]["mADE_m"] != s["none"]["hybrid"]["mADE_m"]
    assert s["speed"]["corridor_cv"]["mADE_m"] != s["none"]["corridor_cv"]["mADE_m"]
    assert "summary: mADE" in r.stdout


def test_the_bench_refuses_profiles_without_hybrid(tmp_path):
    r = subprocess.run([sys.executable, str(REPO / "bench" / "oracle_profiles.py"), "--mode", "corridor_cv", "--oracle", "profiles"],
                       cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "add hybrid to --mode" in r.stderr
