"""A damaged chunk in the middle of a recording loses that chunk only.

Recordings are written by ``McapRecorder`` with small chunks (two frames a
chunk) and then damaged at the byte: a chunk's compressed bytes, its CRC, its
header fields, or its record length field. The offsets come from the
finished file's own chunk indexes (mcap's ``make_reader``); what a chunk held
comes from breaking up the intact original (mcap's ``breakup_chunk``). A chunk
whose record framing is intact is skipped and counted, and every message of
every other chunk is read (``read_messages``, ``inspect``), copied
(``recover``), replayed and exported; a broken record length is still a
truncation.
"""

from __future__ import annotations

import json
import struct
import subprocess
import sys
from pathlib import Path

import pytest
from mcap.reader import make_reader
from mcap.records import Message as McapMessage
from mcap.stream_reader import StreamReader, breakup_chunk

from testkit import helpers as h
from test_mcap import STAMP0_NS, make_frame, make_scene

from bus_schemas import keys
from stages.recorder.core import McapRecorder, RecorderConfig
from stages.recorder.inspect import ReadReport, format_table, inspect, read_messages, recover

N_FRAMES = 80
FRAME_KEY = keys.data_key("t1", "source", "track_frame")
LATE_KEY = keys.data_key("t1", "late", "track_frame")  # first put in the middle: its Channel record is in a middle chunk
LATE_FROM = 40


def write_recording(path: Path, late_key: bool = False) -> Path:
    with McapRecorder(RecorderConfig(path=str(path), chunk_size_bytes=1500), "t1") as rec:
        rec.handle(keys.data_key("t1", "source", "scene"), make_scene("t1").encode(), STAMP0_NS)
        for i in range(N_FRAMES):
            rec.handle(FRAME_KEY, make_frame(i, "t1").encode(), STAMP0_NS + 1 + 2 * i)
            if late_key and i >= LATE_FROM:
                rec.handle(LATE_KEY, make_frame(i, "t1", n_agents=3).encode(), STAMP0_NS + 2 + 2 * i)
    return path


def chunks_of(path: Path) -> list[tuple[int, int, set[int]]]:
    """Every chunk of a finished file in file order: (offset, record length on disk, log times of its messages)."""
    out = []
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
        for ci in sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset):
            f.seek(ci.chunk_start_offset)
            chunk = next(StreamReader(f, skip_magic=True, emit_chunks=True).records)
            times = {r.log_time for r in breakup_chunk(chunk, validate_crc=True) if isinstance(r, McapMessage)}
            out.append((ci.chunk_start_offset, ci.chunk_length, times))
    return out


def own_read(path: Path, report: ReadReport | None = None) -> list[tuple[str, str, bytes, int, int]]:
    return [(m.topic, m.schema, m.data, m.log_time_ns, m.publish_time_ns) for m in read_messages(str(path), report)]


def standard_read(path: Path) -> list[tuple[str, str, bytes, int, int]]:
    """Every message as mcap's make_reader gives it (file order); raises on a file it cannot read whole."""
    with open(path, "rb") as f:
        return [
            (c.topic, s.name if s else "", bytes(m.data), m.log_time, m.publish_time)
            for s, c, m in make_reader(f).iter_messages(log_time_order=False)
        ]


def without(messages: list[tuple], lost: set[int]) -> list[tuple]:
    return [m for m in messages if m[3] not in lost]


def flip(data: bytes, at: int, n: int) -> bytes:
    b = bytearray(data)
    for i in range(at, at + n):
        b[i] ^= 0xFF
    return bytes(b)


def iamp(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "stages.cli", *args], cwd=h.REPO, env=h.python_env(), capture_output=True, text=True, timeout=120)


@pytest.fixture(scope="module")
def original(tmp_path_factory) -> dict:
    path = write_recording(tmp_path_factory.mktemp("damaged") / "full.mcap")
    everything = own_read(path)
    chunks = chunks_of(path)
    assert len(everything) == N_FRAMES + 1 and len({m[3] for m in everything}) == len(everything), "log times tell messages apart"
    assert len(chunks) >= 20 and all(times for _o, _n, times in chunks)
    return {"path": path, "data": path.read_bytes(), "everything": everything, "chunks": chunks}


