#!/usr/bin/env python3
"""Hostile inputs, by section; prints figures, asserts nothing (issues 12 and 13).

    python bench/hostile.py [--section NAME ...] [--n 100000] [--seed 13] [--objects 1000 ...] [--uncapped]
                            [--frames 300] [--speed 1] [--burst 2000] [--burst-at 100] [--burst-rate R]

Sections (``--section`` repeatable; default: all):

- ``fuzz``: ``--n`` seeded mutations of the golden payloads
  (``testkit/mutations.py``: byte, structure and empty-object
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
  1,000 and 500; ``testkit/big_frames.py``: real K729 sequence 013 cars, the
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

- ``burst``: what a burst of malformed payloads on one bus key does to a
  running pipeline. ``launch.py`` (``stages/pipelines/hybrid.toml``, no viewer,
  recorder to a temporary file, ``--speed``) plays the first ``--frames``
  frames (default 300) of the embedded scenario (K729 sequence 013, sliced
  into a temporary data folder). A second Zenoh session of this process,
  joined to the launcher's hub, publishes ``--burst`` payloads (default
  2,000; 0: a baseline run) on ``iamp/<run>/source/track_frame`` once the
  source is at frame ``--burst-at`` (default 100): as fast as it can, or
  ``--burst-rate`` per second. Each payload fails ``bus_schemas.decode``
  (checked before the run): random bytes, a TrackFrame cut short, a
  TrackFrame envelope with a broken body. A third session, listening on
  its own port (``launch.py --connect`` makes every node join it, so it is
  up before the first frame), subscribes to the source's TrackFrames,
  every data output of the run and ``_stats/*``. Prints: sent and the
  burst's duration; the launcher's exit code and its died/restarting lines;
  per node the last NodeStats counters (``received``, ``decode_errors``,
  ``queue_drops``, ``errors_by_kind``, any ``decode_errors.*`` /
  ``queue_drops.*`` per-port counters); "attack counted as decode_errors: X
  of N" summed over the nodes subscribed to the key (the inputs bound to it,
  and the recorder, which takes the whole run); per output key the source
  frames (``header.frame_index``, as seen on the bus) that never appeared on
  it (good frames lost); the log lines and bytes the run printed.
- ``origin``: the viewer core (``stages.viewer.scene.ViewerApp``, on a free
  port, started in this process as ``tests/integration/test_viewer_access.py``
  does) and websocket handshakes (viser's subprotocol) with ``Origin:
  http://evil.example``, with none, and with the viewer's own
  ``http://127.0.0.1:<port>``: per handshake the HTTP status, accepted or
  refused, and the bytes of scene data received in 3 s.
"""

from __future__ import annotations

import argparse
import collections
import math
import os
import re
import resource
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Callable

REPO = Path(__file__).resolve().parents[1]

import msgpack

import bus_schemas as bs


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
    from testkit.mutations import mutated_payloads, targeted_payloads

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
from testkit.big_frames import big_frames, real_frames
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


# --------------------------------------------------------------------------- burst

BURST_RECORDING = "k729_2022-03-16"
BURST_SEQUENCE = "013"
_NODE_LINE = re.compile(r"^\[(?P<tag>[a-z_]+)\] ")


def _slice_scenario(dst: Path, frames: int) -> int:
    """The embedded scenario with sequence 013 cut to its first ``frames`` frames (timestamps); returns the frames kept."""
    from stages.lib.datasets import DEFAULT_DATA_DIR

    shutil.copytree(DEFAULT_DATA_DIR / "maps", dst / "maps")
    src = DEFAULT_DATA_DIR / "recorded_trackfiles" / BURST_RECORDING
    out = dst / "recorded_trackfiles" / BURST_RECORDING
    out.mkdir(parents=True)
    shutil.copy(src / "meta_data.csv", out / "meta_data.csv")
    lines = (src / f"vehicle_tracks_{BURST_SEQUENCE}.csv").read_text().splitlines(keepends=True)
    col = lines[0].rstrip("\n").split(",").index("timestamp_ms")
    stamps = sorted({int(float(line.split(",")[col])) for line in lines[1:] if line.strip()})[:frames]
    keep = set(stamps)
    (out / f"vehicle_tracks_{BURST_SEQUENCE}.csv").write_text(
        lines[0] + "".join(line for line in lines[1:] if line.strip() and int(float(line.split(",")[col])) in keep)
    )
    return len(stamps)


