"""Per-window errors of every mode, with the window's scene, and which windows carry the gap between two modes.

What it measures. It runs ``iamp eval`` in-process (the same options: ``--data``, ``--recording``, ``--model``,
``--mode``, ``--set``, ... and the same windows) and keeps, per scored window and mode, ADE, FDE, the signed
along-track error at 4 s and the steps whose true position is inside the 90 % region, with the window's start:
speed (split slow/fast at 2 m/s as ``iamp eval``), the class of the true future (``manoeuvre_class``), and, on the
corridor the future followed (``followed_corridor``), its relations (a leader within ``--leader-gap`` m, its speed,
an influencing conflict and the rule that chose it) and whether that corridor turns (heading change over the
distance ``max(20, 4 s x speed)`` m ahead above 30 degrees). It writes one JSON line per window (``--windows``) and
prints, for the windows of ``--split`` (default fast), per group: windows, mADE of ``--compare A B`` (default
hybrid baseline), the difference and its share of the split's total difference (sum over the group's windows of
ADE_A - ADE_B over the split's summed difference), the along-track mean at 4 s of both. Then the ratio mADE A /
mADE B on all, slow, fast and moving windows with its 95 % interval by resampling cars (``ratio_interval``:
a car's windows are drawn together; ``--boot N`` draws, 0 for none): how far a ratio measured on one
recording's cars can be trusted.

Run::

    IAMP_TAF_BW=... python bench/window_errors.py --data $IAMP_TAF_BW --recording k729_2022-03-16 \\
        --model artefacts/generalisation/ar_k733_....pt --mode hybrid baseline --no-progress --windows w.jsonl
    python bench/window_errors.py --from-windows w.jsonl [--split fast|slow|all] [--compare hybrid baseline]

It also prints ``iamp eval``'s table and, with ``--json``, writes its report. It asserts nothing (development
figures). ``--from-windows`` prints the tables of a dump without running.
"""

from __future__ import annotations

import argparse
import collections
import json
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np

from stages.lib.base import check_output_arg, json_safe
from stages.offline.evaluation import SLOW_SPEED_MPS, Evaluation, add_arguments, eval_config, format_table
from stages.offline.truth import TURN_MIN_HEADING_DEG, along_track_directions, followed_corridor, manoeuvre_class

LEADER_GAP_M = 50.0
LOOKAHEAD_MIN_M = 20.0
HORIZON_S = 4.0


def corridor_turns(corridor, speed_mps: float) -> bool:
    """Whether the corridor's heading changes by more than ``TURN_MIN_HEADING_DEG`` over the distance
    ``max(LOOKAHEAD_MIN_M, HORIZON_S x speed)`` ahead of the vehicle (the largest change from its start)."""
    s = np.asarray(corridor.s_m, np.float64)
    h = np.unwrap(np.asarray(corridor.heading_rad, np.float64))
    if s.size < 2 or not math.isfinite(corridor.vehicle_s_m):
        return False
    s0 = float(corridor.vehicle_s_m)
    ahead = (s >= s0) & (s <= s0 + max(LOOKAHEAD_MIN_M, HORIZON_S * max(speed_mps, 0.0)))
    if not np.any(ahead):
        return False
    h0 = float(np.interp(s0, s, h))
    return bool(np.max(np.abs(h[ahead] - h0)) > math.radians(TURN_MIN_HEADING_DEG))


