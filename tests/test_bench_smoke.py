"""The dense-traffic benchmarks run end to end on the embedded data and write the JSON keys other tools read
(issue 16: ``modes.<mode>.by_vehicles.<N>.frame_ms_median`` and the rest). Behaviour only: no figure is checked
against a time (the machines are shared); the figures are only required to be there and be finite."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def _run(args: list[str], tmp_path: Path) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k != "IAMP_TAF_BW"}  # the embedded K729 scenario: a fresh checkout's data
    env["OMP_NUM_THREADS"] = "1"
    return subprocess.run([sys.executable, *args], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)


def test_dense_bench_writes_its_keys(tmp_path):
    out = tmp_path / "dense.json"
    r = _run([str(REPO / "bench" / "dense.py"), "--vehicles", "6", "--frames", "3", "--warmup", "1", "--segments", "1",
              "--modes", "hybrid,baseline", "--idle-ms", "1", "--json", str(out)], tmp_path)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    assert "embedded" in r.stdout.splitlines()[0]
    report = json.loads(out.read_text())
    assert report["idle_ms"] == 1.0 and "after 1 ms asleep" in r.stdout
    for mode in ("hybrid", "baseline"):
        n6 = report["modes"][mode]["by_vehicles"]["6"]
        assert n6["frames"] == 3 and n6["vehicles_median"] > 0 and n6["pairs_median"] > 0
        for key in ("frame_ms_median", "frame_ms_p95", "frame_cpu_ms_median"):
            assert math.isfinite(n6[key]) and n6[key] > 0
        markov = n6["stages"]["markov_prediction"]
        for key in ("ms_median", "ms_p95", "cpu_ms_median", "after_last_input_ms_median", "idle_ms_mean"):
            assert math.isfinite(markov[key]) and markov[key] >= 0
        assert set(n6["stages"]) >= {"source", "corridors", "relations", "intentions", "markov_prediction"}
        at_n = n6["at_n"]  # the timed frames within 6 ± 2 vehicles (there may be none of 3)
        assert 0 <= at_n["frames"] <= 3 and at_n["vehicles_within"] == 2
        assert (at_n["frames"] == 0) == math.isnan(at_n["frame_ms_median"])
    assert "ar_inference" in report["modes"]["hybrid"]["by_vehicles"]["6"]["stages"]
    assert "hybrid/baseline frame" in r.stdout
    for key in ("host_reference", "host_reference_end"):  # this host's speed at fixed work, before and after the run
        assert report[key]["python_ms"] > 0 and report[key]["numpy_ms"] > 0
    assert r.stdout.count("host reference v") == 2


def test_frame_phases_names_the_markov_phases(tmp_path):
    out = tmp_path / "phases.json"
    r = _run([str(REPO / "bench" / "frame_phases.py"), "--vehicles", "6", "--frames", "3", "--warmup", "1", "--segments", "1",
              "--function", "stages.markov_prediction.core:MarkovPredictor._mix_standstill",
              "--function", "stages.markov_prediction.core:MarkovPredictor._back_test_choice", "--json", str(out)], tmp_path)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    functions = json.loads(out.read_text())["functions"]
    for name in ("MarkovPredictor._chain_phase", "MarkovPredictor._pairs_phase", "CorridorBuilder.process"):
        assert functions[name]["calls_per_frame"] > 0, name
        # called once a frame: the median frame holds one call's time
        assert 0 < functions[name]["frame_ms_median"] <= functions[name]["ms_per_frame"] * 3, name
    # a staticmethod is wrapped as one: called without an instance, the chain does not fail and bisect its batch
    assert functions["MarkovPredictor._mix_standstill"]["calls_per_frame"] > 0
    # (at most two passes of the frame's chain, and one chain per back test of the online choices: no bisection)
    back_tests = functions.get("MarkovPredictor._back_test_choice", {}).get("calls_per_frame", 0.0)
    assert functions["MarkovPredictor._markov"]["calls_per_frame"] <= 2 * functions["MarkovPredictor._chain_phase"]["calls_per_frame"] + back_tests


def test_markov_kernel_bench_times_the_hybrid_chain_without_map_or_data(tmp_path):
    r = _run([str(REPO / "bench" / "markov_kernel.py"), "--hybrid-only", "--pairs", "2,3", "--repeats", "1"], tmp_path)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    lines = r.stdout.splitlines()
    head = next(i for i, line in enumerate(lines) if line.startswith("hybrid chain"))
    rows = {line.split()[0]: line.split()[-2:] for line in lines[head + 2:] if line.strip()}
    assert {"numpy-numba", "torch-cpu"} <= set(rows)  # "numpy-numba x1" / "x2" split on the space
    for cells in rows.values():
        assert all(float(c) > 0 for c in cells)


def test_markov_kernel_bench_runs_its_full_tables(tmp_path):
    """Without --hybrid-only: the per-backend kernel table, then the hybrid table."""
    r = _run([str(REPO / "bench" / "markov_kernel.py"), "--pairs", "1", "--repeats", "1"], tmp_path)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    assert "numpy-numba" in r.stdout and "hybrid chain" in r.stdout


def test_idle_penalty_bench_replays_the_same_frames_per_gap(tmp_path):
    out = tmp_path / "idle.json"
    r = _run([str(REPO / "bench" / "idle_penalty.py"), "--vehicles", "6", "--frames", "3", "--warmup", "1", "--segments", "1",
              "--rounds", "1", "--repeats", "1", "--gaps", "5,spin2", "--json", str(out)], tmp_path)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    report = json.loads(out.read_text())
    assert report["frames"] == 3 and set(report["gaps"]) == {"0", "5", "spin2"}  # back to back always, as the pairs' base
    assert report["gaps"]["0"]["markov_paired_ms"] == 0.0
    for row in report["gaps"].values():
        for key in ("markov_ms_median", "markov_paired_ms", "python_ms_median", "numba_ms_median"):
            assert math.isfinite(row[key]), key
        assert row["markov_ms_median"] > 0 and row["python_ms_median"] > 0
    bad = _run([str(REPO / "bench" / "idle_penalty.py"), "--gaps", "0,soon"], tmp_path)
    assert bad.returncode == 2 and "--gaps" in bad.stderr


def test_ab_bench_runs_each_version_from_its_own_tree_in_abba_order(tmp_path):
    """bench/ab.py runs the command once per version and round, the base revision from a temporary worktree (its
    packages on PYTHONPATH, removed afterwards) and the head from this tree, and reports the paired differences."""
    probe = ("import json, os, sys, stages; json.dump({'t': {'x': 2.5}, 'own_tree': float(stages.__file__.startswith(os.getcwd())),"
             " 'this_repo': float(os.path.samefile(os.getcwd(), sys.argv[2]))}, open(sys.argv[1], 'w'))")
    out = tmp_path / "ab.json"
    r = _run([str(REPO / "bench" / "ab.py"), "--base", "HEAD", "--rounds", "2", "--metric", "t.x", "--metric", "own_tree",
              "--metric", "this_repo", "--json", str(out), "--", sys.executable, "-c", probe, "{json}", str(REPO)], tmp_path)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    report = json.loads(out.read_text())
    assert [(x["round"], x["version"]) for x in report["runs"]] == [(0, "base"), (0, "head"), (1, "head"), (1, "base")]
    m = report["metrics"]
    assert m["t.x"]["diff"] == [0.0, 0.0] and m["t.x"]["ratio"] == 1.0
    assert m["own_tree"]["base"] == m["own_tree"]["head"] == [1.0, 1.0]  # each imports the project from where it runs
    assert m["this_repo"]["base"] == [0.0, 0.0] and m["this_repo"]["head"] == [1.0, 1.0]  # the base from elsewhere
    assert m["this_repo"]["diff_mean"] == 1.0 and m["this_repo"]["diff_interval95"] == [1.0, 1.0]
    listed = subprocess.run(["git", "worktree", "list"], cwd=REPO, capture_output=True, text=True).stdout
    assert "iamp-ab-" not in listed  # the base's worktree is gone
    writes = [sys.executable, "-c", "import json, sys; json.dump({'a': 1}, open(sys.argv[1], 'w'))", "{json}"]
    bad = _run([str(REPO / "bench" / "ab.py"), "--base", "no-such-rev", "--metric", "a", "--", *writes], tmp_path)
    assert bad.returncode == 2 and "not a revision" in bad.stderr
    missing = _run([str(REPO / "bench" / "ab.py"), "--base", "HEAD", "--metric", "a.b", "--", *writes], tmp_path)
    assert missing.returncode == 2 and "a.b" in missing.stderr
    no_file = _run([str(REPO / "bench" / "ab.py"), "--base", "HEAD", "--metric", "a", "--", sys.executable, "-c", "pass"], tmp_path)
    assert no_file.returncode == 2 and "{json}" in no_file.stderr
    fails = _run([str(REPO / "bench" / "ab.py"), "--base", "HEAD", "--metric", "a", "--", sys.executable, "-c", "raise SystemExit(3)",
                  "{json}"], tmp_path)
    assert fails.returncode == 1 and "exited 3" in fails.stderr
    assert "iamp-ab-" not in subprocess.run(["git", "worktree", "list"], cwd=REPO, capture_output=True, text=True).stdout
