"""Replay an MCAP recording onto the bus, with its original timing or as fast as possible.

Consumes an MCAP file written by ``stages.recorder`` and publishes every
recorded payload, byte for byte, on its recorded key: re-homed under the
current run id (``keys.replace_run``) unless ``run_id_from_file``. Messages
go out in file order; with ``speed = x`` the gaps between their receive times
(``log_time``) are divided by ``x``. With ``speed = "max"`` there are no gaps:
publishing blocks when the transport is full (congestion control BLOCK), and
replay keeps at most ``MAX_SPEED_WINDOW`` header stamps ahead of every live
node that acks ``Progress``. Both are the runtime's pacing
(``stages.runtime.pacing``, the same ``Pacer`` as a source's), with one
difference: a node that has acked nothing within ``FIRST_ACK_GRACE_S`` of
the first wait (a tool holding a liveliness token) is not waited for until
it acks, and relies on its deep input queue; the nodes named by
``--await-nodes`` (a pipeline's, which all ack) are waited for
``CONSUMER_WAIT_S`` like a node behind (a first input set may take seconds).

Infrastructure keys (``_stats``, ``_ack``) are left out unless
``include_infra``: replayed NodeStats would describe nodes that are not
running. Replaying a recording into a recorder therefore gives a second file
whose data channels carry the same payloads, in the same order and number.
``nodes`` restricts the replay to the keys of some recorded nodes (for a
pipeline that recomputes the rest: ``nodes = ["source"]``).

Like every node, replay publishes its own ``NodeStats`` on
``iamp/<run>/_stats/<node>`` every ``--stats-period`` (1 s) and at the end
(``runtime.StatsReporter``): ``processed`` and ``published`` count the
messages replayed, ``skipped`` (by reason: ``skipped.foreign_key``,
``skipped.infrastructure``, ``skipped.other_node``) what it left out,
``damaged_chunks``/``damaged_bytes`` the unreadable chunks passed over and
``truncated_file`` a file that ended before its footer; so the viewer's
Stages table and a recording of the run show it as they show any source.

Replay publishes on keys it learns from the file, not on declared ports, so
it runs its own loop on ``runtime.BusClient`` instead of ``run_stage``; it
starts as every stage does (``runtime.start_stage``: the same flags
``--node-id``, ``--run-id``, ``--params-json``, ``--set``, ``--log-level``,
``--await-nodes`` and the network flags) and holds
a liveliness token at ``iamp/<run>/_alive/<node>``, so the launcher runs it
like a source (``SPEC.kind == "source"``). Before publishing it waits, up to
``wait_for_subscribers_s``, until a subscriber matches one of the keys of the
first messages. It
exits 0 when everything was published (or on SIGINT/SIGTERM), 2 for a bad
file or configuration. ``iamp replay FILE.mcap`` (``stages.cli``) is the same
loop behind a friendlier command line.
"""

from __future__ import annotations

from stages.replay.core import SPEC, main, RecordingPlayer, ReplayConfig, play, run_replay, parse_speed

__all__ = ["SPEC", "main", 'RecordingPlayer', 'ReplayConfig', 'play', 'run_replay', 'parse_speed']
