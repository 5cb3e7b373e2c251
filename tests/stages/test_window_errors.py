"""bench/window_errors.py: one row per scored window whose ADEs average to iamp eval's mADE, and the gap table."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from bench.window_errors import accel_se_line, gap_table, main, ratio_interval, ratio_lines
from stages.lib.datasets import DEFAULT_DATA_DIR, DEFAULT_RECORDING, DEFAULT_SEQUENCE
from stages.offline.truth import MANOEUVRES


def test_rows_match_the_eval_report(tmp_path, capsys):
    if not (DEFAULT_DATA_DIR / "maps").is_dir():
        pytest.skip(f"embedded TAF-BW data not found at {DEFAULT_DATA_DIR}")
    rows, report = tmp_path / "w.jsonl", tmp_path / "eval.json"
    code = main(["--recording", DEFAULT_RECORDING, "--sequence", DEFAULT_SEQUENCE, "--max-frames", "40", "--stride", "2.0",
                 "--mode", "cv", "corridor_cv", "--no-progress", "--windows", str(rows), "--json", str(report),
                 "--compare", "corridor_cv", "cv", "--split", "all"])
    assert code == 0
    windows = [json.loads(line) for line in rows.read_text().splitlines()]
    data = json.loads(report.read_text())
    for mode in ("cv", "corridor_cv"):
        overall = data["modes"][mode]["overall"]
        assert len(windows) == overall["windows"] > 0
        assert math.isclose(np.mean([w["modes"][mode]["ade"] for w in windows]), overall["mADE_m"], rel_tol=1e-9)
        for cls in MANOEUVRES:
            assert sum(w["manoeuvre"] == cls for w in windows) == data["modes"][mode]["by_manoeuvre"][cls]["windows"]
        fast = [w for w in windows if w["split"] == "fast"]
        assert len(fast) == data["modes"][mode]["by_speed"]["fast"]["windows"]
    se = [w["accel_se_mps2"] for w in windows]
    assert any(math.isfinite(x) and x >= 0 for x in se) and all(math.isnan(x) or x >= 0 for x in se)
    printed = capsys.readouterr().out
    assert "-- manoeuvre" in printed and "-- leader" in printed and "-- corridor" in printed
    # --from-windows reads the dump back without running
    assert main(["--from-windows", str(rows), "--compare", "corridor_cv", "cv", "--split", "all"]) == 0
    assert f"all windows: {len(windows)};" in capsys.readouterr().out


def test_gap_table_shares_add_up():
    def row(split, man, leader, a, b):
        return {"split": split, "manoeuvre": man, "leader": leader, "conflict": False, "turning": man == "turns",
                "modes": {"A": {"ade": a, "along4": -1.0}, "B": {"ade": b, "along4": math.nan}}}

    windows = [row("fast", "turns", False, 4.0, 2.0), row("fast", "brakes", True, 2.0, 1.0), row("slow", "stands", False, 9.0, 0.0)]
    lines = gap_table(windows, "A", "B", "fast")
    assert lines[0].startswith("fast windows: 2;") and "summed ADE difference 3.0 m" in lines[0]
    turns = next(line for line in lines if line.startswith("turns "))
    brakes = next(line for line in lines if line.startswith("brakes "))
    assert "67%" in turns and "33%" in brakes and "+2.00" in turns
    assert gap_table(windows, "A", "C", "fast") == ["no fast windows with A and C"]


def test_accel_se_line_takes_the_median_per_split_of_the_windows_with_a_measurement():
    windows = [{"split": "fast", "accel_se_mps2": x} for x in (0.1, 0.3, 0.2, math.nan)] + [{"split": "slow"}]
    line = accel_se_line(windows)
    assert "fast 0.200 m/s2 (3 windows)" in line and "slow -" in line


def _car_windows(track_id, n, a, b, split="fast", manoeuvre="keeps_speed", recording="r"):
    return [{"recording": recording, "track_id": track_id, "split": split, "manoeuvre": manoeuvre,
             "modes": {"A": {"ade": a}, "B": {"ade": b}}} for _ in range(n)]


def test_ratio_interval_resamples_cars_not_windows():
    # every car the same ratio: the interval is that ratio, whatever the draws
    same = [w for t in range(10) for w in _car_windows(t, 3, 1.0 + t, 2.0 + 2 * t)]
    r = ratio_interval(same, "A", "B")
    assert r["ratio"] == pytest.approx(0.5) and r["lo"] == pytest.approx(0.5) and r["hi"] == pytest.approx(0.5)
    assert (r["windows"], r["cars"]) == (30, 10)
    # two kinds of car: the interval holds the ratio, is reproducible, and narrows with more cars
    mixed = [w for t in range(20) for w in _car_windows(t, 5, 1.0 if t % 2 else 3.0, 2.0)]
    r20 = ratio_interval(mixed, "A", "B")
    assert r20["ratio"] == pytest.approx(1.0) and r20["lo"] < 1.0 < r20["hi"] and r20 == ratio_interval(mixed, "A", "B")
    many = [w for t in range(200) for w in _car_windows(t, 5, 1.0 if t % 2 else 3.0, 2.0)]
    r200 = ratio_interval(many, "A", "B")
    assert r200["hi"] - r200["lo"] < 0.5 * (r20["hi"] - r20["lo"])
    # a car's windows move together: 100 windows of one car weigh as one car when drawn, not as 100 independent ones
    lumped = _car_windows(0, 100, 3.0, 2.0) + [w for t in range(1, 20) for w in _car_windows(t, 1, 1.0, 2.0)]
    spread = [w for t in range(100) for w in _car_windows(1000 + t, 1, 3.0, 2.0)] + [w for t in range(1, 20) for w in _car_windows(t, 1, 1.0, 2.0)]
    a, b = ratio_interval(lumped, "A", "B"), ratio_interval(spread, "A", "B")
    assert a["ratio"] == pytest.approx(b["ratio"]) and (a["hi"] - a["lo"]) > 2 * (b["hi"] - b["lo"])
    # the same track id in two recordings is two cars
    assert ratio_interval(_car_windows(7, 2, 1.0, 2.0) + _car_windows(7, 2, 1.0, 2.0, recording="s"), "A", "B")["cars"] == 2


def test_ratio_interval_splits():
    windows = (_car_windows(1, 2, 1.0, 2.0, split="slow", manoeuvre="stands") + _car_windows(2, 2, 3.0, 2.0, split="slow")
               + _car_windows(3, 2, 4.0, 2.0))
    assert ratio_interval(windows, "A", "B", "slow")["windows"] == 4
    assert ratio_interval(windows, "A", "B", "fast")["ratio"] == pytest.approx(2.0)
    assert ratio_interval(windows, "A", "B", "moving")["ratio"] == pytest.approx(7.0 / 4.0)
    assert ratio_interval(windows, "A", "C") is None
    lines = ratio_lines(windows, "A", "B", 200)
    assert lines[0].startswith("mADE A / B, 95 % interval") and any(line.strip().startswith("moving  1.750") for line in lines)


def test_a_negative_boot_is_a_command_line_error(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--from-windows", "unused.jsonl", "--boot", "-1"])
    assert exc.value.code == 2 and "--boot -1: a number of draws >= 0" in capsys.readouterr().err
