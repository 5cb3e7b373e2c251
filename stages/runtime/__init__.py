"""The stage runtime: the only module of hybrid-iamp that imports zenoh.

A stage is a config dataclass, a pure core and a thin binding that hands both,
with its ports, to ``run_stage``. The runtime owns everything else:

- the Zenoh session (peer mode on ``tcp/127.0.0.1``, multicast scouting off,
  explicit endpoints; ``--mode/--connect/--listen/--config`` to join a remote
  router);
- a liveliness token at ``iamp/<run>/_alive/<node>``;
- decoding in the subscriber callback, before anything is queued, through
  the port's message class: a ``SchemaError`` (or any other exception, which
  ``bus_schemas`` should never raise) becomes a counter increment
  (``decode_errors``, and ``decode_errors.<port>``), a dropped message and a
  rate-limited log line (``ProblemLog``); objects with a value outside their
  schema's range are dropped (or the value cleared) by the decoder and
  counted as issues ``out_of_range_dropped`` / ``out_of_range_cleared``; a
  message stamped more than
  ``--stamp-window-s`` ahead of the newest accepted stamp is rejected
  (``rejected_stamps``);
- one bounded queue per input port (``--queue-size`` messages and
  ``--queue-mib`` of payload each): when full, that port's oldest entry is
  dropped and counted (``queue_drops``, ``queue_drops.<port>``, one warning
  line per port and 10 s), so a burst on one key never evicts another
  input's frames; a single loop drains the queues in arrival order, so
  processing is ordered and single-threaded;
  an exception of a core on one input set is counted and dropped the same
  way: no payload can end a stage;
- a bounded, counted join on ``header.stamp_ns`` for stages with several
  inputs; latched inputs (the scene) are kept and queried at start instead;
- latched outputs: the last payload is kept and answered to queries, so a
  stage that (re)starts late still gets it;
- issues from the core: every one counted by kind; logged as episodes
  (``IssueLog``): once when an issue of one kind and agent starts, once when
  it ends, the open ones once at stop;
- encoding and publishing; ``NodeStats`` at ``_stats/<node>`` every second and
  ``Progress`` at ``_ack/<node>`` after every handled input set;
- pacing of sources (recording rate times ``speed``, or ``max``: as fast as
  every live node keeps up, by their ``Progress``);
- a clean stop on SIGINT/SIGTERM (drain the queue, wait until the inputs are
  quiet, print a summary) and exit codes 0 (clean), 1 (crash), 2 (bad
  command line or config).
"""

from __future__ import annotations

import argparse
import collections
import json
import logging
import math
import os
import signal
import sys
import threading
import time
import traceback
from dataclasses import dataclass, field
from typing import Any, Callable, Iterable, Iterator, Mapping, Protocol

import numpy as np
import zenoh

import bus_schemas
from bus_schemas import NodeStats, Progress, SchemaError, keys
from bus_schemas._wire import Message, unpack_envelope

from stages.lib.base import ConfigError, Issue, StageResult

EXIT_OK = 0
EXIT_CRASH = 1
EXIT_USAGE = 2
MiB = 1024 * 1024

DEFAULT_LISTEN = "tcp/127.0.0.1:0"


# --------------------------------------------------------------------------- ports and specs


@dataclass(frozen=True, slots=True)
class Port:
    """A named input or output carrying one message class.

    ``latched``: an output whose last value is kept and answered to queries;
    an input that takes such an output, is queried at start and is not part of
    the stamp join (the core sees its latest value with every update).
    ``optional``: an input that a pipeline may leave unbound.
    """

    schema: type[Message]
    latched: bool = False
    optional: bool = False


class OperatorCore(Protocol):
    def update(self, inputs: Mapping[str, Message]) -> StageResult: ...


class SourceCore(Protocol):
    def __iter__(self) -> Iterator[tuple[int, StageResult]]: ...


class RawSinkCore(Protocol):
    def handle(self, key: str, payload: bytes, recv_ns: int) -> list[Issue] | None: ...

    def close(self) -> None: ...


@dataclass(frozen=True)
class NodeContext:
    """What a core factory gets besides its config."""

    run_id: str
    node_id: str
    stage: str
    log: logging.Logger
    input_keys: Mapping[str, str] = field(default_factory=dict)
    output_keys: Mapping[str, str] = field(default_factory=dict)


@dataclass(frozen=True)
class StageSpec:
    """Everything the runtime needs to know about a stage.

    ``kind`` is ``"source"`` (no inputs; the core is iterable and yields
    ``(stamp_ns, StageResult)``), ``"operator"`` (the core has ``update``) or
    ``"raw_sink"`` (no typed inputs; receives every payload of the run as raw
    bytes: the recorder).
    """

    stage: str
    config_cls: type
    make_core: Callable[[Any, NodeContext], Any]
    inputs: Mapping[str, Port]
    outputs: Mapping[str, Port]
    kind: str = "operator"
    restart_default: bool = True


# --------------------------------------------------------------------------- command line


def add_network_args(parser: argparse.ArgumentParser) -> None:
    """The zenoh-python network flags, shared by stages and tools."""
    g = parser.add_argument_group("network")
    g.add_argument("--mode", choices=["peer", "client"], default="peer", help="zenoh mode (default peer)")
    g.add_argument("--connect", action="append", default=[], metavar="ENDPOINT", help="endpoint to connect to, e.g. tcp/127.0.0.1:7447")
    g.add_argument("--listen", action="append", default=[], metavar="ENDPOINT", help=f"endpoint to listen on (default {DEFAULT_LISTEN})")
    g.add_argument("--config", metavar="FILE", help="zenoh JSON5 config file; the flags above override it")