class WindowEvaluation(Evaluation):
    """``Evaluation`` that also keeps one row per scored (window, mode)."""

    def __init__(self, config, leader_gap_m: float = LEADER_GAP_M) -> None:
        super().__init__(config)
        self.leader_gap_m = leader_gap_m
        self.rows: dict[tuple, dict[str, Any]] = {}
        self._context: dict[str, Any] = {}

    def _instant(self, recording, sequence_id, stamp, frame, corridor_set, relation_set, scene, truth, tau_ns, n_steps, *args, **kwargs):
        relations = {(r.track_id, r.corridor_id): r for r in relation_set.relations} if relation_set is not None else {}
        rows = {int(t): i for i, t in enumerate(frame.track_ids.tolist())}
        self._context = {"recording": recording, "sequence": sequence_id, "stamp": int(stamp), "relations": relations,
                         "rows": rows, "frame": frame, "tau_s": tau_ns * 1e-9}
        return super()._instant(recording, sequence_id, stamp, frame, corridor_set, relation_set, scene, truth, tau_ns, n_steps, *args, **kwargs)

    def _score(self, prediction, track_id, future, acc, vehicle):
        result = super()._score(prediction, track_id, future, acc, vehicle)
        if result is None:
            return None
        ctx = self._context
        mode = next(m for m, a in self.acc.items() if a is acc)
        key = (ctx["recording"], ctx["sequence"], ctx["stamp"], int(track_id))
        row = self.rows.get(key)
        if row is None:
            row = self.rows[key] = self._window(ctx, track_id, future, vehicle)
        along = math.nan
        if result.error_xy is not None:
            d = row["_dir"]  # the true direction of travel at 4 s (NaN where the car stands)
            if np.all(np.isfinite(d)):
                along = float(np.dot(result.error_xy[-1], d))
        row["modes"][mode] = {"ade": result.made, "fde": result.mfde, "along4": along, "covered90": result.covered, "steps": result.steps,
                              "nll": result.nll}
        return result

    def _window(self, ctx, track_id, future, vehicle) -> dict[str, Any]:
        frame, r = ctx["frame"], ctx["rows"][int(track_id)]
        start = (float(frame.x_m[r]), float(frame.y_m[r]))
        if not all(math.isfinite(x) for x in start):
            start = tuple(future[0])
        speed = float(vehicle.speed_mps)
        followed = followed_corridor(vehicle.corridors, future)
        corridor = vehicle.corridors[followed.index]
        rel = ctx["relations"].get((int(track_id), int(corridor.corridor_id)))
        leader = rel is not None and rel.leader_track_id >= 0 and math.isfinite(rel.leader_gap_m) and rel.leader_gap_m <= self.leader_gap_m
        conflict = rel is not None and rel.influencing_index >= 0
        directions = along_track_directions(start, future)
        # the measured acceleration's standard error (the markov stage's fit; NaN without a measurement)
        predictor = next(iter(self.predictors.values()))
        _, accel_se = predictor.measured_acceleration(int(track_id), ctx["stamp"])
        return {
            "recording": ctx["recording"], "sequence": ctx["sequence"], "stamp_ns": ctx["stamp"], "track_id": int(track_id),
            "speed_mps": speed, "split": "slow" if speed <= SLOW_SPEED_MPS else "fast",
            "manoeuvre": manoeuvre_class(start, future, ctx["tau_s"]),
            "followed_error_m": followed.error_m, "corridors": len(vehicle.corridors),
            "leader": bool(leader), "leader_gap_m": float(rel.leader_gap_m) if leader else None,
            "leader_speed_mps": float(rel.leader_speed_mps) if leader and math.isfinite(rel.leader_speed_mps) else None,
            "conflict": bool(conflict), "conflict_rule": rel.influencing_rule if conflict else "",
            "turning": corridor_turns(corridor, speed), "accel_se_mps2": accel_se, "_dir": directions[-1], "modes": {},
        }

    def window_rows(self) -> list[dict[str, Any]]:
        out = []
        for row in self.rows.values():
            row = dict(row)
            row.pop("_dir", None)
            out.append(row)
        return out


GROUPS = (
    ("manoeuvre", lambda w: w["manoeuvre"]),
    ("leader", lambda w: "leader <= %g m" % LEADER_GAP_M if w["leader"] else "no leader"),
    ("conflict", lambda w: "influencing conflict" if w["conflict"] else "no conflict"),
    ("corridor", lambda w: "turning" if w["turning"] else "straight"),
    ("leader x conflict", lambda w: ("L" if w["leader"] else "-") + ("C" if w["conflict"] else "-")),
)


