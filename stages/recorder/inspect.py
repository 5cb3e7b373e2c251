"""Reading hybrid-iamp MCAP recordings, also ones cut short by a kill.

``read_messages(path, report)`` walks the file front to back with mcap's
non-seeking ``StreamReader`` (it never needs the summary), yields every
message of every complete chunk as a ``RecordedMessage`` and stops cleanly
where the file ends early: the ``ReadReport`` then says ``truncated`` and
why, and a warning is logged. A chunk is yielded all or nothing, so a
recording left by ``kill -9`` reads up to its last complete chunk.

A damaged chunk in the middle of a file (its data does not decompress or
fails its CRC, or its fields do not read) whose record framing is intact
(its record length ends inside the file, where the next record begins) is
skipped: its messages are lost, it is counted in ``damaged_chunks`` and
``damaged_bytes``, and reading goes on with the next record. So is a chunk
whose opcode byte is damaged: mcap's reader passes over a record of an
unknown opcode without a word; a record of an unknown opcode whose fields
frame as a chunk's is counted as a damaged chunk. Messages of
later chunks on a channel whose Channel record was in the damaged chunk keep
their topic and schema when the file has its summary section. A record
whose length runs past the end of the file, or a chunk followed by no
record, is a truncation as before: reading stops there.

``inspect(path)`` summarises a recording as a dict (channels with counts,
time range, per-schema counts, TrackFrame frame indices, truncation);
``main(argv)`` is ``iamp inspect FILE.mcap [--json]``: a table by default,
JSON with ``--json``, exit 2 for a missing or unreadable file.

``recover(src, dst)`` rewrites a recording that its writer never finished
(killed: no footer, no summary, maybe a partial last chunk) or that holds
damaged chunks into a complete MCAP file (mcap's ``Writer``, same chunk
compression) with every message of every complete, readable chunk, its
schemas, channels and metadata, so that any MCAP
reader (``mcap.reader.make_reader``, Foxglove, ``mcap`` CLI) reads it whole;
``recover_main`` is ``iamp recover FILE.mcap [OUT.mcap]``.
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import struct
import sys
import tempfile
from dataclasses import dataclass, field
from datetime import datetime, timezone
from typing import Any, Iterator

from mcap.exceptions import EndOfFile, InvalidMagic
from mcap.opcode import Opcode
from mcap.reader import make_reader
from mcap.records import Attachment, Channel, Chunk, DataEnd, Footer, Metadata, Schema, Statistics
from mcap.records import Header as McapHeader
from mcap.records import Message as McapMessage
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap.writer import CompressionType, Writer

from bus_schemas import SchemaError, TrackFrame
from stages.lib.recording_files import put_in_place

# Largest record we try to load; a corrupt length field beyond this is read as truncation.
_RECORD_SIZE_LIMIT = 1 << 31
_MAX_GAPS_LISTED = 50
_MAX_DAMAGE_LISTED = 5
_KNOWN_OPCODES = frozenset(int(op) for op in Opcode)
# a Chunk record's fields before its compression name: start and end time, uncompressed size (8 each), CRC (4), name length (4)
_CHUNK_FIXED_BYTES = 8 + 8 + 8 + 4 + 4
_CHUNK_COMPRESSIONS = frozenset({b"", b"zstd", b"lz4"})


class RecordingError(ValueError):
    """A file that is missing or is not an MCAP recording at all."""


@dataclass(frozen=True, slots=True)
class RecordedMessage:
    """One recorded message: its key (``topic``), schema name ('' if none), times and payload."""

    topic: str
    schema: str
    log_time_ns: int
    publish_time_ns: int
    data: bytes


@dataclass(slots=True)
class ReadReport:
    """What ``read_messages`` found besides the messages; filled in while reading.

    ``truncated`` is True when the file ended (or broke) before its footer;
    ``error`` then says where and how. ``summary_present`` is True when the
    writer finished the file (footer with a summary section). ``metadata``
    maps each metadata record's name to its key/value pairs.
    ``damaged_chunks`` counts the chunks skipped because their data could not
    be read while their record framing was intact (their messages are lost,
    how many is unknown), ``damaged_bytes`` their size on disk (whole
    records), and ``damage`` says which they were and why; ``truncated``
    stays False for such a file when it is read up to its footer.
    """

    truncated: bool = False
    error: str = ""
    summary_present: bool = False
    library: str = ""
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    chunks: int = 0
    messages: int = 0
    summary_message_count: int | None = None
    damaged_chunks: int = 0
    damaged_bytes: int = 0
    damage: str = ""


def _open(path: str):
    try:
        return open(path, "rb")
    except FileNotFoundError:
        raise RecordingError(f"{path}: no such file") from None
    except IsADirectoryError:
        raise RecordingError(f"{path}: is a directory, not an MCAP file") from None
    except OSError as exc:
        raise RecordingError(f"{path}: cannot open: {exc.strerror or exc}") from None


class _DamagedOpcode(Exception):
    """Why a record of an unknown opcode that frames as a chunk was skipped (it names the opcode found)."""


class _ChunkUnreadable(Exception):
    """A chunk that does not read and cannot be skipped (its framing is lost): the end of the usable data."""

    def __init__(self, cause: Exception) -> None:
        super().__init__(str(cause))
        self.cause = cause


class _Records:
    """The records of an open MCAP file front to back (mcap's ``StreamReader``), each chunk broken up (CRC-checked).

    ``take()`` returns ``(record, inner)``: ``inner`` the records of a chunk,
    None for any other record. A chunk that does not read (decompression,
    CRC, its fields, or its opcode byte) but whose record framing is intact
    is skipped, counted and described (``damaged_chunks``, ``damaged_bytes``,
    ``damage``) and the next record read. Raises ``StopIteration`` at the end, ``_ChunkUnreadable``
    for a chunk read whole that does not break up and cannot be skipped, and
    whatever mcap raised for any other record that does not read (a torn tail).
    """

    def __init__(self, f: Any) -> None:
        self.f = f
        self.started = False  # a first record was read
        self.chunks = 0  # chunks read
        self.damaged_chunks = 0
        self.damaged_bytes = 0
        self._damage: list[str] = []
        self._records = StreamReader(f, emit_chunks=True, record_size_limit=_RECORD_SIZE_LIMIT).records

    @property
    def damage(self) -> str:
        more = self.damaged_chunks - len(self._damage)
        return "; ".join(self._damage) + (f"; and {more} more" if more > 0 else "")

    def take(self) -> tuple[Any, list[Any] | None]:
        while True:
            start = self.f.tell() if self.started else len(b"\x89MCAP0\r\n")
            if self.started:
                end = self._chunk_with_damaged_opcode(start)
                if end is not None:  # mcap's reader would pass over it without a word (an unknown opcode)
                    opcode = os.pread(self.f.fileno(), 1, start)[0]
                    self._skip(start, end, _DamagedOpcode(f"its opcode byte is damaged (0x{opcode:02x}, a chunk's is 0x{int(Opcode.CHUNK):02x})"), restart=True)
                    continue
            try:
                record = next(self._records)
            except StopIteration:
                raise
            except Exception as exc:  # mcap raises EndOfFile, struct.error, decompression and CRC errors
                end = self._skippable_chunk(start, exc) if self.started else None
                if end is None:
                    raise
                self._skip(start, end, exc, restart=True)  # a generator that raised is finished
                continue
            self.started = True
            if not isinstance(record, Chunk):
                return record, None
            try:
                inner = breakup_chunk(record, validate_crc=True)
            except Exception as exc:
                end = self._skippable_chunk(start, None)
                if end is None:
                    raise _ChunkUnreadable(exc) from None
                self._skip(start, end, exc, restart=self.f.tell() != end)
                continue
            self.chunks += 1
            return record, inner

    def _skippable_chunk(self, start: int, read_error: Exception | None) -> int | None:
        """Where the chunk record at ``start`` ends when its framing is intact (it can be skipped), else None.

        Intact: a Chunk opcode and a length that ends inside the file, the
        reader did not run out of file inside the record (when it was read:
        a file still being written), and at its end the file ends or a record
        of a known opcode begins. ``read_error`` is what the reader raised
        inside the record (None when the record was read and its data did not
        break up).
        """
        fd = self.f.fileno()
        head = os.pread(fd, 9, start)
        if len(head) < 9:
            return None
        opcode, length = struct.unpack("<BQ", head)
        if opcode != Opcode.CHUNK or length > _RECORD_SIZE_LIMIT:
            return None
        end = start + 9 + length
        if end > os.fstat(fd).st_size:
            return None  # runs past the end: a torn tail
        if self.f.tell() < end and (read_error is None or isinstance(read_error, (EndOfFile, struct.error))):
            return None  # the reader met the end of the file inside the record
        after = os.pread(fd, 1, end)
        if after and after[0] not in _KNOWN_OPCODES:
            return None  # no record follows: the framing is lost
        return end

    def _chunk_with_damaged_opcode(self, start: int) -> int | None:
        """Where the record at ``start`` ends when it is a chunk whose opcode byte is damaged, else None.

        mcap's reader skips a record of an unknown opcode silently (the MCAP
        spec lets later versions add records), so a chunk whose opcode byte
        was hit would vanish with its messages and only the summary's message
        count would show it. Such a record is taken for a chunk when its
        fields frame as a chunk's do (start and end time, sizes, CRC, a known
        compression name, a data length that ends the record exactly) and
        its framing is intact (the file ends or a known record follows).
        """
        fd = self.f.fileno()
        head = os.pread(fd, 9 + _CHUNK_FIXED_BYTES, start)
        if len(head) < 9 + _CHUNK_FIXED_BYTES:
            return None
        opcode, length = struct.unpack_from("<BQ", head)
        if opcode in _KNOWN_OPCODES or length > _RECORD_SIZE_LIMIT or length < _CHUNK_FIXED_BYTES + 8:
            return None
        end = start + 9 + length
        if end > os.fstat(fd).st_size:
            return None
        name_length = struct.unpack_from("<I", head, 9 + 28)[0]
        if name_length > max(len(n) for n in _CHUNK_COMPRESSIONS) or _CHUNK_FIXED_BYTES + name_length + 8 > length:
            return None
        rest = os.pread(fd, name_length + 8, start + 9 + _CHUNK_FIXED_BYTES)
        if len(rest) < name_length + 8 or rest[:name_length] not in _CHUNK_COMPRESSIONS:
            return None
        data_length = struct.unpack_from("<Q", rest, name_length)[0]
        if _CHUNK_FIXED_BYTES + name_length + 8 + data_length != length:
            return None
        after = os.pread(fd, 1, end)
        if after and after[0] not in _KNOWN_OPCODES:
            return None
        return end

    def _skip(self, start: int, end: int, exc: Exception, restart: bool) -> None:
        self.damaged_chunks += 1
        self.damaged_bytes += end - start
        if len(self._damage) < _MAX_DAMAGE_LISTED:
            self._damage.append(f"chunk {self.chunks + self.damaged_chunks} at byte {start} ({end - start} bytes): {_why(exc)}")
        if restart:  # the reader raised, stopped inside the record or read past it: go on from its end
            self.f.seek(end)
            self._records = StreamReader(self.f, skip_magic=True, emit_chunks=True, record_size_limit=_RECORD_SIZE_LIMIT).records


def _summary(path: str):
    """``path``'s summary section (mcap's reader), None when it has none that reads (no footer, a damaged summary)."""
    try:
        with open(path, "rb") as f:
            return make_reader(f).get_summary()
    except Exception:  # noqa: BLE001 - nothing to add
        return None


def _summary_records(path: str) -> tuple[dict[int, Schema], dict[int, Channel]]:
    """The schemas and channels of ``path``'s summary section, empty when it has none that reads."""
    summary = _summary(path)
    if summary is None:
        return {}, {}
    return dict(summary.schemas), dict(summary.channels)


