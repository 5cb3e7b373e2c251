"""End-to-end runs of launch.py over real Zenoh processes on loopback.

Each test starts the launcher on the embedded scenario, waits on what the
launcher and the nodes print (liveliness-gated start lines, restart lines) or
on files and messages, never on fixed sleeps, and checks the MCAP recording.
"""

from __future__ import annotations

import math

import re
import signal
import subprocess
import sys
import threading
from pathlib import Path

import pytest

import bus_schemas as bs
from testkit.helpers import REPO, endpoint, free_port, kill_all, python_env, start_module, stop_process, wait_until
from stages.recorder.inspect import inspect, read_messages


# These runs check the launcher, the recording and restarts on the embedded K729 scenario (sequence 013, the
# tracks source's own default), which every stage keeps up with at these speeds on a small machine; the
# launcher's default pipeline plays the busier K733 recording.
K729 = ("--recording", "k729_2022-03-16")


class Launch:
    """launch.py as a child process whose output lines are collected as they come."""

    def __init__(self, *args: str, cwd: Path) -> None:
        self.lines: list[str] = []
        self._lock = threading.Lock()
        self.proc = subprocess.Popen(
            [sys.executable, str(REPO / "launch.py"), *args],
            cwd=cwd,
            env=python_env(),
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            start_new_session=True,
        )
        threading.Thread(target=self._pump, daemon=True).start()

    def _pump(self) -> None:
        for line in self.proc.stdout:
            with self._lock:
                self.lines.append(line.rstrip("\n"))

    def text(self) -> str:
        with self._lock:
            return "\n".join(self.lines)

    def wait_line(self, pattern: str, timeout_s: float = 90.0, count: int = 1) -> re.Match:
        rx = re.compile(pattern)

        def found():
            ms = [m for m in (rx.search(line) for line in list(self.lines)) if m]
            return ms[count - 1] if len(ms) >= count else None

        try:
            return wait_until(found, timeout_s, f"a launcher line matching {pattern!r}")
        except AssertionError:
            raise AssertionError(f"no line matching {pattern!r} (x{count}); output so far:\n{self.text()[-4000:]}") from None

    def wait(self, timeout_s: float = 120.0) -> int:
        try:
            self.proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            raise AssertionError(f"launcher did not exit within {timeout_s} s:\n{self.text()[-4000:]}") from None
        return self.proc.returncode


def _last_stats(path: Path, node: str) -> bs.NodeStats:
    last = None
    for m in read_messages(str(path)):
        if m.topic.endswith(f"/_stats/{node}"):
            last = bs.NodeStats.decode(m.data)
    assert last is not None, f"no NodeStats of {node} in {path}"
    return last


def run_pipeline_k729(pipeline: str, run_id: str, tmp_path: Path) -> tuple[Path, dict[str, int]]:
    """``launch.py PIPELINE`` on K729 for 3 s at twice real time, recorded: the recording and its message count per
    topic, after checking that the run ended cleanly and that every source frame has a MotionGrid of
    markov_prediction."""
    rec = tmp_path / "run.mcap"
    run = Launch(pipeline, *K729, "--stop-after", "3", "--speed", "2", "--no-viewer", "--record", str(rec), "--run-id", run_id, cwd=tmp_path)
    assert run.wait() == 0, run.text()[-4000:]
    counts = {c["topic"]: c["count"] for c in inspect(str(rec))["channels"]}
    frames = counts[f"iamp/{run_id}/source/track_frame"]
    assert frames > 10 and counts[f"iamp/{run_id}/markov_prediction/motion_grid"] == frames, counts
    return rec, counts


