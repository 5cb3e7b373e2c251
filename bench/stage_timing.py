"""Processing time of the corridors core per frame, in-process; prints figures, asserts nothing.

1. The busiest K729 frame (most vehicles, over every sequence found): a fresh
   core (map already loaded, route caches warm) replays the 20 frames before
   it untimed, then processes it timed; repeated.
2. Sequence 013 frame by frame: a first pass (route geometry built on first
   use, the map load itself excluded) and a second, warm pass.

    python bench/stage_timing.py [--data PATH] [--repeats N]

PATH defaults to the TAF-BW folder beside the repository, else the embedded
``stages/data/taf-bw``.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]

from bus_schemas import AgentType
from plot_frame import default_data_dir, scene_for, track_frames
from stages.corridors import CorridorBuilder, CorridorsConfig, SceneMaps
from stages.lib.datasets import DatasetError, load_recording

RECORDING = "k729_2022-03-16"
VEHICLES = [t.value for t in AgentType if t.is_vehicle]


def _figures(times_s: list[float]) -> str:
    ms = np.asarray(times_s) * 1e3
    return f"median {statistics.median(ms):6.2f} ms  p95 {np.percentile(ms, 95):6.2f} ms  max {ms.max():6.2f} ms  (n={len(ms)})"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", type=Path, default=None)
    parser.add_argument("--repeats", type=int, default=50)
    args = parser.parse_args(argv)
    if args.repeats < 1:
        parser.error(f"--repeats {args.repeats}: must be >= 1")
    data = args.data or default_data_dir()
    try:
        recording = load_recording(data, RECORDING)
    except DatasetError as exc:  # a data folder without the K729 recording: a bad command line
        print(f"stage_timing: error: {exc}", file=sys.stderr)
        return 2
    config = CorridorsConfig()
    scene_maps = SceneMaps(config, data=data)

    busiest = None
    for sequence in recording.sequences:
        is_vehicle = np.isin(sequence.agent_type, VEHICLES)
        if not is_vehicle.any():
            continue
        values, counts = np.unique(sequence.frame_index[is_vehicle], return_counts=True)
        k = int(counts.argmax())
        if busiest is None or counts[k] > busiest[2]:
            busiest = (sequence, int(values[k]), int(counts[k]))
    sequence, frame_index, n_vehicles = busiest
    scene = scene_for(recording, sequence)
    frames = [(view.frame_index, frame) for view, frame in track_frames(sequence, scene.scene_id)]
    position = next(i for i, (index, _f) in enumerate(frames) if index == frame_index)
    before = frames[max(0, position - 20) : position]
    t0 = time.perf_counter()
    warm = CorridorBuilder(config, scene_maps=scene_maps)
    warm.process(frames[position][1], scene)
    print(f"map load + first frame (cold caches): {1e3 * (time.perf_counter() - t0):.1f} ms")
    for _index, frame in frames:  # warm the route caches on the whole sequence
        warm.process(frame, scene)
    times = []
    for _ in range(args.repeats):
        builder = CorridorBuilder(config, scene_maps=scene_maps)
        for _index, frame in before:
            builder.process(frame, scene)
        t0 = time.perf_counter()
        corridor_set, _issues = builder.process(frames[position][1], scene)
        times.append(time.perf_counter() - t0)
    n_corridors = sum(len(v.corridors) for v in corridor_set.vehicles)
    print(
        f"busiest K729 frame: sequence {sequence.id} frame {frame_index}, {n_vehicles} vehicles, "
        f"{len(frames[position][1])} objects, {n_corridors} corridors"
    )
    print(f"  {_figures(times)}")

    sequence = recording.sequence("013")
    scene = scene_for(recording, sequence)
    frames = [frame for _view, frame in track_frames(sequence, scene.scene_id)]
    for label, maps in (("first pass (route caches cold)", SceneMaps(config, data=data)), ("second pass (warm)", None)):
        if maps is not None:
            maps.get(scene, config.projection)  # the map load is not a per-frame cost
            first_maps = maps
        builder = CorridorBuilder(config, scene_maps=maps or first_maps)
        times = []
        for frame in frames:
            t0 = time.perf_counter()
            builder.process(frame, scene)
            times.append(time.perf_counter() - t0)
        print(f"sequence 013, {label}: {_figures(times)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
