"""The hybrid chain's whole run as one CUDA kernel (``stages.lib.markov.cuda_chain``, the ``cuda`` backend) gives the
CPU kernel's numbers (``kernels.speed_priority_run``) to float32 rounding.

Without a GPU the comparison runs on numba's CUDA simulator (``NUMBA_ENABLE_CUDASIM=1``, in a child process: the
simulator is chosen when numba.cuda is first imported) on a small grid: the same kernel code, every thread of a block
run in Python. Where a GPU is present the comparison runs on it too, and the stage's predictions on real frames
(``backend = "cuda"`` against ``"numpy"``).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from stages.lib.markov import MarkovGridConfig, TransitionKind, build_stencils, kernels, load_or_build_stencils, psi_matrix
from stages.markov_prediction import MarkovPredictionConfig, MarkovPredictor
from testkit.hybrid_chain import hybrid_chain_case

SMALL = MarkovGridConfig(v_max_mps=6.0, n_s_cells=30, n_steps=6, n_state_samples=5, n_input_samples=4, n_sub_times=4)
NAMES = ("position_probs", "velocity_probs", "interval_position_probs", "outside_mass", "interval_outside_mass", "pruned_mass")


def _scenario(n_pairs: int, seed: int, threshold: float):
    """Pairs near the window's end (mass leaks), one at rest, curves that forbid inputs; AR-like preferences; the last
    step without an input (as the stage runs it)."""
    case = hybrid_chain_case(SMALL, n_pairs, np.random.default_rng(seed))
    p0, restriction, prefs = case.p0, case.restriction(SMALL), case.preferences
    stencils = build_stencils(SMALL)
    tables = (*kernels.stencil_tables(stencils.kernel(TransitionKind.TIME_POINT)),
              *kernels.collapsed_tables(stencils.kernel(TransitionKind.TIME_INTERVAL)))
    k_steps = SMALL.n_steps
    has_input = [True] * (k_steps - 1) + [False]
    outside0 = np.zeros(n_pairs, np.float32)
    outside0[3] = 0.25  # a pair that starts with mass outside
    return ((p0.input_probs, p0.velocity_probs, p0.position_probs), outside0, tables, k_steps, True, 1e-4, psi_matrix(SMALL.input_centres_mps2()),
            restriction, prefs, has_input, threshold)


def compare(threads: int = 8) -> dict:
    """Max |GPU − CPU| per output over three scenarios (no forbidding; a forbid threshold that bites; no interval), and the largest
    leak seen (the scenarios must exercise it). On the simulator 8 threads a block: fewer threads than cells, so every
    block-stride loop runs more than once (the GPU test runs 256)."""
    from stages.lib.markov import cuda_chain

    worst = {name: 0.0 for name in (*NAMES, "totals")}
    leak = 0.0
    for seed, threshold, with_interval in ((11, 0.0, True), (12, 0.3, True), (13, 0.3, False)):
        args = list(_scenario(4, seed, threshold))  # two pairs that leak, one at rest with mass outside, one free
        args[4] = with_interval
        cpu = kernels.speed_priority_run(*args)
        timings: dict = {}
        gpu = cuda_chain.speed_priority_run(*args, threads=threads, timings=timings)
        assert set(timings) == {"host_prepare", "launch", "h2d", "kernel", "d2h", "host_total"}, timings
        for name, c, g in zip((*NAMES, "totals"), cpu, gpu):
            if c is None or g is None:  # the interval outputs without the interval
                assert c is None and g is None and not with_interval, name
                continue
            assert c.shape == g.shape, (name, c.shape, g.shape)
            worst[name] = max(worst[name], float(np.max(np.abs(c.astype(np.float64) - g))))
        leak = max(leak, float(cpu[3][:, -1].max()))
    return {"worst": worst, "leak": leak}


def _check(report: dict) -> None:
    assert report["leak"] > 1e-3, "the scenario should leak mass past the window"
    for name, err in report["worst"].items():
        assert err <= 2e-6, f"{name}: max |gpu - cpu| = {err:.3g}"


@pytest.mark.skipif(not kernels.available(), reason="numba does not import")
def test_cuda_chain_gives_the_cpu_kernels_numbers_on_the_simulator():
    env = {**os.environ, "NUMBA_ENABLE_CUDASIM": "1"}
    done = subprocess.run([sys.executable, str(Path(__file__).resolve())], env=env, capture_output=True, text=True, timeout=600,
                          cwd=Path(__file__).resolve().parents[2])
    assert done.returncode == 0, done.stderr[-3000:]
    report = json.loads(done.stdout.strip().splitlines()[-1])
    assert report["simulator"]
    _check(report)


def _gpu() -> bool:
    from stages.lib.markov import cuda_chain

    return kernels.available() and cuda_chain.available() and not os.environ.get("NUMBA_ENABLE_CUDASIM")


def test_cuda_chain_gives_the_cpu_kernels_numbers_on_the_gpu():
    if not _gpu():
        pytest.skip("no CUDA GPU numba can use here")
    _check(compare(threads=256))


def test_cuda_backend_without_a_gpu_is_a_clear_start_error():
    if _gpu():
        pytest.skip("a GPU is here")
    config = MarkovPredictionConfig(mode="hybrid", backend="cuda")
    assert config.device == "cuda"
    with pytest.raises(ValueError, match="backend = 'cuda'"):
        MarkovPredictor(config, stencils=load_or_build_stencils(MarkovGridConfig()))


def test_cuda_backend_config():
    assert MarkovPredictionConfig(mode="hybrid", backend="cuda", device="cuda:1").device == "cuda:1"
    for bad in ("gpu", "cuda:x", "cpu:0"):
        with pytest.raises(ValueError, match="cuda backend"):
            MarkovPredictionConfig(mode="hybrid", backend="cuda", device=bad)


def test_cuda_backend_agrees_with_numpy_on_real_frames(tmp_path):
    if not _gpu():
        pytest.skip("no CUDA GPU numba can use here")
    from testkit.chain_messages import dense_frames_with_profiles

    frames = dense_frames_with_profiles(12, 16, tmp_path, lambda n: n >= 10 and n % 3 == 0)
    stencils = load_or_build_stencils(MarkovGridConfig())
    runs = {}
    for backend in ("numpy", "cuda"):
        predictor = MarkovPredictor(MarkovPredictionConfig(mode="hybrid", backend=backend), stencils=stencils)
        runs[backend] = [predictor.process(item.corridor_set, item.relation_set, item.scene, item.frame, intention_belief=item.belief,
                                           acceleration_profiles=profiles)[0] for item, profiles in frames]
    assert sum(p.position_probs.shape[0] for p in runs["cuda"]) > 3 * len(frames)
    for a, b in zip(runs["numpy"], runs["cuda"]):
        np.testing.assert_allclose(b.position_probs, a.position_probs, atol=1e-5)
        np.testing.assert_allclose(b.velocity_probs, a.velocity_probs, atol=1e-5)
        np.testing.assert_allclose(b.mean_xy_m, a.mean_xy_m, atol=1e-3)


if __name__ == "__main__":  # the simulator's child process
    from numba import config as numba_config

    print(json.dumps({**compare(), "simulator": bool(numba_config.ENABLE_CUDASIM)}))


def test_a_gpu_failing_mid_run_costs_no_pair(tmp_path, monkeypatch):
    """A GPU run that raises (a driver fault, memory; injected here: no GPU on this machine) is done again by the CPU
    kernel and every later run too: one frame-level ``gpu_chain_failed`` issue, every pair predicted, the numpy
    backend's numbers."""
    from stages.lib.markov import cuda_chain
    from testkit.chain_messages import dense_frames_with_profiles

    frames = dense_frames_with_profiles(8, 8, tmp_path, lambda n: n >= 4)
    stencils = load_or_build_stencils(MarkovGridConfig())

    def run(fail: bool):
        predictor = MarkovPredictor(MarkovPredictionConfig(mode="hybrid"), stencils=stencils)
        calls = []
        if fail:
            def broken(*args, **kwargs):
                calls.append(1)
                raise RuntimeError("CUDA_ERROR_LAUNCH_FAILED (injected)")

            monkeypatch.setattr(cuda_chain, "speed_priority_run", broken)
            predictor.propagator.chain_device = "cuda"  # as backend "cuda" sets it, without a GPU to check
        out = [predictor.process(item.corridor_set, item.relation_set, item.scene, item.frame, intention_belief=item.belief,
                                 acceleration_profiles=profiles) for item, profiles in frames]
        return out, calls, predictor

    reference, _, _ = run(False)
    ours, calls, predictor = run(True)
    assert calls == [1] and predictor.propagator.chain_device is None  # tried once, then the CPU for good
    kinds = [i.kind for _, issues in ours for i in issues]
    assert kinds.count("gpu_chain_failed") == 1
    assert "pair_failed" not in kinds and "pair_fallback_chain_failed" not in kinds
    assert sum(p.position_probs.shape[0] for p, _ in ours) >= len(frames)
    for (a, _), (b, _) in zip(reference, ours):
        np.testing.assert_array_equal(b.position_probs, a.position_probs)
