"""Per-hop trace of a node (for ``bench/e2e_latency.py``): one JSON line per handled input set, behind ``IAMP_HOP_TRACE``.

With ``IAMP_HOP_TRACE=DIR`` in its environment (the launcher passes its own
to every node), each node appends to ``DIR/<node_id>.jsonl``; without it
nothing is measured or written. Every time is the wall clock
(``time.time_ns()``), so the lines of the nodes of one machine can be put
side by side. The lines:

- ``{"node", "stage", "pid", "inputs": {port: "node/output"}}``: the first
  line (which upstream output each input port is bound to);
- an operator, per input set it ran its core on:
  ``{"stamp", "frame", "wall", "in": {port: [recv, deq, dec]}, "start",
  "end", "cpu_ms", "gc_ms", "out": {port: [enc0, enc1, put1]}}``: for each
  joined input, when the subscriber callback received it (``recv``), when
  the loop took it from the queue (``deq``) and when it was decoded
  (``dec``); the core ran from ``start`` to ``end`` using ``cpu_ms`` of this
  thread's CPU; each output was encoded from ``enc0`` to ``enc1`` and its put
  returned at ``put1``; ``wall`` is the outputs' ``Header.source_wall_ns``;
  ``gc_ms`` the garbage collector's pauses (any thread) from the dequeue of
  the last input to the last put;
- a source, per frame: the same without ``in``, ``start``/``end``;
- a raw sink (the recorder), per payload with a wall stamp:
  ``{"key", "stamp", "wall", "recv", "deq", "end"}``;
- the last line, at stop: ``{"gc": {generation: [collections,
  total_ms, max_ms]}, "gc_pauses_ms_over_1": [[at_ns, ms, gen], ...]}``.

``bench/e2e_latency.py`` reads these files (``hop_table``) and splits each
MotionGrid's end-to-end time along its critical path.
"""

from __future__ import annotations

import gc
import json
import os
import threading
import time
from pathlib import Path
from typing import Any

TRACE_ENV = "IAMP_HOP_TRACE"
#: GC pauses at least this long are listed one by one in the last line (the others only counted).
GC_LIST_MS = 1.0
_GC_LIST_MAX = 10_000


class GcClock:
    """Times every garbage collection through ``gc.callbacks``: totals per generation and a running pause counter."""

    def __init__(self) -> None:
        self.pause_ns = 0  # running total, all generations
        self.by_gen: dict[int, list[float]] = {}  # gen -> [collections, total ms, max ms]
        self.long: list[list[float]] = []  # [[wall ns at start, ms, gen]] for pauses >= GC_LIST_MS
        self._t0 = 0
        self._w0 = 0
        gc.callbacks.append(self._cb)

    def _cb(self, phase: str, info: dict[str, Any]) -> None:
        if phase == "start":
            self._t0 = time.perf_counter_ns()
            self._w0 = time.time_ns()
            return
        dt = time.perf_counter_ns() - self._t0
        self.pause_ns += dt
        gen = int(info.get("generation", -1))
        rec = self.by_gen.setdefault(gen, [0, 0.0, 0.0])
        ms = dt / 1e6
        rec[0] += 1
        rec[1] += ms
        rec[2] = max(rec[2], ms)
        if ms >= GC_LIST_MS and len(self.long) < _GC_LIST_MAX:
            self.long.append([self._w0, round(ms, 3), gen])

    def close(self) -> None:
        try:
            gc.callbacks.remove(self._cb)
        except ValueError:
            pass


class HopTrace:
    """The trace file of one node; ``from_env`` gives None (nothing traced) unless ``IAMP_HOP_TRACE`` names a folder."""

    FLUSH_S = 1.0

    def __init__(self, directory: str | os.PathLike, node_id: str, stage: str, inputs: dict[str, str]) -> None:
        path = Path(directory)
        path.mkdir(parents=True, exist_ok=True)
        self.path = path / f"{node_id}.jsonl"
        self._f = open(self.path, "a", encoding="utf-8")
        self._lock = threading.Lock()
        self._flushed = time.monotonic()
        self.gc = GcClock()
        self.write({"node": node_id, "stage": stage, "pid": os.getpid(), "inputs": inputs})

    @classmethod
    def from_env(cls, node_id: str, stage: str, inputs: dict[str, str]) -> "HopTrace | None":
        directory = os.environ.get(TRACE_ENV, "")
        return cls(directory, node_id, stage, inputs) if directory else None

    def write(self, record: dict[str, Any]) -> None:
        line = json.dumps(record, separators=(",", ":"))
        with self._lock:
            if self._f.closed:
                return
            self._f.write(line + "\n")
            now = time.monotonic()
            if now - self._flushed >= self.FLUSH_S:
                self._flushed = now
                self._f.flush()

    def close(self) -> None:
        self.gc.close()
        self.write({"gc": {str(g): [int(c), round(t, 3), round(m, 3)] for g, (c, t, m) in sorted(self.gc.by_gen.items())},
                    "gc_pauses_ms_over_1": self.gc.long})
        with self._lock:
            self._f.close()
