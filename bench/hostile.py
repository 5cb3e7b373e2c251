#!/usr/bin/env python3
"""Hostile inputs, by section; prints figures, asserts nothing (issues 12 and 13).

    python bench/hostile.py [--section NAME ...] [--n 100000] [--seed 13] [--objects 1000 ...] [--uncapped]

Sections (``--section`` repeatable; default: all):

- ``fuzz``: ``--n`` seeded mutations of the golden payloads
  (``tests/bus_schemas/mutations.py``: byte, structure and empty-object
  mutations) plus the targeted hostile payloads (the ``[0, 2**63]`` shape,
  negative and huge dims, wrong dtypes, byte lengths that do not match, deep
  nesting, 64 MB payloads), each decoded with ``bus_schemas.decode``. Prints
  how many decoded, the typed errors by class, the other exceptions (0 is the
  only right figure), the slowest decode and the peak RSS of this process.
- ``limits``: for every registered schema, a payload of nothing but empty
  maps (arrays of 1,000, under msgpack's ``max_array_len``) just under its
  ``MAX_BYTES``: about the most memory and time a payload can cost before it
  is rejected. Decoded in a child process: time and the child's peak RSS.

- ``big-frame``: well-formed TrackFrames of ``--objects`` objects (default
  1,000 and 500; ``tests/big_frames.py``: real K729 sequence 013 cars, the
  sequence overlaid with itself at other instants, each copy with its own
  track ids; three consecutive frames so tracks have a history) fed
  in-process to each core (corridors, relations, intentions, ar_inference,
  markov_prediction in hybrid mode), each in its own child process that
  loads the upstream outputs (computed once, pickled) and runs only its
  stage. Prints per stage the child's peak RSS and the ms of the last frame,
  objects and pairs kept, the output's encoded size against its schema's
  ``MAX_BYTES``, and issues by kind. Budget (stated in README and the stage
  docstrings): <= 1 GB peak RSS per stage on a 1,000-object frame with the
  default caps. ``--uncapped`` also runs corridors and relations with the
  caps lifted, to show the memory of the computation itself (relations
  took 6.5 GB on 1,000 objects before its projection was pruned and
  chunked).

Other sections (bus burst, the viewer) are meant to be added as functions
in ``SECTIONS``.
"""

from __future__ import annotations

import argparse
import collections
import resource
import subprocess
import sys
import time
from pathlib import Path
from typing import Callable

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "tests" / "bus_schemas"))

import msgpack  # noqa: E402

import bus_schemas as bs  # noqa: E402


def _peak_rss_mb(who: int = resource.RUSAGE_SELF) -> float:
    return resource.getrusage(who).ru_maxrss / 1024.0  # Linux: KiB


def _best_of(data: bytes, k: int = 5) -> float:
    """Decode time of one payload, best of ``k``, ms: tells a slow payload from a scheduling hiccup."""
    best = float("inf")
    for _ in range(k):
        t0 = time.perf_counter()
        try:
            bs.decode(data)
        except Exception:  # noqa: BLE001 - timing only
            pass
        best = min(best, (time.perf_counter() - t0) * 1e3)
    return best


