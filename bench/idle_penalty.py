"""How much slower a stage runs when its process has been idle before the frame, on this host.

``bench/dense.py`` runs the stages back to back in one process: each frame's
markov_prediction starts right after the upstream stages, on a core that was
busy. On the bus every stage is a process that waits for its inputs, ~60-90
ms of every 100 ms frame at 10 Hz, and starts each frame after that wait.
This script measures what the wait costs: it records markov_prediction's
inputs of a dense run (``bench/dense.py``'s ``run_one``, ``--vehicles`` per
frame), then replays them through a fresh stage once per gap and round (the
same frames, the same order, ``prepare`` twice and ``update`` as
``bench/dense.py`` calls them), sleeping ``gap`` ms before each frame (``0``:
back to back), or with ``spinN`` spinning N ms in Python instead (the core
kept busy with other code); rounds alternate the gaps. The frames are the
same in every pass, so each frame's time is compared with its own time back
to back (``paired``: the median over the frames of the difference). The same
for ``testkit.host_speed``'s fixed workloads (Python, and the compiled numba
scatter), which hold none of the project's code.

Prints per gap the median ms per frame and the paired difference; asserts
nothing (other load on the machine shows in the figures). ``--json FILE``
writes ``gaps.<gap>.{markov_ms_median, markov_paired_ms, python_ms_median,
numba_ms_median}``, ``frames``, ``vehicles``, ``pairs_median`` and
``host_reference``.

    python bench/idle_penalty.py [--vehicles 18] [--frames 80] [--segments 8] [--gaps 0,2,20,60,spin20] [--rounds 2]
                                 [--json FILE]
"""

from __future__ import annotations

import argparse
import atexit
import json
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from stages.lib.base import check_output_arg


def parse_gap(text: str) -> tuple[str, float]:
    """``"20"`` -> ("sleep", 0.020), ``"spin20"`` -> ("spin", 0.020); ValueError otherwise."""
    kind, number = ("spin", text[4:]) if text.startswith("spin") else ("sleep", text)
    ms = float(number)
    if not (ms >= 0 and np.isfinite(ms)):
        raise ValueError(text)
    return kind, ms / 1e3


def wait(kind: str, seconds: float) -> None:
    if seconds <= 0:
        return
    if kind == "sleep":
        time.sleep(seconds)
        return
    end = time.perf_counter() + seconds
    while time.perf_counter() < end:  # other Python code on this core meanwhile
        pass


def replay(make_stage, feed, frames: list[dict], kind: str, seconds: float) -> np.ndarray:
    """Wall ms of each frame through a fresh stage (``feed``: ``bench/dense.py``'s ``feed_markov``), ``wait(kind,
    seconds)`` before each."""
    stage = make_stage()
    out = np.empty(len(frames))
    for i, inputs in enumerate(frames):
        wait(kind, seconds)
        t0 = time.perf_counter()
        feed(stage, inputs, profiles=True)  # as bench/dense.py: the pairs, then the chain, then the rest
        out[i] = (time.perf_counter() - t0) * 1e3
        stage.idle()  # (off the frame, as the runtime does it)
    return out


