"""Dense traffic: time per stage and per frame of the whole in-process chain, hybrid and baseline, N = 6 .. 72 vehicles.

For each N (``--vehicles``, default 6,12,18,36,72) a recording of N
vehicles per frame on average is superimposed from real tracks (``iamp data
superimpose``, ``stages/lib/datasets/superimpose.py``): with the full data
(``$IAMP_TAF_BW``) k733_2018-05-02 shifted by multiples of its signal cycle
(``--source k733``, the default) or the K729 sequences together
(``--source k729``); without it the embedded K729 scenario's sequences
(said so on the first line). The frames are played through the cores as
the streaming pipeline runs them, one frame at a time, every core every
frame: source (TrackPlayer), corridors, relations, intentions,
ar_inference (hybrid only) and markov_prediction (as on the bus: where the
chain does not read the belief, as in hybrid, ``prepare`` on the corridors,
``prepare`` on all but the belief, then ``update`` with the messages; else
``update`` alone), once in mode hybrid and once
in mode baseline on the same upstream outputs, with the pipelines' settings
(grid of the interval distribution, intentions' corridor weights, particle
boxes). ``--warmup`` frames are run first, untimed, then ``--frames``
frames timed.

Printed per mode and N: vehicles and vehicle-corridor pairs per frame
(median), median and p95 ms per stage and per frame (the sum of the mode's
stages), the hybrid/baseline ratio, and per mode the exponent of a
least-squares fit log(time) ~ log(pairs) over the N (1 = linear).
Prints figures, asserts nothing; other load on the machine shows in them.

    python bench/dense.py [--vehicles 6,12,18,36,72] [--frames 40] [--warmup 10] [--segments 4] [--source k733|k729]
                          [--modes hybrid,baseline] [--backend numpy|torch|cuda] [--device cpu|cuda] [--threads N] [--json FILE]
                          [--keep DIR] [--set KEY=VALUE ...] [--idle-ms 60]

The timed frames are split over ``--segments`` stretches spread along the
recording (the recording's load varies along it), each on fresh cores after
its own ``--warmup`` frames: ``--frames 40 --segments 4`` times 4 x 10
frames after 4 x 10 warm-up frames (``--frames`` is rounded up to whole
stretches; the first line says what runs).

The stages run back to back: each starts on a core that was just busy. On
the bus each is a process that waits for its inputs, ~60-90 ms of every
100 ms frame, and on some hosts code that has waited runs slower
(``bench/idle_penalty.py`` measures it; on this project's 2-core VM the
stages' Python ~40 % slower after 60 ms, the compiled kernels ~5 %).
``--idle-ms MS`` sleeps MS before each stage's first call of a frame
(outside every timing), so that the figures are those of stages that
waited as on the bus (``idle_ms`` in the JSON).

``--set KEY=VALUE`` sets a markov_prediction parameter for both modes (the
input cells ``input_min_mps2``, ``input_max_mps2``, ``n_inputs`` go to
ar_inference too, and the stencils are built for them).

``--json FILE`` (strict JSON: a figure with no frame to take it from, such as
an ``at_n`` of no frame, is ``null``) writes ``source``, ``backend``,
``device``, ``idle_ms``, ``modes.<mode>.by_vehicles.<N>.frame_ms_median``,
``frame_ms_p95``, ``frames`` (timed), ``vehicles_median``, ``vehicles_mean``,
``pairs_median`` and
``stages.<stage>.ms_median`` / ``ms_p95`` / ``cpu_ms_median`` (CPU time of
the process, less sensitive to other load on the machine than wall time; not
for ``source``),
``frame_cpu_ms_median``, ``stages.markov_prediction.after_last_input_ms_median`` (the ``update`` after the
``prepare`` calls: what is left once the belief is in; on the bus the rest runs while it is on its way),
``stages.markov_prediction.idle_ms_mean`` (the stage's ``idle()``, called after every frame as the runtime
calls it once a frame's outputs are out and nothing waits: the online curve choice's back test, every few
frames; mean ms per timed frame, not in the stage's or the frame's time, as on the bus), plus
``modes.<mode>.exponent.{frame, markov_prediction, markov_prediction_cpu}`` (with two N or more; ``null``
without two different pair counts), and ``...by_vehicles.<N>.at_n.{frames, vehicles_within, frame_ms_median,
markov_prediction_ms_median}``: the medians over the timed frames that hold N ± 2 vehicles (N is the
recording's mean; its frames' load varies along it and the timed stretches need not sit at the mean: the
``veh`` column is their median). ``host_reference`` and ``host_reference_end``: ``testkit.host_speed.reference()``
before and after the run (printed too), this host's speed at fixed work apart from the project's code, so that
figures of other days can be read against the host that gave them.
"""

