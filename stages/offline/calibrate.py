"""``iamp calibrate``: fit the spread of each mode's grids so that the 90 % region holds the truth in 90 % of the windows.

It runs ``iamp eval``'s chain and scoring (``Evaluation``, same windows,
same centre-point grids) on the recordings given (one location: the other
one is for reporting), and for every scored window also scores its grid
with each candidate σ of ``SIGMAS_M``: the vehicle's grid at every step
widened as the stage widens it with the fitted table, in the mode's
``spread_shape`` (default "auto": along the corridors for hybrid, baseline
and corridor_cv, round for cv): along, the vehicle's grid rebuilt with that σ
along its corridors (``FramePrediction.regrid``, the stage's own code; the
table says ``"shape": "along"``); round, blurred by an isotropic Gaussian
(``markov_prediction.spread.blur_grid``). The means do not move. Per
mode, start-speed band (``BANDS_MPS``: standing ≤ 0.5 m/s, slow ≤ 2 m/s,
fast) and step it counts how often the truth lies in the ``--level``
highest-density region of the vehicle's grid for each candidate, and takes
the smallest σ that reaches the level (linear between candidates; the
largest candidate when none does; 0 when the grid already reaches it: the
spread is never narrowed), made non-decreasing over the steps. It writes the
table to ``--out`` (the file the stage's ``spread_calibration`` reads) with
the coverage it measured at the chosen σ on these windows (in-sample) and
what it was fitted on. With ``--speed-noise-gain`` g (default 1) every
candidate is first widened per vehicle to √(σ² + (g·σ_v·t_k)²), σ_v the
scatter of the vehicle's measured speeds (``MarkovPredictor.speed_noise``),
as the stage then blurs with the table (``speed_noise_gain`` in the file),
so that the table holds what the vehicles' own speed noise does not; its
"before" coverage is then that of the noise term alone.

::

    iamp calibrate --data $IAMP_TAF_BW --recording k729_2022-03-16 --model M.pt --out spread_k729.json
        [--mode hybrid baseline corridor_cv cv] [--stride 0.8] [--seed 0] [--level 0.9] [--max-frames N]
        [--speed-noise-gain 1] [--set K=V]...
"""

from __future__ import annotations

import dataclasses
import json
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np

from stages.lib.base import check_output, json_safe
from stages.markov_prediction.rasterise import highest_density_threshold
from stages.markov_prediction.core import SPEED_NOISE_CAP_MPS
from stages.markov_prediction.config import RAW_GRIDS
from stages.markov_prediction.spread import BLUR_MIN_VALUE, SpreadTable, blur_step, with_speed_noise, write_spread
from stages.offline.evaluation import EVAL_MODES, EvalConfig, Evaluation, _key_values

#: candidate σ (m) along the corridor
SIGMAS_M = (0.0, 0.5, 1.0, 2.0, 3.0, 4.5, 6.0, 8.0, 11.0)
#: upper start-speed edges of the bands but the last (standing, slow, fast); the slow/fast edge is iamp eval's
BANDS_MPS = (0.5, 2.0)
BAND_NAMES = ("standing", "slow", "fast")
#: σ_v·t per vehicle (its own speed noise, ``MarkovPredictor.speed_noise``) added to every candidate and written as the
#: table's ``speed_noise_gain``: physics (a speed known to ±σ_v puts the position ±σ_v·t off), not fitted. Chosen by
#: what the two locations' tracks show (README "Calibrated grids"): K729's fast cars' speeds scatter by 0.03 m/s
#: (median), K733's by 1.2 m/s, so a table fitted on one alone over- or under-covers the other
SPEED_NOISE_GAIN = 1.0