def section_fuzz(args: argparse.Namespace) -> None:
    from mutations import mutated_payloads, targeted_payloads

    groups = {
        "mutated": lambda: mutated_payloads(args.n, seed=args.seed),
        "targeted": lambda: targeted_payloads(big=True),
    }
    print(f"## fuzz: {args.n} mutated golden payloads (seed {args.seed}) and the targeted ones, through bus_schemas.decode")
    total = collections.Counter()
    for group, payloads in groups.items():
        n = decoded = 0
        typed: collections.Counter[str] = collections.Counter()
        other: collections.Counter[str] = collections.Counter()
        slowest = (0.0, "", b"")
        times: list[float] = []
        t_all = time.perf_counter()
        for how, data in payloads():
            n += 1
            t0 = time.perf_counter()
            try:
                bs.decode(data, where="iamp/bench/x/y")
                decoded += 1
            except bs.SchemaError as exc:
                typed[type(exc).__name__] += 1
            except Exception as exc:  # noqa: BLE001 - the figure this section exists for
                other[f"{type(exc).__name__}: {str(exc)[:60]}"] += 1
            dt = (time.perf_counter() - t0) * 1e3
            times.append(dt)
            if dt > slowest[0]:
                slowest = (dt, f"{how} ({len(data)} bytes)", data)
        wall = time.perf_counter() - t_all
        total.update(payloads=n, decoded=decoded, typed=sum(typed.values()), other=sum(other.values()))
        print(f"{group}:")
        print(f"  payloads          {n}")
        print(f"  decoded           {decoded}")
        print(f"  typed errors      {sum(typed.values())}  " + ", ".join(f"{k} {v}" for k, v in sorted(typed.items())))
        print(f"  other exceptions  {sum(other.values())}" + "".join(f"\n    {v} x {k}" for k, v in other.most_common()))
        times.sort()
        print(f"  decode ms         p50 {times[len(times) // 2]:.3f}, p99 {times[int(len(times) * 0.99)]:.3f}, max {times[-1]:.1f}")
        print(f"  slowest decode    {slowest[0]:.1f} ms (the same payload again, best of 5: {_best_of(slowest[2]):.2f} ms): {slowest[1]}")
        print(f"  wall              {wall:.1f} s ({wall / max(n, 1) * 1e6:.0f} us per payload, generation included)")
    print(f"all: payloads {total['payloads']}, decoded {total['decoded']}, typed errors {total['typed']}, other exceptions {total['other']}")
    print(f"peak RSS (this process, generation included): {_peak_rss_mb():.0f} MB")


_LIMIT_CHILD = """
import resource, sys, time
sys.path.insert(0, {repo!r})
import msgpack
import bus_schemas as bs
cls = bs.REGISTRY[{schema!r}]
head = b"\\x83" + msgpack.packb("schema") + msgpack.packb(cls.SCHEMA) + msgpack.packb("v") + msgpack.packb(cls.VERSION) + msgpack.packb("body")
# arrays of 1,000 empty maps (under msgpack's max_array_len), as many as fit
inner = b"\\xdc" + (1000).to_bytes(2, "big") + b"\\x80" * 1000
k = (cls.MAX_BYTES - len(head) - 5) // len(inner)
data = head + b"\\xdd" + k.to_bytes(4, "big") + inner * k
rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
t0 = time.perf_counter()
try:
    bs.decode(data)
    what = "decoded"
except bs.SchemaError as exc:
    what = type(exc).__name__
dt = time.perf_counter() - t0
print(len(data), what, f"{{dt * 1e3:.0f}}", f"{{rss0:.0f}}", f"{{resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f}}")
"""


def section_limits(args: argparse.Namespace) -> None:
    print("## limits: per schema, a payload of empty maps just under MAX_BYTES (about the costliest payload still unpacked), in a child process")
    print(f"{'schema':28s} {'MAX_BYTES':>10s} {'result':>18s} {'decode ms':>10s} {'RSS before MB':>14s} {'peak RSS MB':>12s}")
    for schema, cls in sorted(bs.REGISTRY.items(), key=lambda kv: kv[1].MAX_BYTES):
        code = _LIMIT_CHILD.format(repo=str(REPO), schema=schema)
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600)
        if out.returncode != 0:
            print(f"{schema:28s} child failed: {out.stderr.strip().splitlines()[-1:]}")
            continue
        size, what, ms, rss0, rss = out.stdout.split()
        print(f"{schema:28s} {cls.MAX_BYTES:>10d} {what:>18s} {ms:>10s} {rss0:>14s} {rss:>12s}")
    head = msgpack.packb({"body": [], "schema": "x", "v": 1})
    print(f"(a payload whose schema cannot be read from its first bytes, like {head!r}, is held to DEFAULT_MAX_BYTES = {bs._wire.DEFAULT_MAX_BYTES})")


