"""The runtime's pacing (``stages.runtime.pacing``), shared by sources and replay, without a bus: acks and liveliness are fed by hand."""

from __future__ import annotations

import logging
import threading
import time

import pytest

from bus_schemas import Progress
from stages.runtime.pacing import Consumers, Pacer

LOG = logging.getLogger("iamp.test_pacing")


def test_a_fixed_speed_publishes_at_the_recording_rate_times_speed():
    pacer = Pacer(4.0, None, threading.Event(), LOG)
    t0 = time.monotonic()
    for i in range(5):
        assert pacer.before(i * 100_000_000, i)  # 0.1 s apart at 4x: 25 ms
    assert 0.09 <= time.monotonic() - t0 < 1.0


def test_bad_speeds_are_refused():
    for bad in (0, -1.0, "fast"):
        with pytest.raises(ValueError):
            Pacer(bad, None, threading.Event(), LOG)


def test_max_keeps_at_most_the_window_ahead_of_a_node_that_acks():
    consumers = Consumers("src")
    consumers.on_alive("op", True)
    consumers.on_alive("src", True)  # its own token is never waited for
    pacer = Pacer("max", consumers, threading.Event(), LOG, window=2, wait_s=5.0)
    assert pacer.before(1, 1) and pacer.before(2, 2)
    threading.Timer(0.2, lambda: consumers.on_ack_payload(Progress(node_id="op", last_stamp_ns=1, last_frame_index=0, handled=1).encode())).start()
    t0 = time.monotonic()
    assert pacer.before(3, 3)  # waits for op's ack of stamp 1
    assert time.monotonic() - t0 >= 0.15
    assert pacer.before(3, 3)  # another message of the same stamp: no wait
    consumers.on_ack("op", 3)
    t0 = time.monotonic()
    pacer.drain(1.0)
    assert time.monotonic() - t0 < 0.5


def test_a_silent_node_is_not_waited_for_after_the_grace_and_a_behind_one_after_wait_s_until_they_ack(caplog):
    caplog.set_level(logging.INFO, logger=LOG.name)
    consumers = Consumers("src")
    consumers.add_alive(["silent", "slow"])
    consumers.on_ack("slow", 0)
    pacer = Pacer("max", consumers, threading.Event(), LOG, window=1, wait_s=0.3, first_ack_grace_s=0.05)
    pacer.before(1, 1)
    t0 = time.monotonic()
    pacer.before(2, 2)
    assert 0.25 <= time.monotonic() - t0 < 2.0
    text = caplog.text
    assert "not waiting for nodes that report no progress: silent" in text
    assert "nodes behind after 0.3 s, no longer waiting for them until they ack: slow" in text
    assert consumers.waiting_on(2) == ([], [])
    consumers.on_ack("slow", 1)  # it acks again: waited for again
    assert consumers.waiting_on(2) == ([], ["slow"])
    consumers.on_alive("slow", False)
    assert consumers.waiting_on(2) == ([], [])


def test_the_end_of_play_wait_is_not_called_a_pacing_failure(caplog):
    """At the play's end the source waits (``drain``) for the nodes to ack its last frame: a node still behind then
    was logged as "pacing: nodes behind ..., no longer waiting", which read as a pacing failure in a run at real time
    (a new user's probe). It is said as what it is, at INFO."""
    caplog.set_level(logging.INFO, logger=LOG.name)
    consumers = Consumers("src")
    consumers.add_alive(["slow"])
    consumers.on_ack("slow", 0)
    pacer = Pacer(1.0, consumers, threading.Event(), LOG, window=1, wait_s=0.3, expected=["slow"])
    pacer.before(1, 1)
    caplog.clear()
    pacer.drain(0.2)
    records = [r for r in caplog.records if r.name == LOG.name]
    assert [r.levelno for r in records] == [logging.INFO]
    assert "end of play: nodes still behind after 0.2 s: slow; the source stops waiting" in records[0].getMessage()
    assert not any(r.getMessage().startswith("pacing:") for r in records)


def test_an_expected_node_that_has_acked_nothing_is_waited_for_wait_s_not_the_tools_grace(caplog):
    """A pipeline node's first input set may take seconds (caches, compiled kernels): replay must not take it for a
    tool that never acks and flood it; a tool holding a token is still let go after the short grace."""
    caplog.set_level(logging.INFO, logger=LOG.name)
    consumers = Consumers("src")
    consumers.add_alive(["corridors", "viewer"])
    pacer = Pacer("max", consumers, threading.Event(), LOG, window=1, wait_s=0.4, first_ack_grace_s=0.05, expected=["corridors"])
    pacer.before(1, 1)
    threading.Timer(0.2, consumers.on_ack, args=("corridors", 1)).start()  # its first set took 0.2 s (> the grace)
    t0 = time.monotonic()
    pacer.before(2, 2)
    waited = time.monotonic() - t0
    assert 0.15 <= waited < 0.4  # until corridors acked, not the grace, not the whole wait_s
    assert "report no progress: viewer" in caplog.text and "corridors" not in caplog.text
    assert consumers.waiting_on(2) == ([], ["corridors"])  # still followed