class SpreadCalibration(Evaluation):
    """``Evaluation`` that also scores every window's coverage under each candidate σ (per mode, band, step)."""

    def __init__(self, config: EvalConfig, sigmas_m: tuple[float, ...] = SIGMAS_M, level: float = 0.9,
                 speed_noise_gain: float = SPEED_NOISE_GAIN) -> None:
        if any(p == "spread_calibration" for p, _ in config.params):
            raise ValueError("iamp calibrate fits spread_calibration: do not --set it")
        if any(p.startswith("spread_online") for p, _ in config.params):
            raise ValueError("iamp calibrate fits the spread table alone: do not --set spread_online (it widens the grids at run time, on top)")
        if not (math.isfinite(speed_noise_gain) and speed_noise_gain >= 0):
            raise ValueError(f"--speed-noise-gain {speed_noise_gain}: must be a number >= 0")
        n_steps, tau = 10, 0.4  # the margin's bound; the predictors' own steps are read below
        widest = math.hypot(max(sigmas_m), speed_noise_gain * SPEED_NOISE_CAP_MPS * n_steps * tau)
        margin = dict(config.params).get("grid_margin_m", 3.0) + 3.0 * widest  # no candidate's blur leaves the grid
        # the candidates are applied to the raw grids: no table and no online spread under them (both are on by default)
        super().__init__(dataclasses.replace(config, params=(*config.params, ("grid_margin_m", margin), *RAW_GRIDS.items())))
        self.sigmas_m = tuple(float(s) for s in sigmas_m)
        self.level = level
        self.speed_noise_gain = float(speed_noise_gain)
        self._stamp = 0
        n_k = self.predictors[config.modes[0]].config.n_steps
        shape = (len(BAND_NAMES), n_k, len(self.sigmas_m))
        self.hits = {m: np.zeros(shape, np.int64) for m in config.modes}
        self.nll = {m: np.zeros(shape) for m in config.modes}
        self.count = {m: np.zeros((len(BAND_NAMES), n_k), np.int64) for m in config.modes}
        #: per mode, the spread_shape its candidates are applied with (its stage's; "along": each candidate's grid rebuilt)
        self.shapes = {m: self.predictors[m].config.spread_shape for m in config.modes}
        for mode, predictor in self.predictors.items():
            predictor.keep_geometry = self.shapes.get(mode) == "along"

    def _instant(self, recording, sequence_id, stamp, *args, **kwargs) -> None:
        self._stamp = int(stamp)  # for the vehicles' speed noise in _score
        return super()._instant(recording, sequence_id, stamp, *args, **kwargs)

    def _score(self, prediction, track_id, future, acc, vehicle):
        result = super()._score(prediction, track_id, future, acc, vehicle)
        grid = prediction.vehicle_grids.get(track_id)
        if result is None or grid is None:
            return result
        mode = prediction.mode
        band = int(np.searchsorted(np.asarray(BANDS_MPS), float(vehicle.speed_mps), side="left"))
        self.count[mode][band] += 1
        frame = prediction.grid_frame
        cells_true = frame.flat_index(future[:, 0], future[:, 1])
        noise = self.speed_noise_gain * self.predictors[mode].speed_noise(track_id, self._stamp) if self.speed_noise_gain > 0 else 0.0
        times = prediction.step_times_s
        if self.shapes[mode] == "along":  # each candidate's grid rebuilt along the corridors (the stage's _along), all steps at once
            for c, sigma in enumerate(self.sigmas_m):
                sigmas = with_speed_noise(np.full(times.size, sigma), noise, times) if noise > 0 else np.full(times.size, sigma)
                covered, value = truth_in_region(frame, prediction.regrid(track_id, sigmas), future, self.level)
                self.hits[mode][band, :, c] += covered
                self.nll[mode][band, :, c] -= np.log(np.maximum(value, self.config.nll_floor))
            return result
        for k in range(future.shape[0]):
            cells, values = grid.step(k, frame.n_cells)
            for c, sigma in enumerate(self.sigmas_m):
                # the candidate with the vehicle's own speed-noise term, as the stage blurs with the fitted table
                sigma = float(with_speed_noise(sigma, noise, times[k])) if noise > 0 else sigma
                covered, value = _truth_in_blurred(frame, cells, values, int(cells_true[k]), sigma, self.level)
                self.hits[mode][band, k, c] += covered
                self.nll[mode][band, k, c] -= math.log(max(value, self.config.nll_floor))
        return result

    def fit(self) -> tuple[dict[str, SpreadTable], dict[str, Any]]:
        """Per mode, the σ table and what was measured (windows, coverage at each candidate and at the chosen σ)."""
        tables, measured = {}, {}
        sig = np.asarray(self.sigmas_m)
        for mode in self.config.modes:
            n = self.count[mode]
            cov = self.hits[mode] / np.maximum(n[..., None], 1)
            chosen = np.zeros(n.shape)
            for b in range(n.shape[0]):
                for k in range(n.shape[1]):
                    chosen[b, k] = smallest_sigma(sig, cov[b, k], self.level) if n[b, k] else 0.0
                chosen[b] = np.maximum.accumulate(chosen[b])
            tables[mode] = SpreadTable(BANDS_MPS, chosen, self.speed_noise_gain, self.shapes[mode])
            at = np.array([[np.interp(chosen[b, k], sig, cov[b, k]) for k in range(n.shape[1])] for b in range(n.shape[0])])
            nll = self.nll[mode] / np.maximum(n[..., None], 1)
            measured[mode] = {
                "windows": {BAND_NAMES[b]: int(n[b, 0]) for b in range(n.shape[0])},
                "coverage_uncalibrated": {BAND_NAMES[b]: float(cov[b, :, 0].mean()) if n[b, 0] else None for b in range(n.shape[0])},
                "coverage_at_sigma": {BAND_NAMES[b]: float(at[b].mean()) if n[b, 0] else None for b in range(n.shape[0])},
                "nll_uncalibrated": {BAND_NAMES[b]: float(nll[b, :, 0].mean()) if n[b, 0] else None for b in range(n.shape[0])},
                "coverage_by_sigma": {BAND_NAMES[b]: np.round(cov[b], 4).tolist() for b in range(n.shape[0])},
            }
        return tables, measured


