"""Where a dense frame's time goes: wall time of named functions inside the stages, per call and per frame.

``bench/dense.py`` times whole stages; this script runs the same in-process
chain (its ``run_one``: a superimposed recording of about ``--vehicles``
vehicles per frame, fresh cores per segment, warm-up frames untimed) with
timers wrapped around named functions of the stages, so that the parts of a
stage show: for markov_prediction its phases (pairs, chain, belief), the
compiled chain kernel, the grids, the mode's start, the online curve choice's
back test; for the upstream stages their ``process``. Wrappers cost about a
microsecond per call; the functions wrapped are called a few times per frame.

Printed per function, over the timed frames only: ms per frame (its total
divided by the timed frames: what it adds to a frame on average), the median
over the timed frames of its time in each frame (``frame p50``: what the
median frame holds of it, apart from the rare calls such as the back test's),
median ms per call and calls per frame. Nested functions are each counted whole (the
chain phase includes the kernel), so the column does not add up. Prints
figures, asserts nothing; other load on the machine shows in them.

    python bench/frame_phases.py [--vehicles 18] [--frames 30] [--warmup 5] [--segments 2] [--source k733|k729]
                                 [--modes hybrid] [--backend numpy|torch|cuda] [--device cpu|cuda]
                                 [--function MODULE:QUALNAME ...] [--json FILE] [--set KEY=VALUE ...] [--idle-ms MS]

``--function`` adds a function to the default list (``MODULE:Class.method``
or ``MODULE:function``; one named twice is timed once); where a module binds
a wrapped function by name (``from x import f``), wrap it where it is called.
``--frames`` is rounded up to whole ``--segments`` stretches, as in
bench/dense.py. ``--json FILE`` writes
``functions.<qualname>.{ms_per_frame, frame_ms_median, ms_median, calls_per_frame}``,
``frames`` (timed), ``vehicles`` (the requested N; the measured ones are in
``stages``), ``modes``, ``source`` and ``stages`` (bench/dense.py's figures of
the same run, per mode).
"""

from __future__ import annotations

import argparse
import atexit
import collections
import functools
import importlib
import inspect
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from stages.lib.base import check_output_arg

MARKOV = "stages.markov_prediction.core:MarkovPredictor."
DEFAULT_FUNCTIONS = (
    "stages.corridors.core:CorridorBuilder.process",
    "stages.relations.core:RelationExtractor.process",
    "stages.intentions.core:IntentionFilter.process",
    "stages.lib.ar.inference:ARInference.process",
    "stages.lib.ar.model:ARModel.predict",
    MARKOV + "prepare",
    MARKOV + "update",
    MARKOV + "_pairs_phase",
    MARKOV + "_chain_phase",
    MARKOV + "_belief_phase",
    MARKOV + "_predict_chain",
    MARKOV + "_markov",
    MARKOV + "_back_test",
    MARKOV + "_finish_geometry",
    MARKOV + "_finish_grids",
    MARKOV + "_vehicle_pairs",
    MARKOV + "_screen",
    "stages.markov_prediction.modes.hybrid:Hybrid.start",
    "stages.markov_prediction.modes.hybrid:Hybrid.prepare_pairs",
    "stages.markov_prediction.modes.hybrid:Hybrid.read",
    "stages.markov_prediction.chain:PriorityPropagator.run",
    "stages.lib.markov.kernels:speed_priority_run",
    "stages.lib.markov.frame_kernels:footprint_grids",
)