def summary_counts(path: str) -> dict[str, Any] | None:
    """A finished recording's message count and counts per topic from its summary section's statistics, without
    reading its messages (the launcher's report at the end of a run: reading a 2 GB file took 10 s); None when the file
    has no summary with statistics (torn, or written without them): then ``inspect`` reads it."""
    summary = _summary(path)
    if summary is None or summary.statistics is None:
        return None
    per_topic: collections.Counter[str] = collections.Counter()
    for channel_id, n in summary.statistics.channel_message_counts.items():
        channel = summary.channels.get(channel_id)
        if channel is not None:
            per_topic[channel.topic] += n
    return {"messages": summary.statistics.message_count, "channels": len(summary.channels), "per_topic": dict(per_topic)}


def read_messages(path: str, report: ReadReport | None = None) -> Iterator[RecordedMessage]:
    """Yield the messages of ``path`` in file order; stop cleanly at a truncation.

    Raises ``RecordingError`` (before yielding anything) when the file is
    missing or does not start like an MCAP file. A damaged chunk whose record
    framing is intact is skipped and counted (``report.damaged_chunks``,
    ``damaged_bytes``, ``damage``). Anything else that goes wrong later is
    read as the end of the usable data: ``report.truncated`` is set,
    ``report.error`` says what happened, and the iteration ends (callers
    log it; this function does not, so that polling a growing file is quiet).
    """
    report = report if report is not None else ReadReport()
    path = str(path)
    with _open(path) as f:
        reader = _Records(f)
        schemas: dict[int, str] = {}
        channels: dict[int, tuple[str, int]] = {}
        while True:
            try:
                record, inner = reader.take()
            except StopIteration:
                break
            except _ChunkUnreadable as exc:
                report.truncated = True
                report.error = f"chunk {reader.chunks + reader.damaged_chunks + 1} is damaged ({_why(exc.cause)})"
                break
            except Exception as exc:
                if not reader.started:
                    if f.tell() == 0:
                        raise RecordingError(f"{path}: empty file, not an MCAP recording") from None
                    what = "not an MCAP file" if isinstance(exc, InvalidMagic) else f"not a readable MCAP file ({_why(exc)})"
                    raise RecordingError(f"{path}: {what}") from None
                report.truncated = True
                report.error = f"file ends or breaks at byte {f.tell()} before its footer ({_why(exc)})"
                break
            finally:
                _note_damage(reader, report, path, schemas, channels)
            if inner is not None:
                report.chunks = reader.chunks
                for rec in inner:
                    msg = _take(rec, schemas, channels, report)
                    if msg is not None:
                        yield msg
                continue
            msg = _take(record, schemas, channels, report)
            if msg is not None:
                yield msg


