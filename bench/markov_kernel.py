"""Benchmark of the Markov propagation kernel (docs/method.md §3.3–3.5); prints figures, asserts nothing.

For the default grid it prints the stencil build time, the sparse expansion
time and nnz of Υ(τ) and Υ([0, τ]); then, for B = 1, 10, 50, 200
vehicle-corridor pairs in hybrid mode (input distribution replaced every
step), the time per frame (K = 10 steps) and per step on the numpy backend
with its numba kernels (``stages/lib/markov/kernels.py``, the default) and
with the scipy CSR products (``kernel="scipy"``, the reference), torch on CPU
and torch on CUDA when available, with and without the
interval matrix, with and without cropping to the active s-window.

    python bench/markov_kernel.py [--repeats N] [--pairs 1,10,50,200] [--threads N] [--hybrid-only]

Then the hybrid mode's own chain as markov_prediction runs it (``chain.PriorityPropagator`` with an
``InputPriority`` per step: the AR-like preference inside the compiled speed restriction λ_speed of
``kernels.SpeedRestriction``, half of the pairs on a corridor with a 20 m-radius bend 40-60 m ahead; the stage's
prune threshold, cropping and interval distribution), per frame on the numpy backend (the one compiled call,
``kernel_threads`` 1 and 2), torch on CPU and torch on CUDA when available, and the one call as one CUDA kernel
(``backend = "cuda"``, ``stages/lib/markov/cuda_chain.py``) where numba.cuda finds a GPU, with a line per B of
where that call's time goes (median ms: host preparation, the launch call, the two transfers and the kernel by CUDA
events, the call's wall time). It needs no map, data or bus: the
quickest way to time a change of the chain on a GPU machine. ``--hybrid-only`` prints that table alone.

``--threads`` sets torch's CPU threads (default: torch's own choice). The
first numba call of a process compiles (or loads the on-disk cache); the
warm-up run of every row absorbs it.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

from stages.lib.markov import (
    InputReplaced,
    MarkovGridConfig,
    MarkovPropagator,
    TransitionKind,
    build_stencils,
    initial_state,
)


def _scenario(config: MarkovGridConfig, n_pairs: int, seed: int = 0):
    """Urban-like pairs: 5 m into the window, 0–15 m/s, AR-like input distributions per step."""
    rng = np.random.default_rng(seed)
    speeds_mps = rng.uniform(0.0, 15.0, n_pairs)
    centres = config.input_centres_mps2()
    means = rng.uniform(-1.5, 1.0, (n_pairs, config.n_steps + 1))
    sigmas = np.linspace(0.3, 1.0, config.n_steps + 1)[None, :]
    logits = -0.5 * ((centres[None, None, :] - means[..., None]) / sigmas[..., None]) ** 2
    lam = np.exp(logits)
    lam /= lam.sum(axis=-1, keepdims=True)
    p0 = initial_state(
        config,
        s_m=np.full(n_pairs, 5.0),
        v_mps=speeds_mps,
        half_width_s_m=1.0,
        half_width_v_mps=0.5,
        input_probs=lam[:, 0],
    )
    inputs = [InputReplaced(probs=lam[:, k + 1].astype(np.float32)) for k in range(config.n_steps)]
    return p0, inputs


def _hybrid_scenario(config: MarkovGridConfig, n_pairs: int, seed: int = 0):
    """The hybrid chain's inputs for ``n_pairs`` urban-like pairs: ``_scenario``'s start states and AR-like input
    distributions, and λ_speed from the stage's defaults (speed limit 13.89 m/s; every other pair meets a 20 m bend
    40-60 m ahead)."""
    from stages.lib.markov import kernels
    from stages.markov_prediction import MarkovPredictionConfig
    from stages.markov_prediction import priority as pr
    from stages.markov_prediction.chain import InputPriority

    stage = MarkovPredictionConfig(mode="hybrid")
    p0, steps = _scenario(config, n_pairs, seed)
    lam = np.stack([p0.input_probs] + [t.probs for t in steps], axis=1)  # (B, K + 1, M)
    s_m = np.arange(0.0, config.n_s_cells * config.ds_m + 1.0, 1.0)
    bend = np.where((s_m >= 40.0) & (s_m <= 60.0), 1.0 / 20.0, 0.0)
    curvature = [bend if b % 2 else np.zeros_like(s_m) for b in range(n_pairs)]
    adm = pr.admissible_speeds_batch([s_m] * n_pairs, curvature, [stage.default_speed_limit_mps] * n_pairs,
                                     np.asarray(stage.lat_accels_mps2), stage.lookahead_brake_mps2, stage.curvature_smoothing_m)
    weights = np.asarray(stage.lat_accel_weights, dtype=np.float64)
    cells = np.repeat((config.s_edges_m()[: config.n_s_cells] + 0.5 * config.ds_m)[None, :], n_pairs, axis=0)
    restriction = kernels.SpeedRestriction([s_m] * n_pairs, adm, cells, config.v_centres_mps(), config.input_centres_mps2(),
                                           weights / weights.sum(), config.tau_s)
    prefs = (lam[:, 1:] / np.maximum(lam[:, 1:].max(axis=2, keepdims=True), 1e-12)).astype(np.float32)
    thr = stage.forbid_threshold
    inputs: list = []
    for k in range(config.n_steps):
        if k + 1 >= config.n_steps:
            inputs.append(None)  # as the stage: the input after the last step changes no output
            continue
        pref = prefs[:, k]
        inputs.append(InputPriority(
            weights=lambda lo, hi, pref=pref: pr.combine_with_preference(restriction.full()[..., lo:hi], pref, thr),
            at_states=lambda b, v, s, pref=pref: restriction.priority_at_states(pref, b, v, s, thr),
            restriction=restriction, preference=pref, forbid_threshold=thr))
    return p0, inputs


def _hybrid_table(config: MarkovGridConfig, stencils, pair_counts: list[int], repeats: int, torch) -> None:
    """The hybrid chain per frame (ms) on every backend here; see the module's docstring."""
    from stages.lib.markov import kernels, psi_matrix
    from stages.markov_prediction import MarkovPredictionConfig
    from stages.markov_prediction.chain import PriorityPropagator

    stage = MarkovPredictionConfig(mode="hybrid")
    psi = psi_matrix(config.input_centres_mps2(), gamma=stage.psi_gamma)
    targets = [("numpy", "cpu", 1), ("numpy", "cpu", 2)] if kernels.available() else []
    targets.append(("torch", "cpu", 1))
    if torch.cuda.is_available():
        targets.append(("torch", "cuda", 1))
    from stages.lib.markov import cuda_chain

    if kernels.available() and cuda_chain.available():  # the default threads per block, and 512 (119 registers a thread fit)
        targets += [("cuda", "cuda", cuda_chain.THREADS), ("cuda", "cuda", 512)]
    print()
    print("hybrid chain (chain.PriorityPropagator, speed restriction x AR preference), interval on, cropped; ms per frame")
    print(f"{'backend':18s} " + " ".join(f"{'B=' + str(b):>10s}" for b in pair_counts))
    parts: dict[tuple[int, int], dict] = {}
    for backend, device, threads in targets:
        # (the cuda backend's call returns once its results are on the host: nothing to wait for)
        sync = (lambda: torch.cuda.synchronize()) if backend == "torch" and device == "cuda" else (lambda: None)
        default_threads = cuda_chain.THREADS
        if backend == "cuda":  # its threads per block, for this row
            cuda_chain.THREADS = threads
        cells = []
        for n_pairs in pair_counts:
            p0, inputs = _hybrid_scenario(config, n_pairs)
            propagator = PriorityPropagator(stencils, psi, backend="numpy" if backend == "cuda" else backend,
                                            device="cpu" if backend == "cuda" else device, chain_device=device if backend == "cuda" else None,
                                            n_s_cells=config.n_s_cells, prune_threshold=stage.prune_threshold, kernel_threads=threads if backend == "numpy" else 1)
            cells.append(f"{_time_frame(propagator, p0, inputs, True, repeats, sync) * 1e3:10.1f}")
            if backend == "cuda":  # where the call's time goes: host work, the launch call, transfers, the kernel
                runs = []
                for _ in range(max(repeats, 3)):
                    propagator.gpu_timings = {}
                    propagator.run(p0, inputs, with_interval=True)
                    runs.append(propagator.gpu_timings)
                parts[(threads, n_pairs)] = {k: float(np.median([r[k] for r in runs])) for k in runs[0]}
        cuda_chain.THREADS = default_threads
        label = f"numpy-numba x{threads}" if backend == "numpy" else f"cuda-chain t{threads}" if backend == "cuda" else f"torch-{device}"
        print(f"{label:18s} " + " ".join(cells))
    for (threads, n_pairs), part in parts.items():
        print(f"  cuda-chain t{threads} B={n_pairs}, median ms: " + ", ".join(f"{k} {v:.2f}" for k, v in part.items()))


