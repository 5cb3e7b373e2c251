"""The operator join when one input lags: late is waited for, silent is dropped (counted); the launcher's thread env.

Like ``test_runtime_ports.py``: a ``Node`` without a session is handed
payloads as a subscriber callback would, with a recording core; the node's
clock (``time.monotonic``) is driven by the test instead of waited on.
"""

from __future__ import annotations

from dataclasses import dataclass

import msgpack

import bus_schemas as bs
import stages.runtime.node as node_module
from stages.lib.base import ConfigMixin, StageResult
from stages.runtime import JOIN_TIMEOUT_S, JOIN_WINDOW, Node, Port, StageSpec, build_parser, parse_bindings
from stages.runtime.launcher import THREAD_ENV, single_threaded_env
from testkit.helpers import RecordingPublisher
from testkit.samples import SAMPLES


@dataclass(frozen=True)
class _Cfg(ConfigMixin):
    pass


class _Recorder:
    def __init__(self) -> None:
        self.stamps: list[int] = []

    def update(self, inputs):
        assert inputs["a"].header.stamp_ns == inputs["b"].header.stamp_ns
        self.stamps.append(inputs["a"].header.frame_index)
        return StageResult()


def _payload(frame_index: int) -> bytes:
    env = msgpack.unpackb(SAMPLES["iamp.AccelerationProfiles"]().encode(), raw=False)
    env["body"]["header"]["frame_index"] = frame_index
    env["body"]["header"]["stamp_ns"] = 1_000_000_000 + frame_index * 100_000_000
    return msgpack.packb(env, use_bin_type=True)


class _Clock:
    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


def _node() -> Node:
    inputs = {"a": Port(bs.AccelerationProfiles), "b": Port(bs.AccelerationProfiles)}
    spec = StageSpec(stage="tests.join", config_cls=_Cfg, make_core=lambda c, ctx: _Recorder(), inputs=inputs, outputs={})
    args = build_parser(spec).parse_args(["--node-id", "join", "--run-id", "t", "--input", "a=src/a", "--input", "b=src/b"])
    node = Node(spec, args, _Cfg(), parse_bindings(spec, args))
    node._publishers = {}
    node._progress_pub = RecordingPublisher()
    return node


def test_a_lagging_input_is_waited_for_and_a_silent_one_times_out(monkeypatch, caplog):
    caplog.set_level("WARNING")
    clock = _Clock()
    monkeypatch.setattr(node_module.time, "monotonic", clock)
    node, core = _node(), _Recorder()

    def at(t: float, port: str, frame: int) -> None:
        clock.now = 1000.0 + t
        node._accept(port, f"iamp/t/src/{port}", _payload(frame), 0)
        while (item := node.queue.get(timeout=0)) is not None:
            node._handle_operator_item(core, item)

    at(0.0, "a", 0)
    at(0.0, "b", 0)
    for k in range(1, 6):
        at(0.1 * k, "a", k)
    at(0.9 * JOIN_TIMEOUT_S, "b", 1)  # b is behind, but arriving
    at(1.5 * JOIN_TIMEOUT_S, "a", 6)  # sets 2..5 have waited longer than the timeout: b still came recently, so they wait
    for k in range(2, 7):
        at(1.6 * JOIN_TIMEOUT_S, "b", k)
    assert core.stamps == list(range(7))
    assert node.stats.counters["join_drops"] == 0
    # now b stops: the set of frame 7 waits the timeout after b's last message, then goes (counted)
    at(1.7 * JOIN_TIMEOUT_S, "a", 7)
    at(2.5 * JOIN_TIMEOUT_S, "a", 8)  # b silent for 0.9 timeouts: nothing dropped yet
    assert node.stats.counters["join_drops"] == 0
    at(4.0 * JOIN_TIMEOUT_S, "a", 9)  # b silent for 2.4 timeouts: the sets of frames 7 and 8 are dropped
    assert node.stats.counters["join_drops"] == 2
    # the line names what the set lacked and who sends it (a stopped stage upstream was named nowhere)
    assert "dropped input set: reason=join_timeout stamp_ns=1700000000 had=a lacked=b (from src/b)" in caplog.text
    assert set(node._pending) == {1_000_000_000 + 9 * 100_000_000}
    assert core.stamps == list(range(7))


def test_the_join_window_bounds_the_sets_waiting_for_a_lagging_input(monkeypatch):
    clock = _Clock()
    monkeypatch.setattr(node_module.time, "monotonic", clock)
    node, core = _node(), _Recorder()
    for k in range(JOIN_WINDOW + 5):
        node._accept("a", "iamp/t/src/a", _payload(k), 0)
        while (item := node.queue.get(timeout=0)) is not None:
            node._handle_operator_item(core, item)
    assert len(node._pending) == JOIN_WINDOW
    assert node.stats.counters["join_drops"] == 5