def _note_damage(reader: _Records, report: ReadReport, path: str, schemas: dict[int, str], channels: dict[int, tuple[str, int]]) -> None:
    """Copy the reader's damage counts into ``report``; at the first damaged chunk add the summary's schemas and channels."""
    if reader.damaged_chunks == report.damaged_chunks:
        return
    if report.damaged_chunks == 0:  # the damaged chunk may have held Channel records that later messages need
        spare_schemas, spare_channels = _summary_records(path)
        for sid, schema in spare_schemas.items():
            schemas.setdefault(sid, schema.name)
        for cid, channel in spare_channels.items():
            channels.setdefault(cid, (channel.topic, channel.schema_id))
    report.damaged_chunks = reader.damaged_chunks
    report.damaged_bytes = reader.damaged_bytes
    report.damage = reader.damage


def _why(exc: Exception) -> str:
    if isinstance(exc, EndOfFile):
        return "end of file"
    if isinstance(exc, _DamagedOpcode):
        return str(exc)
    name = type(exc).__name__
    if name == "error":  # struct.error
        name = f"{type(exc).__module__}.error"
    text = str(exc)
    return f"{name}: {text}" if text else name


def _take(record: Any, schemas: dict[int, str], channels: dict[int, tuple[str, int]], report: ReadReport) -> RecordedMessage | None:
    if isinstance(record, McapMessage):
        topic, schema_id = channels.get(record.channel_id, (f"<channel {record.channel_id}>", 0))
        report.messages += 1
        return RecordedMessage(
            topic=topic,
            schema=schemas.get(schema_id, ""),
            log_time_ns=record.log_time,
            publish_time_ns=record.publish_time,
            data=bytes(record.data),
        )
    if isinstance(record, Schema):
        schemas[record.id] = record.name
    elif isinstance(record, Channel):
        channels[record.id] = (record.topic, record.schema_id)
    elif isinstance(record, Metadata):
        report.metadata[record.name] = dict(record.metadata)
    elif isinstance(record, McapHeader):
        report.library = record.library
    elif isinstance(record, Statistics):
        report.summary_message_count = record.message_count
    elif isinstance(record, Footer):
        report.summary_present = record.summary_start != 0
    elif isinstance(record, DataEnd):
        pass
    return None


