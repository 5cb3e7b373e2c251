"""``iamp eval`` on a slice of the embedded scenario: the report's keys, finite values, figures and the CLI."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from stages import cli
from stages.lib.datasets import DEFAULT_DATA_DIR, DEFAULT_RECORDING, DEFAULT_SEQUENCE
from stages.offline.evaluation import EVAL_MODES, EvalConfig, Evaluation, _route_hit, format_table
from stages.offline.truth import Track, future_positions
from stages.markov_prediction.rasterise import highest_density_threshold

METRICS = ("windows", "mADE_m", "mFDE_m", "wADE_m", "wFDE_m", "coverage50", "coverage90", "nll")
ROUTE = ("route_top1", "route_windows")


@pytest.fixture(scope="module")
def slice_report(tmp_path_factory):
    figures = tmp_path_factory.mktemp("figures")
    config = EvalConfig(
        data_dir=DEFAULT_DATA_DIR,
        recordings=(DEFAULT_RECORDING,),
        sequences=(DEFAULT_SEQUENCE,),
        stride_s=0.8,
        max_frames_per_sequence=120,
        progress=False,
    )
    evaluation = Evaluation(config)
    report = evaluation.run()
    return report, evaluation.write_figures(figures), figures


def test_report_has_every_key_with_finite_values(slice_report):
    report, _, _ = slice_report
    assert set(report["modes"]) == set(EVAL_MODES)
    windows = {m: report["modes"][m]["overall"]["windows"] for m in EVAL_MODES}
    assert len(set(windows.values())) == 1 and windows["baseline"] > 0, "every mode is scored on the same windows"
    for mode, res in report["modes"].items():
        groups = [res["overall"], res["by_speed"]["slow"], res["by_speed"]["fast"], *res["by_recording"].values(),
                  *res["by_manoeuvre"].values()]
        assert sum(g["windows"] for g in res["by_manoeuvre"].values()) == res["overall"]["windows"]
        assert list(res["by_recording"]) == [DEFAULT_RECORDING]
        for group in groups:
            assert set(group) == set(METRICS) | set(ROUTE)
            assert 0 <= group["route_windows"] <= group["windows"]
            if group["route_windows"]:
                assert 0.0 <= group["route_top1"] <= 1.0
            if group["windows"]:
                assert all(math.isfinite(group[k]) for k in METRICS), (mode, group)
                assert 0.0 <= group["coverage50"] <= group["coverage90"] <= 1.0 and group["nll"] >= 0.0
                assert group["mADE_m"] <= group["wADE_m"] + 1e-9 and group["mFDE_m"] <= group["wFDE_m"] + 1e-9
        assert res["by_speed"]["slow"]["windows"] + res["by_speed"]["fast"]["windows"] == res["overall"]["windows"]
        for key in ("frame_ms_median", "frame_ms_p95", "vehicles_per_frame_mean"):
            assert math.isfinite(res[key]) and res[key] > 0
    assert report["modes"]["cv"]["overall"]["route_windows"] == 0, "the cv line has no corridors to choose between"
    assert report["corridor_weights"] == "intentions" and report["intentions_ms_median"] > 0
    table = format_table(report)
    assert "baseline" in table and "by manoeuvre (true future)" in table and "along-track bias at 4 s" in table
    # the grids are the default's, calibrated with the shipped table, which was fitted on this very recording (in-sample)
    grids = report["grids"]
    assert grids["spread_calibration"] == "shipped" and grids["spread_online"] and grids["spread_in_sample"] == [DEFAULT_RECORDING]
    assert DEFAULT_RECORDING in grids["spread_fitted_on"] and f"IN-SAMPLE on {DEFAULT_RECORDING} (cov50, cov90 and NLL" in table
    json.dumps(report)


def test_figures_are_png_and_svg_files(slice_report):
    _, written, folder = slice_report
    stems = {p.stem for p in written}
    assert {p.suffix for p in written} == {".png", ".svg"} and len(written) == 2 * len(stems)
    names = sorted(s for s in stems if not s.startswith("accel_"))
    assert names == sorted([f"grid_4s_{m}_{DEFAULT_RECORDING}" for m in ("hybrid", "baseline")] + [f"means_{DEFAULT_RECORDING}"])
    accel = [s for s in stems if s.startswith("accel_")]
    assert 1 <= len(accel) <= 2, "hybrid mode draws the acceleration-distribution figure for a car or two per recording"
    for path in written:
        head = path.read_bytes()[:200]
        assert head[:8] == b"\x89PNG\r\n\x1a\n" if path.suffix == ".png" else b"<svg" in head or b"<?xml" in head
    text = (folder / "figures.txt").read_text()
    assert "instant" in text and "AR output red" in text


def test_cli_writes_json(tmp_path, capsys):
    out = tmp_path / "eval.json"
    code = cli.main(
        ["eval", "--recording", DEFAULT_RECORDING, "--sequence", DEFAULT_SEQUENCE, "--max-frames", "40", "--stride", "2.0",
         "--mode", "cv", "corridor_cv", "--json", str(out), "--no-progress"]
    )
    assert code == 0
    data = json.loads(out.read_text())
    assert set(data["modes"]) == {"cv", "corridor_cv"}
    assert "mADE" in capsys.readouterr().out
    assert cli.main(["eval", "--data", str(tmp_path / "nothing"), "--no-progress"]) == 2


def test_ground_truth_must_be_complete_and_bridges_one_missing_frame():
    stamps = np.arange(0, 50) * 100_000_000
    xy = np.column_stack([np.arange(50.0), np.zeros(50)])
    def track(rows):
        return Track(stamps[rows], xy[rows], np.zeros(rows.size), np.zeros(rows.size))

    every = np.arange(50)
    future = future_positions(track(every), 0, 400_000_000, 10)
    np.testing.assert_array_equal(future[:, 0], np.arange(4.0, 41.0, 4.0))
    assert future_positions(track(every), 1_200_000_000, 400_000_000, 10) is None  # 4 s after 1.2 s is past the track
    hole = np.delete(every, 8)  # one frame missing (at 0.8 s): the line between its neighbours
    np.testing.assert_array_equal(future_positions(track(hole), 0, 400_000_000, 10)[:, 0], np.arange(4.0, 41.0, 4.0))
    holes = np.delete(every, [8, 9])  # two: 300 ms between the rows around them, the time not known
    assert future_positions(track(holes), 0, 400_000_000, 10) is None
    assert future_positions(None, 0, 400_000_000, 10) is None


def test_highest_density_region():
    values = np.array([0.5, 0.3, 0.15, 0.05])
    assert highest_density_threshold(values, 0.9) == pytest.approx(0.15)
    assert highest_density_threshold(np.array([0.4, 0.2]), 0.9) == pytest.approx(0.2)  # less than 90 %: every cell


def test_route_hit_scores_the_followed_corridor_and_splits_ties():
    from types import SimpleNamespace

    import bus_schemas as bs

    def corridor(cid, y_end):
        s = np.arange(0.0, 60.5, 0.5)
        y = np.where(s > 20.0, (s - 20.0) / 40.0 * y_end, 0.0)
        return bs.Corridor(
            corridor_id=cid, lanelet_ids=np.array([1], np.int64), lanelet_start_s_m=np.array([0.0]), x_m=s.copy(), y_m=y, s_m=s,
            heading_rad=np.zeros_like(s), curvature_1pm=np.zeros_like(s), width_m=np.full(s.shape, 3.5),
            extension_start_s_m=60.0, vehicle_s_m=0.0, vehicle_d_m=0.0, speed_limit_mps=13.9,
        )

    vehicle = SimpleNamespace(corridors=(corridor(1, 0.0), corridor(2, 15.0)))
    prediction = SimpleNamespace(pairs=(SimpleNamespace(corridor_id=1), SimpleNamespace(corridor_id=2)))
    straight = np.column_stack([np.linspace(4, 40, 10), np.zeros(10)])
    assert _route_hit(prediction, [0, 1], np.array([0.7, 0.3]), vehicle, straight) == 1.0
    assert _route_hit(prediction, [0, 1], np.array([0.3, 0.7]), vehicle, straight) == 0.0
    assert _route_hit(prediction, [0, 1], np.array([0.5, 0.5]), vehicle, straight) == 0.5
    assert _route_hit(prediction, [0], np.array([1.0]), vehicle, straight) is None  # one corridor: nothing to choose
    early = np.column_stack([np.linspace(1, 10, 10), np.zeros(10)])  # before the branch: the future does not decide
    assert _route_hit(prediction, [0, 1], np.array([0.7, 0.3]), vehicle, early) is None
