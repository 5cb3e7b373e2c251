"""The runtime's readable logs (IssueLog, ProblemLog) and its no-crash paths, in process.

Logged lines are read through a real ``logging`` logger (pytest's caplog);
the node tests build a ``Node`` without a session and hand it payloads and
cores directly, with stand-in publishers.
"""

from __future__ import annotations

import logging
import sys
from dataclasses import dataclass
from pathlib import Path

import msgpack
import numpy as np
import pytest

import bus_schemas as bs
from testkit.helpers import RecordingPublisher, wait_until
from testkit.samples import SAMPLES
from stages.lib.base import ConfigMixin, Issue, StageResult
from stages.runtime import IssueLog, Node, Port, ProblemLog, StageSpec, build_parser

LOGGER = "iamp.test_runtime_logs"


def _lines(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.name == LOGGER]


@pytest.fixture
def log(caplog):
    caplog.set_level(logging.INFO, logger=LOGGER)
    return logging.getLogger(LOGGER)


def _frames(ilog: IssueLog, frames: list[list[Issue]], t0: int = 1_000_000_000, dt: int = 100_000_000) -> None:
    for i, issues in enumerate(frames):
        ilog.frame(t0 + i * dt, issues)


OFF = Issue("off_map_heading", 2578, "near car lanelets but heading -2.93 rad agrees with none")


# --------------------------------------------------------------------------- IssueLog


def test_an_issue_on_consecutive_frames_is_logged_when_it_starts_and_when_it_ends(log, caplog):
    ilog = IssueLog(log)
    _frames(ilog, [[OFF]] * 37 + [[]])
    lines = _lines(caplog)
    assert lines == [
        "issue: kind=off_map_heading agent=2578 stamp_ns=1000000000 near car lanelets but heading -2.93 rad agrees with none",
        "issue ended: kind=off_map_heading agent=2578 frames=37 first_stamp_ns=1000000000 last_stamp_ns=4600000000 duration_s=3.6",
    ]
    assert [r.levelno for r in caplog.records if r.name == LOGGER] == [logging.WARNING, logging.INFO]
    assert ilog.open_count() == 0


def test_a_gap_ends_the_episode_and_a_recurrence_starts_a_new_one(log, caplog):
    ilog = IssueLog(log)
    _frames(ilog, [[OFF], [OFF], [], [OFF], []])
    lines = _lines(caplog)
    assert len(lines) == 3
    assert lines[0].startswith("issue: kind=off_map_heading agent=2578 stamp_ns=1000000000 ")
    assert lines[1] == "issue ended: kind=off_map_heading agent=2578 frames=2 first_stamp_ns=1000000000 last_stamp_ns=1100000000 duration_s=0.1"
    assert lines[2].startswith("issue: kind=off_map_heading agent=2578 stamp_ns=1300000000 ")
    # an episode of one frame ends at DEBUG only (its start line said all): half of a busy stage's lines were these
    caplog.clear()
    caplog.set_level(logging.DEBUG, logger=LOGGER)
    _frames(IssueLog(log), [[OFF], []])
    assert [(r.levelno, r.getMessage().split(" first_stamp")[0]) for r in caplog.records if r.name == LOGGER][1] == (
        logging.DEBUG, "issue ended: kind=off_map_heading agent=2578 frames=1")


def test_two_agents_interleaved_are_separate_episodes(log, caplog):
    a = Issue("off_map", 1, "a")
    b = Issue("off_map", 2, "b")
    c = Issue("nan_state", 1, "same agent, other kind")
    ilog = IssueLog(log)
    # a: frames 0-3; b: frames 1, 3 (a gap at 2); c: frame 2 only
    _frames(ilog, [[a], [a, b], [c, a], [b, a], []])
    lines = _lines(caplog)
    starts = [ln for ln in lines if ln.startswith("issue: ")]
    ends = [ln for ln in lines if ln.startswith("issue ended: ")]
    assert [s.split(" stamp_ns")[0] for s in starts] == [
        "issue: kind=off_map agent=1",
        "issue: kind=off_map agent=2",
        "issue: kind=nan_state agent=1",
        "issue: kind=off_map agent=2",
    ]
    assert ends == ["issue ended: kind=off_map agent=1 frames=4 first_stamp_ns=1000000000 last_stamp_ns=1300000000 duration_s=0.3"]


def test_an_issue_of_no_agent_is_an_episode_too_and_repeats_in_one_frame_count_once(log, caplog):
    ilog = IssueLog(log)
    no_frame = Issue("no_frame", -1, "input set without a track_frame")
    _frames(ilog, [[no_frame, no_frame], [no_frame], [no_frame], []])
    assert _lines(caplog) == [
        "issue: kind=no_frame agent=-1 stamp_ns=1000000000 input set without a track_frame",
        "issue ended: kind=no_frame agent=-1 frames=3 first_stamp_ns=1000000000 last_stamp_ns=1200000000 duration_s=0.2 occurrences=4",
    ]


