"""The options of ``iamp eval`` (``stages.offline.evaluation``), apart from the evaluation itself.

``iamp`` builds every subcommand's parser when it starts; importing the evaluation (the stage cores, scipy, numba)
for its options cost every ``iamp`` command about 1.7 s, ``iamp inspect --help`` included. This module imports
nothing heavy; ``stages.offline.evaluation`` re-exports its names.
"""

from __future__ import annotations

from pathlib import Path

from stages.lib.datasets.defaults import DEFAULT_DATA_DIR

#: the modes ``iamp eval`` scores (all by default)
EVAL_MODES = ("hybrid", "baseline", "cv", "corridor_cv")
#: where each corridor's probability comes from
CORRIDOR_WEIGHTS = ("intentions", "uniform")


#: the --dpi a figure may take: below it the text is unreadable, above it one 4 s grid is hundreds of megapixels
DPI_RANGE = (20, 600)


def _dpi(text: str) -> int:
    import argparse

    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number of dots per inch, got {text!r}") from None
    if not DPI_RANGE[0] <= value <= DPI_RANGE[1]:
        raise argparse.ArgumentTypeError(f"{value} is out of range: give {DPI_RANGE[0]} to {DPI_RANGE[1]}")
    return value


def add_arguments(parser) -> None:
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA_DIR, help="data folder laid out like stages/data/taf-bw (default: the embedded scenario)")
    parser.add_argument("--recording", action="extend", nargs="+", default=[], help="recordings to evaluate (one or more, the flag repeatable; default all of --data; in the embedded folder its K729 recording)")
    parser.add_argument("--sequence", action="extend", nargs="+", default=[], help="sequence id to evaluate (one or more, the flag repeatable; default all)")
    parser.add_argument("--mode", nargs="+", default=list(EVAL_MODES), choices=EVAL_MODES, help="prediction modes (default all)")
    parser.add_argument("--stride", type=float, default=0.4, help="seconds between evaluated instants (default 0.4)")
    parser.add_argument("--corridor-weights", choices=list(CORRIDOR_WEIGHTS), default="intentions",
                        help="corridor probabilities: the intentions stage's P(R = c) (default) or uniform")
    parser.add_argument("--model", type=Path, default=None, help="AR model weights for mode hybrid (default: the shipped stages/lib/ar/weights/ar_taf_bw.pt)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the intentions particle filter (default 0)")
    parser.add_argument("--backend", choices=["numpy", "torch", "cuda"], default="numpy",
                        help="Markov backend (default numpy; cuda: the hybrid chain as one CUDA kernel, on --device cuda or cuda:N)")
    parser.add_argument("--device", default="cpu", help="torch device, or the cuda backend's GPU (default cpu)")
    parser.add_argument("--max-frames", type=int, default=0, help="stop each sequence after this many frames (0: all)")
    parser.add_argument("--json", type=Path, default=None, help="write the results as JSON")
    parser.add_argument("--figures", type=Path, default=None,
                        help="write the paper's figures (motion grid at 4 s, predicted means, acceleration distributions) of one instant"
                             " per recording into this folder, PNG and SVG")
    parser.add_argument("--report", type=Path, default=None, metavar="DIR",
                        help="write a report (DIR/report.md, its figures and eval.json) of this run into DIR")
    parser.add_argument("--situations", type=Path, default=None, metavar="FILE.toml",
                        help="named time windows of recordings to report on ([[situation]] recording, sequence, start, end,"
                             " description); default: every recording is one situation")
    parser.add_argument("--svg", choices=["yes", "no"], default="yes", help="write SVG beside each PNG figure (default yes)")
    parser.add_argument("--dpi", type=_dpi, default=100, help=f"resolution of the PNG figures, {DPI_RANGE[0]}-{DPI_RANGE[1]} (default 100)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="markov_prediction parameter for every mode (JSON value), e.g. --set speed_limit_factor=1.1")
    parser.add_argument("--set-ar", action="append", default=[], metavar="KEY=VALUE",
                        help="ar_inference parameter (JSON value), e.g. --set-ar sigma_scale=1.5")
    parser.add_argument("--signals", choices=["on", "off"], default="on",
                        help="play the recordings' signal phases (default on; off: as if they had none; only recordings with phases change)")
    parser.add_argument("--set-intentions", action="append", default=[], metavar="KEY=VALUE",
                        help="intentions parameter (JSON value), e.g. --set-intentions particles_per_vehicle=1000")