def recording_run_id(path: str) -> str | None:
    """The run id a recording was made under (its metadata, else its first key), or None."""
    report = ReadReport()
    for msg in read_messages(path, report):
        meta = report.metadata.get("hybrid-iamp", {})
        if meta.get("run_id"):
            return meta["run_id"]
        parts = msg.topic.split("/")
        return parts[1] if len(parts) >= 2 else None
    return report.metadata.get("hybrid-iamp", {}).get("run_id") or None


# --------------------------------------------------------------------------- recover

_COMPRESSION_BY_NAME = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "": CompressionType.NONE}


@dataclass(slots=True)
class RecoverReport:
    """What ``recover`` copied and where it stopped reading the source."""

    src: str
    dst: str
    messages: int = 0
    channels: int = 0
    schemas: int = 0
    metadata: int = 0
    attachments: int = 0
    chunks: int = 0
    orphan_messages: int = 0  # messages on a channel whose Channel record was never read (left out)
    complete: bool = False  # the source had its footer: nothing was lost but the damaged chunks (if any)
    stopped_at_byte: int = 0  # end of the last record taken from the source
    source_bytes: int = 0
    error: str = ""
    damaged_chunks: int = 0  # chunks of the source that did not read (framing intact): skipped, their messages lost
    damaged_bytes: int = 0  # their size in the source
    damage: str = ""  # which chunks they were and why

    def line(self) -> str:
        state = (
            ("source was complete" + (f" (its end past the footer is damaged: {self.error})" if self.error else ""))
            if self.complete
            else f"stopped at byte {self.stopped_at_byte} of {self.source_bytes} ({self.source_bytes - self.stopped_at_byte} bytes dropped): {self.error}"
        )
        if self.damaged_chunks:
            if self.complete:
                state = "source had its footer" + state[len("source was complete") :]
            state += f"; DAMAGED: {self.damaged_chunks} unreadable chunks skipped ({self.damaged_bytes} bytes, their messages lost): {self.damage}"
        extra = f", {self.orphan_messages} messages without channel left out" if self.orphan_messages else ""
        return f"recovered {self.messages} messages on {self.channels} channels ({self.schemas} schemas, {self.chunks} chunks{extra}) into {self.dst}; {state}"


