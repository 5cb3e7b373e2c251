"""Processing time of the relations core (``RelationExtractor.process``) per frame, in-process.

    python bench/relations_timing.py [--data PATH] [--sequence 013] [--repeat 200]

1. Sequence 013 of K729 (the embedded scenario): the corridors core runs
   over every frame (continuity state as on the bus, not timed), then the
   relations core is timed on each frame once: median, p95 and max.
2. The busiest K729 frames: over every sequence of the data folder (the
   TAF-BW folder beside the repository when present, else the embedded one),
   the frame with the most (vehicle, corridor) pairs times objects, and the
   frame with the most conflict points; the core is timed `--repeat` times
   on each.

The scene's map and `SceneTables` are built on the first frame and are not
part of the per-frame figures; their build time is printed apart. Figures
are wall-clock on this machine (perf_counter), single thread.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]

from stages.corridors import CorridorBuilder, CorridorsConfig, SceneMaps
from stages.lib.datasets import DEFAULT_DATA_DIR, DatasetError, find_recording
from stages.lib.datasets.model import same_sequence_id
from stages.relations import RelationExtractor, RelationsConfig, SceneTables
from stages.tracks_source.core import TrackPlayer, TracksSourceConfig

RECORDING = "k729_2022-03-16"


def default_data_dir() -> Path:
    from stages.lib.datasets import full_data_dir

    full = full_data_dir()
    return full if full is not None and (full / "recorded_trackfiles" / RECORDING).is_dir() else DEFAULT_DATA_DIR


def frames_with_corridors(data: Path, sequences: tuple[str, ...], scene_maps: SceneMaps):
    """(sequence position, scene, track_frame, corridor_set) for every frame, corridors built in order."""
    player = TrackPlayer.open(TracksSourceConfig(data=str(data), recording=RECORDING, sequences=sequences), run_id="bench", producer="tracks")
    builder = CorridorBuilder(CorridorsConfig(), producer="corridors", scene_maps=scene_maps)
    scene = None
    for _stamp, result in player:
        scene = result.outputs.get("scene", scene)
        frame = result.outputs["track_frame"]
        corridor_set = builder.update({"track_frame": frame, "scene": scene}).outputs["corridor_set"]
        yield scene, frame, corridor_set


def stats_ms(times_s: list[float]) -> str:
    t = np.asarray(times_s) * 1e3
    return f"median {np.median(t):.2f} ms, p95 {np.percentile(t, 95):.2f} ms, max {t.max():.2f} ms (n={len(t)})"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", type=Path, default=None, help="data folder laid out like taf-bw")
    parser.add_argument("--sequence", default="013")
    parser.add_argument("--repeat", type=int, default=200)
    args = parser.parse_args(argv)
    if args.repeat < 1:
        parser.error(f"--repeat {args.repeat}: must be >= 1")
    data = args.data or default_data_dir()
    try:  # before the work: the K729 recording and its map in --data, the sequence in the embedded one
        ref = find_recording(data, RECORDING)
        if ref.map_path is None:
            raise DatasetError(f"recording {RECORDING} has no map: expected maps/{RECORDING}.osm in {data}")
        embedded = find_recording(DEFAULT_DATA_DIR, RECORDING)
        if not any(same_sequence_id(s, args.sequence) for s in embedded.sequence_ids):
            raise DatasetError(f"--sequence {args.sequence}: no such sequence of the embedded {RECORDING}; available: {', '.join(embedded.sequence_ids)}")
    except DatasetError as exc:
        print(f"relations_timing: error: {exc}", file=sys.stderr)
        return 2
    scene_maps = SceneMaps(data=data)
    config = RelationsConfig()

    # 1. one sequence, every frame once
    extractor = RelationExtractor(config, scene_maps=scene_maps)
    times, sizes = [], []
    first = True
    for scene, frame, corridor_set in frames_with_corridors(DEFAULT_DATA_DIR, (args.sequence,), scene_maps):
        if first:
            t0 = time.perf_counter()
            SceneTables(scene_maps.get(scene, config.projection).road_map)
            print(f"SceneTables build (once per map): {1e3 * (time.perf_counter() - t0):.2f} ms")
            extractor.process(frame, corridor_set, scene)  # loads the tables of this scene
            first = False
        t0 = time.perf_counter()
        relation_set, _issues = extractor.process(frame, corridor_set, scene)
        times.append(time.perf_counter() - t0)
        sizes.append((len(frame), len(relation_set.relations), sum(len(r.conflict_s_m) for r in relation_set.relations)))
    sizes = np.array(sizes)
    print(f"K729 sequence {args.sequence} ({DEFAULT_DATA_DIR}): {stats_ms(times)}")
    print(f"  objects/frame max {sizes[:, 0].max()}, pairs/frame max {sizes[:, 1].max()}, conflicts/frame max {sizes[:, 2].max()}")

    # 2. the busiest frames of the recording
    extractor = RelationExtractor(config, scene_maps=scene_maps)
    busiest: dict[str, tuple] = {}
    for scene, frame, corridor_set in frames_with_corridors(data, (), scene_maps):
        relation_set, _issues = extractor.process(frame, corridor_set, scene)
        pairs = len(relation_set.relations)
        loads = {
            "most pairs x objects": pairs * len(frame),
            "most conflict points": sum(len(r.conflict_s_m) for r in relation_set.relations),
        }
        for name, load in loads.items():
            if name not in busiest or load > busiest[name][0]:
                busiest[name] = (load, scene, frame, corridor_set)
    for name, (_load, scene, frame, corridor_set) in busiest.items():
        relation_set, issues = extractor.process(frame, corridor_set, scene)
        times = []
        for _ in range(args.repeat):
            t0 = time.perf_counter()
            extractor.process(frame, corridor_set, scene)
            times.append(time.perf_counter() - t0)
        n_conflicts = sum(len(r.conflict_s_m) for r in relation_set.relations)
        n_objects = sum(len(r.object_track_ids) for r in relation_set.relations)
        print(
            f"K729 frame with the {name} ({data}, run frame {frame.header.frame_index}): {len(frame)} objects, "
            f"{len(relation_set.relations)} vehicle-corridor pairs, {n_objects} lateral objects, {n_conflicts} conflicts, {len(issues)} issues"
        )
        print(f"  {stats_ms(times)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