def truth_in_region(frame, grid, future: np.ndarray, level: float) -> tuple[np.ndarray, np.ndarray]:
    """Per step: whether the true position's cell lies in the ``level`` highest-density region of a vehicle's grid,
    and the grid's value there (``iamp eval``'s coverage90/NLL rule)."""
    n_k = future.shape[0]
    covered, value = np.zeros(n_k, np.int64), np.zeros(n_k)
    cells_true = frame.flat_index(future[:, 0], future[:, 1])
    for k in range(n_k):
        cells, values = grid.step(k, frame.n_cells)
        if cells_true[k] < 0 or not cells.size:
            continue
        i = int(np.searchsorted(cells, cells_true[k]))
        if i < cells.size and cells[i] == cells_true[k]:
            value[k] = float(values[i])
            covered[k] = value[k] > 0 and value[k] >= highest_density_threshold(values, level)
    return covered, value


def _truth_in_blurred(frame, cells: np.ndarray, values: np.ndarray, cell_true: int, sigma: float, level: float) -> tuple[bool, float]:
    """Whether the true cell lies in the ``level`` region of one step of a vehicle's grid blurred by σ (``blur_grid``),
    and its value there; on the blocks themselves (a block's cells share its value: the same region, cheaper)."""
    if cell_true < 0 or cells.size == 0:
        return False, 0.0
    if sigma <= 0:
        i = int(np.searchsorted(cells, cell_true))
        if i < cells.size and cells[i] == cell_true:
            v = float(values[i])
            return bool(v > 0 and v >= highest_density_threshold(values, level)), v
        return False, 0.0
    r0, c0, f, blocks = blur_step(frame, cells, values, sigma)
    row, col = divmod(cell_true, frame.n_cols)
    br, bc = (row - r0) // f, (col - c0) // f
    if not (0 <= br < blocks.shape[0] and 0 <= bc < blocks.shape[1]):
        return False, 0.0
    per_block = blocks / (f * f)  # a block's cells share its mass / f²; the stage keeps those above BLUR_MIN_VALUE
    if not per_block[br, bc] > BLUR_MIN_VALUE:
        return False, 0.0
    inside = _blocks_inside(frame, r0, c0, f, blocks.shape)  # cells of each block inside the frame
    flat = per_block.ravel()
    keep = (flat > BLUR_MIN_VALUE) & (inside.ravel() > 0)
    # the region over cells: cells sorted by value
    per_cell = flat[keep]
    counts = inside.ravel()[keep]
    order = np.argsort(-per_cell, kind="stable")
    cumulative = np.cumsum(per_cell[order] * counts[order])
    n = int(np.searchsorted(cumulative, level, side="left"))
    threshold = float(per_cell[order][min(n, order.size - 1)])
    value = float(per_block[br, bc])
    return bool(value >= threshold), value