def make_zenoh_config(mode: str = "peer", connect: Iterable[str] = (), listen: Iterable[str] = (), config_file: str | None = None) -> zenoh.Config:
    conf = zenoh.Config.from_file(config_file) if config_file else zenoh.Config()
    conf.insert_json5("mode", json.dumps(mode))
    conf.insert_json5("scouting/multicast/enabled", "false")
    connect = list(connect)
    listen = list(listen) or ([DEFAULT_LISTEN] if mode == "peer" else [])
    if connect:
        conf.insert_json5("connect/endpoints", json.dumps(connect))
    if listen:
        conf.insert_json5("listen/endpoints", json.dumps(listen))
    return conf


def open_session(mode: str = "peer", connect: Iterable[str] = (), listen: Iterable[str] = (), config_file: str | None = None) -> zenoh.Session:
    """Open a zenoh session with the project's defaults (loopback, no multicast)."""
    return zenoh.open(make_zenoh_config(mode, connect, listen, config_file))


def session_from_args(args: argparse.Namespace) -> zenoh.Session:
    return open_session(args.mode, args.connect, args.listen, args.config)


def parse_set(items: list[str]) -> dict[str, Any]:
    import tomllib

    out: dict[str, Any] = {}
    for item in items:
        if "=" not in item:
            raise ConfigError(f"--set {item!r}: expected key=value")
        k, v = item.split("=", 1)
        try:
            out[k.strip()] = tomllib.loads(f"x = {v}")["x"]
        except tomllib.TOMLDecodeError:
            out[k.strip()] = v
    return out


def build_parser(spec: StageSpec) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=f"python -m {spec.stage}", description=(sys.modules[spec.stage].__doc__ or "").split("\n")[0] if spec.stage in sys.modules else None)
    default_id = spec.stage.rsplit(".", 1)[-1]
    p.add_argument("--node-id", default=default_id, help=f"node id (default {default_id})")
    p.add_argument("--run-id", default="demo", help="run id: keys live under iamp/<run>/ (default demo)")
    p.add_argument("--params-json", default="{}", help="parameters as a JSON object (the launcher passes them)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override one parameter (TOML value)")
    p.add_argument("--inputs-json", default=None, help='input bindings as JSON {"port": "node/output"}')
    p.add_argument("--input", action="append", default=[], metavar="PORT=NODE/OUTPUT", help="bind one input")
    p.add_argument("--queue-size", type=int, default=256, help="bounded queue length of each input (default 256 messages)")
    p.add_argument("--queue-mib", type=float, default=64.0, help="bounded queue size of each input in MiB of payload (default 64)")
    p.add_argument(
        "--stamp-window-s",
        type=float,
        default=60.0,
        help="reject inputs stamped more than this many seconds ahead of the newest accepted stamp (default 60)",
    )
    p.add_argument("--stats-period", type=float, default=1.0, help="seconds between NodeStats (default 1)")
    p.add_argument("--log-level", default="INFO")
    p.add_argument(
        "--await-nodes",
        default="",
        metavar="ID,ID",
        help="sources: wait until these nodes' liveliness tokens are visible before the first publish (the launcher passes them)",
    )
    add_network_args(p)
    return p


# --------------------------------------------------------------------------- statistics