def test_run_records_every_source_frame_and_replay_reproduces_it(tmp_path):
    rec = tmp_path / "run.mcap"
    run = Launch(*K729, "--stop-after", "6", "--speed", "3", "--no-viewer", "--record", str(rec), "--run-id", "itest", cwd=tmp_path)
    assert run.wait() == 0, run.text()[-4000:]
    out = run.text()
    assert f"recording to {rec}" in out and f"recording saved: {rec}" in out

    info = inspect(str(rec))
    counts = {c["topic"]: c["count"] for c in info["channels"]}
    frames = info["frames"]["iamp/itest/source/track_frame"]
    published = _last_stats(rec, "source").counters["published"] - counts["iamp/itest/source/scene"]
    assert frames["count"] == published > 10, (frames, published)
    assert frames["strictly_increasing"] and frames["missing"] == 0 and frames["first"] == 0
    # every frame went through corridors too (the launcher drains in dataflow order)
    cstats = _last_stats(rec, "corridors")
    assert counts["iamp/itest/corridors/corridor_set"] == frames["count"], (cstats.counters, run.text()[-3000:])
    # the default pipeline is hybrid: intentions and ar_inference see every frame, markov_prediction predicts in mode hybrid
    for topic in ("relations/relation_set", "intentions/intention_belief", "ar_inference/acceleration_profiles"):
        assert counts[f"iamp/itest/{topic}"] == frames["count"], (topic, counts)
    grids = [m for m in read_messages(str(rec)) if m.topic == "iamp/itest/markov_prediction/motion_grid"]
    assert grids and {bs.decode(m.data).mode for m in grids} == {"hybrid"}
    # the launcher's last lines say it from the file's summary: every recorded frame, how many got a MotionGrid
    lost = frames["count"] - len(grids)
    assert (f"[launch] predicted: {frames['count']} track frames recorded, MotionGrids of markov_prediction {len(grids)}"
            f" ({len(grids) / frames['count']:.1%})" + (f"; up to {lost} frames without one" if lost else "")) in out, out[-2000:]
    profiles = [bs.decode(m.data) for m in read_messages(str(rec)) if m.topic == "iamp/itest/ar_inference/acceleration_profiles"]
    assert any(p.profiles for p in profiles) and profiles[0].model.startswith("ar_taf_bw.pt@")

    # the streaming corridors stage and the in-process core (what iamp eval runs) give the same
    # state estimates and corridors, byte for byte, from the same frames
    from stages.corridors import CorridorBuilder, CorridorsConfig

    recorded = [(m.topic, bs.decode(m.data)) for m in read_messages(str(rec)) if m.topic.split("/")[-1] in ("scene", "track_frame", "corridor_set")]
    scene = next(msg for topic, msg in recorded if topic.endswith("/scene"))
    streamed = {msg.header.frame_index: msg for topic, msg in recorded if topic.endswith("/corridor_set")}
    builder = CorridorBuilder(CorridorsConfig(), producer="corridors")
    compared = 0
    for topic, msg in recorded:
        if topic.endswith("/track_frame"):
            ours, _ = builder.process(msg, scene)
            assert ours.encode() == streamed[msg.header.frame_index].encode(), msg.header.frame_index
            compared += 1
    assert compared == frames["count"]
    assert any(math.isfinite(v.vx_mps) and v.speed_mps > 1.0 for c in streamed.values() for v in c.vehicles)

    # replay the file onto the bus with a recorder attached: same payloads, same counts
    port = free_port()
    rec2 = tmp_path / "replayed.mcap"
    recorder = start_module("stages.recorder", "--run-id", "again", "--listen", endpoint(port), "--params-json", f'{{"path": "{rec2}"}}')
    try:
        wait_until(lambda: "node up" in Path(recorder.log_path).read_text(), 60, "the recorder to come up")
        replay = subprocess.run(
            [sys.executable, "-m", "stages.cli", "replay", str(rec), "--speed", "max", "--run-id", "again", "--connect", endpoint(port)],
            cwd=REPO,
            env=python_env(),
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert replay.returncode == 0, replay.stderr
        assert stop_process(recorder) == 0
    finally:
        kill_all([recorder])

    def payloads(path: Path, run_id: str) -> dict[str, list[bytes]]:
        out: dict[str, list[bytes]] = {}
        for m in read_messages(str(path)):
            if "/_" not in m.topic:
                out.setdefault(m.topic.replace(f"iamp/{run_id}/", ""), []).append(m.data)
        return out

    first, second = payloads(rec, "itest"), payloads(rec2, "again")
    assert first.keys() == second.keys()
    # the replay maps each recorded wall stamp (source_wall_ns) to its own publish time, one per frame: the same
    # payloads otherwise, and every output of a frame keeps its frame's (new) stamp
    replayed_walls: dict[int, set[int]] = {}
    for topic in first:
        assert len(first[topic]) == len(second[topic]), topic
        for a, b in zip(first[topic], second[topic]):
            ha, hb = getattr(bs.decode(a), "header", None), getattr(bs.decode(b), "header", None)
            if ha is not None:
                assert ha.source_wall_ns > 0 and hb.source_wall_ns > 0 and hb.source_wall_ns != ha.source_wall_ns, topic
                replayed_walls.setdefault(ha.source_wall_ns, set()).add(hb.source_wall_ns)
            same = bs.restamp_source_wall(b, lambda _w: 1) == bs.restamp_source_wall(a, lambda _w: 1)
            assert same, f"payloads differ on {topic}"
    assert all(len(v) == 1 for v in replayed_walls.values())


def _pid_of(run: Launch, node: str, count: int = 1) -> int:
    m = run.wait_line(rf"^\[{node}\] .*node up: .* pid=(\d+)", count=count)
    return int(m.group(1))


def test_killed_processing_stage_is_restarted_and_a_sighup_then_stops_every_node(tmp_path):
    """A killed stage is restarted, gets the latched scene by query and processes again. Then a SIGHUP (a closed
    terminal or ssh session) to the launcher: it died of it and left every stage running (in their own sessions)
    with the recording unfinished; now it stops the run as SIGINT does."""
    import os

    rec = tmp_path / "run.mcap"
    run = Launch(*K729, "--speed", "2", "--no-viewer", "--record", str(rec), "--run-id", "kill", cwd=tmp_path)
    try:
        run.wait_line(r"^\[launch\] all \d+ nodes alive; starting sources")
        pids = {node: _pid_of(run, node) for node in ("source", "markov_prediction", "recorder")}
        run.wait_line(r"^\[corridors\] .*scene loaded")  # it is processing frames
        pid = _pid_of(run, "corridors")
        os.kill(pid, signal.SIGKILL)
        run.wait_line(r"^\[launch\] node corridors died \(signal SIGKILL\)")
        run.wait_line(r"^\[launch\] restarting corridors \(1/5\)")
        pids["corridors"] = new_pid = _pid_of(run, "corridors", count=2)
        assert new_pid != pid
        # the restarted stage gets the latched scene by query and produces corridor sets again
        run.wait_line(r"^\[corridors\] .*scene loaded", count=2)
        run.proc.send_signal(signal.SIGHUP)
        code = run.wait()
    finally:
        kill_all([run.proc])
    assert code == 0, run.text()[-4000:]
    for node, node_pid in pids.items():
        alive = True
        try:
            os.kill(node_pid, 0)
        except ProcessLookupError:
            alive = False
        assert not alive, f"{node} (pid {node_pid}) still runs after the launcher's SIGHUP"
    info = inspect(str(rec))
    assert info["summary_present"] and not info["truncated"], info
    stamps_after = [
        bs.CorridorSet.decode(m.data).header.frame_index for m in read_messages(str(rec)) if m.topic.endswith("/corridors/corridor_set")
    ]
    assert stamps_after, "no corridor sets recorded"
    assert _last_stats(rec, "corridors").counters["processed"] > 0


def test_a_launcher_killed_hard_takes_its_nodes_with_it_and_the_recording_is_finished(tmp_path):
    """A launcher that dies without stopping anything (SIGKILL, a crash, the OOM killer): its nodes ran on headless,
    recording (70 MB more in 30 s in a new user's probe), holding the viewer's port, with nobody reading their logs.
    Each node now watches its launcher (``IAMP_LAUNCHER_PID``, ``stages.runtime.args.watch_launcher``) and stops as on
    Ctrl-C when it is gone: every node ends, and the recording is complete."""
    import os

    rec = tmp_path / "run.mcap"
    run = Launch(*K729, "--speed", "2", "--no-viewer", "--record", str(rec), "--run-id", "orphan", cwd=tmp_path)
    try:
        run.wait_line(r"^\[launch\] all \d+ nodes alive; starting sources")
        pids = {node: _pid_of(run, node) for node in ("source", "corridors", "markov_prediction", "recorder")}
        run.wait_line(r"^\[corridors\] .*scene loaded")  # frames are flowing
        run.proc.kill()
        run.proc.wait()

        def gone(pid: int) -> bool:
            try:
                os.kill(pid, 0)
            except ProcessLookupError:
                return True
            return False

        wait_until(lambda: all(gone(pid) for pid in pids.values()), 60,
                   f"every node gone after the launcher's SIGKILL: {[n for n, p in pids.items() if not gone(p)]}")
    finally:
        kill_all([run.proc])
        for pid in pids.values() if "pids" in locals() else ():
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
    info = inspect(str(rec))
    assert info["summary_present"] and not info["truncated"], info
    assert info["frames"]["iamp/orphan/source/track_frame"]["count"] > 0


def test_killed_recorder_is_restarted_into_the_next_split_and_the_run_goes_on(tmp_path):
    from mcap.reader import make_reader

    rec = tmp_path / "run.mcap"
    split1 = tmp_path / "run.001.mcap"
    run = Launch(*K729, "--speed", "2", "--no-viewer", "--record", str(rec), "--run-id", "killrec", "--set", "recorder.flush_period_s=0.2", cwd=tmp_path)

    def grids_in(path: Path) -> int:
        try:
            return sum(1 for m in read_messages(str(path)) if m.topic == "iamp/killrec/markov_prediction/motion_grid")
        except Exception:  # not created yet
            return 0

    try:
        run.wait_line(r"^\[launch\] all \d+ nodes alive; starting sources")
        pid = _pid_of(run, "recorder")
        wait_until(lambda: grids_in(rec) >= 3, 120, "predictions in the first recording")
        import os

        os.kill(pid, signal.SIGKILL)
        run.wait_line(r"^\[launch\] node recorder died \(signal SIGKILL\)")
        run.wait_line(r"^\[launch\] restarting recorder \(1/5\)")
        run.wait_line(r"^\[launch\] recording goes on in " + re.escape(str(split1)))
        assert _pid_of(run, "recorder", count=2) != pid
        # prediction never stopped: the restarted recorder records new predictions into the next split
        # ... and the scene, which the source published once before the restart: the restarted recorder asks for it (its
        # query is tried again until answered: under load the routes to the source's queryable take a moment)
        scene_in = lambda path: sum(1 for m in read_messages(str(path)) if m.topic == "iamp/killrec/source/scene") if path.exists() else 0  # noqa: E731
        wait_until(lambda: run.proc.poll() is not None or (grids_in(split1) >= 3 and scene_in(split1) >= 1), 120,
                   "predictions and the scene in the second split")
        if run.proc.poll() is None:
            run.proc.send_signal(signal.SIGINT)
        code = run.wait()
    finally:
        kill_all([run.proc])
    out = run.text()
    assert code == 0, out[-4000:]
    assert "stopping the run" not in out and "restarting corridors" not in out and "restarting markov_prediction" not in out
    assert f"recording saved: {split1} (" in out and f"recording saved: {rec} (" in out and "iamp recover" in out

    # the first split is torn: the standard reader cannot read it, our reader reads it up to its last chunk
    info = inspect(str(rec))
    assert info["truncated"] and not info["summary_present"]
    first = info["frames"]["iamp/killrec/source/track_frame"]
    assert first["count"] > 0 and first["first"] == 0 and first["strictly_increasing"] and first["missing"] == 0
    with pytest.raises(Exception):
        with open(rec, "rb") as f:
            list(make_reader(f).iter_messages())
    # ... and iamp recover makes it a finished file the standard reader reads whole
    fixed = tmp_path / "run.recovered.mcap"
    res = subprocess.run([sys.executable, "-m", "stages.cli", "recover", str(rec), str(fixed)], cwd=REPO, env=python_env(), capture_output=True, text=True, timeout=120)
    assert res.returncode == 0 and res.stdout.startswith(f"recovered {info['messages']} messages"), res.stdout + res.stderr
    with open(fixed, "rb") as f:
        recovered = [(c.topic, m.data) for _s, c, m in make_reader(f).iter_messages(log_time_order=False)]
    assert recovered == [(m.topic, m.data) for m in read_messages(str(rec))]

    # the second split was finished cleanly: the standard reader reads it whole, and it goes on where the first stopped
    with open(split1, "rb") as f:
        reader = make_reader(f)
        assert reader.get_summary() is not None
        later = [bs.TrackFrame.decode(m.data).header.frame_index for _s, c, m in reader.iter_messages(log_time_order=False) if c.topic == "iamp/killrec/source/track_frame"]
    assert later and later == sorted(later) and later[0] > first["last"]
    assert grids_in(split1) >= 1
    assert not (tmp_path / "run.002.mcap").exists()
    # ... and it holds the scene, which the source published once before the restart: the restarted recorder asked
    # for it (a replay of the second split alone waited for it forever)
    assert sum(m.topic == "iamp/killrec/source/scene" for m in read_messages(str(split1))) == 1


@pytest.fixture
def scenario_messages():
    """The first frames of the embedded scenario, made by the real source core."""
    from stages.runtime import NodeContext
    from stages.tracks_source import SPEC, TracksSourceConfig

    import logging

    core = SPEC.make_core(TracksSourceConfig(), NodeContext(run_id="bad", node_id="source", stage=SPEC.stage, log=logging.getLogger("t")))
    scene, frames = None, []
    for _stamp, result in core:
        scene = result.outputs.get("scene", scene)
        frames.append(result.outputs["track_frame"])
        if len(frames) == 3:
            break
    return scene, frames


def test_malformed_and_wrong_version_payloads_are_counted_and_the_stage_goes_on(tmp_path, scenario_messages):
    import msgpack

    from stages.runtime import BusClient

    scene, frames = scenario_messages
    port = free_port()
    got: list[int] = []
    stats: list[bs.NodeStats] = []
    with BusClient(listen=[endpoint(port)]) as bus:
        bus.subscribe("iamp/bad/corridors/corridor_set", lambda k, d: got.append(bs.CorridorSet.decode(d).header.frame_index))
        bus.subscribe("iamp/bad/_stats/corridors", lambda k, d: stats.append(bs.NodeStats.decode(d)))
        stage = start_module(
            "stages.corridors",
            "--run-id",
            "bad",
            "--connect",
            endpoint(port),
            "--input",
            "track_frame=source/track_frame",
            "--input",
            "scene=source/scene",
            "--stats-period",
            "0.2",
        )
        try:
            wait_until(lambda: "corridors" in bus.alive_now("iamp/bad/_alive/*", 0.5), 60, "corridors liveliness")
            put_scene = bus.publisher("iamp/bad/source/scene")
            put = bus.publisher("iamp/bad/source/track_frame")
            put(frames[0].encode())  # a frame that overtakes the (latched) scene is held, not dropped
            put_scene(scene.encode())
            wait_until(lambda: got == [frames[0].header.frame_index], 30, "the first corridor set")
            put(b"\x93not an envelope")
            env = msgpack.unpackb(frames[1].encode(), raw=False)
            env["v"] = 99
            put(msgpack.packb(env, use_bin_type=True))
            put(frames[2].encode())
            wait_until(lambda: len(got) == 2, 30, "the corridor set after the bad payloads")
            assert got == [frames[0].header.frame_index, frames[2].header.frame_index]
            wait_until(lambda: stats and stats[-1].counters["decode_errors"] == 2, 30, "stats with 2 decode errors")
            s = stats[-1]
            assert s.errors_by_kind == {"MalformedPayload": 1, "WrongVersion": 1}
            assert s.counters["processed"] == 2
            assert stage.poll() is None  # still running
            assert stop_process(stage) == 0
        finally:
            kill_all([stage])
    log = Path(stage.log_path).read_text()
    assert "dropped message: reason=MalformedPayload key=iamp/bad/source/track_frame" in log
    assert "dropped message: reason=WrongVersion key=iamp/bad/source/track_frame detail=iamp.TrackFrame v99 on iamp/bad/source/track_frame: this build reads v2 (and v1)" in log