def _malformed_payloads(n: int, seed: int) -> list[tuple[str, bytes]]:
    """``n`` payloads that ``bus_schemas.decode`` (and ``TrackFrame.decode``) must refuse, three kinds in turn."""
    import random

    from testkit.samples import track_frame

    rng = random.Random(seed)
    good = [track_frame(k).encode() for k in (4, 8, 16)]

    def random_bytes() -> bytes:
        return rng.randbytes(rng.randint(1, 512))

    def cut_short() -> bytes:
        data = rng.choice(good)
        return data[: rng.randint(1, len(data) - 1)]

    def broken_body() -> bytes:
        env = msgpack.unpackb(rng.choice(good), raw=False)
        body = env["body"]
        how = rng.randrange(5)
        if how == 0:
            body["header"] = "not a header"
        elif how == 1:
            body["x_m"] = ["float64", body["x_m"][1], b"\0" * 3]  # a byte length that does not match the shape
        elif how == 2:
            del body["track_ids"]
        elif how == 3:
            body["agent_types"] = ["complex128", body["agent_types"][1], body["agent_types"][2]]
        else:
            body["y_m"] = ["float64", [2**62], b""]
        return msgpack.packb(env, use_bin_type=True)

    makers = (("random bytes", random_bytes), ("TrackFrame cut short", cut_short), ("TrackFrame, broken body", broken_body))
    out = []
    for i in range(n):
        what, make = makers[i % len(makers)]
        for _ in range(100):
            data = make()
            try:
                bs.decode(data)
            except Exception:  # noqa: BLE001 - what we want
                try:
                    bs.TrackFrame.decode(data)
                except Exception:  # noqa: BLE001
                    break
        else:
            raise RuntimeError(f"could not make a {what} payload that fails to decode")
        out.append((what, data))
    return out


def _ranges(values: list[int]) -> str:
    if not values:
        return "-"
    parts, start, prev = [], values[0], values[0]
    for v in values[1:] + [None]:
        if v is not None and v == prev + 1:
            prev = v
            continue
        parts.append(f"{start}" if start == prev else f"{start}-{prev}")
        if v is not None:
            start = prev = v
    return ", ".join(parts)


class _LaunchOutput:
    """launch.py as a child; its output (every stage's lines, prefixed ``[node]``) kept as it comes."""

    def __init__(self, cmd: list[str], cwd: Path) -> None:
        self.lines: list[str] = []
        self.bytes = 0
        self._lock = threading.Lock()
        env = {**os.environ, "PYTHONUNBUFFERED": "1"}
        self.proc = subprocess.Popen(cmd, cwd=cwd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, start_new_session=True)
        self._pump_thread = threading.Thread(target=self._pump, daemon=True)
        self._pump_thread.start()

    def _pump(self) -> None:
        assert self.proc.stdout is not None
        for raw in self.proc.stdout:
            with self._lock:
                self.bytes += len(raw)
                self.lines.append(raw.decode(errors="replace").rstrip("\n"))

    def snapshot(self) -> list[str]:
        with self._lock:
            return list(self.lines)

    def wait_line(self, pattern: str, timeout_s: float) -> str:
        rx = re.compile(pattern)
        deadline = time.monotonic() + timeout_s
        seen = 0
        while time.monotonic() < deadline:
            lines = self.snapshot()
            for line in lines[seen:]:
                if rx.search(line):
                    return line
            seen = len(lines)
            if self.proc.poll() is not None:
                break
            time.sleep(0.05)
        raise RuntimeError(f"no launcher line matching {pattern!r}; last lines:\n" + "\n".join(self.snapshot()[-30:]))

    def finish(self, timeout_s: float) -> int:
        try:
            self.proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            os.killpg(self.proc.pid, signal.SIGINT)  # the launcher stops its nodes in order
            try:
                self.proc.wait(timeout=60)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait()
        self._pump_thread.join(timeout=10)
        return self.proc.returncode


