"""The recorder stage's core and binding (documented in ``stages/recorder/__init__.py``)."""

from __future__ import annotations

import errno
import json
import logging
import math
import os
import re
import shutil
import sys
import threading
import time
import tomllib
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, BinaryIO

from mcap.exceptions import UnsupportedCompressionError
from mcap.writer import LIBRARY_IDENTIFIER, CompressionType, Writer

from bus_schemas import REGISTRY, SceneInfo, SchemaError, json_schema, keys
from bus_schemas._wire import peek_header

from stages.lib.recording_files import default_path, split_path, split_paths
from stages.lib.base import ConfigError, ConfigMixin, Issue, check_output
from stages.runtime import NodeContext, StageSpec, run_stage

try:
    import fcntl
except ImportError:  # not POSIX: no lock, the existence check alone keeps a second recorder off a file
    fcntl = None  # type: ignore[assignment]

COMPRESSIONS = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}
MESSAGE_ENCODING = "msgpack"
SCHEMA_ENCODING = "jsonschema"
METADATA_NAME = "hybrid-iamp"
# Bytes a message record adds to a chunk besides its payload (opcode, length, channel, sequence, two times).
_MESSAGE_OVERHEAD_BYTES = 1 + 8 + 2 + 4 + 8 + 8
# The mcap Writer closes a chunk by itself only past this size; the recorder closes them earlier.
_WRITER_CHUNK_LIMIT = 1 << 62
# Schemas published latched (the runtime's ``Port(..., latched=True)``: kept by the publisher and answered to queries):
# every split file starts with the newest one of each key, so that each file reads alone (a replay's stages wait for
# the scene), and a payload equal to the one the file already holds on its key is not written again.
LATCHED_SCHEMAS = frozenset({SceneInfo.SCHEMA})


class RecordingExists(ConfigError):
    """The file (or one of its splits) is there and ``overwrite`` is off."""


def iamp_version() -> str:
    """Version of hybrid-iamp: the installed distribution's, else pyproject.toml's."""
    try:
        from importlib.metadata import PackageNotFoundError, version

        return version("hybrid-iamp")
    except PackageNotFoundError:
        pass
    try:
        data = tomllib.loads((Path(__file__).resolve().parents[2] / "pyproject.toml").read_text())  # a source checkout, not installed
        return str(data["project"]["version"])
    except (OSError, KeyError, tomllib.TOMLDecodeError):
        return "unknown"


@dataclass(frozen=True, kw_only=True)
class RecorderConfig(ConfigMixin):
    """Where and how to write the MCAP file (see the module docstring)."""

    path: str = ""
    chunk_size_bytes: int = 256 * 1024
    compression: str = "zstd"
    include_stats: bool = True
    flush_period_s: float = 1.0
    split_bytes: int = 0
    split_s: float = 0.0
    split_index: int = 0
    overwrite: bool = False
    #: with split_bytes or split_s: keep only the newest this many split files of the run, deleting older ones as
    #: new splits open (0: keep every split). A bounded ring of recent files for unattended runs
    keep_splits: int = 0
    #: stop cleanly when the recording's file system has less than this many MiB free (checked about once a second):
    #: with keep_splits the oldest kept split is deleted first; else the current file is finished (it reads whole) and
    #: every later message is counted as not_recorded. 0: no floor (write until the disk is full)
    min_free_mb: float = 64.0

    def __post_init__(self) -> None:
        if self.compression not in COMPRESSIONS:
            raise ValueError(f"compression {self.compression!r} is not one of {', '.join(COMPRESSIONS)}")
        if self.chunk_size_bytes < 1:
            raise ValueError(f"chunk_size_bytes must be >= 1, got {self.chunk_size_bytes}")
        if not self.flush_period_s > 0:
            raise ValueError(f"flush_period_s must be > 0, got {self.flush_period_s}")
        if self.split_bytes < 0:
            raise ValueError(f"split_bytes must be >= 0 (0: no size limit), got {self.split_bytes}")
        if not self.split_s >= 0:
            raise ValueError(f"split_s must be >= 0 (0: no duration limit), got {self.split_s}")
        if self.split_index < 0:
            raise ValueError(f"split_index must be >= 0, got {self.split_index}")
        if self.keep_splits < 0:
            raise ValueError(f"keep_splits must be >= 0 (0: keep every split), got {self.keep_splits}")
        if self.keep_splits and not (self.split_bytes or self.split_s):
            raise ValueError(f"keep_splits = {self.keep_splits} needs split_bytes or split_s > 0 (without them the recording is one file)")
        if not (self.min_free_mb >= 0 and math.isfinite(self.min_free_mb)):
            raise ValueError(f"min_free_mb must be a number >= 0 (0: no floor), got {self.min_free_mb}")