def test_a_damaged_middle_chunk_is_skipped_and_every_other_chunk_read(original, tmp_path):
    k = len(original["chunks"]) // 2
    offset, length, lost = original["chunks"][k]
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(flip(original["data"], offset + length // 2, 50))  # in its compressed bytes
    expected = without(original["everything"], lost)

    report = ReadReport()
    assert own_read(bad, report) == expected
    assert report.truncated is False and report.error == "" and report.summary_present is True
    assert report.damaged_chunks == 1 and report.damaged_bytes == length
    assert report.chunks == len(original["chunks"]) - 1
    assert f"chunk {k + 1} at byte {offset} ({length} bytes)" in report.damage and "CRCValidationError" in report.damage

    info = inspect(str(bad))
    assert info["messages"] == len(expected) and not info["truncated"] and info["error"] is None
    assert info["damaged_chunks"] == 1 and info["damaged_bytes"] == length and info["messages_lost"] == len(lost)
    assert info["frames"][FRAME_KEY]["count"] == N_FRAMES - len(lost) and info["frames"][FRAME_KEY]["missing"] == len(lost)
    table = format_table(info)
    assert "state: DAMAGED" in table and "TRUNCATED" not in table and "1 unreadable chunks skipped" in table, table

    res = iamp("inspect", str(bad), "--json")
    assert res.returncode == 0, res.stderr
    js = json.loads(res.stdout)
    assert js["damaged_chunks"] == 1 and js["damaged_bytes"] == length and js["truncated"] is False and js["messages"] == len(expected)

    # a sound file says so with the new keys
    sound = inspect(str(original["path"]))
    assert sound["damaged_chunks"] == 0 and sound["damaged_bytes"] == 0 and sound["damage"] is None and sound["messages_lost"] == 0
    assert "state: complete" in format_table(sound)


def test_several_damaged_chunks_and_damaged_chunk_fields(original, tmp_path):
    chunks = original["chunks"]
    data = original["data"]
    bad = tmp_path / "bad.mcap"
    picks = (3, 4, len(chunks) - 3)  # two in a row and one near the end
    b = data
    for k in picks:
        offset, length, _ = chunks[k]
        b = flip(b, offset + length - 30, 10)
    bad.write_bytes(b)
    lost = set().union(*(chunks[k][2] for k in picks))
    report = ReadReport()
    assert own_read(bad, report) == without(original["everything"], lost)
    assert not report.truncated and report.damaged_chunks == 3 and report.damaged_bytes == sum(chunks[k][1] for k in picks)

    # a chunk whose own fields are damaged (they do not read, or say something else) with its record length intact
    k = len(chunks) // 3
    offset, length, lost = chunks[k]
    # record: opcode 1, length 8, start 8, end 8, uncompressed size 8, crc 4, compression: length 4 + "zstd", data length 8 + data
    damages = {
        "crc": lambda b: struct.pack_into("<I", b, offset + 33, 12345),
        "compression name": lambda b: b.__setitem__(slice(offset + 41, offset + 45), b"\xff\xfe\xfd\xfc"),
        "compression length": lambda b: struct.pack_into("<I", b, offset + 37, 0x7FFFFFF0),
        "data length shorter": lambda b: struct.pack_into("<Q", b, offset + 45, struct.unpack_from("<Q", b, offset + 45)[0] - 100),
    }
    for name, damage in damages.items():
        b = bytearray(data)
        damage(b)
        bad.write_bytes(bytes(b))
        report = ReadReport()
        assert own_read(bad, report) == without(original["everything"], lost), name
        assert not report.truncated and report.damaged_chunks == 1 and report.damaged_bytes == length, (name, report)


def test_recover_copies_every_readable_chunk(original, tmp_path):
    k = len(original["chunks"]) // 2
    offset, length, lost = original["chunks"][k]
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(flip(original["data"], offset + length // 2, 50))
    expected = without(original["everything"], lost)
    out = tmp_path / "out.mcap"
    report = recover(str(bad), str(out))
    assert report.complete and report.messages == len(expected) and report.orphan_messages == 0
    assert report.damaged_chunks == 1 and report.damaged_bytes == length and report.stopped_at_byte == report.source_bytes
    assert "DAMAGED: 1 unreadable chunks skipped" in report.line()
    assert standard_read(out) == expected  # any MCAP reader reads the recovered file whole
    with open(out, "rb") as f:
        assert make_reader(f).get_summary().statistics.message_count == len(expected)

    res = iamp("recover", str(bad), str(tmp_path / "out2.mcap"), "--json")
    assert res.returncode == 0, res.stderr
    js = json.loads(res.stdout)
    assert js["messages"] == len(expected) and js["complete"] is True and js["damaged_chunks"] == 1 and js["damaged_bytes"] == length
    # a sound file: nothing damaged
    sound = recover(str(original["path"]), str(tmp_path / "sound.mcap"))
    assert sound.damaged_chunks == 0 and sound.damaged_bytes == 0 and sound.damage == "" and "DAMAGED" not in sound.line()


def test_later_messages_keep_their_channel_when_the_damaged_chunk_held_its_record(tmp_path):
    path = write_recording(tmp_path / "late.mcap", late_key=True)
    everything = own_read(path)
    late_first = min(m[3] for m in everything if m[0] == LATE_KEY)
    chunks = chunks_of(path)
    k = next(i for i, (_o, _n, times) in enumerate(chunks) if late_first in times)
    assert k + 3 < len(chunks)
    offset, length, lost = chunks[k]
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(flip(path.read_bytes(), offset + length // 2, 50))
    expected = without(everything, lost)
    assert sum(m[0] == LATE_KEY for m in expected) >= N_FRAMES - LATE_FROM - 3

    report = ReadReport()
    assert own_read(bad, report) == expected, "topics and schemas of the later messages from the summary's channels"
    assert report.damaged_chunks == 1 and not report.truncated

    out = tmp_path / "out.mcap"
    rep = recover(str(bad), str(out))
    assert rep.orphan_messages == 0 and rep.messages == len(expected)
    assert standard_read(out) == expected


def test_a_damaged_chunk_before_a_torn_tail(original, tmp_path):
    chunks = original["chunks"]
    k = len(chunks) // 3
    offset, length, lost = chunks[k]
    cut_in = chunks[2 * len(chunks) // 3]  # the file ends inside this chunk
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(flip(original["data"], offset + length // 2, 20)[: cut_in[0] + cut_in[1] // 2])
    kept = [m for m in original["everything"] if any(m[3] in times for o, _n, times in chunks if o < cut_in[0])]
    expected = without(kept, lost)

    report = ReadReport()
    assert own_read(bad, report) == expected
    assert report.truncated and report.error and report.damaged_chunks == 1 and report.damaged_bytes == length
    info = inspect(str(bad))
    assert info["truncated"] and info["damaged_chunks"] == 1 and info["messages_lost"] is None
    table = format_table(info)
    assert "state: TRUNCATED" in table and "DAMAGED before that" in table, table

    out = tmp_path / "out.mcap"
    rep = recover(str(bad), str(out))
    assert not rep.complete and rep.error and rep.damaged_chunks == 1 and rep.messages == len(expected)
    assert standard_read(out) == expected


@pytest.mark.parametrize("how", ["past the limit", "all ones", "past the end", "into the next record", "one byte long", "to the last byte"])
def test_a_broken_chunk_length_is_still_a_truncation(original, tmp_path, how):
    chunks = original["chunks"]
    data = original["data"]
    k = len(chunks) // 2
    offset, length, _ = chunks[k]
    record_length = length - 9
    new = {
        "past the limit": 1 << 40,
        "all ones": (1 << 64) - 1,
        "past the end": 2 * len(data),
        "into the next record": record_length + 37,
        "one byte long": record_length + 1,
        "to the last byte": len(data) - offset - 9 - 1,
    }[how]
    b = bytearray(data)
    struct.pack_into("<Q", b, offset + 1, new)
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(b))
    before = [m for m in original["everything"] if any(m[3] in times for _o, _n, times in chunks[:k])]

    report = ReadReport()
    got = own_read(bad, report)
    assert report.truncated is True and report.error
    assert got == original["everything"][: len(got)] and len(got) >= len(before), "a prefix, with everything before the broken chunk"
    info = inspect(str(bad))
    assert info["truncated"] and info["messages"] == len(got)

    out = tmp_path / "out.mcap"
    rep = recover(str(bad), str(out))
    assert not rep.complete and rep.error and rep.messages == len(got)
    assert standard_read(out) == got


def test_replay_and_export_read_past_a_damaged_chunk(original, tmp_path):
    from stages.foxglove_bridge.export import export_foxglove
    from stages.replay.core import RecordingPlayer, ReplayConfig

    k = len(original["chunks"]) // 2
    offset, length, lost = original["chunks"][k]
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(flip(original["data"], offset + length // 2, 50))
    expected = without(original["everything"], lost)

    player = RecordingPlayer(ReplayConfig(path=str(bad)), None)
    replayed = list(player)
    assert [(o.key, o.data) for o in replayed] == [(m[0], m[2]) for m in expected]
    assert player.report.damaged_chunks == 1 and not player.report.truncated

    report = export_foxglove(str(bad), str(tmp_path / "fox.mcap"))
    assert report.read == len(expected) and report.damaged_chunks == 1 and report.damaged_bytes == length
    assert "source damaged, 1 unreadable chunks skipped" in report.line() and "source truncated" not in report.line()


@pytest.mark.parametrize("opcode", [0x06 ^ 0xFF, 0x00, 0x42])
def test_a_chunk_whose_opcode_byte_is_damaged_is_counted_like_the_others(original, tmp_path, opcode):
    """mcap's reader passes over a record of an unknown opcode without a word; a chunk whose opcode byte was hit is a damaged chunk."""
    from stages.replay.core import RecordingPlayer, ReplayConfig

    k = len(original["chunks"]) // 2
    offset, length, lost = original["chunks"][k]
    assert original["data"][offset] == 0x06
    b = bytearray(original["data"])
    b[offset] = opcode
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(b))
    expected = without(original["everything"], lost)

    report = ReadReport()
    assert own_read(bad, report) == expected
    assert not report.truncated and report.error == "" and report.summary_present
    assert report.damaged_chunks == 1 and report.damaged_bytes == length and report.chunks == len(original["chunks"]) - 1
    assert f"chunk {k + 1} at byte {offset} ({length} bytes): its opcode byte is damaged (0x{opcode:02x}" in report.damage, report.damage

    info = inspect(str(bad))
    assert info["damaged_chunks"] == 1 and info["damaged_bytes"] == length and info["messages_lost"] == len(lost)
    table = format_table(info)
    damaged_lines = [line for line in table.splitlines() if "DAMAGED" in line]
    assert len(damaged_lines) == 1 and "state: DAMAGED" in damaged_lines[0], table
    assert f"1 unreadable chunks skipped ({length} bytes, {len(lost)} messages lost)" in damaged_lines[0] and "opcode byte is damaged" in damaged_lines[0]

    player = RecordingPlayer(ReplayConfig(path=str(bad)), None)
    assert [(o.key, o.data) for o in player] == [(m[0], m[2]) for m in expected]
    assert player.report.damaged_chunks == 1 and player.report.damaged_bytes == length and "opcode byte is damaged" in player.report.damage

    rep = recover(str(bad), str(tmp_path / "out.mcap"))
    assert rep.complete and rep.damaged_chunks == 1 and rep.messages == len(expected)
    assert standard_read(tmp_path / "out.mcap") == expected
