#!/usr/bin/env python3
"""Bus latency and throughput between two processes over Zenoh on loopback.

    python bench/bus_latency.py [--count 2000] [--rate 200]

Two payload sizes: a TrackFrame of 40 objects (a busy K729 frame), and a
200 x 200 float32 grid (a motion-grid step) carried in the same msgpack
envelope. Latency is publish -> receive-and-decode, one way, measured with the
host's realtime clock (both processes on one machine), at a paced rate so that
queueing does not pollute it. Throughput is messages per second received when
the publisher sends as fast as congestion control lets it. Prints figures;
asserts nothing.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

import bus_schemas as bs
from bus_schemas._wire import Array, Message
from stages.lib.base import check_output_arg
from stages.runtime import BusClient

from typing import Annotated, ClassVar


@dataclasses.dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class _BenchGrid(Message):
    """A 200x200 float32 payload in the standard envelope (benchmark only, not registered)."""

    SCHEMA: ClassVar[str] = "bench.Grid"
    VERSION: ClassVar[int] = 1
    header: bs.Header
    values: Annotated[np.ndarray, Array("float32", (None, None))]


def make_track_frame(n: int, stamp_ns: int, i: int) -> bs.TrackFrame:
    rng = np.random.default_rng(i)
    return bs.TrackFrame(
        header=bs.Header(run_id="bench", frame_index=i, stamp_ns=stamp_ns, producer="bench"),
        scene_id="bench",
        track_ids=np.arange(n, dtype=np.int64),
        agent_types=np.ones(n, np.uint8),
        x_m=rng.normal(size=n),
        y_m=rng.normal(size=n),
        vx_mps=rng.normal(size=n),
        vy_mps=rng.normal(size=n),
        yaw_rad=rng.normal(size=n),
        length_m=np.full(n, 4.5),
        width_m=np.full(n, 1.9),
    )


GRID = np.random.default_rng(0).random((200, 200), dtype=np.float32)


def make_grid(stamp_ns: int, i: int) -> _BenchGrid:
    return _BenchGrid(header=bs.Header(run_id="bench", frame_index=i, stamp_ns=stamp_ns, producer="bench"), values=GRID)


KINDS = {"track_frame": (bs.TrackFrame, lambda s, i: make_track_frame(40, s, i)), "grid_200x200_f32": (_BenchGrid, make_grid)}


def sink(hub: str, kind: str, count: int) -> None:
    cls = KINDS[kind][0]
    lat: list[float] = []
    first = last = None
    with BusClient(connect=[hub]) as bus:

        def cb(_key: str, data: bytes) -> None:
            nonlocal first, last
            now = time.time_ns()
            msg = cls.decode(data)
            lat.append((now - msg.header.stamp_ns) / 1e6)
            first = first or now
            last = now

        bus.subscribe(f"iamp/bench/src/{kind}", cb)
        bus.declare_token(f"iamp/bench/_alive/sink_{kind}")
        deadline = time.monotonic() + 120
        while len(lat) < count and time.monotonic() < deadline:
            time.sleep(0.01)
    print(json.dumps({"received": len(lat), "lat_ms": lat, "span_s": ((last or 0) - (first or 0)) / 1e9}))


def run_case(kind: str, count: int, rate_hz: float | None) -> dict:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    hub = f"tcp/127.0.0.1:{port}"
    with BusClient(listen=[hub]) as bus:
        proc = subprocess.Popen([sys.executable, __file__, "--role", "sink", "--hub", hub, "--kind", kind, "--count", str(count)], stdout=subprocess.PIPE, text=True)
        put, matching = bus.publisher_with_matching(f"iamp/bench/src/{kind}")
        deadline = time.monotonic() + 30
        while not matching() and time.monotonic() < deadline:
            time.sleep(0.01)
        make = KINDS[kind][1]
        size = len(make(0, 0).encode())
        t0 = time.perf_counter()
        for i in range(count):
            if rate_hz:
                due = t0 + i / rate_hz
                while time.perf_counter() < due:
                    time.sleep(max(0.0, min(0.001, due - time.perf_counter())))
            put(make(time.time_ns(), i).encode())
        send_s = time.perf_counter() - t0
        out, _ = proc.communicate(timeout=180)
    res = json.loads(out)
    lat = np.array(res["lat_ms"])
    return {
        "kind": kind,
        "bytes": size,
        "sent": count,
        "received": res["received"],
        "p50_ms": float(np.percentile(lat, 50)) if lat.size else float("nan"),
        "p95_ms": float(np.percentile(lat, 95)) if lat.size else float("nan"),
        "msgs_per_s": res["received"] / max(res["span_s"], send_s, 1e-9),
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--role", choices=["main", "sink"], default="main")
    ap.add_argument("--hub")
    ap.add_argument("--kind", default="track_frame")
    ap.add_argument("--count", type=int, default=2000)
    ap.add_argument("--rate", type=float, default=200.0, help="paced rate for the latency runs (Hz)")
    ap.add_argument("--json", metavar="FILE")
    args = ap.parse_args()
    if args.count < 1:
        ap.error(f"--count {args.count}: must be >= 1")
    if not (args.rate > 0 and math.isfinite(args.rate)):
        ap.error(f"--rate {args.rate:g}: must be a number of Hz > 0")
    check_output_arg(ap, args.json, "--json")  # before the work: a bad path must not cost the run
    if args.role == "sink":
        sink(args.hub, args.kind, args.count)
        return 0
    rows = []
    for kind in KINDS:
        lat = run_case(kind, args.count, args.rate)
        thr = run_case(kind, args.count, None)
        rows.append({**lat, "throughput_msgs_per_s": thr["msgs_per_s"], "throughput_MB_per_s": thr["msgs_per_s"] * thr["bytes"] / 1e6, "throughput_received": thr["received"]})
    print(f"bus latency and throughput, 2 processes on loopback ({os.cpu_count()} cores); latency paced at {args.rate:g} Hz")
    print(f"{'payload':<18} {'bytes':>8} {'p50 ms':>8} {'p95 ms':>8} {'lost':>6} {'msg/s':>9} {'MB/s':>8} {'lost':>6}")
    for r in rows:
        print(
            f"{r['kind']:<18} {r['bytes']:>8} {r['p50_ms']:>8.3f} {r['p95_ms']:>8.3f} {r['sent'] - r['received']:>6} "
            f"{r['throughput_msgs_per_s']:>9.0f} {r['throughput_MB_per_s']:>8.1f} {r['sent'] - r['throughput_received']:>6}"
        )
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
