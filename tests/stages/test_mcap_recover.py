"""``iamp recover``: torn recordings (killed writer) rewritten into files any MCAP reader reads whole.

Torn files are made for real: a real recording cut at several byte offsets,
and a recorder process killed with SIGKILL while messages arrive on a real
(loopback) Zenoh bus. The check is mcap's own ``make_reader``: it cannot read
the torn file whole, and reads the recovered one with every message of every
complete chunk, schemas, channels and metadata kept.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from mcap.reader import make_reader

from testkit import helpers as h
from test_mcap import STAMP0_NS, count_on_disk, make_frame, make_scene, recorder_args

from bus_schemas import TrackFrame, keys
from stages.recorder.inspect import ReadReport, RecordingError, read_messages, recover
from stages.recorder.core import McapRecorder, RecorderConfig
from stages.runtime import BusClient


def standard_read(path: Path) -> tuple[list[tuple[str, str, bytes, int, int, int]], str]:
    """Every message as mcap's make_reader gives it (file order), and the error that stopped it ('' if none)."""
    out = []
    try:
        with open(path, "rb") as f:
            for schema, channel, message in make_reader(f).iter_messages(log_time_order=False):
                out.append((channel.topic, schema.name if schema else "", bytes(message.data), message.log_time, message.publish_time, message.sequence))
    except Exception as exc:  # what the standard reader raises on a torn file
        return out, f"{type(exc).__name__}: {exc}"
    return out, ""


def own_read(path: Path) -> list[tuple[str, str, bytes, int, int]]:
    return [(m.topic, m.schema, m.data, m.log_time_ns, m.publish_time_ns) for m in read_messages(str(path))]


def iamp(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "stages.cli", *args], cwd=h.REPO, env=h.python_env(), capture_output=True, text=True, timeout=120)


@pytest.fixture
def full_recording(tmp_path) -> Path:
    """A finished recording: a scene, 80 frames on small chunks, a payload without schema."""
    path = tmp_path / "full.mcap"
    with McapRecorder(RecorderConfig(path=str(path), chunk_size_bytes=1500), "t1") as rec:
        rec.handle(keys.data_key("t1", "source", "scene"), make_scene("t1").encode(), STAMP0_NS)
        for i in range(80):
            rec.handle(keys.data_key("t1", "source", "track_frame"), make_frame(i, "t1").encode(), STAMP0_NS + 1 + i)
            if i == 40:
                rec.handle(keys.data_key("t1", "bad", "payload"), b"\xc1 not msgpack", STAMP0_NS + 1 + i)
    return path


