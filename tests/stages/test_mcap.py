"""Recorder, replay and inspect on a real Zenoh bus (loopback) with real MCAP files.

Every wait polls a condition (liveliness, a matching subscriber, messages
on disk, a process exit) until a deadline; nothing sleeps for a fixed time.
"""

from __future__ import annotations

import collections
import json
import queue
import signal
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from testkit import helpers as h

from bus_schemas import Header, Progress, SceneInfo, TrackFrame, keys
from stages.recorder.inspect import ReadReport, RecordingError, inspect, read_messages
from stages.recorder.core import McapRecorder, RecorderConfig
from stages.replay.core import MAX_SPEED_WINDOW
from stages.runtime import BusClient

N_FRAMES = 40
STAMP0_NS = 1_700_000_000_000_000_000
GARBAGE = b"\xc1 this is not msgpack"


def make_frame(i: int, run_id: str, n_agents: int = 12) -> TrackFrame:
    rng = np.random.default_rng(i)
    return TrackFrame(
        header=Header(run_id=run_id, frame_index=i, stamp_ns=STAMP0_NS + i * 100_000_000, producer="source"),
        scene_id="scene0",
        track_ids=np.arange(100, 100 + n_agents, dtype=np.int64),
        agent_types=np.ones(n_agents, dtype=np.uint8),
        x_m=rng.normal(0.0, 20.0, n_agents),
        y_m=rng.normal(0.0, 20.0, n_agents),
        vx_mps=rng.normal(0.0, 5.0, n_agents),
        vy_mps=rng.normal(0.0, 5.0, n_agents),
        yaw_rad=rng.uniform(-np.pi, np.pi, n_agents),
        length_m=np.full(n_agents, 4.5),
        width_m=np.full(n_agents, 1.9),
    )


def make_scene(run_id: str) -> SceneInfo:
    return SceneInfo(
        header=Header(run_id=run_id, frame_index=0, stamp_ns=STAMP0_NS, producer="source"),
        scene_id="scene0",
        recording="test",
        location_id="loc0",
        map_name="nonexistent.osm",
        map_sha256="0" * 64,
        projection="utm",
        origin_lat_deg=48.0,
        origin_lon_deg=8.0,
        frame_rate_hz=10.0,
        speed_limit_mps=13.9,
        n_frames=N_FRAMES,
    )


def data_messages(path: Path, report: ReadReport | None = None) -> list:
    """Messages on data keys (no _stats/_ack) of a recording, also of one still being written."""
    out = []
    for m in read_messages(str(path), report):
        try:
            if keys.parse_key(m.topic).is_infrastructure:
                continue
        except keys.KeyFormatError:
            pass
        out.append(m)
    return out


def count_on_disk(path: Path, report: ReadReport | None = None) -> int:
    try:
        return len(data_messages(path, report))
    except RecordingError:  # not created yet, or still empty
        return 0


def recorder_args(run_id: str, port: int, path: Path, **params) -> list[str]:
    return ["--run-id", run_id, "--connect", h.endpoint(port), "--params-json", json.dumps({"path": str(path), **params})]


@pytest.fixture
def procs():
    started: list[subprocess.Popen] = []
    yield started
    h.kill_all(started)


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """A recorder process records a scene, N_FRAMES frames and a garbage payload, then stops on SIGINT."""
    tmp = tmp_path_factory.mktemp("rec")
    path = tmp / "t1.mcap"
    port = h.free_port()
    sent: list[tuple[str, bytes]] = []
    started: list[subprocess.Popen] = []
    try:
        with BusClient(listen=[h.endpoint(port)]) as bus:
            alive = h.AliveSet(bus, keys.alive_pattern("t1"))
            rec = h.start_module("stages.recorder", *recorder_args("t1", port, path, flush_period_s=0.2), log_dir=tmp)
            started.append(rec)
            alive.wait_for(["recorder"])
            frame_key = keys.data_key("t1", "source", "track_frame")
            put_frame, matching = bus.publisher_with_matching(frame_key)
            h.wait_until(matching, 20, "the recorder's subscriber to match")
            scene = make_scene("t1").encode()
            bus.put(keys.data_key("t1", "source", "scene"), scene)
            sent.append((keys.data_key("t1", "source", "scene"), scene))
            for i in range(N_FRAMES):
                data = make_frame(i, "t1").encode()
                put_frame(data)
                sent.append((frame_key, data))
            bad_key = keys.data_key("t1", "bad", "payload")
            bus.put(bad_key, GARBAGE)
            sent.append((bad_key, GARBAGE))
            # the periodic flush puts everything on disk while the recorder still runs
            h.wait_until(lambda: count_on_disk(path) >= len(sent), 20, f"{len(sent)} messages on disk")
            rc = h.stop_process(rec, signal.SIGINT)
        output = h.output_of(rec)
        assert rc == 0, output
        return {"path": path, "sent": sent, "output": output, "tmp": tmp}
    finally:
        h.kill_all(started)


