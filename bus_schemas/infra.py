"""Infrastructure messages published by the runtime of every node."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from ._wire import Message, register


@register
@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class NodeStats(Message):
    """Periodic counters of a node, on ``iamp/<run>/_stats/<node>``.

    ``counters`` holds at least received, processed, published, decode_errors,
    join_drops, queue_drops and issues; ``issues_by_kind`` and
    ``errors_by_kind`` break the totals down. Processing times are per handled
    input set, in milliseconds, over the whole run.
    """

    SCHEMA: ClassVar[str] = "iamp.NodeStats"
    VERSION: ClassVar[int] = 1
    # counters by kind (measured 413 B)
    MAX_BYTES: ClassVar[int] = 64 * 1024

    run_id: str
    node_id: str
    stage: str
    pid: int
    uptime_s: float
    counters: dict[str, int]
    issues_by_kind: dict[str, int]
    errors_by_kind: dict[str, int]
    proc_ms_p50: float
    proc_ms_p95: float
    proc_ms_max: float
    latency_ms_p50: float
    latency_ms_p95: float
    queue_depth: int
    last_stamp_ns: int


@register
@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class Progress(Message):
    """The last source stamp a node has finished with, on ``iamp/<run>/_ack/<node>``.

    Sources pacing at ``speed = max`` and the end-of-run drain wait on these.
    """

    SCHEMA: ClassVar[str] = "iamp.Progress"
    VERSION: ClassVar[int] = 1
    # a node id and three ints (measured 99 B)
    MAX_BYTES: ClassVar[int] = 64 * 1024

    node_id: str
    last_stamp_ns: int
    last_frame_index: int
    handled: int
