"""The ``iamp`` command: record, replay and inspect MCAP recordings; evaluate predictions; train the AR model.

::

    iamp record FILE.mcap --run-id R [network flags]      record iamp/R/** until Ctrl-C
    iamp replay FILE.mcap [--speed X|max] [--run-id R]     publish a recording onto the bus
    iamp inspect FILE.mcap [--json]                        channels, counts, time range, frames
    iamp recover FILE.mcap [OUT.mcap] [--json]             rewrite a torn recording (killed writer) into a finished file
    iamp export foxglove RUN.mcap OUT.mcap [--data PATH] [--grid-step max|all|S]
                                                           the recording in Foxglove's schemas (foxglove-sdk)
    iamp eval [--data PATH] [--recording NAME]... [--mode M...] [--stride S] [--json FILE] [--figures DIR] [--report DIR]
                                                           offline metrics of the prediction modes
    iamp calibrate --recording NAME --out FILE [--model M] [--mode M...]
                                                           fit the spread of the grids (coverage90 = 0.9) on one location
    iamp train [--data PATH] [--recording NAME...] [--split S] [--hidden N] [--out FILE] [--json FILE]
                                                           train the AR acceleration model
    iamp signals --data DIR --recording NAME [--map FILE.osm] [--figure FILE.png] [--json FILE]
                                                           match a KML lane file to the map: report, figure
    iamp data superimpose --data PATH --recording NAME --vehicles N --out DIR [--sequence S]... [--shift-s T] [--duration-s D] [--name NAME]
                                                           dense traffic: time-shifted copies of real tracks of one map

Exit codes: 0 success, 1 crash, 2 bad command line, configuration or file.
Only ``record`` and ``replay`` open a Zenoh session.
"""

from __future__ import annotations

import argparse
import json
import os
import math
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

EXIT_USAGE = 2


def _args_record(p: argparse.ArgumentParser) -> None:
    p.add_argument("file", metavar="FILE.mcap", help="file to write (parent folders are created)")
    p.add_argument("--run-id", required=True, help="run to record: keys iamp/<run>/**")
    p.add_argument("--node-id", default="recorder", help="node id of the recorder (default recorder)")
    p.add_argument("--compression", choices=["zstd", "lz4", "none"], default=None, help="chunk compression (default zstd)")
    p.add_argument("--chunk-size-bytes", type=int, default=None, help="close a chunk at about this size (default 262144)")
    p.add_argument("--flush-period-s", type=float, default=None, help="close the open chunk at least this often (default 1)")
    p.add_argument("--split-bytes", type=int, default=None, help="start the next split file (FILE.001.mcap, ...) at about this size (default 0: never)")
    p.add_argument("--split-s", type=float, default=None, help="start the next split file after this many seconds (default 0: never)")
    p.add_argument("--keep-splits", type=int, default=None, help="with --split-bytes or --split-s: keep only the newest N split files (default 0: all)")
    p.add_argument("--min-free-mb", type=float, default=None, help="finish the file and stop recording (or delete the oldest kept split) below this much"
                   " free space on its file system, MiB (default 64; 0: none)")
    p.add_argument("--no-stats", action="store_true", help="leave out the _stats keys")
    p.add_argument("--overwrite", action="store_true", help="replace FILE.mcap (and its split files) where it exists; without it an existing file is refused")
    from stages.runtime import add_network_args
    from stages.runtime.args import LOG_LEVELS

    p.add_argument("--log-level", default="INFO", type=str.upper, choices=LOG_LEVELS, help="DEBUG, INFO (default), WARNING, ERROR or CRITICAL")

    add_network_args(p)
    p.set_defaults(run=_run_record)


def _run_record(args: argparse.Namespace) -> int:
    from stages import recorder

    params: dict[str, object] = {"path": args.file}
    for name in ("compression", "chunk_size_bytes", "flush_period_s", "split_bytes", "split_s", "keep_splits", "min_free_mb"):
        if getattr(args, name) is not None:
            params[name] = getattr(args, name)
    if args.no_stats:
        params["include_stats"] = False
    if args.overwrite:
        params["overwrite"] = True
    argv = ["--run-id", args.run_id, "--node-id", args.node_id, "--params-json", json.dumps(params), "--log-level", args.log_level, "--mode", args.mode]
    argv += [x for e in args.connect for x in ("--connect", e)]
    argv += [x for e in args.listen for x in ("--listen", e)]
    if args.config:
        argv += ["--config", args.config]
    return recorder.main(argv)


