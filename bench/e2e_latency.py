"""End-to-end latency of the streaming pipeline at real time: source publish -> recorder, per output, and frames lost.

For each entry of ``--vehicles`` (default ``0,18``): 0 plays the launcher's
embedded default scenario as it is (K733's sequence, ``python launch.py``
with no ``--data``); N > 0 first builds a dense recording of N
vehicles per frame on average with ``iamp data superimpose`` (from ``$IAMP_TAF_BW``,
k733_2018-05-02 shifted by multiples of its signal cycle; without the full
data, from the embedded scenario, said so), then runs

    python launch.py [PIPELINE] --data DIR --recording NAME --speed 1 --no-viewer --record FILE.mcap

to its end (or ``--duration-s``), and reads the recording. ``--viewer`` runs
the viewer too (on a free port, no page opened), as ``launch.py`` does by
default: what the viewer costs the stages beside it. Every payload
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
                                [--source k733|k729] [--expect markov_prediction/motion_grid] [--keep DIR] [--json FILE] [--no-trace] [--viewer]
                                [--set NODE.KEY=VALUE ...]

Unless ``--no-trace``, the run goes with ``IAMP_HOP_TRACE`` set
(``stages/runtime/trace.py``: each node writes one JSON line per handled
input set) and two more tables split the time: per stage, p50/p95 ms of
each component over all its input sets (transport: the upstream's put call
-> this node's subscriber callback for the last joined input to arrive;
queue: callback -> the loop took it; decode; join; process: the core;
encode: core end -> the put call of its last output; put: time in the put
calls; e2e: source wall -> its last put; cpu: the core's thread CPU time,
next to process for contention; gc: the collector's pauses while handling
it; skew: last minus first joined input's receipt); and the critical path
of every MotionGrid at the recorder, walked back from the recorder through
each node's last-arriving input to the source, whose parts add up exactly
to the recorder's log_time - source wall (checked, printed), with each
part's mean over the tail (frames at or above the p95) next to its mean over
the frames at or below the median; then each node's GC pauses per
generation. All of one machine's wall clock.

``--json FILE`` (strict JSON: a figure without a sample is ``null``) writes
``runs.<label>.outputs.<node/output>.{n, e2e_ms_p50, e2e_ms_p95, e2e_ms_max,
frames_lost, unknown_wall}`` (``unknown_wall``, the ``no wall`` column: its
messages whose header carries no source wall time, not in the figures), ``runs.<label>.source_frames``,
``runs.<label>.vehicles_mean``, ``runs.<label>.by_vehicles.<lo-hi>.{frames, e2e_ms_p50, e2e_ms_p95}`` (the
MotionGrid's e2e over the frames holding lo-hi vehicles: a dense recording's load varies along it, and its
p95 is mostly the busiest frames), ``runs.<label>.at_n.{frames, e2e_ms_p50, e2e_ms_p95}`` (the same over the
frames within N ± 2 vehicles, for N > 0), ``runs.<label>.node_stats.<node>`` (its last NodeStats: among them
``e2e_ms_p50``, ``e2e_ms_p95``, ``processing_ms_p50``/``_p95`` and the counters ``queue_drops``, ``join_drops`` and
``stale_drops``, the table's ``q drop``, ``j drop`` and ``stale`` columns) and
(traced) ``runs.<label>.hops.{stages.<node>.<part>, path.{total, parts.<node>.<part>, tail, via}, gc.<node>}``
(``hop_table``), and ``host_reference`` / ``host_reference_end`` (``testkit.host_speed.reference()`` before
and after the runs, printed too: this host's speed at fixed work, to read figures of other days against).
"""

from __future__ import annotations

import argparse
import atexit
import json
import math
import os
import shutil
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
from stages.runtime.trace import TRACE_ENV
from stages.lib.base import check_output_arg

REPO = Path(__file__).resolve().parents[1]

SOURCES = {"k733": "k733_2018-05-02", "k729": "k729_2022-03-16"}


def _env(trace: Path | None = None) -> dict[str, str]:
    env = dict(os.environ)
    env.pop(TRACE_ENV, None)
    if trace is not None:
        env[TRACE_ENV] = str(trace)
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


