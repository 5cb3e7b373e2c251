"""Pacing of what a source publishes: at the recording's rate times ``speed``, or (``speed = "max"``) as fast as every live node acks.

One implementation for the runtime's sources (``Node.run_source``) and for
replay (``stages.replay``):

- ``Consumers`` follows the run's liveliness tokens (``iamp/<run>/_alive/*``)
  and the ``Progress`` every node publishes at ``iamp/<run>/_ack/<node>``
  after each handled input set (the newest acked stamp per node; a node
  whose token goes away is forgotten). It is fed by callbacks, so it does not
  care whose session they come from; ``await_nodes`` waits until given
  nodes are visible (a put made before a consumer's subscription is visible
  is routed to nobody and lost).
- ``Pacer.before(time_ns, stamp_ns)`` is called before each publish. With
  a number it sleeps until ``time_ns`` (the recording's clock: the header
  stamp for a source, the receive time for replay) is due at ``speed``
  times the recording's rate. With ``max`` it keeps at most ``window``
  (``MAX_SPEED_WINDOW``) distinct header stamps ahead of every other live
  node: before a new stamp goes out, each must have acked the stamp
  ``window`` stamps back. A node behind for ``wait_s`` (``CONSUMER_WAIT_S``)
  is warned about and not waited for until it acks again; a node that has
  acked nothing ``first_ack_grace_s`` after the first wait (default: the same
  ``wait_s``) is taken for one that never acks and is not waited for until
  it does, unless it is one of ``expected`` (the nodes a source was told to
  await: a pipeline's nodes all ack), which are waited for ``wait_s``.
  ``drain`` waits until the nodes have acked the last stamp published
  (zenoh has no flush: a put still queued when the session closes is
  lost). With ``warmup = N`` (the runtime's sources: ``SOURCE_WARMUP``)
  a number speed first publishes N stamps as ``max`` with a window of 1
  does (each acked by every live node, or given up on after ``wait_s``),
  then starts its clock: a node's first input set builds its caches and
  compiled kernels (measured 100-440 ms per stage at 18 vehicles), and at
  real time the frames published meanwhile would queue behind it all along
  the chain, seconds of backlog that a stage near its frame budget takes
  a long time to work off.
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from typing import Callable, Iterable

from bus_schemas import Progress, SchemaError

MAX_SPEED_WINDOW = 3
CONSUMER_WAIT_S = 10.0
DRAIN_WAIT_S = 3.0
AWAIT_NODES_S = 30.0
FIRST_ACK_GRACE_S = 2.0  # replay's grace for nodes that never ack (tools holding a token)
SOURCE_WARMUP = 1  # stamps a runtime source publishes and awaits before its real-time clock starts (Pacer's warmup)


def parse_speed_value(speed: float | str) -> float | str:
    """``"max"`` or a number > 0 (raises ``ValueError`` otherwise)."""
    if isinstance(speed, str):
        if speed == "max":
            return "max"
        raise ValueError(f"speed must be a number > 0 or 'max', got {speed!r}")
    speed = float(speed)
    if not speed > 0:
        raise ValueError(f"speed must be a number > 0 or 'max', got {speed}")
    return speed


class Consumers:
    """The live nodes of a run and the newest stamp each has acked (fed from any thread)."""

    def __init__(self, self_id: str = "") -> None:
        self.self_id = self_id
        self._lock = threading.Lock()
        self._acks: dict[str, int] = {}
        self._alive: set[str] = set()
        self._ignored: set[str] = set()  # not waited for until they ack again

    # ---- feeding (callbacks)
    def on_ack_payload(self, data: bytes) -> None:
        try:
            msg = Progress.decode(data)
        except SchemaError:
            return
        self.on_ack(msg.node_id, msg.last_stamp_ns)

    def on_ack(self, node_id: str, stamp_ns: int) -> None:
        with self._lock:
            self._acks[node_id] = max(self._acks.get(node_id, stamp_ns), stamp_ns)
            self._ignored.discard(node_id)

    def on_alive(self, node_id: str, alive: bool) -> None:
        with self._lock:
            if alive:
                self._alive.add(node_id)
            else:
                self._alive.discard(node_id)
                self._acks.pop(node_id, None)
                self._ignored.discard(node_id)

    def add_alive(self, node_ids: Iterable[str]) -> None:
        with self._lock:
            self._alive |= set(node_ids)

    # ---- reading
    def alive(self) -> set[str]:
        with self._lock:
            return set(self._alive)

    def waiting_on(self, target: int) -> tuple[list[str], list[str]]:
        """``(silent, behind)``: live others not ignored that have acked nothing, or less than ``target``."""
        with self._lock:
            others = self._alive - self._ignored - {self.self_id}
            silent = sorted(n for n in others if n not in self._acks)
            behind = sorted(n for n in others if n in self._acks and self._acks[n] < target)
        return silent, behind

    def ignore(self, node_ids: Iterable[str]) -> None:
        with self._lock:
            self._ignored |= set(node_ids)

    def await_nodes(self, node_ids: Iterable[str], timeout_s: float, stop: threading.Event, log: logging.Logger | None = None,
                    tick: Callable[[], None] | None = None) -> list[str]:
        """Wait until ``node_ids`` are all alive (or ``stop``, or ``timeout_s``); returns the ones still missing (warned about).
        ``tick`` is called as it waits (the node's ``maybe_stats``: a waiting node still reports what it received)."""
        wanted = set(node_ids)
        if not wanted:
            return []
        deadline = time.monotonic() + timeout_s
        while True:
            missing = sorted(wanted - self.alive())
            if not missing or stop.is_set():
                return missing
            if time.monotonic() > deadline:
                if log is not None:
                    # (at a first start on a machine the stages compile their kernels, a minute or more on 2 cores: not a fault)
                    log.warning("start: %s not up after %.0f s (still starting, or not there); not waiting longer: what this node"
                                " publishes before they are up does not reach them", ",".join(missing), timeout_s)
                return missing
            if tick is not None:
                tick()
            stop.wait(0.005)


class Pacer:
    """Paces one source's publishes (module docstring); ``before`` returns False once ``stop`` is set."""

    def __init__(
        self,
        speed: float | str,
        consumers: Consumers | None,
        stop: threading.Event,
        log: logging.Logger,
        *,
        window: int = MAX_SPEED_WINDOW,
        wait_s: float = CONSUMER_WAIT_S,
        first_ack_grace_s: float | None = None,
        warmup: int = 0,
        expected: Iterable[str] = (),
    ) -> None:
        self.speed = parse_speed_value(speed)
        self.as_fast = self.speed == "max"
        self.consumers = consumers
        self.stop = stop
        self.log = log
        self.window = max(1, window)
        self.wait_s = wait_s
        self.first_ack_grace_s = wait_s if first_ack_grace_s is None else first_ack_grace_s
        self.expected = frozenset(expected)  # nodes known to ack (a pipeline's): their grace is ``wait_s``
        self._stamps: collections.deque[int] = collections.deque(maxlen=self.window)
        self._wall0: float | None = None
        self._time0 = 0
        self._first_wait: float | None = None
        self.warmup = max(0, int(warmup))
        self._published = 0  # distinct stamps let out so far

    def before(self, time_ns: int, stamp_ns: int | None = None) -> bool:
        """Wait until the next message (recording time ``time_ns``, header stamp ``stamp_ns`` or None) may go out."""
        if self.stop.is_set():
            return False
        new_stamp = stamp_ns is not None and not (self._stamps and self._stamps[-1] == stamp_ns)
        if not self.as_fast:
            if new_stamp and self._published and self._published <= self.warmup:
                # warming up: every live node must have handled the last stamp, then the clock (re)starts at this message
                self._wait(self._stamps[-1], time.monotonic() + self.wait_s, self.stop.is_set)
                self._wall0 = None
            if self._wall0 is None:
                self._wall0, self._time0 = time.monotonic(), time_ns
            due = self._wall0 + (time_ns - self._time0) / 1e9 / self.speed
            while not self.stop.is_set():
                left = due - time.monotonic()
                if left <= 0:
                    break
                self.stop.wait(min(left, 0.1))
        if new_stamp:  # (drain waits for the last)
            if self.as_fast and len(self._stamps) >= self.window:
                self._wait(self._stamps[0], time.monotonic() + self.wait_s, self.stop.is_set)
            if self.stop.is_set():
                # stopped while this stamp waited: it is not published, so drain waits for the last one that was,
                # not for acks of a frame nobody receives
                return False
            self._stamps.append(stamp_ns)
            self._published += 1
        return not self.stop.is_set()

    def drain(self, timeout_s: float | None = None, abort: Callable[[], bool] | None = None) -> None:
        """Wait (at most ``timeout_s``, default ``wait_s``) until the live nodes have acked the last stamp; ``abort`` ends it early."""
        if self._stamps:
            self._wait(self._stamps[-1], time.monotonic() + (timeout_s or self.wait_s), abort or (lambda: False), timeout_s or self.wait_s,
                       at_end=True)

    def _wait(self, target: int, deadline: float, abort: Callable[[], bool], wait_s: float | None = None, at_end: bool = False) -> None:
        if self.consumers is None:
            return
        now = time.monotonic()
        if self._first_wait is None:
            self._first_wait = now
        while not abort():
            silent, behind = self.consumers.waiting_on(target)
            now = time.monotonic()
            if silent and now - self._first_wait > self.first_ack_grace_s:
                # a node expected to ack is waited for as long as one behind (a first input set that builds caches
                # and compiles kernels can take seconds); any other is taken for a tool that never acks
                tools = [n for n in silent if n not in self.expected]
                if tools:
                    self.log.info("pacing: not waiting for nodes that report no progress: %s", ",".join(tools))
                    self.consumers.ignore(tools)
                silent = [n for n in silent if n in self.expected]
            if not silent and not behind:
                return
            if now > deadline:
                if at_end:  # the play's end (drain), not pacing: said as such (it read as a pacing failure)
                    self.log.info("end of play: nodes still behind after %.1f s: %s; the source stops waiting (they handle what"
                                  " they have queued as they stop)", wait_s or self.wait_s, ",".join(behind + silent))
                else:
                    self.log.warning("pacing: nodes behind after %.1f s, no longer waiting for them until they ack: %s",
                                     wait_s or self.wait_s, ",".join(behind + silent))
                self.consumers.ignore(behind + silent)
                return
            time.sleep(0.002)
