#!/usr/bin/env python3
"""What hybrid would score with perfect inputs: the true future acceleration as the AR model's output, the true start
speed, or both. An upper bound of what a better learned model, or a better state estimate, could give on a recording.

It runs ``iamp eval`` in-process (the same options: ``--data``, ``--recording``, ``--model``, ``--mode``, ``--set``,
``--set-ar``, ... and the same windows) once per ``--oracle`` variant:

- ``none``: as ``iamp eval`` (the learned profiles, the causal state of the corridors stage);
- ``profiles``: at every scored instant each pair's acceleration profile is replaced by the car's TRUE future
  acceleration at the model's 40 steps (``stages.offline.truth``'s smoothed longitudinal acceleration, the AR training
  target; where it is unknown near a track's end, its last known value is held, 0 without one), turned into the chain's
  input distributions exactly as the AR stage turns the model's (``chunk_distributions``, the model's residual spread
  ``sigma_res`` times ``--set-ar sigma_scale``, default 1, floored): only the mean of every distribution is perfect;
- ``speed``: every vehicle's speed in the instant's CorridorSet (the start speed of the corridor modes' predictions:
  hybrid, baseline, corridor_cv; Cartesian ``cv`` reads the velocity vector, which is not replaced, so its mADE stays,
  only its slow/fast split follows the replaced speed) is replaced by its TRUE speed at the instant: the centred Savitzky–Golay derivative of its positions (the window of the
  acceleration target, 1.5 s; it reads 0.75 s of the future, so it is not a causal estimate, it is the reference);
  vehicles without one (near a track's end) keep the estimate;
- ``both``: the two together.

Printed per variant: ``iamp eval``'s table, then one summary table: mADE (all / slow / fast), hybrid / corridor_cv of
the same run where both modes ran, and the along-track bias at 4 s per manoeuvre class; with ``--json FILE`` the
reports per variant (``variants.<name>``: ``iamp eval``'s report) and the summary (``summary.<name>.<mode>``). The
oracles replace only what the scored instants see (the frames between them go to the cores as recorded), and say how
many profiles and speeds they replaced. Nothing is asserted; every oracle uses the future, so no figure of it is a
prediction: they bound where the error is (docs/evaluation.md "How far perfect inputs go").

    IAMP_TAF_BW=... python bench/oracle_profiles.py --data $IAMP_TAF_BW --recording k733_2018-05-02 \\
        --model artefacts/generalisation/ar_k729_....pt --mode hybrid corridor_cv --oracle none profiles speed both
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np
from scipy.signal import savgol_filter

from bus_schemas import AccelerationProfile, AccelerationProfiles, CorridorSet
from stages.lib.ar.inference import chunk_distributions
from stages.lib.base import check_output_arg, json_safe
from stages.offline.evaluation import Evaluation, add_arguments, eval_config, format_table
from stages.offline.truth import ACCEL_WINDOW_S, Track

VARIANTS = ("none", "profiles", "speed", "both")
_MS_NS = 1_000_000


def true_accelerations(track: Track | None, stamp_ns: int, step_ns: int, n_steps: int) -> np.ndarray | None:
    """(n_steps,) the track's true acceleration at t + k·step, k = 1..n_steps (±1 ms); where a step has none (after the
    track's end, or NaN near it), the last known value held, 0 before any; None without a track."""
    if track is None:
        return None
    want = stamp_ns + int(step_ns) * np.arange(1, n_steps + 1)
    i = np.minimum(np.searchsorted(track.stamps_ns, want - _MS_NS), track.stamps_ns.shape[0] - 1)
    found = np.abs(track.stamps_ns[i] - want) <= _MS_NS
    accel = np.where(found, track.accel_mps2[i], np.nan)
    out = np.zeros(n_steps)
    last = 0.0
    for k, a in enumerate(accel.tolist()):
        if np.isfinite(a):
            last = a
        out[k] = last
    return out