def test_nodes_get_single_threaded_numeric_libraries_unless_the_environment_says_otherwise():
    env = single_threaded_env({"PATH": "/bin", "OMP_NUM_THREADS": "4"})
    assert env["OMP_NUM_THREADS"] == "4" and env["PATH"] == "/bin"
    assert all(env[name] == "1" for name in THREAD_ENV if name != "OMP_NUM_THREADS")


class _Preparing(_Recorder):
    """A core with ``prepare``: records what it was offered; declines frame 3, raises on frame 4."""

    def __init__(self) -> None:
        super().__init__()
        self.offered: list[tuple[int, frozenset, tuple]] = []

    def prepare(self, inputs, missing):
        frame = next(iter(inputs.values())).header.frame_index
        self.offered.append((frame, missing, tuple(sorted(inputs))))
        if frame == 4:
            raise RuntimeError("prepare broke")
        return frame != 3


def test_a_core_may_start_on_a_set_still_missing_inputs(monkeypatch):
    """``prepare(inputs, missing)`` is offered the newest incomplete set each time an input joins it; a refusal is not
    counted, a failure is counted and costs nothing: ``update`` runs on every complete set as before."""
    clock = _Clock()
    monkeypatch.setattr(node_module.time, "monotonic", clock)
    node, core = _node(), _Preparing()

    def feed(port: str, frame: int) -> None:
        node._accept(port, f"iamp/t/src/{port}", _payload(frame), 0)
        while (item := node.queue.get(timeout=0)) is not None:
            node._handle_operator_item(core, item)

    feed("a", 0)
    feed("b", 0)  # completes the set: no prepare, the update
    feed("b", 1)
    feed("a", 2)  # the newest set: offered
    feed("a", 1)  # frame 1 is not the newest pending set: not offered (it completes, and supersedes nothing)
    feed("b", 2)
    for k in (3, 4):
        feed("a", k)
        feed("b", k)
    assert [(f, set(m), keys) for f, m, keys in core.offered] == [
        (0, {"b"}, ("a",)), (1, {"a"}, ("b",)), (2, {"b"}, ("a",)), (3, {"b"}, ("a",)), (4, {"b"}, ("a",))]
    assert core.stamps == [0, 1, 2, 3, 4]
    assert node.stats.counters["prepared"] == 3  # frames 0, 1 and 2; 3 declined, 4 raised
    assert node.stats.errors_by_kind["prepare_exception"] == 1
    assert len(node.stats.prep_ms) == 3 and "prep_ms_p50=" in node.stats.summary()


class _SceneCore:
    def __init__(self) -> None:
        self.stamps: list[int] = []

    def update(self, inputs):
        assert "s" in inputs
        self.stamps.append(inputs["a"].header.frame_index)
        return StageResult()


def test_sets_waiting_for_a_late_latched_input_are_kept_past_the_timeout(monkeypatch):
    """Frames that overtook the latched scene (lost on the wire, then queried) wait for it however long it takes,
    bounded by the join window only; once it comes every one of them runs, in order, none dropped."""
    clock = _Clock()
    monkeypatch.setattr(node_module.time, "monotonic", clock)
    inputs = {"a": Port(bs.AccelerationProfiles), "s": Port(bs.AccelerationProfiles, latched=True)}
    spec = StageSpec(stage="tests.latched", config_cls=_Cfg, make_core=lambda c, ctx: _SceneCore(), inputs=inputs, outputs={})
    args = build_parser(spec).parse_args(["--node-id", "late", "--run-id", "t", "--input", "a=src/a", "--input", "s=src/s"])
    node = Node(spec, args, _Cfg(), parse_bindings(spec, args))
    node._publishers = {}
    node._progress_pub = RecordingPublisher()
    core = _SceneCore()

    def at(t: float, port: str, frame: int) -> None:
        clock.now = 1000.0 + t
        node._accept(port, f"iamp/t/src/{port}", _payload(frame), 0)
        while (item := node.queue.get(timeout=0)) is not None:
            node._handle_operator_item(core, item)

    for k in range(4):
        at(0.1 * k, "a", k)
    at(3.0 * JOIN_TIMEOUT_S, "a", 4)  # frames 0..3 have waited 3 timeouts for the scene
    assert core.stamps == [] and node.stats.counters["join_drops"] == 0
    at(3.1 * JOIN_TIMEOUT_S, "s", 0)
    at(3.2 * JOIN_TIMEOUT_S, "a", 5)
    assert core.stamps == [0, 1, 2, 3, 4, 5]
    assert node.stats.counters["join_drops"] == 0
