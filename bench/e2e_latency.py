"""End-to-end latency of the streaming pipeline at real time: source publish -> recorder, per output, and frames lost.

For each entry of ``--vehicles`` (default ``0,18``): 0 plays the launcher's
embedded default scenario as it is (K733's sequence, ``python launch.py``
with no ``--data``); N > 0 first builds a dense recording of about N
vehicles per frame with ``iamp data superimpose`` (from ``$IAMP_TAF_BW``,
k733_2018-05-02 shifted by multiples of its signal cycle; without the full
data, from the embedded scenario, said so), then runs

    python launch.py [PIPELINE] --data DIR --recording NAME --speed 1 --no-viewer --record FILE.mcap

to its end (or ``--duration-s``), and reads the recording. Every payload
carries ``Header.source_wall_ns``, the wall clock at which the source
published its frame; the recorder writes each payload with ``log_time`` =
its wall clock when the payload arrived (``RecordingWriter``: the runtime's
receive time, ``time.time_ns()`` in the Zenoh callback). End to end at the
recorder = log_time - source_wall_ns, per output key: p50 / p95 / max ms
over the whole run. Frames lost per output: the source's TrackFrames (by
``frame_index``) with no message of that frame on that output (a
MotionGrid not published: dropped from a queue, a join timeout, a core
error). The last ``NodeStats`` of each node (``e2e_ms_p50/p95``: source
publish to the node's own publish) are printed too, and the load average
of the machine before and after: the figures include every other process's
load; nothing is asserted.

    python bench/e2e_latency.py [--vehicles 0,18] [--pipeline hybrid] [--duration-s S] [--speed 1]
                                [--source k733|k729] [--expect markov_prediction/motion_grid] [--keep DIR] [--json FILE]

``--json FILE`` writes ``runs.<label>.outputs.<node/output>.{n, e2e_ms_p50,
e2e_ms_p95, e2e_ms_max, frames_lost}``, ``runs.<label>.source_frames``,
``runs.<label>.vehicles_mean`` and ``runs.<label>.node_stats.<node>``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from bus_schemas import NodeStats, keys
from bus_schemas._wire import unpack_envelope
from stages.lib.datasets import DEFAULT_DATA_DIR, FULL_DATA_ENV, full_data_dir
from stages.recorder.inspect import read_messages

REPO = Path(__file__).resolve().parents[1]

SOURCES = {"k733": "k733_2018-05-02", "k729": "k729_2022-03-16"}


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(REPO) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    return env


def build(n: int, source: str, work: Path, duration_s: float | None) -> tuple[Path, str, str]:
    """A dense recording of about ``n`` vehicles (``iamp data superimpose``): (data dir, recording name, what it was built from)."""
    full = full_data_dir()
    data, origin = (full, f"${FULL_DATA_ENV}") if full is not None else (DEFAULT_DATA_DIR, "the embedded scenario (no full data)")
    recording = SOURCES[source]
    out = work / f"dense{n}"
    cmd = [sys.executable, "-m", "stages.cli", "data", "superimpose", "--data", str(data), "--recording", recording,
           "--vehicles", str(n), "--out", str(out), "--json"]
    if duration_s is not None:
        cmd += ["--duration-s", str(duration_s)]
    r = subprocess.run(cmd, cwd=REPO, env=_env(), capture_output=True, text=True)
    if r.returncode != 0:
        sys.exit(f"iamp data superimpose failed:\n{r.stderr[-3000:]}")
    info = json.loads(r.stdout)
    what = (f"{origin}, {recording} superimposed: {info['layers']} layers, {info['duration_s']:.0f} s, {info['tracks']} tracks, "
            f"vehicles per frame mean {info['vehicles_mean']:.1f} / max {info['vehicles_max']}")
    return out, str(info["recording"]), what


def run_pipeline(pipeline: str, data: Path | None, recording: str | None, rec: Path, speed: str, duration_s: float | None, run_id: str) -> float:
    cmd = [sys.executable, str(REPO / "launch.py"), pipeline, "--speed", speed, "--no-viewer", "--record", str(rec), "--run-id", run_id]
    if data is not None:
        cmd += ["--data", str(data), "--recording", recording]
    if duration_s is not None:
        cmd += ["--stop-after", str(duration_s)]
    t0 = time.monotonic()
    r = subprocess.run(cmd, cwd=rec.parent, env=_env(), capture_output=True, text=True)
    if r.returncode != 0:
        sys.exit(f"launch.py exited {r.returncode}:\n{(r.stdout + r.stderr)[-4000:]}")
    return time.monotonic() - t0


def analyse(rec: Path, expect: tuple[str, ...] = ()) -> dict:
    """e2e at the recorder per output, frames lost per output, the source's vehicles, the last NodeStats per node."""
    e2e: dict[str, list[float]] = {}
    frames: dict[str, set[int]] = {}
    source_frames: set[int] = set()
    unknown: dict[str, int] = {}
    stats: dict[str, NodeStats] = {}
    vehicles: list[int] = []
    for m in read_messages(str(rec)):
        parts = keys.parse_key(m.topic)
        if parts.output == keys.STATS:
            stats[parts.node_id] = NodeStats.decode(m.data)
            continue
        if parts.is_infrastructure:
            continue
        schema, _v, body = unpack_envelope(m.data)
        header = body.get("header") if isinstance(body, dict) else None
        if not isinstance(header, dict) or schema == "iamp.SceneInfo":
            continue
        name = f"{parts.node_id}/{parts.output}"
        frames.setdefault(name, set()).add(int(header["frame_index"]))
        if schema == "iamp.TrackFrame":
            source_frames.add(int(header["frame_index"]))
            types = body.get("agent_types")
            if isinstance(types, list) and len(types) == 3:
                vehicles.append(int(np.isin(np.frombuffer(types[2], np.uint8), [1, 2, 3, 4]).sum()))
        wall = header.get("source_wall_ns", 0)
        if wall:
            e2e.setdefault(name, []).append((m.log_time_ns - wall) / 1e6)
        else:
            unknown[name] = unknown.get(name, 0) + 1
    for name in expect:  # an expected output that never came: every frame lost
        frames.setdefault(name, set())
    outputs = {}
    for name in sorted(frames):
        a = np.asarray(e2e.get(name, []), dtype=np.float64)
        outputs[name] = {
            "n": len(frames[name]),
            "e2e_ms_p50": float(np.median(a)) if a.size else float("nan"),
            "e2e_ms_p95": float(np.percentile(a, 95)) if a.size else float("nan"),
            "e2e_ms_max": float(a.max()) if a.size else float("nan"),
            "unknown_wall": unknown.get(name, 0),
            "frames_lost": len(source_frames - frames[name]),
        }
    node_stats = {
        node: {"e2e_ms_p50": s.e2e_ms_p50, "e2e_ms_p95": s.e2e_ms_p95, "proc_ms_p50": s.proc_ms_p50, "proc_ms_p95": s.proc_ms_p95,
               "queue_drops": s.counters.get("queue_drops", 0), "join_drops": s.counters.get("join_drops", 0)}
        for node, s in sorted(stats.items())
    }
    return {"source_frames": len(source_frames), "vehicles_mean": float(np.mean(vehicles)) if vehicles else 0.0,
            "vehicles_max": int(max(vehicles)) if vehicles else 0, "outputs": outputs, "node_stats": node_stats}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--vehicles", default="0,18", help="comma-separated; 0 = the embedded default scenario as it is")
    ap.add_argument("--pipeline", default="hybrid")
    ap.add_argument("--speed", default="1")
    ap.add_argument("--duration-s", type=float, default=None, help="play at most this long (default: the whole recording)")
    ap.add_argument("--source", choices=sorted(SOURCES), default="k733")
    ap.add_argument("--keep", default=None, help="keep the dense data and recordings in this folder")
    ap.add_argument("--expect", default="markov_prediction/motion_grid", help="outputs listed even when none came (comma-separated)")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    work = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="iamp-e2e-"))
    work.mkdir(parents=True, exist_ok=True)
    result: dict = {"cpu_count": os.cpu_count(), "pipeline": args.pipeline, "speed": args.speed, "runs": {}}
    print(f"e2e latency: pipeline {args.pipeline}, speed {args.speed}, {os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.2f} at start")
    for n in [int(v) for v in args.vehicles.split(",") if v.strip()]:
        if n == 0:
            label, data, recording, origin = "embedded", None, None, "the launcher's embedded default scenario"
        else:
            data, recording, origin = build(n, args.source, work, args.duration_s)
            label = f"dense{n}"
        rec = work / f"{label}.mcap"
        load0 = os.getloadavg()[0]
        wall_s = run_pipeline(args.pipeline, data, recording, rec, args.speed, args.duration_s if n == 0 else None, f"e2e{label}")
        load1 = os.getloadavg()[0]
        res = analyse(rec, tuple(e for e in args.expect.split(",") if e))
        res.update({"wall_s": wall_s, "load_before": load0, "load_after": load1, "origin": origin})
        result["runs"][label] = res
        print(f"\n== {label}: {origin}")
        print(f"   {res['source_frames']} source frames, vehicles per frame mean {res['vehicles_mean']:.1f} / max {res['vehicles_max']}, "
              f"run {wall_s:.0f} s, load average {load0:.2f} -> {load1:.2f}")
        print(f"   {'output (at the recorder)':<40} {'n':>6} {'p50 ms':>8} {'p95 ms':>8} {'max ms':>8} {'lost':>6} {'no wall':>8}")
        for name, o in res["outputs"].items():
            print(f"   {name:<40} {o['n']:>6} {o['e2e_ms_p50']:>8.1f} {o['e2e_ms_p95']:>8.1f} {o['e2e_ms_max']:>8.1f} {o['frames_lost']:>6} {o['unknown_wall']:>8}")
        print(f"   {'NodeStats (last)':<40} {'e2e p50':>8} {'e2e p95':>8} {'proc p50':>8} {'proc p95':>8} {'q drop':>6} {'j drop':>6}")
        for node, s in res["node_stats"].items():
            print(f"   {node:<40} {s['e2e_ms_p50']:>8.1f} {s['e2e_ms_p95']:>8.1f} {s['proc_ms_p50']:>8.1f} {s['proc_ms_p95']:>8.1f} "
                  f"{s['queue_drops']:>6} {s['join_drops']:>6}")
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=2, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
