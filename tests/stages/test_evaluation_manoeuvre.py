"""``iamp eval``'s split by the true future's manoeuvre and its along/cross-track errors.

The classification and the decomposition on synthetic futures with known
answers; a short ``iamp eval`` on the embedded scenario writes the three keys
(``by_manoeuvre``, ``along_track_m``, ``cross_track_m``) with the five classes.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from stages import cli
from stages.lib.datasets import DEFAULT_DATA_DIR, DEFAULT_RECORDING, DEFAULT_SEQUENCE
from stages.offline.evaluation import TRACK_HORIZONS_S, _along_cross
from stages.offline.truth import MANOEUVRES, along_track_directions, manoeuvre_class

STEP_S = 0.4
K = 10


def _speed_profile(v0: float, v1: float) -> np.ndarray:
    """Future positions (K, 2) along +x of a car going from v0 to v1 m/s at constant acceleration over 4 s."""
    t = np.arange(1, K + 1) * STEP_S
    a = (v1 - v0) / (K * STEP_S)
    return np.column_stack([v0 * t + 0.5 * a * t**2, np.zeros(K)])


def _arc(speed: float, turn_deg: float) -> np.ndarray:
    """Future positions (K, 2) at constant speed on a circle turning left by turn_deg over 4 s, starting along +x."""
    t = np.arange(1, K + 1) * STEP_S
    omega = math.radians(turn_deg) / (K * STEP_S)
    r = speed / omega
    return np.column_stack([r * np.sin(omega * t), r * (1.0 - np.cos(omega * t))])


def test_one_synthetic_future_per_class():
    start = (0.0, 0.0)
    rng = np.random.default_rng(0)
    jitter = rng.normal(0.0, 0.05, (K, 2))
    assert manoeuvre_class(start, jitter, STEP_S) == "stands"
    assert manoeuvre_class(start, _arc(8.0, 90.0), STEP_S) == "turns"
    assert manoeuvre_class(start, _speed_profile(12.0, 5.0), STEP_S) == "brakes"
    assert manoeuvre_class(start, _speed_profile(0.0, 6.0), STEP_S) == "accelerates"  # a start from standstill
    assert manoeuvre_class(start, _speed_profile(10.0, 10.5), STEP_S) == "keeps_speed"
    assert set(MANOEUVRES) == {"stands", "turns", "brakes", "accelerates", "keeps_speed"}


def test_classification_thresholds_and_priority():
    start = (0.0, 0.0)
    assert manoeuvre_class(start, _speed_profile(0.2, 0.2), STEP_S) == "stands"  # 0.8 m in 4 s
    assert manoeuvre_class(start, _arc(8.0, 20.0), STEP_S) == "keeps_speed"  # a bend below 30 degrees
    assert manoeuvre_class(start, _arc(8.0, 45.0), STEP_S) == "turns"
    # braking while turning: turns first
    t = np.arange(1, K + 1) * STEP_S
    s = 10.0 * t - 0.5 * 2.0 * t**2
    theta = np.radians(90.0) * s / s[-1]
    r = s[-1] / np.radians(90.0)
    assert manoeuvre_class(start, np.column_stack([r * np.sin(theta), r * (1 - np.cos(theta))]), STEP_S) == "turns"
    # small speed changes: 10 -> 8.5 m/s is below 2 m/s (and below 30 %); 3 -> 2.2 m/s is below the 1 m/s floor
    assert manoeuvre_class(start, _speed_profile(10.0, 8.5), STEP_S) == "keeps_speed"
    assert manoeuvre_class(start, _speed_profile(3.0, 2.2), STEP_S) == "keeps_speed"
    # 5 -> 3 m/s: mean speeds over the first and last 0.8 s 4.8 and 3.2 m/s, 1.6 m/s below 2 m/s but above 30 % of 4.8
    assert manoeuvre_class(start, _speed_profile(5.0, 3.0), STEP_S) == "brakes"
    # the speeds come from the positions: the start position counts, no velocity is passed at all
    assert manoeuvre_class((-100.0, 0.0), _speed_profile(10.0, 10.0), STEP_S) == "brakes"


def test_along_cross_decomposition_known_answer():
    # a straight truth along +y at 5 m/s; the prediction 2 m ahead and 1 m to the left (-x when heading +y)
    t = np.arange(1, K + 1) * STEP_S
    truth = np.column_stack([np.zeros(K), 5.0 * t])
    directions = along_track_directions((0.0, 0.0), truth)
    np.testing.assert_allclose(directions, np.tile([0.0, 1.0], (K, 1)), atol=1e-12)
    prediction = truth + np.array([-1.0, 2.0])
    along, cross = _along_cross(prediction - truth, directions)
    np.testing.assert_allclose(along, 2.0)
    np.testing.assert_allclose(cross, 1.0)  # + = left of the truth
    np.testing.assert_allclose(along**2 + cross**2, np.sum((prediction - truth) ** 2, axis=1))
    # behind and to the right
    along, cross = _along_cross(np.tile([1.0, -3.0], (K, 1)), directions)
    np.testing.assert_allclose(along, -3.0)
    np.testing.assert_allclose(cross, -1.0)


def test_along_track_direction_on_a_curve_and_standing():
    truth = _arc(8.0, 90.0)
    directions = along_track_directions((0.0, 0.0), truth)
    np.testing.assert_allclose(np.hypot(*directions.T), 1.0)
    assert directions[-1] @ np.array([0.0, 1.0]) > 0.95  # the end of a 90 degree left turn heads +y
    error = np.random.default_rng(1).normal(0.0, 2.0, (K, 2))
    along, cross = _along_cross(error, directions)
    np.testing.assert_allclose(along**2 + cross**2, np.sum(error**2, axis=1))
    # a car that stops: at the last steps the central difference is ~0, the direction is that from the start
    stop = np.column_stack([np.minimum(np.arange(1, K + 1), 4) * 1.0, np.zeros(K)])
    directions = along_track_directions((0.0, 0.0), stop)
    np.testing.assert_allclose(directions[-1], [1.0, 0.0])
    # standing still: no direction; the error counts as cross-track only (its whole length)
    directions = along_track_directions((0.0, 0.0), np.zeros((K, 2)))
    assert np.isnan(directions).all()
    along, cross = _along_cross(np.tile([3.0, 4.0], (K, 1)), directions)
    assert np.isnan(along).all()
    np.testing.assert_allclose(cross, 5.0)


def test_cli_writes_manoeuvre_and_track_split(tmp_path, capsys):
    if not (DEFAULT_DATA_DIR / "maps").is_dir():
        pytest.skip(f"embedded TAF-BW data not found at {DEFAULT_DATA_DIR}")
    out = tmp_path / "eval.json"
    code = cli.main(
        ["eval", "--recording", DEFAULT_RECORDING, "--sequence", DEFAULT_SEQUENCE, "--max-frames", "40", "--stride", "2.0",
         "--mode", "cv", "corridor_cv", "--json", str(out), "--no-progress"]
    )
    assert code == 0
    printed = capsys.readouterr().out
    assert "by manoeuvre (true future)" in printed and "along-track bias at 4 s" in printed
    data = json.loads(out.read_text())
    horizons = [f"{h:g}s" for h in TRACK_HORIZONS_S]
    for mode in ("cv", "corridor_cv"):
        res = data["modes"][mode]
        assert list(res["by_manoeuvre"]) == list(MANOEUVRES)
        assert sum(s["windows"] for s in res["by_manoeuvre"].values()) == res["overall"]["windows"] > 0
        assert set(res["by_manoeuvre"]["stands"]) == set(res["by_speed"]["slow"])
        for key, fields in (("along_track_m", {"t_s", "n", "mean", "rms"}), ("cross_track_m", {"t_s", "n", "mean_abs", "rms", "mean_left"})):
            split = res[key]
            assert list(split["by_manoeuvre"]) == list(MANOEUVRES)
            for group in [split["overall"], *split["by_manoeuvre"].values()]:
                assert list(group) == horizons
                assert [g["t_s"] for g in group.values()] == [1.2, 2.0, 3.2, 4.0]
                for g in group.values():
                    assert set(g) == fields
            assert split["overall"]["4s"]["n"] == sum(g["4s"]["n"] for g in split["by_manoeuvre"].values())
        assert res["cross_track_m"]["overall"]["4s"]["n"] == res["overall"]["windows"]
        assert res["along_track_m"]["overall"]["4s"]["n"] <= res["overall"]["windows"]

