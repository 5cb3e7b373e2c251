"""The runtime's input port kinds beyond the joined ones: latest-value (``Port(latest=True)``) and wildcard (``Port(pattern=...)``).

The node tests build a ``Node`` without a session and hand it payloads (as a
subscriber callback would) and a recording core, like
``test_runtime_logs.py``; the last test runs a node in this process on a
real loopback Zenoh session.
"""

from __future__ import annotations

import dataclasses
import threading
import time
from dataclasses import dataclass

import msgpack
import pytest

import bus_schemas as bs
from stages.lib.base import ConfigError, ConfigMixin, StageResult
from stages.runtime import BusClient, Node, Port, StageSpec, build_parser, parse_bindings
from testkit.helpers import RecordingPublisher, endpoint, free_port, wait_until
from testkit.samples import SAMPLES


@dataclass(frozen=True)
class _Cfg(ConfigMixin):
    pass


class _Recorder:
    """Keeps every input set it is run on; publishes nothing."""

    def __init__(self) -> None:
        self.calls: list[dict] = []

    def update(self, inputs):
        self.calls.append(dict(inputs))
        return StageResult()


def _profiles(frame_index: int) -> bytes:
    env = msgpack.unpackb(SAMPLES["iamp.AccelerationProfiles"]().encode(), raw=False)
    env["body"]["header"]["frame_index"] = frame_index
    env["body"]["header"]["stamp_ns"] = 1_000_000_000 + frame_index * 100_000_000
    return msgpack.packb(env, use_bin_type=True)


def _stats(node_id: str, uptime_s: float = 1.0) -> bytes:
    return dataclasses.replace(SAMPLES["iamp.NodeStats"](), node_id=node_id, uptime_s=uptime_s).encode()


def _scene() -> bytes:
    return SAMPLES["iamp.SceneInfo"]().encode()


INPUTS = {
    "profiles": Port(bs.AccelerationProfiles),
    "extra": Port(bs.AccelerationProfiles, latest=True, optional=True),
    "stats": Port(bs.NodeStats, pattern="_stats/*", max_keys=3),
}


def _node(inputs=INPUTS, argv_inputs=("profiles=src/profiles", "extra=other/profiles")) -> Node:
    spec = StageSpec(stage="tests.ports", config_cls=_Cfg, make_core=lambda c, ctx: _Recorder(), inputs=inputs, outputs={})
    argv = ["--node-id", "ports", "--run-id", "t"]
    for b in argv_inputs:
        argv += ["--input", b]
    args = build_parser(spec).parse_args(argv)
    node = Node(spec, args, _Cfg(), parse_bindings(spec, args))
    node._publishers = {}
    node._progress_pub = RecordingPublisher()
    return node


def _deliver(node: Node, core, port: str, key: str, data: bytes) -> None:
    node._accept(port, key, data, 0)
    while (item := node.queue.get(timeout=0)) is not None:
        node._handle_operator_item(core, item)


def _frames(core: _Recorder) -> list[int]:
    return [c["profiles"].header.frame_index for c in core.calls]


# --------------------------------------------------------------------------- declaring


def test_port_kinds_exclude_each_other_and_patterns_are_checked():
    with pytest.raises(ValueError, match="latest=True and latched=True"):
        Port(bs.TrackFrame, latest=True, latched=True)
    with pytest.raises(ValueError, match="wildcard"):
        Port(bs.NodeStats, pattern="_stats/*", latest=True)
    with pytest.raises(ValueError):
        Port(bs.NodeStats, pattern="_stats//x")
    with pytest.raises(ValueError):
        Port(bs.NodeStats, pattern="_stats/Bad Name")
    assert Port(bs.NodeStats, pattern="**").pattern == "**"
    assert [p.joined for p in INPUTS.values()] == [True, False, False]
    assert [p.kind_label() for p in INPUTS.values()] == ["", "latest", "wildcard"]