def _args_replay(p: argparse.ArgumentParser) -> None:
    from stages.replay.core import add_cli_arguments

    add_cli_arguments(p)
    p.set_defaults(run=_run_replay)


def _run_replay(args: argparse.Namespace) -> int:
    from stages.replay.core import run_cli

    return run_cli(args)


def _args_inspect(p: argparse.ArgumentParser) -> None:
    from stages.recorder.inspect import add_arguments

    add_arguments(p)
    p.set_defaults(run=_run_inspect)


def _run_inspect(args: argparse.Namespace) -> int:
    from stages.recorder.inspect import run

    return run(args)


def _args_recover(p: argparse.ArgumentParser) -> None:
    from stages.recorder.inspect import add_recover_arguments

    add_recover_arguments(p)
    p.set_defaults(run=_run_recover)


def _run_recover(args: argparse.Namespace) -> int:
    from stages.recorder.inspect import run_recover

    return run_recover(args)


def _args_export(p: argparse.ArgumentParser) -> None:
    formats = p.add_subparsers(dest="format", metavar="FORMAT")
    from stages.foxglove_bridge.export import add_arguments

    f = formats.add_parser("foxglove", help="the recording in Foxglove's schemas (SceneUpdate, Grid, FrameTransform; JSON stats), written with foxglove-sdk")
    add_arguments(f)
    f.set_defaults(run=_run_export_foxglove)
    p.set_defaults(run=_export_usage(p))


def _export_usage(parser: argparse.ArgumentParser) -> Callable[[argparse.Namespace], int]:
    def run(args: argparse.Namespace) -> int:
        parser.print_usage(sys.stderr)
        sys.stderr.write("iamp export: a format is required (foxglove)\n")
        return EXIT_USAGE

    return run


def _run_export_foxglove(args: argparse.Namespace) -> int:
    from stages.foxglove_bridge.export import run

    return run(args)


def _args_eval(p: argparse.ArgumentParser) -> None:
    from stages.offline.eval_args import add_arguments

    add_arguments(p)
    p.set_defaults(run=_run_eval)


def _run_eval(args: argparse.Namespace) -> int:
    from stages.offline.evaluation import run_cli

    return run_cli(args)


def _args_signals(p: argparse.ArgumentParser) -> None:
    from stages.offline.signals import add_arguments

    add_arguments(p)
    p.set_defaults(run=_run_signals)


def _run_signals(args: argparse.Namespace) -> int:
    from stages.offline.signals import run_cli

    return run_cli(args)


def _args_calibrate(p: argparse.ArgumentParser) -> None:
    from stages.offline.calibrate import add_arguments

    add_arguments(p)
    p.set_defaults(run=_run_calibrate)


def _run_calibrate(args: argparse.Namespace) -> int:
    from stages.offline.calibrate import run_cli

    return run_cli(args)


def _args_train(p: argparse.ArgumentParser) -> None:
    from stages.offline.train.cli import add_arguments

    add_arguments(p)
    p.set_defaults(run=_run_train)


def _run_train(args: argparse.Namespace) -> int:
    from stages.offline.train.cli import run_cli

    return run_cli(args)