from __future__ import annotations

import argparse
import json
import atexit
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from stages.lib.datasets import DEFAULT_DATA_DIR, FULL_DATA_ENV, full_data_dir, load_recording
from stages.lib.datasets.superimpose import MAX_VEHICLES, build_dense

from bus_schemas import AgentType

VEHICLE_TYPES = [t.value for t in AgentType if t.is_vehicle]
UPSTREAM = ("source", "corridors", "relations", "intentions")
MODES = ("hybrid", "baseline")
SOURCES = {"k733": "k733_2018-05-02", "k729": "k729_2022-03-16"}


def _stats(ms: list[float]) -> dict[str, float]:
    a = np.asarray(ms, dtype=np.float64)
    return {"ms_median": float(np.median(a)), "ms_p95": float(np.percentile(a, 95))} if a.size else {"ms_median": float("nan"), "ms_p95": float("nan")}


def markov_config(args, mode: str):
    """markov_prediction's configuration of ``mode``: the pipelines' settings plus ``--set``."""
    from stages.markov_prediction import MarkovPredictionConfig

    return MarkovPredictionConfig.from_params({**dict(args.set), "mode": mode, "backend": args.backend, "device": args.device},
                                              where="bench/dense.py --set")


def feed_markov(predictor, inputs: dict, profiles: bool):
    """One frame's ``inputs`` into markov_prediction as on the bus (README, "Work before the last input"): where the
    chain does not read the belief, ``prepare`` on the corridors (the pairs), ``prepare`` on all but the belief (the
    chain), then ``update`` on the whole set, the part after the last input; else ``update`` alone. ``profiles``: the
    mode reads the acceleration profiles (missing at the first ``prepare``). Returns (update's result, the
    ``time.perf_counter()`` at which ``update`` started)."""
    if not predictor.chain_reads_belief:
        head = {k: inputs[k] for k in ("corridor_set", "scene", "track_frame")}
        predictor.prepare(head, {"relation_set", "intention_belief", *(["acceleration_profiles"] if profiles else [])})
        predictor.prepare({k: v for k, v in inputs.items() if k != "intention_belief"}, {"intention_belief"})
    start = time.perf_counter()
    return predictor.update(inputs), start


#: Frames whose vehicles lie within this many of N make a result's ``at_n``.
AT_N_WITHIN = 2


