"""Leave one location out: train the AR model on one TAF-BW location, evaluate every mode on the other.

What it measures. For each direction (train on K729 ``k729_2022-03-16``,
evaluate on K733 ``k733_2018-05-02``, and the reverse) it trains the AR
acceleration model with ``iamp train --recording A --seed S`` (nothing of
location B is seen) and runs ``iamp eval --recording B --model <that model>
--seed S`` over all modes (hybrid, baseline, corridor_cv, cv), both as
subprocesses (``python -m stages.cli``, what a user runs). One seed set: the
same ``--seed`` for the training and for the eval's intentions particle
filter. It prints and writes to ``--json``:

- per direction a table mode | split | windows | mADE | mFDE | wADE | cov90 |
  NLL for the splits overall, slow (start speed <= 2 m/s) and fast (> 2 m/s),
  from ``iamp eval --json`` (``modes.<m>.overall`` and ``.by_speed``);
- the ratios of mADE hybrid/baseline and hybrid/corridor_cv (overall and fast),
  hybrid/cv (slow), and each mode's median frame time;
- the goal check of the issue, met/missed per item: hybrid mADE <= 0.85 x
  baseline and <= 0.8 x corridor_cv overall and on fast cars, hybrid mADE <=
  cv on slow cars, hybrid coverage90 within 0.85-0.95 on slow and on fast;
- when ``iamp eval`` reports them, the per-manoeuvre class of the true future
  (``by_manoeuvre``: windows and mADE per mode and class), the signed
  along-track error (``along_track_m``) and the cross-track error
  (``cross_track_m``) at 1/2/3/4 s: tables windows / mADE per mode and class,
  along-track signed mean and cross-track RMS per mode and class (the class
  rule is ``iamp eval``'s, ``stages.offline.truth.manoeuvre_class``); all of
  their fields go to the JSON. With an ``iamp eval`` that has no such keys it
  says "not in this iamp eval" (a layout it does not know is printed as is).

It asserts nothing: these are development figures. Whatever parameters were
chosen looking at one location (the AR training options, the markov and
intentions defaults and the manoeuvre class thresholds, which were tuned
mostly on K729) are reported here on the other location, so the K729 -> K733
direction is the closer one to a held-out test; the K733 -> K729 direction
still evaluates on data whose statistics guided those defaults (only the AR
model is held out there).

Without ``--calibrate`` the grids are raw (``spread_calibration = ""``,
``spread_online = false``): the stage's default spread table was fitted on
both locations, so its coverage would be in-sample on either. With
``--calibrate`` each direction first fits the grids' spread on the
training location with its model (``iamp calibrate --recording A --model
<that model> --stride 0.8``, every mode; the file is cached beside the model,
keyed by the model, the ``--set`` values, the modes' spread shapes and the
project's code; ``--recalibrate`` fits again) and the eval reads it (``--set spread_calibration=FILE``), so the
coverage is calibrated on one location and reported on the other. ``--set
KEY=VALUE`` passes a markov_prediction parameter to both; ``--eval-set
KEY=VALUE`` to ``iamp eval`` only (e.g. ``--eval-set spread_online=false``:
the table without the online spread on top, which is on by default and which
``iamp calibrate`` does not take).

Models are cached under ``artefacts/generalisation/`` keyed by training
recording, seed and a hash of the training options (data folder and the
``iamp train`` flags) and of the project's code (``stages.lib.fingerprint``:
every ``.py`` file of ``stages/`` and ``bus_schemas/``), so that a change to
the code trains again instead of scoring a model older code trained (the
spread files likewise); ``--retrain`` forces training. The
eval JSON of each direction and the subprocess logs are kept beside them.

Run (full TAF-BW recordings named by ``IAMP_TAF_BW``)::

    IAMP_TAF_BW=/path/to/taf-bw python bench/generalisation.py
    python bench/generalisation.py --data DIR [--seed 0] [--direction k729-k733|k733-k729|both]
        [--max-frames N] [--stride 0.4] [--retrain] [--train-opt=--hidden=256 ...] [--calibrate [--recalibrate]] [--in-sample]
        [--set KEY=VALUE ...] [--eval-set KEY=VALUE ...] [--modes hybrid ...] [--json OUT]

``--modes`` restricts the modes ``iamp eval`` runs (default all four); the
ratios and goal items that need a mode not run say "unknown". Comparing AR
models: ``--modes hybrid --train-opt=--kind=gru``, one run per candidate.

``--model DIRECTION=FILE`` scores a model you trained yourself (``iamp
train --out FILE``, any options, or your own code writing the same format)
in that direction instead of training one: ``--model k729-k733=my.pt``
scores ``my.pt`` on K733 beside the baseline, corridor_cv and cv of the
same run (with ``--calibrate`` its spread is fitted on K729 with it, as for
a trained one). Repeatable, once per direction; a direction without one is
trained as usual. The file is checked before anything runs: it must load as
an AR model, and the recordings its metadata says it was trained on
(``recordings``) must not include the scored location, or
the figures would not be held out (exit 2; the shipped weights, trained on
both locations, are refused in either direction); a file whose metadata
names no recordings is scored with a warning that this cannot be checked.
The same file is scored for every seed of ``--seeds`` (the eval's particle
filter still takes the seed). The JSON's ``train`` of that direction says
``"given": true`` with the file's SHA-256 (``key``, its first 12 hex digits,
also the calibration cache's key).

``--seeds 0,1,2`` runs everything once per seed (each its own model, cached
per seed) and ends with each mode's mADE mean and range over the seeds per
direction and split (JSON: ``seeds``, ``by_seed.<seed>`` with the directions
of that seed, ``seed_spread.<direction>.<mode>.<split>.{values, mean, min,
max}``; ``directions`` holds the first seed's). One seed's hybrid figures
move by a few per cent (retraining and the particle filter): judge a choice
on the mean.

``--in-sample`` adds, per direction, hybrid scored on the evaluated location
with the model trained there (the other direction's, cached; the eval's
settings those of the held-out run): an optimistic figure, since most of
those windows trained the model, printed beside the held-out hybrid (JSON
``directions.<d>.in_sample.hybrid.<split>.{mADE_m, held_out_mADE_m}``). The
difference bounds from above what the learned model loses between locations
(much of it is the optimism of scoring cars the model trained on: README,
"In sample, for scale", has a time-cut check).

``--max-frames N`` is passed to ``iamp eval`` only (quick mode: each sequence
stops after N frames); training always uses the whole training recording.
Without data (no ``--data`` and ``IAMP_TAF_BW`` unset or not a data folder):
a one-line error, exit 2.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from stages.lib.base import check_output_arg, json_safe
from stages.lib.datasets import FULL_DATA_ENV, full_data_dir

RECORDINGS = {"k729": "k729_2022-03-16", "k733": "k733_2018-05-02"}
DIRECTIONS = {"k729-k733": ("k729", "k733"), "k733-k729": ("k733", "k729")}
MODES = ("hybrid", "baseline", "corridor_cv", "cv")
SPLITS = ("overall", "slow", "fast")
TABLE_METRICS = (("mADE", "mADE_m"), ("mFDE", "mFDE_m"), ("wADE", "wADE_m"), ("cov50", "coverage50"), ("cov90", "coverage90"), ("NLL", "nll"))
SLOW_FAST_MPS = 2.0
OUT_DIR = Path("artefacts") / "generalisation"
DEFAULT_JSON = Path("artefacts") / "generalisation.json"
NEW_KEYS = ("by_manoeuvre", "along_track_m", "cross_track_m")


# --------------------------------------------------------------------------- subprocesses


def _iamp(args: list[str], log: Path) -> tuple[int, float]:
    """Run ``iamp ARGS`` (``python -m stages.cli``) with stdout+stderr to ``log``; (return code, seconds)."""
    cmd = [sys.executable, "-m", "stages.cli", *args]
    print("$ iamp " + " ".join(args), flush=True)
    log.parent.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    with log.open("w") as fh:
        rc = subprocess.run(cmd, stdout=fh, stderr=subprocess.STDOUT).returncode
    seconds = time.perf_counter() - t0
    if rc != 0:
        tail = log.read_text(errors="replace").splitlines()[-15:]
        print(f"iamp {args[0]} failed (exit {rc}); last lines of {log}:\n  " + "\n  ".join(tail), file=sys.stderr)
    return rc, seconds


def train_key(data: Path, recording: str, train_opts: list[str]) -> str:
    """Hash of everything but the seed that decides the trained model (data folder, recording, flags, and the project's
    code: ``stages.lib.fingerprint``)."""
    from stages.lib.fingerprint import code_fingerprint

    blob = json.dumps({"data": str(data), "recording": recording, "train_options": list(train_opts), "code": code_fingerprint()},
                      sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()[:12]


def train_model(data: Path, recording: str, seed: int, train_opts: list[str], retrain: bool) -> dict[str, Any]:
    key = train_key(data, recording, train_opts)
    stem = f"ar_{recording}_seed{seed}_{key}"
    model, report, log = OUT_DIR / f"{stem}.pt", OUT_DIR / f"{stem}.train.json", OUT_DIR / f"{stem}.train.log"
    info: dict[str, Any] = {"recording": recording, "seed": seed, "options": list(train_opts), "key": key,
                            "model": str(model), "report_json": str(report)}
    if model.is_file() and report.is_file() and not retrain:
        info |= {"cached": True, "seconds": None}
        print(f"train {recording}: cached {model}")
    else:
        rc, seconds = _iamp(["train", "--data", str(data), "--recording", recording, "--seed", str(seed),
                             "--out", str(model), "--json", str(report), "--no-progress", *train_opts], log)
        if rc != 0:
            raise SystemExit(rc)
        info |= {"cached": False, "seconds": seconds}
        print(f"train {recording}: {seconds:.0f} s -> {model}")
    rep = json.loads(report.read_text())
    info["sizes"] = rep.get("sizes")
    info["validation"] = {n: {k: rep["validation"][n].get(k) for k in ("mse", "mae")} for n in ("model", "zero", "last")
                          if n in rep.get("validation", {})}
    info["training"] = {k: rep.get("training", {}).get(k) for k in ("epochs_run", "best_epoch", "train_seconds")}
    info["model_kind"] = {k: rep.get("model", {}).get(k) for k in ("kind", "hidden", "parameters")}
    info["inference_ms_per_frame"] = rep.get("inference_ms_per_frame")
    return info


def given_models(items: list[str]) -> tuple[dict[str, Path], list[str]]:
    """``--model DIRECTION=FILE`` values: {direction: file} and the warnings to print; ``ValueError`` with the one line
    that says what to fix (an unknown direction, a direction twice, a file that is not there or not an AR model, a
    model trained on the location the direction scores)."""
    out: dict[str, Path] = {}
    warnings: list[str] = []
    for item in items:
        direction, sep, file = item.partition("=")
        direction = direction.strip()
        if not sep or not file.strip():
            raise ValueError(f"--model {item!r}: expected DIRECTION=FILE, e.g. --model k729-k733=my_model.pt")
        if direction not in DIRECTIONS:
            raise ValueError(f"--model {item!r}: unknown direction {direction!r} (expected one of {', '.join(DIRECTIONS)})")
        if direction in out:
            raise ValueError(f"--model: direction {direction} given twice")
        path = Path(file.strip()).expanduser()
        if not path.is_file():
            raise ValueError(f"--model {item!r}: {path} is not a file")
        from stages.lib.ar.model import load_model

        try:
            metadata = load_model(path).metadata
        except Exception as exc:  # noqa: BLE001 - any failure to load is the same answer: not an AR model file
            raise ValueError(f"--model {item!r}: {path} does not load as an AR model ({type(exc).__name__}: {exc})") from None
        recordings = _trained_on(metadata)
        scored = DIRECTIONS[direction][1]
        if not isinstance(recordings, list) or not recordings:
            warnings.append(f"--model {direction}={path}: its metadata names no training recordings: cannot check that it "
                            f"never saw {scored.upper()} (scored as if held out)")
        elif any(str(r).lower().startswith(scored) for r in recordings):
            raise ValueError(f"--model {item!r}: {path} was trained on {', '.join(map(str, recordings))}, which includes the "
                             f"location this direction scores ({scored.upper()}): not held out (iamp eval gives in-sample figures)")
        out[direction] = path.resolve()
    return out, warnings


def _trained_on(metadata: Any) -> list[str] | None:
    """The recordings a model's metadata says it was trained on (``iamp train`` writes them as ``recordings``; an
    empty ``dataset_config.recordings`` means every recording of its data, so it is not read)."""
    found = metadata.get("recordings") if isinstance(metadata, dict) else None
    return [str(r) for r in found] if isinstance(found, list) and found else None


def given_model(recording: str, seed: int, path: Path) -> dict[str, Any]:
    """The ``train`` entry of a direction whose model is ``--model``'s file: as ``train_model``'s, keyed by the file's
    SHA-256 (the calibration cache follows the file's contents, not its name)."""
    from stages.lib.ar.model import load_model

    digest = hashlib.sha256(path.read_bytes()).hexdigest()
    model = load_model(path)
    metadata = model.metadata
    trained_on = _trained_on(metadata)
    print(f"model for the direction trained on {recording}: given {path} (sha256 {digest[:12]}; trained on "
          f"{', '.join(trained_on) if trained_on else 'recordings its metadata does not name'})")
    return {"recording": recording, "seed": seed, "options": [], "key": digest[:12], "sha256": digest, "model": str(path),
            "given": True, "cached": True, "seconds": None, "trained_on": trained_on,
            "model_kind": {"kind": metadata.get("kind"), "hidden": metadata.get("hidden"),
                           "parameters": int(sum(p.numel() for p in model.net.parameters()))}}


def spread_shapes(sets: list[str]) -> dict[str, str]:
    """Per mode, the spread_shape its markov_prediction resolves to with the ``--set`` values ``sets``."""
    from stages.markov_prediction import MarkovPredictionConfig

    params = {}
    for item in sets:
        key, _, value = item.partition("=")
        try:
            params[key.strip()] = json.loads(value)
        except json.JSONDecodeError:
            params[key.strip()] = value
    shape = params.get("spread_shape", "auto")
    return {m: MarkovPredictionConfig(mode=m, spread_shape=shape).spread_shape for m in MODES}


def calibrate(data: Path, recording: str, model: str, seed: int, sets: list[str], recalibrate: bool,
              model_sha256: str | None = None) -> dict[str, Any]:
    """``iamp calibrate`` on the training location with its model (every mode; stride 0.8 s): the spread file the eval reads.
    ``model_sha256``: a ``--model`` file's digest, part of the cache key (a trained model's name holds its own key)."""
    # the shape each mode's table is fitted for is part of the key (spread_shape "auto" resolves per mode, and a file
    # fitted before the shape existed is round)
    # and the project's code (the modes' grids decide the fit)
    from stages.lib.fingerprint import code_fingerprint

    keyed = {"model": model, "sets": sets, "shapes": spread_shapes(sets), "code": code_fingerprint()}
    if model_sha256 is not None:
        keyed["model_sha256"] = model_sha256
    key = hashlib.sha256(json.dumps(keyed, sort_keys=True).encode()).hexdigest()[:12]
    out = OUT_DIR / f"spread_{recording}_seed{seed}_{key}.json"
    report, log = out.with_suffix(".report.json"), out.with_suffix(".log")
    info: dict[str, Any] = {"recording": recording, "file": str(out), "report_json": str(report)}
    if out.is_file() and report.is_file() and not recalibrate:
        print(f"calibrate {recording}: cached {out}")
        info["cached"], info["seconds"] = True, None
    else:
        rc, seconds = _iamp(["calibrate", "--data", str(data), "--recording", recording, "--model", model, "--seed", str(seed),
                             "--stride", "0.8", "--mode", *MODES, "--out", str(out), "--json", str(report), "--no-progress",
                             *[f"--set={x}" for x in sets]], log)
        if rc != 0:
            raise SystemExit(rc)
        info["cached"], info["seconds"] = False, seconds
        print(f"calibrate {recording}: {seconds:.0f} s -> {out}")
    rep = json.loads(report.read_text())
    info["tables"] = rep.get("tables")
    info["in_sample"] = {m: {k: v[k] for k in ("windows", "coverage_uncalibrated", "coverage_at_sigma")} for m, v in rep.get("measured", {}).items()}
    return info


def eval_model(data: Path, recording: str, model: str, seed: int, stride: float, max_frames: int, tag: str,
               sets: list[str] = (), modes: tuple[str, ...] = MODES) -> tuple[dict[str, Any], float, str]:
    suffix = f"_seed{seed}_stride{stride:g}" + (f"_mf{max_frames}" if max_frames else "")
    if sets:
        suffix += "_" + hashlib.sha256(json.dumps(list(sets)).encode()).hexdigest()[:8]
    if tuple(modes) != MODES:  # a subset of the modes, with its model: its own files (the full run's stay)
        suffix += "_" + "-".join(modes) + "_" + Path(model).stem.rsplit("_", 1)[-1]
    out, log = OUT_DIR / f"eval_{tag}{suffix}.json", OUT_DIR / f"eval_{tag}{suffix}.log"
    args = ["eval", "--data", str(data), "--recording", recording, "--model", model, "--seed", str(seed),
            "--stride", f"{stride:g}", "--mode", *modes, "--json", str(out), "--no-progress", *[f"--set={x}" for x in sets]]
    if max_frames:
        args += ["--max-frames", str(max_frames)]
    rc, seconds = _iamp(args, log)
    if rc != 0:
        raise SystemExit(rc)
    print(f"eval {recording}: {seconds:.0f} s -> {out}")
    return json.loads(out.read_text()), seconds, str(out)


# --------------------------------------------------------------------------- figures


def _split(mode_res: dict[str, Any], split: str) -> dict[str, Any]:
    return mode_res.get("overall", {}) if split == "overall" else mode_res.get("by_speed", {}).get(split, {})


def _f(x: Any, digits: int = 2) -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "n/a"
    if isinstance(x, int) and not isinstance(x, bool):
        return str(x)
    return f"{x:.{digits}f}"


def _ratio(a: Any, b: Any) -> float | None:
    if a is None or b is None or not (math.isfinite(a) and math.isfinite(b)) or b == 0:
        return None
    return a / b


def summarise(report: dict[str, Any]) -> dict[str, Any]:
    """Table rows, ratios, frame times and the goal check of one eval report."""
    modes = report.get("modes", {})
    table = {m: {s: {"windows": _split(modes[m], s).get("windows")} | {k: _split(modes[m], s).get(k) for _, k in TABLE_METRICS}
                 for s in SPLITS} for m in MODES if m in modes}

    def made(mode: str, split: str) -> float | None:
        return table.get(mode, {}).get(split, {}).get("mADE_m")

    ratios = {
        "hybrid/baseline overall": _ratio(made("hybrid", "overall"), made("baseline", "overall")),
        "hybrid/baseline fast": _ratio(made("hybrid", "fast"), made("baseline", "fast")),
        "hybrid/corridor_cv overall": _ratio(made("hybrid", "overall"), made("corridor_cv", "overall")),
        "hybrid/corridor_cv fast": _ratio(made("hybrid", "fast"), made("corridor_cv", "fast")),
        "hybrid/cv slow": _ratio(made("hybrid", "slow"), made("cv", "slow")),
    }
    frame_ms = {m: modes[m].get("frame_ms_median") for m in MODES if m in modes}

    def check(value: float | None, ok) -> str:
        return "unknown" if value is None else ("met" if ok(value) else "missed")

    cov = {s: table.get("hybrid", {}).get(s, {}).get("coverage90") for s in ("slow", "fast")}
    goal = {
        "hybrid mADE <= 0.85 x baseline, overall": (ratios["hybrid/baseline overall"], 0.85),
        "hybrid mADE <= 0.85 x baseline, fast (> 2 m/s)": (ratios["hybrid/baseline fast"], 0.85),
        "hybrid mADE <= 0.8 x corridor_cv, overall": (ratios["hybrid/corridor_cv overall"], 0.8),
        "hybrid mADE <= 0.8 x corridor_cv, fast (> 2 m/s)": (ratios["hybrid/corridor_cv fast"], 0.8),
        "hybrid mADE <= cv, slow (<= 2 m/s)": (ratios["hybrid/cv slow"], 1.0),
    }
    checks = {name: {"value": v, "limit": f"<= {lim:g}", "status": check(v, lambda x, lim=lim: x <= lim)} for name, (v, lim) in goal.items()}
    for s in ("slow", "fast"):
        checks[f"hybrid coverage90 in [0.85, 0.95], {s}"] = {"value": cov[s], "limit": "0.85-0.95",
                                                             "status": check(cov[s], lambda x: 0.85 <= x <= 0.95)}
    new = {key: {m: _find_key(modes[m], key) for m in MODES if m in modes} for key in NEW_KEYS}
    return {"table": table, "ratios": ratios, "frame_ms_median": frame_ms, "goal": checks,
            "new_keys_present": {k: any(v is not None for v in new[k].values()) for k in NEW_KEYS}}


def _find_key(mode_res: dict[str, Any], key: str) -> Any:
    """``key`` at the mode's top level or under its ``overall`` (where the eval puts it is not fixed yet)."""
    if key in mode_res:
        return mode_res[key]
    return mode_res.get("overall", {}).get(key) if isinstance(mode_res.get("overall"), dict) else None


def format_direction(name: str, train: dict[str, Any], ev: dict[str, Any], summary: dict[str, Any]) -> str:
    a, b = DIRECTIONS[name]
    how = "given: --model" if train.get("given") else "cached" if train["cached"] else f"trained in {train['seconds']:.0f} s"
    lines = [f"=== train {RECORDINGS[a]} -> eval {RECORDINGS[b]} ===", f"model {train['model']} ({how})"]
    sizes, val = train.get("sizes") or {}, train.get("validation") or {}
    if sizes and val:
        lines.append(f"  training on {a}: {sizes.get('train')} train / {sizes.get('val')} validation samples; "
                     "validation MSE/MAE: " + ", ".join(f"{n} {_f(val[n]['mse'], 3)}/{_f(val[n]['mae'], 3)}" for n in val))
    kind, inf = train.get("model_kind") or {}, train.get("inference_ms_per_frame") or {}
    if kind:
        lines.append(f"  model kind {kind.get('kind')} hidden {kind.get('hidden')} ({kind.get('parameters')} parameters)"
                     + (f"; predict {_f(inf.get('median_ms'))} ms median / {_f(inf.get('min_ms'))} ms min per frame of {inf.get('pairs')} pairs (cpu)" if inf else ""))
    lines.append(f"  eval on {b}: {ev.get('instants')} instants, skipped {ev.get('skipped')}")
    lines.append("")
    head = f"{'mode':<12} {'split':<8} {'windows':>7}" + "".join(f" {h:>6}" for h, _ in TABLE_METRICS)
    lines += [head, "-" * len(head)]
    for mode, splits in summary["table"].items():
        for split, row in splits.items():
            lines.append(f"{mode:<12} {split:<8} {_f(row['windows']):>7}" + "".join(f" {_f(row[k]):>6}" for _, k in TABLE_METRICS))
    lines.append("(slow: start speed <= 2 m/s, fast: > 2 m/s)")
    lines.append("")
    lines.append("mADE ratios: " + "; ".join(f"{k} {_f(v, 3)}" for k, v in summary["ratios"].items()))
    lines.append("frame time median: " + "; ".join(f"{m} {_f(v, 1)} ms" for m, v in summary["frame_ms_median"].items()))
    lines.append("")
    lines.append("goal check:")
    for item, c in summary["goal"].items():
        lines.append(f"  {c['status']:<7} {item}: {_f(c['value'], 3)} (goal {c['limit']})")
    lines.append("")
    lines += format_new_keys(ev.get("modes", {}))
    return "\n".join(lines)


def format_new_keys(modes: dict[str, Any]) -> list[str]:
    """The manoeuvre, along-track and cross-track tables of one eval report ("not in this iamp eval" where absent)."""
    lines: list[str] = []
    classes: list[str] = []
    by_man = {m: _find_key(modes[m], "by_manoeuvre") for m in MODES if m in modes}
    if not any(v is not None for v in by_man.values()):
        lines.append("by_manoeuvre: not in this iamp eval")
    else:
        classes = list(dict.fromkeys(c for v in by_man.values() if isinstance(v, dict) for c in v))
        lines.append("by_manoeuvre (class of the true future, from positions): windows / mADE (m)")
        lines.append(f"{'mode':<12}" + "".join(f" {c[:18]:>18}" for c in classes))
        for m, v in by_man.items():
            cells = []
            for c in classes:
                st = v.get(c) if isinstance(v, dict) else None
                cells.append(f"{_f(st.get('windows'))} / {_f(st.get('mADE_m'))}" if isinstance(st, dict) else "-")
            lines.append(f"{m:<12}" + "".join(f" {c:>18}" for c in cells))
    for key, field, what in (("along_track_m", "mean", "along-track error, signed mean (m, + = ahead of the truth)"),
                             ("cross_track_m", "rms", "cross-track error, RMS (m)")):
        per_mode = {m: _find_key(modes[m], key) for m in MODES if m in modes}
        if not any(v is not None for v in per_mode.values()):
            lines.append(f"{key}: not in this iamp eval")
            continue
        table = _track_table(per_mode, field, classes)
        if table is None:  # a layout this bench does not know: print it as it is
            lines.append(f"{key}: {what}, as iamp eval lays it out")
            for m, v in per_mode.items():
                lines += [f"  {m}"] + [f"    {row}" for row in _generic_rows(v)]
        else:
            lines.append("")
            lines.append(f"{key}: {what}; per class of the true future")
            lines += table
    return lines


def _track_table(per_mode: dict[str, Any], field: str, classes: list[str]) -> list[str] | None:
    """``{overall: {1s: {t_s, n, FIELD}}, by_manoeuvre: {class: {1s: ...}}}`` per mode as rows mode | group | 1s..4s (n at 4 s)."""
    try:
        first = next(v for v in per_mode.values() if v is not None)
        horizons = list(first["overall"])
        steps = ", ".join(f"{h} = {first['overall'][h]['t_s']:g} s" for h in horizons)
    except (StopIteration, KeyError, TypeError, AttributeError):
        return None
    head = f"{'mode':<12} {'group':<12}" + "".join(f" {h:>6}" for h in horizons) + f" {'n@' + horizons[-1]:>6}"
    lines = [f"(prediction steps: {steps})", head, "-" * len(head)]
    for m, v in per_mode.items():
        if not isinstance(v, dict) or not isinstance(v.get("overall"), dict):
            continue
        groups = [("overall", v["overall"])] + [(c, v.get("by_manoeuvre", {}).get(c)) for c in (classes or v.get("by_manoeuvre", {}))]
        for name, g in groups:
            if not isinstance(g, dict):
                continue
            cells = [g.get(h, {}).get(field) if isinstance(g.get(h), dict) else None for h in horizons]
            n_last = g.get(horizons[-1], {}).get("n") if isinstance(g.get(horizons[-1]), dict) else None
            lines.append(f"{m:<12} {name:<12}" + "".join(f" {_f(c):>6}" for c in cells) + f" {_f(n_last):>6}")
    return lines


def _generic_rows(value: Any, prefix: str = "") -> list[str]:
    """A nested dict/list of numbers as rows 'path: k1 v1  k2 v2 ...' (the leaves' parent is one row)."""
    if isinstance(value, dict):
        if all(not isinstance(v, (dict, list)) for v in value.values()):
            return [f"{prefix}{'  '.join(f'{k} {_f(v)}' for k, v in value.items())}"]
        rows: list[str] = []
        for k, v in value.items():
            rows += _generic_rows(v, f"{prefix}{k}: ") if isinstance(v, (dict, list)) else [f"{prefix}{k} {_f(v)}"]
        return rows
    if isinstance(value, list):
        if all(not isinstance(v, (dict, list)) for v in value):
            return [f"{prefix}[{', '.join(_f(v) for v in value)}]"]
        rows = []
        for i, v in enumerate(value):
            rows += _generic_rows(v, f"{prefix}{i}: ")
        return rows
    return [f"{prefix}{_f(value)}"]


# --------------------------------------------------------------------------- main


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--data", type=Path, default=None, help=f"full TAF-BW data folder (default ${FULL_DATA_ENV})")
    p.add_argument("--seed", type=int, default=0, help="seed of iamp train and of iamp eval's particle filter (default 0)")
    p.add_argument("--seeds", default=None, metavar="S,S,...",
                   help="run every direction once per seed (train and eval) and print each mode's mADE mean and range over them "
                        "(one seed's figures move by a few %%: judge a choice on the mean); overrides --seed")
    p.add_argument("--direction", choices=(*DIRECTIONS, "both"), default="both")
    p.add_argument("--max-frames", type=int, default=0, help="passed to iamp eval: stop each sequence after N frames (0: all)")
    p.add_argument("--stride", type=float, default=0.4, help="iamp eval --stride, s (default 0.4)")
    p.add_argument("--retrain", action="store_true", help="train even when a cached model exists")
    p.add_argument("--train-opt", action="append", default=[], metavar="FLAG",
                   help="extra iamp train flag, e.g. --train-opt=--hidden=256 (repeatable; part of the cache key)")
    p.add_argument("--in-sample", action="store_true",
                   help="also score hybrid on each direction's scored location with the model trained there (in sample, "
                        "optimistic): how much of hybrid's held-out error is the model's transfer between locations")
    p.add_argument("--calibrate", action="store_true",
                   help="fit the grids' spread with iamp calibrate on the training location (its model) and evaluate with it")
    p.add_argument("--recalibrate", action="store_true", help="with --calibrate: fit even when a cached file exists")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="markov_prediction parameter for iamp calibrate and iamp eval (repeatable)")
    p.add_argument("--eval-set", action="append", default=[], metavar="KEY=VALUE",
                   help="markov_prediction parameter for iamp eval only (repeatable), e.g. --eval-set spread_online=true")
    p.add_argument("--modes", nargs="+", choices=MODES, default=list(MODES),
                   help="modes iamp eval runs (default all; e.g. --modes hybrid to compare AR models without re-running the others)")
    p.add_argument("--model", action="append", default=[], metavar="DIRECTION=FILE",
                   help="score this AR model file in DIRECTION (k729-k733: it must not have seen K733) instead of training one; "
                        "repeatable, once per direction")
    p.add_argument("--json", type=Path, default=DEFAULT_JSON, help=f"write everything here (default {DEFAULT_JSON})")
    args = p.parse_args(argv)
    check_output_arg(p, args.json, "--json")  # before the work (training and evaluations: minutes to hours)
    try:
        args.given, warnings = given_models(args.model)
    except ValueError as exc:
        p.error(str(exc))
    for line in warnings:
        print(f"warning: {line}", file=sys.stderr, flush=True)

    data = args.data if args.data is not None else full_data_dir()
    if data is None or not (Path(data) / "recorded_trackfiles").is_dir():
        where = f"--data {args.data}" if args.data is not None else f"${FULL_DATA_ENV}"
        sys.stderr.write(f"generalisation: error: no TAF-BW data ({where} is not a folder with recorded_trackfiles/); "
                         f"set {FULL_DATA_ENV} or pass --data\n")
        return 2
    data = Path(data).expanduser().resolve()
    missing = [r for r in RECORDINGS.values() if not (data / "recorded_trackfiles" / r).is_dir()]
    if missing:
        sys.stderr.write(f"generalisation: error: {data} lacks recording(s) {', '.join(missing)}\n")
        return 2

    seeds = [args.seed]
    if args.seeds is not None:
        try:
            seeds = [int(x) for x in args.seeds.split(",") if x.strip()]
        except ValueError:
            seeds = []
        if not seeds or len(set(seeds)) != len(seeds):
            sys.stderr.write(f"generalisation: error: --seeds {args.seeds!r}: expected distinct integers separated by commas\n")
            return 2
    t0 = time.perf_counter()
    names = list(DIRECTIONS) if args.direction == "both" else [args.direction]
    out: dict[str, Any] = {"data": str(data), "seed": seeds[0], "stride_s": args.stride, "max_frames": args.max_frames,
                           "train_options": args.train_opt, "modes": [m for m in MODES if m in args.modes], "calibrate": args.calibrate, "set": args.set, "eval_set": args.eval_set, "slow_fast_split_mps": SLOW_FAST_MPS, "directions": {}}
    per_seed: dict[int, dict[str, Any]] = {}
    for seed in seeds:
        if len(seeds) > 1:
            print(f"\n##### seed {seed}", flush=True)
        per_seed[seed] = _run_seed(args, data, names, seed)
    out["directions"] = per_seed[seeds[0]]
    if len(seeds) > 1:
        out["seeds"] = seeds
        out["by_seed"] = {str(seed): dirs for seed, dirs in per_seed.items()}
        out["seed_spread"] = seed_spread({seed: {n: d["table"] for n, d in dirs.items()} for seed, dirs in per_seed.items()})
        print("\n" + format_seed_spread(out["seed_spread"]), flush=True)
    out["seconds"] = time.perf_counter() - t0
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(json_safe(out), indent=2, allow_nan=False))
    print(f"total {out['seconds']:.0f} s; wrote {args.json}")
    return 0


