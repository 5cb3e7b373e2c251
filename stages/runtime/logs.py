"""What a node counts and logs: ``NodeStats`` counters (``_Stats``), core issues as episodes (``IssueLog``), rate-limited problems (``ProblemLog``).

Every drop is counted in ``NodeStats`` (``received``, ``processed``,
``published``, ``decode_errors``, ``join_drops``, ``queue_drops``,
``stale_drops``, ``duplicate_inputs`` (a frame received twice: not a loss),
``rejected_stamps``, ``rejected_keys``, ``issues``, ``core_errors``, most
also per port as ``<counter>.<port>``; ``issues_by_kind``,
``errors_by_kind``) and logged so that a person can read the log: issues
once per episode, other problems once per kind and 10 s with the count of
those not shown.
"""

from __future__ import annotations

import collections
import logging
import math
import os
import threading
import time
from dataclasses import dataclass
from typing import Any, Callable, Iterable

import numpy as np

from bus_schemas import NodeStats

from stages.lib.base import Issue


E2E_WINDOW = 1024  # NodeStats.e2e_ms_*: over a node's last this many input sets with a known wall stamp (~100 s at 10 Hz)


class _Stats:
    """The counters and timings a node reports as ``NodeStats`` (at ``_stats/<node>``) and in its stop summary."""

    def __init__(self) -> None:
        self.counters: dict[str, int] = collections.Counter()
        for k in ("received", "processed", "published", "decode_errors", "join_drops", "queue_drops", "stale_drops", "duplicate_inputs",
                  "issues", "core_errors"):
            self.counters[k] = 0
        self.issues_by_kind: dict[str, int] = collections.Counter()
        self.errors_by_kind: dict[str, int] = collections.Counter()
        self.proc_ms: collections.deque[float] = collections.deque(maxlen=4096)
        self.latency_ms: collections.deque[float] = collections.deque(maxlen=4096)
        # source publish -> this node's publish (a sink: its receipt), ms, per input set with a known wall stamp
        self.e2e_ms: collections.deque[float] = collections.deque(maxlen=E2E_WINDOW)
        self.proc_ms_max = 0.0
        # a core's ``prepare`` on a set still missing inputs (node._maybe_prepare), ms, per call that ran
        self.prep_ms: collections.deque[float] = collections.deque(maxlen=4096)
        self.last_stamp_ns = 0

    @staticmethod
    def _pct(values: Iterable[float], q: float, empty: float = 0.0) -> float:
        arr = np.fromiter(values, dtype=float)
        return float(np.percentile(arr, q)) if arr.size else empty

    def message(self, run_id: str, node_id: str, stage: str, started: float, depth: int) -> NodeStats:
        return NodeStats(
            run_id=run_id,
            node_id=node_id,
            stage=stage,
            pid=os.getpid(),
            uptime_s=time.monotonic() - started,
            counters=dict(self.counters),
            issues_by_kind=dict(self.issues_by_kind),
            errors_by_kind=dict(self.errors_by_kind),
            proc_ms_p50=self._pct(self.proc_ms, 50),
            proc_ms_p95=self._pct(self.proc_ms, 95),
            proc_ms_max=self.proc_ms_max,
            latency_ms_p50=self._pct(self.latency_ms, 50),
            latency_ms_p95=self._pct(self.latency_ms, 95),
            e2e_ms_p50=self._pct(self.e2e_ms, 50, empty=math.nan),
            e2e_ms_p95=self._pct(self.e2e_ms, 95, empty=math.nan),
            queue_depth=depth,
            last_stamp_ns=self.last_stamp_ns,
        )

    def summary(self) -> str:
        parts = [f"{k}={v}" for k, v in sorted(self.counters.items()) if v or "." not in k]  # per-port counters when not 0
        if self.issues_by_kind:
            parts.append("issues_by_kind=" + ",".join(f"{k}:{v}" for k, v in sorted(self.issues_by_kind.items())))
        if self.errors_by_kind:
            parts.append("errors_by_kind=" + ",".join(f"{k}:{v}" for k, v in sorted(self.errors_by_kind.items())))
        parts.append(f"proc_ms_p50={self._pct(self.proc_ms, 50):.2f} proc_ms_p95={self._pct(self.proc_ms, 95):.2f}")
        if self.prep_ms:
            parts.append(f"prep_ms_p50={self._pct(self.prep_ms, 50):.2f} prep_ms_p95={self._pct(self.prep_ms, 95):.2f}")
        if self.e2e_ms:
            parts.append(f"e2e_ms_p50={self._pct(self.e2e_ms, 50):.2f} e2e_ms_p95={self._pct(self.e2e_ms, 95):.2f}")
        return " ".join(parts)