def _time_frame(propagator: MarkovPropagator, p0, inputs, with_interval: bool, repeats: int, sync) -> float:
    propagator.run(p0, inputs, with_interval=with_interval)  # warm-up (lazy matrices, kernels)
    times = []
    for _ in range(repeats):
        sync()
        start = time.perf_counter()
        propagator.run(p0, inputs, with_interval=with_interval)
        sync()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def parse_pairs(text: str) -> list[int]:
    """``--pairs``: comma-separated whole numbers of vehicle-corridor pairs, each >= 1."""
    try:
        counts = [int(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected comma-separated whole numbers, e.g. 1,10,50") from None
    if not counts or min(counts) < 1:
        raise argparse.ArgumentTypeError(f"{text!r}: each a number of pairs >= 1")
    return counts


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--pairs", type=parse_pairs, default="1,10,50,200", help="comma-separated pairs per frame (default 1,10,50,200)")
    parser.add_argument("--threads", type=int, default=0, help="torch CPU threads (0: torch's default)")
    parser.add_argument("--hybrid-only", action="store_true", help="only the hybrid chain's table")
    args = parser.parse_args(argv)
    if args.repeats < 1:
        parser.error(f"--repeats {args.repeats}: must be >= 1")
    if args.threads < 0:
        parser.error(f"--threads {args.threads}: must be >= 0 (0: torch's default)")
    pair_counts = args.pairs

    config = MarkovGridConfig()
    start = time.perf_counter()
    stencils = build_stencils(config)
    build_s = time.perf_counter() - start
    if args.hybrid_only:
        import torch

        if args.threads:
            torch.set_num_threads(args.threads)
        _hybrid_table(config, stencils, pair_counts, args.repeats, torch)
        return 0
    print(f"grid: ds={config.ds_m} m dv={config.dv_mps} m/s v_max={config.v_max_mps} m/s "
          f"N_s={config.n_s_cells} N_v={config.n_v_cells} M={config.n_inputs} tau={config.tau_s} s K={config.n_steps}")
    print(f"samples: {config.n_state_samples}x{config.n_state_samples} states x {config.n_input_samples} inputs, "
          f"n_t={config.n_sub_times}; stencil offsets D={stencils.n_offsets}")
    print(f"stencil build (both kinds): {build_s * 1e3:.0f} ms")
    for kind in TransitionKind:
        start = time.perf_counter()
        matrix = stencils.expand_sparse(kind)
        expand_s = time.perf_counter() - start
        per_column = stencils.nnz(kind) / (config.n_inputs * config.n_v_cells)
        print(f"{kind.name:14s} stencil entries={stencils.nnz(kind)} ({per_column:.1f}/column) "
              f"CSR {matrix.shape[0]}x{matrix.shape[1]} nnz={matrix.nnz} expand={expand_s * 1e3:.1f} ms")

    import torch

    from stages.lib.markov import kernels

    if args.threads:
        torch.set_num_threads(args.threads)
    targets = [("numpy", "cpu", "scipy"), ("torch", "cpu", "auto")]
    if kernels.available():
        targets.insert(0, ("numpy", "cpu", "numba"))
    else:
        print(f"numba does not import ({kernels.unavailable_reason()}): no numba figures")
    if torch.cuda.is_available():
        targets.append(("torch", "cuda", "auto"))
    else:
        print("torch.cuda.is_available() is False: no CUDA figures")
    print(f"torch {torch.__version__}, CPU threads {torch.get_num_threads()}")
    print()
    print(f"{'backend':14s} {'crop':5s} {'interval':8s} " + " ".join(f"{'B=' + str(b):>20s}" for b in pair_counts))
    print(f"{'':14s} {'':5s} {'':8s} " + " ".join(f"{'frame / step [ms]':>20s}" for _ in pair_counts))
    for backend, device, kernel in targets:
        sync = (lambda: torch.cuda.synchronize()) if device == "cuda" else (lambda: None)
        for crop in (False, True):
            for with_interval in (False, True):
                cells = []
                for n_pairs in pair_counts:
                    p0, inputs = _scenario(config, n_pairs)
                    propagator = MarkovPropagator(stencils, backend=backend, device=device, crop=crop, kernel=kernel)
                    frame_s = _time_frame(propagator, p0, inputs, with_interval, args.repeats, sync)
                    cells.append(f"{frame_s * 1e3:9.1f} / {frame_s * 1e2:7.2f}")
                label = f"{backend}-{kernel}" if backend == "numpy" else f"{backend}-{device}"
                print(f"{label:14s} {str(crop):5s} {str(with_interval):8s} " + " ".join(f"{c:>20s}" for c in cells))
    _hybrid_table(config, stencils, pair_counts, args.repeats, torch)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