def gap_table(windows: list[dict[str, Any]], a: str, b: str, split: str) -> list[str]:
    """Per group: windows, mADE of a and b, the difference, its share of the split's summed difference, along-track at 4 s."""
    sel = [w for w in windows if a in w["modes"] and b in w["modes"] and (split == "all" or w["split"] == split)]
    if not sel:
        return [f"no {split} windows with {a} and {b}"]
    total = sum(w["modes"][a]["ade"] - w["modes"][b]["ade"] for w in sel)
    lines = [f"{split} windows: {len(sel)}; mADE {a} {np.mean([w['modes'][a]['ade'] for w in sel]):.3f}, {b} "
             f"{np.mean([w['modes'][b]['ade'] for w in sel]):.3f}; summed ADE difference {total:.1f} m",
             f"{'group':<28} {'n':>5} {a[:8]:>8} {b[:8]:>8} {'diff':>7} {'share':>6} {'along4 ' + a[:3]:>10} {'along4 ' + b[:3]:>10}"]
    for name, key in GROUPS:
        lines.append(f"-- {name}")
        groups: dict[str, list] = collections.defaultdict(list)
        for w in sel:
            groups[key(w)].append(w)
        for g, ws in sorted(groups.items(), key=lambda kv: -len(kv[1])):
            ea = np.array([w["modes"][a]["ade"] for w in ws])
            eb = np.array([w["modes"][b]["ade"] for w in ws])
            la = np.nanmean([w["modes"][a]["along4"] for w in ws]) if any(math.isfinite(w["modes"][a]["along4"]) for w in ws) else math.nan
            lb = np.nanmean([w["modes"][b]["along4"] for w in ws]) if any(math.isfinite(w["modes"][b]["along4"]) for w in ws) else math.nan
            share = (ea - eb).sum() / total if total else math.nan
            lines.append(f"{g:<28} {len(ws):>5} {ea.mean():>8.2f} {eb.mean():>8.2f} {ea.mean() - eb.mean():>+7.2f} {share:>6.0%} {la:>+10.2f} {lb:>+10.2f}")
    return lines


SPLITS = ("all", "slow", "fast", "moving")


def _in_split(w: dict[str, Any], split: str) -> bool:
    return split == "all" or (split == "moving" and w["manoeuvre"] != "stands") or w["split"] == split


def ratio_interval(windows: list[dict[str, Any]], a: str, b: str, split: str = "all", *, draws: int = 4000,
                   seed: int = 0, level: float = 0.95) -> dict[str, float] | None:
    """mADE of ``a`` over mADE of ``b`` on the windows of ``split`` (all, slow, fast, or moving: every class but
    stands) and its ``level`` interval by resampling cars: the windows of one car (recording, track id) overlap in
    time and share its tracker and its corridors, so they are drawn together (a cluster bootstrap, ``draws`` draws
    of as many cars as there are, with replacement; the ratio of the drawn cars' summed ADEs). None without windows.
    """
    sel = [w for w in windows if a in w["modes"] and b in w["modes"] and _in_split(w, split)]
    if not sel:
        return None
    cars: dict[tuple, list[float]] = {}
    for w in sel:
        acc = cars.setdefault((w["recording"], w["track_id"]), [0.0, 0.0])
        acc[0] += w["modes"][a]["ade"]
        acc[1] += w["modes"][b]["ade"]
    sums = np.array(list(cars.values()))  # (cars, 2)
    total_b = sums[:, 1].sum()
    ratio = float(sums[:, 0].sum() / total_b) if total_b > 0 else math.nan  # b exact on every window: no ratio
    rng = np.random.default_rng(seed)
    picks = rng.integers(0, len(sums), size=(draws, len(sums)))
    drawn = sums[picks].sum(axis=1)  # (draws, 2)
    ok = drawn[:, 1] > 0
    ratios = drawn[ok, 0] / drawn[ok, 1]
    lo, hi = np.percentile(ratios, [50 * (1 - level), 50 * (1 + level)]) if ratios.size else (math.nan, math.nan)
    return {"ratio": ratio, "lo": float(lo), "hi": float(hi), "windows": len(sel), "cars": len(sums), "draws": draws, "level": level}