_BIG_PREP = """
import pickle, sys
sys.path.insert(0, {repo!r}); sys.path.insert(0, {tests!r})
from big_frames import big_frames, real_frames
from stages.corridors import CorridorBuilder, CorridorsConfig, SceneMaps
from stages.relations import RelationExtractor, RelationsConfig
from stages.intentions import IntentionFilter, IntentionsConfig
from stages.ar_inference import ARInference, ARInferenceConfig
source = real_frames()
sm = SceneMaps()
out = {{}}
for n in {objects!r}:
    scene, frames = big_frames(n, 3, source=source)
    cb, re_ = CorridorBuilder(CorridorsConfig(), scene_maps=sm), RelationExtractor(RelationsConfig(), scene_maps=sm)
    it, ar = IntentionFilter(IntentionsConfig(), scene_maps=sm), ARInference(ARInferenceConfig())
    chain = []
    for f in frames:
        cs, _ = cb.process(f, scene)
        rs, _ = re_.process(f, cs, scene)
        belief, _ = it.process(f, cs, rs, scene)
        profiles, _ = ar.process(cs, rs, f, scene)
        chain.append((f, cs, rs, belief, profiles))
    out[n] = (scene, chain)
pickle.dump(out, open(sys.argv[1], "wb"))
"""

_BIG_STAGE = """
import collections, pickle, resource, sys, time
sys.path.insert(0, {repo!r})
stage, n, uncapped = sys.argv[2], int(sys.argv[3]), sys.argv[4] == "1"
scene, chain = pickle.load(open(sys.argv[1], "rb"))[n]
from stages.corridors import CorridorBuilder, CorridorsConfig, SceneMaps
from stages.relations import RelationExtractor, RelationsConfig
from stages.intentions import IntentionFilter, IntentionsConfig
from stages.ar_inference import ARInference, ARInferenceConfig
from stages.markov_prediction import MarkovPredictionConfig, MarkovPredictor
from bus_schemas import Header
lift = dict(max_objects=10**6) if uncapped else {{}}
sm = SceneMaps()
if stage == "corridors":
    core = CorridorBuilder(CorridorsConfig(**lift), scene_maps=sm); run = lambda f, cs, rs, b, p: core.process(f, scene)
elif stage == "relations":
    core = RelationExtractor(RelationsConfig(**lift, **(dict(max_pairs=10**6) if uncapped else {{}})), scene_maps=sm)
    if uncapped:  # the uncapped corridor sets, so relations sees every object's corridors
        cb = CorridorBuilder(CorridorsConfig(**lift), scene_maps=sm)
        chain = [(f, cb.process(f, scene)[0], rs, b, p) for f, cs, rs, b, p in chain]
    run = lambda f, cs, rs, b, p: core.process(f, cs, scene)
elif stage == "intentions":
    core = IntentionFilter(IntentionsConfig(), scene_maps=sm); run = lambda f, cs, rs, b, p: core.process(f, cs, rs, scene)
elif stage == "ar_inference":
    core = ARInference(ARInferenceConfig()); run = lambda f, cs, rs, b, p: core.process(cs, rs, f, scene)
else:
    core = MarkovPredictor(MarkovPredictionConfig(mode="hybrid"))
    def run(f, cs, rs, b, p):
        pred, issues = core.process(cs, rs, scene, f, intention_belief=b, acceleration_profiles=p)
        header = Header(run_id="big", frame_index=f.header.frame_index, stamp_ns=f.header.stamp_ns, producer="markov_prediction")
        return pred.motion_grid(header, scene.scene_id), issues
# the real sequence's 3 frames (for the map load and caches) are not what is measured: a warm-up on the first big frame
rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
for item in chain[:-1]:
    run(*item)
t0 = time.perf_counter()
out, issues = run(*chain[-1])
ms = (time.perf_counter() - t0) * 1e3
rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
f, cs = chain[-1][0], chain[-1][1]
if stage == "corridors":
    kept = f"{{sum(bool(v.corridors) for v in out.vehicles)}} vehicles with corridors, {{sum(len(v.corridors) for v in out.vehicles)}} pairs"
elif stage == "relations":
    kept = f"{{len(out.relations)}} pairs related"
elif stage == "intentions":
    kept = f"{{len(out.vehicles)}} vehicles"
elif stage == "ar_inference":
    kept = f"{{len(out.profiles)}} pairs"
else:
    kept = f"{{out.n_rows}} x {{out.n_cols}} grid, {{sum(len(step.values) for step in out.steps)}} cells listed over {{len(out.steps)}} steps"
size = len(out.encode())
kinds = collections.Counter(i.kind for i in issues)
print(f"{{rss:.0f}}\t{{ms:.0f}}\t{{kept}}\t{{size}}\t{{type(out).MAX_BYTES}}\t" + ", ".join(f"{{k}} {{v}}" for k, v in sorted(kinds.items())))
"""