def oracle_profiles(profiles: AccelerationProfiles, truth: dict[int, Track], stamp_ns: int, sigma_res: np.ndarray, *,
                    sigma_scale: float, sigma_floor: float) -> tuple[AccelerationProfiles, int]:
    """``profiles`` with every profile's acceleration replaced by the car's true future acceleration (and its
    distributions made from it as the AR stage makes them); returns the message and how many were replaced (a profile of
    a vehicle without a track stays as it was)."""
    step_ns = int(round(profiles.step_s * 1e9))
    chunk_steps = int(round(profiles.chunk_s / profiles.step_s))
    edges = np.asarray(profiles.input_edges_mps2, dtype=np.float64)
    out: list[AccelerationProfile] = []
    replaced = 0
    for p in profiles.profiles:
        accel = true_accelerations(truth.get(int(p.track_id)), stamp_ns, step_ns, int(p.accel_mps2.shape[0]))
        if accel is None:
            out.append(p)
            continue
        mu, sigma, probs = chunk_distributions(accel[None, :], chunk_steps, sigma_res, edges, sigma_scale=sigma_scale, sigma_floor=sigma_floor)
        out.append(dataclasses.replace(p, accel_mps2=accel.astype(np.float32), chunk_mean_mps2=mu[0].astype(np.float32),
                                       chunk_sigma_mps2=sigma[0].astype(np.float32), input_probs=probs[0].astype(np.float32)))
        replaced += 1
    return dataclasses.replace(profiles, profiles=tuple(out)), replaced


def true_speed(track: Track, stamp_ns: int, period_ns: int) -> float | None:
    """The speed (m/s) of the track at ``stamp_ns`` from its positions: the centred Savitzky–Golay derivative (degree 2,
    the acceleration target's window) of the gap-free piece around it; None where the window does not fit inside it."""
    w = max(int(round(ACCEL_WINDOW_S * 1e9 / period_ns)), 3) | 1
    i = int(np.searchsorted(track.stamps_ns, stamp_ns - _MS_NS))
    if i >= track.stamps_ns.shape[0] or abs(int(track.stamps_ns[i]) - stamp_ns) > _MS_NS:
        return None
    half = w // 2
    a, b = i - half, i + half + 1
    if a < 0 or b > track.stamps_ns.shape[0] or np.any(np.abs(np.diff(track.stamps_ns[a:b]) - period_ns) > _MS_NS):
        return None
    dt = period_ns * 1e-9
    vx = savgol_filter(track.xy[a:b, 0], w, 2, deriv=1, delta=dt)[half]
    vy = savgol_filter(track.xy[a:b, 1], w, 2, deriv=1, delta=dt)[half]
    speed = float(np.hypot(vx, vy))
    return speed if np.isfinite(speed) else None


def with_true_speeds(corridor_set: CorridorSet, truth: dict[int, Track], stamp_ns: int, period_ns: int) -> tuple[CorridorSet, int]:
    """``corridor_set`` with every vehicle's ``speed_mps`` replaced by ``true_speed``; returns it and how many were."""
    vehicles = []
    replaced = 0
    for v in corridor_set.vehicles:
        track = truth.get(int(v.track_id))
        speed = true_speed(track, stamp_ns, period_ns) if track is not None else None
        if speed is None:
            vehicles.append(v)
        else:
            vehicles.append(dataclasses.replace(v, speed_mps=speed))
            replaced += 1
    return dataclasses.replace(corridor_set, vehicles=tuple(vehicles)), replaced


