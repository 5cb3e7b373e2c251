"""Command line of ``iamp train`` (see ``stages.offline.train.fit``): arguments only, nothing heavy imported.

``stages.cli`` builds every subcommand's parser on each ``iamp`` call, so this
module imports neither torch nor the data code; ``run_cli`` imports
``stages.offline.train.fit`` when the command runs.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from stages.offline.train import DEFAULT_CACHE_DIR, DEFAULT_OUT, LOSSES, SPLITS


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The flags of ``iamp train`` (module docstring of ``stages.offline.train.fit``)."""
    from stages.lib.datasets import DEFAULT_DATA_DIR

    p.add_argument("--data", type=Path, default=DEFAULT_DATA_DIR, help=f"data folder (default the embedded {DEFAULT_DATA_DIR})")
    p.add_argument("--recording", action="extend", nargs="+", default=[], metavar="NAME", help="recordings to use (default all of --data; in the embedded folder its K729 recording)")
    p.add_argument("--sequence", action="extend", nargs="+", default=[], metavar="ID", help="sequences to use (default all)")
    p.add_argument("--split", choices=SPLITS, default="sequence", help="how to hold out validation data (default sequence)")
    p.add_argument("--val-fraction", type=float, default=0.2, help="share held out for validation (default 0.2)")
    p.add_argument("--kind", choices=("ar", "gru"), default="ar", help="ar: AR-Net, linear or with --hidden one ReLU layer (default); gru: a GRU over the history")
    p.add_argument("--hidden", type=int, default=None, help="kind ar: 0 linear AR-Net (default), N one ReLU hidden layer of N units; kind gru: GRU units (default 32)")
    p.add_argument("--tied-routes", choices=("weight", "drop", "first"), default="weight",
                   help="windows whose route the future cannot decide: one sample per tied corridor weighted 1/k (default), dropped, or on the first")
    p.add_argument("--min-future-steps", type=int, default=10, help="least known target steps (of 40) a window needs (default 10; 40: whole 4 s future only)")
    p.add_argument("--epochs", type=int, default=200, help="maximum epochs (default 200; early stopping usually ends sooner)")
    p.add_argument("--patience", type=int, default=20, help="epochs without validation improvement before stopping (default 20; 0: no early stopping, train --epochs and keep the last epoch's weights)")
    p.add_argument("--folds", type=int, default=0, metavar="R",
                   help="choose the epoch count by the mean validation loss of R repeated --split splits trained side by side,"
                        " then train one net on every sample for that many epochs (0: one split, early stopping; default 0)")
    p.add_argument("--batch-size", type=int, default=256)
    p.add_argument("--lr", type=float, default=1e-3, help="Adam learning rate, the cosine schedule's peak (default 1e-3)")
    p.add_argument("--weight-decay", type=float, default=None, help="Adam L2 weight decay (default 0.3 linear, 0.1 with --hidden, 0.01 for --kind gru)")
    p.add_argument("--z-clip", type=float, default=3.0, help="clip the z-scored features to ± this (default 3)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--device", default="cpu", help="cpu (default) or cuda")
    p.add_argument("--drop-feature", nargs="+", default=[], metavar="NAME", help="leave features out (ablation), names as in FEATURE_NAMES")
    p.add_argument("--loss", choices=LOSSES, default="accel",
                   help="what the loss (MSE + MAE) compares: the target steps' accelerations (default) or the along-track"
                        " displacement they integrate to over the 4 s (what mADE scores)")
    p.add_argument("--accel-window", type=float, default=None, help="causal acceleration window, s (default 1.0)")
    p.add_argument("--position-noise", type=float, default=0.0, metavar="M",
                   help="augmentation: jitter each track's positions by white noise of a σ drawn per track from [0, M] m (default 0: off)")
    p.add_argument("--speed-factors", type=_factors, default=(), metavar="F,F",
                   help="augmentation: also play each sequence at these speed factors (time scaled by 1/F, the whole scene;"
                        " e.g. 0.8,1.25; default none)")
    p.add_argument("--max-frames", type=int, default=0, help="use at most this many frames per sequence (0: all)")
    p.add_argument("--out", type=Path, default=DEFAULT_OUT, help=f"weights file to write (default {DEFAULT_OUT})")
    p.add_argument("--json", type=Path, default=None, help="write the report as JSON")
    p.add_argument("--cache-dir", type=Path, default=DEFAULT_CACHE_DIR, help=f"data set cache (default {DEFAULT_CACHE_DIR})")
    p.add_argument("--no-cache", action="store_true", help="neither read nor write the data set cache")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")


def _factors(text: str) -> tuple[float, ...]:
    """``--speed-factors``: comma-separated numbers (their range is checked by DatasetConfig)."""
    try:
        return tuple(float(x) for x in text.split(",") if x.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected comma-separated numbers, e.g. 0.8,1.25") from None


def run_cli(args: argparse.Namespace) -> int:
    from stages.offline.train.fit import run_from_args

    return run_from_args(args)


__all__ = ["DEFAULT_CACHE_DIR", "DEFAULT_OUT", "SPLITS", "add_arguments", "run_cli"]