class _Stats:
    def __init__(self) -> None:
        self.counters: dict[str, int] = collections.Counter()
        for k in ("received", "processed", "published", "decode_errors", "join_drops", "queue_drops", "issues", "core_errors"):
            self.counters[k] = 0
        self.issues_by_kind: dict[str, int] = collections.Counter()
        self.errors_by_kind: dict[str, int] = collections.Counter()
        self.proc_ms: collections.deque[float] = collections.deque(maxlen=4096)
        self.latency_ms: collections.deque[float] = collections.deque(maxlen=4096)
        self.proc_ms_max = 0.0
        self.last_stamp_ns = 0

    @staticmethod
    def _pct(values: Iterable[float], q: float) -> float:
        arr = np.fromiter(values, dtype=float)
        return float(np.percentile(arr, q)) if arr.size else 0.0

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
        return " ".join(parts)


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
    many were not shown.
    """

    MAX_STOP_LINES = 20

    def __init__(self, log: logging.Logger, max_starts: int = 20, period_s: float = 10.0, clock: Callable[[], float] = time.monotonic) -> None:
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

    def frame(self, stamp_ns: int, issues: Iterable[Issue], scope: str | None = None) -> None:
        """The issues of one handled frame (or, for a raw sink, one message on key ``scope``)."""
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
        for k in [k for k in episodes if k not in seen]:
            ep = episodes.pop(k)
            if ep.shown:
                self._line(logging.INFO, "issue ended", scope, k, ep)
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


# --------------------------------------------------------------------------- the bounded queue


class _InputQueue:
    """Bounded FIFOs, one per input port, drained in arrival order by one loop.

    Each port has its own bound, ``maxlen`` entries and ``max_bytes`` of
    payload: a burst on one key can only push out older entries of that same
    key, never a good frame of another input. When a port is full, an
    operator's queue drops that port's oldest entry and calls
    ``on_drop(port, nbytes)``: fresh frames matter more than old ones. A raw
    sink's queue (``block=True``, the recorder) instead makes the subscriber
    callback wait, which pushes back through Zenoh's congestion control to
    the publishers, so nothing is lost. ``get`` returns the oldest entry over
    all ports (a global arrival sequence), so processing stays in arrival
    order.
    """

    def __init__(self, maxlen: int, on_drop: Callable[[Any, int], None], block: bool = False, max_bytes: int = 0) -> None:
        self._q: dict[Any, collections.deque] = {}
        self._bytes: collections.Counter = collections.Counter()
        self._maxlen = max(1, maxlen)
        self._max_bytes = max(0, max_bytes)  # 0: no byte bound
        self._cv = threading.Condition()
        self._on_drop = on_drop
        self._block = block
        self._seq = 0
        self._len = 0
        self.closed = False

    def _full(self, port: Any, nbytes: int) -> bool:
        dq = self._q.get(port)
        if not dq:
            return False  # one entry always fits, however large (its size was bounded by its schema)
        return len(dq) >= self._maxlen or (self._max_bytes > 0 and self._bytes[port] + nbytes > self._max_bytes)

    def put(self, item: Any, port: Any = None, nbytes: int = 0) -> None:
        with self._cv:
            if self._block:
                while self._full(port, nbytes) and not self.closed:
                    self._cv.wait(0.1)
            else:
                while self._full(port, nbytes):
                    _seq, _old, old_bytes = self._q[port].popleft()
                    self._bytes[port] -= old_bytes
                    self._len -= 1
                    self._on_drop(port, old_bytes)
            self._seq += 1
            self._q.setdefault(port, collections.deque()).append((self._seq, item, nbytes))
            self._bytes[port] += nbytes
            self._len += 1
            self._cv.notify_all()

    def get(self, timeout: float) -> Any | None:
        with self._cv:
            if not self._len:
                self._cv.wait(timeout)
            if not self._len:
                return None
            port = min((p for p, dq in self._q.items() if dq), key=lambda p: self._q[p][0][0])
            _seq, item, nbytes = self._q[port].popleft()
            self._bytes[port] -= nbytes
            self._len -= 1
            if self._block:
                self._cv.notify_all()
            return item

    def depth(self, port: Any) -> int:
        dq = self._q.get(port)
        return len(dq) if dq else 0

    def __len__(self) -> int:
        return self._len


# --------------------------------------------------------------------------- the node


class StopRequested(Exception):
    pass


class Node:
    """One running stage: session, ports, loop. Built by ``run_stage``."""

    def __init__(self, spec: StageSpec, args: argparse.Namespace, config: Any, bindings: dict[str, str]) -> None:
        self.spec = spec
        self.args = args
        self.config = config
        self.run_id = args.run_id
        self.node_id = args.node_id
        self.log = logging.getLogger(f"iamp.{self.node_id}")
        self.stats = _Stats()
        self.issue_log = IssueLog(self.log)
        self.problems = ProblemLog(self.log)
        self.started = time.monotonic()
        self.stop_event = threading.Event()
        self.signals = 0
        self.queue = _InputQueue(
            args.queue_size, self._count_queue_drop, block=spec.kind == "raw_sink", max_bytes=int(getattr(args, "queue_mib", 64) * MiB)
        )
        self.bindings = bindings
        self.input_keys = {port: f"{keys.ROOT}/{self.run_id}/{ref}" for port, ref in bindings.items()}
        # callbacks (zenoh's threads) and the loop both count: one lock, and every key made here
        # so that copying the counters for NodeStats never meets a key being added
        self._count_lock = threading.Lock()
        for port in self.input_keys:
            for k in ("received", "decode_errors", "queue_drops", "rejected_stamps"):
                self.stats.counters[f"{k}.{port}"] = 0
        self.stats.counters["rejected_stamps"] = 0
        self._stamp_clock_ns: int | None = None  # newest stamp accepted on a joined input
        self.output_keys = {port: keys.data_key(self.run_id, self.node_id, port) for port in spec.outputs}
        self.session: zenoh.Session | None = None
        self._publishers: dict[str, Any] = {}
        self._latched_out: dict[str, bytes] = {}
        self._latched_in: dict[str, Message] = {}
        self._pending: "collections.OrderedDict[int, dict[str, Message]]" = collections.OrderedDict()
        self._pending_since: dict[int, float] = {}
        self._keepalive: list[Any] = []
        self._last_stats = 0.0
        self._last_input_mono = time.monotonic()
        self._progress_pub = None
        self._acks: dict[str, Progress] = {}
        self._alive: set[str] = set()
        self._ack_lock = threading.Lock()
        self._frames_published: collections.deque[int] = collections.deque(maxlen=64)

    # ---- counters used from callbacks
    def _count(self, key: str, port: str | None = None, n: int = 1) -> None:
        with self._count_lock:
            self.stats.counters[key] += n
            if port is not None:
                self.stats.counters[f"{key}.{port}"] += n

    def _count_queue_drop(self, port: str | None, nbytes: int) -> None:
        """A full input queue dropped the oldest entry of ``port``: an overflow, never a malformed payload."""
        self._count("queue_drops", port)
        self.problems.report(
            f"queue_overflow:{port}",
            logging.WARNING,
            "input queue full: port=%s dropped its oldest message (%d bytes; limits %d messages, %.0f MiB per input): the stage is behind its input",
            port,
            nbytes,
            self.args.queue_size,
            getattr(self.args, "queue_mib", 64),
        )

    # ---- session and declarations
    def open(self) -> None:
        self.session = session_from_args(self.args)
        s = self.session
        for port, key in self.output_keys.items():
            cc = zenoh.CongestionControl.BLOCK
            self._publishers[port] = s.declare_publisher(key, congestion_control=cc)
            if self.spec.outputs[port].latched:
                self._keepalive.append(s.declare_queryable(key, self._make_latched_reply(port)))
        if self.spec.kind == "raw_sink":
            self._keepalive.append(s.declare_subscriber(keys.run_pattern(self.run_id), self._on_raw_sample))
        for port, key in self.input_keys.items():
            self._keepalive.append(s.declare_subscriber(key, self._make_input_cb(port)))
            if self.spec.inputs[port].latched:
                threading.Thread(target=self._query_latched, args=(port, key), daemon=True).start()
        self._stats_pub = s.declare_publisher(keys.stats_key(self.run_id, self.node_id), congestion_control=zenoh.CongestionControl.DROP)
        self._progress_pub = s.declare_publisher(keys.ack_key(self.run_id, self.node_id), congestion_control=zenoh.CongestionControl.DROP)
        if self.spec.kind == "source":
            self._keepalive.append(s.declare_subscriber(keys.ack_pattern(self.run_id), self._on_ack))
            self._keepalive.append(s.liveliness().declare_subscriber(keys.alive_pattern(self.run_id), self._on_alive, history=True))
        self._token = s.liveliness().declare_token(keys.alive_key(self.run_id, self.node_id))
        self.log.info(
            "node up: stage=%s run=%s inputs=%s outputs=%s pid=%d",
            self.spec.stage,
            self.run_id,
            ",".join(f"{p}<-{k}" for p, k in self.input_keys.items()) or "-",
            ",".join(self.output_keys.values()) or "-",
            os.getpid(),
        )

    def _make_latched_reply(self, port: str) -> Callable[[Any], None]:
        key = self.output_keys[port]

        def reply(query: Any) -> None:
            data = self._latched_out.get(port)
            if data is not None:
                query.reply(key, data)

        return reply

    def _query_latched(self, port: str, key: str) -> None:
        """Ask the publisher of a latched input for its last value until one arrives.

        A query sent before this session knows the route to the publisher's
        queryable gets no answer (as with puts), so it is repeated until the
        value has come, by reply or by subscription.
        """
        attempt = 0
        while port not in self._latched_in and not self.stop_event.is_set():
            attempt += 1
            try:
                for reply in self.session.get(key, timeout=1.0):
                    if reply.ok is not None:
                        self._count("received", port)
                        self._accept(port, key, reply.ok.payload.to_bytes(), time.time_ns())
                        return
            except Exception as exc:  # the session may be closing
                self.log.debug("latched query failed: port=%s error=%s", port, exc)
                return
            if attempt == 10:
                self.log.info("still waiting for latched input: port=%s key=%s", port, key)
            self.stop_event.wait(0.2)

    def _make_input_cb(self, port: str) -> Callable[[Any], None]:
        def cb(sample: Any) -> None:
            self._count("received", port)
            self._accept(port, str(sample.key_expr), sample.payload.to_bytes(), time.time_ns())

        return cb

    def _on_raw_sample(self, sample: Any) -> None:
        key = str(sample.key_expr)
        if f"/{keys.ACK}/" in key:
            return
        self._count("received")
        data = sample.payload.to_bytes()
        self.queue.put((None, key, data, time.time_ns()), None, len(data))

    def _accept(self, port: str, key: str, data: bytes, recv_ns: int) -> None:
        """Decode one input and queue it: what does not decode never takes a queue slot.

        Decoding here, on the subscriber's thread, means a burst of malformed
        payloads is counted as such (``decode_errors``) and cannot push good
        messages out of the queue; only well-formed messages compete for it,
        each port within its own bound (``queue_drops``, by port). A message
        whose stamp lies more than ``--stamp-window-s`` ahead of the newest
        stamp accepted so far is rejected (``rejected_stamps``): one message
        from the far future would otherwise make every later frame look
        stale to the join.
        """
        msg = self._decode(port, key, data)
        if msg is None:
            return
        if not self.spec.inputs[port].latched:
            header = getattr(msg, "header", None)
            if header is not None and not self._stamp_ok(port, key, int(header.stamp_ns)):
                return
        self.queue.put((port, key, msg, recv_ns), port, len(data))

    def _stamp_ok(self, port: str, key: str, stamp: int) -> bool:
        window_ns = int(getattr(self.args, "stamp_window_s", 60.0) * 1e9)
        with self._count_lock:
            clock = self._stamp_clock_ns
            if clock is None or stamp <= clock + window_ns:
                self._stamp_clock_ns = stamp if clock is None else max(clock, stamp)
                return True
        self._count("rejected_stamps", port)
        self.problems.report(
            f"stamp_window:{port}",
            logging.WARNING,
            "dropped message: reason=stamp_out_of_window key=%s stamp_ns=%d is %.1f s ahead of the newest accepted stamp (window %.0f s)",
            key,
            stamp,
            (stamp - clock) / 1e9,
            window_ns / 1e9,
        )
        return False

    def _on_ack(self, sample: Any) -> None:
        try:
            msg = Progress.decode(sample.payload.to_bytes())
        except SchemaError:
            return
        with self._ack_lock:
            self._acks[msg.node_id] = msg

    def _on_alive(self, sample: Any) -> None:
        node = str(sample.key_expr).rsplit("/", 1)[-1]
        with self._ack_lock:
            if sample.kind == zenoh.SampleKind.PUT:
                self._alive.add(node)
            else:
                self._alive.discard(node)
                self._acks.pop(node, None)

    # ---- publishing
    def publish(self, result: StageResult, stamp_ns: int, frame_index: int) -> None:
        for port, msg in result.outputs.items():
            if port not in self._publishers:
                raise RuntimeError(f"core returned output {port!r}, which {self.spec.stage} does not declare")
            want = self.spec.outputs[port].schema
            if not isinstance(msg, want):
                raise RuntimeError(f"core returned {type(msg).__name__} on {port!r}, declared {want.__name__}")
            data = msg.encode()
            if self.spec.outputs[port].latched:
                self._latched_out[port] = data
            self._publishers[port].put(data)
            self.stats.counters["published"] += 1
        for issue in result.issues:
            self.stats.counters["issues"] += 1
            self.stats.issues_by_kind[issue.kind] += 1
        self.issue_log.frame(stamp_ns, result.issues)
        self.stats.last_stamp_ns = max(self.stats.last_stamp_ns, stamp_ns)
        self.stats.counters["processed"] += 1
        self._progress_pub.put(
            Progress(node_id=self.node_id, last_stamp_ns=stamp_ns, last_frame_index=frame_index, handled=self.stats.counters["processed"]).encode()
        )

    def maybe_stats(self, force: bool = False) -> None:
        now = time.monotonic()
        if force or now - self._last_stats >= self.args.stats_period:
            self._last_stats = now
            with self._count_lock:
                msg = self.stats.message(self.run_id, self.node_id, self.spec.stage, self.started, len(self.queue))
            self._stats_pub.put(msg.encode())

    # ---- decode
    def _decode(self, port: str | None, key: str, data: bytes) -> Message | None:
        report: list = []
        try:
            if port is None:
                msg = bus_schemas.decode_any(data, where=key, report=report)
            else:
                msg = self.spec.inputs[port].schema.decode(data, where=key, report=report)
            if report:
                self._count_out_of_range(key, report)
            return msg
        except SchemaError as exc:
            reason, kind, detail = type(exc).__name__, type(exc).__name__, str(exc)
        except Exception as exc:  # bus_schemas raises only SchemaError; if it ever does not, the stage still goes on
            reason, kind, detail = f"decode_exception:{type(exc).__name__}", "decode_exception", str(exc)
        with self._count_lock:
            self.stats.counters["decode_errors"] += 1
            if port is not None:
                self.stats.counters[f"decode_errors.{port}"] += 1
            self.stats.errors_by_kind[kind] += 1
        self.problems.report(f"decode:{reason}:{key}", logging.WARNING, "dropped message: reason=%s key=%s detail=%s", reason, key, detail[:500])
        return None

    def _count_out_of_range(self, key: str, report: list) -> None:
        """Objects dropped or values cleared at decoding for being out of their schema's range: issues, counted and logged."""
        with self._count_lock:
            for rec in report:
                kind = f"out_of_range_{rec.action}"
                self.stats.counters["issues"] += rec.count
                self.stats.issues_by_kind[kind] += rec.count
        for rec in report:
            self.problems.report(
                f"out_of_range:{rec.action}:{rec.field}:{key}",
                logging.WARNING,
                "input out of range: action=%s field=%s count=%d key=%s detail=%s",
                rec.action,
                rec.field,
                rec.count,
                key,
                rec.detail[:300],
            )

    # ---- operator loop
    def _join_ports(self) -> list[str]:
        return [p for p in self.input_keys if not self.spec.inputs[p].latched]

    def _required_latched(self) -> list[str]:
        return [p for p in self.input_keys if self.spec.inputs[p].latched]

    def _handle_operator_item(self, core: Any, item: tuple) -> None:
        port, _key, msg, recv_ns = item  # decoded by _accept
        lat_ms = math.nan
        if self.spec.inputs[port].latched:
            self._latched_in[port] = msg
        else:
            header = getattr(msg, "header", None)
            stamp = int(header.stamp_ns) if header is not None else 0
            lat_ms = (recv_ns - stamp) / 1e6 if header is not None else math.nan
            entry = self._pending.setdefault(stamp, {})
            self._pending_since.setdefault(stamp, time.monotonic())
            if port in entry:
                self.stats.counters["join_drops"] += 1
                self.problems.report(f"duplicate:{port}", logging.WARNING, "duplicate input: port=%s stamp_ns=%d (older one replaced)", port, stamp)
            entry[port] = msg
        self._run_ready(core, lat_ms)
        self._expire_pending()

    def _run_ready(self, core: Any, lat_ms: float) -> None:
        """Run the core on every complete input set, oldest first.

        Sets wait (bounded by the join window and timeout) while a latched
        input has not arrived yet: a frame may overtake the scene on the wire.
        """
        if any(p not in self._latched_in for p in self._required_latched()):
            return
        join = self._join_ports()
        ready = sorted(s for s, e in self._pending.items() if all(p in e for p in join))
        for s in ready:
            # a complete newer stamp makes every older incomplete one stale
            for old in [o for o in self._pending if o < s and o not in ready]:
                self._drop_pending(old, "superseded")
            inputs = self._pending.pop(s)
            self._pending_since.pop(s, None)
            inputs.update(self._latched_in)
            self._run_update(core, inputs, s, lat_ms)

    def _drop_pending(self, stamp: int, reason: str) -> None:
        missing_latched = [p for p in self._required_latched() if p not in self._latched_in]
        if missing_latched:
            reason = f"waiting_for_latched ports={','.join(missing_latched)}"
        entry = self._pending.pop(stamp, None)
        self._pending_since.pop(stamp, None)
        if entry is not None:
            self.stats.counters["join_drops"] += 1
            self.problems.report(
                f"join:{reason}", logging.WARNING, "dropped input set: reason=%s stamp_ns=%d had=%s", reason, stamp, ",".join(sorted(entry))
            )

    def _expire_pending(self) -> None:
        limit = max(2, getattr(self.args, "join_window", 16))
        while len(self._pending) > limit:
            self._drop_pending(next(iter(self._pending)), "join_window_full")
        if len(self.queue):
            # inputs still queued may complete a set: time spent in the core is not time the set waited
            # for a missing input, so the timeout is judged only once everything received is joined
            return
        now = time.monotonic()
        for s in [s for s, t in self._pending_since.items() if now - t > JOIN_TIMEOUT_S]:
            self._drop_pending(s, "join_timeout")

    def _run_update(self, core: Any, inputs: dict[str, Message], stamp: int, lat_ms: float) -> None:
        t0 = time.perf_counter()
        try:
            result = core.update(inputs)
        except Exception as exc:
            self._count_failure("core_exception", exc, "core failed on stamp_ns=%d (input set dropped)", stamp)
            return
        dt = (time.perf_counter() - t0) * 1e3
        self.stats.proc_ms.append(dt)
        self.stats.proc_ms_max = max(self.stats.proc_ms_max, dt)
        if not math.isnan(lat_ms):
            self.stats.latency_ms.append(lat_ms + dt)
        frame_index = _frame_index_of(inputs)
        try:
            self.publish(result, stamp, frame_index)
        except Exception as exc:  # an output that does not encode: that input set is lost, the stage goes on
            self._count_failure("publish_exception", exc, "publishing failed on stamp_ns=%d (outputs of this input set dropped)", stamp)

    def _count_failure(self, kind: str, exc: BaseException, fmt: str, *args: Any) -> None:
        """Count an exception of a core (or of handling one message) and log it, rate-limited."""
        self.stats.counters["core_errors"] += 1
        self.stats.errors_by_kind[kind] += 1
        self.problems.report(
            f"{kind}:{type(exc).__name__}",
            logging.ERROR,
            fmt + ": %s: %s",
            *args,
            type(exc).__name__,
            str(exc)[:500],
            first_extra=lambda: traceback.format_exc().rstrip(),
        )

    def run_operator(self, core: Any) -> None:
        self._serve(lambda item: self._handle_operator_item(core, item))

    def run_raw_sink(self, core: Any) -> None:
        def handle(item: tuple) -> None:
            _port, key, data, recv_ns = item
            t0 = time.perf_counter()
            try:
                issues = core.handle(key, data, recv_ns) or []
            except Exception as exc:
                self._count_failure("core_exception", exc, "sink failed on key=%s (message dropped)", key)
                return
            dt = (time.perf_counter() - t0) * 1e3
            self.stats.proc_ms.append(dt)
            self.stats.proc_ms_max = max(self.stats.proc_ms_max, dt)
            self.stats.counters["processed"] += 1
            stamp = _peek_stamp(data)
            if stamp is not None and stamp > self.stats.last_stamp_ns:
                self.stats.last_stamp_ns = stamp
                self._progress_pub.put(
                    Progress(node_id=self.node_id, last_stamp_ns=stamp, last_frame_index=-1, handled=self.stats.counters["processed"]).encode()
                )
            for issue in issues:
                self.stats.counters["issues"] += 1
                self.stats.issues_by_kind[issue.kind] += 1
            self.issue_log.frame(stamp if stamp is not None else recv_ns, issues, scope=key)

        try:
            self._serve(handle)
        finally:
            core.close()

    def _serve(self, handle: Callable[[tuple], None]) -> None:
        quiet_s = DRAIN_QUIET_S
        while True:
            item = self.queue.get(timeout=0.05)
            if item is not None:
                self._last_input_mono = time.monotonic()
                try:
                    handle(item)
                except Exception as exc:  # the last net: one message never ends the stage
                    self._count_failure("handler_exception", exc, "handling a message from key=%s failed (dropped)", item[1])
            else:
                self._expire_pending()
            self.maybe_stats()
            if self.stop_event.is_set() and item is None:
                if self.signals > 1 or time.monotonic() - self._last_input_mono >= quiet_s:
                    break

    # ---- source loop
    def run_source(self, core: Any) -> None:
        speed = getattr(self.config, "speed", 1.0)
        as_fast = isinstance(speed, str) and speed == "max"
        if not as_fast:
            speed = float(speed)
            if not speed > 0:
                raise ConfigError(f"speed must be > 0 or 'max', got {speed}")
        self._await_nodes([n for n in self.args.await_nodes.split(",") if n], AWAIT_NODES_S)
        t_wall0 = None
        stamp0 = None
        n = 0
        for stamp, result in core:
            if self.stop_event.is_set():
                break
            if as_fast:
                self._wait_for_consumers(stamp, window=MAX_SPEED_WINDOW)
            else:
                if t_wall0 is None:
                    t_wall0, stamp0 = time.monotonic(), stamp
                due = t_wall0 + (stamp - stamp0) / 1e9 / speed
                while not self.stop_event.is_set():
                    left = due - time.monotonic()
                    if left <= 0:
                        break
                    self.stop_event.wait(min(left, 0.1))
                if self.stop_event.is_set():
                    break
            t0 = time.perf_counter()
            self.publish(result, stamp, _frame_index_of(result.outputs))
            self.stats.proc_ms.append((time.perf_counter() - t0) * 1e3)
            self._frames_published.append(stamp)
            n += 1
            self.maybe_stats()
        else:
            self.log.info("source finished: frames=%d", n)
        self.maybe_stats(force=True)
        # Let every live node confirm the last frame before the session closes: a put
        # still queued in the session would otherwise be lost with it.
        self._wait_for_consumers(None, window=0, timeout_s=CONSUMER_WAIT_S if as_fast else DRAIN_WAIT_S)

    def _await_nodes(self, node_ids: list[str], timeout_s: float) -> None:
        """Wait until this session sees the liveliness of ``node_ids``.

        A node declares its token after its subscribers, so once its token is
        visible here, so are its subscriptions: a put made earlier could be
        routed to nobody and lost (measured: 14 of 20 first puts of a fresh
        peer were lost; none after its token was seen).
        """
        if not node_ids:
            return
        deadline = time.monotonic() + timeout_s
        while not self.stop_event.is_set():
            with self._ack_lock:
                missing = sorted(set(node_ids) - self._alive)
            if not missing:
                return
            if time.monotonic() > deadline:
                self.log.warning("start: nodes not visible after %.0f s, publishing anyway: %s", timeout_s, ",".join(missing))
                return
            time.sleep(0.005)

    def _wait_for_consumers(self, stamp: int | None, window: int, timeout_s: float = 0.0) -> None:
        """Block until every live node has acked the frame ``window`` frames back.

        ``window`` 0 means the last frame published (the drain at the end)."""
        if stamp is not None and len(self._frames_published) < window:
            return
        target = self._frames_published[-window] if window else (self._frames_published[-1] if self._frames_published else None)
        if target is None:
            return
        timeout_s = timeout_s or CONSUMER_WAIT_S
        deadline = time.monotonic() + timeout_s
        draining = window == 0
        while draining or not self.stop_event.is_set():
            with self._ack_lock:
                others = [n for n in self._alive if n != self.node_id]
                behind = [n for n in others if n not in self._acks or self._acks[n].last_stamp_ns < target]
            if not behind:
                return
            if time.monotonic() > deadline or (draining and self.signals > 1):
                self.log.warning("pacing: nodes behind after %.1f s, going on: %s", timeout_s, ",".join(sorted(behind)))
                with self._ack_lock:
                    for n in behind:  # do not wait on them again until they ack
                        self._acks[n] = Progress(node_id=n, last_stamp_ns=2**62, last_frame_index=-1, handled=0)
                return
            time.sleep(0.002)

    def close(self) -> None:
        self.issue_log.close()
        self.problems.close()
        self.maybe_stats(force=True)
        with self._count_lock:
            summary = self.stats.summary()
        self.log.info("node stopping: %s", summary)
        try:
            if self.session is not None:
                self._token.undeclare()
                time.sleep(CLOSE_LINGER_S)  # zenoh has no flush: let queued puts leave before closing
                self.session.close()
        except Exception as exc:
            self.log.debug("session close failed: %s", exc)