def run_pipeline(pipeline: str, data: Path | None, recording: str | None, rec: Path, speed: str, duration_s: float | None, run_id: str,
                 trace: Path | None = None, sets: tuple[str, ...] = (), viewer: bool = False) -> float:
    cmd = [sys.executable, str(REPO / "launch.py"), pipeline, "--speed", speed, "--record", str(rec), "--overwrite", "--run-id", run_id]
    # the viewer on a free port, no page opened (what a user's default run costs the stages beside it)
    cmd += ["--set", "viewer.port=0"] if viewer else ["--no-viewer"]
    for item in sets:
        cmd += ["--set", item]
    if data is not None:
        cmd += ["--data", str(data), "--recording", recording]
    if duration_s is not None:
        cmd += ["--stop-after", str(duration_s)]
    t0 = time.monotonic()
    r = subprocess.run(cmd, cwd=rec.parent, env=_env(trace), capture_output=True, text=True)
    if r.returncode != 0:
        sys.exit(f"launch.py exited {r.returncode}:\n{(r.stdout + r.stderr)[-4000:]}")
    return time.monotonic() - t0


def analyse(rec: Path, expect: tuple[str, ...] = (), target: float | None = None) -> dict:
    """e2e at the recorder per output, frames lost per output, the source's vehicles, the last NodeStats per node;
    the MotionGrid's e2e by vehicles in its frame (``by_vehicles``) and, with ``target`` N, over the frames within
    N ± ``AT_N_WITHIN`` vehicles (``at_n``)."""
    e2e: dict[str, list[float]] = {}
    frame_e2e: dict[str, dict[int, float]] = {}
    vehicles_of: dict[int, int] = {}
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
                vehicles_of[int(header["frame_index"])] = vehicles[-1]
        wall = header.get("source_wall_ns", 0)
        if wall:
            e2e.setdefault(name, []).append((m.log_time_ns - wall) / 1e6)
            frame_e2e.setdefault(name, {})[int(header["frame_index"])] = (m.log_time_ns - wall) / 1e6
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
               "queue_drops": s.counters.get("queue_drops", 0), "join_drops": s.counters.get("join_drops", 0),
               "stale_drops": s.counters.get("stale_drops", 0)}
        for node, s in sorted(stats.items())
    }
    return {"source_frames": len(source_frames), "vehicles_mean": float(np.mean(vehicles)) if vehicles else 0.0,
            "vehicles_max": int(max(vehicles)) if vehicles else 0, "outputs": outputs, "node_stats": node_stats,
            "by_vehicles": by_vehicles(frame_e2e.get("/".join(GRID), {}), vehicles_of),
            **({"at_n": at_n(frame_e2e.get("/".join(GRID), {}), vehicles_of, target)} if target is not None else {})}


#: Frames whose vehicles lie within this many of N make ``at_n`` (as ``bench/dense.py``'s).
AT_N_WITHIN = 2


def at_n(e2e_of_frame: dict[int, float], vehicles_of: dict[int, int], target: float) -> dict[str, float]:
    """The MotionGrid's e2e over the frames holding ``target`` ± ``AT_N_WITHIN`` vehicles: {frames, e2e_ms_p50, e2e_ms_p95}."""
    v = [ms for f, ms in e2e_of_frame.items() if f in vehicles_of and abs(vehicles_of[f] - target) <= AT_N_WITHIN]
    return {"frames": len(v), "vehicles_within": AT_N_WITHIN, "e2e_ms_p50": float(np.median(v)) if v else float("nan"),
            "e2e_ms_p95": float(np.percentile(v, 95)) if v else float("nan")}


#: Width of the vehicles-per-frame bins of ``by_vehicles`` (bins 0-3, 4-7, ..., 16-19, ...).
VEHICLE_BIN = 4