def test_recover_a_recording_cut_at_several_offsets(full_recording, tmp_path):
    data = full_recording.read_bytes()
    whole, err = standard_read(full_recording)
    assert err == "" and len(whole) == 82
    cut = tmp_path / "cut.mcap"
    out = tmp_path / "out.mcap"
    seen_partial = set()
    for size in (len(data) - 40, (2 * len(data)) // 3 + 3, len(data) // 2, len(data) // 5 + 11):
        cut.write_bytes(data[:size])
        torn, err = standard_read(cut)
        assert err or len(torn) < len(whole), f"cut at {size}: the standard reader read it whole"
        report = recover(str(cut), str(out))
        assert not report.complete and report.error and 0 < report.stopped_at_byte <= size == report.source_bytes
        got, err = standard_read(out)
        assert err == "", f"cut at {size}: recovered file does not read: {err}"
        # every message of every complete chunk, in order, with its times, schema and channel
        expected = own_read(cut)
        assert [(t, s, d, lt, pt) for t, s, d, lt, pt, _seq in got] == expected
        assert got == whole[: len(got)], "a prefix of the finished file, sequences included"
        assert report.messages == len(got) > 0
        assert report.channels == len({g[0] for g in got})
        seen_partial.add(len(got))
        with open(out, "rb") as f:
            reader = make_reader(f)
            summary = reader.get_summary()
            assert summary is not None and summary.statistics.message_count == len(got)
            assert {ci.compression for ci in summary.chunk_indexes} == {"zstd"}
            assert [m.name for m in reader.iter_metadata()] == ["hybrid-iamp"]
            assert {s.encoding for s in summary.schemas.values()} == {"jsonschema"}
            assert {c.message_encoding for c in summary.channels.values()} == {"msgpack"}
    assert len(seen_partial) >= 3, seen_partial  # the cuts really fell in different chunks


def test_recover_a_finished_file_keeps_everything_and_can_replace_it_in_place(full_recording):
    whole, _ = standard_read(full_recording)
    report = recover(str(full_recording), str(full_recording))
    assert report.complete and report.messages == len(whole) == 82 and report.channels == 3
    again, err = standard_read(full_recording)
    assert err == "" and again == whole
    assert not list(full_recording.parent.glob(".recover-*")), "no temporary file left behind"
    # the recovered file has a new file's mode (0666 less the umask), not the temporary file's 0600: as readable as the
    # recording it replaces
    mask = os.umask(0)
    os.umask(mask)
    assert full_recording.stat().st_mode & 0o777 == 0o666 & ~mask


def test_recover_a_recording_left_by_a_recorder_killed_with_sigkill(tmp_path):
    path = tmp_path / "killed.mcap"
    port = h.free_port()
    sent: list[bytes] = []
    started: list[subprocess.Popen] = []
    try:
        with BusClient(listen=[h.endpoint(port)]) as bus:
            alive = h.AliveSet(bus, keys.alive_pattern("t1"))
            rec = h.start_module("stages.recorder", *recorder_args("t1", port, path, chunk_size_bytes=2048, flush_period_s=600.0), log_dir=tmp_path)
            started.append(rec)
            alive.wait_for(["recorder"])
            put, matching = bus.publisher_with_matching(keys.data_key("t1", "source", "track_frame"))
            h.wait_until(matching, 20, "the recorder's subscriber to match")

            def publish_until_chunks(n_chunks: int) -> bool:
                for _ in range(3):
                    data = make_frame(len(sent), "t1").encode()
                    put(data)
                    sent.append(data)
                report = ReadReport()
                count_on_disk(path, report)
                return report.chunks >= n_chunks

            h.wait_until(lambda: publish_until_chunks(6), 30, "6 complete chunks on disk")
            rec.send_signal(signal.SIGKILL)
            rec.wait(timeout=20)
        assert rec.returncode == -signal.SIGKILL
    finally:
        h.kill_all(started)

    torn, err = standard_read(path)
    assert err, f"the standard reader read the torn file without error ({len(torn)} messages)"
    assert len(torn) == 0, "RecordLengthLimitExceeded on the missing footer: nothing"
    own_all = list(read_messages(str(path)))  # frames and the recorder's own _stats
    own = [m.data for m in own_all if m.schema == TrackFrame.SCHEMA]
    assert len(own) >= 6
    n_channels = len({m.topic for m in own_all})

    out = tmp_path / "killed.recovered.mcap"
    res = iamp("recover", str(path))  # default output name
    assert res.returncode == 0, res.stderr
    line = res.stdout.strip()
    assert line.startswith(f"recovered {len(own_all)} messages on {n_channels} channels") and f"into {out}" in line and "stopped at byte" in line, line
    got, err = standard_read(out)
    assert err == ""
    assert [d for _t, s, d, *_ in got if s == TrackFrame.SCHEMA] == own == sent[: len(own)]
    assert [TrackFrame.decode(d).header.frame_index for _t, s, d, *_ in got if s == TrackFrame.SCHEMA] == list(range(len(own)))
    assert [(t, s, d, lt, pt) for t, s, d, lt, pt, _seq in got] == [(m.topic, m.schema, m.data, m.log_time_ns, m.publish_time_ns) for m in own_all]

    res = iamp("recover", str(path), str(tmp_path / "sub" / "r.mcap"), "--json")
    assert res.returncode == 0, res.stderr
    info = json.loads(res.stdout)
    assert info["messages"] == len(own_all) and info["channels"] == n_channels and not info["complete"]
    assert info["stopped_at_byte"] <= info["source_bytes"] == path.stat().st_size


def test_recover_refuses_missing_and_non_mcap_files(tmp_path):
    garbage = tmp_path / "garbage.mcap"
    garbage.write_bytes(b"definitely not an mcap file")
    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    for bad in (garbage, empty, tmp_path / "missing.mcap"):
        with pytest.raises(RecordingError):
            recover(str(bad), str(tmp_path / "x.mcap"))
        res = iamp("recover", str(bad), str(tmp_path / "x.mcap"))
        assert res.returncode == 2 and str(bad) in res.stderr, res.stderr
    assert not (tmp_path / "x.mcap").exists()
    assert not list(tmp_path.glob(".recover-*"))