JOIN_TIMEOUT_S = 2.0
DRAIN_QUIET_S = 0.3
DRAIN_WAIT_S = 3.0
CLOSE_LINGER_S = 0.05
AWAIT_NODES_S = 30.0
MAX_SPEED_WINDOW = 3
CONSUMER_WAIT_S = 10.0


def _peek_stamp(data: bytes) -> int | None:
    """``header.stamp_ns`` of a payload if it has one (no full decode)."""
    try:
        _schema, _v, body = unpack_envelope(data)
        stamp = body.get("header", {}).get("stamp_ns")
    except (SchemaError, AttributeError):
        return None
    return stamp if type(stamp) is int else None


def _frame_index_of(messages: Mapping[str, Any]) -> int:
    for m in messages.values():
        h = getattr(m, "header", None)
        if h is not None:
            return int(h.frame_index)
    return -1


# --------------------------------------------------------------------------- entry point


def parse_bindings(spec: StageSpec, args: argparse.Namespace) -> dict[str, str]:
    """Input bindings port -> 'node/output', checked against the spec."""
    raw: dict[str, str] = json.loads(args.inputs_json) if args.inputs_json else {}
    if not isinstance(raw, dict):
        raise ConfigError("--inputs-json must be a JSON object {port: 'node/output'}")
    for item in args.input:
        if "=" not in item:
            raise ConfigError(f"--input {item!r}: expected PORT=NODE/OUTPUT")
        p, ref = item.split("=", 1)
        raw[p.strip()] = ref.strip()
    for port, ref in raw.items():
        if port not in spec.inputs:
            raise ConfigError(f"{spec.stage}: unknown input port {port!r}; known: {', '.join(spec.inputs) or '(none)'}")
        parts = str(ref).split("/")
        if len(parts) != 2:
            raise ConfigError(f"{spec.stage}: input {port} = {ref!r}: expected 'node/output'")
        keys.check_name(parts[0], "node id")
        keys.check_name(parts[1], "output name")
    missing = [p for p, port in spec.inputs.items() if p not in raw and not port.optional]
    if missing and spec.kind == "operator":
        raise ConfigError(f"{spec.stage}: input port(s) {', '.join(missing)} not bound; use --input PORT=NODE/OUTPUT")
    return raw