def default_recovered_path(src: str) -> str:
    """``run.mcap`` -> ``run.recovered.mcap`` next to it."""
    root, ext = os.path.splitext(str(src))
    return f"{root}.recovered{ext or '.mcap'}"


def recover(src: str, dst: str | None = None) -> RecoverReport:
    """Rewrite ``src`` into a finished MCAP file ``dst`` (default ``<src>.recovered.mcap``).

    Reads ``src`` front to back with mcap's ``StreamReader`` (chunks whole,
    CRC-checked: a chunk is taken all or nothing) and stops at the first
    record that cannot be read, which for a killed writer is the torn tail;
    a damaged chunk whose record framing is intact is skipped and counted
    (``damaged_chunks``, ``damaged_bytes``, ``damage``) and copying goes on.
    Schemas, channels (topic, encoding, channel metadata), metadata records,
    attachments and messages (log and publish time, sequence, payload) are
    written in file order with mcap's ``Writer`` and the file is finished
    (summary, indexes, footer). ``dst`` may equal ``src``: the new file is
    written next to it and then replaces it. Raises ``RecordingError`` when
    ``src`` is missing or not an MCAP file; nothing is written then.
    """
    src = str(src)
    dst = str(dst) if dst else default_recovered_path(src)
    report = RecoverReport(src=src, dst=dst)
    with _open(src) as f:
        report.source_bytes = os.fstat(f.fileno()).st_size
        records = _Records(f)
        try:
            first = records.take()
        except Exception as exc:
            if report.source_bytes == 0:
                raise RecordingError(f"{src}: empty file, not an MCAP recording") from None
            what = "not an MCAP file" if isinstance(exc, InvalidMagic) else f"not a readable MCAP file ({_why(exc)})"
            raise RecordingError(f"{src}: {what}") from None
        out_dir = os.path.dirname(os.path.abspath(dst))
        os.makedirs(out_dir, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=".recover-", suffix=".mcap", dir=out_dir)
        try:
            with os.fdopen(fd, "wb") as out:
                _copy_records(first, records, f, out, report, src)
            put_in_place(tmp, dst)
        except BaseException:
            try:
                os.unlink(tmp)
            except OSError:
                pass
            raise
    return report


