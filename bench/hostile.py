#!/usr/bin/env python3
"""Hostile inputs, by section; prints figures, asserts nothing (issues 12 and 13).

    python bench/hostile.py [--section NAME ...] [--n 100000] [--seed 13]

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

Other sections (bus burst, a 1,000-object frame, the viewer) are meant to be
added as functions in ``SECTIONS``.
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


SECTIONS: dict[str, Callable[[argparse.Namespace], None]] = {
    "fuzz": section_fuzz,
    "limits": section_limits,
}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--section", action="append", choices=sorted(SECTIONS), help="section to run (repeatable; default all)")
    p.add_argument("--n", type=int, default=100_000, help="fuzz: number of mutated payloads (default 100000)")
    p.add_argument("--seed", type=int, default=13, help="fuzz: seed (default 13)")
    args = p.parse_args(argv)
    for name in args.section or list(SECTIONS):
        SECTIONS[name](args)
        print()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
