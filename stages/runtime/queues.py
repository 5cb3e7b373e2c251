"""The per-input bounded queues between the subscriber callbacks and the node's single loop."""

from __future__ import annotations

import collections
import threading
import time
from typing import Any, Callable


class InputQueue:
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

    With ``max_age_s`` > 0 the entries of the ``ageing`` ports are also
    bounded in age: ``get`` drops an entry that has waited longer than that in
    the queue (``time.monotonic`` from its ``put``) and calls
    ``on_stale(port, nbytes, item)``, as long as a newer entry of the same port
    is queued (the newest of a port is always handed out, so a stage that is
    slower than its input still works on its freshest frames). A live
    pipeline's stage that falls behind then skips to recent frames instead of
    working through seconds of old ones; ``queue_size`` alone bounds the
    backlog only in frames.
    """

    def __init__(self, maxlen: int, on_drop: Callable[[Any, int], None], block: bool = False, max_bytes: int = 0,
                 max_age_s: float = 0.0, ageing: frozenset | set = frozenset(), on_stale: Callable[[Any, int, Any], None] | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
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
        self._max_age_s = float(max_age_s) if max_age_s and max_age_s > 0 and not block else 0.0
        self._ageing = frozenset(ageing)
        self._on_stale = on_stale
        self._clock = clock

    def _full(self, port: Any, nbytes: int) -> bool:
        dq = self._q.get(port)
        if not dq:
            return False  # one entry always fits, however large (its size was bounded by its schema)
        return len(dq) >= self._maxlen or (self._max_bytes > 0 and self._bytes[port] + nbytes > self._max_bytes)

    def full(self, port: Any, nbytes: int) -> bool:
        """Whether putting ``nbytes`` on ``port`` now would drop (or, blocking, wait for) an older entry."""
        with self._cv:
            return self._full(port, nbytes)

    def verify(self, port: Any, check: Callable[[Any], Any | None]) -> None:
        """Pass every entry of ``port`` through ``check``: None drops it (malformed), anything else replaces it."""
        with self._cv:
            dq = self._q.get(port)
            if not dq:
                return
            kept: collections.deque = collections.deque()
            for seq, item, nbytes, put_s in dq:
                new = check(item)
                if new is None:
                    self._bytes[port] -= nbytes
                    self._len -= 1
                else:
                    kept.append((seq, new, nbytes, put_s))
            self._q[port] = kept

    def put(self, item: Any, port: Any = None, nbytes: int = 0) -> None:
        with self._cv:
            if self._block:
                while self._full(port, nbytes) and not self.closed:
                    self._cv.wait(0.1)
            else:
                while self._full(port, nbytes):
                    _seq, old, old_bytes, _put_s = self._q[port].popleft()
                    self._bytes[port] -= old_bytes
                    self._len -= 1
                    self._on_drop(port, old_bytes, old)
            self._seq += 1
            self._q.setdefault(port, collections.deque()).append((self._seq, item, nbytes, self._clock() if self._max_age_s else 0.0))
            self._bytes[port] += nbytes
            self._len += 1
            self._cv.notify_all()

    def get(self, timeout: float) -> Any | None:
        with self._cv:
            if not self._len:
                self._cv.wait(timeout)
            while self._len:
                port = min((p for p, dq in self._q.items() if dq), key=lambda p: self._q[p][0][0])
                dq = self._q[port]
                _seq, item, nbytes, put_s = dq.popleft()
                self._bytes[port] -= nbytes
                self._len -= 1
                if self._block:
                    self._cv.notify_all()
                if self._max_age_s and dq and port in self._ageing and self._clock() - put_s > self._max_age_s:
                    if self._on_stale is not None:  # (a newer entry of the port is queued: this one is skipped)
                        self._on_stale(port, nbytes, item)
                    continue
                return item
            return None

    def depth(self, port: Any) -> int:
        dq = self._q.get(port)
        return len(dq) if dq else 0

    def __len__(self) -> int:
        return self._len