def _args_data(p: argparse.ArgumentParser) -> None:
    from stages.lib.datasets.superimpose import MAX_DURATION_S, MAX_SHIFT_S, MAX_VEHICLE_SECONDS, MAX_VEHICLES

    data_sub = p.add_subparsers(dest="data_command", metavar="DATA_COMMAND")
    s = data_sub.add_parser(
        "superimpose",
        help="write a recording (maps/ + recorded_trackfiles/, like TAF-BW) of N vehicles per frame on average, "
        "superimposed from time-shifted copies of a recording's sequences with fresh track ids",
    )
    s.add_argument("--data", required=True, help="source data folder (maps/ + recorded_trackfiles/, INTERACTION format)")
    s.add_argument("--recording", required=True, help="source recording, e.g. k733_2018-05-02")
    s.add_argument("--sequence", action="append", default=[], help="source sequence (repeatable; default all)")
    s.add_argument("--vehicles", type=float, required=True,
                   help=f"target mean number of vehicles per frame (above 0, at most {MAX_VEHICLES}; "
                   f"--vehicles x --duration-s at most {MAX_VEHICLE_SECONDS:.0f} vehicle-seconds)")
    s.add_argument("--out", required=True,
                   help="output data folder (created; the recording's files in it are replaced once the new ones are complete; "
                   "it may not hold the source recording or its map, as --data does, nor lie in the source recording's folder)")
    s.add_argument("--name", default=None,
                   help="name of the new recording, a plain folder name (no '/', '\\' or '..', not starting with '.'; "
                   "default <recording>-dense<N>, N as given)")
    s.add_argument("--shift-s", type=float, default=None,
                   help=f"time shift between copies, above 0 and at most {MAX_SHIFT_S:.0f} s (default: the signal cycle estimated "
                   "from the tracks)")
    s.add_argument("--duration-s", type=float, default=None,
                   help=f"duration of the output, at most {MAX_DURATION_S:.0f} s (a day) (default: the longest source sequence)")
    s.add_argument("--json", action="store_true", help="print the result as JSON")
    p.set_defaults(run=_run_data, parser=p)


def _run_data(args: argparse.Namespace) -> int:
    if getattr(args, "data_command", None) != "superimpose":
        args.parser.print_usage(sys.stderr)
        sys.stderr.write("iamp data: error: a data command is required (superimpose)\n")
        return EXIT_USAGE
    from stages.lib.base import ConfigError, check_output
    from stages.lib.datasets import DatasetError
    from stages.lib.datasets.loader import find_recording
    from stages.lib.datasets.superimpose import build_dense, check_name, check_out_apart, check_request

    finite = [v for v in (args.vehicles, args.shift_s, args.duration_s) if v is not None]
    if not all(math.isfinite(v) for v in finite) or not args.vehicles > 0 or (args.shift_s is not None and not args.shift_s > 0) \
            or (args.duration_s is not None and not args.duration_s > 0):
        sys.stderr.write("iamp data superimpose: --vehicles, --shift-s and --duration-s must be finite and positive "
                         "(--shift-s 0 stacks the copies of a sequence on one another)\n")
        return EXIT_USAGE
    try:  # before the output folder is created: a refused command line leaves no folder behind
        check_request(args.vehicles, shift_s=args.shift_s, duration_s=args.duration_s)
        if args.name is not None:
            check_name(args.name)
        try:
            source = find_recording(args.data, args.recording)
        except DatasetError:
            source = None  # reported by build_dense, after --out's own check (a bad --out is named first)
        if source is not None:
            check_out_apart(args.out, source)
    except DatasetError as exc:
        sys.stderr.write(f"iamp data superimpose: {exc}\n")
        return EXIT_USAGE
    out = Path(args.out)
    made = [f for f in (out, *out.parents) if not f.exists()]  # the folders check_output creates, deepest first
    try:
        check_output(args.out, "--out", folder=True)
    except ConfigError as exc:
        sys.stderr.write(f"iamp data superimpose: {exc}\n")
        return EXIT_USAGE
    try:
        result = build_dense(
            args.data, args.recording, args.vehicles, args.out, name=args.name, sequences=args.sequence or None,
            shift_s=args.shift_s, duration_s=args.duration_s,
        )
    except (DatasetError, OSError) as exc:
        for folder in made:  # a refused request leaves no folder behind (only those it made, and only while empty)
            try:
                folder.rmdir()
            except OSError:
                break
        if isinstance(exc, DatasetError):
            sys.stderr.write(f"iamp data superimpose: {exc}\n")
            return EXIT_USAGE
        sys.stderr.write(f"iamp data superimpose: writing the recording failed: {exc.strerror or exc}"
                         f"{f' ({exc.filename})' if exc.filename else ''}; an earlier recording of that name is as it was\n")
        return 1
    summary = {
        "out": str(result.out_dir), "recording": result.name, "layers": len(result.layers),
        "shifts_s": [round(l.shift_s, 3) for l in result.layers],
        "shares": [round(l.share, 3) for l in result.layers], "duration_s": result.duration_s, "tracks": result.n_tracks,
        "rows": result.n_rows, "vehicles_mean": result.vehicles_mean, "vehicles_median": result.vehicles_median,
        "vehicles_max": result.vehicles_max,
    }
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        partial = [l.share for l in result.layers if l.share < 1.0]
        part = f" (the last {partial[-1]:.0%} of its tracks)" if partial else ""
        print(f"{result.out_dir}: recording {result.name}, {len(result.layers)} layers{part}, {result.duration_s:.1f} s, "
              f"{result.n_tracks} tracks; vehicles per frame mean {result.vehicles_mean:.1f}, median {result.vehicles_median:.0f}, "
              f"max {result.vehicles_max}")
    return 0