def setup_logging(level: str, node_id: str) -> None:
    logging.basicConfig(
        level=getattr(logging, str(level).upper(), logging.INFO),
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        datefmt="%H:%M:%S",
        stream=sys.stderr,
        force=True,
    )


def run_stage(spec: StageSpec, argv: list[str] | None = None) -> int:
    """Parse the command line, build config and core, run until stopped.

    Returns the process exit code: 0 clean stop, 1 crash, 2 bad command line
    or config.
    """
    parser = build_parser(spec)
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:
        return EXIT_OK if exc.code == 0 else EXIT_USAGE
    setup_logging(args.log_level, args.node_id)
    log = logging.getLogger(f"iamp.{args.node_id}")
    try:
        keys.check_run_id(args.run_id)
        keys.check_name(args.node_id, "node id")
        params = json.loads(args.params_json)
        if not isinstance(params, dict):
            raise ConfigError("--params-json must be a JSON object")
        params.update(parse_set(args.set))
        config = spec.config_cls.from_params(params, where=f"node {args.node_id} ({spec.stage})")
        bindings = parse_bindings(spec, args)
    except (ConfigError, ValueError, json.JSONDecodeError) as exc:
        log.error("bad configuration: %s", exc)
        return EXIT_USAGE

    node = Node(spec, args, config, bindings)

    def on_signal(signum: int, _frame: Any) -> None:
        node.signals += 1
        node.stop_event.set()
        if node.signals == 1:
            log.info("stop requested: signal=%s, draining", signal.Signals(signum).name)

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    ctx = NodeContext(
        run_id=args.run_id, node_id=args.node_id, stage=spec.stage, log=log, input_keys=node.input_keys, output_keys=node.output_keys
    )
    try:
        try:
            core = spec.make_core(config, ctx)
        except (ConfigError, FileNotFoundError, ValueError) as exc:
            log.error("bad configuration: %s", exc)
            return EXIT_USAGE
        node.open()
        if spec.kind == "source":
            node.run_source(core)
        elif spec.kind == "raw_sink":
            node.run_raw_sink(core)
        else:
            node.run_operator(core)
    except ConfigError as exc:
        log.error("bad configuration: %s", exc)
        return EXIT_USAGE
    except Exception:
        log.error("crashed:\n%s", traceback.format_exc().rstrip())
        node.close()
        return EXIT_CRASH
    node.close()
    return EXIT_OK


