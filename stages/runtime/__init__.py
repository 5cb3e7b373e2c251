"""The stage runtime: the only package of hybrid-iamp that imports zenoh.

A stage is a config dataclass, a pure core and a thin binding that hands both,
with its ports, to ``run_stage``. The runtime owns everything else, by module:

- ``ports.py``: ``Port`` (joined, latched, latest-value and wildcard inputs;
  latched outputs), ``StageSpec``, ``NodeContext`` and the core protocols;
- ``args.py``: the command line every stage shares, the start-up
  (``start_stage``: flags, parameters, bindings, logging) and the Zenoh
  session (peer mode on ``tcp/127.0.0.1``, multicast scouting off, explicit
  endpoints; ``--mode/--connect/--listen/--config`` to join a remote router);
- ``node.py``: the node (liveliness token at ``iamp/<run>/_alive/<node>``,
  decoding (in the loop; on the subscriber thread when an input queue is full), the stamp join, the core, publishing,
  ``NodeStats`` at ``_stats/<node>`` and ``Progress`` at ``_ack/<node>``, the
  clean stop) and ``run_stage``;
- ``queues.py``: one bounded queue per input port, drained in arrival order;
- ``logs.py``: the counters of ``NodeStats`` and the readable logs
  (``IssueLog`` episodes, rate-limited ``ProblemLog``); ``StatsReporter``, the
  same ``NodeStats`` for a node with a loop of its own (replay);
- ``pacing.py``: pacing of sources and replay (recording rate times
  ``speed``, or ``max``: as fast as every live node acks; a source first
  waits until every node has handled its first frame: the warm-up);
- ``trace.py``: the per-hop trace behind ``IAMP_HOP_TRACE`` (one JSON line
  per handled input set: receipt, queue, decode, core, encode, put, GC
  pauses), read by ``bench/e2e_latency.py``;
- ``bus.py``: ``BusClient``, a plain session for tools that are not stages;
- ``pipeline.py`` (pipeline TOML) and ``launcher.py`` (the launcher).

Every node freezes Python's garbage collector's generations before it opens
its session and once more after its first input sets (``node.gc_freeze``;
``IAMP_GC_FREEZE=0`` leaves the collector as it is): a full collection then
no longer walks the node's long-lived heap (modules, torch, numba, map,
model), measured at 100-470 ms per pause before.

No payload can end a stage: whatever does not decode, is out of range or
makes a core raise is counted, dropped and logged rate-limited. Exit codes:
0 (clean), 1 (crash), 2 (bad command line or config).
"""

from __future__ import annotations

from stages.runtime.args import (
    DEFAULT_LISTEN,
    EXIT_CRASH,
    EXIT_OK,
    EXIT_USAGE,
    StageStart,
    add_network_args,
    build_parser,
    make_zenoh_config,
    on_stop_signals,
    open_session,
    parse_bindings,
    parse_set,
    session_from_args,
    setup_logging,
    start_stage,
)
from stages.runtime.bus import BusClient
from stages.runtime.logs import IssueLog, ProblemLog, StatsReporter
from stages.runtime.node import CLOSE_LINGER_S, DRAIN_QUIET_S, JOIN_TIMEOUT_S, JOIN_WINDOW, MiB, Node, StopRequested, run_closing_stage, run_stage
from stages.runtime.pacing import AWAIT_NODES_S, CONSUMER_WAIT_S, DRAIN_WAIT_S, MAX_SPEED_WINDOW, Consumers, Pacer
from stages.runtime.ports import WILDCARD_MAX_KEYS, NodeContext, OperatorCore, Port, RawSinkCore, SourceCore, StageSpec
from stages.runtime.queues import InputQueue

__all__ = [
    "AWAIT_NODES_S",
    "BusClient",
    "CLOSE_LINGER_S",
    "CONSUMER_WAIT_S",
    "Consumers",
    "DEFAULT_LISTEN",
    "DRAIN_QUIET_S",
    "DRAIN_WAIT_S",
    "EXIT_CRASH",
    "EXIT_OK",
    "EXIT_USAGE",
    "InputQueue",
    "IssueLog",
    "JOIN_TIMEOUT_S",
    "JOIN_WINDOW",
    "MAX_SPEED_WINDOW",
    "MiB",
    "Node",
    "NodeContext",
    "OperatorCore",
    "Pacer",
    "Port",
    "ProblemLog",
    "RawSinkCore",
    "SourceCore",
    "StageSpec",
    "StageStart",
    "StatsReporter",
    "StopRequested",
    "WILDCARD_MAX_KEYS",
    "add_network_args",
    "build_parser",
    "make_zenoh_config",
    "on_stop_signals",
    "open_session",
    "parse_bindings",
    "parse_set",
    "run_closing_stage",
    "run_stage",
    "session_from_args",
    "setup_logging",
    "start_stage",
]
