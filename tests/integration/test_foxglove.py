"""Foxglove: a real run served live over the Foxglove WebSocket protocol, then its recording exported and decoded.

One launcher run (embedded scenario, ``--foxglove``, recorded) serves both
tests: a WebSocket client on loopback checks the advertised channels and decodes a ``foxglove.SceneUpdate`` with
the protobuf schema the server advertised; then ``iamp export foxglove`` turns
the run's recording into Foxglove's schemas, and every channel of the output
is decoded with the schemas written in the file (protobuf FileDescriptorSets
of foxglove-sdk, JSON Schema for the statistics) and checked against the
recording's own messages for a known frame.

Subprotocol: foxglove-sdk's server (0.30) speaks the Foxglove WebSocket
protocol under the name ``foxglove.sdk.v1`` (the same messages as
``foxglove.websocket.v1``, renamed by Foxglove) and refuses a client that
offers only the old name; the client offers both, as current Foxglove and
Lichtblick do.
"""

from __future__ import annotations

import asyncio
import base64
import json
import math
import os
import re
import signal
import struct
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

import bus_schemas as bs
from testkit.helpers import REPO, python_env, wait_until

pytest.importorskip("foxglove")
descriptor_pb2 = pytest.importorskip("google.protobuf.descriptor_pb2")
from google.protobuf import descriptor_pool, message_factory  # noqa: E402

RUN_ID = "fox"


class Launch:
    """launch.py as a child process; its output lines are collected as they come."""

    def __init__(self, *args: str, cwd: Path) -> None:
        self.lines: list[str] = []
        self.proc = subprocess.Popen([sys.executable, str(REPO / "launch.py"), *args], cwd=cwd, env=python_env(), stdout=subprocess.PIPE,
                                     stderr=subprocess.STDOUT, text=True, start_new_session=True)
        threading.Thread(target=self._pump, daemon=True).start()

    def _pump(self) -> None:
        for line in self.proc.stdout:
            self.lines.append(line.rstrip("\n"))

    def wait_line(self, pattern: str, timeout_s: float = 120.0) -> re.Match:
        rx = re.compile(pattern)
        try:
            return wait_until(lambda: next((m for m in map(rx.search, list(self.lines)) if m), None), timeout_s, f"line {pattern!r}")
        except AssertionError:
            raise AssertionError(f"no line matching {pattern!r}; output:\n" + "\n".join(self.lines[-60:])) from None

    def stop(self, timeout_s: float = 120.0) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
        try:
            return self.proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            raise


def message_class(schema_name: str, descriptor_set: bytes):
    """The protobuf class of ``schema_name`` from a serialized FileDescriptorSet (as MCAP and the WebSocket carry it)."""
    fds = descriptor_pb2.FileDescriptorSet.FromString(descriptor_set)
    pool = descriptor_pool.DescriptorPool()
    for f in fds.file:
        pool.Add(f)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(schema_name))


async def _client(url: str, want_topics: set[str], timeout_s: float) -> dict:
    """Connect as Foxglove does, subscribe to every advertised channel, collect until a SceneUpdate with cubes and every wanted topic arrived."""
    import websockets

    got: dict = {"server_info": None, "channels": {}, "messages": {}, "subscriptions": {}, "advertised_at": {}}
    async with websockets.connect(url, subprotocols=["foxglove.sdk.v1", "foxglove.websocket.v1"], max_size=None) as ws:
        got["subprotocol"] = ws.subprotocol
        subs: dict[int, int] = got["subscriptions"]
        loop = asyncio.get_running_loop()
        end = loop.time() + timeout_s
        while loop.time() < end:
            try:
                raw = await asyncio.wait_for(ws.recv(), timeout=max(0.1, end - loop.time()))
            except asyncio.TimeoutError:
                break
            if isinstance(raw, str):
                msg = json.loads(raw)
                if msg.get("op") == "serverInfo":
                    got["server_info"] = msg
                elif msg.get("op") == "advertise":
                    new = []
                    for ch in msg["channels"]:
                        got["channels"][ch["id"]] = ch
                        got["advertised_at"][ch["topic"]] = round(loop.time() - end + timeout_s, 2)
                        sub_id = len(subs) + 1
                        subs[sub_id] = ch["id"]
                        new.append({"id": sub_id, "channelId": ch["id"]})
                    await ws.send(json.dumps({"op": "subscribe", "subscriptions": new}))
                continue
            if raw[0] != 1:  # MESSAGE_DATA: opcode, subscription id (u32), log time (u64), payload
                continue
            sub_id, log_time = struct.unpack_from("<IQ", raw, 1)
            ch = got["channels"][subs[sub_id]]
            got["messages"].setdefault(ch["topic"], []).append((log_time, bytes(raw[13:])))
            objects = got["messages"].get("/objects", [])
            if want_topics <= set(got["messages"]) and objects:
                break
    return got


