"""Which accelerations do the true 4 s futures hold? The range the chain's input cells must cover.

What it measures. For every vehicle of a TAF-BW recording at instants
``--stride`` apart (the eval's instants: multiples of the stride from each
sequence's first stamp) with its whole 4 s future of positions (the eval's
``no_full_future`` rule; unlike the eval it does not ask for a corridor
match, so it sees a few more windows), it classifies the true future
(``stages.offline.truth.manoeuvre_class``: stands, turns, brakes,
accelerates, keeps_speed) and reads the true longitudinal acceleration at
0.1 s steps over that future (``ground_truth``: Savitzky-Golay from
positions, the AR training targets; unknown in the first and last 1.5 s of a
track). Per class it prints the windows, how many have known accelerations,
percentiles of each window's largest and smallest acceleration, and the
share of windows whose 0.1 s accelerations (``step``) or 0.4 s chunk means
(``chunk``, what one Markov step uses) go above 2 / 2.5 / 3 m/s² or below
-3 / -3.5 / -4 m/s²; and over all known steps the share of the samples
outside [-3, 2] (the input cells' range when this was written). It asserts
nothing.

Run::

    IAMP_TAF_BW=/path/to/taf-bw python bench/accel_range.py [--recording k733_2018-05-02 ...] [--stride 0.4] [--json OUT]
"""

from __future__ import annotations

import argparse
import collections
import json
import sys
from pathlib import Path

import numpy as np

from stages.lib.datasets import DatasetError, discover, full_data_dir, find_recording, load_ref
from stages.offline.truth import MANOEUVRES, future_positions, ground_truth, manoeuvre_class
from stages.lib.base import check_output_arg

HORIZON_S = 4.0
STEP_S = 0.1
CHUNK_STEPS = 4
ABOVE_MPS2 = (2.0, 2.5, 3.0)
BELOW_MPS2 = (-3.0, -3.5, -4.0)
RANGE_MPS2 = (-3.0, 2.0)


def windows(seq, stride_s: float):
    """(class, accelerations (40,) with NaN where unknown) of every vehicle window of one sequence with a full 4 s future."""
    truth = ground_truth(seq)
    stride_ns, step_ns = int(round(stride_s * 1e9)), int(round(STEP_S * 1e9))
    tau_ns, k_tau, n = int(round(0.4e9)), int(round(HORIZON_S / 0.4)), int(round(HORIZON_S / STEP_S))
    first = int(seq.stamp_ns[0]) if seq.n_rows else 0
    ms = 1_000_000
    for track_id, track in truth.items():
        for j, stamp in enumerate(track.stamps_ns.tolist()):
            off = (stamp - first) % stride_ns
            if off > ms and stride_ns - off > ms:
                continue
            future = future_positions(track, stamp, tau_ns, k_tau)
            if future is None:
                continue
            cls = manoeuvre_class(track.xy[j], future, tau_ns * 1e-9)
            want = stamp + step_ns * np.arange(1, n + 1)
            i = np.minimum(np.searchsorted(track.stamps_ns, want - ms), track.stamps_ns.shape[0] - 1)
            acc = np.where(np.abs(track.stamps_ns[i] - want) <= ms, track.accel_mps2[i], np.nan)
            yield cls, acc