def test_shutdown_logs_the_open_episodes_once(log, caplog):
    ilog = IssueLog(log)
    _frames(ilog, [[OFF, Issue("off_map", 7, "x")], [OFF]])
    caplog.clear()
    ilog.close()
    ilog.close()  # a second close has nothing left to say
    assert _lines(caplog) == [
        "issue open at stop: kind=off_map_heading agent=2578 frames=2 first_stamp_ns=1000000000 last_stamp_ns=1100000000 duration_s=0.1"
    ]
    assert ilog.open_count() == 0


def test_shutdown_lists_at_most_max_stop_lines(log, caplog):
    ilog = IssueLog(log, max_starts=1000)
    ilog.frame(5, [Issue("off_map", i, "") for i in range(IssueLog.MAX_STOP_LINES + 3)])
    caplog.clear()
    ilog.close()
    lines = _lines(caplog)
    assert len(lines) == IssueLog.MAX_STOP_LINES + 1
    assert lines[-1] == "issues open at stop: 3 more not listed"


def test_raw_sink_scopes_are_separate_keys(log, caplog):
    ilog = IssueLog(log)
    bad = Issue("not_an_envelope", -1, "not an envelope: ...")
    ilog.frame(1, [bad], scope="iamp/r/a/x")
    ilog.frame(2, [], scope="iamp/r/b/y")  # another key does not end the episode of the first
    ilog.frame(3, [bad], scope="iamp/r/a/x")
    ilog.frame(4, [], scope="iamp/r/a/x")
    assert _lines(caplog) == [
        "issue: kind=not_an_envelope key=iamp/r/a/x stamp_ns=1 not an envelope: ...",
        "issue ended: kind=not_an_envelope key=iamp/r/a/x frames=2 first_stamp_ns=1 last_stamp_ns=3 duration_s=0.0",
    ]


# --------------------------------------------------------------------------- ProblemLog


def test_problem_log_shows_a_kind_once_per_period_with_the_count_in_between(log, caplog):
    now = [0.0]
    plog = ProblemLog(log, period_s=10.0, clock=lambda: now[0])
    for i in range(5):
        now[0] = float(i)
        plog.report("decode:MalformedPayload:k", logging.WARNING, "dropped message: reason=%s n=%d", "MalformedPayload", i)
    plog.report("decode:WrongVersion:k", logging.WARNING, "dropped message: reason=%s", "WrongVersion")
    now[0] = 12.0
    plog.report("decode:MalformedPayload:k", logging.WARNING, "dropped message: reason=%s n=%d", "MalformedPayload", 5)
    now[0] = 13.0
    plog.report("decode:MalformedPayload:k", logging.WARNING, "dropped message: reason=%s n=%d", "MalformedPayload", 6)
    plog.close()
    assert _lines(caplog) == [
        "dropped message: reason=MalformedPayload n=0",
        "dropped message: reason=WrongVersion",
        "dropped message: reason=MalformedPayload n=5 [4 more of this kind in the last 12 s]",
        "not shown at stop: 1 more of kind decode:MalformedPayload:k",
    ]


def test_problem_log_appends_the_first_extra_only_to_the_first_line(log, caplog):
    now = [0.0]
    plog = ProblemLog(log, period_s=1.0, clock=lambda: now[0])
    calls = []

    def extra() -> str:
        calls.append(1)
        return "Traceback ..."

    plog.report("core:ValueError", logging.ERROR, "core failed", first_extra=extra)
    plog.report("core:ValueError", logging.ERROR, "core failed", first_extra=extra)
    now[0] = 5.0
    plog.report("core:ValueError", logging.ERROR, "core failed", first_extra=extra)
    assert _lines(caplog) == ["core failed\nTraceback ...", "core failed [1 more of this kind in the last 5 s]"]
    assert len(calls) == 1  # the traceback is only formatted when shown


# --------------------------------------------------------------------------- the node goes on


@dataclass(frozen=True)
class _Cfg(ConfigMixin):
    pass


class _EchoCore:
    """Echoes its input; raises on frame_index 13; issues on even frames."""

    def update(self, inputs):
        msg = inputs["profiles"]
        if msg.header.frame_index == 13:
            raise ValueError("unlucky frame")
        issues = [Issue("even_frame", 7, "an even frame")] if msg.header.frame_index % 2 == 0 else []
        return StageResult(outputs={"profiles": msg}, issues=issues)


