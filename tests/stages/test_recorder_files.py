"""The recorder never destroys a file it was not asked to replace, never shares a file with a second writer, and a file
it starts late (a recorder started mid-run, a restart, a split) holds the run's latched scene.

Found by running the tools as a new user would: ``--record`` naming an existing recording (or the file a replay
reads) emptied it the moment the recorder started, whatever happened next; two recorders on one file both reported
success and left a damaged file; every split after the first had no SceneInfo, so a replay of it waited forever.
"""

from __future__ import annotations

import signal
import subprocess
import sys
from pathlib import Path

import pytest

from testkit import helpers as h
from test_mcap import STAMP0_NS, make_frame, make_scene, recorder_args

from bus_schemas import keys
from stages.lib.base import ConfigError
from stages.recorder.core import McapRecorder, RecorderConfig, RecordingExists, preflight, split_path
from stages.recorder.inspect import inspect, read_messages
from stages.runtime import BusClient

SCENE_KEY = keys.data_key("t1", "source", "scene")
FRAME_KEY = keys.data_key("t1", "source", "track_frame")


def _record(path: Path, n: int = 3, **params) -> McapRecorder:
    with McapRecorder(RecorderConfig(path=str(path), **params), "t1") as rec:
        rec.handle(SCENE_KEY, make_scene("t1").encode(), STAMP0_NS)
        for i in range(n):
            rec.handle(FRAME_KEY, make_frame(i, "t1").encode(), STAMP0_NS + i)
    return rec


def test_an_existing_recording_is_refused_and_left_as_it_was(tmp_path):
    path = tmp_path / "keep.mcap"
    _record(path)
    before = path.read_bytes()
    with pytest.raises(RecordingExists, match="exists: a recording is never replaced unless asked"):
        McapRecorder(RecorderConfig(path=str(path)), "t2")
    with pytest.raises(RecordingExists):
        preflight(RecorderConfig(path=str(path)))
    assert path.read_bytes() == before


def test_a_split_file_of_the_name_is_refused_too(tmp_path):
    base = tmp_path / "run.mcap"
    _record(split_path(base, 1))  # an older run's second split, its first file gone
    with pytest.raises(RecordingExists, match=r"run\.001\.mcap exists"):
        McapRecorder(RecorderConfig(path=str(base)), "t1")
    assert not base.exists()


def test_overwrite_replaces_the_file(tmp_path):
    path = tmp_path / "old.mcap"
    _record(path, n=10)
    rec = _record(path, n=2, overwrite=True)
    assert rec.messages == 3
    assert len(list(read_messages(str(path)))) == 3


def test_a_second_recorder_on_the_same_file_is_refused_and_the_first_file_stays_whole(tmp_path):
    path = tmp_path / "one.mcap"
    with McapRecorder(RecorderConfig(path=str(path)), "t1") as first:
        first.handle(SCENE_KEY, make_scene("t1").encode(), STAMP0_NS)
        with pytest.raises(ConfigError, match="being written by another recorder"):
            McapRecorder(RecorderConfig(path=str(path), overwrite=True), "t1")
        with pytest.raises(RecordingExists):
            McapRecorder(RecorderConfig(path=str(path)), "t1")
        first.handle(FRAME_KEY, make_frame(0, "t1").encode(), STAMP0_NS + 1)
    info = inspect(str(path))
    assert info["summary_present"] is True and info["messages"] == 2


def test_abandon_removes_the_file_it_made_when_nothing_came(tmp_path):
    path = tmp_path / "sub" / "never.mcap"
    rec = McapRecorder(RecorderConfig(path=str(path)), "t1")
    assert path.exists()
    rec.abandon()  # what run_stage does when the node's bus session cannot open (a bad --connect)
    assert not path.exists()


def test_every_split_starts_with_the_newest_scene_and_a_repeated_scene_is_written_once(tmp_path):
    base = tmp_path / "run.mcap"
    scene = make_scene("t1")
    with McapRecorder(RecorderConfig(path=str(base), chunk_size_bytes=2000, split_bytes=6000), "t1") as rec:
        rec.handle(SCENE_KEY, scene.encode(), STAMP0_NS)
        rec.handle(SCENE_KEY, scene.encode(), STAMP0_NS)  # re-published as it was (a live tracker's latched scene)
        for i in range(30):
            rec.handle(FRAME_KEY, make_frame(i, "t1").encode(), STAMP0_NS + 1 + i)
    assert rec.latched_repeats == 1 and rec.messages == 31
    assert len(rec.paths) >= 3
    for path in rec.paths:
        msgs = list(read_messages(str(path)))
        assert msgs[0].topic == SCENE_KEY and msgs[0].schema == "iamp.SceneInfo" and msgs[0].data == scene.encode(), path.name
        assert sum(m.topic == SCENE_KEY for m in msgs) == 1, path.name


