#!/usr/bin/env python3
"""Two versions of the code under one benchmark, run in turn: paired differences that the host's drift cancels out of.

    python bench/ab.py --base REV [--rounds 4] --metric KEY [--metric KEY ...] [--json OUT] -- COMMAND ... {json} ...

On these shared machines a figure moves by 25-60 % with the host's state over
hours (docs/performance.md), more than most changes of the code. Comparing two
runs made an hour apart compares hosts; this runs the two versions side by
side instead: ``base`` is git revision REV, checked out into a temporary
worktree (removed at the end); ``head`` is this working tree as it is,
uncommitted changes included. Each round runs COMMAND once per version, in
the order base, head in even rounds and head, base in odd ones (ABBA, so that
a steady drift does not favour either), each in its version's root folder
with ``PYTHONPATH`` set to it (so ``stages``, ``bus_schemas`` and ``testkit``
import from that version, not from the editable install), ``{json}`` in
COMMAND replaced by a fresh file that COMMAND is to write its JSON report to.
The program (COMMAND's first word, e.g. ``.venv/bin/python``) is looked up
from where ab.py starts, the same for both; its relative arguments (such as
``bench/dense.py``) are each version's own.

Each ``--metric`` is a dotted path into that JSON (``modes.hybrid.by_vehicles.18.stages.markov_prediction.ms_median``:
each part a key, or an index into a list). Printed per run, then per metric:
base and head (mean and the values), the paired difference head - base per
round, its mean with a 95 % interval from resampling the rounds (2000 draws,
seeded), and head / base. ``--json OUT`` writes the same. Asserts nothing:
an interval that excludes 0 says the difference stood out from this run's
rounds, no more (another day's host may differ).

A command that fails stops the comparison (exit 1, its output's tail
printed); a bad revision, a metric the report does not hold or a COMMAND
without ``{json}``: a message and exit 2. Numba's on-disk cache lives beside
the sources, so the base worktree compiles its kernels on its first run (in
the benches' warm-up, which they do not time).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
PLACEHOLDER = "{json}"
DRAWS = 2000


def _git(*args: str, cwd: Path = REPO) -> subprocess.CompletedProcess:
    return subprocess.run(["git", *args], cwd=cwd, capture_output=True, text=True)


def lookup(report: Any, path: str) -> float:
    """The number at the dotted ``path`` of ``report``; KeyError naming the first part that is missing."""
    node = report
    for part in path.split("."):
        if isinstance(node, dict) and part in node:
            node = node[part]
        elif isinstance(node, list) and part.lstrip("-").isdigit() and -len(node) <= int(part) < len(node):
            node = node[int(part)]
        else:
            raise KeyError(f"{path}: no {part!r} there" + (f" (keys: {', '.join(map(str, list(node)[:12]))})" if isinstance(node, dict) else ""))
    if isinstance(node, bool) or not isinstance(node, (int, float)):
        raise KeyError(f"{path}: {node!r} is not a number")
    return float(node)


def _short(metric: str) -> str:
    """The last two parts of a dotted metric path (``markov_prediction.ms_median``)."""
    return ".".join(metric.split(".")[-2:])


def interval(diffs: list[float], draws: int = DRAWS, seed: int = 0) -> tuple[float, float]:
    """95 % interval of the mean of ``diffs`` by resampling them (percentiles 2.5 and 97.5 of ``draws`` means)."""
    import numpy as np

    d = np.asarray(diffs, dtype=np.float64)
    if d.size < 2:
        return (math.nan, math.nan)
    rng = np.random.default_rng(seed)
    means = d[rng.integers(0, d.size, size=(draws, d.size))].mean(axis=1)
    return float(np.percentile(means, 2.5)), float(np.percentile(means, 97.5))


def run_once(command: list[str], root: Path, out: Path) -> tuple[dict, float]:
    """COMMAND in ``root`` with that version on PYTHONPATH; its JSON report and wall seconds."""
    env = dict(os.environ)
    env["PYTHONPATH"] = str(root) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    argv = [str(out) if a == PLACEHOLDER else a.replace(PLACEHOLDER, str(out)) for a in command]
    t0 = time.monotonic()
    try:
        r = subprocess.run(argv, cwd=root, env=env, capture_output=True, text=True)
    except OSError as exc:
        raise RuntimeError(f"{argv[0]}: cannot run it in {root}: {exc}") from None
    seconds = time.monotonic() - t0
    if r.returncode != 0:
        raise RuntimeError(f"{' '.join(argv)} in {root} exited {r.returncode}:\n{(r.stdout + r.stderr)[-3000:]}")
    try:
        return json.loads(out.read_text()), seconds
    except (OSError, ValueError) as exc:
        raise RuntimeError(f"{' '.join(argv)} in {root} wrote no JSON report to {out}: {exc}") from None


def compare(base_rev: str, command: list[str], metrics: list[str], rounds: int, say=print) -> dict:
    """The comparison of the module docstring; returns the report that ``--json`` writes."""
    found = _git("rev-parse", "--verify", "--quiet", f"{base_rev}^{{commit}}")
    if found.returncode != 0:
        raise ValueError(f"--base {base_rev!r}: not a revision of {REPO}")
    sha = found.stdout.strip()
    head = _git("rev-parse", "HEAD").stdout.strip()
    dirty = bool(_git("status", "--porcelain", "--untracked-files=no").stdout.strip())
    values: dict[str, dict[str, list[float]]] = {m: {"base": [], "head": []} for m in metrics}
    runs = []
    with tempfile.TemporaryDirectory(prefix="iamp-ab-") as tmp:
        tree = Path(tmp) / "base"
        added = _git("worktree", "add", "--detach", str(tree), sha)
        if added.returncode != 0:
            raise ValueError(f"--base {base_rev}: git worktree add failed: {added.stderr.strip()}")
        try:
            for r in range(rounds):
                order = ("base", "head") if r % 2 == 0 else ("head", "base")
                for version in order:
                    out = Path(tmp) / f"{version}{r}.json"
                    report, seconds = run_once(command, tree if version == "base" else REPO, out)
                    got = {m: lookup(report, m) for m in metrics}
                    for m, v in got.items():
                        values[m][version].append(v)
                    runs.append({"round": r, "version": version, "seconds": seconds, "metrics": got})
                    say(f"round {r} {version:4s} ({seconds:5.1f} s): " + ", ".join(f"{_short(m)} = {v:.4g}" for m, v in got.items()))
        finally:
            _git("worktree", "remove", "--force", str(tree))
            _git("worktree", "prune")
    summary = {}
    for m in metrics:
        b, h = values[m]["base"], values[m]["head"]
        diffs = [y - x for x, y in zip(b, h)]
        lo, hi = interval(diffs)
        mean_b, mean_h = sum(b) / len(b), sum(h) / len(h)
        summary[m] = {"base": b, "head": h, "diff": diffs, "base_mean": mean_b, "head_mean": mean_h,
                      "diff_mean": sum(diffs) / len(diffs), "diff_interval95": [lo, hi],
                      "ratio": mean_h / mean_b if mean_b else math.nan}
    return {"base": sha, "head": head, "head_dirty": dirty, "rounds": rounds, "command": command, "runs": runs, "metrics": summary}


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    cut = argv.index("--") if "--" in argv else len(argv)
    own, command = argv[:cut], (argv[cut + 1:] if cut < len(argv) else None)
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                usage="%(prog)s --base REV [--rounds N] --metric KEY [--metric KEY ...] [--json OUT] -- COMMAND ... {json} ...")
    p.add_argument("--base", required=True, help="git revision to compare this working tree with")
    p.add_argument("--rounds", type=int, default=4, help="rounds, each one run per version (default 4; at least 2)")
    p.add_argument("--metric", action="append", required=True, help="dotted path of a number in the command's JSON (repeatable)")
    p.add_argument("--json", type=Path, default=None, help="write the comparison here")
    args = p.parse_args(own)  # (--help: the usage, exit 0)
    if command is None:
        p.error(f"give the benchmark command after --, with {PLACEHOLDER} where it writes its report")
    if args.rounds < 2:
        p.error("--rounds must be at least 2 (the interval needs two paired rounds)")
    if not command or not any(PLACEHOLDER in a for a in command):
        p.error(f"the command after -- must contain {PLACEHOLDER} (the file it writes its JSON report to)")
    program = shutil.which(command[0])  # the same program for both versions (e.g. .venv/bin/python), found from here
    if program is None:
        p.error(f"{command[0]}: no such program")
    command = [os.path.abspath(program), *command[1:]]  # (not resolved: a venv's python is a link that must stay one)
    try:
        result = compare(args.base, command, args.metric, args.rounds)
    except ValueError as exc:
        print(f"bench/ab.py: {exc}", file=sys.stderr)
        return 2
    except KeyError as exc:
        print(f"bench/ab.py: metric {exc.args[0]}", file=sys.stderr)
        return 2
    except RuntimeError as exc:
        print(f"bench/ab.py: {exc}", file=sys.stderr)
        return 1
    print(f"\nbase {result['base'][:10]} vs head {result['head'][:10]}{' + uncommitted changes' if result['head_dirty'] else ''}, "
          f"{result['rounds']} rounds (ABBA); head - base per round, mean and 95 % interval over the rounds")
    for m, s in result["metrics"].items():
        lo, hi = s["diff_interval95"]
        print(f"{m}\n  base {s['base_mean']:.4g} ({', '.join(f'{v:.4g}' for v in s['base'])})"
              f"\n  head {s['head_mean']:.4g} ({', '.join(f'{v:.4g}' for v in s['head'])})"
              f"\n  head - base {s['diff_mean']:+.4g} [{lo:+.4g}, {hi:+.4g}], head / base {s['ratio']:.3f}")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