def check_not_there(base: Path, overwrite: bool) -> None:
    """Refuse (``RecordingExists``) to start a recording at ``base`` where it or one of its split files is there, unless
    ``overwrite``: a run writes split 0 first, so such a file is another recording's (a recorder restarted by the
    launcher goes on at ``split_index`` > 0 of its own run, and is not asked)."""
    if overwrite:
        return
    there = [p for _i, p in split_paths(base)]
    if there:
        more = f" and {len(there) - 1} more of its split files" if len(there) > 1 else ""
        raise RecordingExists(f"path {there[0]}{more} exists: a recording is never replaced unless asked"
                              " (choose another path, or pass --overwrite: the recorder's overwrite = true)")


def preflight(config: RecorderConfig) -> None:
    """The launcher's check before any node starts (``StageSpec.preflight``): the file can be written and is not
    another recording."""
    base = Path(config.path) if config.path else None
    if base is None:
        return
    try:
        check_output(split_path(base, config.split_index), "path")
    except ConfigError as exc:  # (a read-only checkout: the default runs/ folder cannot be made)
        raise ConfigError(f"{exc}: record elsewhere (launch.py --record FILE.mcap) or not at all (--no-record)") from None
    if config.split_index == 0:
        check_not_there(base, config.overwrite)


class McapRecorder:
    """Writes raw bus payloads into an MCAP file; a context manager that always finishes the file.

    ``handle(key, payload, recv_ns)`` records one payload and returns the
    issues it raised; ``close()`` writes the summary and closes the file.
    Thread-safe: a background timer closes a chunk that has stayed open for
    ``flush_period_s``.
    """

    def __init__(self, config: RecorderConfig, run_id: str, log: logging.Logger | None = None, node_id: str = "recorder") -> None:
        self.config = config
        self.run_id = keys.check_run_id(run_id)
        self.log = log or logging.getLogger(f"iamp.{node_id}")
        self.base_path = Path(config.path) if config.path else default_path(run_id)
        self.split_index = config.split_index
        self.paths: list[Path] = []  # every file this recorder has written, the current one last
        self.node_id = node_id
        self.messages = 0
        self.unrecognised = 0
        self.old_versions = 0  # payloads of an older schema version this build upgrades: recorded without schema, no issue
        self._lock = threading.Lock()
        self._sequences: dict[tuple[str, str], int] = {}  # per (topic, schema name), across splits
        self._closed = threading.Event()
        self._latched: dict[str, tuple[bytes, int, str]] = {}  # key -> (payload, publish ns, schema) of its newest latched message
        self._file_latched: dict[str, bytes] = {}  # key -> the latched payload the current file holds last
        self.latched_repeats = 0  # latched payloads equal to the one the file held on their key: not written again
        self.write_failed: OSError | None = None  # the error that stopped the recording (a full disk): nothing is written after it
        self.not_recorded = 0  # messages received after it
        self.finished_early = False  # stopped by the free-space floor: the file was finished first (it reads whole)
        self.splits_removed = 0  # old splits deleted (keep_splits, or to stay above min_free_mb)
        self._space_checked = 0.0  # monotonic time of the last free-space check
        self._created: list[Path] = []  # files this recorder created (not there before it)
        # the first file's folder now, with a message that names the parameter (an OSError later, at a split, is a crash)
        check_output(split_path(self.base_path, self.split_index), "path")
        if self.split_index == 0:
            check_not_there(self.base_path, config.overwrite)
        self._open_file()
        self._timer = threading.Thread(target=self._flush_periodically, name="recorder-flush", daemon=True)
        self._timer.start()
        self.log.info("recording: path=%s run=%s", self.path, run_id)

    def _open_file(self) -> None:
        """Open split ``self.split_index``: a new file with its header and metadata (schemas and channels again as used),
        locked against a second writer, then the newest latched payloads of the run so far."""
        config = self.config
        self.path = split_path(self.base_path, self.split_index)
        self._schema_ids: dict[str, int] = {}
        self._channel_ids: dict[tuple[str, int], int] = {}
        self._file_latched = {}
        self._chunk_bytes = 0
        self._chunk_opened = 0.0  # monotonic time of the first message in the open chunk
        self._file_messages = 0
        self._file_opened = time.monotonic()
        self.path.parent.mkdir(parents=True, exist_ok=True)
        existed = self.path.exists()
        self._file: BinaryIO = self._open_locked(self.path)
        if existed:
            self.log.warning("overwriting existing file: path=%s", self.path)
        else:
            self._created.append(self.path)
        self._file_fresh = 0  # messages received into this file (its latched start not counted)
        try:
            self._writer = Writer(self._file, chunk_size=_WRITER_CHUNK_LIMIT, compression=COMPRESSIONS[config.compression])
        except UnsupportedCompressionError as exc:
            self._file.close()
            raise ConfigError(f"compression {config.compression!r} is not available here: {exc}") from None
        version = iamp_version()
        start_ns = time.time_ns()
        self._writer.start(profile="", library=f"hybrid-iamp/{version}; {LIBRARY_IDENTIFIER}")
        self._writer.add_metadata(
            METADATA_NAME,
            {
                "run_id": self.run_id,
                "version": version,
                "recorder_node": self.node_id,
                "split_index": str(self.split_index),
                "base_path": str(self.base_path),
                "start_time_ns": str(start_ns),
                "start_time_utc": datetime.fromtimestamp(start_ns / 1e9, tz=timezone.utc).isoformat(),
                "compression": config.compression,
            },
        )
        self._writer.flush()
        self.paths.append(self.path)
        for key, (payload, publish_ns, schema_name) in self._latched.items():  # each split reads alone: its scene first
            self._write(key, payload, time.time_ns(), publish_ns, schema_name)
            self._file_latched[key] = payload

    def _open_locked(self, path: Path) -> BinaryIO:
        """``path`` opened for writing, emptied only once this process holds its exclusive lock (``flock``): a second
        recorder on the same file is refused before it has written a byte, and never tears the first one's file."""
        fd = os.open(path, os.O_WRONLY | os.O_CREAT, 0o666)
        if fcntl is not None:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                os.close(fd)
                raise ConfigError(f"path {path} is being written by another recorder (it holds the file's lock):"
                                  " choose another path") from None
        os.ftruncate(fd, 0)
        return os.fdopen(fd, "wb")

    def _split_due(self) -> bool:
        if not self._file_fresh:
            return False  # a split always holds messages received into it
        if self.config.split_bytes and self._file.tell() + self._chunk_bytes >= self.config.split_bytes:
            return True
        return bool(self.config.split_s) and time.monotonic() - self._file_opened >= self.config.split_s

    def _next_split(self) -> None:
        """Finish the current file (summary, indexes) and go on in the next split; called with the lock held."""
        self._writer.finish()
        self._file.close()
        self.log.info("split closed: path=%s messages=%d; next split %d", self.path, self._file_messages, self.split_index + 1)
        self.split_index += 1
        self._open_file()

    def _prune_splits(self) -> None:
        """keep_splits: the newest ``keep_splits`` files stay, the current one among them (called when the current split
        receives its first message: a split the last cut opened and nothing reached is removed at the close instead)."""
        older = self._older_splits()
        for _index, path in older[: max(0, len(older) - (self.config.keep_splits - 1))]:
            self._remove_split(path, f"keep_splits = {self.config.keep_splits}")

    def _older_splits(self) -> list[tuple[int, Path]]:
        """This recording's split files on disk before the current one, oldest first."""
        return [(i, p) for i, p in split_paths(self.base_path) if i < self.split_index]

    def _remove_split(self, path: Path, why: str) -> bool:
        """Delete one finished split file (``why``: the rule that asked); False where it could not be."""
        try:
            path.unlink()
        except OSError as exc:
            self.log.warning("could not remove split %s (%s): %s", path, why, exc.strerror or exc)
            return False
        self.splits_removed += 1
        self.log.info("split removed (%s): path=%s", why, path)
        return True

    def _check_space(self) -> None:
        """The free-space floor (the lock held, about once a second): below ``min_free_mb`` delete the oldest kept split
        (with keep_splits) or finish the current file and stop recording (one ERROR line)."""
        floor = self.config.min_free_mb
        now = time.monotonic()
        if not floor or now - self._space_checked < 1.0:
            return
        self._space_checked = now
        try:
            free = shutil.disk_usage(self.path.parent).free
        except OSError:
            return  # (the write that fails then says what is wrong)
        if free >= floor * 2**20:
            return
        older = self._older_splits() if self.config.keep_splits else []
        if older and self._remove_split(older[0][1], f"{free / 2**20:.0f} MiB free, min_free_mb = {floor:g}"):
            return
        self._finish_early(free)

    def _finish_early(self, free: int) -> None:
        """Below the free-space floor with nothing to delete: the current file finished (summary and indexes: it reads
        whole) and closed, one ERROR line, every later message ``not_recorded``, the node's exit 1 at the end."""
        reason = f"{free / 2**20:.0f} MiB free on its file system, below min_free_mb = {self.config.min_free_mb:g}"
        try:
            self._writer.finish()
            self._file.close()
            self.finished_early = True
        except OSError as exc:
            self._stop_writing(exc)
            return
        self.write_failed = OSError(errno.ENOSPC, reason)
        self.log.error(
            "recording stopped: %s, after %d messages; %s is finished and reads whole; the run goes on without recording,"
            " every later message counted as not_recorded (free space, or bound the recording with recorder.split_bytes and"
            " keep_splits)", reason, self.messages, self.path,
        )

    def __enter__(self) -> "McapRecorder":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    @property
    def channels(self) -> int:
        """Distinct (topic, schema) channels recorded, over all splits."""
        return len(self._sequences)

    # ---- recording
    def handle(self, key: str, payload: bytes, recv_ns: int) -> list[Issue] | None:
        """Record one payload received on ``key`` at ``recv_ns`` (wall clock, ns)."""
        if not self.config.include_stats and f"/{keys.STATS}/" in key:
            return None
        issue = None
        old_version = False
        schema_name = ""
        publish_ns = recv_ns
        try:
            name, version, header = peek_header(payload, where=key)  # (the body walked, not built: only its header is read)
        except SchemaError as exc:
            issue = f"not an envelope: {exc}"
        else:
            cls = REGISTRY.get(name)
            if cls is None:
                issue = f"unknown schema {name} v{version}"
            elif cls.VERSION != version and not (type(version) is int and version in cls.UPGRADES):
                issue = f"{name} v{version}, this build describes v{cls.VERSION}"
            else:
                if cls.VERSION == version:
                    schema_name = name
                else:  # an older version this build reads (upgrades): known, but the MCAP schema describes VERSION only
                    old_version = True
                if isinstance(header, dict) and type(header.get("stamp_ns")) is int and header["stamp_ns"] >= 0:
                    publish_ns = header["stamp_ns"]
        with self._lock:
            if self._closed.is_set():
                raise RuntimeError(f"recorder for {self.path} is closed")
            if self.write_failed is not None:
                self.not_recorded += 1
                return [Issue(kind="not_recorded", agent_id=-1, detail=f"the recording stopped: {self.write_failed}")]
            try:
                return self._record(key, payload, recv_ns, publish_ns, schema_name, old_version, issue)
            except OSError as exc:  # a full disk, the medium gone: predictions go on, the recording stops, said once
                self._stop_writing(exc)
                self.not_recorded += 1
                return [Issue(kind="not_recorded", agent_id=-1, detail=f"the recording stopped: {exc}")]

    def _record(self, key: str, payload: bytes, recv_ns: int, publish_ns: int, schema_name: str, old_version: bool,
                issue: str | None) -> list[Issue] | None:
        """``handle``'s writing part, the lock held."""
        if schema_name in LATCHED_SCHEMAS:
            payload = bytes(payload)
            if self._file_latched.get(key) == payload:  # a re-publication, or the start query's answer to a value already in
                self.latched_repeats += 1
                return None
            self._latched[key] = (payload, publish_ns, schema_name)
            self._file_latched[key] = payload
        self._write(key, payload, recv_ns, publish_ns, schema_name)
        self.messages += 1
        self._file_fresh += 1
        if self._file_fresh == 1 and self.config.keep_splits:
            self._prune_splits()
        self.old_versions += old_version
        if self._split_due():
            self._next_split()
            self._space_checked = 0.0  # a new file: the floor checked at once
            self._check_space()
        elif self._chunk_bytes >= self.config.chunk_size_bytes or time.monotonic() - self._chunk_opened >= self.config.flush_period_s:
            self._close_chunk()
        if issue is None:
            return None
        self.unrecognised += 1
        return [Issue(kind="unrecognised_payload", agent_id=-1, detail=f"recorded without schema: {issue}")]

    def _stop_writing(self, exc: OSError) -> None:
        """The first write error (the lock held): nothing more is written (the MCAP writer's state after a failed write
        is not to be trusted), one ERROR line now, and every later message counted in ``not_recorded``."""
        if self.write_failed is not None:
            return
        self.write_failed = exc
        self.log.error(
            "recording stopped: cannot write %s (%s) after %d messages; the run goes on without recording, every later"
            " message counted as not_recorded; free the space and start a new recording (the file is torn: `iamp recover`"
            " reads what it holds; recorder.split_bytes / split_s bound each file)", self.path, exc.strerror or exc, self.messages,
        )

    def _write(self, key: str, payload: bytes, log_ns: int, publish_ns: int, schema_name: str) -> None:
        """One message into the open chunk (the lock held); ``schema_name`` empty: a channel without schema."""
        schema_id = self._schema_id(schema_name) if schema_name else 0
        channel_id = self._channel_id(key, schema_id)
        seq = self._sequences[(key, schema_name)] = (self._sequences.get((key, schema_name), 0) + 1) & 0xFFFFFFFF
        self._writer.add_message(channel_id=channel_id, log_time=log_ns, data=bytes(payload), publish_time=publish_ns, sequence=seq)
        self._file_messages += 1
        if self._chunk_bytes == 0:
            self._chunk_opened = time.monotonic()
        self._chunk_bytes += len(payload) + _MESSAGE_OVERHEAD_BYTES

    def _schema_id(self, name: str) -> int:
        sid = self._schema_ids.get(name)
        if sid is None:
            data = json.dumps(json_schema(REGISTRY[name]), sort_keys=True).encode()
            sid = self._schema_ids[name] = self._writer.register_schema(name=name, encoding=SCHEMA_ENCODING, data=data)
            self._chunk_bytes += len(data)
        return sid

    def _channel_id(self, topic: str, schema_id: int) -> int:
        cid = self._channel_ids.get((topic, schema_id))
        if cid is None:
            cid = self._channel_ids[(topic, schema_id)] = self._writer.register_channel(topic=topic, message_encoding=MESSAGE_ENCODING, schema_id=schema_id)
            self._chunk_bytes += len(topic) + 32
        return cid

    def _close_chunk(self) -> None:
        # Writer.flush() closes the open chunk (compressed, with its message
        # indexes) and flushes the file object, so the chunk reaches the OS now.
        self._writer.flush()
        self._chunk_bytes = 0

    def flush(self) -> None:
        """Close the open chunk now and hand it to the OS."""
        with self._lock:
            if not self._closed.is_set() and self._chunk_bytes and self.write_failed is None:
                try:
                    self._close_chunk()
                except OSError as exc:
                    self._stop_writing(exc)

    def _flush_periodically(self) -> None:
        period = self.config.flush_period_s
        while not self._closed.wait(min(period / 4, 0.25)):
            with self._lock:
                if self._closed.is_set():
                    return
                if self.write_failed is not None:
                    continue
                try:
                    if self._split_due():
                        self._next_split()
                    elif self._chunk_bytes and time.monotonic() - self._chunk_opened >= period:
                        self._close_chunk()
                    self._check_space()
                except OSError as exc:  # (it was logged every 0.25 s, thousands of lines, while the disk stayed full)
                    self._stop_writing(exc)

    # ---- end
    def close(self) -> None:
        """Write the summary and indexes and close the file (idempotent)."""
        with self._lock:
            if self._closed.is_set():
                return
            self._closed.set()
            try:
                if self.write_failed is None:
                    self._writer.finish()
            except OSError as exc:  # the summary does not fit either: the file stays torn, said once
                self._stop_writing(exc)
            finally:
                try:
                    self._file.close()  # (a second close of a file finished early does nothing)
                except OSError as exc:
                    self._stop_writing(exc)
            if not self._file_fresh and len(self.paths) > 1:  # opened by the last cut, never used
                self.path.unlink(missing_ok=True)
                self.paths.pop()
                self.path = self.paths[-1]
        if len(self.paths) > 1:
            kept = [p for p in self.paths if p.exists()]
            self.log.info("recording closed: path=%s messages=%d channels=%d old_versions=%d latched_repeats=%d splits=%d (%s)%s", self.path, self.messages, self.channels, self.old_versions, self.latched_repeats, len(self.paths), ", ".join(p.name for p in kept),
                          f"; {self.splits_removed} older splits removed" if self.splits_removed else "")
        else:
            self.log.info("recording closed: path=%s messages=%d channels=%d old_versions=%d latched_repeats=%d", self.path, self.messages, self.channels, self.old_versions, self.latched_repeats)

    def end_failure(self) -> str | None:
        """Why the run's recording is not whole, for the node's exit code (1), or None: it stopped on a write error."""
        if self.write_failed is None:
            return None
        if self.finished_early:
            return (f"the recording stopped early: {self.write_failed.strerror}; {self.messages} messages recorded ({self.path}"
                    f" reads whole), {self.not_recorded} received after it not recorded")
        return (f"the recording stopped on a write error ({self.write_failed.strerror or self.write_failed}) after {self.messages}"
                f" messages; {self.not_recorded} received after it were not recorded; {self.path} is torn: `iamp recover` reads it")

    def abandon(self) -> None:
        """The node could not start (its bus session failed): close, and remove the files this recorder created if
        nothing was received into them, so that a bad command line leaves no file behind."""
        self.close()
        if not self.messages:
            for path in self._created:
                path.unlink(missing_ok=True)


def _make_core(config: RecorderConfig, ctx: NodeContext) -> McapRecorder:
    return McapRecorder(config, run_id=ctx.run_id, log=ctx.log, node_id=ctx.node_id)


SPEC = StageSpec(
    stage="stages.recorder",
    config_cls=RecorderConfig,
    make_core=_make_core,
    inputs={},
    outputs={},
    kind="raw_sink",
    restart_default=True,  # the launcher restarts a killed recorder into the next split file
    preflight=preflight,
)


# The runtime's input queue drops its oldest entry when full; a recorder must lose
# nothing, so it gets a deep queue unless the command line (or the launcher's
# queue_size) says otherwise. A burst of this many messages is absorbed.
RECORDER_QUEUE_SIZE = 100_000


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not any(a == "--queue-size" or a.startswith("--queue-size=") for a in argv):
        argv = ["--queue-size", str(RECORDER_QUEUE_SIZE), *argv]
    return run_stage(SPEC, argv)