def workload(fn, kind: str, seconds: float, repeats: int) -> float:
    """Median wall ms of ``fn()``, ``wait(kind, seconds)`` before each call."""
    ms = []
    for _ in range(repeats):
        wait(kind, seconds)
        t0 = time.perf_counter()
        fn()
        ms.append((time.perf_counter() - t0) * 1e3)
    return float(np.median(ms))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--vehicles", type=int, default=18)
    parser.add_argument("--frames", type=int, default=80, help="frames recorded (and replayed) after the warm-up ones")
    parser.add_argument("--warmup", type=int, default=10, help="frames before each segment's recorded ones (replayed, not counted)")
    parser.add_argument("--segments", type=int, default=8)
    parser.add_argument("--source", choices=("k733", "k729"), default="k733")
    parser.add_argument("--gaps", default="0,2,20,60,spin20", help="comma-separated: ms asleep before each frame, or spinN (N ms busy)")
    parser.add_argument("--rounds", type=int, default=2, help="passes per gap, alternated")
    parser.add_argument("--repeats", type=int, default=15, help="calls of each host_speed workload per gap and round")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    check_output_arg(parser, args.json, "--json")
    try:
        gaps = {g: parse_gap(g) for g in (t.strip() for t in args.gaps.split(",")) if g}
    except ValueError as exc:
        parser.error(f"--gaps: {exc} is not a number of ms or spinN")
    if "0" not in gaps:
        gaps = {"0": ("sleep", 0.0), **gaps}
    if args.vehicles < 1 or args.frames < 1 or args.rounds < 1 or args.repeats < 1:
        parser.error("--vehicles, --frames, --rounds and --repeats must be >= 1")
    try:  # as a script, its folder is first on the module path (bench/ is not an installed package)
        import dense
    except ImportError:
        from bench import dense
    from stages.lib.datasets import DEFAULT_DATA_DIR, FULL_DATA_ENV, full_data_dir
    from stages.lib.datasets.superimpose import build_dense
    from stages.lib.markov import load_or_build_stencils
    from stages.markov_prediction import MarkovPredictor
    from stages.markov_prediction.core import grid_config
    from testkit import host_speed

    ns = dense.parse_args(["--vehicles", str(args.vehicles), "--frames", str(args.frames), "--warmup", str(args.warmup),
                           "--segments", str(args.segments), "--source", args.source, "--modes", "hybrid", "--backend", "numpy", "--device", "cpu"])
    full = full_data_dir()
    data, recording = (full, dense.SOURCES[args.source]) if full is not None else (DEFAULT_DATA_DIR, dense.SOURCES["k729"])
    print(f"data: {data}" + ("" if full is not None else f" ({FULL_DATA_ENV} not set: the embedded K729 scenario)") + f", source {recording}")
    host = host_speed.reference()
    print(host_speed.line(host))
    stencils = load_or_build_stencils(grid_config(dense.markov_config(ns, "hybrid")))
    keep = Path(tempfile.mkdtemp(prefix="iamp-idle-"))
    atexit.register(shutil.rmtree, keep, ignore_errors=True)
    built = build_dense(data, recording, args.vehicles, keep)

    # the hybrid stage's input sets of a dense run, in order (warm-up frames too: the replay's history is the run's)
    frames: list[dict] = []
    timed: list[bool] = []
    state = {"timed": False}
    original = MarkovPredictor.update

    def recording_update(self, inputs):
        frames.append(dict(inputs))
        timed.append(state["timed"])
        return original(self, inputs)

    MarkovPredictor.update = recording_update
    try:
        result = dense.run_one(keep, built.name, ns, stencils, on_frame=lambda t: state.__setitem__("timed", t))
    finally:
        MarkovPredictor.update = original
    counted = np.asarray(timed)
    config = dense.markov_config(ns, "hybrid")

    def make_stage():
        return MarkovPredictor(config, producer="markov_prediction", stencils=stencils)

    inputs = host_speed._numba_inputs() if host_speed.numba is not None else None
    loads = {"python": host_speed._python_work}
    if inputs is not None:
        loads["numba"] = lambda: host_speed._scatter_rows(*inputs)
    for fn in loads.values():  # (numba's compiled, the first call's allocations made) before any timing
        fn()
    times: dict[str, list[np.ndarray]] = {g: [] for g in gaps}
    load_ms: dict[str, dict[str, list[float]]] = {g: {k: [] for k in loads} for g in gaps}
    replay(make_stage, dense.feed_markov, frames[: min(len(frames), 10)], "sleep", 0.0)  # warm: compiled kernels, tables
    for r in range(args.rounds):
        for g, (kind, seconds) in gaps.items():
            times[g].append(replay(make_stage, dense.feed_markov, frames, kind, seconds)[counted])
            for name, fn in loads.items():
                load_ms[g][name].append(workload(fn, kind, seconds, args.repeats))
            print(f"round {r}, gap {g}: markov_prediction {np.median(times[g][-1]):.2f} ms, "
                  + ", ".join(f"{n} {load_ms[g][n][-1]:.2f}" for n in loads), flush=True)
    base = np.median(np.stack(times["0"]), axis=0)
    report = {"source": recording, "vehicles": args.vehicles, "frames": int(counted.sum()),
              "pairs_median": result["hybrid"]["pairs_median"], "rounds": args.rounds, "host_reference": host, "gaps": {}}
    print(f"\n{int(counted.sum())} frames, {result['hybrid']['vehicles_median']:.0f} vehicles and {result['hybrid']['pairs_median']:.0f} "
          f"pairs per frame (median); per gap the median over the frames (and rounds), paired: each frame against its own time back to back")
    print(f"{'gap':>8} {'markov ms':>10} {'paired':>8} " + " ".join(f"{n + ' ms':>10}" for n in loads))
    for g in gaps:
        per_frame = np.median(np.stack(times[g]), axis=0)
        row = {"markov_ms_median": float(np.median(per_frame)), "markov_paired_ms": float(np.median(per_frame - base)),
               **{f"{n}_ms_median": float(np.median(load_ms[g][n])) for n in loads}}
        report["gaps"][g] = row
        print(f"{g:>8} {row['markov_ms_median']:10.2f} {row['markov_paired_ms']:+8.2f} "
              + " ".join(f"{row[f'{n}_ms_median']:10.2f}" for n in loads))
    report["host_reference_end"] = host_speed.reference()
    print(host_speed.line(report["host_reference_end"]))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(report, indent=2))
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
