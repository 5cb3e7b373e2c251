"""Per-frame hashes of the markov_prediction core's outputs in every mode, to show a refactor changes no byte.

The embedded K729 sequence goes in-process through the upstream cores
(tracks_source -> corridors -> relations -> intentions -> ar_inference);
each frame's inputs then feed one ``MarkovPredictor`` per mode (cv,
corridor_cv, baseline, hybrid, plus a few config variants on fewer frames)
through ``update``, and the SHA-256 of every encoded CorridorPredictions and
MotionGrid (and of the issue list) is kept per frame. ``--save-inputs``
stores the upstream messages (encoded) so that a later run replays the very
same inputs (``--inputs``), untouched by changes upstream. Prints figures,
asserts nothing; ``--compare`` prints the frames that differ (exit status 1
if any).

    python bench/markov_modes_identity.py --frames 300 --save-inputs /tmp/in.pkl --save /tmp/ref.json
    python bench/markov_modes_identity.py --inputs /tmp/in.pkl --compare /tmp/ref.json
"""

from __future__ import annotations

import argparse
import hashlib
import json
import pickle
import runpy
import sys
import time
from pathlib import Path

import bus_schemas as bs

#: name -> (mode, extra config, frame set, frames: 0 = all)
RUNS: dict[str, tuple[str, dict, str, int]] = {
    "cv": ("cv", {}, "embedded", 0),
    "corridor_cv": ("corridor_cv", {}, "embedded", 0),
    "baseline": ("baseline", {}, "embedded", 0),
    "hybrid": ("hybrid", {}, "embedded", 0),
    "baseline-point-uniform": ("baseline", {"grid_distribution": "point", "corridor_weights": "uniform", "initial_box": "measurement"}, "embedded", 60),
    # the first 60 embedded frames have standing cars only: with hybrid's default standstill rates they would not reach
    # the chain, so these two keep the fixed rate (their hashes are those of before the scene rates)
    "hybrid-direct": ("hybrid", {"hybrid_input": "direct", "hybrid_speed_restriction": False, "hybrid_standstill_rates_hz": ()}, "embedded", 60),
    "hybrid-psi-unrestricted": ("hybrid", {"hybrid_speed_restriction": False, "hybrid_standstill_rates_hz": ()}, "embedded", 60),
    # the fixed standstill start rate of every standing car (hybrid's default before the scene rates)
    "hybrid-standstill-fixed": ("hybrid", {"hybrid_standstill_rates_hz": ()}, "embedded", 0),
    "baseline-torch": ("baseline", {"backend": "torch"}, "embedded", 30),
    "hybrid-torch": ("hybrid", {"backend": "torch"}, "embedded", 30),
    # the calibrated and online spread (along the corridors: the lateral spread per step; cv: the round blur)
    "hybrid-spread": ("hybrid", {"spread_calibration": "shipped", "spread_online": True}, "embedded", 0),
    "corridor_cv-spread": ("corridor_cv", {"spread_calibration": "shipped", "spread_online": True}, "embedded", 100),
    "cv-spread": ("cv", {"spread_calibration": "shipped", "spread_online": True}, "embedded", 100),
    # the embedded scenario has no crossing conflicts: bench/markov_stage.py's synthetic frames have (the second pass)
    "cv-synthetic": ("cv", {}, "synthetic", 0),
    "corridor_cv-synthetic": ("corridor_cv", {}, "synthetic", 0),
    "baseline-synthetic": ("baseline", {}, "synthetic", 0),
    "hybrid-synthetic": ("hybrid", {}, "synthetic", 0),
}
_PORTS = ("track_frame", "corridor_set", "relation_set", "scene", "intention_belief", "acceleration_profiles")


def upstream(n_frames: int) -> list[dict[str, bytes]]:
    """The encoded input messages of the markov stage for the first ``n_frames`` frames."""
    from stages.ar_inference import ARInference, ARInferenceConfig
    from stages.corridors import SceneMaps
    from stages.intentions import IntentionsConfig
    from stages.lib.datasets import DEFAULT_DATA_DIR, DEFAULT_RECORDING, DEFAULT_SEQUENCE, load_recording
    from stages.offline.chain import Chain

    rec = load_recording(DEFAULT_DATA_DIR, DEFAULT_RECORDING, (DEFAULT_SEQUENCE,))
    chain = Chain(rec, rec.sequences[0], SceneMaps(), intentions=IntentionsConfig(), max_frames=n_frames, map_sha256="", run_id="bench", producer="bench")
    ar = ARInference(ARInferenceConfig(), producer="bench")
    out = []
    for item in chain:
        profiles, _ = ar.process(item.corridor_set, item.relation_set, item.frame, item.scene)
        msgs = dict(zip(_PORTS, (item.frame, item.corridor_set, item.relation_set, item.scene, item.belief, profiles)))
        out.append({k: (type(m).__name__, m.encode()) for k, m in msgs.items() if m is not None})
    return out


