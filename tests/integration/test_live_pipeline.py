"""``python launch.py live``: the whole hybrid pipeline on the frames of a tracker it does not start.

The tracker is a separate process that only knows the hub's endpoint and the
keys (here the dataset player run as node ``tracker`` of run ``live``, its
frames stamped with the wall clock as a live tracker's are, as the README's
"Predicting from a live tracker" shows); the test waits on messages
and liveliness, never on fixed sleeps, and checks the recording.
"""

from __future__ import annotations

import signal
import threading

import bus_schemas as bs
from testkit.helpers import endpoint, free_port, kill_all, output_of, start_module, stop_process, wait_until
from stages.recorder.inspect import inspect, read_messages
from stages.runtime import BusClient
from test_launch_run import Launch

STAGES = ("corridors", "relations", "intentions", "ar_inference", "markov_prediction", "recorder")


def test_live_pipeline_predicts_every_frame_of_an_outside_tracker(tmp_path):
    port = free_port()
    rec = tmp_path / "live.mcap"
    run = Launch("live", "--no-viewer", "--listen", endpoint(port), "--record", str(rec), cwd=tmp_path)
    tracker = None
    try:
        run.wait_line(rf"^\[launch\] all {len(STAGES)} nodes alive; starting sources: \(none\)")
        grids: list[int] = []
        lock = threading.Lock()

        def on_grid(_key: str, data: bytes) -> None:
            with lock:
                grids.append(bs.MotionGrid.decode(data).header.stamp_ns)

        with BusClient(connect=[endpoint(port)]) as bus:
            bus.subscribe("iamp/live/markov_prediction/motion_grid", on_grid)
            # a tracker that waits until the stages are visible (a real one may just publish; frames sent before a
            # stage's subscription reaches it are lost, and this test counts every frame)
            tracker = start_module("stages.tracks_source", "--run-id", "live", "--node-id", "tracker", "--connect", endpoint(port),
                                   "--set", 'recording="k729_2022-03-16"', "--set", "speed=3", "--set", 'clock="wall"',
                                   "--await-nodes", ",".join(STAGES))
            wait_until(lambda: len(grids) >= 30 or tracker.poll() is not None, 120.0, "30 MotionGrids of the tracker's frames")
            assert len(grids) >= 30, output_of(tracker)[-3000:]
            assert min(grids) > 1_700_000_000 * 10**9  # stamped with the wall clock, as a live tracker stamps its frames
            assert stop_process(tracker) == 0, output_of(tracker)[-3000:]
        run.proc.send_signal(signal.SIGINT)  # the launcher stops the stages in dataflow order, each draining its queue
        assert run.wait() == 0, run.text()[-4000:]
    finally:
        kill_all([p for p in (run.proc, tracker) if p is not None])

    counts = {c["topic"]: c["count"] for c in inspect(str(rec))["channels"]}
    frames = counts["iamp/live/tracker/track_frame"]
    assert frames >= 30 and "iamp/live/tracker/scene" in counts, counts
    # every frame of the tracker went through every stage into a hybrid MotionGrid
    for topic in ("corridors/corridor_set", "relations/relation_set", "intentions/intention_belief",
                  "ar_inference/acceleration_profiles", "markov_prediction/corridor_predictions", "markov_prediction/motion_grid"):
        assert counts.get(f"iamp/live/{topic}") == frames, (topic, counts)
    modes, cells = set(), 0
    for m in read_messages(str(rec)):
        if m.topic == "iamp/live/markov_prediction/motion_grid":
            grid = bs.MotionGrid.decode(m.data)
            modes.add(grid.mode)
            cells += sum(step.values.size for step in grid.steps)
    assert modes == {"hybrid"} and cells > 0
    last: dict[str, bs.NodeStats] = {}
    for m in read_messages(str(rec)):
        if "/_stats/" in m.topic:
            stats = bs.NodeStats.decode(m.data)
            last[stats.node_id] = stats
    assert set(STAGES) <= set(last), sorted(last)
    assert all(last[n].counters.get("core_errors", 0) == 0 for n in STAGES), {n: last[n].counters for n in STAGES}


def test_a_tracker_restarted_on_another_clock_is_followed_both_ways(tmp_path):
    """A live tracker restarted on another clock: from a recording's clock to the wall clock (every stamp ~1.8e18 ns
    ahead, beyond every stage's stamp window: each stage follows once 20 messages in a row agree, the first ones
    dropped and counted) and back (every core resets its state on a stamp that went back). The pipeline keeps
    predicting each time, without a core error, and the stand-in tracker's start is not held up by a node that never
    acks a stamp below the newest it has seen (the recorder did not)."""
    port = free_port()
    rec = tmp_path / "restarts.mcap"
    run = Launch("live", "--no-viewer", "--listen", endpoint(port), "--record", str(rec), cwd=tmp_path)
    tracker = None
    big = 10**18
    try:
        run.wait_line(rf"^\[launch\] all {len(STAGES)} nodes alive; starting sources: \(none\)")
        grids: list[int] = []
        lock = threading.Lock()

        def on_grid(_key: str, data: bytes) -> None:
            with lock:
                grids.append(bs.MotionGrid.decode(data).header.stamp_ns)

        def count(wall: bool) -> int:
            with lock:
                return sum((s >= big) == wall for s in grids)

        with BusClient(connect=[endpoint(port)]) as bus:
            bus.subscribe("iamp/live/markov_prediction/motion_grid", on_grid)
            for clock, wall, want in (("recording", False, 15), ("wall", True, 15), ("recording", False, 30)):
                tracker = start_module("stages.tracks_source", "--run-id", "live", "--node-id", "tracker", "--connect", endpoint(port),
                                       "--set", 'recording="k729_2022-03-16"', "--set", "speed=4", "--set", f'clock="{clock}"',
                                       "--await-nodes", ",".join(STAGES))
                wait_until(lambda: count(wall) >= want or tracker.poll() is not None, 120.0, f"{want} MotionGrids on the {clock} clock")
                assert count(wall) >= want, output_of(tracker)[-3000:]
                assert stop_process(tracker) == 0, output_of(tracker)[-3000:]
                if not wall:  # (on the wall clock the first frames are rejected, so the warm-up gives up on the stages)
                    said = output_of(tracker)
                    assert "no longer waiting" not in said and "not waiting for nodes" not in said, said[-3000:]
        run.proc.send_signal(signal.SIGINT)
        assert run.wait() == 0, run.text()[-4000:]
    finally:
        kill_all([p for p in (run.proc, tracker) if p is not None])
    out = run.text()
    for node in ("corridors", "relations", "intentions", "ar_inference", "markov_prediction"):
        assert any(line.startswith(f"[{node}]") and "stamp clock moved ahead by" in line for line in out.splitlines()), node
    last: dict[str, bs.NodeStats] = {}
    for m in read_messages(str(rec)):
        if "/_stats/" in m.topic:
            stats = bs.NodeStats.decode(m.data)
            last[stats.node_id] = stats
    assert all(last[n].counters.get("core_errors", 0) == 0 for n in STAGES), {n: last[n].counters for n in STAGES}
    assert last["corridors"].counters.get("stamp_clock_jumps") == 1