def test_a_wildcard_input_is_bound_by_the_runtime_and_takes_no_binding():
    node = _node()
    assert node.input_keys == {"profiles": "iamp/t/src/profiles", "extra": "iamp/t/other/profiles", "stats": "iamp/t/_stats/*"}
    spec = node.spec
    args = build_parser(spec).parse_args(["--run-id", "t", "--input", "profiles=src/profiles", "--input", "stats=a/b"])
    with pytest.raises(ConfigError, match="wildcard input"):
        parse_bindings(spec, args)


# --------------------------------------------------------------------------- latest-value


def test_a_latest_value_input_is_absent_until_it_comes_then_its_newest_value_goes_with_every_update():
    node, core = _node(), _Recorder()
    _deliver(node, core, "profiles", "iamp/t/src/profiles", _profiles(0))
    assert _frames(core) == [0] and "extra" not in core.calls[0]  # it does not hold the update back
    _deliver(node, core, "extra", "iamp/t/other/profiles", _profiles(100))
    _deliver(node, core, "extra", "iamp/t/other/profiles", _profiles(101))
    assert _frames(core) == [0]  # a latest value does not run the core itself
    _deliver(node, core, "profiles", "iamp/t/src/profiles", _profiles(1))
    _deliver(node, core, "profiles", "iamp/t/src/profiles", _profiles(2))
    assert _frames(core) == [0, 1, 2]
    assert [c["extra"].header.frame_index for c in core.calls[1:]] == [101, 101]  # only the newest is kept


def test_a_latest_value_input_is_not_joined_and_does_not_move_the_stamp_clock():
    node, core = _node(), _Recorder()
    # stamped far ahead of the frames: a joined input would push the clock; a latest value may be of any age
    _deliver(node, core, "extra", "iamp/t/other/profiles", _profiles(10_000))
    for i in range(3):
        _deliver(node, core, "profiles", "iamp/t/src/profiles", _profiles(i))
    assert _frames(core) == [0, 1, 2]
    c = node.stats.counters
    assert c["rejected_stamps"] == 0 and c["join_drops"] == 0 and c["processed"] == 3


def test_a_latest_value_input_that_does_not_decode_is_counted_and_the_previous_value_stays():
    node, core = _node(), _Recorder()
    _deliver(node, core, "extra", "iamp/t/other/profiles", _profiles(100))
    _deliver(node, core, "extra", "iamp/t/other/profiles", b"\x93junk")
    _deliver(node, core, "profiles", "iamp/t/src/profiles", _profiles(0))
    assert core.calls[0]["extra"].header.frame_index == 100
    assert node.stats.counters["decode_errors.extra"] == 1


# --------------------------------------------------------------------------- wildcard


def test_a_wildcard_input_gives_the_core_the_newest_message_of_every_key():
    node, core = _node(), _Recorder()
    _deliver(node, core, "profiles", "iamp/t/src/profiles", _profiles(0))
    assert "stats" not in core.calls[0]  # absent until the first message
    _deliver(node, core, "stats", "iamp/t/_stats/a", _stats("a", 1.0))
    _deliver(node, core, "stats", "iamp/t/_stats/b", _stats("b", 1.0))
    _deliver(node, core, "stats", "iamp/t/_stats/a", _stats("a", 2.0))
    assert len(core.calls) == 1  # wildcard messages do not run the core themselves
    _deliver(node, core, "profiles", "iamp/t/src/profiles", _profiles(1))
    got = core.calls[1]["stats"]
    assert sorted(got) == ["iamp/t/_stats/a", "iamp/t/_stats/b"]
    assert got["iamp/t/_stats/a"].uptime_s == 2.0 and got["iamp/t/_stats/b"].node_id == "b"
    with pytest.raises(TypeError):
        got["x"] = None  # read-only
    _deliver(node, core, "stats", "iamp/t/_stats/c", _stats("c"))
    assert sorted(got) == ["iamp/t/_stats/a", "iamp/t/_stats/b"]  # what the core was given is a snapshot