def section_burst(args: argparse.Namespace) -> None:
    import tempfile

    from stages.runtime import launcher as launch
    from stages.runtime.pipeline import load_pipeline
    from stages.runtime import BusClient

    n_bad = args.burst
    pace = f"{args.burst_rate:g}/s" if args.burst_rate else "as fast as possible"
    run_id = f"hostile-burst-{os.getpid()}"
    hub = f"tcp/127.0.0.1:{_free_port()}"
    watch = f"tcp/127.0.0.1:{_free_port()}"  # the observer listens here and every node of the run connects to it: it is up before the first frame
    with tempfile.TemporaryDirectory(prefix="hostile-burst-") as tmp:
        work = Path(tmp)
        data = work / "data"
        frames = _slice_scenario(data, args.frames)
        launch_args = ["--no-viewer", "--run-id", run_id, "--listen", hub, "--connect", watch, "--data", str(data), "--recording", BURST_RECORDING,
                       "--speed", str(args.speed), "--record", str(work / "run.mcap")]
        pipeline = load_pipeline(launch.DEFAULT_PIPELINE, edit=launch.make_editor(launch.build_parser().parse_args(launch_args)))
        source = next(n for n in pipeline.nodes if n.kind == "source")
        target = "track_frame"
        target_ref = f"{source.id}/{target}"
        target_key = pipeline.output_key(source.id, target)
        subscribers = [n.id for n in pipeline.nodes if target_ref in n.inputs.values()] + [n.id for n in pipeline.nodes if n.kind == "raw_sink"]
        out_keys = [pipeline.output_key(n.id, o) for n in pipeline.topo_order() for o in n.spec.outputs if n.kind != "source"]
        print(f"## burst: {n_bad} malformed payloads ({pace}) on {target_key} at source frame {args.burst_at}; "
              f"{pipeline.name} pipeline without the viewer, {frames} frames of K729 {BURST_SEQUENCE}, speed {args.speed}")
        bad = _malformed_payloads(n_bad, args.seed)
        if bad:
            print("payloads: " + ", ".join(f"{v} x {k}" for k, v in collections.Counter(k for k, _ in bad).items())
                  + f" ({sum(len(d) for _, d in bad)} bytes); each fails bus_schemas.decode and TrackFrame.decode")

        lock = threading.Lock()
        got: dict[str, list[bytes]] = collections.defaultdict(list)
        source_frames: dict[int, float] = {}  # frame_index -> monotonic arrival at the observer
        bad_seen = [0]
        stats: dict[str, bs.NodeStats] = {}
        at_frame = threading.Event()

        def on_data(key: str, payload: bytes) -> None:
            if key == target_key:
                try:
                    fi = bs.TrackFrame.decode(payload).header.frame_index
                except Exception:  # noqa: BLE001 - one of ours
                    with lock:
                        bad_seen[0] += 1
                    return
                with lock:
                    source_frames[fi] = time.monotonic()
                if fi >= args.burst_at:
                    at_frame.set()
            else:
                with lock:
                    got[key].append(payload)

        def on_stats(key: str, payload: bytes) -> None:
            try:
                s = bs.NodeStats.decode(payload)
            except Exception:  # noqa: BLE001
                return
            with lock:
                stats[s.node_id] = s

        observer = BusClient(listen=[watch])
        for key in [target_key, *out_keys]:
            observer.subscribe(key, on_data)
        observer.subscribe(bs.keys.stats_pattern(run_id), on_stats)
        run = _LaunchOutput([sys.executable, str(REPO / "launch.py"), *launch_args], cwd=work)
        attacker = None
        sent, burst_s, burst_frames, before = 0, 0.0, (None, None), {}
        code = None
        try:
            run.wait_line(r"^\[launch\] all \d+ nodes alive", 240)
            attacker = BusClient(connect=[hub])  # its own session, joined to the launcher's hub
            put, matching = attacker.publisher_with_matching(target_key)
            if n_bad:
                if not at_frame.wait(timeout=args.frames / 10.0 / args.speed + 120):
                    raise RuntimeError(f"the source did not reach frame {args.burst_at}; last lines:\n" + "\n".join(run.snapshot()[-20:]))
                deadline = time.monotonic() + 10
                while not matching() and time.monotonic() < deadline:
                    time.sleep(0.01)
                with lock:
                    before = {k: dict(v.counters) for k, v in stats.items()}
                    first = max(source_frames)
                t0 = time.perf_counter()
                for i, (_, payload) in enumerate(bad):
                    if args.burst_rate:
                        due = t0 + i / args.burst_rate
                        while (left := due - time.perf_counter()) > 0:
                            time.sleep(left)
                    put(payload)
                    sent += 1
                burst_s = time.perf_counter() - t0
                with lock:
                    burst_frames = (first, max(source_frames))
            code = run.finish(args.frames / 10.0 / args.speed + 240)
            time.sleep(1.0)  # the last NodeStats on their way
        finally:
            for bus in (attacker, observer):
                if bus is not None:
                    bus.close()
            if code is None:
                run.finish(0.1)

    lines = run.snapshot()
    if n_bad:
        print(f"sent {sent} in {burst_s:.3f} s ({sent / burst_s if burst_s else 0:.0f}/s), source at frame {burst_frames[0]} when it began, "
              f"{burst_frames[1]} when it ended; the observer's session got {bad_seen[0]} of them")
    else:
        print("no burst: a baseline run")
    troubles = [line for line in lines if line.startswith("[launch]") and re.search(r"died|restarting|failed|not alive|escalating", line)]
    print(f"launcher exit code {code}; died/restart lines: {len(troubles)}" + "".join(f"\n  {t}" for t in troubles))

    print(f"{'node':18s} {'received':>9s} {'processed':>9s} {'decode_err':>10s} {'queue_drops':>11s} {'join_drops':>10s}  errors_by_kind; per-port counters")
    for node in [n.id for n in pipeline.topo_order()]:
        s = stats.get(node)
        if s is None:
            print(f"{node:18s} no NodeStats received")
            continue
        c = s.counters
        ports = {k: v for k, v in sorted(c.items()) if k.startswith(("decode_errors.", "queue_drops."))}
        print(f"{node:18s} {c.get('received', 0):>9d} {c.get('processed', 0):>9d} {c.get('decode_errors', 0):>10d} {c.get('queue_drops', 0):>11d} "
              f"{c.get('join_drops', 0):>10d}  {dict(sorted(s.errors_by_kind.items())) or '{}'}; {ports or 'none'}")
    counted = sum(stats[n].counters.get("decode_errors", 0) - before.get(n, {}).get("decode_errors", 0) for n in subscribers if n in stats)
    expected = sent * len(subscribers)
    pct = 100.0 * counted / expected if expected else 0.0
    if sent:
        print(f"attack counted as decode_errors: {counted} of {expected} ({pct:.1f} %), summed over the {len(subscribers)} nodes subscribed to "
              f"{target_key} ({', '.join(subscribers)}; {sent} each)")
    stage_subs = [n for n in subscribers if pipeline.node(n).kind != "raw_sink"]
    counted_stages = sum(stats[n].counters.get("decode_errors", 0) - before.get(n, {}).get("decode_errors", 0) for n in stage_subs if n in stats)
    if stage_subs and sent:
        print(f"  of which the {len(stage_subs)} stage inputs bound to it: {counted_stages} of {sent * len(stage_subs)} "
              f"({100.0 * counted_stages / (sent * len(stage_subs)):.1f} %); the recorder takes every payload as it comes (its issues below)")
    for n in subscribers:
        if n in stats and sent:
            d = stats[n].counters.get("decode_errors", 0) - before.get(n, {}).get("decode_errors", 0)
            q = stats[n].counters.get("queue_drops", 0) - before.get(n, {}).get("queue_drops", 0)
            i = stats[n].counters.get("issues", 0) - before.get(n, {}).get("issues", 0)
            kinds = ", ".join(f"{k} {v}" for k, v in sorted(stats[n].issues_by_kind.items())) if i else ""
            print(f"  {n:18s} decode_errors +{d} ({100.0 * d / sent:.1f} % of {sent}), queue_drops +{q}, issues +{i} during and after the burst"
                  + (f" (issues by kind, whole run: {kinds})" if kinds else ""))

    published = stats[source.id].counters.get("published", 0) if source.id in stats else None
    src = sorted(source_frames)
    print(f"good frames lost (source frames seen on {target_key}: {len(src)}"
          + (f" {src[0]}..{src[-1]}" if src else "") + f"; the source counts {published} published, its scene included):")
    for key in out_keys:
        seen = set()
        undecodable = 0
        for payload in got.get(key, []):
            try:
                seen.add(bs.decode(payload).header.frame_index)
            except Exception:  # noqa: BLE001
                undecodable += 1
        lost = [fi for fi in src if fi not in seen]
        print(f"  {key:64s} {len(lost):4d} lost: {_ranges(lost)}" + (f" ({undecodable} undecodable)" if undecodable else ""))

    tags = collections.Counter(m.group("tag") if (m := _NODE_LINE.match(line)) else "(untagged)" for line in lines)
    dropped = sum("dropped message" in line for line in lines)
    print(f"log lines of the run: {len(lines)} ({run.bytes} bytes); {dropped} 'dropped message' lines; by node: "
          + ", ".join(f"{k} {v}" for k, v in tags.most_common()))
    shapes = collections.Counter(re.sub(r"\d+", "N", line)[:140] for line in lines)
    for shape, count in shapes.most_common(3):
        print(f"  {count:5d} x {shape}")