def run_one(data_dir: Path, name: str, args, stencils, on_frame=None, target: float | None = None) -> dict:
    """Play the recording ``name`` through the cores; timings per stage and mode. ``on_frame(timed)``, if given, is
    called before each frame the cores see (``timed``: one of the timed frames, not the warm-up). With ``target``
    (N), ``at_n``: the medians over the timed frames holding N ± ``AT_N_WITHIN`` vehicles (the recording's mean is N,
    its frames' load varies along it, and the timed stretches need not sit at the mean)."""
    from stages.ar_inference import ARInference, ARInferenceConfig
    from stages.corridors import CorridorBuilder, CorridorsConfig, SceneMaps
    from stages.intentions import IntentionFilter, IntentionsConfig
    from stages.markov_prediction import MarkovPredictor
    from stages.relations import RelationExtractor, RelationsConfig
    from stages.tracks_source.core import TrackPlayer, TracksSourceConfig

    recording = load_recording(data_dir, name)
    scene_maps = SceneMaps(data=data_dir)
    ar_model = None
    times: dict[str, list[float]] = {s: [] for s in (*UPSTREAM, "ar_inference", *(f"markov_prediction/{m}" for m in args.modes))}
    cpu: dict[str, list[float]] = {s: [] for s in ("corridors", "relations", "intentions", "ar_inference", *(f"markov_prediction/{m}" for m in args.modes))}
    vehicles, pairs = [], []
    # markov_prediction's update on the whole set after its prepare calls: its work once the last input (the belief) is in
    last_input: dict[str, list[float]] = {m: [] for m in args.modes}
    # markov_prediction's idle(): the work the runtime does once a frame's outputs are out and nothing waits (the
    # online curve choice's back test), outside the frame's time as on the bus; its mean per timed frame is reported
    idle: dict[str, list[float]] = {m: [] for m in args.modes}
    after: dict[str, float] = {}
    n_frames = recording.sequences[0].n_frames
    segments = max(1, int(args.segments))
    idle_s = float(getattr(args, "idle_ms", 0.0)) / 1e3

    def rest() -> None:  # --idle-ms: the wait of a process on the bus for its inputs, outside every timing
        if idle_s > 0:
            time.sleep(idle_s)

    per_segment = -(-args.frames // segments)
    for segment in range(segments):
        # fresh cores per segment, started at an evenly spread frame: the recording's edges are sparser
        start = int((segment + 0.5) * n_frames / segments) - args.warmup - per_segment // 2
        start = min(max(start, 0), max(n_frames - args.warmup - per_segment, 0))
        player = TrackPlayer(TracksSourceConfig(recording=name), recording, map_sha256="", run_id="dense", producer="source")
        corridors = CorridorBuilder(CorridorsConfig(), scene_maps=scene_maps)
        relations = RelationExtractor(RelationsConfig(), scene_maps=scene_maps)
        intentions = IntentionFilter(IntentionsConfig(), producer="intentions", scene_maps=scene_maps)
        configs = {mode: markov_config(args, mode) for mode in args.modes}
        ar = ARInference(ARInferenceConfig.from_params({"device": args.device, **markov_config(args, "hybrid").input_cells()}, where="bench/dense.py"),
                         producer="ar_inference", model=ar_model)
        ar_model = ar.model
        predictors = {mode: MarkovPredictor(configs[mode], producer="markov_prediction", stencils=stencils) for mode in args.modes}
        scene = None
        iterator = iter(player)
        for n in range(start + args.warmup + per_segment):
            timed = n >= start + args.warmup
            if on_frame is not None and n >= start:
                on_frame(timed)
            t0 = time.perf_counter()
            try:
                _stamp, result = next(iterator)
            except StopIteration:
                break
            t_source = time.perf_counter() - t0
            if "scene" in result.outputs:
                scene = result.outputs["scene"]
            if n < start:
                continue  # skipped: the cores first see the frame ``start``
            frame = result.outputs["track_frame"]
            rest()
            t0, c0 = time.perf_counter(), time.process_time()
            corridor_set = corridors.process(frame, scene)[0]
            t1, c1 = time.perf_counter(), time.process_time()
            rest()
            t1r, c1r = time.perf_counter(), time.process_time()
            relation_set = relations.process(frame, corridor_set, scene)[0]
            t2, c2 = time.perf_counter(), time.process_time()
            rest()
            t2r, c2r = time.perf_counter(), time.process_time()
            belief = intentions.process(frame, corridor_set, relation_set, scene)[0]
            t3, c3 = time.perf_counter(), time.process_time()
            rest()
            t3r, c3r = time.perf_counter(), time.process_time()
            profiles = ar.process(corridor_set, relation_set, frame, scene)[0] if "hybrid" in args.modes else None
            t4, c4 = time.perf_counter(), time.process_time()
            markov_ms, markov_cpu, idle_ms = {}, {}, {}
            inputs = {"corridor_set": corridor_set, "relation_set": relation_set, "scene": scene, "track_frame": frame,
                      "intention_belief": belief}
            for mode, predictor in predictors.items():
                if mode == "hybrid":
                    inputs["acceleration_profiles"] = profiles
                rest()
                m0, mc0 = time.perf_counter(), time.process_time()
                result, m1 = feed_markov(predictor, inputs, profiles=mode == "hybrid")
                markov_ms[mode] = (time.perf_counter() - m0) * 1e3
                markov_cpu[mode] = (time.process_time() - mc0) * 1e3
                after[mode] = (time.perf_counter() - m1) * 1e3
                i0 = time.perf_counter()
                predictor.idle()
                idle_ms[mode] = (time.perf_counter() - i0) * 1e3
                if mode == args.modes[0] and timed:  # (every mode predicts the same pairs)
                    pairs.append(len(result.outputs["corridor_predictions"].predictions))
            if not timed:
                continue
            vehicles.append(int(np.isin(frame.agent_types, VEHICLE_TYPES).sum()))
            times["source"].append(t_source * 1e3)
            times["corridors"].append((t1 - t0) * 1e3)
            times["relations"].append((t2 - t1r) * 1e3)
            times["intentions"].append((t3 - t2r) * 1e3)
            times["ar_inference"].append((t4 - t3r) * 1e3)
            for mode in args.modes:
                times[f"markov_prediction/{mode}"].append(markov_ms[mode])
                last_input[mode].append(after[mode])
                idle[mode].append(idle_ms[mode])
            for name, ms in (("corridors", c1 - c0), ("relations", c2 - c1r), ("intentions", c3 - c2r), ("ar_inference", c4 - c3r)):
                cpu[name].append(ms * 1e3)
            for mode in args.modes:
                cpu[f"markov_prediction/{mode}"].append(markov_cpu[mode])
    out = {}
    for mode in args.modes:
        stages = [*UPSTREAM, *(["ar_inference"] if mode == "hybrid" else []), f"markov_prediction/{mode}"]
        per_frame = np.sum([times[s] for s in stages], axis=0)
        cpu_frame = np.sum([cpu[s] for s in stages if s in cpu], axis=0)
        out[mode] = {
            "frame_cpu_ms_median": float(np.median(cpu_frame)) if cpu_frame.size else float("nan"),
            **{k: v for k, v in zip(("frame_ms_median", "frame_ms_p95"), _stats(list(per_frame)).values())},
            "frames": int(per_frame.size),
            "vehicles_median": float(np.median(vehicles)) if vehicles else 0.0,
            "vehicles_mean": float(np.mean(vehicles)) if vehicles else 0.0,
            "pairs_median": float(np.median(pairs)) if pairs else 0.0,
            "stages": {s.split("/")[0]: {**_stats(times[s]), **({"cpu_ms_median": float(np.median(cpu[s]))} if s in cpu and cpu[s] else {})}
                       for s in stages},
        }
        if target is not None:
            near = np.abs(np.asarray(vehicles, dtype=np.float64) - target) <= AT_N_WITHIN
            markov = np.asarray(times[f"markov_prediction/{mode}"])
            out[mode]["at_n"] = {"frames": int(near.sum()), "vehicles_within": AT_N_WITHIN,
                                 "frame_ms_median": float(np.median(per_frame[near])) if near.any() else float("nan"),
                                 "markov_prediction_ms_median": float(np.median(markov[near])) if near.any() else float("nan")}
        # the part of markov_prediction left once its last input is in (all of it where the chain reads the belief)
        out[mode]["stages"]["markov_prediction"]["after_last_input_ms_median"] = _stats(last_input[mode])["ms_median"]
        out[mode]["stages"]["markov_prediction"]["idle_ms_mean"] = float(np.mean(idle[mode])) if idle[mode] else 0.0
    return out


def exponent(pairs: list[float], ms: list[float]) -> float | None:
    """The slope of a least-squares fit log(ms) ~ log(pairs) over the rows with pairs > 0 and a finite time > 0;
    None where fewer than two different pair counts are left."""
    x, y = np.asarray(pairs, dtype=np.float64), np.asarray(ms, dtype=np.float64)
    ok = (x > 0) & np.isfinite(y) & (y > 0)
    if np.unique(x[ok]).size < 2:
        return None
    return float(np.polyfit(np.log(x[ok]), np.log(y[ok]), 1)[0])


def finite_json(value):
    """``value`` with every non-finite float (NaN: no frame of that kind) as None: strict JSON, which has no NaN."""
    if isinstance(value, float):
        return value if np.isfinite(value) else None
    if isinstance(value, dict):
        return {k: finite_json(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [finite_json(v) for v in value]
    return value


def write_json(path: str | Path, report: dict) -> None:
    """``report`` as strict JSON (``finite_json``; numpy scalars as floats) into ``path`` (the benches' --json)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(finite_json(report), indent=2, allow_nan=False, default=float))


def vehicle_counts(text: str, minimum: int = 1) -> list[int]:
    """``--vehicles``: comma-separated whole numbers of vehicles per frame, each ``minimum`` to ``MAX_VEHICLES``
    (bench/e2e_latency.py takes 0 too: the embedded scenario as it is)."""
    try:
        sizes = [int(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected comma-separated whole numbers, e.g. {minimum},18") from None
    if not sizes or not all(minimum <= n <= MAX_VEHICLES for n in sizes):
        each = (f"each 0 (the embedded scenario) or a number of vehicles per frame up to {MAX_VEHICLES}" if minimum == 0
                else f"each a number of vehicles per frame from {minimum} to {MAX_VEHICLES}")
        raise argparse.ArgumentTypeError(f"{text!r}: {each}")
    return sizes


def parse_args(argv: list[str] | None = None, error=None) -> argparse.Namespace:
    """The command line, checked: ``vehicles`` a list of ints, ``modes`` a tuple of ``MODES``, ``set`` the parsed
    ``--set`` pairs (each a markov_prediction parameter of a valid value). ``error``: where a check's message goes
    (default this parser's usage error; bench/frame_phases.py passes its own)."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--vehicles", type=vehicle_counts, default="6,12,18,36,72", help="comma-separated vehicles per frame (default 6,12,18,36,72)")
    parser.add_argument("--frames", type=int, default=40, help="timed frames per N")
    parser.add_argument("--warmup", type=int, default=10, help="untimed frames before each segment's timed ones (track histories, caches)")
    parser.add_argument("--segments", type=int, default=4, help="the timed frames are split over this many stretches spread over the recording")
    parser.add_argument("--source", choices=sorted(SOURCES), default="k733")
    parser.add_argument("--backend", choices=("numpy", "torch", "cuda"), default=None,
                        help="markov_prediction's backend (default: numpy on --device cpu; on a CUDA --device the cuda backend where"
                             " numba.cuda finds the GPU, else torch); cuda: the hybrid chain as one CUDA kernel (numba.cuda), on --device"
                             " (cuda if cpu)")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--threads", type=int, default=0, help="torch threads (0: leave torch's default)")
    parser.add_argument("--json", type=Path, default=None)
    parser.add_argument("--keep", type=Path, default=None, help="write the dense recordings here (default a temporary folder)")
    parser.add_argument("--modes", default=",".join(MODES), help="comma-separated modes to time (default hybrid,baseline; the ratio needs both)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="markov_prediction parameter (JSON value) for both modes, e.g. --set n_inputs=12; the input cells go to ar_inference too")
    parser.add_argument("--idle-ms", type=float, default=0.0,
                        help="sleep this long before each stage's first call of a frame (untimed), as a process on the bus waits for its"
                             " inputs (60: ~10 Hz); 0: back to back (bench/idle_penalty.py: what the wait costs on this host)")
    args = parser.parse_args(argv)
    fail = error or parser.error
    from stages.lib.base import ConfigError, check_output

    for flag, path, folder in (("--json", args.json, False), ("--keep", args.keep, True)):
        try:  # before the work: a bad path must not cost the run
            check_output(path, flag, folder=folder)
        except ConfigError as exc:
            fail(str(exc))
    for flag, value, least in (("--frames", args.frames, 1), ("--segments", args.segments, 1), ("--warmup", args.warmup, 0),
                               ("--threads", args.threads, 0)):
        if value < least:
            fail(f"{flag} {value}: must be >= {least}")
    if not (args.idle_ms >= 0 and args.idle_ms < 10_000):
        fail(f"--idle-ms {args.idle_ms}: expected 0 to 10000 ms")
    args.modes = tuple(m.strip() for m in args.modes.split(",") if m.strip())
    if not args.modes or set(args.modes) - set(MODES):
        fail(f"--modes {','.join(args.modes)!s}: choose among {', '.join(MODES)}")
    from stages.offline.evaluation import _key_values

    try:
        args.set = _key_values(args.set, "--set")
        for mode in args.modes:  # unknown keys and bad values now, not after the dense data are built
            markov_config(argparse.Namespace(set=args.set, backend="numpy", device="cpu"), mode)
    except (ValueError, ConfigError) as exc:
        fail(str(exc))
    # the backend of the device, and the device itself, before any work (a CPU machine asked for cuda: exit 2, not 0)
    if args.backend is None:  # the device's fastest chain: on a GPU the one-kernel chain where numba.cuda can run it
        from stages.lib.markov import cuda_chain

        args.backend = "numpy" if args.device == "cpu" else "cuda" if args.device.startswith("cuda") and cuda_chain.available() else "torch"
    if args.backend == "cuda":
        from stages.lib.markov import cuda_chain

        if args.device == "cpu":
            args.device = "cuda"
        if (reason := cuda_chain.unavailable_reason()) is not None:
            fail(f"--backend cuda: {reason}; nothing measured")
    elif args.device != "cpu":
        args.backend = "torch"
        import torch

        if args.device.startswith("cuda") and not torch.cuda.is_available():
            fail(f"--device {args.device}: no CUDA device here (torch.cuda.is_available() is false); nothing measured")
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    sizes = args.vehicles
    if args.threads:
        import torch

        torch.set_num_threads(args.threads)
    full = full_data_dir()
    if full is not None:
        data, recording, sequences = full, SOURCES[args.source], None
        print(f"data: {full} ({FULL_DATA_ENV}), source {recording}")
    else:
        data, recording, sequences = DEFAULT_DATA_DIR, SOURCES["k729"], None
        print(f"data: {FULL_DATA_ENV} not set: the embedded K729 scenario's sequences (short: figures less stable)")
    from stages.lib.markov import load_or_build_stencils
    from stages.markov_prediction.core import grid_config

    keep = args.keep
    if keep is not None:
        from stages.lib.datasets import DatasetError
        from stages.lib.datasets.loader import find_recording
        from stages.lib.datasets.superimpose import check_out_apart

        try:
            check_out_apart(keep, find_recording(data, recording), flag="--keep")
        except DatasetError as exc:
            print(f"bench/dense.py: {exc}", file=sys.stderr)
            return 2
    stencils = load_or_build_stencils(grid_config(markov_config(args, "baseline")))  # --set applies to both modes: one grid
    if keep is None:  # a temporary folder holds ~20 MB per N: removed at exit, also when the run fails
        keep = Path(tempfile.mkdtemp(prefix="iamp-dense-"))
        atexit.register(shutil.rmtree, keep, ignore_errors=True)
    per_segment = -(-args.frames // args.segments)  # (run_one's split: whole stretches)
    print(f"cpu cores {os.cpu_count()}, backend {args.backend} on {args.device}; per N {args.segments} stretch(es) of {args.warmup} warm-up + "
          f"{per_segment} timed frames ({args.segments * per_segment} timed); timings include any other load on the machine"
          + (f"; each stage after {args.idle_ms:g} ms asleep (--idle-ms)" if args.idle_ms else "; the stages back to back"))
    from testkit import host_speed

    host = host_speed.reference()  # (this host's speed apart from the project's code: figures of other days read against it)
    print(host_speed.line(host))
    report: dict = {"source": recording, "backend": args.backend, "device": args.device, "host_reference": host, "idle_ms": args.idle_ms,
                    "modes": {m: {"by_vehicles": {}} for m in args.modes}}
    for n in sizes:
        built = build_dense(data, recording, n, keep, sequences=sequences)
        res = run_one(keep, built.name, args, stencils, target=n)
        for mode in args.modes:
            report["modes"][mode]["by_vehicles"][str(n)] = res[mode]
        print(f"N={n}: {built.name}, {len(built.layers)} layers, recording mean {built.vehicles_mean:.1f} vehicles/frame; "
              + "; ".join(f"{m} frame p50 {res[m]['frame_ms_median']:.1f} ms (cpu {res[m]['frame_cpu_ms_median']:.1f}), markov_prediction p50 "
                          f"{res[m]['stages']['markov_prediction']['ms_median']:.1f} ms (cpu {res[m]['stages']['markov_prediction']['cpu_ms_median']:.1f}, "
                          f"after its last input {res[m]['stages']['markov_prediction']['after_last_input_ms_median']:.1f}, "
                          f"idle {res[m]['stages']['markov_prediction']['idle_ms_mean']:.1f} per frame, "
                          f"{res[m]['pairs_median']:.0f} pairs; at {n} ± {AT_N_WITHIN} vehicles, {res[m]['at_n']['frames']} frames: frame "
                          f"{res[m]['at_n']['frame_ms_median']:.1f}, markov_prediction {res[m]['at_n']['markov_prediction_ms_median']:.1f})"
                          for m in args.modes),
              flush=True)
        if args.json:  # written after every N, so that a run cut short keeps what it measured
            write_json(args.json, report)
    stage_names = [*UPSTREAM, "ar_inference", "markov_prediction"]
    print()
    print(f"{'mode':<9}{'N':>4}{'veh':>6}{'pairs':>7} | " + " ".join(f"{s[:12]:>12}" for s in stage_names) + " | frame p50    p95")
    for mode in args.modes:
        for n in sizes:
            r = report["modes"][mode]["by_vehicles"][str(n)]
            cells = [f"{r['stages'][s]['ms_median']:12.1f}" if s in r["stages"] else f"{'-':>12}" for s in stage_names]
            print(f"{mode:<9}{n:>4}{r['vehicles_median']:>6.0f}{r['pairs_median']:>7.0f} | " + " ".join(cells)
                  + f" | {r['frame_ms_median']:9.1f} {r['frame_ms_p95']:6.1f}")
    print("(stage columns: median wall ms per frame; frame = sum of the mode's stages)")
    print()
    print("CPU time of this process (time.process_time: less sensitive to other load than wall time; all threads counted)")
    print(f"{'mode':<9}{'N':>4}{'pairs':>7} | " + " ".join(f"{s[:12]:>12}" for s in stage_names[1:]) + " | frame cpu p50")
    for mode in args.modes:
        for n in sizes:
            r = report["modes"][mode]["by_vehicles"][str(n)]
            cells = [f"{r['stages'][s]['cpu_ms_median']:12.1f}" if s in r["stages"] else f"{'-':>12}" for s in stage_names[1:]]
            print(f"{mode:<9}{n:>4}{r['pairs_median']:>7.0f} | " + " ".join(cells) + f" | {r['frame_cpu_ms_median']:9.1f}")
    print()
    for n in sizes if set(args.modes) == set(MODES) else ():
        h, b = (report["modes"][m]["by_vehicles"][str(n)] for m in MODES)
        print(f"N={n:>3}: hybrid/baseline frame {h['frame_ms_median'] / b['frame_ms_median']:.2f}, "
              f"markov_prediction {h['stages']['markov_prediction']['ms_median'] / b['stages']['markov_prediction']['ms_median']:.2f}")
    if len(sizes) > 1:
        for mode in args.modes:
            rows = [report["modes"][mode]["by_vehicles"][str(n)] for n in sizes]
            fits = {label: exponent([r["pairs_median"] for r in rows], values)
                    for label, values in (("frame", [r["frame_ms_median"] for r in rows]),
                                          ("markov_prediction", [r["stages"]["markov_prediction"]["ms_median"] for r in rows]),
                                          ("markov_prediction_cpu", [r["stages"]["markov_prediction"]["cpu_ms_median"] for r in rows]))}
            report["modes"][mode]["exponent"] = fits
            if fits["frame"] is None:
                print(f"{mode}: no exponent of time vs pairs (fewer than two different pair counts with a time)")
                continue
            print(f"{mode}: time ~ pairs^{fits['frame']:.2f} (frame), ^{fits['markov_prediction']:.2f} (markov_prediction), "
                  f"^{fits['markov_prediction_cpu']:.2f} (markov_prediction cpu)")
    report["host_reference_end"] = host_speed.reference()  # (the host may have changed under the run: its speed after it)
    print(f"after the run: {host_speed.line(report['host_reference_end'])}")
    if args.json:
        write_json(args.json, report)
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