class OracleEvaluation(Evaluation):
    """``Evaluation`` whose scored instants get the true profiles and/or the true start speeds (module docstring)."""

    def __init__(self, config, variant: str) -> None:
        if variant not in VARIANTS:
            raise ValueError(f"oracle variant {variant!r}: expected one of {', '.join(VARIANTS)}")
        super().__init__(config)
        self.variant = variant
        self.counts = {"profiles_replaced": 0, "profiles_kept": 0, "speeds_replaced": 0, "speeds_kept": 0}
        self._period_ns = 100_000_000

    def _sequence(self, rec, seq, map_sha256, bar) -> None:
        self._period_ns = int(seq.period_ns)
        return super()._sequence(rec, seq, map_sha256, bar)

    def _instant(self, recording, sequence_id, stamp, frame, corridor_set, relation_set, scene, truth, tau_ns, n_steps,
                 belief=None, profiles=None, **kwargs):
        if self.variant in ("speed", "both"):
            corridor_set, n = with_true_speeds(corridor_set, truth, int(stamp), self._period_ns)
            self.counts["speeds_replaced"] += n
            self.counts["speeds_kept"] += len(corridor_set.vehicles) - n
        if self.variant in ("profiles", "both") and profiles is not None:
            ar = self.ar_config
            profiles, n = oracle_profiles(profiles, truth, int(stamp), np.asarray(self._ar_model.sigma_res_chunks, dtype=np.float64),
                                          sigma_scale=ar.sigma_scale, sigma_floor=ar.sigma_floor_mps2)
            self.counts["profiles_replaced"] += n
            self.counts["profiles_kept"] += len(profiles.profiles) - n
        return super()._instant(recording, sequence_id, stamp, frame, corridor_set, relation_set, scene, truth, tau_ns, n_steps,
                                belief, profiles, **kwargs)


def summary(report: dict[str, Any]) -> dict[str, Any]:
    """Per mode: mADE all / slow / fast and the along-track bias at 4 s per manoeuvre class (``iamp eval``'s report)."""
    out = {}
    for mode, m in report["modes"].items():
        speed = m.get("by_speed", {})
        along = m.get("along_track_m", {}).get("by_manoeuvre", {})
        out[mode] = {
            "mADE_m": m["overall"]["mADE_m"],
            "slow_mADE_m": speed.get("slow", {}).get("mADE_m"),
            "fast_mADE_m": speed.get("fast", {}).get("mADE_m"),
            "along_4s_m": {k: v.get("4s", {}).get("mean") for k, v in along.items()},
        }
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    add_arguments(p)
    p.add_argument("--oracle", nargs="+", choices=VARIANTS, default=list(VARIANTS), help="variants to run, in order (default: all four)")
    args = p.parse_args(argv)
    check_output_arg(p, args.json, "--json")
    try:
        config = eval_config(args)
    except ValueError as exc:
        p.error(str(exc))
    if "hybrid" not in config.modes and any(v in ("profiles", "both") for v in args.oracle):
        p.error("--oracle profiles/both replace the AR profiles, which only mode hybrid reads: add hybrid to --mode")
    reports: dict[str, Any] = {}
    summaries: dict[str, Any] = {}
    for variant in args.oracle:
        evaluation = OracleEvaluation(config, variant)
        try:
            report = evaluation.run()
        except ValueError as exc:
            sys.stderr.write(f"oracle_profiles: error: {exc}\n")
            return 2
        report["oracle"] = {"variant": variant, **evaluation.counts}
        print(f"=== oracle {variant}: {', '.join(f'{k} {v}' for k, v in evaluation.counts.items())}")
        print(format_table(report))
        reports[variant] = report
        summaries[variant] = summary(report)
    classes = ("stands", "turns", "brakes", "accelerates", "keeps_speed")
    print("\nsummary: mADE all / slow / fast (m), hybrid / corridor_cv of the same run, along-track bias at 4 s (m, + ahead): "
          + " / ".join(classes))
    for variant, modes in summaries.items():
        ratio = ""
        if "hybrid" in modes and "corridor_cv" in modes:
            ratio = f"{modes['hybrid']['mADE_m'] / modes['corridor_cv']['mADE_m']:.3f}"
        for mode, s in modes.items():
            along = " / ".join("  -  " if s["along_4s_m"].get(c) is None else f"{s['along_4s_m'][c]:+.2f}" for c in classes)
            print(f"  {variant:9s} {mode:12s} {s['mADE_m']:.3f} / {s['slow_mADE_m']:.3f} / {s['fast_mADE_m']:.3f}"
                  f"   {ratio if mode == 'hybrid' else '':5s}   {along}")
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(json_safe({"variants": reports, "summary": summaries}), indent=2, allow_nan=False))
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