def test_a_wildcard_input_keeps_at_most_max_keys_and_counts_the_rest():
    node, core = _node(), _Recorder()
    for i in range(10):
        _deliver(node, core, "stats", f"iamp/t/_stats/n{i}", _stats(f"n{i}"))
    _deliver(node, core, "stats", "iamp/t/_stats/n0", _stats("n0", 5.0))  # a kept key is still updated
    _deliver(node, core, "profiles", "iamp/t/src/profiles", _profiles(0))
    got = core.calls[0]["stats"]
    assert sorted(got) == ["iamp/t/_stats/n0", "iamp/t/_stats/n1", "iamp/t/_stats/n2"] and got["iamp/t/_stats/n0"].uptime_s == 5.0
    assert node.stats.counters["rejected_keys"] == 7 and node.stats.counters["rejected_keys.stats"] == 7


def test_a_stage_without_joined_inputs_runs_on_every_latest_or_wildcard_message_once_its_latched_input_is_in():
    inputs = {"scene": Port(bs.SceneInfo, latched=True), "stats": Port(bs.NodeStats, pattern="_stats/*")}
    node, core = _node(inputs, ("scene=src/scene",)), _Recorder()
    _deliver(node, core, "stats", "iamp/t/_stats/a", _stats("a"))
    assert core.calls == []  # the latched scene has not come yet
    _deliver(node, core, "scene", "iamp/t/src/scene", _scene())
    _deliver(node, core, "stats", "iamp/t/_stats/b", _stats("b"))
    assert len(core.calls) == 1 and sorted(core.calls[0]["stats"]) == ["iamp/t/_stats/a", "iamp/t/_stats/b"] and "scene" in core.calls[0]


# --------------------------------------------------------------------------- on a real bus


def test_latest_and_wildcard_inputs_on_a_real_bus():
    """A node in this process, on loopback Zenoh: the wildcard sees other publishers' NodeStats and its own."""
    port = free_port()
    core = _Recorder()
    spec = StageSpec(stage="tests.ports", config_cls=_Cfg, make_core=lambda c, ctx: core, inputs=INPUTS, outputs={})
    argv = ["--node-id", "ports", "--run-id", "busports", "--input", "profiles=src/profiles", "--input", "extra=other/profiles"]
    argv += ["--connect", endpoint(port), "--stats-period", "0.1"]
    args = build_parser(spec).parse_args(argv)
    with BusClient(listen=[endpoint(port)]) as bus:
        node = Node(spec, args, _Cfg(), parse_bindings(spec, args))
        node.open()
        loop = threading.Thread(target=node.run_operator, args=(core,), daemon=True)
        loop.start()
        try:
            wait_until(lambda: "ports" in bus.alive_now("iamp/busports/_alive/*", 0.5), 30, "the node's liveliness")
            frames, extra, stats = bus.publisher("iamp/busports/src/profiles"), bus.publisher("iamp/busports/other/profiles"), bus.publisher("iamp/busports/_stats/other")
            extra(_profiles(100))
            stats(_stats("other"))
            wait_until(lambda: node.stats.counters["received.stats"] >= 2 and node.stats.counters["received.extra"] == 1, 30, "stats and extra received")
            for i in range(3):
                frames(_profiles(i))
            wait_until(lambda: len(core.calls) == 3, 30, "three updates")
            last = core.calls[-1]
            assert last["extra"].header.frame_index == 100
            assert {"iamp/busports/_stats/other", "iamp/busports/_stats/ports"} <= set(last["stats"])
        finally:
            node.stop_event.set()
            node.signals = 2
            loop.join(10)
            node.close()


def test_latest_and_wildcard_messages_do_not_hold_off_a_stop():
    """A stop waits until the joined inputs are quiet; the run's NodeStats (a wildcard) never are."""
    node, core = _node(), _Recorder()
    node._stats_pub = RecordingPublisher()
    done = threading.Event()

    def feed() -> None:
        i = 0
        while not done.is_set():
            node._accept("stats", "iamp/t/_stats/a", _stats("a", float(i)), 0)
            node._accept("extra", "iamp/t/other/profiles", _profiles(100 + i), 0)
            i += 1
            done.wait(0.02)

    feeder = threading.Thread(target=feed, daemon=True)
    feeder.start()
    try:
        node.stop_event.set()
        node.signals = 1
        t0 = time.monotonic()
        node.run_operator(core)
        assert time.monotonic() - t0 < 3.0
    finally:
        done.set()
        feeder.join(5)