def _copy_records(first: tuple[Any, list[Any] | None], records: _Records, f: Any, out: Any, report: RecoverReport, src: str) -> None:
    writer: Writer | None = None
    header: McapHeader | None = first[0] if isinstance(first[0], McapHeader) else None
    schema_ids: dict[int, int] = {}  # source id -> written id
    channel_ids: dict[int, int] = {}
    pending: list[Any] = [] if header is not None else (first[1] if first[1] is not None else [first[0]])
    # the source summary's schemas and channels, read at the first damaged chunk: that chunk may have held
    # Channel records that messages of later chunks need
    spare_schemas: dict[int, Schema] = {}
    spare_channels: dict[int, Channel] = {}

    deferred: list[Any] = []  # metadata/attachments before the first chunk: the writer takes that chunk's compression

    def ensure_writer(compression: str = "zstd") -> Writer:
        nonlocal writer
        if writer is None:
            writer = Writer(out, compression=_COMPRESSION_BY_NAME.get(compression, CompressionType.ZSTD))
            writer.start(profile=header.profile if header else "", library=header.library if header else "")
            for rec in deferred:
                take(rec)
            deferred.clear()
        return writer

    def take(rec: Any) -> None:
        if isinstance(rec, Schema):
            if rec.id not in schema_ids:
                schema_ids[rec.id] = ensure_writer().register_schema(name=rec.name, encoding=rec.encoding, data=bytes(rec.data))
                report.schemas += 1
        elif isinstance(rec, Channel):
            if rec.id not in channel_ids:
                sid = schema_ids.get(rec.schema_id, 0) if rec.schema_id else 0
                channel_ids[rec.id] = ensure_writer().register_channel(
                    topic=rec.topic, message_encoding=rec.message_encoding, schema_id=sid, metadata=dict(rec.metadata)
                )
                report.channels += 1
        elif isinstance(rec, McapMessage):
            cid = channel_ids.get(rec.channel_id)
            if cid is None and rec.channel_id in spare_channels:
                channel = spare_channels[rec.channel_id]
                if channel.schema_id in spare_schemas:
                    take(spare_schemas[channel.schema_id])
                take(channel)
                cid = channel_ids.get(rec.channel_id)
            if cid is None:
                report.orphan_messages += 1
                return
            ensure_writer().add_message(channel_id=cid, log_time=rec.log_time, data=bytes(rec.data), publish_time=rec.publish_time, sequence=rec.sequence)
            report.messages += 1
        elif isinstance(rec, (Metadata, Attachment)) and writer is None:
            deferred.append(rec)
        elif isinstance(rec, Metadata):
            ensure_writer().add_metadata(rec.name, dict(rec.metadata))
            report.metadata += 1
        elif isinstance(rec, Attachment):
            ensure_writer().add_attachment(create_time=rec.create_time, log_time=rec.log_time, name=rec.name, media_type=rec.media_type, data=bytes(rec.data))
            report.attachments += 1
        elif isinstance(rec, Footer):
            report.complete = True
        # Header, DataEnd, indexes, statistics and summary offsets are rewritten by the Writer.

    report.stopped_at_byte = f.tell()
    for rec in pending:
        take(rec)
    while True:
        try:
            record, inner = records.take()
        except StopIteration:
            break
        except _ChunkUnreadable as exc:
            report.error = f"chunk {records.chunks + records.damaged_chunks + 1} (after byte {report.stopped_at_byte}) is damaged ({_why(exc.cause)})"
            break
        except Exception as exc:  # EndOfFile, struct.error, a length past the limit: the torn tail
            report.error = f"{_why(exc)} reading the record after byte {report.stopped_at_byte}"
            break
        finally:
            if records.damaged_chunks and not report.damaged_chunks:
                schemas, channels = _summary_records(src)
                spare_schemas.update(schemas)
                spare_channels.update(channels)
            report.damaged_chunks, report.damaged_bytes, report.damage = records.damaged_chunks, records.damaged_bytes, records.damage
        if inner is not None:
            ensure_writer(record.compression)
            report.chunks += 1
            for rec in inner:
                take(rec)
        else:
            take(record)
        report.stopped_at_byte = f.tell()
    if report.complete:
        report.stopped_at_byte = report.source_bytes
    elif not report.error:
        report.error = "file ends before its footer"
    ensure_writer().finish()


