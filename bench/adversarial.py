"""Adversarial recordings through the whole streaming pipeline, one oddity at a time.

For each recording written by ``testkit/adversarial.py`` (``adv_clean`` plus one
per oddity: velocities x0.5 / x2 / zero for the first second / negated, a car
at 30 m/s, a car starting off the map, a wrong-way car, a 50 m teleport,
duplicated and re-used ids, a one-frame track, NaN/inf positions, velocities,
yaws and sizes, 100 vehicles in one frame), this

1. runs the default pipeline as real processes over Zenoh:
   ``python launch.py --data DIR --recording NAME --speed max --no-viewer --record NAME.mcap``;
2. reads the MCAP with the project's reader (``stages.recorder.inspect.read_messages``):
   TrackFrames, MotionGrids, frames with a TrackFrame but no MotionGrid
   (``lost``), and each node's last ``NodeStats`` (core_errors, join_drops,
   issues by kind);
3. runs ``iamp eval --data DIR --recording NAME`` in-process (default modes)
   and keeps its exit code and skip counts.

It prints one table row per recording, then per recording the issue kinds
counted (``node.kind=count``; ``*`` marks a kind above ``adv_clean``'s
count), the kinds expected for its oddity (``testkit/adversarial.py``,
``ODDITIES``) and whether one of them was counted. Timings are printed, not
judged. Asserts nothing; exit code 0 unless the bench itself breaks.

    python bench/adversarial.py [--data DIR] [--only NAME ...] [--json OUT] [--keep DIR] [--no-eval]

``--data``: a folder written by ``python -m testkit.adversarial DIR`` (default:
written afresh into a temporary folder, seed ``--seed``). ``--keep DIR``
keeps the MCAP files and launcher logs there.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

from stages.lib.base import check_output_arg

REPO = Path(__file__).resolve().parents[1]


def load_adversarial():
    """The recording generator, ``testkit.adversarial``."""
    from testkit import adversarial

    return adversarial


def main(argv: list[str] | None = None) -> int:
    adv = load_adversarial()
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", type=Path, default=None, help="adversarial data folder (default: written afresh to a temp folder)")
    p.add_argument("--seed", type=int, default=0, help="seed when writing the recordings (default 0)")
    p.add_argument("--only", nargs="+", default=None, metavar="NAME", help="recordings to run (default: all of the folder)")
    p.add_argument("--json", type=Path, default=None, help="write the results as JSON")
    p.add_argument("--keep", type=Path, default=None, help="keep MCAP files and launcher logs in this folder")
    p.add_argument("--no-eval", action="store_true", help="leave out iamp eval")
    p.add_argument("--timeout", type=float, default=600.0, help="seconds per launcher run before it is stopped (default 600)")
    args = p.parse_args(argv)
    check_output_arg(p, args.json, "--json")  # before the work: a bad path must not cost the run
    if args.data is not None and not (args.data / "manifest.json").is_file():
        p.error(f"--data {args.data}: no manifest.json there (a folder written by python -m testkit.adversarial DIR)")

    with tempfile.TemporaryDirectory(prefix="iamp-adv-") as tmp:
        data = args.data
        if data is None:
            data = Path(tmp) / "data"
            adv.write_recordings(data, seed=args.seed)
            print(f"wrote adversarial recordings to {data} (seed {args.seed})")
        manifest = json.loads((data / "manifest.json").read_text())["recordings"]
        names = args.only or sorted(manifest, key=lambda n: (n != "adv_clean", n))
        missing = [n for n in names if n not in manifest]
        if missing:
            p.error(f"not in {data}/manifest.json: {missing}")
        work = args.keep or Path(tmp) / "runs"
        work.mkdir(parents=True, exist_ok=True)
        results = []
        for name in names:
            mcap = work / f"{name}.mcap"
            if mcap.exists():
                mcap.unlink()
            print(f"== {name}: pipeline ...", flush=True)
            run = adv.run_pipeline(data, name, mcap, run_id="adv", timeout_s=args.timeout, cwd=work)
            (work / f"{name}.launch.log").write_text(run.output)
            summary = adv.summarise(mcap, "adv") if mcap.exists() else adv.RecordingSummary()
            row = {"recording": name, "exit_code": run.exit_code, "wall_s": round(run.wall_s, 1), **summary.to_json(),
                   "oddities": manifest[name]["oddities"]}
            if not args.no_eval:
                print(f"== {name}: iamp eval ...", flush=True)
                t0 = time.monotonic()
                row["eval"] = adv.run_eval(data, name)
                row["eval"]["wall_s"] = round(time.monotonic() - t0, 1)
            results.append(row)
            print(format_row(row, header=True), flush=True)
        clean = next((r for r in results if r["recording"] == "adv_clean"), None)
        for r in results:
            r["expected"] = expected_found(r)
            r["above_clean"] = above_clean(r, clean)
        print()
        print(format_table(results))
        print()
        print(format_issues(results))
        if args.json is not None:
            args.json.parent.mkdir(parents=True, exist_ok=True)
            args.json.write_text(json.dumps({"data": str(data), "results": results}, indent=2) + "\n")
            print(f"wrote {args.json}")
    return 0


def expected_found(row: dict) -> dict[str, dict]:
    """Per oddity: the expected kinds and which of them some node counted."""
    totals: dict[str, int] = {}
    for kinds in row["issues_by_kind"].values():
        for k, v in kinds.items():
            totals[k] = totals.get(k, 0) + v
    out = {}
    for odd, spec in row["oddities"].items():
        kinds = spec["expected_kinds"]
        out[odd] = {"expected": kinds, "counted": {k: totals[k] for k in kinds if totals.get(k)}}
    return out


def above_clean(row: dict, clean: dict | None) -> dict[str, int]:
    """node.kind -> count, for kinds counted more often than in adv_clean (all kinds without it)."""
    base = clean["issues_by_kind"] if clean is not None else {}
    out = {}
    for node, kinds in row["issues_by_kind"].items():
        for k, v in kinds.items():
            if v > base.get(node, {}).get(k, 0):
                out[f"{node}.{k}"] = v
    return out


_COLS = ("recording", "exit", "wall_s", "TrackFrames", "MotionGrids", "lost", "core_errors", "join_drops", "expected", "eval", "eval_s", "eval skipped")


def _cells(r: dict) -> list[str]:
    errs = {n: v for n, v in r["core_errors"].items() if v}
    joins = sum(c.get("join_drops", 0) for c in r["counters"].values())
    exp = r.get("expected") or expected_found(r)
    with_kinds = [o for o, e in exp.items() if e["expected"]]
    hit = [o for o in with_kinds if exp[o]["counted"]]
    expected = f"{len(hit)}/{len(with_kinds)}" if with_kinds else "-"
    ev = r.get("eval")
    skipped = ",".join(f"{k}={v}" for k, v in ev["skipped"].items()) if ev else "-"
    return [
        r["recording"], str(r["exit_code"]), f"{r['wall_s']:.0f}", str(r["track_frames"]), str(r["motion_grids"]),
        str(len(r["frames_without_grid"])), ",".join(f"{n}={v}" for n, v in errs.items()) or "0", str(joins), expected,
        str(ev["exit_code"]) if ev else "-", f"{ev['wall_s']:.0f}" if ev else "-", skipped,
    ]


def format_row(r: dict, header: bool = False) -> str:
    cells = _cells(r)
    return "   " + "  ".join(f"{c}={v}" for c, v in zip(_COLS[1:], cells[1:]))


def format_table(results: list[dict]) -> str:
    rows = [list(_COLS)] + [_cells(r) for r in results]
    widths = [max(len(row[i]) for row in rows) for i in range(len(_COLS))]
    lines = ["  ".join(c.ljust(w) for c, w in zip(row, widths)).rstrip() for row in rows]
    lines.insert(1, "-" * len(lines[0]))
    return "\n".join(lines)


def format_issues(results: list[dict]) -> str:
    lines = ["issues by kind (last NodeStats per node; * above adv_clean), expected kinds per oddity:"]
    for r in results:
        above = r.get("above_clean", {})
        counted = [f"{'*' if f'{n}.{k}' in above else ''}{n}.{k}={v}" for n, kinds in sorted(r["issues_by_kind"].items())
                   for k, v in sorted(kinds.items())]
        lines.append(f"{r['recording']}: {' '.join(counted) or '(none)'}")
        for odd, e in r["expected"].items():
            if not e["expected"]:
                lines.append(f"    {odd}: no kind expected (must only be survived)")
                continue
            verdict = "counted " + ",".join(f"{k}={v}" for k, v in e["counted"].items()) if e["counted"] else "NOT COUNTED"
            lines.append(f"    {odd}: expects any of {','.join(e['expected'])}: {verdict}")
        if r["frames_without_grid"]:
            fr = r["frames_without_grid"]
            lines.append(f"    frames without MotionGrid: {len(fr)} (first {fr[:10]})")
        if r.get("eval") and r["eval"]["exit_code"] != 0:
            lines.append(f"    iamp eval failed: {r['eval']['error']}")
    return "\n".join(lines)


if __name__ == "__main__":
    raise SystemExit(main())