def _node(log, *argv: str) -> tuple[Node, RecordingPublisher]:
    spec = StageSpec(
        stage="tests.echo",
        config_cls=_Cfg,
        make_core=lambda c, ctx: _EchoCore(),
        inputs={"profiles": Port(bs.AccelerationProfiles)},
        outputs={"profiles": Port(bs.AccelerationProfiles)},
    )
    args = build_parser(spec).parse_args(["--node-id", "echo", "--run-id", "t", "--input", "profiles=src/profiles", *argv])
    node = Node(spec, args, _Cfg(), {"profiles": "src/profiles"})
    node.log = log
    node.issue_log = IssueLog(log)
    node.problems = ProblemLog(log)
    out = RecordingPublisher()
    node._publishers = {"profiles": out}
    node._progress_pub = RecordingPublisher()
    return node, out


def _deliver(node: Node, core, port: str, key: str, data: bytes) -> None:
    """What a subscriber callback does (decode, queue) and then what the loop does with the queue."""
    node._accept(port, key, data, 0)
    while (item := node.queue.get(timeout=0)) is not None:
        node._handle_operator_item(core, item)


def _profiles(frame_index: int) -> bytes:
    msg = SAMPLES["iamp.AccelerationProfiles"]()
    env = msgpack.unpackb(msg.encode(), raw=False)
    env["body"]["header"]["frame_index"] = frame_index
    env["body"]["header"]["stamp_ns"] = 1_000_000_000 + frame_index * 100_000_000
    return msgpack.packb(env, use_bin_type=True)


def _huge_dim_profiles() -> bytes:
    """The payload that ended markov_prediction (issue 13): an empty 2-D array of shape [0, 2**63]."""
    env = msgpack.unpackb(_profiles(1), raw=False)
    p = env["body"]["profiles"][0]
    for f in ("chunk_mean_mps2", "chunk_sigma_mps2"):
        p[f] = ["float32", [0], b""]
    p["input_probs"] = ["float32", [0, 2**63], b""]
    return msgpack.packb(env, use_bin_type=True)


def test_hostile_payloads_and_a_failing_core_are_counted_and_the_node_goes_on(log, caplog, monkeypatch):
    node, out = _node(log)
    key = "iamp/t/src/profiles"
    items = [_profiles(0), _huge_dim_profiles(), b"\x93not an envelope", _profiles(13), _profiles(2), _profiles(3)]
    core = _EchoCore()
    for data in items:
        _deliver(node, core, "profiles", key, data)
    got = [bs.AccelerationProfiles.decode(d).header.frame_index for d in out.sent]
    assert got == [0, 2, 3]
    c = node.stats.counters
    assert c["decode_errors"] == 2 and c["core_errors"] == 1 and c["processed"] == 3
    assert dict(node.stats.errors_by_kind) == {"MalformedPayload": 2, "core_exception": 1}
    assert c["issues"] == 2 and node.stats.issues_by_kind["even_frame"] == 2

    # a decoder that raises something else (it should not) is counted too
    def boom(data, *, where="", report=None):
        raise RuntimeError("decoder bug")

    monkeypatch.setattr(bs.AccelerationProfiles, "decode", staticmethod(boom))
    _deliver(node, core, "profiles", key, _profiles(4))
    assert c["decode_errors"] == 3 and node.stats.errors_by_kind["decode_exception"] == 1
    text = "\n".join(_lines(caplog))
    assert "dropped message: reason=MalformedPayload key=iamp/t/src/profiles detail=iamp.AccelerationProfiles.profiles[0].input_probs" in text
    assert "dropped message: reason=decode_exception:RuntimeError key=iamp/t/src/profiles detail=decoder bug" in text
    assert "core failed on stamp_ns=2300000000 (input set dropped): ValueError: unlucky frame\nTraceback" in text


def test_the_serve_loop_survives_a_handler_that_raises(log, caplog):
    node, _out = _node(log)
    handled = []

    def handle(item):
        handled.append(item[1])
        if item[1] == "bad":
            raise KeyError("oops")

    for k in ("good", "bad", "good2"):
        node.queue.put((None, k, b"", 0), None, 0)
    node._stats_pub = RecordingPublisher()
    node.stop_event.set()
    node.signals = 2  # stop as soon as the queue is empty
    node._serve(handle)
    assert handled == ["good", "bad", "good2"]
    assert node.stats.errors_by_kind["handler_exception"] == 1
    assert any("handling a message from key=bad failed (dropped): KeyError" in ln for ln in _lines(caplog))


