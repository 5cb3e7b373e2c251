"""Does any stage's state grow over a long live run? A recording played again and again with fresh track ids.

    python bench/soak.py [--passes 8] [--data PATH] [--recording k733_2018-05-02] [--json FILE]

A live tracker's stream never ends and every car gets a new id, so per-track
state that is never evicted, or a list of every track ever seen, grows all
day and with it the time per frame. This plays the recording through every
core of the hybrid pipeline in process (corridors, relations, intentions,
ar_inference, markov_prediction with its idle work), ``--passes`` times, each
pass with its track ids moved by 100,000 and its stamps continuing the
clock, and prints after each pass: its wall time, the process's peak RSS, the
number of container objects Python's collector tracks (``gc.get_objects``)
with the types whose count changed since the previous pass, and every list,
dict, set or deque attribute of the cores (and of their
attributes, one level down) holding more than 50 entries. Bounded state shows
as the same figures pass after pass. Prints figures, asserts nothing.

Session 38 (K733, 8 passes): peak RSS 421.9 MB after the first pass, 425.6
from the fourth on; 268,037 containers from the second pass on (the bench's
own records left out), no type changing. The one attribute that grew, the corridors stage's
decided tracks (132 per pass), is now capped at 1,000
(``kinematic_state.DECIDED_WINDOW``).
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import gc
import json
import resource
import sys
import time

from stages.lib.base import check_output_arg

ID_SHIFT = 100_000


def _sizes(obj, depth: int = 0, path: str = "", out: dict[str, int] | None = None) -> dict[str, int]:
    """Lengths of the list/dict/set/deque attributes of ``obj`` and of its project-defined attributes, one level down."""
    out = {} if out is None else out
    for name, value in (vars(obj).items() if hasattr(obj, "__dict__") else ()):
        if isinstance(value, (dict, list, set)) or type(value).__name__ == "deque":
            out[path + name] = len(value)
        elif depth < 1 and hasattr(value, "__dict__") and not isinstance(value, type) and type(value).__module__.startswith("stages"):
            _sizes(value, depth + 1, path + name + ".", out)
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--passes", type=int, default=8)
    p.add_argument("--data", default="", help="data folder (default: the embedded stages/data/taf-bw)")
    p.add_argument("--recording", default="k733_2018-05-02")
    p.add_argument("--json", help="write the per-pass figures here")
    args = p.parse_args(argv)
    if args.passes < 1:
        p.error(f"--passes {args.passes}: must be >= 1")
    check_output_arg(p, args.json, "--json")

    from stages.ar_inference import ARInference, ARInferenceConfig
    from stages.corridors import CorridorBuilder, CorridorsConfig, SceneMaps
    from stages.intentions import IntentionFilter, IntentionsConfig
    from stages.lib.datasets import DEFAULT_DATA_DIR, DatasetError, load_recording
    from stages.markov_prediction import MarkovPredictionConfig, MarkovPredictor
    from stages.relations import RelationExtractor, RelationsConfig
    from stages.tracks_source.core import TrackPlayer, TracksSourceConfig

    data = args.data or str(DEFAULT_DATA_DIR)
    try:
        recording = load_recording(data, args.recording)
    except DatasetError as exc:  # a data folder or recording that is not there: a bad command line
        print(f"soak: error: {exc}", file=sys.stderr)
        return 2
    maps = SceneMaps(data=data)
    cores = {
        "corridors": CorridorBuilder(CorridorsConfig(data=data), scene_maps=maps),
        "relations": RelationExtractor(RelationsConfig(data=data), scene_maps=maps),
        "intentions": IntentionFilter(IntentionsConfig(data=data), producer="intentions", scene_maps=maps),
        "ar_inference": ARInference(ARInferenceConfig.from_params({}, where="bench/soak.py"), producer="ar_inference"),
        "markov_prediction": MarkovPredictor(MarkovPredictionConfig.from_params({"mode": "hybrid", "corridor_weights": "intentions"},
                                                                                where="bench/soak.py"), producer="markov_prediction"),
    }
    cor, rel, intent, ar, markov = cores.values()
    print(f"soak: {args.recording}, {args.passes} passes, track ids moved by {ID_SHIFT:,} a pass", flush=True)
    scene, offset_ns, rows, types_before = None, 0, [], collections.Counter()
    for k in range(args.passes):
        t0, last, frames = time.perf_counter(), offset_ns, 0
        player = TrackPlayer(TracksSourceConfig(data=data, recording=args.recording), recording, map_sha256="", run_id="soak", producer="source")
        for _stamp, result in player:
            if scene is None and "scene" in result.outputs:
                scene = result.outputs["scene"]
            f = result.outputs["track_frame"]
            f = dataclasses.replace(f, header=dataclasses.replace(f.header, stamp_ns=f.header.stamp_ns + offset_ns),
                                    track_ids=f.track_ids + k * ID_SHIFT)
            corridor_set = cor.process(f, scene)[0]
            relation_set = rel.process(f, corridor_set, scene)[0]
            belief = intent.process(f, corridor_set, relation_set, scene)[0]
            profiles = ar.process(corridor_set, relation_set, f, scene)[0]
            markov.update({"corridor_set": corridor_set, "relation_set": relation_set, "scene": scene, "track_frame": f,
                           "intention_belief": belief, "acceleration_profiles": profiles})
            markov.idle()
            last, frames = f.header.stamp_ns, frames + 1
        offset_ns = last + 100_000_000  # the next pass continues the clock
        gc.collect()
        large = {f"{name}.{attr}": n for name, core in cores.items() for attr, n in _sizes(core).items() if n > 50}
        own = {id(r) for r in rows}  # this bench's own per-pass records, left out
        objects = [o for o in gc.get_objects() if id(o) not in own]
        types = collections.Counter(f"{type(o).__module__}.{type(o).__qualname__}" for o in objects)
        changed = {t: types[t] - types_before[t] for t in types.keys() | types_before.keys() if types[t] != types_before[t]} if k else {}
        types_before = types
        row = {"pass": k, "frames": frames, "wall_s": round(time.perf_counter() - t0, 1),
               "maxrss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1), "containers": len(objects),
               "types_changed": dict(sorted(changed.items(), key=lambda kv: -abs(kv[1]))[:8]), "large_state": large}
        del objects
        rows.append(row)
        print(f"pass {k}: {frames} frames in {row['wall_s']} s, peak RSS {row['maxrss_mb']} MB, containers {row['containers']:,}"
              f" (changed since the last pass: {row['types_changed'] or '-'}), state over 50 entries {large}", flush=True)
    if args.json:
        with open(args.json, "w") as handle:
            json.dump({"recording": args.recording, "passes": rows}, handle, indent=2)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