def ratio_lines(windows: list[dict[str, Any]], a: str, b: str, draws: int) -> list[str]:
    """``ratio_interval`` of every split, one line each."""
    lines = [f"mADE {a} / {b}, 95 % interval by resampling cars ({draws} draws):"]
    for split in SPLITS:
        r = ratio_interval(windows, a, b, split, draws=draws)
        lines.append(f"  {split:<7} -" if r is None else
                     f"  {split:<7} {r['ratio']:.3f} [{r['lo']:.3f}, {r['hi']:.3f}]  ({r['windows']} windows, {r['cars']} cars)")
    return lines


def accel_se_line(windows: list[dict[str, Any]]) -> str:
    """The median standard error of the measured acceleration (``accel_se_mps2``) per split, over the windows
    that have one (a dump written before it was kept has none)."""
    parts = []
    for split in ("slow", "fast"):
        se = [w["accel_se_mps2"] for w in windows if w["split"] == split and math.isfinite(w.get("accel_se_mps2", math.nan))]
        parts.append(f"{split} {np.median(se):.3f} m/s2 ({len(se)} windows)" if se else f"{split} -")
    return "median standard error of the measured acceleration: " + ", ".join(parts)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    add_arguments(p)
    p.add_argument("--windows", type=Path, default=None, help="write one JSON line per scored window here")
    p.add_argument("--from-windows", type=Path, default=None, help="read a --windows file instead of running the evaluation")
    p.add_argument("--compare", nargs=2, default=["hybrid", "baseline"], metavar=("A", "B"))
    p.add_argument("--split", choices=("fast", "slow", "all"), default="fast")
    p.add_argument("--leader-gap", type=float, default=LEADER_GAP_M, help=f"a leader counts within this gap, m (default {LEADER_GAP_M:g})")
    p.add_argument("--boot", type=int, default=4000, metavar="N",
                   help="draws of the interval of the mADE ratio of --compare, resampling cars (default 4000; 0: none)")
    args = p.parse_args(argv)
    check_output_arg(p, args.json, "--json")  # before the work: a bad path must not cost the run
    check_output_arg(p, args.windows, "--windows")
    if args.boot < 0:
        p.error(f"--boot {args.boot}: a number of draws >= 0 (0: no interval)")
    if args.from_windows is not None:
        windows = [json.loads(line) for line in args.from_windows.read_text().splitlines() if line.strip()]
    else:
        try:
            evaluation = WindowEvaluation(eval_config(args), leader_gap_m=args.leader_gap)
            report = evaluation.run()
        except ValueError as exc:
            sys.stderr.write(f"window_errors: error: {exc}\n")
            return 2
        print(format_table(report))
        if args.json is not None:  # the report iamp eval --json writes
            args.json.parent.mkdir(parents=True, exist_ok=True)
            args.json.write_text(json.dumps(json_safe(report), indent=2, allow_nan=False))
            print(f"wrote {args.json}")
        windows = evaluation.window_rows()
        if args.windows is not None:
            args.windows.parent.mkdir(parents=True, exist_ok=True)
            with args.windows.open("w") as fh:
                for w in windows:
                    fh.write(json.dumps(w, default=float) + "\n")
            print(f"wrote {args.windows} ({len(windows)} windows)")
    print(accel_se_line(windows))
    print("\n".join(gap_table(windows, *args.compare, args.split)))
    if args.boot > 0:
        print("\n".join(ratio_lines(windows, *args.compare, args.boot)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
