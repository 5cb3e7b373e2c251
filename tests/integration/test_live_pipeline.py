"""``python launch.py live``: the whole hybrid pipeline on the frames of a tracker it does not start.

The tracker is a separate process that only knows the hub's endpoint and the
keys (here the dataset player run as node ``tracker`` of run ``live``, its
frames stamped with the wall clock as a live tracker's are, as the README's
"Predicting from a live tracker" shows); the tests wait on messages
and liveliness, never on fixed sleeps, and check the recording.
"""

from __future__ import annotations

import contextlib
import dataclasses
import re
import signal
import subprocess
import threading
from pathlib import Path
from typing import Iterator

import bus_schemas as bs
from testkit.helpers import endpoint, free_port, kill_all, output_of, start_module, stop_process, wait_until
from stages.recorder.inspect import read_messages
from stages.runtime import BusClient
from test_launch_run import Launch

STAGES = ("corridors", "relations", "intentions", "ar_inference", "markov_prediction", "recorder")
WALL = 10**18  # stamps from here on are a wall clock's (Unix ns)


class LiveRun:
    """``launch.py live`` recorded to ``rec``, the MotionGrids' stamps as they arrive, and stand-in trackers."""

    def __init__(self, rec: Path) -> None:
        self.port = free_port()
        self.rec = rec
        self.run = Launch("live", "--no-viewer", "--listen", endpoint(self.port), "--record", str(rec), cwd=rec.parent)
        self.trackers: list[subprocess.Popen] = []
        self._grids: list[int] = []
        self._lock = threading.Lock()

    def on_grid(self, _key: str, data: bytes) -> None:
        with self._lock:
            self._grids.append(bs.MotionGrid.decode(data).header.stamp_ns)

    def grids(self, wall: bool | None = None) -> list[int]:
        with self._lock:
            return [s for s in self._grids if wall is None or (s >= WALL) == wall]

    def tracker(self, clock: str, speed: int) -> subprocess.Popen:
        """The dataset player as the outside tracker. It waits until the stages are visible (a real one may just
        publish: frames sent before a stage's subscription reaches it are lost, and these tests count frames)."""
        proc = start_module("stages.tracks_source", "--run-id", "live", "--node-id", "tracker", "--connect", endpoint(self.port),
                            "--set", 'recording="k729_2022-03-16"', "--set", f"speed={speed}", "--set", f'clock="{clock}"',
                            "--await-nodes", ",".join(STAGES))
        self.trackers.append(proc)
        return proc

    def last_stats(self) -> dict[str, bs.NodeStats]:
        last: dict[str, bs.NodeStats] = {}
        for m in read_messages(str(self.rec)):
            if "/_stats/" in m.topic:
                stats = bs.NodeStats.decode(m.data)
                last[stats.node_id] = stats
        assert set(STAGES) <= set(last), sorted(last)
        assert all(last[n].counters.get("core_errors", 0) == 0 for n in STAGES), {n: last[n].counters for n in STAGES}
        return last


@contextlib.contextmanager
def live_run(rec: Path) -> Iterator[LiveRun]:
    """The pipeline up, a bus session on its MotionGrids; on exit the launcher stopped by SIGINT (the stages in
    dataflow order, each draining its queue) and its clean exit checked."""
    live = LiveRun(rec)
    try:
        live.run.wait_line(rf"^\[launch\] all {len(STAGES)} nodes alive; starting sources: \(none\)")
        with BusClient(connect=[endpoint(live.port)]) as bus:
            bus.subscribe("iamp/live/markov_prediction/motion_grid", live.on_grid)
            yield live
        live.run.proc.send_signal(signal.SIGINT)
        assert live.run.wait() == 0, live.run.text()[-4000:]
    finally:
        kill_all([live.run.proc, *live.trackers])