class StatsReporter:
    """``NodeStats`` for a node that runs its own loop instead of ``run_stage`` (replay), as every node publishes them.

    ``count``/``set``/``processed`` update the counters (the caller's thread); a thread of this reporter puts the
    message through ``put`` (a publisher on ``_stats/<node>``) every ``period_s``, also while the caller's loop
    waits (pacing, a recording's gap), and ``close`` puts the last one. The counters are the runtime's (``_Stats``):
    the same names, the same message.
    """

    def __init__(self, put: Callable[[bytes], None], run_id: str, node_id: str, stage: str, period_s: float = 1.0, counters: Iterable[str] = (),
                 refresh: Callable[[], None] | None = None) -> None:
        self._put = put
        self._refresh = refresh  # called before each message: counters kept elsewhere copied in then, not per item
        self._ids = (run_id, node_id, stage)
        self._period_s = period_s
        self._started = time.monotonic()
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self.stats = _Stats()
        for key in counters:  # present, at 0, from the first message on
            self.stats.counters[key] = 0
        self._thread: threading.Thread | None = None

    def start(self) -> "StatsReporter":
        self._thread = threading.Thread(target=self._run, name="node-stats", daemon=True)
        self._thread.start()
        return self

    def count(self, key: str, n: int = 1) -> None:
        with self._lock:
            self.stats.counters[key] += n

    def set(self, key: str, value: int) -> None:
        with self._lock:
            self.stats.counters[key] = int(value)

    def processed(self, proc_ms: float, stamp_ns: int | None = None) -> None:
        """One message (or input set) handled and published, in ``proc_ms``; its header stamp, if any."""
        with self._lock:
            self.stats.counters["processed"] += 1
            self.stats.counters["published"] += 1
            self.stats.proc_ms.append(proc_ms)
            self.stats.proc_ms_max = max(self.stats.proc_ms_max, proc_ms)
            if stamp_ns is not None:
                self.stats.last_stamp_ns = max(self.stats.last_stamp_ns, stamp_ns)

    def summary(self) -> str:
        with self._lock:
            return self.stats.summary()

    def publish(self) -> None:
        if self._refresh is not None:
            self._refresh()
        with self._lock:
            msg = self.stats.message(*self._ids, self._started, 0)
        try:
            self._put(msg.encode())
        except Exception:  # noqa: BLE001 - the session closing: stats are never worth a crash
            pass

    def _run(self) -> None:
        while not self._stop.wait(self._period_s):
            self.publish()

    def close(self) -> None:
        """Stop the thread and put the final counters."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        self.publish()


# --------------------------------------------------------------------------- logs a person can read


@dataclass(slots=True)
class _Episode:
    detail: str
    first_ns: int
    last_ns: int
    frames: int = 1
    occurrences: int = 1
    shown: bool = True  # its start was logged (else its end is not either)


class IssueLog:
    """Issues of a core logged as episodes, not once per frame.

    An episode is one issue kind for one agent (``agent_id``; -1 for issues
    about no single agent) on consecutive frames of one scope: the node's
    handled frames for an operator or a source, the messages of one key for a
    raw sink (``scope=key``). It is logged when it starts, with its detail::

        issue: kind=off_map_heading agent=2578 stamp_ns=26800000000 near car lanelets but heading ...

    and once when a frame of its scope comes without it, with the number of
    frames it lasted and its first and last stamps::

        issue ended: kind=off_map_heading agent=2578 frames=37 first_stamp_ns=26800000000 last_stamp_ns=30400000000 duration_s=3.6