# Subcommands, in the order `iamp --help` lists them: name, help, and the function that adds the command's arguments
# and `run` (a function args -> exit code that imports the heavy modules). Only the chosen command's arguments are
# added (``build_parser(only)``): a command's options may import its module (`iamp eval`'s the stage cores, scipy,
# numba: ~1.7 s), so the others' must not be built on every start.
@dataclass(frozen=True)
class _Command:
    name: str
    help: str
    add_arguments: Callable[[argparse.ArgumentParser], None]


SUBCOMMANDS: list[_Command] = [
    _Command("record", help="record every key of a run into an MCAP file until Ctrl-C", add_arguments=_args_record),
    _Command("replay", help="publish a recording onto the bus (original timing or --speed max)", add_arguments=_args_replay),
    _Command("inspect", help="summarise a recording: channels, counts, time range, frames", add_arguments=_args_inspect),
    _Command("recover", help="rewrite a recording cut short by a killed writer into a finished MCAP file that any reader reads", add_arguments=_args_recover),
    _Command("export", help="convert a recording for another tool: `iamp export foxglove RUN.mcap OUT.mcap` (Foxglove's schemas)", add_arguments=_args_export),
    _Command("eval", help="offline comparison of prediction modes against ground truth (mADE/mFDE, coverage, NLL)", add_arguments=_args_eval),
    _Command("calibrate", help="fit each mode's grid spread per step and speed band so that the 90 %% region holds the truth in 90 %% of windows", add_arguments=_args_calibrate),
    _Command("train", help="train the AR acceleration model on recordings (validation vs zero / last-value baselines)", add_arguments=_args_train),
    _Command("signals", help="match a recording's KML lane file to its map: report and figure of the signalised stop lines", add_arguments=_args_signals),
    _Command("data", help="build data folders from recordings (superimpose: dense traffic from real tracks)", add_arguments=_args_data),
]


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """The ``iamp`` parser: every command with its arguments (``only`` None), or with ``only`` the arguments of that
    command alone (the others listed with their help; any other word, e.g. "": none has its arguments)."""
    parser = argparse.ArgumentParser(prog="iamp", description="hybrid-iamp tools: record, replay and inspect runs; evaluate predictions.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for command in SUBCOMMANDS:
        p = sub.add_parser(command.name, help=command.help)
        if only in (None, command.name):
            command.add_arguments(p)
    return parser


def main(argv: list[str] | None = None) -> int:
    words = list(sys.argv[1:] if argv is None else argv)
    # the command is the first word that is not an option (iamp has no options of its own but -h): only its arguments are
    # built; without one (`iamp`, `iamp --help`) none are
    parser = build_parser(next((w for w in words if not w.startswith("-")), ""))
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:
        return 0 if exc.code == 0 else EXIT_USAGE
    if getattr(args, "run", None) is None:
        parser.print_usage(sys.stderr)
        sys.stderr.write("iamp: error: a command is required\n")
        return EXIT_USAGE
    args.argv = list(argv) if argv is not None else sys.argv[1:]  # the command line as given (iamp eval --report writes it)
    try:
        return int(args.run(args))
    except KeyboardInterrupt:  # Ctrl-C: one line, not a traceback (the offline tools write their outputs at the end)
        sys.stderr.write(f"iamp {getattr(args, 'command', '')}: interrupted\n")
        return 130
    except BrokenPipeError:  # `iamp ... | head`: the reader has what it wanted; the work (a file written) is done
        try:
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # no second error when Python flushes stdout at exit
        except (OSError, ValueError):
            pass
        return 1


if __name__ == "__main__":
    sys.exit(main())
