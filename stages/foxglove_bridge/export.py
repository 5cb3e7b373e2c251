"""``iamp export foxglove RUN.mcap OUT.mcap``: a recording in Foxglove's own schemas.

Reads the recording with the recorder's reader (``stages.recorder.inspect``,
the home of mcap; a recording cut short reads up to its last complete
chunk), decodes each payload with ``bus_schemas`` and hands it to
``FoxgloveScene``, whose channels write, through ``foxglove-sdk``'s MCAP
writer (``foxglove.open_mcap`` on a context of its own), protobuf messages
of Foxglove's schemas (``foxglove.SceneUpdate``, ``foxglove.Grid``,
``foxglove.FrameTransform``) and JSON for the plottable stage statistics.
Every message keeps its log time from the recording; entities carry their
source stamp. The map is found by SceneInfo's map name in ``--data``
(default the embedded ``stages/data/taf-bw``) and checked by sha256.

Exit codes: 0 written; 2 a missing, foreign or empty input file, an output
that cannot be written, or a bad option (one line on stderr saying what).
A payload that does not decode is counted and left out (one line at the end).
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from dataclasses import dataclass, field
from typing import Any

from bus_schemas import REGISTRY, SchemaError, decode_any
from stages.lib.base import ConfigError, check_output
from stages.lib.recording_files import put_in_place
from stages.recorder.inspect import ReadReport, RecordingError, read_messages


@dataclass
class ExportReport:
    src: str
    dst: str
    read: int = 0
    undecodable: int = 0
    truncated: bool = False
    error: str = ""
    damaged_chunks: int = 0
    damaged_bytes: int = 0
    damage: str = ""
    logged: dict[str, int] = field(default_factory=dict)
    skipped: dict[str, int] = field(default_factory=dict)
    map_problems: list[str] = field(default_factory=list)

    def line(self) -> str:
        total = sum(self.logged.values())
        parts = [f"exported {total} Foxglove messages on {len(self.logged)} topics from {self.read} recorded messages into {self.dst}"]
        if self.undecodable:
            parts.append(f"{self.undecodable} undecodable payloads left out")
        if self.truncated:
            parts.append(f"source truncated, read up to its last complete chunk: {self.error}")
        if self.damaged_chunks:
            parts.append(f"source damaged, {self.damaged_chunks} unreadable chunks skipped ({self.damaged_bytes} bytes, their messages left out): {self.damage}")
        if self.map_problems:
            parts.append(f"map not drawn: {'; '.join(self.map_problems)}")
        return "; ".join(parts)


def export_foxglove(src: str, dst: str, *, data: str | None = None, grid_step: str | float = "max") -> ExportReport:
    """Convert recording ``src`` into ``dst`` (Foxglove schemas); raises ``RecordingError`` for an input that is no MCAP recording.

    The output is written to a temporary file next to ``dst`` and moved into
    place when complete, so a failed export leaves no half file.
    """
    import foxglove  # loaded when used: `iamp --help` does not pay for it

    from stages.foxglove_bridge.scene import FoxgloveScene

    src, dst = str(src), str(dst)
    report = ExportReport(src=src, dst=dst)
    read = ReadReport()
    messages = read_messages(src, read)
    first = next(messages, None)  # RecordingError here for a missing or foreign file, before anything is written
    if first is None and not read.messages:
        raise RecordingError(f"{src}: holds no messages ({read.error or 'an empty recording'})")
    out_dir = os.path.dirname(os.path.abspath(dst))
    os.makedirs(out_dir, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=".export-", suffix=".mcap", dir=out_dir)
    os.close(fd)
    context = foxglove.Context()
    try:
        writer = foxglove.open_mcap(tmp, allow_overwrite=True, context=context)
        try:
            scene = FoxgloveScene(context, data=data, grid_step=grid_step)
            msg = first
            foreign: dict[str, int] = {}
            while msg is not None:
                report.read += 1
                if msg.schema not in REGISTRY:
                    foreign[msg.schema or "(none)"] = foreign.get(msg.schema or "(none)", 0) + 1
                if msg.schema in REGISTRY:
                    try:
                        scene.add(msg.topic, decode_any(msg.data), msg.log_time_ns)
                    except SchemaError:
                        report.undecodable += 1
                else:
                    report.undecodable += 1
                msg = next(messages, None)
            scene.finish()  # what still waits for its partner message is counted as left out
        finally:
            writer.close()
        if report.undecodable == report.read:
            names = ", ".join(f"{k} ({v})" for k, v in sorted(foreign.items(), key=lambda kv: -kv[1])[:5]) or "none"
            raise RecordingError(f"{src}: not a hybrid-iamp recording: none of its {report.read} messages is a bus message of this build (schemas: {names})")
        put_in_place(tmp, dst)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise
    report.truncated, report.error = read.truncated, read.error
    report.damaged_chunks, report.damaged_bytes, report.damage = read.damaged_chunks, read.damaged_bytes, read.damage
    report.logged = dict(sorted(scene.counts.logged.items()))
    report.skipped = dict(scene.counts.skipped)
    report.map_problems = list(scene.counts.map_problems)
    return report


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("file", metavar="RUN.mcap", help="a hybrid-iamp recording (msgpack MCAP)")
    parser.add_argument("out", metavar="OUT.mcap", help="the MCAP file to write, in Foxglove schemas (replaced if it exists)")
    parser.add_argument("--data", default="", help="data folder whose maps/ holds the scene's map (default: the embedded stages/data/taf-bw)")
    parser.add_argument("--grid-step", default="max", help="motion grid written: max (maximum over the steps, default), all (one topic per step) or a step time in seconds, e.g. 2.0")


def run(args: argparse.Namespace) -> int:
    """``iamp export foxglove``: 0 written, 2 bad input, output or option."""
    from stages.foxglove_bridge.scene import parse_grid_step

    try:
        grid_step = parse_grid_step(args.grid_step)
    except ValueError as exc:
        sys.stderr.write(f"iamp export foxglove: --grid-step: {exc}\n")
        return 2
    if args.data and not os.path.isdir(args.data):  # else the export ran and drew no map, exit 0
        sys.stderr.write(f"iamp export foxglove: --data {args.data}: no such folder (expected a data folder with maps/<recording>.osm)\n")
        return 2
    if os.path.abspath(args.file) == os.path.abspath(args.out):
        sys.stderr.write("iamp export foxglove: OUT.mcap must differ from RUN.mcap\n")
        return 2
    try:
        check_output(args.out, "OUT.mcap")
    except ConfigError as exc:
        sys.stderr.write(f"iamp export foxglove: {exc}\n")
        return 2
    try:
        report = export_foxglove(args.file, args.out, data=args.data or None, grid_step=grid_step)
    except RecordingError as exc:
        sys.stderr.write(f"iamp export foxglove: {exc}\n")
        return 2
    except OSError as exc:
        sys.stderr.write(f"iamp export foxglove: cannot write {args.out}: {exc.strerror or exc}\n")
        return 2
    sys.stdout.write(report.line() + "\n")
    for topic, n in report.logged.items():
        sys.stdout.write(f"  {topic:40s} {n}\n")
    for reason, n in report.skipped.items():
        sys.stdout.write(f"  left out: {reason}: {n}\n")
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="iamp export foxglove", description=__doc__.splitlines()[0])
    add_arguments(parser)
    return run(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