An episode of one frame ends at DEBUG only: its start line says all there
is to say, and at a busy junction a tracker's one-frame quirks (a
velocity rejected, a state pending) made half of a stage's log lines
"ended" lines with ``frames=1``.

    ``close()`` (node shutdown) logs the episodes still open, once each
    (``issue open at stop: ...``, same fields). A raw sink's lines name the
    key (``key=...``) instead of the agent, and its agent too when not -1.
    Several occurrences in one frame count once in ``frames``; when that
    happens the lines add ``occurrences=``. This class only logs: the node
    counts every occurrence in NodeStats itself.

    Episodes that start and end on every message (a burst of bad payloads
    interleaved with good ones, 100 vehicles each with its own episode) are
    bounded too: at most ``max_starts`` episode starts of one kind are
    logged per ``period_s``; the others are counted, their end is not
    logged, and the next shown start of the kind (or ``close``) says how
    many were not shown. The defaults (5 per minute) keep a kind that a
    recording's tracker raises for every car (K733's reported velocities
    point backwards: ``velocity_rejected`` for each new track) to a few lines a
    minute, with the count of the others, while an occasional kind is
    shown every time; NodeStats counts every occurrence either way.
    """

    MAX_STOP_LINES = 20

    def __init__(self, log: logging.Logger, max_starts: int = 5, period_s: float = 60.0, clock: Callable[[], float] = time.monotonic) -> None:
        self.log = log
        self._open: dict[str | None, dict[tuple[str, int], _Episode]] = {}
        self.max_starts = max_starts
        self.period_s = period_s
        self._clock = clock
        self._starts: dict[str, collections.deque] = {}
        self._hidden: collections.Counter[str] = collections.Counter()

    def _may_show(self, kind: str) -> bool:
        now = self._clock()
        recent = self._starts.setdefault(kind, collections.deque())
        while recent and now - recent[0] >= self.period_s:
            recent.popleft()
        if len(recent) >= self.max_starts:
            self._hidden[kind] += 1
            return False
        recent.append(now)
        return True

    def frame(self, stamp_ns: int, issues: Iterable[Issue], scope: str | None = None, *, closes: bool = True) -> None:
        """The issues of one handled frame (or, for a raw sink, one message on key ``scope``). ``closes`` false: a call
        of the core that handled no frame (grid_fusion run by a clock tick or by one shard's part of a frame, which
        publishes nothing): its issues start or go on with their episodes, and the episodes it lacks are not ended
        (each such call ended a shard outage's episode: one outage logged as many, until the rate limit hid the next)."""
        episodes = self._open.get(scope)
        if episodes is None:
            if not issues:
                return
            episodes = self._open[scope] = {}
        seen: set[tuple[str, int]] = set()
        for issue in issues:
            k = (issue.kind, issue.agent_id)
            ep = episodes.get(k)
            if ep is None:
                shown = self._may_show(issue.kind)
                episodes[k] = _Episode(issue.detail, stamp_ns, stamp_ns, shown=shown)
                if shown:
                    hidden = self._hidden.pop(issue.kind, 0)
                    more = f" [{hidden} more episodes of this kind not shown in the last {self.period_s:.0f} s]" if hidden else ""
                    self.log.warning("issue: kind=%s %s stamp_ns=%d %s%s", issue.kind, self._who(scope, issue.agent_id), stamp_ns, issue.detail, more)
            elif k in seen:
                ep.occurrences += 1
            else:
                ep.frames += 1
                ep.occurrences += 1
                ep.last_ns = stamp_ns
            seen.add(k)
        for k in [k for k in episodes if k not in seen] if closes else ():
            ep = episodes.pop(k)
            if ep.shown:  # (an episode of one frame: its start line said all; its end at DEBUG)
                self._line(logging.INFO if ep.frames > 1 else logging.DEBUG, "issue ended", scope, k, ep)
        if not episodes:
            del self._open[scope]

    def open_count(self) -> int:
        return sum(len(e) for e in self._open.values())

    def close(self) -> None:
        """Log every episode still open, once, and forget them."""
        items = [(scope, k, ep) for scope, eps in self._open.items() for k, ep in eps.items() if ep.shown]
        self._open.clear()
        for kind, n in sorted(self._hidden.items()):
            self.log.info("issue episodes not shown: kind=%s %d (more than %d starts in %.0f s)", kind, n, self.max_starts, self.period_s)
        self._hidden.clear()
        for scope, k, ep in items[: self.MAX_STOP_LINES]:
            self._line(logging.INFO, "issue open at stop", scope, k, ep)
        if len(items) > self.MAX_STOP_LINES:
            self.log.info("issues open at stop: %d more not listed", len(items) - self.MAX_STOP_LINES)

    @staticmethod
    def _who(scope: str | None, agent_id: int) -> str:
        if scope is None:
            return f"agent={agent_id}"
        return f"key={scope}" if agent_id == -1 else f"key={scope} agent={agent_id}"

    def _line(self, level: int, what: str, scope: str | None, k: tuple[str, int], ep: _Episode) -> None:
        extra = f" occurrences={ep.occurrences}" if ep.occurrences != ep.frames else ""
        self.log.log(
            level,
            "%s: kind=%s %s frames=%d first_stamp_ns=%d last_stamp_ns=%d duration_s=%.1f%s",
            what,
            k[0],
            self._who(scope, k[1]),
            ep.frames,
            ep.first_ns,
            ep.last_ns,
            (ep.last_ns - ep.first_ns) / 1e9,
            extra,
        )


class ProblemLog:
    """One log line per kind of problem, then at most one per ``period_s``.

    ``report(kind, level, fmt, *args)``: the first problem of a kind is
    logged at once (with ``first_extra``, e.g. a traceback, appended only
    then); later ones within ``period_s`` of that kind's last line are only
    counted, and the next line of the kind says how many were not shown::

        dropped message: reason=MalformedPayload key=... detail=... [41 more of this kind in the last 10 s]

    ``close()`` logs, once, the kinds with problems not shown yet. Counting
    for NodeStats is the caller's.
    """

    def __init__(self, log: logging.Logger, period_s: float = 10.0, clock: Callable[[], float] = time.monotonic) -> None:
        self.log = log
        self.period_s = period_s
        self._clock = clock
        self._last: dict[str, float] = {}
        self._hidden: collections.Counter[str] = collections.Counter()
        self._lock = threading.Lock()  # subscriber callbacks report too

    def report(self, kind: str, level: int, fmt: str, *args: Any, first_extra: str | Callable[[], str] = "") -> None:
        with self._lock:
            now = self._clock()
            last = self._last.get(kind)
            if last is not None and now - last < self.period_s:
                self._hidden[kind] += 1
                return
            hidden = self._hidden.pop(kind, 0)
            self._last[kind] = now
        if last is None and first_extra:
            fmt, args = fmt + "\n%s", (*args, first_extra() if callable(first_extra) else first_extra)
        elif hidden:
            fmt, args = fmt + " [%d more of this kind in the last %.0f s]", (*args, hidden, now - last)
        self.log.log(level, fmt, *args)

    def close(self) -> None:
        for kind, n in sorted(self._hidden.items()):
            self.log.warning("not shown at stop: %d more of kind %s", n, kind)
        self._hidden.clear()