@pytest.fixture(scope="module")
def live_run(tmp_path_factory):
    """The hybrid pipeline on the embedded scenario with --foxglove, a client connected while it plays, then stopped."""
    tmp = tmp_path_factory.mktemp("foxglove")
    rec = tmp / "run.mcap"
    run = Launch("--foxglove", "--set", "foxglove.port=0", "--no-viewer", "--record", str(rec), "--run-id", RUN_ID, "--speed", "1", cwd=tmp)
    try:
        url = run.wait_line(r"^\[launch\] foxglove: (ws://127\.0\.0\.1:\d+)$").group(1)
        want = {"/map", "/objects", "/markov_prediction/means", "/markov_prediction/motion_grid"}
        got = asyncio.run(_client(url, want, timeout_s=120.0))
    finally:
        code = run.stop()
    assert code == 0, "\n".join(run.lines[-40:])
    return {"url": url, "got": got, "recording": rec, "tmp": tmp, "lines": run.lines}


def test_live_bridge_advertises_the_scene_and_sends_scene_updates_over_loopback(live_run):
    got = live_run["got"]
    assert got["subprotocol"] == "foxglove.sdk.v1"
    assert got["server_info"] is not None and got["server_info"]["name"] == f"hybrid-iamp {RUN_ID}"
    by_topic = {ch["topic"]: ch for ch in got["channels"].values()}
    for topic, schema in (("/map", "foxglove.SceneUpdate"), ("/tf", "foxglove.FrameTransform"), ("/objects", "foxglove.SceneUpdate"),
                          ("/markov_prediction/means", "foxglove.SceneUpdate"), ("/markov_prediction/motion_grid", "foxglove.Grid")):
        assert topic in by_topic, f"{topic} not advertised: {sorted(by_topic)}"
        assert by_topic[topic]["schemaName"] == schema and by_topic[topic]["encoding"] == "protobuf"
    # a SceneUpdate from the wire, decoded with the schema the server advertised
    ch = by_topic["/objects"]
    SceneUpdate = message_class(ch["schemaName"], base64.b64decode(ch["schema"]))
    log_time, payload = got["messages"]["/objects"][-1]
    update = SceneUpdate.FromString(payload)
    (entity,) = update.entities
    assert entity.id == "objects" and entity.frame_id == "map"
    assert len(entity.cubes) >= 1 and len(entity.texts) == len(entity.cubes)
    assert all(t.text.isdigit() for t in entity.texts)
    # the map arrived too (a subscriber to /map gets it again with the next frame), with lines
    counts = {t: len(m) for t, m in got["messages"].items()}
    assert "/map" in got["messages"], (
        f"no /map message; messages per topic {counts}; channel ids {({t: c['id'] for t, c in by_topic.items()})}; subscriptions"
        f" {got['subscriptions']}; advertised (s after connecting) {got['advertised_at']}; the run's last lines:\n"
        + "\n".join(live_run["lines"][-30:]))
    Map = message_class(by_topic["/map"]["schemaName"], base64.b64decode(by_topic["/map"]["schema"]))
    (lanelets,) = Map.FromString(got["messages"]["/map"][-1][1]).entities
    assert lanelets.id == "lanelets" and sum(len(line.points) for line in lanelets.lines) > 100


def _decode_file(path: Path) -> dict[str, list[tuple[int, object, str]]]:
    """Every message of an MCAP file decoded with the schema stored in the file: {topic: [(log_time, message, schema name)]}."""
    from mcap.reader import make_reader

    classes: dict[int, object] = {}
    out: dict[str, list] = {}
    with open(path, "rb") as f:
        reader = make_reader(f)
        for schema, channel, message in reader.iter_messages():
            if channel.message_encoding == "protobuf":
                assert schema.encoding == "protobuf"
                if schema.id not in classes:
                    classes[schema.id] = message_class(schema.name, schema.data)
                decoded = classes[schema.id].FromString(message.data)
            else:
                assert channel.message_encoding == "json" and schema.encoding == "jsonschema", (channel.topic, channel.message_encoding)
                decoded = json.loads(message.data)
                for key, spec in json.loads(schema.data)["properties"].items():
                    assert key in decoded
                    if spec["type"] == "number" and decoded[key] is not None:
                        assert isinstance(decoded[key], (int, float))
            out.setdefault(channel.topic, []).append((message.log_time, decoded, schema.name))
    return out


