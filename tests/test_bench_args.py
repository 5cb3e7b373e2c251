"""A bad command line stops a bench script with one line naming the problem and exit code 2, never a traceback:
a data folder, recording, sequence or recording file that is not there, numbers out of range, unknown names,
an output path that is a folder. Each case fails before the work (a second or two: the imports)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
BENCH = REPO / "bench"
MISSING = "/nonexistent/dir"


def _run(args: list[str], cwd: Path) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k != "IAMP_TAF_BW"}  # the embedded data, as on a fresh checkout
    env["OMP_NUM_THREADS"] = "1"
    return subprocess.run([sys.executable, str(BENCH / args[0]), *args[1:]], cwd=cwd, env=env, capture_output=True, text=True,
                          timeout=120)


def _problem_lines(stderr: str) -> list[str]:
    """stderr less argparse's usage block (``usage:`` and its indented continuation lines)."""
    return [line for line in stderr.splitlines() if line.strip() and not line.startswith(("usage:", " "))]


def _has_cuda() -> bool:
    import torch

    return torch.cuda.is_available()


# (script and arguments, a text the one line must hold)
BAD = [
    # a data folder that is not there
    *[([script, "--data", MISSING], MISSING) for script in (
        "accel_range.py", "corridor_coverage.py", "intentions_particles.py", "plot_frame.py", "scenario_traffic.py", "soak.py",
        "stage_timing.py", "state_estimator.py", "velocity_robustness.py", "relations_timing.py", "adversarial.py",
        "window_errors.py", "oracle_profiles.py", "generalisation.py")],
    (["standing_starts.py", "--data", MISSING, "--recording", "k729_2022-03-16"], MISSING),
    # a recording or sequence the (embedded) data does not hold
    (["scenario_traffic.py", "--sequence", "999"], "'999'"),
    (["velocity_robustness.py", "--sequence", "999"], "'999'"),
    (["relations_timing.py", "--sequence", "999"], "999"),
    (["state_estimator.py", "--data", str(REPO / "stages" / "data" / "taf-bw"), "--recording", "nosuch"], "'nosuch'"),
    (["standing_starts.py", "--data", str(REPO / "stages" / "data" / "taf-bw"), "--recording", "nosuch"], "'nosuch'"),
    # a recording file that is not there
    (["codec.py", "/nonexistent.mcap"], "/nonexistent.mcap"),
    (["scenario_traffic.py", "--mcap", "/nonexistent.mcap"], "/nonexistent.mcap"),
    # numbers
    (["dense.py", "--frames", "-5"], "--frames -5"),
    (["dense.py", "--vehicles", "abc"], "--vehicles"),
    (["dense.py", "--vehicles", "0"], "--vehicles"),
    (["dense.py", "--warmup", "-1"], "--warmup -1"),
    (["e2e_latency.py", "--vehicles", "abc"], "--vehicles"),
    (["e2e_latency.py", "--pipeline", "nosuch"], "--pipeline nosuch: no such pipeline file"),
    (["e2e_latency.py", "--pipeline", "/nonexistent/p.toml"], "/nonexistent/p.toml"),
    (["markov_kernel.py", "--pairs", "x"], "--pairs"),
    (["markov_kernel.py", "--repeats", "0"], "--repeats 0"),
    (["markov_stage.py", "--pairs", "0"], "--pairs"),
    (["markov_stage.py", "--repeats", "0"], "--repeats 0"),
    (["hostile.py", "--section", "fuzz", "--n", "-1"], "--n -1"),
    (["codec.py", "--per-schema", "0", "--frames", "0"], "--per-schema 0"),
    (["codec.py", "--vehicles", "5000"], "--vehicles 5000"),
    (["bus_latency.py", "--count", "0"], "--count 0"),
    (["relations_timing.py", "--repeat", "0"], "--repeat 0"),
    (["stage_timing.py", "--repeats", "0"], "--repeats 0"),
    # names
    (["markov_stage.py", "--backends", "nosuch"], "numpy, torch-cpu, torch-cuda"),
    (["ab.py", "--base", "HEAD", "--metric", "a"], "after --"),
    # a model of one's own for bench/generalisation.py: a direction it does not know, no file, not a model, not held out
    (["generalisation.py", "--model", "nosuch=/x.pt"], "'nosuch'"),
    (["generalisation.py", "--model", "k729-k733=/nonexistent.pt"], "/nonexistent.pt"),
    (["generalisation.py", "--model", f"k733-k729={REPO / 'README.md'}"], "does not load as an AR model"),
    (["generalisation.py", "--model", f"k729-k733={REPO / 'stages' / 'lib' / 'ar' / 'weights' / 'ar_taf_bw.pt'}"], "not held out"),
    # found by a new-user probe (each was a traceback, some after minutes of work): --set not KEY=VALUE, an unknown
    # parameter or a bad value; a --keep that is a file or the source's own data folder; a --function of no module;
    # a duration or speed that is not positive (they failed in the commands the bench runs, naming flags not given)
    (["dense.py", "--set", "junk"], "--set 'junk': expected KEY=VALUE"),
    (["dense.py", "--set", "nosuchkey=3"], "unknown parameter(s) nosuchkey"),
    (["dense.py", "--set", "n_inputs=abc"], "n_inputs = 'abc' should be int"),
    (["dense.py", "--keep", str(REPO / "README.md")], "--keep"),
    (["dense.py", "--keep", str(REPO / "stages" / "data" / "taf-bw")], "--keep"),
    (["frame_phases.py", "--set", "junk"], "--set 'junk'"),
    (["frame_phases.py", "--function", ":foo"], "--function ':foo'"),
    (["frame_phases.py", "--modes", "nonsense"], "--modes nonsense"),
    (["e2e_latency.py", "--duration-s", "-1"], "--duration-s -1"),
    (["e2e_latency.py", "--speed", "0"], "--speed 0"),
    (["e2e_latency.py", "--keep", str(REPO / "README.md")], "--keep"),
    # a GPU asked for on a machine without one (CI has none; each case is skipped where a GPU is there): it printed
    # "nothing measured" and exit 0, and frame_phases.py died of a traceback (a new user's probe)
    (["dense.py", "--device", "cuda"], "--device cuda: no CUDA device here"),
    (["frame_phases.py", "--device", "cuda"], "--device cuda: no CUDA device here"),
    # output paths
    (["plot_frame.py", "--out", "/tmp"], "is a folder"),
    (["plot_frame.py", "--out", "frame.nosuchformat"], ".nosuchformat"),
]


