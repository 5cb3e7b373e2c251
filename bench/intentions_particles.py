#!/usr/bin/env python3
"""Particles per vehicle for the intentions stage: time per frame and route accuracy for 100, 300 and 1000.

    python bench/intentions_particles.py [--data DIR] [--recording NAME] [--sequence ID ...] [--particles 100 300 1000] [--seeds 0 1 2]

Runs the corridors and relations cores once over the embedded K729
recording (every sequence in ``stages/data/taf-bw``, or those given), then the
``IntentionFilter`` for each particle count and seed over the same frames.
Prints, per particle count: the CPU and wall time of one
``IntentionFilter.process`` call (all vehicles of a frame; CPU time is the
figure to compare on a shared machine), per vehicle, and route_top1 of the
evaluation (``stages.offline.intentions_eval``) in the last frames before the
intersection entrance (bins 1 s and 0 s, pooled) and at 3 s and 2 s, as the
mean over the seeds and its spread (min..max), since a particle filter's
answer is random. Asserts nothing.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

from stages.corridors import SceneMaps
from stages.lib.datasets import DEFAULT_DATA_DIR, DEFAULT_RECORDING, DatasetError, load_recording
from stages.intentions import IntentionFilter, IntentionsConfig
from stages.offline.chain import chain_frames
from stages.offline.intentions_eval import IntentionEvalConfig, entering_events, route_windows
from stages.offline.truth import ground_truth, route_top1
from stages.tracks_source.core import file_sha256


def timed_run(frames, config: IntentionsConfig, scene_maps: SceneMaps):
    """Frames with beliefs, CPU and wall ms per frame (arrays), vehicles per frame."""
    intentions = IntentionFilter(config, producer="bench", scene_maps=scene_maps)
    out, cpu, wall, vehicles = [], [], [], []
    for item in frames:
        c0, w0 = time.process_time(), time.perf_counter()
        belief, _ = intentions.process(item.frame, item.corridor_set, item.relation_set, item.scene)
        cpu.append((time.process_time() - c0) * 1e3)
        wall.append((time.perf_counter() - w0) * 1e3)
        vehicles.append(len(belief.vehicles))
        out.append(dataclasses.replace(item, belief=belief))
    return out, np.asarray(cpu), np.asarray(wall), np.asarray(vehicles)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA_DIR)
    parser.add_argument("--recording", default=DEFAULT_RECORDING)
    parser.add_argument("--sequence", nargs="*", default=[])
    parser.add_argument("--particles", type=int, nargs="*", default=[100, 300, 1000])
    parser.add_argument("--seeds", type=int, nargs="*", default=[0, 1, 2])
    args = parser.parse_args(argv)
    if not args.particles or min(args.particles) < 1:
        parser.error("--particles: give one or more particle counts, each >= 1")
    if not args.seeds:
        parser.error("--seeds: give one or more seeds")

    scene_maps = SceneMaps(data=args.data)
    try:
        recording = load_recording(args.data, args.recording, tuple(args.sequence) or None)
    except DatasetError as exc:  # a data folder, recording or sequence that is not there: a bad command line
        print(f"intentions_particles: error: {exc}", file=sys.stderr)
        return 2
    sha = file_sha256(recording.map_path)
    t0 = time.perf_counter()
    sequences = [chain_frames(recording, seq, scene_maps, map_sha256=sha) for seq in recording.sequences]
    n_frames = sum(len(f) for f in sequences)
    print(f"{recording.name} sequences {','.join(s.id for s in recording.sequences)}: {n_frames} frames;"
          f" corridors + relations in {time.perf_counter() - t0:.1f} s")
    eval_cfg = IntentionEvalConfig()
    truth = []
    for seq, frames in zip(recording.sequences, sequences):
        road_map = scene_maps.get(frames[0].scene).road_map
        truth.append((ground_truth(seq), entering_events(frames, road_map)))

    print(f"{'particles':>9} {'cpu ms/frame':>12} {'p95':>6} {'wall ms':>8} {'cpu ms/veh':>10}"
          f" {'top1 last 1 s':>16} {'top1 3 s':>16} {'top1 2 s':>16} {'windows':>8}")
    for n in args.particles:
        cpu_all, wall_all, veh_all = [], [], []
        last, at3, at2 = [], [], []
        n_windows = 0
        for seed in args.seeds:
            windows = []
            for frames, (tracks, events) in zip(sequences, truth):
                scored, cpu, wall, vehicles = timed_run(frames, IntentionsConfig(particles_per_vehicle=n, seed=seed), scene_maps)
                cpu_all.append(cpu)
                wall_all.append(wall)
                veh_all.append(vehicles)
                windows += route_windows(scored, tracks, events, eval_cfg, recording.name, {})
            pick = lambda bins: [w for w in windows if w.bin_s in bins]  # noqa: E731
            last.append(route_top1([w.probabilities for w in pick((1.0, 0.0))], [w.truth for w in pick((1.0, 0.0))]))
            at3.append(route_top1([w.probabilities for w in pick((3.0,))], [w.truth for w in pick((3.0,))]))
            at2.append(route_top1([w.probabilities for w in pick((2.0,))], [w.truth for w in pick((2.0,))]))
            n_windows = len(pick((1.0, 0.0)))
        cpu = np.concatenate(cpu_all)
        wall = np.concatenate(wall_all)
        vehicles = np.concatenate(veh_all)
        busy = vehicles > 0
        per_vehicle = float(cpu[busy].sum() / vehicles[busy].sum())

        def spread(values):
            return f"{np.mean(values):.3f} ({min(values):.2f}..{max(values):.2f})"

        print(f"{n:>9d} {cpu.mean():>12.2f} {np.percentile(cpu, 95):>6.2f} {np.median(wall):>8.2f} {per_vehicle:>10.3f}"
              f" {spread(last):>16} {spread(at3):>16} {spread(at2):>16} {n_windows:>8d}")
    print(f"seeds {args.seeds}; top1 = route_top1 over windows with >= 2 corridors, mean over seeds (min..max);"
          f" {float(np.mean(vehicles)):.1f} vehicles per frame")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