def test_recorder_writes_one_channel_per_key_with_counts_frames_and_summary(recorded):
    info = inspect(str(recorded["path"]))
    channels = {c["topic"]: c for c in info["channels"]}
    assert channels["iamp/t1/source/track_frame"] == {"topic": "iamp/t1/source/track_frame", "schema": "iamp.TrackFrame", "count": N_FRAMES}
    assert channels["iamp/t1/source/scene"] == {"topic": "iamp/t1/source/scene", "schema": "iamp.SceneInfo", "count": 1}
    assert channels["iamp/t1/bad/payload"] == {"topic": "iamp/t1/bad/payload", "schema": "", "count": 1}
    assert channels["iamp/t1/_stats/recorder"]["schema"] == "iamp.NodeStats"
    frames = info["frames"]["iamp/t1/source/track_frame"]
    assert frames["count"] == N_FRAMES and frames["first"] == 0 and frames["last"] == N_FRAMES - 1
    assert frames["strictly_increasing"] is True and frames["gaps"] == [] and frames["undecodable"] == 0
    assert info["summary_present"] is True and info["truncated"] is False
    assert info["metadata"]["hybrid-iamp"]["run_id"] == "t1"
    assert info["start_ns"] <= info["end_ns"]
    # payloads are recorded byte for byte, in the order they were sent
    got = [(m.topic, m.data) for m in data_messages(recorded["path"])]
    assert got == recorded["sent"]
    # header stamps become the publish time
    stamps = [m.publish_time_ns for m in read_messages(str(recorded["path"])) if m.schema == "iamp.TrackFrame"]
    assert stamps == [STAMP0_NS + i * 100_000_000 for i in range(N_FRAMES)]
    out = recorded["output"]
    assert f"recording: path={recorded['path']} run=t1" in out
    assert f"recording closed: path={recorded['path']} messages=" in out
    assert "kind=unrecognised_payload" in out


