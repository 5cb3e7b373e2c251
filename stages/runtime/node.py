"""The node: one running stage, its session, its ports and its single loop (decode, queue, join, run, publish).

- decoding happens in the subscriber callback, before anything is queued,
  through the port's message class: a ``SchemaError`` (or any other
  exception) is counted (``decode_errors``, ``decode_errors.<port>``),
  dropped and logged rate-limited; objects out of their schema's range are
  dropped (or the value cleared) by the decoder and counted as issues
  ``out_of_range_dropped`` / ``out_of_range_cleared``; a joined input stamped
  more than ``--stamp-window-s`` ahead of the newest accepted stamp is
  rejected (``rejected_stamps``), unless ``STAMP_JUMP_AFTER`` in a row agree
  with one another (a source whose clock jumped: followed from then on,
  ``stamp_clock_jumps``);
- the decoded messages wait in the per-input bounded queues (``queues.py``),
  drained in arrival order by one loop, so processing is ordered and
  single-threaded;
- operators: a bounded, counted join on ``header.stamp_ns`` over the joined
  inputs (``JOIN_WINDOW`` incomplete sets at most; ``JOIN_TIMEOUT_S``: a set
  is dropped when its missing inputs have been silent that long, never while
  one of them is still arriving, only behind); latched inputs are queried
  at start and awaited (sets wait for them, bounded by the join window
  alone: no timeout while a latched input is missing); latest-value and wildcard inputs are kept as they
  come (``ports.py``); the core sees all of them with every complete set. An
  exception of a core on one input set is counted (``core_errors``) and that
  set dropped: no payload can end a stage;
- outputs are encoded and published; a latched output's last payload is
  answered to queries; ``NodeStats`` go to ``_stats/<node>`` every
  ``--stats-period`` and ``Progress`` to ``_ack/<node>`` after every handled
  input set;
- sources are paced by ``pacing.Pacer``; raw sinks (the recorder) get every
  payload of the run, with back-pressure instead of drops;
- ``run_stage``: start-up (``args.start_stage``), then a clean stop on
  SIGINT/SIGTERM (drain the queue, wait until the inputs are quiet, print a
  summary) and the exit codes 0 (clean), 1 (crash), 2 (bad command line or
  config).
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import gc
import logging
import math
import os
import signal
import threading
import time
import traceback
from types import MappingProxyType
from typing import Any, Callable, Mapping

import zenoh

import bus_schemas
from bus_schemas import Progress, SchemaError, keys
from bus_schemas._wire import Message, peek_header

from stages.lib.base import ConfigError, StageResult
from stages.runtime.args import EXIT_CRASH, EXIT_OK, EXIT_USAGE, on_stop_signals, session_from_args, start_stage
from stages.runtime.logs import IssueLog, ProblemLog, _Stats
from stages.runtime.pacing import AWAIT_NODES_S, CONSUMER_WAIT_S, DRAIN_WAIT_S, SOURCE_WARMUP, Consumers, Pacer
from stages.runtime.ports import NodeContext, StageSpec, pattern_key
from stages.runtime.queues import InputQueue
from stages.runtime.trace import HopTrace

MiB = 1024 * 1024


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
        self.queue = InputQueue(
            args.queue_size, self._count_queue_drop, block=spec.kind == "raw_sink", max_bytes=int(getattr(args, "queue_mib", 64) * MiB),
            # --max-age-s (a live pipeline's max_age_s): a joined input that waited longer than that is skipped where a
            # newer one of its port is queued (stale_drops); latched, latest-value and wildcard inputs never
            max_age_s=float(getattr(args, "max_age_s", 0.0) or 0.0) if spec.kind == "operator" else 0.0,
            ageing=frozenset(p for p, port in spec.inputs.items() if port.joined), on_stale=self._count_stale,
        )
        self.bindings = bindings
        self.input_keys = {port: f"{keys.ROOT}/{self.run_id}/{ref}" for port, ref in bindings.items()}
        if spec.kind == "operator":  # wildcard inputs: bound by the runtime to their pattern
            for port, p in spec.inputs.items():
                if p.pattern is not None:
                    self.input_keys[port] = pattern_key(self.run_id, p.pattern)
        # callbacks (zenoh's threads) and the loop both count: one lock, and every key made here
        # so that copying the counters for NodeStats never meets a key being added
        self._count_lock = threading.Lock()
        for port in self.input_keys:
            for k in ("received", "decode_errors", "queue_drops", "stale_drops", "duplicate_inputs", "rejected_stamps"):
                self.stats.counters[f"{k}.{port}"] = 0
        self.stats.counters["rejected_stamps"] = 0
        wildcards = [p for p in self.input_keys if self.spec.inputs[p].pattern is not None]
        for port in wildcards:
            self.stats.counters[f"rejected_keys.{port}"] = 0
        if wildcards:
            self.stats.counters["rejected_keys"] = 0
        self._stamp_clock_ns: int | None = None  # newest stamp accepted on a joined input
        self._stamp_window_ns = int(getattr(args, "stamp_window_s", 60.0) * 1e9)  # --stamp-window-s
        # joined messages in a row stamped beyond the window, each within the window of the run's newest: [first, newest, count]
        self._ahead_run: list[int] | None = None
        self.output_keys = {port: keys.data_key(self.run_id, self.node_id, port) for port in spec.outputs}
        self.session: zenoh.Session | None = None
        self._publishers: dict[str, Any] = {}
        self._latched_out: dict[str, bytes] = {}
        self._latched_in: dict[str, Message] = {}
        self._latest_in: dict[str, Message] = {}  # latest-value inputs
        self._wild_in: dict[str, dict[str, Message]] = {}  # wildcard inputs: port -> key -> newest
        self._pending: "collections.OrderedDict[int, dict[str, Message]]" = collections.OrderedDict()
        self._pending_since: dict[int, float] = {}
        # the stamps of the last input sets handled -> (when (monotonic), their joined ports): a joined message for one
        # of them on one of those ports, soon after, is a duplicate (DUPLICATE_WINDOW_S)
        self._handled: "collections.OrderedDict[int, tuple[float, frozenset[str]]]" = collections.OrderedDict()
        self._port_seen: dict[str, float] = {}  # joined port -> when a message of it was last joined (monotonic)
        joined = [p for p in self.input_keys if spec.inputs[p].joined]
        self._gap_port = joined[0] if joined else None  # whose frame indices count frames never received
        self._last_frame_index: int | None = None
        self._keepalive: list[Any] = []
        self._last_stats = 0.0
        self._last_input_mono = time.monotonic()
        self._had_input = False  # an input of a kind a stop drains (joined, latched, raw) has come
        self._silent_since: float | None = None  # when the inputs fell silent (warned once), None while they flow
        self._progress_pub = None
        self._stats_pub = None  # both declared by open(); a node whose open() failed publishes no final stats
        # the inputs a stop waits to be quiet: not latest-value or wildcard ones (the run's NodeStats never are)
        self._drain_ports = {p for p in self.input_keys if spec.inputs[p].joined or spec.inputs[p].latched}
        self.consumers = Consumers(self.node_id)  # sources: the live nodes and their acks, for pacing
        # per-hop trace (IAMP_HOP_TRACE, trace.py): None unless asked; then the times of each joined input set
        self._trace: HopTrace | None = None
        self._hops: dict[int, dict[str, list[int]]] = {}  # stamp -> port -> [recv, deq, dec] (wall ns)
        self._prep_ns: dict[int, list[list[int]]] = {}  # stamp -> [start, end] (wall ns) of each prepare that ran on it, traced
        self._deq_ns = 0  # wall clock when the loop took the item it is handling from the queue
        self._deq_gc_ns = 0  # the trace's GC pause counter then
        self._out_times: dict[str, list[int]] = {}  # output -> [encode start, encode end, put end] of the last publish
        self._last_wall_ns = 0  # the source_wall_ns of the last publish (0: none)
        # the collector's generations are frozen at start and once more after the first input sets (gc_freeze)
        self._gc_refreeze_at = GC_FREEZE_AFTER if gc_freeze_enabled(self.log) else 0

    # ---- counters used from callbacks
    def _count(self, key: str, port: str | None = None, n: int = 1) -> None:
        with self._count_lock:
            self.stats.counters[key] += n
            if port is not None:
                self.stats.counters[f"{key}.{port}"] += n

    def _count_queue_drop(self, port: str | None, nbytes: int, item: Any = None) -> None:
        """A full input queue dropped the oldest entry of ``port``: counted as an overflow only if it was well-formed.

        An entry still undecoded (raw bytes) is decoded here first, so a
        malformed one counts as ``decode_errors`` and never as ``queue_drops``.
        """
        if port is not None and item is not None and isinstance(item[2], (bytes, bytearray)):
            if self._decode(port, item[1], item[2]) is None:
                return
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

    def _count_stale(self, port: str | None, nbytes: int, item: Any = None) -> None:
        """The queue skipped an entry of ``port`` older than ``--max-age-s`` (a newer one is queued): ``stale_drops``.
        Not decoded first (a stage that is behind has no time for it): a malformed entry skipped so counts here too."""
        self._count("stale_drops", port)
        self.problems.report(
            f"stale:{port}",
            logging.WARNING,
            "input older than %.2f s skipped: port=%s (a newer one is queued; the stage is behind its input and works on"
            " its freshest frames; max_age_s)",
            self.args.max_age_s,
            port,
        )

    # ---- session and declarations
    def open(self) -> None:
        self._trace = HopTrace.from_env(self.node_id, self.spec.stage, dict(self.bindings))
        self.session = session_from_args(self.args)
        s = self.session
        for port, key in self.output_keys.items():
            cc = zenoh.CongestionControl.BLOCK
            self._publishers[port] = s.declare_publisher(key, congestion_control=cc)
            if self.spec.outputs[port].latched:
                self._keepalive.append(s.declare_queryable(key, self._make_latched_reply(port)))
        if self.spec.kind == "raw_sink":
            self._keepalive.append(s.declare_subscriber(keys.run_pattern(self.run_id), self._on_raw_sample))
            # the run's latched values (the scene) published before this sink came up (a recorder started late, or
            # restarted into the next split) are answered by their publishers' queryables
            threading.Thread(target=self._query_latched_raw, daemon=True).start()
        for port, key in self.input_keys.items():
            self._keepalive.append(s.declare_subscriber(key, self._make_input_cb(port)))
            if self.spec.inputs[port].latched:
                threading.Thread(target=self._query_latched, args=(port, key), daemon=True).start()
        self._stats_pub = s.declare_publisher(keys.stats_key(self.run_id, self.node_id), congestion_control=zenoh.CongestionControl.DROP)
        self._progress_pub = s.declare_publisher(keys.ack_key(self.run_id, self.node_id), congestion_control=zenoh.CongestionControl.DROP)
        if self.spec.kind == "source":
            self._keepalive.append(s.declare_subscriber(keys.ack_pattern(self.run_id), self._on_ack))
        if self.spec.kind == "source" or self._awaited():
            self._keepalive.append(s.liveliness().declare_subscriber(keys.alive_pattern(self.run_id), self._on_alive, history=True))
        self._token = s.liveliness().declare_token(keys.alive_key(self.run_id, self.node_id))
        if getattr(self.args, "connect", None):
            threading.Thread(target=self._check_link, daemon=True).start()
        self.log.info(
            "node up: stage=%s run=%s inputs=%s outputs=%s pid=%d",
            self.spec.stage,
            self.run_id,
            ",".join(f"{p}<-{k}" for p, k in self.input_keys.items()) or "-",
            ",".join(self.output_keys.values()) or "-",
            os.getpid(),
        )

    def _check_link(self) -> None:
        """One warning when ``LINK_CHECK_S`` after the start this session has no link to any router or peer although it
        was told to ``--connect``: nothing listens there, or it refused this node (wrong or missing credentials). A
        node did nothing and said nothing then (zenoh keeps trying to connect; this says so once)."""
        if self.stop_event.wait(LINK_CHECK_S):
            return
        try:
            linked = bool(self.session.info.routers_zid()) or bool(self.session.info.peers_zid())
        except Exception:  # noqa: BLE001 - the session closing
            return
        if not linked:
            self.log.warning("no link after %.0f s to --connect %s: nothing listens there, or it refused this node (credentials?);"
                             " zenoh keeps trying", LINK_CHECK_S, " ".join(self.args.connect))

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
        gaps = port == self._gap_port

        def cb(sample: Any) -> None:
            self._count("received", port)
            data = sample.payload.to_bytes()
            if gaps:
                self._count_unreceived(data)
            self._accept(port, str(sample.key_expr), data, time.time_ns())

        return cb

    def _count_unreceived(self, data: bytes) -> None:
        """Frames the source numbered that never reached this node (``frames_unreceived``): gaps in the
        ``header.frame_index`` of its first joined input as received, before any queue (whose own drops are
        ``queue_drops``). A node that was stopped or hung, or too slow for its transport, lost them silently: its
        counters said 0 while it had 301 of 574 frames. (A live tracker that numbers its frames with gaps counts
        its gaps here too.) A frame index that goes back starts the count afresh (a source started over)."""
        try:
            _schema, _v, header = peek_header(data)
            index = header.get("frame_index") if isinstance(header, dict) else None
        except (SchemaError, AttributeError):
            return
        if type(index) is not int:
            return
        with self._count_lock:
            last, self._last_frame_index = self._last_frame_index, index
        if last is not None and last + 1 < index < last + MAX_FRAME_GAP:
            self._count("frames_unreceived", n=index - last - 1)
            self.problems.report("frames_unreceived", logging.WARNING,
                                 "frames not received: %d before frame %d (lost on the way: this node or the one before it was stopped, hung or behind its transport, or the publisher skipped them, or sent frames this node could not read: see decode_errors)",
                                 index - last - 1, index)

    def _query_latched_raw(self) -> None:
        """A raw sink's start: queue what the run's latched outputs answer (a query on the run's keys, tried again until
        one is answered, as a query sent before the routes have settled gets no answer); the sink takes a value it
        already has once (the recorder writes a latched payload once per file)."""
        for wait_s in LATCHED_QUERY_WAITS_S:  # until an answer comes: under load the routes take seconds to settle
            if self.stop_event.wait(wait_s):
                return
            answered = False
            try:
                for reply in self.session.get(keys.run_pattern(self.run_id), timeout=1.0):
                    if reply.ok is not None:
                        data = reply.ok.payload.to_bytes()
                        self._count("received")
                        self.queue.put((LATCHED_QUERY, str(reply.ok.key_expr), data, time.time_ns()), None, len(data))
                        answered = True
            except Exception as exc:  # the session may be closing
                self.log.debug("latched query failed: error=%s", exc)
                return
            if answered:
                return

    def _on_raw_sample(self, sample: Any) -> None:
        key = str(sample.key_expr)
        if f"/{keys.ACK}/" in key:
            return
        self._count("received")
        data = sample.payload.to_bytes()
        self.queue.put((None, key, data, time.time_ns()), None, len(data))

    def _accept(self, port: str, key: str, data: bytes, recv_ns: int) -> None:
        """Queue one input; a malformed one never pushes a good one out, and every drop is counted by its cause.

        While the port's queue has room the bytes are queued and the loop
        decodes them. When it is full, this subscriber thread decodes the
        incoming payload and then the port's entries still undecoded: the
        malformed ones leave (``decode_errors``) and only a well-formed
        message can push out the oldest well-formed one (``queue_drops``, by
        port). So a burst of malformed payloads costs no good frame, and
        decoding stays off the subscriber threads in normal running. A message
        whose stamp lies more than ``--stamp-window-s`` ahead of the newest
        stamp accepted so far is rejected (``rejected_stamps``): one message
        from the far future would otherwise make every later frame look
        stale to the join.
        """
        if not self.queue.full(port, len(data)):
            # room: queue the bytes, the loop decodes them (decoding here competes with the core for the GIL:
            # measured on 2 cores, markov_prediction lost 57-173 of 1,123 frames at speed 1 that way, 11 otherwise)
            self.queue.put((port, key, data, recv_ns), port, len(data))
            return
        # full: only a well-formed message may push an older one out, and only a well-formed one may be pushed
        # out: decode this one now, then the port's entries still undecoded (the malformed ones leave, counted)
        msg = self._decode(port, key, data)
        if msg is None or not self._stamp_accepted(port, key, msg):
            return
        self.queue.verify(port, self._verified)
        self.queue.put((port, key, msg, recv_ns), port, len(data))

    def _verified(self, item: tuple) -> tuple | None:
        """A queued entry decoded (unchanged if it already is); None when it is malformed or out of the stamp window."""
        port, key, msg, recv_ns = item
        if not isinstance(msg, (bytes, bytearray)):
            return item
        decoded = self._decode(port, key, msg)
        if decoded is None or not self._stamp_accepted(port, key, decoded):
            return None
        return (port, key, decoded, recv_ns)

    def _stamp_accepted(self, port: str, key: str, msg: Message) -> bool:
        if self.spec.inputs[port].joined:  # the stamp clock is the joined inputs' (a latest value may be of any age)
            header = getattr(msg, "header", None)
            if header is not None and not self._stamp_ok(port, key, int(header.stamp_ns)):
                return False
        return True

    def _stamp_ok(self, port: str, key: str, stamp: int) -> bool:
        """Whether a joined message's stamp is within the window ahead of the stamp clock (then the clock moves to it).

        Beyond it the message is rejected, unless it completes a run of ``STAMP_JUMP_AFTER`` such messages in a row,
        each within the window of the run's newest: a source whose clock jumped ahead (a live tracker restarted
        minutes later, re-synchronised, or switched to another clock) is then followed from that message on, once
        (``stamp_clock_jumps``, one warning); without that every later frame would be rejected for good. A lone far
        stamp, or stamps far ahead that do not follow one another, stay rejected."""
        window_ns = self._stamp_window_ns
        with self._count_lock:
            clock = self._stamp_clock_ns
            if clock is None or stamp <= clock + window_ns:
                self._stamp_clock_ns = stamp if clock is None else max(clock, stamp)
                self._ahead_run = None
                return True
            run = self._ahead_run
            if run is not None and abs(stamp - run[1]) <= window_ns:
                run[1], run[2] = max(run[1], stamp), run[2] + 1
            else:
                run = self._ahead_run = [stamp, stamp, 1]
            jumped = run[2] >= STAMP_JUMP_AFTER
            if jumped:
                self._stamp_clock_ns, self._ahead_run = run[1], None
        if jumped:
            self._count("stamp_clock_jumps", port)
            self.log.warning(
                "stamp clock moved ahead by %.1f s: %d messages in a row stamped beyond the window (%.0f s) agree with one"
                " another (a restarted or re-synchronised source); the first %d of them were dropped (rejected_stamps)",
                (run[0] - clock) / 1e9, run[2], window_ns / 1e9, run[2] - 1,
            )
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
        self.consumers.on_ack_payload(sample.payload.to_bytes())

    def _on_alive(self, sample: Any) -> None:
        self.consumers.on_alive(str(sample.key_expr).rsplit("/", 1)[-1], sample.kind == zenoh.SampleKind.PUT)

    # ---- publishing
    def publish(self, result: StageResult, stamp_ns: int, frame_index: int) -> None:
        """Encode and put every output; a source stamps its headers' ``source_wall_ns`` (the wall clock now) where its core left 0.

        The end-to-end latency of this input set (``NodeStats.e2e_ms_*``) is
        the wall clock after the puts minus the outputs' ``source_wall_ns``
        (the earliest known one), when any output carries one.
        """
        wall_from = 0
        source = self.spec.kind == "source"
        trace = self._trace is not None
        self._out_times = {}
        for port, msg in result.outputs.items():
            if port not in self._publishers:
                raise RuntimeError(f"core returned output {port!r}, which {self.spec.stage} does not declare")
            want = self.spec.outputs[port].schema
            if not isinstance(msg, want):
                raise RuntimeError(f"core returned {type(msg).__name__} on {port!r}, declared {want.__name__}")
            header = getattr(msg, "header", None)
            if source and header is not None and not header.source_wall_ns:
                header = dataclasses.replace(header, source_wall_ns=time.time_ns())
                msg = dataclasses.replace(msg, header=header)
            enc0 = time.time_ns()
            data = msg.encode()
            if self.spec.outputs[port].latched:
                self._latched_out[port] = data
            enc1 = time.time_ns()
            self._publishers[port].put(data)
            if trace:
                self._out_times[port] = [enc0, enc1, time.time_ns()]
            self.stats.counters["published"] += 1
            if header is not None and header.source_wall_ns and not self.spec.outputs[port].latched:
                wall_from = min(wall_from or header.source_wall_ns, header.source_wall_ns)
        if wall_from:
            self.stats.e2e_ms.append((time.time_ns() - wall_from) / 1e6)
        self._last_wall_ns = wall_from
        for issue in result.issues:
            self.stats.counters["issues"] += 1
            self.stats.issues_by_kind[issue.kind] += 1
        # the frame the issues are about: the one published (grid_fusion publishes an older frame than the input that
        # ran it, or none: a clock tick, stamp 0); a call that published nothing while the node has outputs handled no
        # frame and ends no episode
        published = next((int(m.header.stamp_ns) for m in result.outputs.values() if getattr(m, "header", None) is not None), None)
        self.issue_log.frame(stamp_ns if published is None else published, result.issues,
                             closes=bool(result.outputs) or not self._publishers)
        self.stats.last_stamp_ns = max(self.stats.last_stamp_ns, stamp_ns)
        self.stats.counters["processed"] += 1
        self._progress_pub.put(
            Progress(node_id=self.node_id, last_stamp_ns=stamp_ns, last_frame_index=frame_index, handled=self.stats.counters["processed"]).encode()
        )

    def maybe_stats(self, force: bool = False) -> None:
        now = time.monotonic()
        if force or now - self._last_stats >= self.args.stats_period:
            self._last_stats = now
            if self._stats_pub is None:  # not opened (its session failed): nothing to publish on
                return
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
        return [p for p in self.input_keys if self.spec.inputs[p].joined]

    def _required_latched(self) -> list[str]:
        return [p for p in self.input_keys if self.spec.inputs[p].latched]

    def _handle_operator_item(self, core: Any, item: tuple) -> None:
        item = self._verified(item)  # queued undecoded by _accept unless its queue was full
        if item is None:
            return
        port, key, msg, recv_ns = item
        lat_ms = math.nan
        spec = self.spec.inputs[port]
        if spec.latched:
            self._latched_in[port] = msg
        elif spec.latest:
            self._latest_in[port] = msg
        elif spec.pattern is not None:
            if not self._keep_wildcard(port, key, msg):
                return
        else:
            header = getattr(msg, "header", None)
            stamp = int(header.stamp_ns) if header is not None else 0
            lat_ms = (recv_ns - stamp) / 1e6 if header is not None else math.nan
            now = time.monotonic()
            handled = self._handled.get(stamp)
            if handled is not None and port in handled[1] and now - handled[0] <= DUPLICATE_WINDOW_S and stamp not in self._pending:
                # its set, with this input, was handled a moment ago: a frame sent twice, not a new set (nor one to drop later)
                self._count("duplicate_inputs", port)
                self.problems.report(f"duplicate:{port}", logging.WARNING, "duplicate input: port=%s stamp_ns=%d (its input set was"
                                     " handled %.0f ms ago: ignored)", port, stamp, (now - handled[0]) * 1e3)
                return
            entry = self._pending.setdefault(stamp, {})
            self._pending_since.setdefault(stamp, now)
            self._port_seen[port] = now
            if self._trace is not None:
                self._hops.setdefault(stamp, {})[port] = [recv_ns, self._deq_ns, time.time_ns()]
            if port in entry:
                self._count("duplicate_inputs", port)
                self.problems.report(f"duplicate:{port}", logging.WARNING, "duplicate input: port=%s stamp_ns=%d (older one replaced)", port, stamp)
            entry[port] = msg
            self._maybe_prepare(core, stamp, entry)
        if not spec.joined and not spec.latched and not self._join_ports():
            # no joined input bound: every latest-value or wildcard message is an update
            if all(p in self._latched_in for p in self._required_latched()):
                header = getattr(msg, "header", None)
                self._run_update(core, self._not_joined_inputs(), int(header.stamp_ns) if header is not None else 0, lat_ms)
            return
        self._run_ready(core, lat_ms)
        self._expire_pending()

    def _maybe_prepare(self, core: Any, stamp: int, entry: dict[str, Message]) -> None:
        """Let a core that has ``prepare(inputs, missing)`` start on a set still missing some joined inputs.

        Called when a joined input adds to the newest pending set and it is still incomplete (with every latched
        input there); the core decides whether it can do anything yet (``markov_prediction`` runs its chain
        before the intentions stage's belief comes) and returns whether it did (counted, ``prepared``). Its
        ``update`` on the whole set follows as usual; a failure here is counted (``prepare_exception``) and
        costs nothing else: the update then does all the work itself.
        """
        prepare = getattr(core, "prepare", None)
        if prepare is None or stamp != max(self._pending):
            return
        missing = frozenset(p for p in self._join_ports() if p not in entry)
        if not missing or any(p not in self._latched_in for p in self._required_latched()):
            return
        inputs = dict(entry)
        inputs.update(self._not_joined_inputs())
        t0, start_ns = time.perf_counter(), time.time_ns()
        try:
            ran = prepare(inputs, missing)
        except Exception as exc:  # noqa: BLE001 - the update does the work then
            self._count_failure("prepare_exception", exc, "prepare failed on stamp_ns=%d (the whole set runs in update)", stamp)
            return
        if ran:
            self._count("prepared")
            self.stats.prep_ms.append((time.perf_counter() - t0) * 1e3)
            if self._trace is not None:
                self._prep_ns.setdefault(stamp, []).append([start_ns, time.time_ns()])

    def _keep_wildcard(self, port: str, key: str, msg: Message) -> bool:
        """File a wildcard input's message as its key's newest; a new key beyond the port's ``max_keys`` is dropped and counted."""
        latest = self._wild_in.setdefault(port, {})
        if key not in latest and len(latest) >= self.spec.inputs[port].max_keys:
            self._count("rejected_keys", port)
            self.problems.report(
                f"wildcard_keys:{port}",
                logging.WARNING,
                "dropped message: reason=too_many_keys port=%s key=%s (the port keeps at most %d keys)",
                port,
                key,
                self.spec.inputs[port].max_keys,
            )
            return False
        latest[key] = msg
        return True

    def _not_joined_inputs(self) -> dict[str, Any]:
        """What the core sees besides a joined set: latched and latest values, and a copy of each wildcard's ``{key: message}``."""
        out: dict[str, Any] = dict(self._latched_in)
        out.update(self._latest_in)
        for port, latest in self._wild_in.items():
            out[port] = MappingProxyType(dict(latest))
        return out

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
            self._handled[s] = (time.monotonic(), frozenset(inputs))
            self._handled.move_to_end(s)
            while len(self._handled) > DUPLICATE_MEMORY:
                self._handled.popitem(last=False)
            inputs.update(self._not_joined_inputs())
            self._run_update(core, inputs, s, lat_ms, self._hops.pop(s, None))

    def _drop_pending(self, stamp: int, reason: str) -> None:
        missing_latched = [p for p in self._required_latched() if p not in self._latched_in]
        if missing_latched:
            reason = f"waiting_for_latched ports={','.join(missing_latched)}"
        entry = self._pending.pop(stamp, None)
        self._pending_since.pop(stamp, None)
        self._hops.pop(stamp, None)
        self._prep_ns.pop(stamp, None)
        if entry is not None:
            self.stats.counters["join_drops"] += 1
            # what it waited for, and from whom (a stage stopped upstream was named nowhere: "had=" alone)
            lacked = ",".join(f"{p} (from {self.bindings.get(p, '?')})" for p in self._join_ports() if p not in entry)
            self.problems.report(
                f"join:{reason}", logging.WARNING, "dropped input set: reason=%s stamp_ns=%d had=%s lacked=%s", reason, stamp,
                ",".join(sorted(entry)), lacked or "-"
            )

    def _expire_pending(self) -> None:
        limit = max(2, getattr(self.args, "join_window", JOIN_WINDOW))
        while len(self._pending) > limit:
            self._drop_pending(next(iter(self._pending)), "join_window_full")
        if len(self.queue):
            # inputs still queued may complete a set: time spent in the core is not time the set waited
            # for a missing input, so the timeout is judged only once everything received is joined
            return
        if any(p not in self._latched_in for p in self._required_latched()):
            # every set waits for a latched input that has not come yet (the scene a frame overtook on the wire, or
            # one still being queried): it is coming, not silent; the join window alone bounds the wait
            return
        now = time.monotonic()
        join = self._join_ports()
        for s in [s for s, t in self._pending_since.items() if now - t > JOIN_TIMEOUT_S]:
            # a missing input that is still arriving (for other stamps) is behind, not gone: its set waits for it
            # (bounded by the join window; an older set is superseded once a newer one completes); only a set whose
            # missing inputs have all been silent for the timeout is dropped
            missing = [p for p in join if p not in self._pending.get(s, {})]
            if any(now - self._port_seen.get(p, self._pending_since[s]) <= JOIN_TIMEOUT_S for p in missing):
                continue
            self._drop_pending(s, "join_timeout")

    def _run_update(self, core: Any, inputs: dict[str, Message], stamp: int, lat_ms: float, hops: dict[str, list[int]] | None = None) -> None:
        start_ns, cpu0 = time.time_ns(), time.thread_time_ns()
        t0 = time.perf_counter()
        try:
            result = core.update(inputs)
        except Exception as exc:
            self._count_failure("core_exception", exc, "core failed on stamp_ns=%d (input set dropped)", stamp)
            return
        dt = (time.perf_counter() - t0) * 1e3
        end_ns, cpu_ms = time.time_ns(), (time.thread_time_ns() - cpu0) / 1e6
        self.stats.proc_ms.append(dt)
        self.stats.proc_ms_max = max(self.stats.proc_ms_max, dt)
        if not math.isnan(lat_ms):
            self.stats.latency_ms.append(lat_ms + dt)
        frame_index = _frame_index_of(inputs)
        try:
            self.publish(result, stamp, frame_index)
        except Exception as exc:  # an output that does not encode: that input set is lost, the stage goes on
            self._count_failure("publish_exception", exc, "publishing failed on stamp_ns=%d (outputs of this input set dropped)", stamp)
            return
        if self._trace is not None:
            record = {"stamp": stamp, "frame": frame_index, "wall": self._last_wall_ns, "in": hops or {}, "start": start_ns, "end": end_ns,
                      "cpu_ms": round(cpu_ms, 3), "gc_ms": round((self._trace.gc.pause_ns - self._deq_gc_ns) / 1e6, 3), "out": self._out_times}
            prep = self._prep_ns.pop(stamp, None)
            if prep is not None:
                record["prep"] = prep
            self._trace.write(record)

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

    def _awaited(self) -> list[str]:
        """The nodes of ``--await-nodes``: their liveliness tokens must be visible before this node publishes."""
        return [n for n in getattr(self.args, "await_nodes", "").split(",") if n]

    def run_operator(self, core: Any) -> None:
        # before the first input set is handled: what it publishes reaches only the subscriptions this session sees (inputs
        # that arrive meanwhile wait in the queues)
        self.consumers.await_nodes(self._awaited(), AWAIT_NODES_S, self.stop_event, self.log, tick=self.maybe_stats)
        self._serve(lambda item: self._handle_operator_item(core, item), getattr(core, "idle", None))

    def run_raw_sink(self, core: Any) -> None:
        acked = False
        window_ns = self._stamp_window_ns

        def handle(item: tuple) -> None:
            nonlocal acked
            port, key, data, recv_ns = item
            t0 = time.perf_counter()
            try:
                issues = core.handle(key, data, recv_ns) or []
            except Exception as exc:
                self._count_failure("core_exception", exc, "sink failed on key=%s (message dropped)", key)
                return
            if port == LATCHED_QUERY:  # an old value asked for at the start: recorded, not progress (no ack, no latency)
                return
            dt = (time.perf_counter() - t0) * 1e3
            self.stats.proc_ms.append(dt)
            self.stats.proc_ms_max = max(self.stats.proc_ms_max, dt)
            self.stats.counters["processed"] += 1
            stamp, wall = _peek_stamps(data)
            if wall:  # a sink publishes nothing: end to end is to its receipt
                self.stats.e2e_ms.append((recv_ns - wall) / 1e6)
                if self._trace is not None:
                    self._trace.write({"key": key, "stamp": stamp, "wall": wall, "recv": recv_ns, "deq": self._deq_ns, "end": time.time_ns()})
            went_back = stamp is not None and acked and stamp < self.stats.last_stamp_ns - window_ns
            if stamp is not None and (stamp > self.stats.last_stamp_ns or not acked or went_back):
                # the first stamp too, even 0 (a recording's first frame): a source's warm-up waits for every node's ack
                # of it; and a clock that went back by more than the stamp window (a source restarted on an earlier
                # clock), whose frames would otherwise never be acked: its warm-up and drain waited on the sink
                acked = True
                self.stats.last_stamp_ns = stamp if went_back else max(stamp, self.stats.last_stamp_ns)
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

    def _serve(self, handle: Callable[[tuple], None], idle: Callable[[], None] | None = None) -> None:
        """The loop: handle each queued item; ``idle`` (a core's, where it has one) whenever one leaves the queues empty
        and no input set waiting for the rest of its inputs."""
        quiet_s = DRAIN_QUIET_S
        while True:
            item = self.queue.get(timeout=0.05)
            if item is not None:
                self._deq_ns = time.time_ns()
                if self._trace is not None:
                    self._deq_gc_ns = self._trace.gc.pause_ns
            drained = item is None or not (item[0] is None or item[0] in self._drain_ports)
            if not drained:
                now = time.monotonic()
                if self._silent_since is not None:  # the inputs are back
                    self.log.info("inputs resumed after %.0f s of silence", now - self._silent_since)
                    self._silent_since = None
                self._last_input_mono = now
                self._had_input = True
            elif self._had_input and self._silent_since is None and not self.stop_event.is_set() \
                    and time.monotonic() - self._last_input_mono >= SILENT_AFTER_S:
                # a tracker, source or upstream stage that stopped (killed, hung, its link lost): once, not per frame
                self._silent_since = self._last_input_mono
                self.stats.counters["input_silences"] += 1
                # INFO, not a warning: a recording's own gap in its stamps is silence too (the embedded K733 scenario
                # has 15 s without a frame), and then nothing is wrong
                self.log.info("no input for %.0f s (inputs: %s): a gap in the recording, or its publisher stopped, hung or lost its link",
                              SILENT_AFTER_S, ",".join(sorted(self.input_keys.values())) or "the run's keys")
            if item is not None:
                try:
                    handle(item)
                except Exception as exc:  # the last net: one message never ends the stage
                    self._count_failure("handler_exception", exc, "handling a message from key=%s failed (dropped)", item[1])
                if idle is not None and not len(self.queue) and not self._pending:
                    # work the core keeps off its frames' path (markov_prediction's back test), now that nothing is queued
                    # and no input set is partly in (it would hold up that set's last input)
                    try:
                        idle()
                    except Exception as exc:  # noqa: BLE001
                        self._count_failure("idle_exception", exc, "the core's idle work failed after key=%s", item[1])
                self._maybe_refreeze()
            else:
                self._expire_pending()
            self.maybe_stats()
            if self.stop_event.is_set() and drained and not any(self.queue.depth(p) for p in self._drain_ports | {None}):
                # nothing of the inputs a stop waits for is queued (latest-value and wildcard messages may still come)
                if self.signals > 1 or time.monotonic() - self._last_input_mono >= quiet_s:
                    break

    def _maybe_refreeze(self) -> None:
        """After the first ``GC_FREEZE_AFTER`` handled input sets, freeze what the warm-up built (caches, compiled kernels) too."""
        if self._gc_refreeze_at and self.stats.counters["processed"] >= self._gc_refreeze_at:
            self._gc_refreeze_at = 0
            gc.freeze()  # no collection first: that would pause this frame; a few cycles of warm-up garbage stay, once
            self.log.debug("gc: froze %d objects after the warm-up", gc.get_freeze_count())

    # ---- source loop
    def run_source(self, core: Any) -> None:
        """Publish what the core yields, paced (``pacing.Pacer``: the stamps at ``speed`` times their rate, or ``max``)."""
        speed = getattr(self.config, "speed", 1.0)
        try:
            pacer = Pacer(speed, self.consumers, self.stop_event, self.log, warmup=SOURCE_WARMUP)
        except ValueError as exc:
            raise ConfigError(str(exc)) from None
        self.consumers.await_nodes(self._awaited(), AWAIT_NODES_S, self.stop_event, self.log, tick=self.maybe_stats)
        n = 0
        for stamp, result in core:
            if not pacer.before(stamp, stamp):
                break
            t0 = time.perf_counter()
            frame_index = _frame_index_of(result.outputs)
            gc0 = self._trace.gc.pause_ns if self._trace is not None else 0
            self.publish(result, stamp, frame_index)
            self.stats.proc_ms.append((time.perf_counter() - t0) * 1e3)
            if self._trace is not None:
                self._trace.write({"stamp": stamp, "frame": frame_index, "wall": self._last_wall_ns, "gc_ms": round((self._trace.gc.pause_ns - gc0) / 1e6, 3),
                                   "out": self._out_times})
            n += 1
            self._maybe_refreeze()
            self.maybe_stats()
        else:
            self.log.info("source finished: frames=%d", n)
        self.maybe_stats(force=True)
        # Let every live node confirm the last frame before the session closes: a put
        # still queued in the session would otherwise be lost with it.
        pacer.drain(CONSUMER_WAIT_S if pacer.as_fast else DRAIN_WAIT_S, abort=lambda: self.signals > 1)

    def close(self) -> None:
        if self._trace is not None:
            self._trace.close()
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
#: Joined messages in a row, stamped beyond the stamp window and following one another, after which a node follows
#: their clock (``Node._stamp_ok``): 2 s of a 10 Hz source's frames.
STAMP_JUMP_AFTER = 20
#: Incomplete input sets an operator keeps waiting (the oldest is dropped beyond, ``join_window_full``): 64 frames
#: = 6.4 s at 10 Hz, so that an input lagging by a few seconds on a loaded machine costs latency, not frames.
JOIN_WINDOW = 64
#: A joined message whose stamp's input set was handled at most this long ago is a duplicate (a tracker or a link that
#: sends a frame twice): counted as ``duplicate_inputs`` and ignored, where it used to open a set that was then
#: dropped (``join_drops``, "superseded") although its frame was predicted. Later, the same stamp is a new set (a
#: source restarted on the same clock).
DUPLICATE_WINDOW_S = 2.0
#: How many handled stamps a node remembers for that
DUPLICATE_MEMORY = 64
DRAIN_QUIET_S = 0.3
CLOSE_LINGER_S = 0.05


#: Set to 0 (or off, no, false) to keep Python's collector as it is (``gc_freeze``): for comparisons.
GC_FREEZE_ENV = "IAMP_GC_FREEZE"
#: Handled input sets after which a node freezes the collector's generations once more (the warm-up's objects).
GC_FREEZE_AFTER = 20


def gc_freeze_enabled(log: logging.Logger | None = None) -> bool:
    """Whether nodes freeze the collector (``IAMP_GC_FREEZE``: unset, 1, on, yes, true: yes; 0, off, no, false: no; else yes, logged)."""
    value = os.environ.get(GC_FREEZE_ENV, "").strip().lower()
    if value in ("", "1", "on", "yes", "true"):
        return True
    if value in ("0", "off", "no", "false"):
        return False
    if log is not None:
        log.warning("%s=%r is not one of 1/on/yes/true or 0/off/no/false: freezing the collector (the default)", GC_FREEZE_ENV, value)
    return True


def gc_freeze() -> int:
    """Collect once, then move every object tracked so far to the collector's permanent generation; returns how many.

    A long-running node holds a large heap of long-lived objects (modules,
    torch and numba, the map, the model): without this, each full (gen 2)
    collection walks all of it, measured at 100-1,044 ms per pause, 3-9 per
    node in a minute of the streaming pipeline at 18 vehicles
    (``bench/e2e_latency.py``'s GC table; 0.2-33 ms frozen), and a frame
    that meets one waits that long, then the frames queued behind it. Frozen objects are never scanned again (nor collected: a node
    freezes what it keeps for the whole run). Called before the node opens
    its session (nothing is waiting on it yet) and once more, without the
    collection, after its first ``GC_FREEZE_AFTER`` input sets.
    """
    gc.collect()
    gc.freeze()
    return gc.get_freeze_count()


def _peek_stamps(data: bytes) -> tuple[int | None, int]:
    """``header.stamp_ns`` (None if none) and ``header.source_wall_ns`` (0 if none) of a payload (no full decode)."""
    try:
        _schema, _v, header = peek_header(data)
        header = header if header is not None else {}
        stamp, wall = header.get("stamp_ns"), header.get("source_wall_ns", 0)
    except (SchemaError, AttributeError):
        return None, 0
    return (stamp if type(stamp) is int else None), (wall if type(wall) is int and wall > 0 else 0)


# The queue's port of a raw sink's answers to its start query for latched values (``Node._query_latched_raw``).
LATCHED_QUERY = "_latched_query"
# The pauses before each of that query's tries (s), until one is answered: a run with no latched value yet costs 6 tries.
LATCHED_QUERY_WAITS_S = (0.0, 0.5, 1.0, 1.5, 2.0, 4.0)
# A jump of the frame index this large or larger is no run of lost frames but another numbering (not counted).
MAX_FRAME_GAP = 100_000
# How long after its start a node told to --connect may be without any link before it says so.
LINK_CHECK_S = 5.0
# Inputs that flowed and then stopped for this long are reported once (and their return); longer than a run's drain.
SILENT_AFTER_S = 10.0


def _frame_index_of(messages: Mapping[str, Any]) -> int:
    for m in messages.values():
        h = getattr(m, "header", None)
        if h is not None:
            return int(h.frame_index)
    return -1


def run_stage(spec: StageSpec, argv: list[str] | None = None) -> int:
    """Parse the command line, build config and core, run until stopped.

    Returns the process exit code: 0 clean stop, 1 crash, 2 bad command line
    or config.
    """
    start = start_stage(spec, argv)
    if isinstance(start, int):
        return start
    args, config, log = start.args, start.config, start.log
    node = Node(spec, args, config, args.bindings)

    def on_signal(signum: int) -> None:
        node.signals += 1
        node.stop_event.set()
        if node.signals == 1:
            log.info("stop requested: signal=%s, draining", signal.Signals(signum).name)

    on_stop_signals(on_signal)
    ctx = NodeContext(
        run_id=args.run_id, node_id=args.node_id, stage=spec.stage, log=log, input_keys=node.input_keys, output_keys=node.output_keys
    )
    try:
        try:
            core = spec.make_core(config, ctx)
        except (ConfigError, FileNotFoundError, ValueError) as exc:
            log.error("bad configuration: %s", exc)
            return EXIT_USAGE
        if node._gc_refreeze_at:
            gc_freeze()
        try:
            node.open()
        except BaseException:
            abandon = getattr(core, "abandon", None)  # a core that made files (the recorder) removes what holds nothing
            if abandon is not None:
                abandon()
            raise
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
    end_failure = getattr(core, "end_failure", None)  # a core that went on after losing its purpose (the recorder, a full disk)
    failure = end_failure() if end_failure is not None else None
    if failure:
        log.error("failed: %s", failure)
        return EXIT_CRASH
    return EXIT_OK


def run_closing_stage(spec: StageSpec, argv: list[str] | None = None) -> int:
    """``run_stage`` for a sink whose core holds a server and threads (the viewer, the Foxglove bridge).

    ``spec.make_core`` takes a third argument, a list: it appends what it
    opened as soon as it is made (before starting it), and everything appended
    is closed, newest first, when the stage ends, however it ends.
    """
    opened: list = []
    make = spec.make_core
    try:
        return run_stage(dataclasses.replace(spec, make_core=lambda config, ctx: make(config, ctx, opened)), argv)
    finally:
        for item in reversed(opened):
            item.close()
