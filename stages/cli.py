"""The ``iamp`` command: record, replay and inspect MCAP recordings; evaluate predictions; train the AR model.

::

    iamp record FILE.mcap --run-id R [network flags]      record iamp/R/** until Ctrl-C
    iamp replay FILE.mcap [--speed X|max] [--run-id R]     publish a recording onto the bus
    iamp inspect FILE.mcap [--json]                        channels, counts, time range, frames
    iamp recover FILE.mcap [OUT.mcap] [--json]             rewrite a torn recording (killed writer) into a finished file
    iamp eval [--data PATH] [--recording NAME]... [--mode M...] [--stride S] [--json FILE] [--figures DIR]
                                                           offline metrics of the prediction modes
    iamp calibrate --recording NAME --out FILE [--model M] [--mode M...]
                                                           fit the spread of the grids (coverage90 = 0.9) on one location
    iamp train [--data PATH] [--recording NAME...] [--split S] [--hidden N] [--out FILE] [--json FILE]
                                                           train the AR acceleration model

Exit codes: 0 success, 1 crash, 2 bad command line, configuration or file.
Only ``record`` and ``replay`` open a Zenoh session.
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Callable

EXIT_USAGE = 2


def _add_record(sub: "argparse._SubParsersAction") -> None:
    p = sub.add_parser("record", help="record every key of a run into an MCAP file until Ctrl-C")
    p.add_argument("file", metavar="FILE.mcap", help="file to write (parent folders are created)")
    p.add_argument("--run-id", required=True, help="run to record: keys iamp/<run>/**")
    p.add_argument("--node-id", default="recorder", help="node id of the recorder (default recorder)")
    p.add_argument("--compression", choices=["zstd", "lz4", "none"], default=None, help="chunk compression (default zstd)")
    p.add_argument("--chunk-size-bytes", type=int, default=None, help="close a chunk at about this size (default 262144)")
    p.add_argument("--flush-period-s", type=float, default=None, help="close the open chunk at least this often (default 1)")
    p.add_argument("--split-bytes", type=int, default=None, help="start the next split file (FILE.001.mcap, ...) at about this size (default 0: never)")
    p.add_argument("--split-s", type=float, default=None, help="start the next split file after this many seconds (default 0: never)")
    p.add_argument("--no-stats", action="store_true", help="leave out the _stats keys")
    p.add_argument("--log-level", default="INFO")
    from stages.runtime import add_network_args

    add_network_args(p)
    p.set_defaults(run=_run_record)


def _run_record(args: argparse.Namespace) -> int:
    from stages import recorder

    params: dict[str, object] = {"path": args.file}
    for name in ("compression", "chunk_size_bytes", "flush_period_s", "split_bytes", "split_s"):
        if getattr(args, name) is not None:
            params[name] = getattr(args, name)
    if args.no_stats:
        params["include_stats"] = False
    argv = ["--run-id", args.run_id, "--node-id", args.node_id, "--params-json", json.dumps(params), "--log-level", args.log_level, "--mode", args.mode]
    argv += [x for e in args.connect for x in ("--connect", e)]
    argv += [x for e in args.listen for x in ("--listen", e)]
    if args.config:
        argv += ["--config", args.config]
    return recorder.main(argv)


def _add_replay(sub: "argparse._SubParsersAction") -> None:
    from stages.replay.core import add_cli_arguments

    p = sub.add_parser("replay", help="publish a recording onto the bus (original timing or --speed max)")
    add_cli_arguments(p)
    p.set_defaults(run=_run_replay)


def _run_replay(args: argparse.Namespace) -> int:
    from stages.replay.core import run_cli

    return run_cli(args)


def _add_inspect(sub: "argparse._SubParsersAction") -> None:
    from stages.recorder.inspect import add_arguments

    p = sub.add_parser("inspect", help="summarise a recording: channels, counts, time range, frames")
    add_arguments(p)
    p.set_defaults(run=_run_inspect)


def _run_inspect(args: argparse.Namespace) -> int:
    from stages.recorder.inspect import run

    return run(args)


def _add_recover(sub: "argparse._SubParsersAction") -> None:
    from stages.recorder.inspect import add_recover_arguments

    p = sub.add_parser("recover", help="rewrite a recording cut short by a killed writer into a finished MCAP file that any reader reads")
    add_recover_arguments(p)
    p.set_defaults(run=_run_recover)


def _run_recover(args: argparse.Namespace) -> int:
    from stages.recorder.inspect import run_recover

    return run_recover(args)


def _add_eval(sub: "argparse._SubParsersAction") -> None:
    from stages.offline.evaluation import add_arguments

    p = sub.add_parser("eval", help="offline comparison of prediction modes against ground truth (mADE/mFDE, coverage, NLL)")
    add_arguments(p)
    p.set_defaults(run=_run_eval)


def _run_eval(args: argparse.Namespace) -> int:
    from stages.offline.evaluation import run_cli

    return run_cli(args)


def _add_calibrate(sub: "argparse._SubParsersAction") -> None:
    from stages.offline.calibrate import add_arguments

    p = sub.add_parser("calibrate", help="fit each mode's grid spread per step and speed band so that the 90 % region holds the truth in 90 % of windows")
    add_arguments(p)
    p.set_defaults(run=_run_calibrate)


def _run_calibrate(args: argparse.Namespace) -> int:
    from stages.offline.calibrate import run_cli

    return run_cli(args)


def _add_train(sub: "argparse._SubParsersAction") -> None:
    from stages.offline.train.cli import add_arguments

    p = sub.add_parser("train", help="train the AR acceleration model on recordings (validation vs zero / last-value baselines)")
    add_arguments(p)
    p.set_defaults(run=_run_train)


def _run_train(args: argparse.Namespace) -> int:
    from stages.offline.train.cli import run_cli

    return run_cli(args)


# Subcommands, in the order `iamp --help` lists them. Later issues add theirs here:
#   eval  -> _add_eval  (offline comparison: hybrid vs baseline vs constant velocity; mADE/mFDE table)
#   train -> _add_train (retrain the AR acceleration model)
# Each adder declares its subparser and sets `run` to a function args -> exit code,
# importing its heavy modules inside that function.
SUBCOMMANDS: list[Callable[["argparse._SubParsersAction"], None]] = [
    _add_record,
    _add_replay,
    _add_inspect,
    _add_recover,
    _add_eval,
    _add_calibrate,
    _add_train,
]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="iamp", description="hybrid-iamp tools: record, replay and inspect runs; evaluate predictions.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for add in SUBCOMMANDS:
        add(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:
        return 0 if exc.code == 0 else EXIT_USAGE
    if getattr(args, "run", None) is None:
        parser.print_usage(sys.stderr)
        sys.stderr.write("iamp: error: a command is required\n")
        return EXIT_USAGE
    return int(args.run(args))


if __name__ == "__main__":
    sys.exit(main())
