"""Intentions and ar_inference alone on dense traffic: CPU ms per frame, and a digest of their outputs to check identity.

    python bench/intentions_ar.py [--vehicles 18] [--frames 20] [--warmup 5] [--segments 2] [--source k733|k729]
                                  [--save FILE | --check FILE] [--repeat 1] [--profile] [--restrict REGEX]

The frames are those of ``bench/dense.py`` and ``bench/upstream.py`` (the
same recording built by ``build_dense``, the same segments, fresh cores per
segment). The source, ``CorridorBuilder`` and ``RelationExtractor`` run
once, untimed; their outputs are then played ``--repeat`` times through
fresh ``IntentionFilter`` and ``ARInference`` cores (each loads the model,
as the stage does). Printed per stage: median and p95 CPU ms
(``time.process_time``) and median wall ms over the timed frames, each figure the median of the runs'
medians.

Identity: every frame (warm-up frames too) of every segment, the encoded
``IntentionBelief`` and ``AccelerationProfiles`` (``Message.encode``: every
float bit for bit) and the issues (kind, track, detail) are hashed
(sha256). ``--save`` writes the digests per frame to a JSON file,
``--check`` compares with such a file and prints the first frames that
differ (exit status 1 if any does): run ``--save`` before changing either
stage and ``--check`` after it. The particle filter's random numbers come
from generators seeded by (seed, frame, track), so the digests are the same
from run to run.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from stages.lib.datasets import full_data_dir, load_recording
from stages.lib.datasets.superimpose import build_dense

from upstream import SOURCES, _issues_digest, _play, dense_spans, save_or_check

STAGES = ("intentions", "ar_inference")


def upstream_outputs(data_dir: Path, name: str, spans) -> list[list[tuple]]:
    """Per span, per frame: (frame, corridor_set, relation_set, scene) from fresh corridors and relations cores."""
    from stages.corridors import CorridorBuilder, CorridorsConfig, SceneMaps
    from stages.relations import RelationExtractor, RelationsConfig

    recording = load_recording(data_dir, name)
    scene_maps = SceneMaps(data=data_dir)
    out = []
    for first, warmup, timed in spans:
        corridors = CorridorBuilder(CorridorsConfig(), scene_maps=scene_maps)
        relations = RelationExtractor(RelationsConfig(), scene_maps=scene_maps)
        frames = []
        for _n, frame, scene in _play(recording, name, first, warmup + timed):
            corridor_set = corridors.process(frame, scene)[0]
            relation_set = relations.process(frame, corridor_set, scene)[0]
            frames.append((frame, corridor_set, relation_set, scene))
        out.append(frames)
    return out


def run(data_dir: Path, spans, played, *, profile=None) -> tuple[dict, list[str]]:
    """The frames `played` (per span) through fresh intentions and ar_inference cores; times and digests."""
    from stages.ar_inference import ARInference, ARInferenceConfig
    from stages.corridors import SceneMaps
    from stages.intentions import IntentionFilter, IntentionsConfig

    scene_maps = SceneMaps(data=data_dir)
    cpu = {s: [] for s in STAGES}
    wall = {s: [] for s in STAGES}
    digests: list[str] = []
    for (first, warmup, timed), frames in zip(spans, played):
        intentions = IntentionFilter(IntentionsConfig(), producer="intentions", scene_maps=scene_maps)
        ar = ARInference(ARInferenceConfig(), producer="ar_inference")  # loads the model: its name carries the file's digest
        for k, (frame, corridor_set, relation_set, scene) in enumerate(frames):
            timed = k >= warmup
            if profile is not None and timed:
                profile.enable()
            t0, c0 = time.perf_counter(), time.process_time()
            belief, belief_issues = intentions.process(frame, corridor_set, relation_set, scene)
            t1, c1 = time.perf_counter(), time.process_time()
            profiles, ar_issues = ar.process(corridor_set, relation_set, frame, scene)
            t2, c2 = time.perf_counter(), time.process_time()
            if profile is not None:
                profile.disable()
            h = hashlib.sha256()
            h.update(belief.encode() if belief is not None else b"none")
            h.update(_issues_digest(belief_issues))
            h.update(profiles.encode())
            h.update(_issues_digest(ar_issues))
            digests.append(h.hexdigest())
            if timed:
                cpu["intentions"].append((c1 - c0) * 1e3)
                cpu["ar_inference"].append((c2 - c1) * 1e3)
                wall["intentions"].append((t1 - t0) * 1e3)
                wall["ar_inference"].append((t2 - t1) * 1e3)
    figures = {
        stage: {
            "cpu_ms_median": float(np.median(cpu[stage])),
            "cpu_ms_p95": float(np.percentile(cpu[stage], 95)),
            "ms_median": float(np.median(wall[stage])),
        }
        for stage in STAGES
    }
    figures["frames"] = len(cpu["intentions"])
    return figures, digests


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--vehicles", default="18")
    parser.add_argument("--frames", type=int, default=20)
    parser.add_argument("--warmup", type=int, default=5)
    parser.add_argument("--segments", type=int, default=2)
    parser.add_argument("--source", choices=sorted(SOURCES), default="k733")
    parser.add_argument("--repeat", type=int, default=1)
    parser.add_argument("--keep", type=Path, default=None, help="folder for the dense recordings (reused when already built)")
    parser.add_argument("--save", type=Path, default=None, help="write the output digests per frame here")
    parser.add_argument("--check", type=Path, default=None, help="compare the output digests with this file")
    parser.add_argument("--profile", action="store_true", help="cProfile of the two stages over the timed frames of the first run: the top functions")
    parser.add_argument("--sort", default="tottime", help="profile order (pstats key)")
    parser.add_argument("--restrict", default="", help="profile: only functions whose file and name match this regex")
    args = parser.parse_args(argv)
    full = full_data_dir()
    if full is None:
        print("no full data ($IAMP_TAF_BW): nothing measured")
        return 2
    profile = None
    if args.profile:
        import cProfile

        profile = cProfile.Profile()
    keep = args.keep or Path(tempfile.gettempdir()) / "iamp-upstream-bench"
    print(f"data: {full}, source {SOURCES[args.source]}; {args.warmup} warm-up + {args.frames} timed frames per N in {args.segments} segments")
    all_digests: dict[str, list[str]] = {}
    for n in (int(x) for x in args.vehicles.split(",")):
        label = f"N={n}"
        built_name = f"{SOURCES[args.source]}-dense{n}"
        if not (keep / "recorded_trackfiles" / built_name).is_dir():
            build_dense(full, SOURCES[args.source], n, keep)
        n_frames = load_recording(keep, built_name).sequences[0].n_frames
        spans = dense_spans(n_frames, args.frames, args.warmup, args.segments)
        played = upstream_outputs(keep, built_name, spans)
        pairs = [sum(len(v.corridors) for v in cs.vehicles) for frames, (_f, w, _t) in zip(played, spans) for (_fr, cs, _r, _s) in frames[w:]]
        runs = []
        for r in range(max(1, args.repeat)):
            figures, digests = run(keep, spans, played, profile=profile if r == 0 else None)
            runs.append(figures)
            if r == 0:
                all_digests[label] = digests
            elif digests != all_digests[label]:
                print(f"{label}: outputs differ between runs (not deterministic)")
        fig = {stage: {k: float(np.median([f[stage][k] for f in runs])) for k in runs[0][stage]} for stage in STAGES}
        print(f"{label:>6}: pairs p50 {np.median(pairs):5.0f}, {runs[0]['frames']} frames x {len(runs)} | "
              + " | ".join(f"{stage} cpu p50 {fig[stage]['cpu_ms_median']:6.2f} ms p95 {fig[stage]['cpu_ms_p95']:6.2f} (wall p50 {fig[stage]['ms_median']:6.2f})"
                           for stage in STAGES), flush=True)
    status = save_or_check(all_digests, args.save, args.check)
    if profile is not None:
        import pstats

        pstats.Stats(profile).sort_stats(args.sort).print_stats(args.restrict, 45)
    return status


if __name__ == "__main__":
    sys.exit(main())