def by_vehicles(e2e_of_frame: dict[int, float], vehicles_of: dict[int, int]) -> dict[str, dict[str, float]]:
    """The MotionGrid's e2e split by the vehicles in its frame: ``"16-19": {frames, e2e_ms_p50, e2e_ms_p95}``.

    A dense recording's load varies along it (N is its mean: K733's dense18 holds 9-33 vehicles a frame), so a
    run's p95 is mostly its busiest frames; these rows say what a frame of a given load waits.
    """
    bins: dict[int, list[float]] = {}
    for f, ms in e2e_of_frame.items():
        if f in vehicles_of:
            bins.setdefault(vehicles_of[f] // VEHICLE_BIN, []).append(ms)
    return {f"{b * VEHICLE_BIN}-{b * VEHICLE_BIN + VEHICLE_BIN - 1}": {
                "frames": len(v), "e2e_ms_p50": float(np.median(v)), "e2e_ms_p95": float(np.percentile(v, 95))}
            for b, v in sorted(bins.items())}


# ---------------------------------------------------------------- the per-hop trace (IAMP_HOP_TRACE, stages/runtime/trace.py)

#: The components of one hop, in the order they follow each other: their sum is the hop (see ``hop_components``).
HOP_PARTS = ("transport", "queue", "decode", "join", "process", "encode")
GRID = ("markov_prediction", "motion_grid")


def read_traces(folder: Path) -> dict[str, dict]:
    """``{node: {"inputs": {port: "node/output"}, "records": [...], "gc": {...}, "gc_long": [...]}}`` from ``folder/*.jsonl``."""
    out: dict[str, dict] = {}
    for f in sorted(Path(folder).glob("*.jsonl")):
        node: dict = {"inputs": {}, "records": [], "gc": {}, "gc_long": []}
        for line in f.read_text().splitlines():
            try:
                r = json.loads(line)
            except json.JSONDecodeError:  # a line cut by a kill: the rest is still read
                continue
            if "node" in r:
                node["inputs"] = r.get("inputs", {})
                node["stage"] = r.get("stage", "")
            elif "gc" in r:
                node["gc"], node["gc_long"] = r["gc"], r.get("gc_pauses_ms_over_1", [])
            else:
                node["records"].append(r)
        out[f.stem] = node
    return out


def _put_index(traces: dict[str, dict]) -> dict[tuple[str, str, int], int]:
    """``(node, output, stamp) -> when the put of that output was called`` over every operator and source record."""
    idx = {}
    for node, t in traces.items():
        for r in t["records"]:
            for port, (_enc0, enc1, _put1) in (r.get("out") or {}).items():
                idx[(node, port, r["stamp"])] = enc1
    return idx


def hop_components(traces: dict[str, dict], node: str, r: dict, puts: dict, output: str | None = None) -> tuple[dict[str, float], tuple[str, str] | None]:
    """One operator record split into ``HOP_PARTS`` (ms) and the upstream output its last-arriving joined input came from.

    From the upstream's put call for that input to this node's put call
    for ``output`` (the last output when None): ``transport`` (upstream put
    called -> this node's subscriber callback: the put itself, Zenoh, the
    callback thread getting the GIL), ``queue`` (callback -> the loop took
    it: behind earlier messages, or the wake-up), ``decode``, ``join``
    (decoded -> core start: bookkeeping), ``process`` (the core),
    ``encode`` (core end -> the put call of ``output``: encoding it, and
    encoding and putting the outputs before it). Their sum is the hop; a
    component is NaN when its upstream record is missing (a frame dropped
    there, a trace cut).
    """
    ins = r.get("in") or {}
    outs = r.get("out") or {}
    out_put = outs[output][1] if output in outs else max((v[1] for v in outs.values()), default=r["end"])
    parts = {k: math.nan for k in HOP_PARTS}
    parts["process"] = (r["end"] - r["start"]) / 1e6
    parts["encode"] = (out_put - r["end"]) / 1e6
    if not ins:
        return parts, None
    port = max(ins, key=lambda p: ins[p][0])
    recv, deq, dec = ins[port]
    ref = traces[node]["inputs"].get(port, "")
    up = tuple(ref.split("/", 1)) if "/" in ref else None
    parts["queue"] = (deq - recv) / 1e6
    parts["decode"] = (dec - deq) / 1e6
    parts["join"] = (r["start"] - dec) / 1e6
    if up is not None and (up[0], up[1], r["stamp"]) in puts:
        parts["transport"] = (recv - puts[(up[0], up[1], r["stamp"])]) / 1e6
    return parts, up


def hop_table(traces: dict[str, dict], grid: tuple[str, str] = GRID) -> dict:
    """Per-stage components (all input sets) and the critical path of every ``grid`` output that reached the recorder.

    ``stages.<node>.<part>``: p50/p95 ms over the node's records (and
    ``e2e`` = its last put - source wall, ``cpu`` = the core's thread CPU,
    ``gc`` = GC pauses while handling, ``skew`` = last minus first joined
    input's receipt). ``path``: per MotionGrid at the recorder, walked back
    from the recorder through each node's last-arriving input to the
    source; ``path.total`` (= recorder receipt - source wall, the e2e of the
    recorder's log_time) is the sum of ``path.parts.<node>.<part>``;
    ``path.tail`` the mean of each part over the frames at or above the
    total's p95 next to its mean over the frames at or below the median.
    """
    puts = _put_index(traces)
    recs = {node: {r["stamp"]: r for r in t["records"] if "stamp" in r} for node, t in traces.items()}
    stages: dict[str, dict] = {}
    for node, t in traces.items():
        cols: dict[str, list[float]] = {}
        for r in t["records"]:
            if "key" in r or "start" not in r:
                continue
            parts, _up = hop_components(traces, node, r, puts)
            outs = (r.get("out") or {}).values()
            last_put = max((v[2] for v in outs), default=r["end"])
            parts.update({"e2e": (last_put - r["wall"]) / 1e6 if r.get("wall") else math.nan, "cpu": r.get("cpu_ms", math.nan),
                          "gc": r.get("gc_ms", math.nan), "put": sum(v[2] - v[1] for v in outs) / 1e6})
            ins = r.get("in") or {}
            parts["skew"] = (max(v[0] for v in ins.values()) - min(v[0] for v in ins.values())) / 1e6 if ins else math.nan
            prep = r.get("prep")  # the core's prepare calls on the set before its last input came (markov: pairs, chain)
            parts["prepare"] = sum(end - start for start, end in prep) / 1e6 if prep else math.nan
            for k, v in parts.items():
                cols.setdefault(k, []).append(v)
        src = [r for r in t["records"] if "out" in r and "start" not in r]
        for r in src:  # a source: encoding and putting every output is its e2e
            last_put = max(v[2] for v in r["out"].values())
            for k, v in (("encode", sum(v[1] - v[0] for v in r["out"].values()) / 1e6), ("put", sum(v[2] - v[1] for v in r["out"].values()) / 1e6),
                         ("e2e", (last_put - r["wall"]) / 1e6), ("gc", r.get("gc_ms", math.nan))):
                cols.setdefault(k, []).append(v)
        sink = [r for r in t["records"] if "key" in r]
        for r in sink:
            if not r["key"].endswith(f"/{grid[0]}/{grid[1]}"):
                continue
            p = puts.get((grid[0], grid[1], r["stamp"]))
            for k, v in (("transport", (r["recv"] - p) / 1e6 if p else math.nan), ("queue", (r["deq"] - r["recv"]) / 1e6),
                         ("process", (r["end"] - r["deq"]) / 1e6), ("e2e", (r["recv"] - r["wall"]) / 1e6)):
                cols.setdefault(k, []).append(v)
        stages[node] = {k: _p(v) for k, v in cols.items()}
    # the critical path of each MotionGrid at the recorder
    rows: list[dict[str, float]] = []
    totals: list[float] = []
    via: dict[str, int] = {}
    for node, t in traces.items():
        for r in t["records"]:
            if "key" not in r or not r["key"].endswith(f"/{grid[0]}/{grid[1]}"):
                continue
            p = puts.get((grid[0], grid[1], r["stamp"]))
            if p is None:
                continue
            row = {f"{node}.transport": (r["recv"] - p) / 1e6}
            cur, out, ok = grid[0], grid[1], True
            for _ in range(len(traces)):
                rr = recs.get(cur, {}).get(r["stamp"])
                if rr is None:
                    ok = False
                    break
                if "start" not in rr:  # the source: wall (stamped before encoding) -> its put call of this output
                    row[f"{cur}.encode"] = (rr["out"][out][1] - rr["wall"]) / 1e6
                    break
                parts, up = hop_components(traces, cur, rr, puts, out)
                for k, v in parts.items():
                    row[f"{cur}.{k}"] = v
                if up is None:
                    ok = False
                    break
                via[cur + "<-" + up[0]] = via.get(cur + "<-" + up[0], 0) + 1
                cur, out = up
            if not ok or any(math.isnan(v) for v in row.values()):
                continue
            rows.append(row)
            totals.append((r["recv"] - r["wall"]) / 1e6)
    path: dict = {"n": len(rows), "via": via}
    if rows:
        names = sorted({k for row in rows for k in row}, key=lambda k: k)
        tot = np.asarray(totals)
        hi, lo = tot >= np.percentile(tot, 95), tot <= np.median(tot)
        mat = np.asarray([[row.get(k, 0.0) for k in names] for row in rows])
        path["total"] = _p(totals) | {"max": float(tot.max())}
        path["sum_check_ms"] = float(np.abs(mat.sum(axis=1) - tot).max())  # 0 up to rounding: the parts add up to the total
        path["parts"] = {k: _p(mat[:, i]) | {"tail_mean": float(mat[hi, i].mean()), "median_mean": float(mat[lo, i].mean())} for i, k in enumerate(names)}
        path["tail"] = {"n": int(hi.sum()), "total_mean": float(tot[hi].mean()), "median_total_mean": float(tot[lo].mean())}
    gc_stats = {node: {"by_gen": t["gc"], "pauses_over_1ms": len(t["gc_long"]),
                       "max_ms": max((g[2] for g in t["gc"].values()), default=0.0)} for node, t in traces.items() if t["gc"]}
    return {"stages": stages, "path": path, "gc": gc_stats}


def _p(values) -> dict[str, float]:
    a = np.asarray([v for v in values if not math.isnan(v)], dtype=np.float64)
    return {"p50": float(np.median(a)) if a.size else math.nan, "p95": float(np.percentile(a, 95)) if a.size else math.nan, "n": int(a.size)}


STAGE_COLS = ("transport", "queue", "decode", "join", "process", "encode", "put", "e2e", "cpu", "gc", "skew", "prepare")


def print_hops(h: dict, indent: str = "   ") -> None:
    """The decomposition tables of ``hop_table``."""
    print(f"{indent}per stage, all input sets, ms p50/p95 (transport: upstream put called -> callback of the last joined input; queue: callback -> loop;"
          f" encode: core end -> last put called; put: time in the put calls; cpu: the core's thread CPU; skew: last - first joined input received;"
          f" prepare: the core's work on the set before its last input came, where it did any)")
    print(indent + f"{'node':<20}" + "".join(f"{c:>14}" for c in STAGE_COLS))
    for node, cols in h["stages"].items():
        cells = "".join(f"{_cell(cols.get(c)):>14}" for c in STAGE_COLS)
        print(f"{indent}{node:<20}{cells}")
    path = h["path"]
    if not path.get("n"):
        print(f"{indent}critical path: no MotionGrid traced end to end")
        return
    t = path["total"]
    print(f"{indent}critical path of {path['n']} MotionGrids (recorder receipt - source wall = the sum of the parts, within {path['sum_check_ms']:.3f} ms):"
          f" total p50 {t['p50']:.1f} / p95 {t['p95']:.1f} / max {t['max']:.1f} ms; via {', '.join(f'{k} {v}' for k, v in sorted(path['via'].items()))}")
    print(f"{indent}{'part':<32}{'p50':>8}{'p95':>8}{'mean in the tail':>18}{'mean <= median':>16}   (tail: {path['tail']['n']} frames >= p95, "
          f"mean total {path['tail']['total_mean']:.1f} vs {path['tail']['median_total_mean']:.1f} ms)")
    for k, v in path["parts"].items():
        if v["tail_mean"] < 0.05 and v["p95"] < 0.05:
            continue
        print(f"{indent}{k:<32}{v['p50']:>8.1f}{v['p95']:>8.1f}{v['tail_mean']:>18.1f}{v['median_mean']:>16.1f}")
    if h["gc"]:
        print(f"{indent}GC per node: collections / total ms / max ms per generation, pauses >= 1 ms")
        for node, g in h["gc"].items():
            gens = "  ".join(f"gen{k} {c[0]}/{c[1]:.0f}/{c[2]:.1f}" for k, c in g["by_gen"].items())
            print(f"{indent}  {node:<20} {gens}  >=1ms: {g['pauses_over_1ms']}")


def _cell(v: dict | None) -> str:
    if not v or math.isnan(v["p50"]):
        return "-"
    return f"{v['p50']:.1f}/{v['p95']:.1f}"


def vehicle_counts(text: str) -> list[int]:
    """``--vehicles``: bench/dense.py's, with 0 too (the embedded scenario as it is)."""
    try:  # as a script, its folder is first on the module path
        from dense import vehicle_counts as counts
    except ImportError:
        from bench.dense import vehicle_counts as counts
    return counts(text, minimum=0)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--vehicles", type=vehicle_counts, default="0,18", help="comma-separated; 0 = the embedded default scenario as it is")
    ap.add_argument("--pipeline", default="hybrid")
    ap.add_argument("--speed", default="1", help="playback speed: a number > 0 (1: real time) or 'max'")
    ap.add_argument("--duration-s", type=float, default=None, help="play at most this long (default: the whole recording)")
    ap.add_argument("--source", choices=sorted(SOURCES), default="k733")
    ap.add_argument("--keep", default=None, help="keep the dense data and recordings in this folder")
    ap.add_argument("--expect", default="markov_prediction/motion_grid", help="outputs listed even when none came (comma-separated)")
    ap.add_argument("--json", default=None)
    ap.add_argument("--no-trace", action="store_true", help=f"run without the per-hop trace ({TRACE_ENV}): no decomposition table")
    ap.add_argument("--viewer", action="store_true", help="run the viewer too (on a free port, no page opened), as launch.py does by default")
    ap.add_argument("--set", action="append", default=[], metavar="NODE.KEY=VALUE",
                    help="passed to launch.py --set (repeatable), e.g. markov_prediction.kernel_threads=1")
    args = ap.parse_args()
    check_output_arg(ap, args.json, "--json")  # before the work: a bad path must not cost the run
    check_output_arg(ap, args.keep, "--keep", folder=True)
    if args.duration_s is not None and not (math.isfinite(args.duration_s) and args.duration_s > 0):
        ap.error(f"--duration-s {args.duration_s:g}: give a time above 0 s")
    from stages.runtime.pacing import parse_speed_value

    try:  # (launch.py's own rule, before the dense data is built)
        parse_speed_value(args.speed if args.speed == "max" else float(args.speed))
    except ValueError:
        ap.error(f"--speed {args.speed}: give a number above 0 (1: real time) or 'max'")
    from stages.runtime.launcher import PIPELINES_DIR, resolve_pipeline_arg

    pipeline = Path(resolve_pipeline_arg(args.pipeline))
    if not pipeline.is_file():  # (before the dense data is built; launch.py runs in the work folder, so a path is made absolute)
        names = ", ".join(sorted(p.stem for p in PIPELINES_DIR.glob("*.toml")))
        ap.error(f"--pipeline {args.pipeline}: no such pipeline file, nor a shipped pipeline ({names})")
    args.pipeline = args.pipeline if pipeline.parent == PIPELINES_DIR and pipeline.stem == args.pipeline else str(pipeline.resolve())
    if args.keep:
        work = Path(args.keep)
    else:  # the dense data and its recording (~100 MB for the whole dense18): removed at exit, also when the run fails
        work = Path(tempfile.mkdtemp(prefix="iamp-e2e-"))
        atexit.register(shutil.rmtree, work, ignore_errors=True)
    work.mkdir(parents=True, exist_ok=True)
    result: dict = {"cpu_count": os.cpu_count(), "pipeline": args.pipeline, "speed": args.speed, "set": list(args.set),
                    "viewer": args.viewer, "runs": {}}
    sets = "".join(f", --set {item}" for item in args.set) + (", with the viewer (no page open)" if args.viewer else "")
    print(f"e2e latency: pipeline {args.pipeline}{sets}, speed {args.speed}, {os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.2f} at start")
    from testkit import host_speed

    result["host_reference"] = host_speed.reference()  # (this host's speed apart from the project's code, before the runs)
    print(host_speed.line(result["host_reference"]))
    for n in args.vehicles:
        if n == 0:
            label, data, recording, origin = "embedded", None, None, "the launcher's embedded default scenario"
        else:
            data, recording, origin = build(n, args.source, work, args.duration_s)
            label = f"dense{n}"
        rec = work / f"{label}.mcap"
        trace = None if args.no_trace else work / f"{label}-trace"
        if trace is not None:
            shutil.rmtree(trace, ignore_errors=True)
        load0 = os.getloadavg()[0]
        wall_s = run_pipeline(args.pipeline, data, recording, rec, args.speed, args.duration_s if n == 0 else None, f"e2e{label}", trace, tuple(args.set),
                              args.viewer)
        load1 = os.getloadavg()[0]
        res = analyse(rec, tuple(e for e in args.expect.split(",") if e), target=n if n > 0 else None)
        if trace is not None:
            res["hops"] = hop_table(read_traces(trace))
        res.update({"wall_s": wall_s, "load_before": load0, "load_after": load1, "origin": origin})
        result["runs"][label] = res
        print(f"\n== {label}: {origin}")
        print(f"   {res['source_frames']} source frames, vehicles per frame mean {res['vehicles_mean']:.1f} / max {res['vehicles_max']}, "
              f"run {wall_s:.0f} s, load average {load0:.2f} -> {load1:.2f}")
        print(f"   {'output (at the recorder)':<40} {'n':>6} {'p50 ms':>8} {'p95 ms':>8} {'max ms':>8} {'lost':>6} {'no wall':>8}")
        for name, o in res["outputs"].items():
            print(f"   {name:<40} {o['n']:>6} {o['e2e_ms_p50']:>8.1f} {o['e2e_ms_p95']:>8.1f} {o['e2e_ms_max']:>8.1f} {o['frames_lost']:>6} {o['unknown_wall']:>8}")
        if res["by_vehicles"]:
            print(f"   {'/'.join(GRID)} by vehicles in its frame: " + "; ".join(
                f"{k}: {v['frames']} frames, {v['e2e_ms_p50']:.1f} / {v['e2e_ms_p95']:.1f} ms" for k, v in res["by_vehicles"].items()))
        if "at_n" in res:
            a = res["at_n"]
            print(f"   {'/'.join(GRID)} at {n} ± {a['vehicles_within']} vehicles: {a['frames']} frames, p50 {a['e2e_ms_p50']:.1f} / p95 {a['e2e_ms_p95']:.1f} ms")
        print(f"   {'NodeStats (last)':<40} {'e2e p50':>8} {'e2e p95':>8} {'proc p50':>8} {'proc p95':>8} {'q drop':>6} {'j drop':>6} {'stale':>6}")
        for node, s in res["node_stats"].items():
            print(f"   {node:<40} {s['e2e_ms_p50']:>8.1f} {s['e2e_ms_p95']:>8.1f} {s['proc_ms_p50']:>8.1f} {s['proc_ms_p95']:>8.1f} "
                  f"{s['queue_drops']:>6} {s['join_drops']:>6} {s['stale_drops']:>6}")
        if "hops" in res:
            print_hops(res["hops"])
    result["host_reference_end"] = host_speed.reference()  # (and after them: the host may change under a run)
    print(f"\nafter the runs: {host_speed.line(result['host_reference_end'])}")
    if args.json:
        try:  # (strict JSON: NaN, where a figure had no sample, is null)
            from dense import write_json
        except ImportError:
            from bench.dense import write_json
        write_json(args.json, result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