class Timers:
    """Wall time of wrapped functions, kept only while ``timed`` is set."""

    def __init__(self) -> None:
        self.timed = False
        self.frames = 0
        self.calls: dict[str, list[float]] = collections.defaultdict(list)
        self.frame_of: dict[str, list[int]] = collections.defaultdict(list)  # the timed frame (0, 1, ...) of each call

    def on_frame(self, timed: bool) -> None:
        self.timed = timed
        self.frames += int(timed)

    def wrap(self, spec: str) -> None:
        """Wrap ``MODULE:QUALNAME`` in place (on its class or module); ``ValueError`` with a message when it is not found."""
        module_name, _, qualname = spec.partition(":")
        if not qualname:
            raise ValueError(f"--function {spec!r}: expected MODULE:QUALNAME, e.g. stages.corridors.core:CorridorBuilder.process")
        try:
            owner = importlib.import_module(module_name)
            *path, name = qualname.split(".")
            for part in path:
                owner = getattr(owner, part)
            original = getattr(owner, name)
            static = isinstance(inspect.getattr_static(owner, name), staticmethod)  # (wrapped as one again: no self)
        except (ImportError, AttributeError, ValueError) as exc:
            raise ValueError(f"--function {spec!r}: not found ({exc})") from None
        calls, frame_of = self.calls[qualname], self.frame_of[qualname]

        @functools.wraps(original)
        def timed(*args, **kwargs):
            if not self.timed:
                return original(*args, **kwargs)
            t0 = time.perf_counter()
            try:
                return original(*args, **kwargs)
            finally:
                calls.append(time.perf_counter() - t0)
                frame_of.append(self.frames - 1)

        setattr(owner, name, staticmethod(timed) if static else timed)

    def table(self) -> dict[str, dict[str, float]]:
        frames = max(self.frames, 1)
        out = {}
        for q, c in self.calls.items():
            if not c:
                continue
            per_frame = np.bincount(np.asarray(self.frame_of[q]), weights=np.asarray(c), minlength=frames)[:frames]
            out[q] = {"ms_per_frame": float(np.sum(c)) / frames * 1e3, "frame_ms_median": float(np.median(per_frame)) * 1e3,
                      "ms_median": float(np.median(c)) * 1e3, "calls_per_frame": len(c) / frames}
        return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--vehicles", type=int, default=18)
    parser.add_argument("--frames", type=int, default=30, help="timed frames")
    parser.add_argument("--warmup", type=int, default=5, help="untimed frames before each segment's timed ones")
    parser.add_argument("--segments", type=int, default=2)
    parser.add_argument("--source", choices=("k733", "k729"), default="k733")
    parser.add_argument("--modes", default="hybrid", help="comma-separated markov_prediction modes (hybrid, baseline)")
    parser.add_argument("--backend", choices=("numpy", "torch", "cuda"), default="numpy", help="markov_prediction's chain backend (as bench/dense.py)")
    parser.add_argument("--device", default="cpu", help="cpu or cuda (torch backend; ar_inference's net too)")
    parser.add_argument("--function", action="append", default=[], metavar="MODULE:QUALNAME", help="also time this function")
    parser.add_argument("--json", type=Path, default=None)
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="markov_prediction parameter (JSON value), as bench/dense.py --set, e.g. --set spread_online=true")
    parser.add_argument("--idle-ms", type=float, default=0.0, help="as bench/dense.py --idle-ms: each stage after this long asleep")
    args = parser.parse_args(argv)
    check_output_arg(parser, args.json, "--json")  # before the work: a bad path must not cost the run
    try:  # as a script, its folder is first on the module path (bench/ is not an installed package)
        import dense
    except ImportError:
        from bench import dense

    if not 1 <= args.vehicles <= dense.MAX_VEHICLES or args.frames < 1:
        parser.error(f"--vehicles must be 1 to {dense.MAX_VEHICLES} and --frames >= 1")

    # bench/dense.py's arguments, for its run_one
    dense_args = ["--vehicles", str(args.vehicles), "--frames", str(args.frames), "--warmup", str(args.warmup),
                  "--segments", str(args.segments), "--source", args.source, "--modes", args.modes,
                  "--backend", args.backend, "--device", args.device, "--idle-ms", str(args.idle_ms),
                  *(a for kv in args.set for a in ("--set", kv))]
    ns = dense.parse_args(dense_args, error=parser.error)  # (its checks, with this script's usage)
    timers = Timers()
    for spec in dict.fromkeys((*DEFAULT_FUNCTIONS, *args.function)):  # a function named twice is timed once
        try:
            timers.wrap(spec)
        except ValueError as exc:
            parser.error(str(exc))
    from stages.lib.datasets import DEFAULT_DATA_DIR, FULL_DATA_ENV, full_data_dir
    from stages.lib.datasets.superimpose import build_dense
    from stages.lib.markov import load_or_build_stencils
    from stages.markov_prediction.core import grid_config

    full = full_data_dir()
    data, recording = (full, dense.SOURCES[args.source]) if full is not None else (DEFAULT_DATA_DIR, dense.SOURCES["k729"])
    print(f"data: {data}" + ("" if full is not None else f" ({FULL_DATA_ENV} not set: the embedded K729 scenario)") + f", source {recording}")
    stencils = load_or_build_stencils(grid_config(dense.markov_config(ns, "baseline")))
    keep = Path(tempfile.mkdtemp(prefix="iamp-phases-"))
    atexit.register(shutil.rmtree, keep, ignore_errors=True)
    built = build_dense(data, recording, args.vehicles, keep)
    result = dense.run_one(keep, built.name, ns, stencils, on_frame=timers.on_frame)
    table = timers.table()
    first = result[ns.modes[0]]
    print(f"N={args.vehicles}: {timers.frames} timed frames, {first['vehicles_median']:.0f} vehicles and {first['pairs_median']:.0f} pairs per "
          f"frame (median); " + "; ".join(f"{m} frame p50 {r['frame_ms_median']:.1f} ms" for m, r in result.items()))
    print(f"{'function':<40}{'ms/frame':>10}{'frame p50':>11}{'median/call':>13}{'calls/frame':>13}")
    for q, row in sorted(table.items(), key=lambda kv: -kv[1]["ms_per_frame"]):
        print(f"{q:<40}{row['ms_per_frame']:10.2f}{row['frame_ms_median']:11.2f}{row['ms_median']:13.2f}{row['calls_per_frame']:13.2f}")
    print("(wall ms over the timed frames; nested functions each counted whole)")
    if args.json:
        dense.write_json(args.json, {"vehicles": args.vehicles, "frames": timers.frames, "modes": list(ns.modes), "source": recording,
                                     "functions": table, "stages": result})
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
