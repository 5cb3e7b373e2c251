"""Recorder split files (``split_bytes``, ``split_s``, ``split_index``): real MCAP files read with mcap's own reader."""

from __future__ import annotations

import json

import sys
from pathlib import Path

import pytest
from mcap.reader import make_reader

from testkit import helpers as h
from test_mcap import STAMP0_NS, make_frame, make_scene

from bus_schemas import SceneInfo, TrackFrame, json_schema, keys
from stages.recorder.core import McapRecorder, RecorderConfig, split_path, split_paths


def read_whole(path: Path) -> list[tuple[str, str, bytes, int]]:
    with open(path, "rb") as f:
        reader = make_reader(f)
        assert reader.get_summary() is not None, f"{path} is not finished"
        return [(c.topic, s.name if s else "", bytes(m.data), m.sequence) for s, c, m in reader.iter_messages(log_time_order=False)]


def test_split_path_names():
    assert split_path("runs/run.mcap", 0) == Path("runs/run.mcap")
    assert split_path("runs/run.mcap", 1) == Path("runs/run.001.mcap")
    assert split_path("runs/run.mcap", 12) == Path("runs/run.012.mcap")
    assert split_path("a.b/run.x.mcap", 2) == Path("a.b/run.x.002.mcap")
    assert split_path("rec", 3) == Path("rec.003.mcap")


def test_split_bytes_makes_finished_files_that_each_read_alone(tmp_path):
    base = tmp_path / "run.mcap"
    frame_key, scene_key = keys.data_key("t1", "source", "track_frame"), keys.data_key("t1", "source", "scene")
    sent = []
    with McapRecorder(RecorderConfig(path=str(base), chunk_size_bytes=2000, split_bytes=6000), "t1") as rec:
        rec.handle(scene_key, make_scene("t1").encode(), STAMP0_NS)
        sent.append((scene_key, make_scene("t1").encode()))
        for i in range(60):
            data = make_frame(i, "t1").encode()
            rec.handle(frame_key, data, STAMP0_NS + 1 + i)
            sent.append((frame_key, data))
    files = split_paths(base)
    assert [i for i, _ in files] == list(range(len(files))) and len(files) >= 4, files
    assert [p for _, p in files] == rec.paths
    got = []
    for i, p in files:
        msgs = read_whole(p)
        assert msgs, f"split {i} is empty"
        assert all(s == "iamp.TrackFrame" for t, s, _d, _q in msgs if t == frame_key), "schemas repeated in every split"
        with open(p, "rb") as f:
            meta = {m.name: m.metadata for m in make_reader(f).iter_metadata()}
        assert meta["hybrid-iamp"]["split_index"] == str(i) and meta["hybrid-iamp"]["base_path"] == str(base)
        if i < len(files) - 1:
            # one chunk (2000) and the records every split repeats (schemas, channels, metadata, summary) beyond split_bytes
            schemas = sum(len(json.dumps(json_schema(c), sort_keys=True)) for c in (TrackFrame, SceneInfo))
            assert p.stat().st_size < 6000 + 4000 + schemas + 1000, "a split is cut near split_bytes"
        if i > 0:  # each split reads alone: it starts with the newest latched scene (a replay's stages wait for it)
            assert (msgs[0][0], msgs[0][2]) == sent[0] and msgs[0][1] == "iamp.SceneInfo", f"split {i} starts with the scene"
            msgs = msgs[1:]
        got += msgs
    assert [(t, d) for t, _s, d, _q in got] == sent, "every message once, in order, over the splits"
    assert [q for t, _s, _d, q in got if t == frame_key] == list(range(1, 61)), "sequences go on across splits"
    assert rec.messages == 61 and rec.channels == 2, "messages received (a split's scene is not counted again)"


def test_split_s_cuts_by_duration_and_never_writes_an_empty_split(tmp_path):
    base = tmp_path / "dur.mcap"
    frame_key = keys.data_key("t1", "source", "track_frame")
    with McapRecorder(RecorderConfig(path=str(base), split_s=0.05, flush_period_s=0.02), "t1") as rec:
        rec.handle(frame_key, make_frame(0, "t1").encode(), STAMP0_NS)
        h.wait_until(lambda: len(rec.paths) >= 2, 20, "a second split after split_s")  # the timer cuts it
        n = len(rec.paths)
        rec.handle(frame_key, make_frame(1, "t1").encode(), STAMP0_NS + 1)
        h.wait_until(lambda: len(rec.paths) > n, 20, "a split after the second message")
    files = split_paths(base)
    counts = [len(read_whole(p)) for _, p in files]
    # the split opened by the last cut held nothing: close() removed it
    assert counts == [1, 1], counts
    assert [p for _, p in files] == rec.paths
    assert [TrackFrame.decode(d).header.frame_index for _, p in files for _t, _s, d, _q in read_whole(p)] == [0, 1]


def test_split_index_starts_at_a_later_split_and_stale_files_are_told_apart(tmp_path):
    base = tmp_path / "run.mcap"
    frame_key = keys.data_key("t1", "source", "track_frame")
    with McapRecorder(RecorderConfig(path=str(base)), "t1") as rec:
        rec.handle(frame_key, make_frame(0, "t1").encode(), STAMP0_NS)
    with McapRecorder(RecorderConfig(path=str(base), split_index=2), "t1") as rec2:
        rec2.handle(frame_key, make_frame(1, "t1").encode(), STAMP0_NS + 1)
    assert rec2.paths == [tmp_path / "run.002.mcap"]
    assert [i for i, _ in split_paths(base)] == [0, 2]
    assert split_paths(base, since_s=base.stat().st_mtime + 3600) == []