def seed_spread(tables: dict[int, dict[str, dict[str, Any]]]) -> dict[str, Any]:
    """``{direction: {mode: {split: {"values", "mean", "min", "max"}}}}`` of mADE over the seeds, from each seed's
    ``summarise(...)["table"]`` per direction (``tables[seed][direction]``); a seed without a figure is left out of
    that cell (``values`` holds the seeds' figures in seed order, None where missing)."""
    out: dict[str, Any] = {}
    seeds = list(tables)
    directions = [d for d in DIRECTIONS if any(d in tables[s] for s in seeds)]
    for d in directions:
        modes = [m for m in MODES if any(m in tables[s].get(d, {}) for s in seeds)]
        out[d] = {}
        for m in modes:
            out[d][m] = {}
            for split in SPLITS:
                values = [tables[s].get(d, {}).get(m, {}).get(split, {}).get("mADE_m") for s in seeds]
                known = [v for v in values if v is not None and math.isfinite(v)]
                out[d][m][split] = {"values": values, "mean": sum(known) / len(known) if known else None,
                                    "min": min(known) if known else None, "max": max(known) if known else None}
    return out


def format_seed_spread(spread: dict[str, Any]) -> str:
    lines = ["mADE over the seeds: mean (min-max), m"]
    for d, modes in spread.items():
        lines.append(f"=== {d} ===")
        lines.append(f"{'mode':<12} " + " ".join(f"{split:>18}" for split in SPLITS))
        for m, splits in modes.items():
            cells = []
            for split in SPLITS:
                c = splits[split]
                cells.append(f"{_f(c['mean'])} ({_f(c['min'])}-{_f(c['max'])})".rjust(18))
            lines.append(f"{m:<12} " + " ".join(cells))
    return "\n".join(lines)