@pytest.fixture(scope="module")
def bad_runs(tmp_path_factory) -> list[subprocess.CompletedProcess]:
    """Every case of BAD, run in one child process (``testkit.script_batch``: each script as its own ``__main__``), in
    the order of BAD: a process per case cost the suite 25 s of starting Python and importing the stages."""
    cwd = tmp_path_factory.mktemp("bench_args")
    env = {k: v for k, v in os.environ.items() if k != "IAMP_TAF_BW"}
    env["OMP_NUM_THREADS"] = "1"
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(BENCH), env.get("PYTHONPATH")]))  # the scripts' own imports of one another
    cases = [[str(BENCH / args[0]), args[1:]] for args, _ in BAD]
    done = subprocess.run([sys.executable, "-m", "testkit.script_batch"], input=json.dumps(cases), cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    return [subprocess.CompletedProcess(args, r["code"], r["stdout"], r["stderr"]) for (args, _), r in zip(BAD, json.loads(done.stdout))]


@pytest.mark.parametrize("case", range(len(BAD)), ids=[" ".join(a) for a, _ in BAD])
def test_bad_command_line_is_one_line_and_exit_2(case, bad_runs):
    named = BAD[case][1]
    if "--device" in BAD[case][0] and _has_cuda():
        pytest.skip("a CUDA device is here")
    r = bad_runs[case]
    assert "Traceback" not in r.stderr + r.stdout, r.stderr[-3000:]
    assert r.returncode == 2, r.stdout[-2000:] + r.stderr[-2000:]
    lines = _problem_lines(r.stderr)
    assert len(lines) == 1 and named in lines[0], r.stderr


def test_ab_help_prints_the_usage(tmp_path):
    r = _run(["ab.py", "--help"], tmp_path)
    assert r.returncode == 0, r.stderr
    assert r.stdout.startswith("usage:") and "--base" in r.stdout and "--metric" in r.stdout and "-- COMMAND" in r.stdout


def test_plot_frame_prints_the_files_it_wrote(tmp_path):
    """Without a suffix matplotlib writes FILE.png: that name is printed, and the SVG beside it."""
    out = tmp_path / "x" / "noext"
    r = _run(["plot_frame.py", "--out", str(out)], tmp_path)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    wrote = [line.split(",")[0].removeprefix("wrote ") for line in r.stdout.splitlines() if line.startswith("wrote ")]
    assert wrote == [str(out) + ".png", str(out) + ".svg"]
    assert all(Path(p).is_file() for p in wrote) and not out.exists()


def test_dense_figures_as_strict_json_and_an_exponent_only_where_it_can_be_fitted():
    """bench/dense.py --modes baseline counted no pairs, so the fit of time against pairs had only zeros and failed
    with a LinAlgError after the whole run; an ``at_n`` of no frame was written as a bare NaN, not JSON."""
    from bench import dense

    assert dense.exponent([10, 20, 40], [1.0, 2.0, 4.0]) == pytest.approx(1.0)
    assert dense.exponent([0, 0], [1.0, 2.0]) is None and dense.exponent([10, 10], [1.0, 2.0]) is None
    assert dense.exponent([10, 20, 40], [1.0, float("nan"), 4.0]) == pytest.approx(1.0)
    text = json.dumps(dense.finite_json({"a": float("nan"), "b": [1.5, float("inf")], "c": {"d": 2}}), allow_nan=False)
    assert json.loads(text) == {"a": None, "b": [1.5, None], "c": {"d": 2}}


def test_gpu_checks_stop_at_once_without_a_gpu(tmp_path):
    """bench/gpu_checks.sh on a machine without a GPU ran its 30 minutes of steps, each failing (and without $PYTHON
    it ran the system python3, which cannot import the project): it stops before any step now, in one line."""
    if _has_cuda():
        pytest.skip("a CUDA device is here")
    r = subprocess.run(["bash", str(BENCH / "gpu_checks.sh"), str(tmp_path / "out")], cwd=tmp_path, capture_output=True, text=True,
                       timeout=120, env={k: v for k, v in os.environ.items() if k != "PYTHON"} | {"PYTHON": sys.executable})
    assert r.returncode == 2 and "no CUDA device here" in r.stderr and not (tmp_path / "out").exists(), r.stdout[-2000:] + r.stderr