def test_the_serve_loop_runs_the_cores_idle_work_only_when_nothing_waits(log, caplog):
    """A core's ``idle`` (markov_prediction's back test) runs once an item leaves the queues empty and no input set
    is partly in (it would hold up that set's last input); an idle that raises is counted and the loop goes on."""
    node, _out = _node(log)
    node._stats_pub = RecordingPublisher()
    calls, idles = [], []

    def idle():
        calls.append(("idle", len(node.queue), len(node._pending)))
        idles.append(1)
        if len(idles) == 3:
            raise RuntimeError("idle bug")

    for k in ("a", "b"):  # the second item waits while the first is handled: one idle, after the second
        node.queue.put((None, k, b"", 0), None, 0)
    node.stop_event.set()
    node.signals = 2  # stop as soon as the queue is empty
    node._serve(lambda item: calls.append(("handle", item[1])), idle)
    assert calls == [("handle", "a"), ("handle", "b"), ("idle", 0, 0)]

    calls.clear()
    node._pending[7] = {}  # a frame with some of its inputs in: no idle while it waits for the rest
    node.queue.put((None, "c", b"", 0), None, 0)
    node._serve(lambda item: calls.append(("handle", item[1])), idle)
    assert calls == [("handle", "c")]
    node._pending.clear()
    for k in ("d", "e"):  # each alone in the queue: idle after each; the second idle raises
        node.queue.put((None, k, b"", 0), None, 0)
        node._serve(lambda item: calls.append(("handle", item[1])), idle)
    assert calls == [("handle", "c"), ("handle", "d"), ("idle", 0, 0), ("handle", "e"), ("idle", 0, 0)]
    assert node.stats.errors_by_kind["idle_exception"] == 1 and node.stats.counters["core_errors"] == 1
    assert any("the core's idle work failed after key=e: RuntimeError: idle bug" in ln for ln in _lines(caplog))


def _two_input_node(log, queue_size: int = 8) -> Node:
    spec = StageSpec(
        stage="tests.echo2",
        config_cls=_Cfg,
        make_core=lambda c, ctx: _EchoCore(),
        inputs={"profiles": Port(bs.AccelerationProfiles), "other": Port(bs.AccelerationProfiles, optional=True)},
        outputs={"profiles": Port(bs.AccelerationProfiles)},
    )
    argv = ["--node-id", "echo", "--run-id", "t", "--input", "profiles=src/profiles", "--input", "other=src/other", "--queue-size", str(queue_size)]
    node = Node(spec, build_parser(spec).parse_args(argv), _Cfg(), {"profiles": "src/profiles", "other": "src/other"})
    node.log = log
    node.issue_log = IssueLog(log)
    node.problems = ProblemLog(log)
    return node


def _queued(node: Node) -> list[tuple]:
    """Every queued entry in order, decoded as the loop would (an entry may still be raw bytes)."""
    out = []
    while (item := node.queue.get(timeout=0)) is not None:
        out.append(node._verified(item))
    return out


def test_a_malformed_burst_takes_no_queue_slot_and_is_counted_as_malformed(log, caplog):
    """Issue 13 item 4: 2,000 bad payloads between two good frames evict nothing; every one is a decode error.

    The queue (8 per input) fills with the first bad ones; from then on the subscriber side decodes what comes
    and, before a good message takes a place, the port's undecoded entries: the bad ones leave, counted."""
    node = _two_input_node(log)
    node._accept("profiles", "iamp/t/src/profiles", _profiles(1), 0)
    for i in range(2000):
        node._accept("profiles", "iamp/t/src/profiles", b"\x93junk" + i.to_bytes(4, "little"), 0)
    node._accept("profiles", "iamp/t/src/profiles", _profiles(2), 0)
    c = node.stats.counters
    assert c["decode_errors"] == 2000 and c["decode_errors.profiles"] == 2000 and c["queue_drops"] == 0
    got = [it[2].header.frame_index for it in _queued(node)]
    assert got == [1, 2]
    assert node.stats.counters["decode_errors"] == 2000
    lines = [ln for ln in _lines(caplog) if "dropped message" in ln]
    assert len(lines) == 1  # rate-limited: one line per kind and 10 s


def test_an_overflow_on_one_input_never_evicts_another_inputs_frames(log, caplog):
    node = _two_input_node(log, queue_size=8)
    node._accept("other", "iamp/t/src/other", _profiles(1), 0)
    for i in range(100):  # well-formed flood on "profiles"
        node._accept("profiles", "iamp/t/src/profiles", _profiles(2 + i), 0)
    c = node.stats.counters
    assert c["queue_drops"] == 92 and c["queue_drops.profiles"] == 92 and c["queue_drops.other"] == 0 and c["decode_errors"] == 0
    items = _queued(node)
    assert items[0][0] == "other" and items[0][2].header.frame_index == 1  # arrival order kept across ports
    assert [it[2].header.frame_index for it in items[1:]] == list(range(94, 102))  # the newest 8 of the flood
    assert len([ln for ln in _lines(caplog) if "input queue full: port=profiles" in ln]) == 1


