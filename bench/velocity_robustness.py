"""How much the predictions lean on the tracker: iamp eval on a recording as given, with its velocities spoiled, and at half its frame rate.

Variants (of every INTERACTION-format track file of the recording; positions,
yaw and everything else untouched):

- ``given``: the recording as it is (read from ``--data`` directly);
- ``vel_half``: velocities (``vx``/``vy``) x 0.5;
- ``vel_zero_1s``: velocity 0 for the first second of each track;
- ``vel_reversed``: velocities negated;
- ``rate_half``: every other frame left out (a 10 Hz recording played as a
  5 Hz tracker's; ``frameRate_hz`` of ``meta_data.csv`` halved): the stages
  work from the stamps, not from a rate. The windows are those whose start
  and future are still there (a few fewer).

Each modified recording is written to a temporary folder in the same layout
(``maps/<rec>.osm`` and ``meta_data.csv`` copied, track files rewritten by
header name, other columns kept as text), and ``iamp eval`` runs in-process
on it (``stages.offline.evaluation.Evaluation``, the default modes hybrid baseline
corridor_cv cv, stride 0.4 s). Printed per variant and mode: windows, mADE,
mFDE, coverage90, and the ratio of each to the ``given`` run (> 1 for the
errors, < 1 for coverage: worse); the same for the fast windows (speed > 2
m/s: most K729 windows are cars standing at a signal, whose velocity is 0
however it is spoiled), plus what the loader repaired (its load
report: the loader already undoes some spoiling, e.g. a sequence whose
velocities all point against the motion is flipped back). Asserts nothing.

    python bench/velocity_robustness.py --data DIR --recording NAME [--sequence ID ...] [--mode M ...]
        [--variant V ...] [--model WEIGHTS.pt] [--max-frames N] [--json OUT]

Session 38, ``--data $IAMP_TAF_BW --recording k733_2018-05-02 --mode hybrid
corridor_cv cv --variant rate_half --model`` the K729-trained seed-0 net of
``bench/generalisation.py``: mADE 2.31 / 2.91 / 3.47 m on 1,636 windows at
5 Hz, against 2.41 / 3.00 / 3.57 on 1,647 as given (10 Hz).

Defaults: the embedded ``stages/data/taf-bw``, recording ``k729_2022-03-16``.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import shutil
import sys
import tempfile
import time
from pathlib import Path

from stages.lib.datasets import DEFAULT_DATA_DIR, DEFAULT_RECORDING, DatasetError, find_recording, load_recording
from stages.lib.datasets.model import same_sequence_id
from stages.lib.datasets.interaction import META_FILE, TRACK_FILE_RE
from stages.lib.base import check_output_arg, json_safe
from stages.offline.evaluation import EVAL_MODES, EvalConfig, Evaluation

VARIANTS = ("given", "vel_half", "vel_zero_1s", "vel_reversed", "rate_half")
DEFAULT_MODES = ("hybrid", "baseline", "corridor_cv", "cv")
METRICS = ("mADE_m", "mFDE_m", "coverage90")


def _num(text: str) -> float | None:
    try:
        return float(text)
    except ValueError:
        return None


def _read_rows(path: Path) -> list[list[str]]:
    with path.open(newline="", encoding="utf-8-sig") as fh:
        return list(csv.reader(fh))


def _write_rows(path: Path, rows: list[list[str]]) -> None:
    with path.open("w", newline="", encoding="utf-8") as fh:
        csv.writer(fh, lineterminator="\n").writerows(rows)


def spoil_track_file(src: Path, dst: Path, variant: str) -> int:
    """Write ``src`` to ``dst`` with the velocity columns changed; returns the rows changed."""
    rows = _read_rows(src)
    if not rows:
        shutil.copyfile(src, dst)
        return 0
    header = [h.strip() for h in rows[0]]
    if "vx" not in header or "vy" not in header:
        shutil.copyfile(src, dst)
        return 0
    ix, iy = header.index("vx"), header.index("vy")
    it, its = header.index("track_id"), header.index("timestamp_ms")
    first_ms: dict[str, float] = {}
    for r in rows[1:]:
        if len(r) > max(it, its) and (t := _num(r[its])) is not None:
            first_ms[r[it]] = min(first_ms.get(r[it], math.inf), t)
    changed = 0
    for r in rows[1:]:
        if len(r) <= max(ix, iy, it, its):
            continue
        vx, vy = _num(r[ix]), _num(r[iy])
        if vx is None or vy is None:
            continue
        if variant == "vel_half":
            vx, vy = 0.5 * vx, 0.5 * vy
        elif variant == "vel_reversed":
            vx, vy = -vx, -vy
        elif variant == "vel_zero_1s":
            t = _num(r[its])
            if t is None or t >= first_ms[r[it]] + 1000.0:
                continue
            vx, vy = 0.0, 0.0
        else:
            raise ValueError(variant)
        r[ix], r[iy] = repr(vx), repr(vy)
        changed += 1
    _write_rows(dst, rows)
    return changed


def thin_track_file(src: Path, dst: Path) -> int:
    """Write ``src`` to ``dst`` with every other frame left out (frames counted on the file's own period from its first
    stamp; the even ones kept); returns the rows left out."""
    rows = _read_rows(src)
    header = [h.strip() for h in rows[0]] if rows else []
    if "timestamp_ms" not in header:
        shutil.copyfile(src, dst)
        return 0
    its = header.index("timestamp_ms")
    stamps = sorted({t for r in rows[1:] if len(r) > its and (t := _num(r[its])) is not None})
    period = min((b - a for a, b in zip(stamps, stamps[1:]) if b > a), default=100.0)
    keep = [rows[0]] + [r for r in rows[1:] if len(r) > its and (t := _num(r[its])) is not None and round((t - stamps[0]) / period) % 2 == 0]
    _write_rows(dst, keep)
    return len(rows) - len(keep)


def _halve_frame_rate(src: Path, dst: Path) -> None:
    """``meta_data.csv`` with ``frameRate_hz`` halved (the loader's frame period)."""
    rows = _read_rows(src)
    header = [h.strip() for h in rows[0]]
    if "frameRate_hz" in header:
        i = header.index("frameRate_hz")
        for r in rows[1:]:
            if len(r) > i and (rate := _num(r[i])) is not None:
                r[i] = repr(rate / 2)
    _write_rows(dst, rows)


def write_variant(data: Path, recording: str, out: Path, variant: str, sequences: tuple[str, ...] = ()) -> int:
    """The recording's folder and map under ``out`` with spoiled (or, ``rate_half``, thinned) track files (those of
    ``sequences``, default all; the others are left out); returns the rows changed (left out)."""
    ref = find_recording(data, recording)
    if ref.format != "interaction":
        raise SystemExit(f"{recording}: format {ref.format}; only INTERACTION-format recordings are supported")
    folder = out / "recorded_trackfiles" / recording
    folder.mkdir(parents=True, exist_ok=True)
    (out / "maps").mkdir(parents=True, exist_ok=True)
    if ref.map_path is not None:
        shutil.copyfile(ref.map_path, out / "maps" / ref.map_path.name)
    thinned = variant == "rate_half"
    (_halve_frame_rate if thinned else shutil.copyfile)(ref.folder / META_FILE, folder / META_FILE)
    rewrite = thin_track_file if thinned else (lambda src, dst: spoil_track_file(src, dst, variant))
    changed = 0
    for path in ref.track_files:
        m = TRACK_FILE_RE.match(path.name)
        if m and (not sequences or any(same_sequence_id(m.group(2), s) for s in sequences)):
            changed += rewrite(path, folder / path.name)
    return changed


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", type=Path, default=DEFAULT_DATA_DIR, help="data folder laid out like stages/data/taf-bw (default: the embedded one)")
    p.add_argument("--recording", default=DEFAULT_RECORDING, help=f"recording (default {DEFAULT_RECORDING})")
    p.add_argument("--sequence", action="append", default=[], help="sequence id (repeatable; default all)")
    p.add_argument("--mode", nargs="+", default=list(DEFAULT_MODES), choices=EVAL_MODES)
    p.add_argument("--variant", nargs="+", default=list(VARIANTS), choices=VARIANTS, help="variants (given is always run)")
    p.add_argument("--stride", type=float, default=0.4)
    p.add_argument("--model", type=Path, default=None, help="AR weights for hybrid (default: the shipped model, trained on all of TAF-BW)")
    p.add_argument("--max-frames", type=int, default=0, help="stop each sequence after this many frames (0: all)")
    p.add_argument("--json", type=Path, default=None)
    args = p.parse_args(argv)
    check_output_arg(p, args.json, "--json")  # before the work: a bad path must not cost the run
    variants = ["given"] + [v for v in args.variant if v != "given"]
    try:  # before the work: a data folder, recording or sequence that is not there is a bad command line
        ref = find_recording(args.data, args.recording)
        for want in args.sequence:
            if not any(same_sequence_id(s, want) for s in ref.sequence_ids):
                raise DatasetError(f"recording {ref.name}: no track file for sequence {want!r}; available: {', '.join(ref.sequence_ids)}")
    except DatasetError as exc:
        print(f"velocity_robustness: error: {exc}", file=sys.stderr)
        return 2

    results: dict[str, dict] = {}
    with tempfile.TemporaryDirectory(prefix="iamp-velrob-") as tmp:
        for variant in variants:
            data = args.data
            changed = 0
            if variant != "given":
                data = Path(tmp) / variant
                changed = write_variant(args.data, args.recording, data, variant, tuple(args.sequence))
            seqs = tuple(args.sequence) or None
            load_report = load_recording(data, args.recording, seqs).report.summary()
            t0 = time.monotonic()
            print(f"== {variant}: {changed} rows changed (rate_half: left out); loader: {load_report}", flush=True)
            report = Evaluation(EvalConfig(
                data_dir=data, recordings=(args.recording,), sequences=tuple(args.sequence), modes=tuple(args.mode),
                stride_s=args.stride, max_frames_per_sequence=max(args.max_frames, 0), progress=False, model_path=args.model,
            )).run()
            results[variant] = {
                "rows_changed": changed, "loader": load_report, "wall_s": round(time.monotonic() - t0, 1),
                "skipped": report["skipped"],
                "modes": {m: {"windows": r["overall"]["windows"], **{k: r["overall"][k] for k in METRICS},
                              "fast": {"windows": r["by_speed"]["fast"]["windows"], **{k: r["by_speed"]["fast"][k] for k in METRICS}}}
                          for m, r in report["modes"].items()},
            }
    for variant, res in results.items():
        for mode, r in res["modes"].items():
            base = results["given"]["modes"][mode]
            r["ratio"] = _ratios(r, base)
            r["fast"]["ratio"] = _ratios(r["fast"], base["fast"])
    print()
    print(format_table(results))
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        payload = {"data": str(args.data), "recording": args.recording, "sequences": args.sequence, "results": results}
        args.json.write_text(json.dumps(json_safe(payload), indent=2, allow_nan=False) + "\n")
        print(f"wrote {args.json}")
    return 0


def _ratios(r: dict, base: dict) -> dict:
    ok = lambda v: v is not None and isinstance(v, float) and math.isfinite(v)  # noqa: E731
    return {k: (r[k] / base[k] if ok(r[k]) and ok(base[k]) and base[k] else None) for k in METRICS}


def format_table(results: dict[str, dict]) -> str:
    head = (f"{'variant':<13} {'mode':<12} {'windows':>7} {'mADE':>6} {'mFDE':>6} {'cov90':>6}  {'mADE/given':>10} {'mFDE/given':>10}"
            f" {'cov90/given':>11}  {'fast':>5} {'fast mADE':>9} {'fast mFDE':>9} {'/given':>6} {'/given':>6}")
    lines = [head, "-" * len(head)]
    f = lambda v, spec: "-" if v is None or (isinstance(v, float) and not math.isfinite(v)) else format(v, spec)  # noqa: E731
    for variant, res in results.items():
        for mode, r in res["modes"].items():
            q = r["ratio"]
            lines.append(
                f"{variant:<13} {mode:<12} {r['windows']:>7d} {f(r['mADE_m'], '6.2f')} {f(r['mFDE_m'], '6.2f')} {f(r['coverage90'], '6.2f')}"
                f"  {f(q['mADE_m'], '10.3f')} {f(q['mFDE_m'], '10.3f')} {f(q['coverage90'], '11.3f')}"
                f"  {r['fast']['windows']:>5d} {f(r['fast']['mADE_m'], '9.2f')} {f(r['fast']['mFDE_m'], '9.2f')}"
                f" {f(r['fast']['ratio']['mADE_m'], '6.3f')} {f(r['fast']['ratio']['mFDE_m'], '6.3f')}"
            )
    lines.append("")
    for variant, res in results.items():
        lines.append(f"{variant}: {res['rows_changed']} rows changed, loader {res['loader']}, eval {res['wall_s']:.0f} s, skipped {res['skipped']}")
    return "\n".join(lines)




if __name__ == "__main__":
    sys.exit(main())