def add_recover_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("file", metavar="FILE.mcap", help="recording to recover (e.g. left by a killed recorder)")
    parser.add_argument("out", metavar="OUT.mcap", nargs="?", help="file to write (default FILE.recovered.mcap; may be FILE itself)")
    parser.add_argument("--json", action="store_true", help="print the report as JSON")


def run_recover(args: argparse.Namespace) -> int:
    """Run ``iamp recover`` on parsed arguments: 0 written, 2 missing or not an MCAP file."""
    try:
        report = recover(args.file, args.out)
    except RecordingError as exc:
        sys.stderr.write(f"iamp recover: {exc}\n")
        return 2
    except OSError as exc:
        sys.stderr.write(f"iamp recover: cannot write {args.out or default_recovered_path(args.file)}: {exc.strerror or exc}\n")
        return 2
    if args.json:
        from dataclasses import asdict

        sys.stdout.write(json.dumps(asdict(report), indent=2) + "\n")
    else:
        sys.stdout.write(report.line() + "\n")
    return 0


# --------------------------------------------------------------------------- inspect


def _frame_summary(indices: list[int]) -> dict[str, Any]:
    gaps: list[list[int]] = []
    missing = 0
    increasing = True
    for a, b in zip(indices, indices[1:]):
        if b <= a:
            increasing = False
        elif b > a + 1:
            missing += b - a - 1
            if len(gaps) < _MAX_GAPS_LISTED:
                gaps.append([a, b])
    return {
        "count": len(indices),
        "first": indices[0] if indices else None,
        "last": indices[-1] if indices else None,
        "strictly_increasing": increasing,
        "gaps": gaps,
        "missing": missing,
    }


def inspect(path: str) -> dict[str, Any]:
    """Summarise a recording.

    Keys: ``channels`` (list of ``{"topic", "schema", "count"}``, one per
    topic and schema, sorted by topic), ``start_ns`` and ``end_ns`` (log
    times, None for an empty file), ``messages``, ``truncated``, ``error``,
    ``summary_present``, ``chunks``, ``by_schema`` (counts), ``metadata``,
    ``frames``: for every ``iamp.TrackFrame`` topic the decoded frame
    indices as ``{count, first, last, strictly_increasing, gaps, missing,
    undecodable}``; ``damaged_chunks`` and ``damaged_bytes`` (chunks skipped
    because they did not read, 0 for a sound file), ``damage`` (which and
    why, None if none) and ``messages_lost``: how many messages the
    summary's statistics count beyond those read (the skipped chunks' and any
    other record mcap's reader passed over; 0 for a sound file), None when
    the file was not read to a summary with statistics.
    """
    report = ReadReport()
    counts: collections.Counter[tuple[str, str]] = collections.Counter()
    by_schema: collections.Counter[str] = collections.Counter()
    frame_indices: dict[str, list[int]] = collections.defaultdict(list)
    undecodable: collections.Counter[str] = collections.Counter()
    start_ns: int | None = None
    end_ns: int | None = None
    for msg in read_messages(path, report):
        counts[(msg.topic, msg.schema)] += 1
        by_schema[msg.schema] += 1
        start_ns = msg.log_time_ns if start_ns is None else min(start_ns, msg.log_time_ns)
        end_ns = msg.log_time_ns if end_ns is None else max(end_ns, msg.log_time_ns)
        if msg.schema == TrackFrame.SCHEMA:
            try:
                frame = TrackFrame.decode(msg.data, where=msg.topic)
            except SchemaError:
                undecodable[msg.topic] += 1
                continue
            frame_indices[msg.topic].append(frame.header.frame_index)
    frames = {}
    for topic in sorted(set(frame_indices) | set(undecodable)):
        frames[topic] = {**_frame_summary(frame_indices.get(topic, [])), "undecodable": undecodable.get(topic, 0)}
    return {
        "path": str(path),
        "channels": [{"topic": t, "schema": s, "count": n} for (t, s), n in sorted(counts.items())],
        "start_ns": start_ns,
        "end_ns": end_ns,
        "messages": report.messages,
        "truncated": report.truncated,
        "error": report.error or None,
        "summary_present": report.summary_present,
        "chunks": report.chunks,
        "by_schema": dict(sorted(by_schema.items())),
        "metadata": report.metadata,
        "frames": frames,
        "damaged_chunks": report.damaged_chunks,
        "damaged_bytes": report.damaged_bytes,
        "damage": report.damage or None,
        "messages_lost": (
            report.summary_message_count - report.messages if report.summary_message_count is not None and not report.truncated else None
        ),
    }