def _blocks_inside(frame, r0: int, c0: int, f: int, shape: tuple[int, int]) -> np.ndarray:
    """(R, C): how many of each block's f × f cells lie inside the frame."""
    rows = r0 + np.arange(shape[0] * f)
    cols = c0 + np.arange(shape[1] * f)
    r_in = ((rows >= 0) & (rows < frame.n_rows)).reshape(shape[0], f).sum(axis=1)
    c_in = ((cols >= 0) & (cols < frame.n_cols)).reshape(shape[1], f).sum(axis=1)
    return r_in[:, None] * c_in[None, :]


def smallest_sigma(sigmas: np.ndarray, coverage: np.ndarray, level: float) -> float:
    """The smallest σ at which ``coverage`` (per candidate σ) reaches ``level``, linear between candidates."""
    if coverage[0] >= level:
        return 0.0
    above = np.flatnonzero(coverage >= level)
    if not above.size:
        return float(sigmas[-1])
    i = int(above[0])
    lo, hi = coverage[i - 1], coverage[i]
    f = (level - lo) / (hi - lo) if hi > lo else 1.0
    return float(sigmas[i - 1] + f * (sigmas[i] - sigmas[i - 1]))


def format_fit(tables: dict[str, SpreadTable], measured: dict[str, Any]) -> str:
    lines = []
    for mode, table in tables.items():
        m = measured[mode]
        lines.append(f"{mode}: σ (m) per step, and coverage on these windows (in-sample) before -> at σ")
        for b, name in enumerate(BAND_NAMES):
            before, after = m["coverage_uncalibrated"][name], m["coverage_at_sigma"][name]
            lines.append(f"  {name:<9} {m['windows'][name]:>6} windows  σ " + " ".join(f"{s:4.1f}" for s in table.sigma_m[b])
                         + (f"  cov {before:.2f} -> {after:.2f}" if before is not None else "  (no windows: σ 0)"))
    return "\n".join(lines)


def add_arguments(parser) -> None:
    from stages.lib.datasets import DEFAULT_DATA_DIR

    parser.add_argument("--data", type=Path, default=DEFAULT_DATA_DIR, help="data folder laid out like stages/data/taf-bw (default: the embedded scenario)")
    parser.add_argument("--recording", action="extend", nargs="+", default=[], help="recording to fit on (one or more, the flag repeatable; default all): one location")
    parser.add_argument("--sequence", action="extend", nargs="+", default=[], help="sequence id (one or more, the flag repeatable; default all)")
    parser.add_argument("--mode", nargs="+", default=list(EVAL_MODES), choices=EVAL_MODES, help="modes to calibrate (default all)")
    parser.add_argument("--stride", type=float, default=0.8, help="seconds between windows (default 0.8)")
    parser.add_argument("--model", type=Path, default=None, help="AR model weights for mode hybrid (default: the shipped one)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the intentions particle filter (default 0)")
    parser.add_argument("--level", type=float, default=0.9, help="coverage the region of that level should reach (default 0.9)")
    parser.add_argument("--max-frames", type=int, default=0, help="stop each sequence after this many frames (0: all)")
    parser.add_argument("--speed-noise-gain", type=float, default=SPEED_NOISE_GAIN,
                        help=f"each vehicle's σ also grows by this × its speed noise × t (default {SPEED_NOISE_GAIN:g}; 0: the table alone)")
    parser.add_argument("--out", type=Path, required=True, help="calibration file to write (the stage's spread_calibration)")
    parser.add_argument("--json", type=Path, default=None, help="also write what was measured as JSON")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="markov_prediction parameter (JSON value)")
    parser.add_argument("--set-ar", action="append", default=[], metavar="KEY=VALUE", help="ar_inference parameter (JSON value)")
    parser.add_argument("--set-intentions", action="append", default=[], metavar="KEY=VALUE", help="intentions parameter (JSON value)")