def _run_seed(args, data: Path, names: list[str], seed: int) -> dict[str, Any]:
    """Every direction of ``names`` with one seed: train (cached), calibrate (optional), eval; printed as it goes."""
    directions: dict[str, Any] = {}
    for name in names:
        a, b = DIRECTIONS[name]
        given = getattr(args, "given", {}).get(name)
        train = given_model(RECORDINGS[a], seed, given) if given is not None else train_model(data, RECORDINGS[a], seed, args.train_opt, args.retrain)
        sets, cal = list(args.set), None
        if args.calibrate:
            cal = calibrate(data, RECORDINGS[a], train["model"], seed, sets, args.recalibrate, train.get("sha256"))
            sets.append(f"spread_calibration={cal['file']}")
        else:  # raw grids: the stage's default, the shipped table, was fitted on both locations (in-sample on either)
            from stages.markov_prediction.config import RAW_GRIDS

            sets = [*(f"{k}={json.dumps(v)}" for k, v in RAW_GRIDS.items()), *sets]
        sets.extend(args.eval_set)
        tag = name if given is None else f"{name}_model{train['key']}"  # (a given model's eval its own files)
        ev, ev_seconds, ev_path = eval_model(data, RECORDINGS[b], train["model"], seed, args.stride, args.max_frames, tag, sets,
                                             tuple(m for m in MODES if m in args.modes))
        summary = summarise(ev)
        text = format_direction(name, train, ev, summary)
        print("\n" + text + "\n", flush=True)
        if cal is not None:
            text += "\n\nspread calibrated on " + RECORDINGS[a] + " (iamp calibrate): " + cal["file"]
            print(text.rsplit("\n", 1)[-1], flush=True)
        directions[name] = {"train_recording": RECORDINGS[a], "eval_recording": RECORDINGS[b], "train": train,
                            "calibration": cal, "sets": sets, "seed": seed,
                            "eval_seconds": ev_seconds, "eval_json": ev_path, "eval_instants": ev.get("instants"),
                            "eval_skipped": ev.get("skipped"), **summary,
                            **{k: {m: _find_key(ev["modes"][m], k) for m in ev.get("modes", {})} for k in NEW_KEYS}}
        if args.in_sample and "hybrid" in ev.get("modes", {}):
            directions[name]["in_sample"] = in_sample(args, data, RECORDINGS[b], seed, sets, ev)
    return directions