BIG_STAGES = ("corridors", "relations", "intentions", "ar_inference", "markov_prediction")
BIG_BUDGET_MB = 1024.0  # peak RSS per stage on a 1,000-object frame with the default caps


def section_big_frame(args: argparse.Namespace) -> None:
    import tempfile

    objects = tuple(args.objects or (1000, 500))
    print(f"## big-frame: TrackFrames of {', '.join(map(str, objects))} objects (real K729 013 cars overlaid), each core in a child process")
    with tempfile.TemporaryDirectory() as tmp:
        data = str(Path(tmp) / "chain.pkl")
        t0 = time.perf_counter()
        prep = subprocess.run(
            [sys.executable, "-c", _BIG_PREP.format(repo=str(REPO), tests=str(REPO / "tests"), objects=objects), data],
            capture_output=True, text=True, timeout=3600,
        )
        if prep.returncode != 0:
            print(f"preparing the upstream outputs failed: {prep.stderr.strip().splitlines()[-1:]}")
            return
        print(f"(upstream outputs prepared in {time.perf_counter() - t0:.0f} s)")
        print(f"{'objects':>7s} {'stage':18s} {'caps':8s} {'peak RSS MB':>11s} {'ms':>7s} {'bytes':>9s} {'MAX_BYTES':>9s}  kept; issues by kind")
        verdict = []
        runs = [(n, stage, False) for n in objects for stage in BIG_STAGES]
        if args.uncapped:
            runs += [(n, stage, True) for n in objects for stage in ("corridors", "relations")]
        for n, stage, uncapped in runs:
            code = _BIG_STAGE.format(repo=str(REPO))
            out = subprocess.run([sys.executable, "-c", code, data, stage, str(n), "1" if uncapped else "0"], capture_output=True, text=True, timeout=3600)
            caps = "lifted" if uncapped else "default"
            if out.returncode != 0:
                print(f"{n:>7d} {stage:18s} {caps:8s} child failed: {out.stderr.strip().splitlines()[-1:]}")
                verdict.append(f"{stage} {n} {caps}: FAILED")
                continue
            rss, ms, kept, size, limit, kinds = out.stdout.rstrip("\n").split("\n")[-1].split("\t")
            print(f"{n:>7d} {stage:18s} {caps:8s} {rss:>11s} {ms:>7s} {size:>9s} {limit:>9s}  {kept}; {kinds or 'none'}")
            if not uncapped:
                ok = float(rss) <= BIG_BUDGET_MB and int(size) <= int(limit)
                verdict.append(f"{stage} {n}: {'holds' if ok else 'EXCEEDED'}")
    print(f"budget <= {BIG_BUDGET_MB:.0f} MB peak RSS per stage and output <= MAX_BYTES, default caps: " + "; ".join(verdict))


SECTIONS: dict[str, Callable[[argparse.Namespace], None]] = {
    "fuzz": section_fuzz,
    "limits": section_limits,
    "big-frame": section_big_frame,
}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--section", action="append", choices=sorted(SECTIONS), help="section to run (repeatable; default all)")
    p.add_argument("--n", type=int, default=100_000, help="fuzz: number of mutated payloads (default 100000)")
    p.add_argument("--seed", type=int, default=13, help="fuzz: seed (default 13)")
    p.add_argument("--objects", type=int, action="append", help="big-frame: objects per frame (repeatable; default 1000 and 500)")
    p.add_argument("--uncapped", action="store_true", help="big-frame: also run corridors and relations with the caps lifted")
    args = p.parse_args(argv)
    for name in args.section or list(SECTIONS):
        SECTIONS[name](args)
        print()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