def _model_sha256(model: Path | None) -> str:
    """The sha256 of the AR weights the table was fitted with (hybrid's spread belongs to them): ``iamp eval`` warns
    when a table is used with other weights. '' when the file cannot be read."""
    import hashlib

    from stages.lib.ar.model import DEFAULT_MODEL_PATH

    try:
        return hashlib.sha256(Path(model or DEFAULT_MODEL_PATH).read_bytes()).hexdigest()
    except OSError:
        return ""


def run_cli(args) -> int:
    try:
        check_output(args.out, "--out")  # the outputs' places first: a bad one must not cost the run
        check_output(args.json, "--json")
        if not 0 < args.level < 1:
            raise ValueError(f"--level {args.level}: must lie in (0, 1)")
        config = EvalConfig(
            params=_key_values(args.set, "--set"), intentions_params=_key_values(args.set_intentions, "--set-intentions"),
            ar_params=_key_values(args.set_ar, "--set-ar"), model_path=args.model, seed=args.seed, data_dir=args.data,
            recordings=tuple(args.recording), sequences=tuple(args.sequence), modes=tuple(dict.fromkeys(args.mode)),
            stride_s=args.stride, max_frames_per_sequence=max(args.max_frames, 0), progress=not args.no_progress,
            coverage_level=args.level,
        )
        cal = SpreadCalibration(config, level=args.level, speed_noise_gain=args.speed_noise_gain)
        cal.run()
    except ValueError as exc:
        sys.stderr.write(f"iamp calibrate: error: {exc}\n")
        return 2
    tables, measured = cal.fit()
    if not any(sum(measured[m]["windows"].values()) for m in tables):  # a table of σ 0 from nothing would make every grid a point
        left_out = ", ".join(f"{k} {v}" for k, v in sorted(cal.skipped.items())) or "nothing counted"
        sys.stderr.write(f"iamp calibrate: error: no window to fit the spread on ({left_out}); {args.out} not written\n")
        return 2
    stage = next(iter(cal.predictors.values())).config
    fitted_on = {"data": str(args.data), "recordings": cal.recordings, "stride_s": args.stride, "seed": args.seed,
                 "model": str(args.model) if args.model else "shipped", "model_sha256": _model_sha256(args.model),
                 "level": args.level, "sigmas_m": list(cal.sigmas_m),
                 "speed_noise_gain": cal.speed_noise_gain,
                 # the grid the σ were fitted on (a table carries over between cell sizes; docs/evaluation.md, "Calibrated grids")
                 "grid_cell_m": stage.grid_cell_m, "spread_fold_start": stage.spread_fold_start,
                 "params": {k: v for k, v in config.params}, "windows": {m: measured[m]["windows"] for m in tables}}
    write_spread(args.out, tables, fitted_on)
    print(format_fit(tables, measured))
    print(f"wrote {args.out}")
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(json_safe({"fitted_on": fitted_on, "tables": {m: t.as_dict() for m, t in tables.items()},
                                                   "measured": measured}), indent=2, allow_nan=False))
    return 0


__all__ = ["BANDS_MPS", "SIGMAS_M", "SpreadCalibration", "add_arguments", "run_cli", "smallest_sigma", "truth_in_region"]