def _unusable_scene_first(live: LiveRun) -> None:
    """A tracker whose SceneInfo names a map of another sha256 (a message, not the run's configuration): the launcher
    says so in one line and the run goes on (before, it stopped the whole run with exit 2); the trackers after it
    publish a scene the stages can load, under another scene_id, and are predicted."""
    from testkit.big_frames import real_frames

    scene, frames = real_frames(3, run_id="live", producer="tracker", map_sha256=True)
    bad = dataclasses.replace(scene, scene_id="unusable-map", map_sha256="0" * 64)
    said = re.compile(r"^\[launch\] corridors reports map \S+ unusable: map_sha256_mismatch.*the run goes on$")
    with BusClient(connect=[endpoint(live.port)]) as bus:
        sent = iter(range(10**6))

        def reported() -> bool:
            # the scene and a frame again until the launcher says it (a put before the new session's routes reach the
            # stages is lost), the frames on the wall clock as the second tracker's below
            bus.put("iamp/live/tracker/scene", bad.encode())
            n = next(sent)
            frame = frames[n % len(frames)]
            header = dataclasses.replace(frame.header, stamp_ns=WALL + n * 100_000_000, frame_index=n)
            bus.put("iamp/live/tracker/track_frame", dataclasses.replace(frame, header=header, scene_id=bad.scene_id).encode())
            return any(said.search(line) for line in list(live.run.lines))

        wait_until(reported, 60.0, "the launcher's line on the tracker's unusable map", interval_s=0.1)
    assert live.run.proc.poll() is None, live.run.text()[-3000:]


def _feed(live: LiveRun, clock: str, speed: int, want: int) -> str:
    """One stand-in tracker on ``clock`` until ``want`` MotionGrids of its clock came; stopped; returns its log."""
    wall = clock == "wall"
    tracker = live.tracker(clock, speed)
    wait_until(lambda: len(live.grids(wall)) >= want or tracker.poll() is not None, 120.0, f"{want} MotionGrids on the {clock} clock")
    assert len(live.grids(wall)) >= want, output_of(tracker)[-3000:]
    assert stop_process(tracker) == 0, output_of(tracker)[-3000:]
    return output_of(tracker)


def test_live_pipeline_predicts_every_frame_of_an_outside_tracker_and_follows_its_restarts_on_other_clocks(tmp_path):
    """An outside tracker restarted on another clock: from a recording's clock to the wall clock, as a live tracker
    stamps its frames (every stamp ~1.8e18 ns ahead, beyond every stage's stamp window: each stage follows once 20
    messages in a row agree, the first ones dropped and counted) and back (every core resets its state on a stamp
    that went back). The pipeline keeps predicting each time, without a core error, and the stand-in tracker's start
    is not held up by a node that never acks a stamp below the newest it has seen (the recorder did not). After both
    restarts every frame of the tracker goes through every stage into a hybrid MotionGrid. (One pipeline for what
    were two tests: a run each cost the suite 9 s.)"""
    with live_run(tmp_path / "live.mcap") as live:
        _unusable_scene_first(live)
        for clock, want in (("recording", 15), ("wall", 15), ("recording", 45)):
            said = _feed(live, clock, 4, want)
            if clock == "recording":  # (on the wall clock the first frames are rejected, so its warm-up gives up on the stages)
                assert "no longer waiting" not in said and "not waiting for nodes" not in said, said[-3000:]
    assert len(live.grids(wall=True)) >= 15  # stamped with the wall clock, as a live tracker stamps its frames

    def last_run(topic: str) -> list[int]:
        """The stamps of ``topic`` in the order recorded, from its last wall-clock one on: the third tracker's."""
        stamps = [bs.decode(m.data).header.stamp_ns for m in read_messages(str(live.rec)) if m.topic == f"iamp/live/{topic}"]
        walls = [i for i, stamp in enumerate(stamps) if stamp >= WALL]
        assert walls, topic
        return stamps[walls[-1] + 1:]

    frames = last_run("tracker/track_frame")
    assert len(frames) >= 20, len(frames)  # (45 recording-clock grids in all: 15 or a few more came from the first tracker)
    for topic in ("corridors/corridor_set", "relations/relation_set", "intentions/intention_belief",
                  "ar_inference/acceleration_profiles", "markov_prediction/corridor_predictions", "markov_prediction/motion_grid"):
        assert last_run(topic) == frames, topic
    grids = [bs.MotionGrid.decode(m.data) for m in read_messages(str(live.rec)) if m.topic == "iamp/live/markov_prediction/motion_grid"]
    assert {g.mode for g in grids} == {"hybrid"} and sum(step.values.size for g in grids for step in g.steps) > 0
    assert any(m.topic == "iamp/live/tracker/scene" for m in read_messages(str(live.rec)))
    out = live.run.text()
    for node in ("corridors", "relations", "intentions", "ar_inference", "markov_prediction"):
        assert any(line.startswith(f"[{node}]") and "stamp clock moved ahead by" in line for line in out.splitlines()), node
    assert live.last_stats()["corridors"].counters.get("stamp_clock_jumps") == 1