def test_a_recorder_started_after_the_scene_was_published_asks_for_it(tmp_path):
    """The scene is published once, latched (its publisher answers queries): a recorder that comes up later (``iamp
    record`` started mid-run, or the launcher's restart of a killed recorder) used to record a file without it."""
    port = h.free_port()
    path = tmp_path / "late.mcap"
    scene = make_scene("t1").encode()
    started: list[subprocess.Popen] = []
    try:
        with BusClient(listen=[h.endpoint(port)]) as bus:
            bus.declare_queryable(SCENE_KEY, lambda: scene)  # the source's latched scene; never put after this point
            alive = h.AliveSet(bus, keys.alive_pattern("t1"))
            rec = h.start_module("stages.recorder", *recorder_args("t1", port, path, flush_period_s=0.2), log_dir=tmp_path)
            started.append(rec)
            alive.wait_for(["recorder"])
            put_frame, matching = bus.publisher_with_matching(FRAME_KEY)
            h.wait_until(matching, 20, "the recorder's subscriber to match")
            for i in range(5):
                put_frame(make_frame(i, "t1").encode())
            h.wait_until(lambda: sum(m.topic == FRAME_KEY for m in _readable(path)) >= 5, 30, "5 frames on disk")
            h.wait_until(lambda: any(m.topic == SCENE_KEY for m in _readable(path)), 30, "the scene on disk")
            assert h.stop_process(rec, signal.SIGINT) == 0, h.output_of(rec)
    finally:
        h.kill_all(started)
    msgs = list(read_messages(str(path)))
    assert [m.data for m in msgs if m.topic == SCENE_KEY] == [scene], "the scene once, asked for at the start"


def _readable(path: Path) -> list:
    try:
        return list(read_messages(str(path)))
    except Exception:  # noqa: BLE001 - not written yet
        return []


def test_iamp_record_refuses_an_existing_file_before_it_touches_it(tmp_path):
    path = tmp_path / "keep.mcap"
    _record(path)
    before = path.read_bytes()
    done = subprocess.run([sys.executable, "-m", "stages.cli", "record", str(path), "--run-id", "demo"], capture_output=True, text=True,
                          timeout=60, env=h.python_env())
    assert done.returncode == 2, done.stderr
    assert "exists: a recording is never replaced unless asked" in done.stderr and "Traceback" not in done.stderr
    assert path.read_bytes() == before
    # a bad endpoint on a new file: refused, and no torn file left behind
    new = tmp_path / "new.mcap"
    done = subprocess.run([sys.executable, "-m", "stages.cli", "record", str(new), "--run-id", "demo", "--connect", "garbage"],
                          capture_output=True, text=True, timeout=60, env=h.python_env())
    assert done.returncode == 2, done.stderr
    assert not new.exists(), "a file the recorder made and never used is removed when its bus session cannot open"


class _SmallDisk:
    """A file that takes ``room`` bytes, then fails every write as a full disk does (ENOSPC)."""

    def __init__(self, f, room: int) -> None:
        self._f, self.room = f, room

    def write(self, data) -> int:
        import errno
        import os

        if self.room < len(data):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        self.room -= len(data)
        return self._f.write(data)

    def __getattr__(self, name):
        return getattr(self._f, name)


def test_a_full_disk_stops_the_recording_once_and_loudly_and_the_messages_after_are_counted(tmp_path, monkeypatch, caplog):
    """A full disk (a 20 MB tmpfs in a soak run): every message after it failed in the recorder, its flush thread logged
    "flush failed" four times a second (thousands of lines) and the run only learnt of it at the stop, from a crash.
    Now: one ERROR line, the rest counted as not_recorded (an issue the runtime counts), the file kept as far as it
    got (readable), and the node's exit a failure (``end_failure``)."""
    import logging

    real_open = McapRecorder._open_locked
    monkeypatch.setattr(McapRecorder, "_open_locked", lambda self, path: _SmallDisk(real_open(self, path), 6000))
    path = tmp_path / "run.mcap"
    rec = McapRecorder(RecorderConfig(path=str(path), chunk_size_bytes=1000, flush_period_s=0.05), "t1", log=logging.getLogger("iamp.rec"))
    with caplog.at_level(logging.ERROR, logger="iamp.rec"):
        rec.handle(SCENE_KEY, make_scene("t1").encode(), STAMP0_NS)
        kinds = [[i.kind for i in (rec.handle(FRAME_KEY, make_frame(i, "t1").encode(), STAMP0_NS + i) or [])] for i in range(200)]
        assert rec.write_failed is not None and rec.not_recorded > 0
        first = kinds.index(["not_recorded"])
        assert all(k == ["not_recorded"] for k in kinds[first:]) and rec.messages >= first + 1  # (the chunk that failed counted too)
        h.wait_until(lambda: rec._timer.is_alive(), 5.0, "the flush thread")  # it went on running, quietly
        rec.flush()
        rec.close()  # the summary does not fit either: no exception
    errors = [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]
    assert len(errors) == 1 and "recording stopped: cannot write" in errors[0] and "No space left on device" in errors[0], errors
    assert "not recorded" in rec.end_failure() and "iamp recover" in rec.end_failure()
    assert [m.topic for m in read_messages(str(path))][:1] == [SCENE_KEY]  # what it wrote before reads back