def _utc(ns: int | None) -> str:
    if ns is None:
        return "-"
    return datetime.fromtimestamp(ns / 1e9, tz=timezone.utc).strftime("%Y-%m-%d %H:%M:%S.%f")[:-3] + "Z"


def format_table(info: dict[str, Any]) -> str:
    """The human-readable form of ``inspect``'s dict."""
    lines = [f"file: {info['path']}"]
    damaged = info.get("damaged_chunks", 0)
    lost = info.get("messages_lost")
    if damaged:
        damage = f"{damaged} unreadable chunks skipped ({info['damaged_bytes']} bytes, {f'{lost} messages' if lost is not None else 'their messages'} lost): {info['damage']}"
    elif (lost or 0) > 0:
        damage = f"{lost} of the {info['messages'] + lost} messages its summary counts were not read"
    damaged = damaged or (lost or 0) > 0
    if info["truncated"]:
        lines.append(
            f"state: TRUNCATED, read up to the last complete chunk: {info['error']}"
            + (f"; DAMAGED before that: {damage}" if damaged else "")
            + f" (`iamp recover {info['path']}` writes a finished copy)"
        )
    elif damaged:
        lines.append(
            f"state: DAMAGED, read to the end, summary {'present' if info['summary_present'] else 'absent'}: {damage} "
            f"(`iamp recover {info['path']}` writes a copy without them)"
        )
    else:
        lines.append(f"state: complete, summary {'present' if info['summary_present'] else 'absent'}")
    dur = (info["end_ns"] - info["start_ns"]) / 1e9 if info["start_ns"] is not None else 0.0
    lines.append(
        f"messages: {info['messages']}  channels: {len(info['channels'])}  chunks: {info['chunks']}  "
        f"start: {_utc(info['start_ns'])}  end: {_utc(info['end_ns'])}  duration_s: {dur:.3f}"
    )
    for name, meta in info["metadata"].items():
        lines.append(f"metadata {name}: " + " ".join(f"{k}={v}" for k, v in sorted(meta.items())))
    if info["channels"]:
        wt = max(len("topic"), *(len(c["topic"]) for c in info["channels"]))
        ws = max(len("schema"), *(len(c["schema"] or "-") for c in info["channels"]))
        lines.append(f"{'topic':<{wt}}  {'schema':<{ws}}  {'count':>8}")
        for c in info["channels"]:
            lines.append(f"{c['topic']:<{wt}}  {c['schema'] or '-':<{ws}}  {c['count']:>8}")
    for topic, fr in info["frames"].items():
        lines.append(
            f"frames {topic}: count={fr['count']} first={fr['first']} last={fr['last']} "
            f"strictly_increasing={'yes' if fr['strictly_increasing'] else 'NO'} gaps={len(fr['gaps'])} "
            f"missing={fr['missing']} undecodable={fr['undecodable']}"
        )
    return "\n".join(lines)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("file", metavar="FILE.mcap", help="recording to inspect")
    parser.add_argument("--json", action="store_true", help="print the summary as JSON")


def run(args: argparse.Namespace) -> int:
    """Run ``iamp inspect`` on parsed arguments; returns the exit code."""
    try:
        info = inspect(args.file)
    except RecordingError as exc:
        sys.stderr.write(f"iamp inspect: {exc}\n")
        return 2
    sys.stdout.write((json.dumps(info, indent=2) if args.json else format_table(info)) + "\n")
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="iamp inspect", description="Summarise an MCAP recording of hybrid-iamp.")
    add_arguments(parser)
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:
        return 0 if exc.code == 0 else 2
    return run(args)


if __name__ == "__main__":
    sys.exit(main())
