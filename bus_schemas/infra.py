"""Infrastructure messages published by the runtime of every node."""

from __future__ import annotations

from dataclasses import dataclass
import math
from typing import Any, ClassVar

from ._wire import Message, register


@register
@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class NodeStats(Message):
    """Periodic counters of a node, on ``iamp/<run>/_stats/<node>``.

    ``counters`` holds at least received, processed, published, decode_errors,
    join_drops, queue_drops and issues; ``issues_by_kind`` and
    ``errors_by_kind`` break the totals down. Processing times are per handled
    input set, in milliseconds, over the whole run.

    ``latency_ms_*``: receive time of the joined input minus its header's
    ``stamp_ns``, plus the processing time: meaningful only where stamps are
    wall-clock times (a live tracker); for recorded data it is the age of the
    recording. ``e2e_ms_*`` (v2): end to end, from the source's publish
    (``Header.source_wall_ns``) to this node's publish of its output (a sink:
    to its receipt of a message), in milliseconds over the node's last
    ``E2E_WINDOW`` outputs with a known wall stamp; NaN when none had one (an
    old recording replayed).
    """

    SCHEMA: ClassVar[str] = "iamp.NodeStats"
    VERSION: ClassVar[int] = 2  # v2: e2e_ms_p50, e2e_ms_p95
    UPGRADES: ClassVar[dict[int, Any]] = {1: lambda body: _add_e2e(body)}  # v1 reads as v2 with e2e NaN (unknown)
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
    e2e_ms_p50: float = math.nan
    e2e_ms_p95: float = math.nan


def _add_e2e(body: Any) -> Any:
    if isinstance(body, dict) and "e2e_ms_p50" not in body and "e2e_ms_p95" not in body:
        return {**body, "e2e_ms_p50": math.nan, "e2e_ms_p95": math.nan}
    return body


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