def test_the_byte_bound_of_an_input_queue_drops_by_size(log):
    node = _two_input_node(log, queue_size=1000)
    one = len(_profiles(1))
    node.queue._max_bytes = 3 * one
    for i in range(10):
        node._accept("profiles", "iamp/t/src/profiles", _profiles(1 + i), 0)
    assert len(node.queue) == 3 and node.stats.counters["queue_drops.profiles"] == 7


def test_a_stamp_far_ahead_of_the_run_clock_is_rejected_and_later_frames_still_pass(log, caplog):
    node = _two_input_node(log)
    node._accept("profiles", "iamp/t/src/profiles", _profiles(1), 0)
    env = msgpack.unpackb(_profiles(2), raw=False)
    env["body"]["header"]["stamp_ns"] = 2**63 - 1
    node._accept("profiles", "iamp/t/src/profiles", msgpack.packb(env, use_bin_type=True), 0)
    node._accept("profiles", "iamp/t/src/profiles", _profiles(3), 0)
    kept = [it for it in _queued(node) if it is not None]  # the loop decodes, and checks the stamp window
    c = node.stats.counters
    assert c["rejected_stamps"] == 1 and c["rejected_stamps.profiles"] == 1
    assert [it[2].header.frame_index for it in kept] == [1, 3]
    assert any("reason=stamp_out_of_window" in ln for ln in _lines(caplog))


def _profiles_at(frame_index: int, stamp_ns: int) -> bytes:
    env = msgpack.unpackb(_profiles(frame_index), raw=False)
    env["body"]["header"]["stamp_ns"] = stamp_ns
    return msgpack.packb(env, use_bin_type=True)


def test_a_source_whose_clock_jumped_ahead_is_followed_after_a_run_of_frames_a_lone_far_stamp_is_not(log, caplog):
    """A live tracker restarted after minutes (or re-synchronised, or switched from a recording's clock to the wall
    clock) stamps every frame far ahead of the stamps the stage has seen: the stamp window rejected them all, for
    good. A run of ``STAMP_JUMP_AFTER`` joined messages that agree with one another moves the stage's stamp clock to
    them (the earlier ones of the run are lost, counted, one warning says so); a lone far stamp, or a few, stay
    rejected, and so does a run that jumps about."""
    from stages.runtime.node import STAMP_JUMP_AFTER

    node = _two_input_node(log, queue_size=1000)
    old = 1_000_000_000
    node._accept("profiles", "iamp/t/src/profiles", _profiles_at(1, old), 0)
    far = old + 10**18
    for i in range(3):  # a few far stamps, then the old clock again: rejected, and the run forgotten
        node._accept("profiles", "iamp/t/src/profiles", _profiles_at(2 + i, far + i * 100_000_000), 0)
    node._accept("profiles", "iamp/t/src/profiles", _profiles_at(5, old + 100_000_000), 0)
    # stamps far ahead but not of one clock (each a minute from the last): never followed
    for i in range(2 * STAMP_JUMP_AFTER):
        node._accept("profiles", "iamp/t/src/profiles", _profiles_at(6, far + i * 120 * 10**9), 0)
    # the restarted tracker: 10 Hz from 300 s later
    restart = old + 300 * 10**9
    for i in range(STAMP_JUMP_AFTER + 5):
        node._accept("profiles", "iamp/t/src/profiles", _profiles_at(100 + i, restart + i * 100_000_000), 0)
    kept = [it[2].header.frame_index for it in _queued(node) if it is not None]
    assert kept == [1, 5, *range(100 + STAMP_JUMP_AFTER - 1, 100 + STAMP_JUMP_AFTER + 5)]
    c = node.stats.counters
    assert c["rejected_stamps"] == 3 + 2 * STAMP_JUMP_AFTER + STAMP_JUMP_AFTER - 1
    assert c["stamp_clock_jumps"] == 1
    assert sum("stamp clock moved ahead by 299.9 s" in ln for ln in _lines(caplog)) == 1