def test_a_stop_ends_a_wait_and_await_nodes_reports_the_missing():
    stop = threading.Event()
    consumers = Consumers("src")
    consumers.add_alive(["op"])
    pacer = Pacer("max", consumers, stop, LOG, window=1, wait_s=30.0)
    pacer.before(1, 1)
    threading.Timer(0.1, stop.set).start()
    t0 = time.monotonic()
    assert not pacer.before(2, 2)
    assert time.monotonic() - t0 < 5.0
    assert Consumers().await_nodes(["a", "b"], 0.05, threading.Event(), LOG) == ["a", "b"]


def _publish_in_thread(pacer: Pacer, time_ns: int, stamp: int) -> threading.Thread:
    t = threading.Thread(target=pacer.before, args=(time_ns, stamp), daemon=True)
    t.start()
    return t


def test_a_warmup_at_a_fixed_speed_waits_for_the_first_frame_to_be_handled_then_starts_the_clock():
    """``warmup=1``: the second stamp waits until every live node acked the first; the recording's clock starts from it, so nothing is late."""
    consumers = Consumers("src")
    consumers.on_alive("op", True)
    pacer = Pacer(1.0, consumers, threading.Event(), LOG, warmup=1, wait_s=30.0)
    assert pacer.before(0, 0)  # the first frame goes out at once
    second = _publish_in_thread(pacer, 100_000_000, 1)
    second.join(0.4)  # 0.1 s is when it would be due at speed 1
    assert second.is_alive(), "the second frame waits for op's ack of the first"
    acked_at = time.monotonic()
    consumers.on_ack("op", 0)
    second.join(5.0)
    assert not second.is_alive()
    # the clock (re)started at the second frame, once op had acked: later frames keep the recording's rate from it,
    # not from the first frame (they would all be late by the warm-up)
    assert pacer._time0 == 100_000_000 and pacer._wall0 >= acked_at
    assert pacer.before(200_000_000, 2)
    # without a warm-up nothing waits for acks at a fixed speed
    plain = Pacer(50.0, consumers, threading.Event(), LOG, wait_s=30.0)
    assert plain.before(0, 10) and plain.before(100_000_000, 11)


def test_a_warmup_gives_up_on_a_node_that_never_acks_after_wait_s():
    consumers = Consumers("src")
    consumers.add_alive(["mute"])
    pacer = Pacer(100.0, consumers, threading.Event(), LOG, warmup=1, wait_s=0.2)
    assert pacer.before(0, 0)
    second = _publish_in_thread(pacer, 100_000_000, 1)
    second.join(5.0)
    assert not second.is_alive()
    assert consumers.waiting_on(1) == ([], [])  # not waited for any more (until it acks)


@pytest.mark.parametrize("speed", [1.0, "max"])
def test_a_stop_during_the_wait_drains_on_the_last_stamp_published_not_the_one_held_back(speed, caplog):
    """Ctrl-C or ``--stop-after`` while the source waits for its next frame (due at real time, or at ``max`` a node's
    ack): ``before`` returns False and that frame is not published, so ``drain`` must wait for the acks of the one
    before it, not of a frame nobody received (which cost 3 s and a warning that every node was behind, at every
    stop)."""
    caplog.set_level(logging.INFO, logger=LOG.name)
    stop = threading.Event()
    consumers = Consumers("src")
    consumers.on_alive("op", True)
    pacer = Pacer(speed, consumers, stop, LOG, window=1, wait_s=2.0)
    assert pacer.before(0, 0)  # published
    if speed != "max":
        consumers.on_ack("op", 0)  # handled at once
    threading.Timer(0.1, stop.set).start()  # the stop comes while the next frame waits (due 1 s later; at max, op's ack)
    threading.Timer(0.2, consumers.on_ack, args=("op", 0)).start()  # op handles frame 0 (again: acks only grow)
    assert not pacer.before(1_000_000_000, 1)
    t0 = time.monotonic()
    pacer.drain(2.0)
    assert time.monotonic() - t0 < 1.0
    assert "nodes behind" not in caplog.text
