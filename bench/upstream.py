"""Corridors and relations alone on dense traffic: CPU ms per frame, and a digest of their outputs to check identity.

    python bench/upstream.py [--vehicles 18] [--frames 20] [--warmup 5] [--segments 2] [--source k733|k729]
                             [--embedded] [--save FILE | --check FILE] [--repeat 1] [--profile]

The frames are those of ``bench/dense.py`` (the same recording built by
``build_dense``, the same segments, fresh cores per segment) but only the
source, ``CorridorBuilder.process`` and ``RelationExtractor.process`` run;
printed per stage: median and p95 CPU ms (``time.process_time``) and median
wall ms over the timed frames (``--repeat`` runs, each figure the median of
the runs' medians). With ``--embedded`` the embedded K729 scenario's
sequences are played whole, back to back by one player (every frame
timed), instead of the dense recording.

Identity: every frame (warm-up frames too) of every segment, the encoded
``CorridorSet`` and ``RelationSet`` (``Message.encode``: every float bit for
bit) and the issues (kind, track, detail) are hashed (sha256). ``--save``
writes the digests per frame to a JSON file, ``--check`` compares with such
a file and prints the first frames that differ (exit status 1 if any does):
run ``--save`` before changing either stage and ``--check`` after it.
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

from stages.lib.datasets import DEFAULT_DATA_DIR, full_data_dir, load_recording
from stages.lib.datasets.superimpose import build_dense

SOURCES = {"k733": "k733_2018-05-02", "k729": "k729_2022-03-16"}


def _issues_digest(issues) -> bytes:
    return repr([(i.kind, i.agent_id, i.detail) for i in issues]).encode()


def _play(recording, name: str, first: int, count: int):
    """Yield (frame index, frame, scene) from frame ``first`` for ``count`` frames, a fresh player (sequences back to back)."""
    from stages.tracks_source.core import TrackPlayer, TracksSourceConfig

    config = TracksSourceConfig(recording=name)
    player = TrackPlayer(config, recording, map_sha256="", run_id="upstream", producer="source")
    scene = None
    for n, (_stamp, result) in enumerate(player):
        if n >= first + count:
            break
        if "scene" in result.outputs:
            scene = result.outputs["scene"]
        if n >= first:
            yield n, result.outputs["track_frame"], scene


def run(data_dir: Path, name: str, spans, *, profile=None) -> tuple[dict, list[str]]:
    """Play ``spans`` ((first frame, warm-up, timed frames)) through fresh cores each; times and digests."""
    from stages.corridors import CorridorBuilder, CorridorsConfig, SceneMaps
    from stages.relations import RelationExtractor, RelationsConfig

    recording = load_recording(data_dir, name)
    scene_maps = SceneMaps(data=data_dir)
    cpu = {"corridors": [], "relations": []}
    wall = {"corridors": [], "relations": []}
    digests: list[str] = []
    pairs = []
    for first, warmup, timed in spans:
        corridors = CorridorBuilder(CorridorsConfig(), scene_maps=scene_maps)
        relations = RelationExtractor(RelationsConfig(), scene_maps=scene_maps)
        for n, frame, scene in _play(recording, name, first, warmup + timed):
            timed_frame = n >= first + warmup
            if profile is not None and timed_frame:
                profile.enable()
            t0, c0 = time.perf_counter(), time.process_time()
            corridor_set, corridor_issues = corridors.process(frame, scene)
            t1, c1 = time.perf_counter(), time.process_time()
            relation_set, relation_issues = relations.process(frame, corridor_set, scene)
            t2, c2 = time.perf_counter(), time.process_time()
            if profile is not None and timed_frame:
                profile.disable()
            h = hashlib.sha256()
            h.update(corridor_set.encode())
            h.update(_issues_digest(corridor_issues))
            h.update(relation_set.encode() if relation_set is not None else b"none")
            h.update(_issues_digest(relation_issues))
            digests.append(h.hexdigest())
            if timed_frame:
                cpu["corridors"].append((c1 - c0) * 1e3)
                cpu["relations"].append((c2 - c1) * 1e3)
                wall["corridors"].append((t1 - t0) * 1e3)
                wall["relations"].append((t2 - t1) * 1e3)
                pairs.append(sum(len(v.corridors) for v in corridor_set.vehicles))
    figures = {
        stage: {
            "cpu_ms_median": float(np.median(cpu[stage])),
            "cpu_ms_p95": float(np.percentile(cpu[stage], 95)),
            "ms_median": float(np.median(wall[stage])),
        }
        for stage in cpu
    }
    figures["pairs_median"] = float(np.median(pairs)) if pairs else 0.0
    figures["frames"] = len(pairs)
    return figures, digests


def dense_spans(n_frames: int, frames: int, warmup: int, segments: int):
    """The segments of ``bench/dense.py``: (first frame, warm-up, timed) spread evenly over the recording."""
    per_segment = -(-frames // segments)
    spans = []
    for segment in range(segments):
        start = int((segment + 0.5) * n_frames / segments) - warmup - per_segment // 2
        start = min(max(start, 0), max(n_frames - warmup - per_segment, 0))
        spans.append((start, warmup, per_segment))
    return spans


def save_or_check(all_digests: dict[str, list[str]], save: Path | None, check: Path | None) -> int:
    """``--save``: write the per-frame digests; ``--check``: compare with such a file, print the first frames that
    differ; returns the exit status (1 if any label is missing or any frame differs)."""
    status = 0
    if save:
        save.write_text(json.dumps(all_digests, indent=1))
        print(f"wrote digests of {sum(len(d) for d in all_digests.values())} frames to {save}")
    if check:
        reference = json.loads(check.read_text())
        for label, digests in all_digests.items():
            ref = reference.get(label)
            if ref is None:
                print(f"{label}: not in {check}")
                status = 1
                continue
            differ = [k for k, (a, b) in enumerate(zip(digests, ref)) if a != b]
            if differ or len(ref) != len(digests):
                print(f"{label}: {len(differ)} of {len(digests)} frames differ (first {differ[:5]}), {len(ref)} frames in the reference")
                status = 1
            else:
                print(f"{label}: all {len(digests)} frames identical to {check}")
    return status


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--vehicles", default="18")
    parser.add_argument("--frames", type=int, default=20)
    parser.add_argument("--warmup", type=int, default=5)
    parser.add_argument("--segments", type=int, default=2)
    parser.add_argument("--source", choices=sorted(SOURCES), default="k733")
    parser.add_argument("--embedded", action="store_true", help="the embedded K729 scenario's sequences, whole, instead of dense traffic")
    parser.add_argument("--repeat", type=int, default=1)
    parser.add_argument("--keep", type=Path, default=None, help="folder for the dense recordings (reused when already built)")
    parser.add_argument("--save", type=Path, default=None, help="write the output digests per frame here")
    parser.add_argument("--check", type=Path, default=None, help="compare the output digests with this file")
    parser.add_argument("--profile", action="store_true", help="cProfile of the two stages over the timed frames of the first run: the top functions")
    parser.add_argument("--sort", default="tottime", help="profile order (pstats key)")
    parser.add_argument("--restrict", default="", help="profile: only functions whose file and name match this regex")
    args = parser.parse_args(argv)
    profile = None
    if args.profile:
        import cProfile

        profile = cProfile.Profile()
    keep = args.keep or Path(tempfile.gettempdir()) / "iamp-upstream-bench"
    results: dict[str, list] = {}
    if args.embedded:
        name = SOURCES["k729"]
        recording = load_recording(DEFAULT_DATA_DIR, name)
        cases = [("embedded", DEFAULT_DATA_DIR, name, [(0, 0, recording.n_frames)])]
        print(f"data: the embedded {name}, {len(recording.sequences)} sequences back to back, every frame")
    else:
        full = full_data_dir()
        if full is None:
            print("no full data ($IAMP_TAF_BW): use --embedded")
            return 2
        cases = []
        for n in (int(x) for x in args.vehicles.split(",")):
            built_name = f"{SOURCES[args.source]}-dense{n}"
            if not (keep / "recorded_trackfiles" / built_name).is_dir():
                build_dense(full, SOURCES[args.source], n, keep)
            n_frames = load_recording(keep, built_name).sequences[0].n_frames
            cases.append((f"N={n}", keep, built_name, dense_spans(n_frames, args.frames, args.warmup, args.segments)))
        print(f"data: {full}, source {SOURCES[args.source]}; {args.warmup} warm-up + {args.frames} timed frames per N in {args.segments} segments")
    all_digests: dict[str, list[str]] = {}
    report = {}
    for label, data_dir, name, spans in cases:
        runs = []
        for r in range(max(1, args.repeat)):
            figures, digests = run(data_dir, name, spans, profile=profile if r == 0 else None)
            runs.append(figures)
            if r == 0:
                all_digests[label] = digests
            elif digests != all_digests[label]:
                print(f"{label}: outputs differ between runs (not deterministic)")
        fig = {stage: {k: float(np.median([f[stage][k] for f in runs])) for k in runs[0][stage]} for stage in ("corridors", "relations")}
        report[label] = {**fig, "pairs_median": runs[0]["pairs_median"]}
        print(f"{label:>9}: pairs p50 {runs[0]['pairs_median']:5.0f}, {runs[0]['frames']} frames | "
              + " | ".join(f"{stage} cpu p50 {fig[stage]['cpu_ms_median']:6.2f} ms p95 {fig[stage]['cpu_ms_p95']:6.2f} (wall p50 {fig[stage]['ms_median']:6.2f})"
                           for stage in ("corridors", "relations")), flush=True)
    if len(report) > 1:
        x = np.log([max(r["pairs_median"], 1.0) for r in report.values()])
        for stage in ("corridors", "relations"):
            slope = float(np.polyfit(x, np.log([r[stage]["cpu_ms_median"] for r in report.values()]), 1)[0])
            print(f"{stage}: cpu time ~ pairs^{slope:.2f}")
    status = save_or_check(all_digests, args.save, args.check)
    if profile is not None:
        import pstats

        pstats.Stats(profile).sort_stats(args.sort).print_stats(args.restrict, 40)
    return status


if __name__ == "__main__":
    sys.exit(main())