def test_recording_has_jsonschema_schemas_msgpack_channels_and_a_summary(recorded):
    with open(recorded["path"], "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        schemas = {s.name: s for s in summary.schemas.values()}
        assert schemas["iamp.TrackFrame"].encoding == "jsonschema"
        assert json.loads(schemas["iamp.TrackFrame"].data)["title"] == "iamp.TrackFrame"
        by_topic = {c.topic: c for c in summary.channels.values()}
        assert all(c.message_encoding == "msgpack" for c in by_topic.values())
        assert by_topic["iamp/t1/bad/payload"].schema_id == 0
        assert summary.statistics.message_count == sum(1 for _ in read_messages(str(recorded["path"])))
        assert summary.chunk_indexes, "chunked file"
        assert {ci.compression for ci in summary.chunk_indexes} == {"zstd"}


def test_killed_recorder_leaves_a_file_that_reads_up_to_its_last_chunk(tmp_path, procs):
    path = tmp_path / "killed.mcap"
    port = h.free_port()
    sent: list[bytes] = []
    with BusClient(listen=[h.endpoint(port)]) as bus:
        alive = h.AliveSet(bus, keys.alive_pattern("t1"))
        # small chunks, no periodic flush: chunks are closed by size only
        rec = h.start_module("stages.recorder", *recorder_args("t1", port, path, chunk_size_bytes=2048, flush_period_s=600.0), log_dir=tmp_path)
        procs.append(rec)
        alive.wait_for(["recorder"])
        put, matching = bus.publisher_with_matching(keys.data_key("t1", "source", "track_frame"))
        h.wait_until(matching, 20, "the recorder's subscriber to match")

        def chunks_on_disk() -> int:
            report = ReadReport()
            count_on_disk(path, report)
            return report.chunks

        def publish_until_chunks(n_chunks: int) -> bool:
            for _ in range(3):
                data = make_frame(len(sent), "t1").encode()
                put(data)
                sent.append(data)
            return chunks_on_disk() >= n_chunks

        h.wait_until(lambda: publish_until_chunks(8), 30, "8 complete chunks on disk")
        for _ in range(2):  # likely still in the open chunk when the recorder dies
            data = make_frame(len(sent), "t1").encode()
            put(data)
            sent.append(data)
        rec.kill()
        rec.wait(timeout=20)
    assert rec.returncode == -signal.SIGKILL

    report = ReadReport()
    frames = [m for m in read_messages(str(path), report) if m.schema == "iamp.TrackFrame"]
    assert report.truncated is True and report.summary_present is False
    assert report.chunks >= 8
    assert 0 < len(frames) <= len(sent)
    indices = [TrackFrame.decode(m.data).header.frame_index for m in frames]
    assert indices == list(range(len(frames))), "a gap-free prefix of what was sent"
    assert [m.data for m in frames] == sent[: len(frames)]
    info = inspect(str(path))
    assert info["truncated"] is True and info["summary_present"] is False
    assert info["frames"]["iamp/t1/source/track_frame"]["strictly_increasing"] is True
    print(f"kill -9: recovered {len(frames)} of {len(sent)} frames in {report.chunks} chunks")


def _record_replay(tmp: Path, procs: list, src: Path, run_id: str, replay_cmd: list[str], expected: int) -> tuple[Path, str]:
    """Start a recorder for ``run_id``, run ``replay_cmd`` (connect flag appended) to completion, stop the recorder."""
    path = tmp / f"{run_id}.mcap"
    port = h.free_port()
    with BusClient(listen=[h.endpoint(port)]) as bus:
        alive = h.AliveSet(bus, keys.alive_pattern(run_id))
        rec = h.start_module("stages.recorder", *recorder_args(run_id, port, path, flush_period_s=0.2), log_dir=tmp)
        procs.append(rec)
        alive.wait_for(["recorder"])
        rp = h.start_module(*replay_cmd, "--connect", h.endpoint(port), log_dir=tmp)
        procs.append(rp)
        rp.wait(timeout=60)
        replay_out = h.output_of(rp)
        assert rp.returncode == 0, replay_out
        h.wait_until(lambda: count_on_disk(path) >= expected, 30, f"{expected} replayed messages on disk")
        assert h.stop_process(rec, signal.SIGINT) == 0, h.output_of(rec)
    return path, replay_out


def _by_topic(messages) -> dict[str, list[bytes]]:
    out: dict[str, list[bytes]] = collections.defaultdict(list)
    for m in messages:
        out[m.topic].append(m.data)
    return dict(out)


def test_replay_into_a_second_recorder_gives_identical_payloads(recorded, procs):
    src = recorded["path"]
    original = data_messages(src)
    cmd = ["stages.replay", "--run-id", "t2", "--params-json", json.dumps({"path": str(src), "speed": 1.0})]
    path, out = _record_replay(recorded["tmp"], procs, src, "t2", cmd, len(original))
    again = data_messages(path)
    assert len(again) == len(original)
    want = {keys.replace_run(t, "t2"): d for t, d in _by_topic(original).items()}
    assert _by_topic(again) == want
    assert inspect(str(path))["summary_present"] is True
    assert f"replay finished: messages={len(original)}" in out


def test_replay_at_max_speed_loses_nothing_into_a_recorder(tmp_path, procs):
    src = tmp_path / "big.mcap"
    n = 3000
    with McapRecorder(RecorderConfig(path=str(src)), "t1") as rec:
        rec.handle(keys.data_key("t1", "source", "scene"), make_scene("t1").encode(), STAMP0_NS)
        for i in range(n):
            rec.handle(keys.data_key("t1", "source", "track_frame"), make_frame(i, "t1", n_agents=4).encode(), STAMP0_NS + i * 100_000_000)
    original = data_messages(src)
    cmd = ["stages.cli", "replay", str(src), "--speed", "max", "--run-id", "t3"]
    path, out = _record_replay(tmp_path, procs, src, "t3", cmd, n + 1)
    again = data_messages(path)
    assert len(again) == n + 1
    assert _by_topic(again) == {keys.replace_run(t, "t3"): d for t, d in _by_topic(original).items()}
    assert f"replay finished: messages={n + 1}" in out


def test_replay_at_max_speed_stays_a_small_window_ahead_of_acking_nodes(tmp_path, procs):
    """A consumer that acks Progress (like every operator) is never more than the window behind."""
    src = tmp_path / "paced.mcap"
    n = 300
    with McapRecorder(RecorderConfig(path=str(src)), "t1") as rec:
        rec.handle(keys.data_key("t1", "source", "scene"), make_scene("t1").encode(), STAMP0_NS)
        for i in range(n):
            rec.handle(keys.data_key("t1", "source", "track_frame"), make_frame(i, "t1", n_agents=4).encode(), STAMP0_NS + i)
    inbox: queue.Queue = queue.Queue()
    state = {"acked": -1, "lead": 0, "handled": 0}
    port = h.free_port()
    with BusClient(listen=[h.endpoint(port)]) as bus:
        ack = bus.publisher(keys.ack_key("t4", "op"))

        def on_frame(_key: str, data: bytes) -> None:
            frame = TrackFrame.decode(data)
            state["lead"] = max(state["lead"], frame.header.frame_index - state["acked"])
            inbox.put(frame)

        def work() -> None:
            while (frame := inbox.get()) is not None:
                state["acked"] = frame.header.frame_index
                state["handled"] += 1
                ack(Progress(node_id="op", last_stamp_ns=frame.header.stamp_ns, last_frame_index=frame.header.frame_index, handled=state["handled"]).encode())

        worker = threading.Thread(target=work, daemon=True)
        worker.start()
        bus.subscribe(keys.data_key("t4", "source", "track_frame"), on_frame)
        bus.declare_token(keys.alive_key("t4", "op"))
        rp = h.start_module("stages.cli", "replay", str(src), "--speed", "max", "--run-id", "t4", "--connect", h.endpoint(port), log_dir=tmp_path)
        procs.append(rp)
        rp.wait(timeout=60)
        out = h.output_of(rp)
        assert rp.returncode == 0, out
        h.wait_until(lambda: state["handled"] == n, 20, f"{n} frames handled")
        inbox.put(None)
    assert f"replay finished: messages={n + 1}" in out
    assert "no longer waiting" not in out
    assert 1 <= state["lead"] <= MAX_SPEED_WINDOW


def test_read_messages_stops_cleanly_where_a_file_is_cut(tmp_path):
    full = tmp_path / "full.mcap"
    with McapRecorder(RecorderConfig(path=str(full), chunk_size_bytes=1024), "t1") as rec:
        for i in range(60):
            rec.handle(keys.data_key("t1", "source", "track_frame"), make_frame(i, "t1").encode(), STAMP0_NS + i)
    data = full.read_bytes()
    everything = [m.data for m in read_messages(str(full))]
    assert len(everything) == 60
    cut = tmp_path / "cut.mcap"
    for size in (len(data) - 1, len(data) // 2, len(data) // 3 + 7):
        cut.write_bytes(data[:size])
        report = ReadReport()
        got = [m.data for m in read_messages(str(cut), report)]
        assert report.truncated is True and report.error
        assert got == everything[: len(got)]
    cut.write_bytes(data[: len(data) // 2])
    assert 0 < len(list(read_messages(str(cut)))) < 60


def test_inspect_cli_json_and_bad_files(recorded, tmp_path):
    run = subprocess.run([sys.executable, "-m", "stages.cli", "inspect", str(recorded["path"]), "--json"], cwd=h.REPO, env=h.python_env(), capture_output=True, text=True, timeout=60)
    assert run.returncode == 0, run.stderr
    info = json.loads(run.stdout)
    assert {"channels", "start_ns", "end_ns"} <= set(info)
    assert all(set(c) == {"topic", "schema", "count"} for c in info["channels"])
    assert isinstance(info["start_ns"], int) and isinstance(info["end_ns"], int)
    table = subprocess.run([sys.executable, "-m", "stages.cli", "inspect", str(recorded["path"])], cwd=h.REPO, env=h.python_env(), capture_output=True, text=True, timeout=60)
    assert table.returncode == 0 and "iamp/t1/source/track_frame" in table.stdout
    garbage = tmp_path / "garbage.mcap"
    garbage.write_bytes(b"definitely not an mcap file")
    for bad in (garbage, tmp_path / "missing.mcap"):
        res = subprocess.run([sys.executable, "-m", "stages.cli", "inspect", str(bad), "--json"], cwd=h.REPO, env=h.python_env(), capture_output=True, text=True, timeout=60)
        assert res.returncode == 2 and str(bad) in res.stderr
    res = subprocess.run([sys.executable, "-m", "stages.cli", "frobnicate"], cwd=h.REPO, env=h.python_env(), capture_output=True, text=True, timeout=60)
    assert res.returncode == 2 and "usage" in res.stderr


def test_payloads_of_an_older_version_replay_paced_and_with_their_scene_latched(tmp_path):
    """The recorder writes older-version payloads without an MCAP schema; the player reads the envelope instead.

    Before, such a file went out unpaced (no stamps) and its scene was not
    latched (no queryable): a stage that missed the scene's one put held every
    frame in its join window and lost the oldest (seen in CI: 64 of 71 frames).
    """
    import msgpack

    from stages.replay.core import RecordingPlayer, ReplayConfig

    path = tmp_path / "old.mcap"
    writer = McapRecorder(RecorderConfig(path=str(path)), run_id="t1")
    msgs = [(keys.data_key("t1", "source", "scene"), make_scene("t1").encode())]
    msgs += [(keys.data_key("t1", "source", "track_frame"), make_frame(i, "t1").encode()) for i in range(3)]
    for i, (key, data) in enumerate(msgs):
        env = msgpack.unpackb(data, raw=False)
        env["v"] -= 1  # the version before Header.source_wall_ns
        del env["body"]["header"]["source_wall_ns"]
        writer.handle(key, msgpack.packb(env, use_bin_type=True), STAMP0_NS + i)
    writer.handle(keys.data_key("t1", "bad", "payload"), GARBAGE, STAMP0_NS + 9)
    writer.close()
    assert writer.old_versions == 4
    assert {m.schema for m in read_messages(str(path))} == {""}  # as recorded: no MCAP schema on these channels
    out = list(RecordingPlayer(ReplayConfig(path=str(path), speed="max"), "t2"))
    assert [o.schema for o in out] == [SceneInfo.SCHEMA] + [TrackFrame.SCHEMA] * 3 + [""]
    assert [o.stamp_ns for o in out] == [None] + [STAMP0_NS + i * 100_000_000 for i in range(3)] + [None]  # frames are acked, the scene is not


def test_replay_of_a_foreign_file_or_of_no_node_says_so_and_exits_2(recorded, tmp_path):
    """A foreign MCAP (or --node naming nothing the file has) replayed nothing and said `replay finished`, exit 0."""
    from mcap.writer import Writer

    foreign = tmp_path / "foreign.mcap"
    with open(foreign, "wb") as f:
        w = Writer(f)
        w.start()
        cid = w.register_channel(topic="/camera", message_encoding="json", schema_id=w.register_schema(name="x", encoding="jsonschema", data=b"{}"))
        for i in range(5):
            w.add_message(channel_id=cid, log_time=i, data=b"{}", publish_time=i)
        w.finish()
    for args, want in (([str(foreign)], "not a hybrid-iamp recording"),
                       ([str(recorded["path"]), "--node", "nosuch"], "--node names nodes the recording does not have: nosuch; its nodes: ")):
        done = subprocess.run([sys.executable, "-m", "stages.cli", "replay", *args, "--speed", "max"], capture_output=True, text=True,
                              timeout=120, env=h.python_env())
        assert done.returncode == 2 and want in done.stderr, (args, done.stderr[-2000:])