def test_out_of_range_objects_are_counted_as_issues_and_never_reach_the_core(log, caplog):
    """Issue 13 item 2 at the runtime: a profile of 1e308 is dropped at decoding, counted, logged once."""
    node, out = _node(log)
    core = _EchoCore()
    env = msgpack.unpackb(_profiles(3), raw=False)
    good = env["body"]["profiles"][0]
    bad = dict(good, chunk_sigma_mps2=["float32", [len(good["chunk_sigma_mps2"][2]) // 4], np.full(len(good["chunk_sigma_mps2"][2]) // 4, -1.0, "<f4").tobytes()])
    env["body"]["profiles"] = [bad, good]
    _deliver(node, core, "profiles", "iamp/t/src/profiles", msgpack.packb(env, use_bin_type=True))
    assert len(out.sent) == 1 and len(bs.AccelerationProfiles.decode(out.sent[0]).profiles) == 1
    assert node.stats.issues_by_kind["out_of_range_dropped"] == 1 and node.stats.counters["decode_errors"] == 0
    assert any("input out of range: action=dropped field=iamp.AccelerationProfiles.profiles count=1" in ln for ln in _lines(caplog))


def test_episodes_that_start_and_end_on_every_message_are_bounded(log, caplog):
    """A raw sink fed bad/good/bad/... on one key: 2 lines per bad payload before; now at most max_starts per period."""
    clock = [0.0]
    il = IssueLog(log, max_starts=5, period_s=10.0, clock=lambda: clock[0])
    bad = [Issue("unrecognised_payload", -1, "recorded without schema")]
    for i in range(1000):
        il.frame(i, bad, scope="iamp/t/source/track_frame")
        il.frame(i, [], scope="iamp/t/source/track_frame")
    lines = _lines(caplog)
    assert sum("issue: kind=unrecognised_payload" in ln for ln in lines) == 5
    assert sum("issue ended: kind=unrecognised_payload" in ln for ln in lines) == 0  # one-frame episodes: their ends at DEBUG
    clock[0] = 11.0
    il.frame(2000, bad, scope="iamp/t/source/track_frame")
    assert "[995 more episodes of this kind not shown in the last 10 s]" in _lines(caplog)[-1]
    il.close()


def test_a_kind_that_every_new_car_raises_costs_a_few_lines_a_minute(log, caplog):
    """The defaults: 5 episode starts of one kind per minute, whatever the number of agents (a tracker quirk raised for
    each new track, K733's velocities), the others counted and told with the next one shown; an occasional other kind
    is shown."""
    clock = [0.0]
    il = IssueLog(log, clock=lambda: clock[0])
    for car in range(40):  # a new car every 0.5 s, each with its own one-frame episode
        clock[0] = 0.5 * car
        il.frame(car, [Issue("velocity_rejected", car, "reported velocity off the positions'"), Issue("position_jump", -1, "a jump")]
                 if car == 7 else [Issue("velocity_rejected", car, "reported velocity off the positions'")])
    lines = _lines(caplog)
    assert sum("issue: kind=velocity_rejected" in ln for ln in lines) == 5
    assert sum("issue ended: kind=velocity_rejected" in ln for ln in lines) == 0  # one-frame episodes: their ends at DEBUG
    assert sum("issue: kind=position_jump" in ln for ln in lines) == 1
    clock[0] = 61.0
    il.frame(100, [Issue("velocity_rejected", 100, "reported velocity off the positions'")])
    assert "issue: kind=velocity_rejected agent=100" in _lines(caplog)[-1]
    assert "[35 more episodes of this kind not shown in the last 60 s]" in _lines(caplog)[-1]
    il.close()


def test_frames_that_never_reached_the_node_are_counted(log, caplog):
    """A node stopped (kill -STOP) for 30 s had 273 of 574 frames and every counter at 0: the frames lost before its
    queue were counted nowhere. Gaps in the frame index of its first joined input, as received, are now counted
    (``frames_unreceived``) with one warning; a frame index that goes back (a source started over) is no gap, and
    frames of another input are not counted again."""
    from types import SimpleNamespace

    node = _two_input_node(log, queue_size=1000)
    cb, other = node._make_input_cb("profiles"), node._make_input_cb("other")

    def deliver(callback, frame_index):
        callback(SimpleNamespace(key_expr="iamp/t/src/profiles", payload=SimpleNamespace(to_bytes=lambda: _profiles(frame_index))))

    for i in [0, 1, 2, 6, 7, 20]:  # 3 lost before 6, 12 before 20
        deliver(cb, i)
    for i in [0, 5, 9]:  # the other input's gaps: not counted twice
        deliver(other, i)
    for i in [0, 1, 3]:  # started over: 1 lost before 3
        deliver(cb, i)
    assert node.stats.counters["frames_unreceived"] == 3 + 12 + 1
    assert sum("frames not received: 3 before frame 6" in ln for ln in _lines(caplog)) == 1


def test_inputs_that_fall_silent_are_reported_once_and_their_return_too(log, caplog, monkeypatch):
    """A live tracker killed: no stage said anything about its silent input, nor when it came back."""
    import threading
    import time as _time

    from stages.runtime import node as node_mod

    monkeypatch.setattr(node_mod, "SILENT_AFTER_S", 0.3)
    node, _out = _node(log)
    node._stats_pub = RecordingPublisher()
    handled = []

    def feed():
        try:  # (a wait that times out ends the feed; the assertions below then say what was missing)
            node.queue.put((None, "a", b"", 0), None, 0)
            wait_until(lambda: node._silent_since is not None, 30, "the silence reported")  # > 0.3 s: once, however many loop turns
            wait_until(lambda: _time.monotonic() - node._last_input_mono >= 1.0, 30, "a second of silence")  # (the return's figure)
            node.queue.put((None, "b", b"", 0), None, 0)
            wait_until(lambda: node._silent_since is None, 30, "the input resumed")
        finally:
            node.stop_event.set()
            node.signals = 2

    t = threading.Thread(target=feed)
    t.start()
    node._serve(lambda item: handled.append(item[1]))
    t.join()
    lines = _lines(caplog)
    assert handled == ["a", "b"]
    assert sum("no input for 0 s" in ln for ln in lines) == 1 and node.stats.counters["input_silences"] == 1, lines
    assert any("inputs resumed after 1 s of silence" in ln for ln in lines), lines


class _Clock:
    """A monotonic clock the test moves by hand (the queue's ``clock``)."""

    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def test_the_input_queue_skips_entries_older_than_max_age_but_never_a_ports_newest():
    """``max_age_s``: an entry of an ageing port that waited longer is skipped (``on_stale``) where a newer one of its
    port is queued; the newest is handed out however old; other ports, and a blocking queue, keep everything."""
    from stages.runtime.queues import InputQueue

    clock, stale = _Clock(), []
    q = InputQueue(64, lambda *a: None, max_age_s=0.5, ageing={"frames"}, on_stale=lambda port, n, item: stale.append((port, item)), clock=clock)
    for i in range(5):
        q.put(("frames", i), "frames", 10)
        q.put(("scene", i), "scene", 10)
        clock.now += 0.2  # frame i waited (5 - i) * 0.2 s when the loop comes to it
    got = []
    while (item := q.get(timeout=0)) is not None:
        got.append(item)
    # frames 0..2 waited 1.0, 0.8, 0.6 s (> 0.5): skipped; 3 (0.4 s) and 4 are handed out; every scene entry stays
    assert [i for p, i in got if p == "frames"] == [3, 4] and [i for p, i in got if p == "scene"] == [0, 1, 2, 3, 4]
    assert stale == [("frames", ("frames", 0)), ("frames", ("frames", 1)), ("frames", ("frames", 2))] and len(q) == 0
    q.put(("frames", 9), "frames", 10)
    clock.now += 60.0
    assert q.get(timeout=0) == ("frames", 9) and len(stale) == 3  # alone in its port: handed out, however old
    sink = InputQueue(64, lambda *a: None, block=True, max_age_s=0.5, ageing={"frames"}, on_stale=lambda *a: stale.append(a), clock=clock)
    for i in range(3):
        sink.put(("frames", i), "frames", 10)
    clock.now += 60.0
    assert [sink.get(timeout=0) for _ in range(3)] == [("frames", 0), ("frames", 1), ("frames", 2)] and len(stale) == 3


def test_a_node_with_max_age_skips_stale_joined_inputs_counted_and_said_once(log, caplog):
    """``--max-age-s``: a stage that fell behind its input skips to its freshest frames; each skipped frame is a
    ``stale_drops`` (and per port), one WARNING line for the episode, and the frames it works on are the newest."""
    node, out = _node(log, "--max-age-s", "0.5")
    clock = _Clock()
    node.queue._clock = clock  # (the queue's clock, moved by hand: a stage busy for 2.5 s while 20 frames came)
    for i in range(20):
        node._accept("profiles", "iamp/t/src/profiles", _profiles(i), 0)
        clock.now += 0.125
    while (item := node.queue.get(timeout=0)) is not None:
        node._handle_operator_item(_EchoCore(), item)
    echoed = [bs.AccelerationProfiles.decode(p).header.frame_index for p in out.sent]
    assert echoed == [16, 17, 18, 19]  # waited 0.5 s or less (frame 16: exactly 0.5)
    c = node.stats.counters
    assert c["stale_drops"] == 16 and c["stale_drops.profiles"] == 16 and c["queue_drops"] == 0
    said = [ln for ln in _lines(caplog) if "input older than 0.50 s skipped: port=profiles" in ln]
    assert len(said) == 1, _lines(caplog)


def test_a_frame_received_twice_is_a_duplicate_not_a_dropped_set(log, caplog, monkeypatch):
    """A probe's tracker sent frames twice: each copy opened a set that was later dropped as superseded
    (``join_drops``) although its frame was predicted. Now a joined message whose set was handled within
    ``DUPLICATE_WINDOW_S`` is ``duplicate_inputs`` (one line per episode) and ignored, as is a second copy inside a set
    still waiting; later, the same stamp is a new set (a source restarted on the same clock)."""
    import stages.runtime.node as node_module

    node, out = _node(log)
    clock = _Clock()
    monkeypatch.setattr(node_module.time, "monotonic", clock)
    for i in (1, 1, 2, 2, 2, 3):
        _deliver(node, _EchoCore(), "profiles", "iamp/t/src/profiles", _profiles(i))
        clock.now += 0.1
    echoed = [bs.AccelerationProfiles.decode(p).header.frame_index for p in out.sent]
    c = node.stats.counters
    assert echoed == [1, 2, 3] and c["duplicate_inputs"] == 3 and c["duplicate_inputs.profiles"] == 3 and c["join_drops"] == 0
    assert len([ln for ln in _lines(caplog) if ln.startswith("duplicate input: port=profiles")]) == 1
    clock.now += node_module.DUPLICATE_WINDOW_S + 1.0
    _deliver(node, _EchoCore(), "profiles", "iamp/t/src/profiles", _profiles(1))  # long after: a replay, a new set
    assert [bs.AccelerationProfiles.decode(p).header.frame_index for p in out.sent] == [1, 2, 3, 1] and c["duplicate_inputs"] == 3
    # a copy inside a set still waiting for its other input replaces the first: a duplicate too
    spec = StageSpec(stage="tests.echo2", config_cls=_Cfg, make_core=lambda c, ctx: _EchoCore(), outputs={"profiles": Port(bs.AccelerationProfiles)},
                     inputs={"profiles": Port(bs.AccelerationProfiles), "other": Port(bs.AccelerationProfiles)})
    argv = ["--node-id", "echo", "--run-id", "t", "--input", "profiles=src/profiles", "--input", "other=src/other"]
    two = Node(spec, build_parser(spec).parse_args(argv), _Cfg(), {"profiles": "src/profiles", "other": "src/other"})
    two.log, two.issue_log, two.problems = log, IssueLog(log), ProblemLog(log)
    two._publishers, two._progress_pub = {"profiles": RecordingPublisher()}, RecordingPublisher()
    for port in ("profiles", "profiles", "other"):
        _deliver(two, _EchoCore(), port, f"iamp/t/src/{port}", _profiles(5))
    assert len(two._publishers["profiles"].sent) == 1
    assert two.stats.counters["duplicate_inputs.profiles"] == 1 and two.stats.counters["join_drops"] == 0


class _FusionLikeCore:
    """As grid_fusion: most calls publish nothing (a clock tick, one shard's part of a frame); every other input is a
    whole frame, published as the frame of the stamp before it (an older frame than the input that ran the core),
    with ``shard_missing`` while ``down`` holds its frame index."""

    def __init__(self, down: range) -> None:
        self.down = down
        self.previous = None

    def update(self, inputs):
        msg = inputs["profiles"]
        i = msg.header.frame_index
        if i % 2:  # a part of a frame, or a tick: nothing published
            return StageResult()
        out, self.previous = self.previous, msg
        if out is None:
            return StageResult()
        issues = [Issue("shard_missing", -1, "published with shard(s) [0] only")] if out.header.frame_index in self.down else []
        return StageResult(outputs={"profiles": out}, issues=issues)


def test_calls_that_publish_nothing_neither_end_an_episode_nor_give_it_their_stamp(log, caplog):
    """A new-user probe killed one shard of the sharded pipeline: grid_fusion logged the outage as one episode per
    frame (each tick or partial frame between two published ones ended it), the rate limit then hid the next outage
    altogether, and the lines carried the tick's stamp (0): a negative duration. Now the calls that publish nothing
    end no episode, and an episode's stamps are those of the frames published."""
    node, _out = _node(log)
    core = _FusionLikeCore(down=range(10, 20))
    for i in range(40):
        _deliver(node, core, "profiles", "src/profiles", _profiles(i))
    node.issue_log.close()
    lines = [line for line in _lines(caplog) if "shard_missing" in line]
    assert lines == [
        "issue: kind=shard_missing agent=-1 stamp_ns=2000000000 published with shard(s) [0] only",
        "issue ended: kind=shard_missing agent=-1 frames=5 first_stamp_ns=2000000000 last_stamp_ns=2800000000 duration_s=0.8",
    ], lines
    assert node.stats.issues_by_kind["shard_missing"] == 5
