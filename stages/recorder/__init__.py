"""MCAP recorder: every payload of a run, as received, into one MCAP file.

Consumes every key under ``iamp/<run>/**`` as raw bytes (runtime kind
``raw_sink``; the runtime leaves out ``_ack``), whatever its schema, and
produces an MCAP file with one channel per key (topic = key, message
encoding ``msgpack``). Schemas come from ``bus_schemas.REGISTRY`` by the
envelope's schema name (schema encoding ``jsonschema``, data = the JSON
description of the message body). A payload that is no valid envelope, or of
a schema or version this build does not know, is still recorded, on a
channel without schema (schema id 0), and counted as the issue
``unrecognised_payload``: a recording loses nothing. A payload of an older
version of a known schema that this build still reads (the class's
``UPGRADES``: e.g. a v1 TrackFrame from an old recording replayed) is
recognised: recorded as it is, also on a channel without schema (the
registered schema describes the current version), with its header's stamp
as ``publish_time``, counted in ``McapRecorder.old_versions`` and not an
issue. ``log_time`` is the
receive time, ``publish_time`` the header's ``stamp_ns`` where the message
has a header (else the receive time). A metadata record ``hybrid-iamp``
holds the run id, the hybrid-iamp version and the start time.

Durability: chunks are closed by the recorder itself, when about
``chunk_size_bytes`` of messages are buffered or ``flush_period_s`` after the
first message of the chunk (a background timer covers quiet periods), and
each closed chunk is flushed to the OS at once (``Writer.flush``). A
``kill -9`` therefore loses at most the open chunk, and the file still reads
up to its last complete chunk (``stages.recorder.inspect.read_messages``). A
clean stop (SIGINT/SIGTERM) writes the summary and indexes.

Split files: the recording is a sequence of files ``run.mcap``,
``run.001.mcap``, ``run.002.mcap``, ... (``split_path``). The recorder starts
a new file when the current one reaches ``split_bytes`` or has been open
``split_s`` seconds (each finished with its summary, schemas and channels
repeated: every split reads alone), and the launcher restarts a killed
recorder into the next split (``split_index``), so a recorder crash costs
the messages of its open chunk and of its restart, never the run. A split
torn by a kill reads with ``stages.recorder.inspect.read_messages``, and
``iamp recover`` rewrites it into a finished file.

Parameters (``RecorderConfig``): ``path`` (empty: ``runs/<run>-<UTC
yyyymmdd-hhmmss>.mcap`` under the current directory), ``chunk_size_bytes``,
``compression`` (``zstd``, ``lz4`` or ``none``), ``include_stats`` (record
``_stats`` keys), ``flush_period_s``, ``split_bytes`` (0: no size limit),
``split_s`` (0: no duration limit), ``split_index`` (the split this process
writes first; 0 is ``path`` itself), ``overwrite`` (false: a ``path`` that is
there, or a split of it, is refused before anything is written),
``keep_splits`` (with splits: keep only the newest this many files, deleting
older ones as new splits receive their first message; 0: keep all),
``min_free_mb`` (default 64; 0: none): the free-space floor, checked about
once a second, below which the oldest kept split is deleted or, with none to
delete, the current file is finished (it reads whole) and recording stops:
one ERROR line, every later message an issue ``not_recorded``, exit 1 at the
end (``end_failure``). A write error (a disk full before the floor saw it)
stops it the same way, the file then torn.

Files: each is locked (``flock``) while written, so a second recorder on it
is refused; a file the recorder made and never wrote a message into is
removed when the node cannot start (``abandon``). Latched payloads (the
scene): every split starts with the newest one of each key, a payload equal
to the one the file holds on its key is not written again
(``latched_repeats``), and the runtime asks the run's latched outputs for
their values when the recorder comes up, so a recorder started mid-run or
restarted still records the scene.
"""

from __future__ import annotations

from stages.recorder.core import SPEC, main, McapRecorder, RecorderConfig, default_path, split_path, split_paths, iamp_version

__all__ = ["SPEC", "main", 'McapRecorder', 'RecorderConfig', 'default_path', 'split_path', 'split_paths', 'iamp_version']