# --------------------------------------------------------------------------- origin


def section_origin(args: argparse.Namespace) -> None:
    import logging

    import viser
    from websockets.exceptions import InvalidStatus
    from websockets.sync.client import connect

    from stages.viewer.config import TOKEN_ENV, ViewerConfig
    from stages.viewer.scene import ViewerApp

    os.environ.pop(TOKEN_ENV, None)  # no token: the Origin check alone
    app = ViewerApp(ViewerConfig(port=0, stats=False), run_id="hostile-origin", log=logging.getLogger("iamp.viewer"))
    app.start()
    try:
        port = app.server.get_port()
        print(f"## origin: websocket handshakes (subprotocol viser-v{viser.__version__}) with the viewer core on {app.url}, no token, "
              "no run on the bus (the scene data is viser's initial scene and GUI state)")
        print(f"{'Origin':34s} {'result':>24s} {'scene bytes in 3 s':>19s} {'messages':>9s}")
        for origin in ("http://evil.example", None, f"http://127.0.0.1:{port}"):
            headers = {} if origin is None else {"Origin": origin}
            n_bytes = n_msgs = 0
            try:
                with connect(f"ws://127.0.0.1:{port}/", additional_headers=headers, subprotocols=[f"viser-v{viser.__version__}"], open_timeout=20) as ws:
                    result = f"accepted (HTTP {ws.response.status_code})"
                    deadline = time.monotonic() + 3.0
                    while (left := deadline - time.monotonic()) > 0:
                        try:
                            msg = ws.recv(timeout=left)
                        except TimeoutError:
                            break
                        n_bytes += len(msg)
                        n_msgs += 1
            except InvalidStatus as exc:
                result = f"refused (HTTP {exc.response.status_code})"
            except Exception as exc:  # noqa: BLE001 - printed, not judged
                result = f"failed: {type(exc).__name__}"
            print(f"{origin or '(none)':34s} {result:>24s} {n_bytes:>19d} {n_msgs:>9d}")
        print(f"refused by the guard: {app.guard.refused}")
    finally:
        app.close()


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