def synthetic(n_frames: int = 6, n_pairs: int = 40) -> list[dict[str, bytes]]:
    """bench/markov_stage.py's platoons with crossing conflicts, one seed per frame, encoded."""
    scenario = runpy.run_path(str(Path(__file__).resolve().parent / "markov_stage.py"))["scenario"]
    out = []
    for seed in range(n_frames):
        cs, rs = scenario(n_pairs, seed)
        out.append({"corridor_set": (type(cs).__name__, cs.encode()), "relation_set": (type(rs).__name__, rs.encode())})
    return out


def decode(frame: dict) -> dict[str, object]:
    return {k: getattr(bs, name).decode(data) for k, (name, data) in frame.items()}


def digest(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()[:16]


def run_modes(frames: dict[str, list[dict]], names: list[str]) -> tuple[dict[str, list[list[str]]], dict[str, float]]:
    """Per run name, per frame: [corridor_predictions hash, motion_grid hash, issues hash]; and seconds per run.

    ``frames`` holds the encoded inputs per frame set (``upstream``, ``synthetic``).
    """
    from stages.lib.markov import MarkovGridConfig, load_or_build_stencils
    from stages.markov_prediction import MarkovPredictionConfig, MarkovPredictor

    stencils = load_or_build_stencils(MarkovGridConfig())
    hashes: dict[str, list[list[str]]] = {}
    seconds: dict[str, float] = {}
    for name in names:
        mode, extra, which, limit = RUNS[name]
        predictor = MarkovPredictor(MarkovPredictionConfig(mode=mode, **extra), producer="bench", stencils=stencils)
        rows = []
        t0 = time.perf_counter()
        for i, frame in enumerate(frames[which][: limit or None]):
            result = predictor.update(decode(frame))
            issues = "\n".join(f"{x.kind}|{x.agent_id}|{x.detail}" for x in result.issues).encode()
            rows.append([digest(result.outputs["corridor_predictions"].encode()), digest(result.outputs["motion_grid"].encode()), digest(issues)])
        seconds[name] = time.perf_counter() - t0
        hashes[name] = rows
    return hashes, seconds


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=300, help="frames of the embedded sequence (ignored with --inputs)")
    ap.add_argument("--inputs", type=Path, help="replay upstream messages saved by --save-inputs")
    ap.add_argument("--save-inputs", type=Path)
    ap.add_argument("--save", type=Path, help="write the hashes as JSON")
    ap.add_argument("--compare", type=Path, help="compare with hashes written by --save")
    ap.add_argument("--runs", default=",".join(RUNS), help=f"comma-separated subset of {', '.join(RUNS)}")
    args = ap.parse_args(argv)
    if args.inputs:
        frames = pickle.loads(args.inputs.read_bytes())
    else:
        t0 = time.perf_counter()
        frames = {"embedded": upstream(args.frames), "synthetic": synthetic()}
        print(f"upstream: {len(frames['embedded'])} embedded and {len(frames['synthetic'])} synthetic frames in {time.perf_counter() - t0:.1f} s")
    if args.save_inputs:
        args.save_inputs.write_bytes(pickle.dumps(frames))
    names = [n for n in args.runs.split(",") if n]
    hashes, seconds = run_modes(frames, names)
    for name in names:
        rows = hashes[name]
        whole = digest("".join("".join(r) for r in rows).encode())
        print(f"{name:26s} {len(rows):4d} frames  {seconds[name]:7.1f} s  all-frames hash {whole}")
    if args.save:
        args.save.write_text(json.dumps(hashes))
    if args.compare:
        ref = json.loads(args.compare.read_text())
        bad = 0
        for name in names:
            if name not in ref:
                print(f"{name}: not in {args.compare}")
                continue
            mine, theirs = hashes[name], ref[name]
            diff = [i for i, (a, b) in enumerate(zip(mine, theirs)) if a != b]
            if len(mine) != len(theirs):
                diff.append(min(len(mine), len(theirs)))
            bad += len(diff)
            what = "byte-identical" if not diff else f"{len(diff)} frames differ, first {diff[:5]}"
            print(f"{name:26s} {len(mine)} frames vs {len(theirs)}: {what}")
        return 1 if bad else 0
    return 0


if __name__ == "__main__":
    sys.exit(main())