def in_sample(args, data: Path, recording: str, seed: int, sets: list[str], held_out: dict[str, Any]) -> dict[str, Any]:
    """``--in-sample``: hybrid scored on ``recording`` with the model trained on it (the other direction's, cached), the
    eval's other settings those of the held-out run (``sets``, its spread file included); printed next to the held-out
    hybrid. Optimistic by construction: most of those windows trained the model (its validation part did not), so the
    difference to the held-out figure is an upper bound on what the learned model loses between locations."""
    model = train_model(data, recording, seed, args.train_opt, args.retrain)["model"]
    ev, _seconds, path = eval_model(data, recording, model, seed, args.stride, args.max_frames, "insample_" + recording.split("_")[0],
                                    sets, ("hybrid",))
    rows = {}
    for split in ("overall", "fast", "slow"):
        mine, held = _split(ev["modes"]["hybrid"], split).get("mADE_m"), _split(held_out["modes"]["hybrid"], split).get("mADE_m")
        rows[split] = {"mADE_m": mine, "held_out_mADE_m": held}
    print(f"in sample (model trained on {recording}, scored there; optimistic): hybrid mADE "
          + ", ".join(f"{k} {_f(v['mADE_m'])} (held out {_f(v['held_out_mADE_m'])})" for k, v in rows.items()), flush=True)
    return {"model": model, "eval_json": path, "hybrid": rows}


if __name__ == "__main__":
    raise SystemExit(main())
