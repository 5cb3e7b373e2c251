"""Which causal speed estimate predicts a car's next seconds best? Figures for stages.lib.kinematic_state.

For every car sample with at least 1 s of history, each candidate's speed
times T is compared with the straight-line distance the car really covers in
the next T = 1, 2, 3, 4 s (the constant-speed displacement error, mean |e|
in m; ``bias4`` is the signed mean at 4 s). Candidates: the reported speed,
causal least-squares fits over the last W s of positions (degree 1 and 2),
and ``KinematicEstimator`` on positions alone and as every stage uses it
(positions fused with the calibrated, gated reported velocity: its bank of
filters, the published one chosen by a causal back test), and each filter of
the bank alone (``accel noise q alone``). Also
printed: the share of standing samples (true displacement over the next 2 s
below 0.3 m) whose estimated speed is above 0.5 m/s.

    python bench/state_estimator.py --data DIR [--recording NAME ...] [--json OUT]

Printed figures only; nothing is asserted.
"""

from __future__ import annotations

import argparse
import json
import math
import sys

import numpy as np

from bus_schemas import AgentType
from stages.lib.datasets import DatasetError, discover, find_recording, load_recording
from stages.lib.kinematic_state import EstimatorConfig, KinematicEstimator
from stages.lib.base import check_output_arg

HORIZONS_S = (1.0, 2.0, 3.0, 4.0)


def causal_fit(t: np.ndarray, x: np.ndarray, y: np.ndarray, window_s: float, degree: int) -> np.ndarray:
    """Speed at each sample from a least-squares polynomial over the samples of the last ``window_s``."""
    n = t.shape[0]
    out = np.full(n, np.nan)
    for i in range(n):
        j = int(np.searchsorted(t, t[i] - window_s - 1e-9))
        m = i - j + 1
        if m < 2:
            continue
        d = min(degree, m - 1)
        pinv = np.linalg.pinv((t[j : i + 1] - t[i])[:, None] ** np.arange(d + 1))
        out[i] = math.hypot(float(pinv[1] @ x[j : i + 1]), float(pinv[1] @ y[j : i + 1]))
    return out


def estimator_speed(ids, stamps, x, y, vx, vy, config: EstimatorConfig) -> np.ndarray:
    """Speeds from one KinematicEstimator fed every row in frame order (as the corridors stage does)."""
    est = KinematicEstimator(config)
    out = np.full(ids.shape[0], np.nan)
    issues: list = []
    for i in np.lexsort((ids, stamps)).tolist():
        out[i] = est.update(int(ids[i]), int(stamps[i]), float(x[i]), float(y[i]), float(vx[i]), float(vy[i]), issues).speed_mps
    return out


def score(recording) -> dict[str, dict[str, float]]:
    errors: dict[str, list[np.ndarray]] = {}
    standing: dict[str, list[np.ndarray]] = {}
    for seq in recording.sequences:
        cars = seq.agent_type == int(AgentType.CAR)
        columns = (seq.track_id, seq.stamp_ns, seq.x_m, seq.y_m, seq.vx_mps, seq.vy_mps)
        positions_only = estimator_speed(*columns, EstimatorConfig(fuse_reported=False))
        fused = estimator_speed(*columns, EstimatorConfig())
        singles = {q: estimator_speed(*columns, EstimatorConfig(accel_noise_m2ps3=q, accel_noise_bank=(q,)))
                   for q in EstimatorConfig().filter_bank}
        for tid in np.unique(seq.track_id[cars]).tolist():
            m = (seq.track_id == tid) & cars
            t = seq.stamp_ns[m] * 1e-9
            x, y = seq.x_m[m], seq.y_m[m]
            if t.shape[0] < 20:
                continue
            cands = {
                "reported": np.hypot(seq.vx_mps[m], seq.vy_mps[m]),
                "linear 0.6 s": causal_fit(t, x, y, 0.6, 1),
                "linear 1.0 s": causal_fit(t, x, y, 1.0, 1),
                "quadratic 1.0 s": causal_fit(t, x, y, 1.0, 2),
                "estimator, positions": positions_only[m],
                "estimator (default)": fused[m],
                **{f"accel noise {q:g} alone": speed[m] for q, speed in singles.items()},
            }
            history = t - t[0] >= 1.0
            j2 = np.minimum(np.searchsorted(t, t + 2.0 - 1e-6), t.shape[0] - 1)
            still = history & (np.searchsorted(t, t + 2.0 - 1e-6) < t.shape[0]) & (np.hypot(x[j2] - x, y[j2] - y) < 0.3)
            for name, speed in cands.items():
                rows = []
                for horizon in HORIZONS_S:
                    j = np.searchsorted(t, t + horizon - 1e-6)
                    ok = history & (j < t.shape[0])
                    jj = np.minimum(j, t.shape[0] - 1)
                    rows.append(np.where(ok, speed * horizon - np.hypot(x[jj] - x, y[jj] - y), np.nan))
                errors.setdefault(name, []).append(np.array(rows))
                standing.setdefault(name, []).append(speed[still] > 0.5)
    out = {}
    for name, parts in errors.items():
        e = np.concatenate(parts, axis=1)
        s = np.concatenate(standing[name])
        out[name] = {f"abs_err_{int(h)}s_m": float(np.nanmean(np.abs(e[k]))) for k, h in enumerate(HORIZONS_S)}
        out[name]["bias_4s_m"] = float(np.nanmean(e[-1]))
        out[name]["standing_above_0p5_share"] = float(np.mean(s)) if s.size else math.nan
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True, help="data folder laid out like stages/data/taf-bw")
    ap.add_argument("--recording", nargs="*", help="recordings (default: all)")
    ap.add_argument("--json", help="write the figures here")
    args = ap.parse_args(argv)
    check_output_arg(ap, args.json, "--json")  # before the work: a bad path must not cost the run
    try:  # before the work: a data folder or recording that is not there is a bad command line
        names = args.recording or [r.name for r in discover(args.data)]
        for name in args.recording or ():
            find_recording(args.data, name)
    except DatasetError as exc:
        print(f"state_estimator: error: {exc}", file=sys.stderr)
        return 2
    result = {}
    for name in names:
        figures = score(load_recording(args.data, name))
        result[name] = figures
        print(f"{name}: constant-speed displacement error, mean |e| (m) at 1/2/3/4 s, bias at 4 s, standing cars > 0.5 m/s")
        for cand, f in figures.items():
            errs = " ".join(f"{f[f'abs_err_{int(h)}s_m']:5.2f}" for h in HORIZONS_S)
            print(f"  {cand:20s} {errs}   bias {f['bias_4s_m']:+.2f}   standing>0.5 {f['standing_above_0p5_share']:.3f}")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(result, fh, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