SECTIONS: dict[str, Callable[[argparse.Namespace], None]] = {
    "fuzz": section_fuzz,
    "limits": section_limits,
    "big-frame": section_big_frame,
    "burst": section_burst,
    "origin": section_origin,
}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--section", action="append", choices=sorted(SECTIONS), help="section to run (repeatable; default all)")
    p.add_argument("--n", type=int, default=100_000, help="fuzz: number of mutated payloads (default 100000)")
    p.add_argument("--seed", type=int, default=13, help="fuzz: seed (default 13)")
    p.add_argument("--objects", type=int, action="append", help="big-frame: objects per frame (repeatable; default 1000 and 500)")
    p.add_argument("--uncapped", action="store_true", help="big-frame: also run corridors and relations with the caps lifted")
    p.add_argument("--frames", type=int, default=300, help="burst: frames of K729 013 the run plays (default 300)")
    p.add_argument("--speed", type=float, default=1.0, help="burst: playback speed of the source (default 1: 10 frames/s)")
    p.add_argument("--burst", type=int, default=2000, help="burst: malformed payloads to publish (default 2000; 0: a baseline run)")
    p.add_argument("--burst-at", type=int, default=100, help="burst: source frame index at which the burst starts (default 100)")
    p.add_argument("--burst-rate", type=float, default=0.0, help="burst: payloads per second (default 0: as fast as possible)")
    args = p.parse_args(argv)
    for flag, value, least in (("--n", args.n, 1), ("--frames", args.frames, 1), ("--burst", args.burst, 0), ("--burst-at", args.burst_at, 0),
                               *(("--objects", n, 1) for n in args.objects or ())):
        if value < least:
            p.error(f"{flag} {value}: must be >= {least}")
    if not (args.speed > 0 and math.isfinite(args.speed)):
        p.error(f"--speed {args.speed}: must be a number > 0")
    if not (args.burst_rate >= 0 and math.isfinite(args.burst_rate)):
        p.error(f"--burst-rate {args.burst_rate}: must be a number >= 0 (0: as fast as possible)")
    for name in args.section or list(SECTIONS):
        SECTIONS[name](args)
        print()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