def test_export_decodes_every_channel_with_the_official_schemas(live_run, tmp_path):
    from stages.cli import main as iamp
    from stages.foxglove_bridge.scene import CORRIDOR_THICKNESS_M, belief_text, grid_values
    from stages.recorder.inspect import inspect, read_messages

    rec = live_run["recording"]
    out = tmp_path / "fox.mcap"
    assert iamp(["export", "foxglove", str(rec), str(out)]) == 0
    mask = os.umask(0)
    os.umask(mask)
    assert out.stat().st_mode & 0o777 == 0o666 & ~mask  # a new file's mode, not the temporary file's 0600
    decoded = _decode_file(out)
    schemas = {t: {m[2] for m in msgs} for t, msgs in decoded.items()}
    expected = {
        "/map": "foxglove.SceneUpdate", "/tf": "foxglove.FrameTransform", "/objects": "foxglove.SceneUpdate",
        "/markov_prediction/corridors": "foxglove.SceneUpdate", "/markov_prediction/means": "foxglove.SceneUpdate",
        "/markov_prediction/motion_grid": "foxglove.Grid", "/intentions/vehicles": "foxglove.SceneUpdate",
        "/stats/markov_prediction": "iamp.NodeStatsPlot", "/stats/source": "iamp.NodeStatsPlot",
    }
    for topic, schema in expected.items():
        assert schemas.get(topic) == {schema}, f"{topic}: {schemas.get(topic)}"

    # the recording's own messages of one known frame: the newest frame that has predictions, a grid and a belief
    recorded: dict[str, dict[int, tuple[int, object]]] = {}
    for m in read_messages(str(rec)):
        if m.schema in ("iamp.TrackFrame", "iamp.CorridorPredictions", "iamp.MotionGrid", "iamp.IntentionBelief", "iamp.CorridorSet"):
            msg = bs.decode(m.data)
            recorded.setdefault(m.schema, {})[msg.header.stamp_ns] = (m.log_time_ns, msg)
    stamps = set(recorded["iamp.TrackFrame"]) & set(recorded["iamp.CorridorPredictions"]) & set(recorded["iamp.MotionGrid"]) & set(recorded["iamp.IntentionBelief"]) & set(recorded["iamp.CorridorSet"])
    stamps = [s for s in stamps if len(recorded["iamp.CorridorPredictions"][s][1].predictions) and len(recorded["iamp.IntentionBelief"][s][1].vehicles)]
    assert stamps, "no frame with predictions, a grid and a belief in the recording"
    stamp = max(stamps)

    def at(topic: str, kind: str, *partners: str):
        # logged when the message and the partners it is drawn with are all in: at the latest of their log times
        log_time = max(recorded[k][stamp][0] for k in (kind, *partners))
        hits = [d for t, d, _ in decoded[topic] if t == log_time and (d.entities[0] if hasattr(d, "entities") else d).timestamp.seconds * 10**9 + (d.entities[0] if hasattr(d, "entities") else d).timestamp.nanos == stamp]
        assert len(hits) == 1, f"{topic}: {len(hits)} messages at log time {log_time} with stamp {stamp}"
        return hits[0]

    # objects: a cube per object at its position, coloured by type, its id as text
    frame = recorded["iamp.TrackFrame"][stamp][1]
    (objects,) = at("/objects", "iamp.TrackFrame").entities
    finite = np.isfinite(frame.x_m) & np.isfinite(frame.y_m)
    assert len(objects.cubes) == int(finite.sum())
    assert [t.text for t in objects.texts] == [str(int(i)) for i in frame.track_ids[finite]]
    np.testing.assert_allclose([c.pose.position.x for c in objects.cubes], frame.x_m[finite], atol=1e-9)
    np.testing.assert_allclose([c.pose.position.y for c in objects.cubes], frame.y_m[finite], atol=1e-9)
    cars = [c for c, t in zip(objects.cubes, frame.agent_types[finite]) if t == bs.AgentType.CAR]
    assert all((round(c.color.r, 2), round(c.color.g, 2), round(c.color.b, 2)) == (0.12, 0.56, 1.0) for c in cars)

    # corridors: thickness from P(route); means: one sphere per finite mean of every step
    pred = recorded["iamp.CorridorPredictions"][stamp][1]
    (corr,) = at("/markov_prediction/corridors", "iamp.CorridorPredictions", "iamp.CorridorSet").entities
    probs = sorted(CORRIDOR_THICKNESS_M[0] + CORRIDOR_THICKNESS_M[1] * p.probability for p in pred.predictions)
    assert sorted(line.thickness for line in corr.lines) == pytest.approx(probs, abs=1e-6)
    (means,) = at("/markov_prediction/means", "iamp.CorridorPredictions").entities
    n_means = sum(int((np.isfinite(p.mean_x_m) & np.isfinite(p.mean_y_m)).sum()) for p in pred.predictions)
    assert len(means.spheres) == n_means and means.id == f"means/{pred.mode}"

    # the grid: float32 occupancy, the maximum over the steps, cropped; its cells equal the recorded grid's
    grid_msg = recorded["iamp.MotionGrid"][stamp][1]
    grid = at("/markov_prediction/motion_grid", "iamp.MotionGrid")
    assert [f.name for f in grid.fields] == ["occupancy"] and grid.cell_stride == 4 and grid.row_stride == 4 * grid.column_count
    values = np.frombuffer(grid.data, dtype="<f4").reshape(-1, grid.column_count)
    dense = grid_values(grid_msg, None)
    c0 = round((grid.pose.position.x - grid_msg.origin_x_m) / grid_msg.cell_m)
    r0 = round((grid.pose.position.y - grid_msg.origin_y_m) / grid_msg.cell_m)
    np.testing.assert_array_equal(values, dense[r0 : r0 + values.shape[0], c0 : c0 + values.shape[1]])
    assert values.sum() == pytest.approx(float(dense.sum()), rel=1e-6)  # the crop dropped only zeros

    # per-vehicle texts: P(stop) and the top route of every vehicle of the frame
    belief = recorded["iamp.IntentionBelief"][stamp][1]
    (texts,) = at("/intentions/vehicles", "iamp.IntentionBelief", "iamp.TrackFrame").entities
    assert sorted(t.text for t in texts.texts) == sorted(belief_text(v) for v in belief.vehicles if v.track_id in set(frame.track_ids.tolist()))

    # the map and its transform
    (lanelets,) = decoded["/map"][0][1].entities
    assert sum(len(line.points) for line in lanelets.lines) > 100
    tf = decoded["/tf"][0][1]
    assert (tf.parent_frame_id, tf.child_frame_id, tf.rotation.w) == ("world", "map", 1.0)

    # stats: plottable numbers
    last = decoded["/stats/markov_prediction"][-1][1]
    assert last["node_id"] == "markov_prediction" and last["counters"]["processed"] > 0 and math.isfinite(last["proc_ms_p50"])

    # iamp inspect lists the exported channels with their schema names and counts
    info = inspect(str(out))
    listed = {c["topic"]: (c["schema"], c["count"]) for c in info["channels"]}
    for topic, msgs in decoded.items():
        assert listed[topic] == (msgs[0][2], len(msgs))