# --------------------------------------------------------------------------- helpers for tools (launcher, replay, tests, benchmarks)


class BusClient:
    """A plain session for tools that are not stages: publish, subscribe, watch liveliness.

    Used by the launcher (liveliness, progress), replay, tests and benchmarks,
    so that they too never import zenoh themselves.
    """

    def __init__(self, mode: str = "peer", connect: Iterable[str] = (), listen: Iterable[str] = (), config_file: str | None = None) -> None:
        self.session = open_session(mode, connect, listen, config_file)
        self._keep: list[Any] = []

    def __enter__(self) -> "BusClient":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def close(self) -> None:
        try:
            self.session.close()
        except Exception:
            pass

    def locators(self) -> list[str]:
        """Endpoints this session listens on (with the real port when 0 was asked)."""
        return _own_locators(self.session)

    def publisher(self, key: str, *, block: bool = True) -> Callable[[bytes], None]:
        pub = self.session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK if block else zenoh.CongestionControl.DROP)
        self._keep.append(pub)
        return lambda data: pub.put(data)

    def publisher_with_matching(self, key: str) -> tuple[Callable[[bytes], None], Callable[[], bool]]:
        pub = self.session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
        self._keep.append(pub)
        return (lambda data: pub.put(data)), (lambda: bool(pub.matching_status.matching))

    def put(self, key: str, data: bytes) -> None:
        self.session.put(key, data, congestion_control=zenoh.CongestionControl.BLOCK)

    def subscribe(self, key: str, callback: Callable[[str, bytes], None]) -> None:
        def cb(sample: Any) -> None:
            callback(str(sample.key_expr), sample.payload.to_bytes())

        self._keep.append(self.session.declare_subscriber(key, cb))

    def watch_alive(self, pattern: str, callback: Callable[[str, bool], None]) -> None:
        """Call ``callback(node_id, alive)`` for every liveliness change (with history)."""

        def cb(sample: Any) -> None:
            callback(str(sample.key_expr).rsplit("/", 1)[-1], sample.kind == zenoh.SampleKind.PUT)

        self._keep.append(self.session.liveliness().declare_subscriber(pattern, cb, history=True))

    def alive_now(self, pattern: str, timeout_s: float = 2.0) -> set[str]:
        out = set()
        for reply in self.session.liveliness().get(pattern, timeout=timeout_s):
            if reply.ok is not None:
                out.add(str(reply.ok.key_expr).rsplit("/", 1)[-1])
        return out

    def declare_queryable(self, key: str, reply: Callable[[], bytes | None]) -> None:
        """Answer queries on ``key`` with ``reply()`` (nothing when it returns None)."""

        def cb(query: Any) -> None:
            data = reply()
            if data is not None:
                query.reply(key, data)

        self._keep.append(self.session.declare_queryable(key, cb))

    def declare_token(self, key: str) -> None:
        self._keep.append(self.session.liveliness().declare_token(key))

    def query(self, key: str, timeout_s: float = 2.0) -> list[bytes]:
        out = []
        for reply in self.session.get(key, timeout=timeout_s):
            if reply.ok is not None:
                out.append(reply.ok.payload.to_bytes())
        return out


def _own_locators(session: zenoh.Session) -> list[str]:
    info = session.info
    # zenoh-python exposes the session's own locators through its config/state; fall back to none
    for attr in ("locators",):
        fn = getattr(info, attr, None)
        if callable(fn):
            try:
                return [str(x) for x in fn()]
            except Exception:
                pass
    return []