def summarise(rows: list[np.ndarray]) -> dict:
    """Figures of one class: windows, known, percentiles of per-window max/min, shares beyond the thresholds."""
    out: dict = {"windows": len(rows)}
    known = [a for a in rows if np.isfinite(a).sum() >= CHUNK_STEPS]
    out["known"] = len(known)
    if not known:
        return out
    amax = np.array([np.nanmax(a) for a in known])
    amin = np.array([np.nanmin(a) for a in known])
    chunks = []
    for a in known:
        c = a[: len(a) // CHUNK_STEPS * CHUNK_STEPS].reshape(-1, CHUNK_STEPS)
        with np.errstate(all="ignore"):
            chunks.append(np.where(np.isfinite(c).all(axis=1), c.mean(axis=1), np.nan))
    cmax = np.array([np.nanmax(c) if np.isfinite(c).any() else np.nan for c in chunks])
    cmin = np.array([np.nanmin(c) if np.isfinite(c).any() else np.nan for c in chunks])
    out["max_percentiles"] = dict(zip(("p50", "p90", "p99"), np.percentile(amax, [50, 90, 99]).round(2).tolist()))
    out["min_percentiles"] = dict(zip(("p50", "p10", "p1"), np.percentile(amin, [50, 10, 1]).round(2).tolist()))
    for t in ABOVE_MPS2:
        out[f"step_above_{t:g}"] = float(np.mean(amax > t))
        out[f"chunk_above_{t:g}"] = float(np.nanmean(cmax > t))
    for t in BELOW_MPS2:
        out[f"step_below_{t:g}"] = float(np.mean(amin < t))
        out[f"chunk_below_{t:g}"] = float(np.nanmean(cmin < t))
    samples = np.concatenate([a[np.isfinite(a)] for a in known])
    out["samples"] = int(samples.size)
    out["samples_above_range"] = float(np.mean(samples > RANGE_MPS2[1]))
    out["samples_below_range"] = float(np.mean(samples < RANGE_MPS2[0]))
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", type=Path, default=None, help="TAF-BW data folder (default $IAMP_TAF_BW)")
    p.add_argument("--recording", action="append", default=[], help="recording name (default: all in the folder)")
    p.add_argument("--stride", type=float, default=0.4, help="seconds between instants (default 0.4, the eval's)")
    p.add_argument("--json", type=Path, default=None, help="write the figures here")
    args = p.parse_args(argv)
    check_output_arg(p, args.json, "--json")  # before the work: a bad path must not cost the run
    data = args.data or full_data_dir()
    if data is None:
        print("accel_range: no data folder (--data or IAMP_TAF_BW)", file=sys.stderr)
        return 2
    try:  # before the work: a data folder or recording that is not there is a bad command line
        refs = {r.name: r for r in discover(data)}
        for name in args.recording:
            find_recording(data, name)
    except DatasetError as exc:
        print(f"accel_range: error: {exc}", file=sys.stderr)
        return 2
    result = {}
    for name in args.recording or sorted(refs):
        rec = load_ref(refs[name])
        per: dict[str, list[np.ndarray]] = collections.defaultdict(list)
        for seq in rec.sequences:
            for cls, acc in windows(seq, args.stride):
                per[cls].append(acc)
        per["moving"] = [a for c in MANOEUVRES if c != "stands" for a in per.get(c, [])]
        result[name] = {c: summarise(per.get(c, [])) for c in (*MANOEUVRES, "moving")}
        print(f"\n{name} (stride {args.stride:g} s; step: 0.1 s values, chunk: 0.4 s means; share of windows with known accelerations)")
        head = ["class", "windows", "known", "max p50/p90/p99", "min p50/p10/p1"]
        head += [f"{k} >{t:g}" for t in ABOVE_MPS2 for k in ("step",)] + ["chunk >2", "chunk >2.5"]
        head += [f"step <{t:g}" for t in BELOW_MPS2] + ["chunk <-3", "samples outside [-3,2] (above/below)"]
        print(" | ".join(head))
        for c, s in result[name].items():
            if not s.get("known"):
                print(f"{c} | {s['windows']} | 0")
                continue
            cells = [c, str(s["windows"]), str(s["known"]), "/".join(f"{v:.2f}" for v in s["max_percentiles"].values()),
                     "/".join(f"{v:.2f}" for v in s["min_percentiles"].values())]
            cells += [f"{s[f'step_above_{t:g}']:.2f}" for t in ABOVE_MPS2] + [f"{s['chunk_above_2']:.2f}", f"{s['chunk_above_2.5']:.2f}"]
            cells += [f"{s[f'step_below_{t:g}']:.2f}" for t in BELOW_MPS2] + [f"{s['chunk_below_-3']:.2f}"]
            cells += [f"{s['samples_above_range']:.3f} / {s['samples_below_range']:.3f}"]
            print(" | ".join(cells))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