def test_export_refuses_truncated_foreign_and_missing_input_with_one_line(live_run, tmp_path, capsys):
    from stages.cli import main as iamp

    rec = live_run["recording"]
    cases = {}
    head = tmp_path / "head.mcap"
    head.write_bytes(rec.read_bytes()[:12])  # magic and a torn header
    cases["head"] = head
    foreign = tmp_path / "notes.mcap"
    foreign.write_text("not an mcap file\n")
    cases["foreign"] = foreign
    exported = tmp_path / "exported.mcap"
    assert iamp(["export", "foxglove", str(rec), str(exported)]) == 0
    cases["exported"] = exported  # an MCAP file, but in Foxglove's schemas, not ours
    cases["missing"] = tmp_path / "nope.mcap"
    capsys.readouterr()
    for name, path in cases.items():
        out = tmp_path / f"{name}.out.mcap"
        assert iamp(["export", "foxglove", str(path), str(out)]) == 2, name
        err = capsys.readouterr().err
        assert err.startswith("iamp export foxglove: ") and err.count("\n") == 1 and "Traceback" not in err, (name, err)
        assert not out.exists()
    # an output that is a folder, or whose folder cannot be made: one line naming OUT.mcap, before reading anything
    for out, why in ((tmp_path, "is a folder; expected a file name"), (Path("/proc/iamp-no-such-folder/x.mcap"), "cannot create the folder")):
        assert iamp(["export", "foxglove", str(rec), str(out)]) == 2
        err = capsys.readouterr().err
        assert err.startswith(f"iamp export foxglove: OUT.mcap {out}: ") and why in err and err.count("\n") == 1, err
    # a recording torn mid-way (a killed recorder) exports what its complete chunks hold, and says so
    torn = tmp_path / "torn.mcap"
    data = rec.read_bytes()
    torn.write_bytes(data[: len(data) * 2 // 3])
    assert iamp(["export", "foxglove", str(torn), str(tmp_path / "torn.out.mcap")]) == 0
    assert "source truncated" in capsys.readouterr().out


def test_a_map_subscription_logs_the_map_at_the_next_frame_and_again_later():
    """foxglove-sdk may call on_subscribe before the subscription takes messages: the map is asked for at each of RELOG_AFTER_S."""
    import time
    from types import SimpleNamespace

    from stages.foxglove_bridge.core import RELOG_AFTER_S, _Listener

    assert RELOG_AFTER_S[0] == 0.0 and len(RELOG_AFTER_S) >= 3 and list(RELOG_AFTER_S) == sorted(RELOG_AFTER_S)
    listener = _Listener()
    listener.on_subscribe(None, SimpleNamespace(topic="/objects"))
    assert not listener.relog_due(1e12)  # other topics ask for nothing
    listener.on_subscribe(None, SimpleNamespace(topic="/map"))
    listener.on_subscribe(None, SimpleNamespace(topic="/tf"))  # the two subscriptions of one client: one relog per due time
    now = time.monotonic()
    assert listener.relog_due(now)
    assert not listener.relog_due(now)
    for before, after in zip(RELOG_AFTER_S, RELOG_AFTER_S[1:]):
        assert not listener.relog_due(now + (before + after) / 2)
        assert listener.relog_due(now + after + 0.01)
    assert not listener.relog_due(now + 10 * RELOG_AFTER_S[-1])
    # frames that come late: several due times at once count once
    listener.on_subscribe(None, SimpleNamespace(topic="/map"))
    assert listener.relog_due(time.monotonic() + RELOG_AFTER_S[-1] + 1) and not listener.relog_due(1e12)


def test_export_draws_what_was_recorded_before_its_partner(live_run, tmp_path):
    """The recorder logs messages as they arrive, so a frame's predictions can precede its corridor set (and a belief
    its track frame): the export dropped those corridors (139 of 140 drawn on a 15 s run). Here every prediction is
    recorded before its corridor set and every belief before its frame: all are drawn, none is left out."""
    from stages.foxglove_bridge.export import export_foxglove
    from stages.recorder.core import McapRecorder, RecorderConfig
    from stages.recorder.inspect import read_messages

    msgs = list(read_messages(str(live_run["recording"])))
    rank = {"iamp.CorridorPredictions": 0, "iamp.CorridorSet": 1, "iamp.IntentionBelief": 0, "iamp.TrackFrame": 1}
    later = [m for m in msgs if m.schema in rank]
    order = sorted(later, key=lambda m: (m.publish_time_ns, rank[m.schema]))  # per stamp: the partner after
    swapped = tmp_path / "swapped.mcap"
    with McapRecorder(RecorderConfig(path=str(swapped)), RUN_ID) as rec:
        for m in [m for m in msgs if m.schema not in rank] + order:
            rec.handle(m.topic, m.data, m.log_time_ns)
    n_pred = sum(m.schema == "iamp.CorridorPredictions" for m in msgs)
    n_belief = sum(m.schema == "iamp.IntentionBelief" for m in msgs)
    report = export_foxglove(str(swapped), str(tmp_path / "fox.mcap"))
    assert report.logged.get("/markov_prediction/corridors") == n_pred > 0, report.logged
    assert report.logged.get("/intentions/vehicles") == n_belief > 0, report.logged
    assert not any("without" in k for k in report.skipped), report.skipped


def test_the_sdk_s_repeated_lines_are_collapsed():
    """A Foxglove client that stopped reading and then left: the SDK logged one ERROR line per message still queued
    for it (127 in one second). One passes, the rest of the same kind within 10 s are held back and counted."""
    import logging

    from stages.foxglove_bridge.core import RepeatFilter

    now = [0.0]
    flt = RepeatFilter(clock=lambda: now[0])
    records = []

    def emit(name, msg):
        rec = logging.LogRecord(name, logging.ERROR, __file__, 1, msg, (), None)
        if flt.filter(rec):
            records.append(rec.getMessage())

    for i in range(127):
        emit("foxglove.websocket.connected_client.poller", f"Error sending message to client 127.0.0.1:{57836 + i % 2}: IO error: Broken pipe (os error 32)")
    emit("iamp.foxglove", "a line of ours")  # never held back
    assert len(records) == 2 and records[1] == "a line of ours"
    now[0] = 11.0
    emit("foxglove.websocket.connected_client.poller", "Error sending message to client 127.0.0.1:57836: IO error: Broken pipe (os error 32)")
    assert records[-1].endswith("(126 more like it in the 10 s before)"), records[-1]
