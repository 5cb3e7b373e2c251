"""``iamp eval --report DIR``: a self-contained evaluation report, DIR/report.md with its figures and eval.json beside it.

Every number in report.md is read from the evaluation's ``--json`` dict
(written beside it as ``eval.json``, the same run), so the report and the
JSON cannot disagree. Sections:

1. how it was made: the command, data (recordings, sequences, frames), model
   (path, sha256), parameters, package versions and the git commit;
2. the situations (the paper's Table I: vehicles seen, duration played,
   windows) and the paper's "Quantitative results" table per situation and
   mode: time per prediction step, mADE, mFDE (best per situation bold);
3. calibration: coverage of the 10..90 % highest-probability regions against
   their nominal level (reliability diagram), coverage at 50/90 % and NLL
   per mode and speed split;
4. error against horizon (1-4 s) per mode and speed split;
5. the manoeuvre classes of the true future and the along/cross-track split;
6. compute time per frame against vehicles per frame;
7. the paper's figures for one instant per recording (motion grid at 4 s,
   comparison of predicted means, acceleration distributions);
8. what was skipped, and the metric definitions.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import math
import platform
import subprocess
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np

from stages.lib.base import json_safe

REPO = Path(__file__).resolve().parents[2]
_SPLITS = (("overall", "all"), ("slow", "≤ 2 m/s"), ("fast", "> 2 m/s"))
_PACKAGES = ("numpy", "scipy", "torch", "matplotlib", "lanelet2", "eclipse-zenoh")


def fmt(value: Any, digits: int = 2) -> str:
    """A number as the report prints it ("–" for None/NaN)."""
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "–"
    if isinstance(value, (int, np.integer)) and not isinstance(value, bool):
        return f"{int(value):,}"
    return f"{float(value):.{digits}f}"


def _versions() -> dict[str, str]:
    out = {"python": platform.python_version()}
    for name in _PACKAGES:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = "not installed"
    return out


def _git(out_dir: Path | None = None) -> str:
    """HEAD, and whether the tracked files differ from it (the report's own folder not counted: it is being rewritten)."""
    try:
        head = subprocess.run(["git", "rev-parse", "--short=12", "HEAD"], cwd=REPO, capture_output=True, text=True, timeout=10)
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=REPO, capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return "unknown (no git)"
    if head.returncode != 0:
        return "unknown (not a git checkout)"
    own = None
    if out_dir is not None:
        try:
            own = Path(out_dir).resolve().relative_to(REPO).as_posix().rstrip("/") + "/"
        except ValueError:
            own = None
    changed = [line[3:] for line in dirty.stdout.splitlines() if line.strip()]
    changed = [f for f in changed if own is None or not f.startswith(own)]
    return head.stdout.strip() + (" with uncommitted changes" if changed else "")


def _sha256(path: str | None) -> str:
    if not path:
        return ""
    try:
        return hashlib.sha256(Path(path).read_bytes()).hexdigest()[:16]
    except OSError:
        return "unreadable"


def _short(path: str) -> str:
    """A path relative to the repository when it lies inside it; the development data folder as ``$IAMP_TAF_BW``."""
    import os

    data = os.environ.get("IAMP_TAF_BW")
    if data and str(path).rstrip("/") == data.rstrip("/"):
        return "$IAMP_TAF_BW"
    try:
        return Path(path).resolve().relative_to(REPO).as_posix()
    except ValueError:
        return str(path)


def _cell(text: Any) -> str:
    """A table cell's text: a ``|`` (a situation's name, a loader's example row) would end the cell, a newline the row."""
    return str(text).replace("|", "\\|").replace("\r", " ").replace("\n", " ")


def _table(head: list[str], rows: list[list[str]]) -> list[str]:
    def line(cells) -> str:
        return "| " + " | ".join(_cell(c) for c in cells) + " |"

    return [line(head), "|" + "|".join("---" for _ in head) + "|", *(line(r) for r in rows)]


def _bold_min(cells: list[str], values: list[float]) -> list[str]:
    finite = [v for v in values if v is not None and math.isfinite(v)]
    if len(finite) < 2:
        return cells
    best = min(finite)
    return [f"**{c}**" if v is not None and math.isfinite(v) and v == best else c for c, v in zip(cells, values)]


def quantitative_rows(report: dict[str, Any]) -> list[list[str]]:
    """The paper's "Quantitative results" table: per situation and mode, windows, time per step (ms), mADE, mFDE."""
    rows = []
    modes = list(report["modes"])
    for sit in report.get("situations", []):
        name = sit["name"]
        stats = [report["modes"][m]["by_situation"][name] for m in modes]
        made = _bold_min([fmt(s["mADE_m"]) for s in stats], [s["mADE_m"] for s in stats])
        mfde = _bold_min([fmt(s["mFDE_m"]) for s in stats], [s["mFDE_m"] for s in stats])
        tps = _bold_min([fmt(s["time_per_step_ms"], 1) for s in stats], [s["time_per_step_ms"] for s in stats])
        for i, mode in enumerate(modes):
            rows.append([name if i == 0 else "", mode, fmt(stats[i]["windows"]), tps[i], made[i], mfde[i]])
    return rows


QUANTITATIVE_HEAD = ["situation", "mode", "windows", "time per step (ms)", "mADE (m)", "mFDE (m)"]


def _online(hybrid: dict[str, Any]) -> str:
    """What hybrid learnt on the recordings (``modes.hybrid.initial_blend``, ``curve_choice``, ``accel_shift`` and ``speed_lead``), in
    words, per recording where there were several (``learnt_by_recording``: each starts afresh); '' if nothing."""
    by_recording = hybrid.get("learnt_by_recording") or {}
    if len(by_recording) > 1:
        words = ((name, _learnt(learnt)) for name, learnt in by_recording.items())
        return "; ".join(f"{name}: {said}" for name, said in words if said)
    return _learnt(hybrid)


#: the online choices of ``_learnt``: their key in the eval JSON, their name and the unit of their candidates
_CHOICE_WORDS = (("curve_choice", "curve factor", ""), ("accel_shift", "acceleration shift", " m/s²"), ("speed_lead", "speed lead", " s"))


def _learnt(hybrid: dict[str, Any]) -> str:
    """``_online`` of one recording's learners."""
    parts = []
    blend = hybrid.get("initial_blend")
    if blend:
        parts.append(f"weight of the measured acceleration in λ(0) {blend['weight']:.2f} from {fmt(blend['resolved'])} records")
    for key, name, unit in _CHOICE_WORDS:
        c = hybrid.get(key)
        if c:
            parts.append(f"{name} {c['factor']:g}{unit} of {', '.join(f'{f:g}' for f in c['factors'])} from {fmt(c['samples'])}"
                         f" back-tested vehicles (mean ADE {' / '.join(f'{a:.2f}' for a in c['mean_ade_m'])} m)")
    return "; ".join(parts)


#: the report's figures with a fixed name (the instant figures' names hold their instant)
_FIXED_FIGURES = ("reliability", "error_by_horizon", "by_manoeuvre", "timing")


def write_report(evaluation, report: dict[str, Any], directory: Path, command: str, *, formats: tuple[str, ...] = ("png", "svg"),
                 dpi: int = 100, keep: dict[str, Any] | None = None) -> Path:
    """Write DIR/report.md, DIR/eval.json and the figures; returns the report's path. ``keep`` receives the matplotlib
    figures by file stem (the tests read them)."""
    from stages.offline import figures as fg

    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    # an earlier report's figures: the instant ones' names hold the instant, and a rerun with --svg no writes no SVG
    for pattern in ("grid_4s_*", "means_*", "accel_*", *(f"{stem}.*" for stem in _FIXED_FIGURES)):
        for stale in directory.glob(pattern):
            if stale.suffix in (".png", ".svg"):
                stale.unlink()
    (directory / "eval.json").write_text(json.dumps(json_safe(report), indent=1, allow_nan=False))
    modes = report["modes"]
    first = next(iter(modes.values()))

    def emit(fig, stem: str) -> str:
        fg.save(fig, directory, stem, formats, dpi)
        if keep is not None:
            keep[stem] = fig
        return stem

    frame_ms = {m: evaluation.acc[m].frame_ms for m in modes}
    vehicles = {m: evaluation.acc[m].vehicles for m in modes}
    ar_median = modes.get("hybrid", {}).get("ar_inference_ms_median")
    charts = {
        "reliability": emit(fg.reliability_figure(report), "reliability"),
        "horizon": emit(fg.horizon_figure(report), "error_by_horizon"),
        "manoeuvre": emit(fg.manoeuvre_figure(report), "by_manoeuvre"),
        "timing": emit(fg.timing_figure(frame_ms, vehicles, ar_median), "timing"),
    }
    evaluation.write_figures(directory, formats, dpi, keep)
    svg = "svg" in formats

    def img(stem: str, alt: str) -> str:
        return f"![{alt}]({stem}.png)" + (f" ([SVG]({stem}.svg))" if svg else "")

    L: list[str] = []
    L.append("# Evaluation report: hybrid IAMP against its baseline and constant-velocity references")
    L.append("")
    L.append("Regenerate with:")
    L.append("")
    L.append("```sh")
    L.append(command)
    L.append("```")
    L.append("")
    L.append(f"Made {_dt.datetime.now(_dt.timezone.utc).strftime('%Y-%m-%d %H:%M UTC')} by `iamp eval --report`; every number below"
             " is in [eval.json](eval.json) (the `--json` output of the same run).")
    L.append("")
    # ---------------------------------------------------------------- provenance
    L.append("## How it was made")
    L.append("")
    model = report.get("model") or (str(REPO / "stages" / "lib" / "ar" / "weights" / "ar_taf_bw.pt") if "hybrid" in modes else None)
    online = _online(report["modes"]["hybrid"]) if "hybrid" in report["modes"] else ""
    rows = [
        ["data", f"`{_short(report['data'])}`: " + ", ".join(report["recordings"])],
        ["modes", ", ".join(modes)],
        ["instants", f"every {report['stride_s']:g} s from each sequence's first frame: {fmt(report['instants'])} instants,"
                     f" {fmt(first['overall']['windows'])} windows (vehicle with a full 4 s future, matched to corridors)"],
        ["model (hybrid)", f"`{_short(model)}` (sha256 {_sha256(model)}…)" if model else "–"],
        ["corridor weights", report["corridor_weights"]],
        ["Markov backend", f"{report['backend']} on {report['device']}"],
        ["parameters (--set)", ", ".join(f"{k}={v}" for k, v in report["params"].items()) or "defaults"],
        *([["learnt online (hybrid)", online]] if online else []),
        ["seed", str(report.get("seed", "–"))],
        ["code", _git(directory)],
        ["versions", ", ".join(f"{k} {v}" for k, v in _versions().items())],
    ]
    L += _table(["", ""], [[f"**{a}**", b] for a, b in rows])
    L.append("")
    inside = report.get("model_in_sample")
    if inside:  # the model file names the recordings it was trained on
        L.append(f"*hybrid's model was trained on {', '.join(report.get('model_trained_on') or [])}: on {', '.join(inside)} its"
                 " figures are in-sample (optimistic). For held-out figures train on one location and evaluate on the other"
                 " (`bench/generalisation.py`).*")
        L.append("")
    elif inside is None and model and "stages/lib/ar/weights" in str(model).replace("\\", "/"):
        L.append("*The shipped AR weights were trained on TAF-BW (K729 and K733): on these recordings hybrid's figures are"
                 " in-sample. For held-out figures train on one location and evaluate on the other (`bench/generalisation.py`).*")
        L.append("")
    grids = report.get("grids") or {}
    if grids.get("spread_in_sample"):  # the spread table names the recordings it was fitted on
        L.append(f"*The grids' spread table ({grids.get('spread_calibration')}) was fitted on {', '.join(grids.get('spread_fitted_on') or [])}:"
                 f" on {', '.join(grids['spread_in_sample'])} cov50, cov90 and NLL are in-sample (optimistic); means and mADE do not"
                 " depend on it. For held-out coverage fit the table on another location (`bench/generalisation.py --calibrate`).*")
        L.append("")
    elif grids and not grids.get("spread_calibration"):
        L.append("*Raw grids (`spread_calibration = \"\"`): over-confident for moving cars; cov90 is expected well under 0.9 for them.*")
        L.append("")
    L.append("Timing figures are wall time on the machine that made the report, with whatever else ran on it;"
             " compare modes within this report only.")
    L.append("")
    # ---------------------------------------------------------------- situations and the paper's table
    L.append("## Situations and quantitative results")
    L.append("")
    L.append("Situations as in the paper: a named time window of a recording (`--situations FILE.toml`; without it every"
             " recording is one situation). Vehicles: the vehicles seen in the window; duration: the frames played in it.")
    L.append("")
    L += _table(["situation", "recording", "window", "vehicles", "duration (s)", "windows scored", "description"],
                [[s["name"], s["recording"],
                  (f"sequence {s['sequence']}" if s["sequence"] else "all sequences")
                  + ("" if (s["start_s"] or 0) <= 0 and s["end_s"] is None else f", {s['start_s']:g}–{'end' if s['end_s'] is None else format(s['end_s'], 'g')} s"),
                  fmt(s["vehicles"]), fmt(s["duration_s"], 1), fmt(first["by_situation"][s["name"]]["windows"]), s["description"]]
                 for s in report.get("situations", [])])
    L.append("")
    L.append("**Quantitative results** (the paper's Table III for our data). Time per step: mean wall time of one prediction"
             " of all vehicles of the frame (grid included; hybrid: AR inference included); mADE/mFDE: the corridor mean"
             " with the smallest ADE/FDE (the paper's min form). Best per situation in bold.")
    L.append("")
    L += _table(QUANTITATIVE_HEAD, quantitative_rows(report))
    L.append("")
    # ---------------------------------------------------------------- all metrics per speed split
    L.append("All windows, by start speed (the speed split of every claim; wADE/wFDE: corridors weighted by their probability):")
    L.append("")
    head = ["mode", "split", "windows", "mADE", "mFDE", "wADE", "wFDE", "coverage50", "coverage90", "NLL", "route top1"]
    rows = []
    for mode, res in modes.items():
        for split, label in _SPLITS:
            st = res["overall"] if split == "overall" else res["by_speed"][split]
            cal = res.get("calibration", {}).get(split, {}).get("coverage")
            rows.append([mode, label, fmt(st["windows"]), fmt(st["mADE_m"]), fmt(st["mFDE_m"]), fmt(st["wADE_m"]), fmt(st["wFDE_m"]),
                         fmt(cal[4] if cal else None), fmt(st["coverage90"]), fmt(st["nll"]), fmt(st["route_top1"])])
    L += _table(head, rows)
    L.append("")
    if all("by_signal" in res for res in modes.values()):  # recordings with signal phases only
        keys = list(first["by_signal"])
        L.append("By the signal state of the car's group at the window start (recordings with signal phases;"
                 " `by_signal` in eval.json): mADE in m (windows).")
        L.append("")
        L += _table(["mode", *keys], [[mode, *[f"{fmt(res['by_signal'][k]['mADE_m'])} ({fmt(res['by_signal'][k]['windows'])})"
                                              for k in keys]] for mode, res in modes.items()])
        L.append("")
    # ---------------------------------------------------------------- calibration
    L.append("## Calibration")
    L.append("")
    L.append("Share of (vehicle, step) pairs whose true position lies in the highest-probability region of the vehicle's"
             " centre-point grid at that step, against the region's nominal level; a calibrated grid lies on the diagonal,"
             " below it the grid is over-confident. NLL: mean −ln P(true cell) in nats (floor 1e-6).")
    L.append("")
    L.append(img(charts["reliability"], "reliability diagram"))
    L.append("")
    levels = first.get("calibration", {}).get("levels", [])
    rows = []
    for mode, res in modes.items():
        for split, label in _SPLITS:
            cov = res.get("calibration", {}).get(split, {}).get("coverage", [])
            st = res["overall"] if split == "overall" else res["by_speed"][split]
            rows.append([mode, label, *[fmt(c) for c in cov], fmt(st["nll"])])
    L += _table(["mode", "split", *[f"{lv:.0%}" for lv in levels], "NLL"], rows)
    L.append("")
    # ---------------------------------------------------------------- horizon
    L.append("## Error against horizon")
    L.append("")
    L.append(img(charts["horizon"], "error against horizon"))
    L.append("")
    t_s = first.get("error_by_step_m", {}).get("t_s", [])
    picks = [min(range(len(t_s)), key=lambda i: (abs(t_s[i] - h), -t_s[i])) for h in (1.0, 2.0, 3.0, 4.0)] if t_s else []
    rows = []
    for mode, res in modes.items():
        e = res.get("error_by_step_m")
        if not e:
            continue
        for split, label in _SPLITS:
            rows.append([mode, label, *[fmt(e[split]["mean"][i]) for i in picks]])
    L.append("Mean displacement error (m) of the corridor mADE scores, at the prediction step nearest each horizon:")
    L.append("")
    L += _table(["mode", "split", *[f"{t_s[i]:g} s" for i in picks]], rows)
    L.append("")
    # ---------------------------------------------------------------- manoeuvres
    L.append("## By manoeuvre of the true future, along and across the track")
    L.append("")
    L.append(report.get("manoeuvre_classes", ""))
    L.append("")
    L.append(img(charts["manoeuvre"], "error by manoeuvre"))
    L.append("")
    classes = list(first.get("by_manoeuvre", {}))
    rows = [["windows", fmt(first["overall"]["windows"]), *[fmt(first["by_manoeuvre"][c]["windows"]) for c in classes]]]
    for mode, res in modes.items():
        rows.append([f"mADE {mode}", fmt(res["overall"]["mADE_m"]), *[fmt(res["by_manoeuvre"][c]["mADE_m"]) for c in classes]])
    for mode, res in modes.items():
        a = res.get("along_track_m")
        if a:
            rows.append([f"along bias 4 s {mode}", fmt(a["overall"]["4s"]["mean"]), *[fmt(a["by_manoeuvre"][c]["4s"]["mean"]) for c in classes]])
    for mode, res in modes.items():
        c_ = res.get("cross_track_m")
        if c_:
            rows.append([f"cross RMS 4 s {mode}", fmt(c_["overall"]["4s"]["rms"]), *[fmt(c_["by_manoeuvre"][c]["4s"]["rms"]) for c in classes]])
    L += _table(["", "all", *classes], rows)
    L.append("")
    L.append("Along-track (signed, + = ahead of the truth) and cross-track error of the mADE corridor at 1/2/3/4 s, all windows"
             " (" + report.get("along_cross_track", "") + "):")
    L.append("")
    rows = []
    for mode, res in modes.items():
        a, c_ = res.get("along_track_m", {}).get("overall", {}), res.get("cross_track_m", {}).get("overall", {})
        for key in a:
            rows.append([mode, f"{key} ({a[key]['t_s']:g} s)", fmt(a[key]["mean"]), fmt(a[key]["rms"]), fmt(c_[key]["mean_abs"]),
                         fmt(c_[key]["rms"]), fmt(a[key]["n"])])
    L += _table(["mode", "horizon", "along mean", "along RMS", "cross mean abs", "cross RMS", "windows with a direction"], rows)
    L.append("")
    # ---------------------------------------------------------------- timing
    L.append("## Compute time")
    L.append("")
    L.append(img(charts["timing"], "compute time per frame against vehicles"))
    L.append("")
    rows = []
    for mode, res in modes.items():
        ar = f"{fmt(res.get('ar_inference_ms_median'), 1)} / {fmt(res.get('ar_inference_ms_p95'), 1)}" if "ar_inference_ms_median" in res else "–"
        rows.append([mode, fmt(res["frames"]), fmt(res["vehicles_per_frame_mean"], 1), fmt(res["frame_ms_median"], 1), fmt(res["frame_ms_p95"], 1), ar])
    L += _table(["mode", "frames", "vehicles per frame", "frame ms median", "frame ms p95", "AR inference ms median / p95"], rows)
    L.append("")
    # ---------------------------------------------------------------- the paper's figures
    L.append("## The paper's figures, one instant per recording")
    L.append("")
    L.append("For each recording the instant with the most scored vehicles above 2 m/s (then the most scored vehicles).")
    L.append("")
    for recording in report["recordings"]:
        entries = [e for e in getattr(evaluation, "figure_index", []) if e["recording"] == recording]
        L.append(f"### {recording}")
        L.append("")
        if not entries:
            L.append("No instant with a vehicle with a full 4 s future: no figure.")
            L.append("")
            continue
        fig = evaluation.figures.get(recording)
        if fig is not None and fig.scores:
            L.append(f"Metrics at this instant ({fig.n_windows} vehicles; the paper's Table II):")
            L.append("")
            L += _table(["", *fig.scores], [["mADE (m)", *[fmt(s["mADE_m"]) for s in fig.scores.values()]],
                                            ["mFDE (m)", *[fmt(s["mFDE_m"]) for s in fig.scores.values()]]])
            L.append("")
        for e in entries:
            L.append(img(e["stem"], e["kind"]))
            L.append("")
            L.append(f"*{e['caption']}*")
            L.append("")
    # ---------------------------------------------------------------- skipped and definitions
    L.append("## What was left out, and the definitions")
    L.append("")
    if report["skipped"]:
        L += _table(["reason", "count", "first occurrence"],
                    [[k, fmt(v), report.get("skipped_examples", {}).get(k, "")] for k, v in report["skipped"].items()])
    else:
        L.append("Nothing was skipped.")
    L.append("")
    loads = {name: rep for name, rep in report.get("load_report", {}).items() if rep.get("problems") or rep.get("ignored_files")}
    if loads:
        L.append("What the loader left out or changed in the recordings' files (`load_report` in eval.json): fewer or other"
                 " windows than the files hold.")
        L.append("")
        rows = []
        for name, rep in loads.items():
            for reason, v in rep.get("problems", {}).items():
                rows.append([name, v["action"], reason, fmt(v["count"]), v.get("first", "")])
            for ignored in rep.get("ignored_files", []):
                rows.append([name, "ignored", "file", "", ignored])
        L += _table(["recording", "action", "reason", "rows", "first occurrence"], rows)
        L.append("")
    if report.get("stage_issues"):
        L.append("Issues the stages flagged (`stage_issues` in eval.json; the frames were still predicted):")
        L.append("")
        L += _table(["stage:kind", "count", "first occurrence"],
                    [[key, fmt(v["count"]), v.get("first", "")] for key, v in report["stage_issues"].items()])
        L.append("")
    for key, text in report.get("metrics", {}).items():
        L.append(f"- `{key}`: {text}")
    L.append("")
    path = directory / "report.md"
    path.write_text("\n".join(L) + "\n")
    return path


__all__ = ["QUANTITATIVE_HEAD", "fmt", "quantitative_rows", "write_report"]