def test_keep_splits_keeps_the_newest_files_each_reading_alone(tmp_path):
    """``keep_splits = 2``: as splits open, older ones are deleted; the two left are finished, start with the scene and
    hold the newest frames, in order."""
    base = tmp_path / "run.mcap"
    frame_key, scene_key = keys.data_key("t1", "source", "track_frame"), keys.data_key("t1", "source", "scene")
    frames = [make_frame(i, "t1").encode() for i in range(60)]
    with McapRecorder(RecorderConfig(path=str(base), chunk_size_bytes=2000, split_bytes=6000, keep_splits=2), "t1") as rec:
        rec.handle(scene_key, make_scene("t1").encode(), STAMP0_NS)
        for i, data in enumerate(frames):
            rec.handle(frame_key, data, STAMP0_NS + 1 + i)
    files = split_paths(base)
    assert len(files) == 2 and rec.splits_removed == len(rec.paths) - 2 >= 2, (files, rec.paths)
    assert [p for _, p in files] == rec.paths[-2:]
    got = []
    for _i, p in files:
        msgs = read_whole(p)
        assert msgs[0][1] == "iamp.SceneInfo", "each kept split reads alone: the scene first"
        got += [d for t, _s, d, _q in msgs[1:] if t == frame_key]
    assert got == frames[-len(got):] and len(got) >= 2, "the newest frames, in order"


def test_free_space_floor_finishes_the_file_and_counts_what_follows(tmp_path):
    """Below ``min_free_mb`` (here more than any disk has, so the real free space is always below it) the recorder
    finishes its file (summary and indexes: it reads whole), says so once, counts every later message as
    ``not_recorded`` and reports the early stop for the node's exit code; nothing raises."""
    base = tmp_path / "run.mcap"
    frame_key = keys.data_key("t1", "source", "track_frame")
    rec = McapRecorder(RecorderConfig(path=str(base), min_free_mb=1e12), "t1")
    try:
        assert rec.handle(frame_key, make_frame(0, "t1").encode(), STAMP0_NS) is None
        h.wait_until(lambda: rec.finished_early, 10.0, "the flush timer's free-space check")
        issues = rec.handle(frame_key, make_frame(1, "t1").encode(), STAMP0_NS + 1)
        assert [i.kind for i in issues] == ["not_recorded"] and "min_free_mb" in issues[0].detail
    finally:
        rec.close()
    assert rec.not_recorded == 1 and rec.messages == 1
    assert [d for t, _s, d, _q in read_whole(base)] == [make_frame(0, "t1").encode()]
    assert "reads whole" in rec.end_failure()
    with pytest.raises(ValueError, match="keep_splits = 2 needs split_bytes or split_s"):
        RecorderConfig(keep_splits=2)


@pytest.mark.parametrize("bad", [{"split_bytes": -1}, {"split_s": -0.5}, {"split_index": -1}, {"keep_splits": -1}, {"min_free_mb": -1.0},
                                 {"min_free_mb": float("nan")}])
def test_bad_split_parameters_are_refused(bad):
    with pytest.raises(ValueError):
        RecorderConfig(**bad)


def test_iamp_record_split_bytes_on_a_real_bus(tmp_path):
    import signal

    from stages.runtime import BusClient

    base = tmp_path / "live.mcap"
    port = h.free_port()
    started = []
    sent = []
    try:
        with BusClient(listen=[h.endpoint(port)]) as bus:
            alive = h.AliveSet(bus, keys.alive_pattern("t1"))
            rec = h.start_module(
                "stages.cli", "record", str(base), "--run-id", "t1", "--connect", h.endpoint(port),
                "--split-bytes", "8000", "--chunk-size-bytes", "2000", "--no-stats", log_dir=tmp_path,
            )
            started.append(rec)
            alive.wait_for(["recorder"], 60)
            put, matching = bus.publisher_with_matching(keys.data_key("t1", "source", "track_frame"))
            h.wait_until(matching, 20, "the recorder's subscriber to match")

            def publish_until_splits(n: int) -> bool:
                data = make_frame(len(sent), "t1").encode()
                put(data)
                sent.append(data)
                return len(split_paths(base)) >= n

            h.wait_until(lambda: publish_until_splits(3), 60, "three split files")

            def on_disk() -> int:  # the open split reads up to its last chunk (closed at least every second)
                from stages.recorder.inspect import RecordingError, read_messages

                try:
                    return sum(1 for _, p in split_paths(base) for m in read_messages(str(p)) if m.topic.endswith("/track_frame"))
                except RecordingError:  # a split just opened, not even its header on disk yet
                    return 0

            h.wait_until(lambda: on_disk() >= len(sent), 30, f"{len(sent)} frames on disk")
            assert h.stop_process(rec, signal.SIGINT) == 0, h.output_of(rec)
    finally:
        h.kill_all(started)
    files = split_paths(base)
    got = [d for _, p in files for t, _s, d, _q in read_whole(p) if t.endswith("/track_frame")]
    assert got == sent, "every frame once, in order, each split finished"
    assert "splits=" in h.output_of(rec)
