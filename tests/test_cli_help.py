"""Every command's ``--help`` prints: argparse %-formats each help string (``%(default)s``), so a bare ``%`` in one
("the 90 % region") made ``iamp --help`` end in a TypeError traceback instead of the list of commands."""

from __future__ import annotations

import argparse
import ast
import re
from pathlib import Path

import pytest

from stages import cli

REPO = Path(__file__).resolve().parents[1]
# what argparse may put into a help string's %-formatting: "%%" and the action's attributes as "%(name)s"
# (``HelpFormatter._expand_help``). Any other "%" is a conversion: with one, the help prints garbage ("90 % region"
# formats the action's attributes in place of "% r"), with two it raises
_ALLOWED = re.compile(r"%%|%\((prog|default|type|choices|metavar|dest|const|nargs|required|option_strings)\)[sdr]")


def bare_percent(text: str) -> bool:
    """Whether ``text``, a help string, has a "%" argparse would read as a conversion of its own."""
    return "%" in _ALLOWED.sub("", text)


def _parsers(parser: argparse.ArgumentParser, path: tuple[str, ...] = ("iamp",)):
    """``parser`` and every subparser under it, with the words that reach each."""
    yield path, parser
    for action in parser._actions:  # noqa: SLF001 - argparse keeps its subparsers only there
        if isinstance(action, argparse._SubParsersAction):  # noqa: SLF001
            for name, sub in action.choices.items():
                yield from _parsers(sub, (*path, name))


def test_iamp_help_and_every_subcommands_help_print(capsys):
    parser = cli.build_parser()
    seen = []
    for path, p in _parsers(parser):
        text = p.format_help()  # raises on a help string argparse cannot format
        assert p.prog.split()[0] == "iamp" and text.startswith("usage:"), path
        seen.append(" ".join(path))
    assert {"iamp", "iamp eval", "iamp calibrate", "iamp data superimpose", "iamp export foxglove"} <= set(seen)
    assert cli.main(["--help"]) == 0
    out = capsys.readouterr().out
    assert "calibrate" in out and "90 % region" in out


def _help_strings(tree: ast.AST):
    """(line, text) of every ``help=`` keyword given a string literal (an f-string's literal parts, its fields as 'X')."""
    for node in ast.walk(tree):
        if not isinstance(node, ast.Call):
            continue
        for kw in node.keywords:
            if kw.arg != "help":
                continue
            if isinstance(kw.value, ast.Constant) and isinstance(kw.value.value, str):
                yield kw.value.lineno, kw.value.value
            elif isinstance(kw.value, ast.JoinedStr):
                yield kw.value.lineno, "".join(v.value if isinstance(v, ast.Constant) else "X" for v in kw.value.values)


def test_no_help_string_in_the_project_has_a_bare_percent():
    files = [REPO / "launch.py", *sorted((REPO / "stages").rglob("*.py")), *sorted((REPO / "bench").rglob("*.py"))]
    bad = []
    checked = 0
    for path in files:
        for line, text in _help_strings(ast.parse(path.read_text(), filename=str(path))):
            checked += 1
            if bare_percent(text):
                bad.append(f"{path.relative_to(REPO)}:{line}: {text!r} (write %% for a percent sign)")
    assert checked > 100  # the walk found the project's help strings
    assert not bad, "\n".join(bad)


@pytest.mark.parametrize("text, bare", [("the 90 % region", True), ("100%", True), ("90 %% of windows", False),
                                        ("(default %(default)s)", False), ("%(prog)s runs", False), ("%d cells", True)])
def test_the_check_tells_a_bare_percent_from_argparse_s_own(text, bare):
    assert bare_percent(text) is bare


@pytest.mark.parametrize("words", [["--help"], ["inspect", "--help"], ["frobnicate"]])
def test_a_command_builds_only_its_own_options_so_iamp_starts_without_the_evaluation(words):
    """`iamp eval`'s options came from the evaluation module (the stage cores, scipy, numba): building every command's
    options on every start cost `iamp --help` and `iamp inspect` ~2 s each. Each command now builds only its own."""
    import json
    import subprocess
    import sys

    code = ("import json, sys; from stages import cli; rc = cli.main(json.loads(sys.argv[1])); "
            "print(json.dumps([rc, [m for m in ('stages.offline.evaluation', 'stages.markov_prediction', 'scipy', 'torch') if m in sys.modules]]))")
    done = subprocess.run([sys.executable, "-c", code, json.dumps(words)], cwd=REPO, capture_output=True, text=True, timeout=120)
    rc, heavy = json.loads(done.stdout.strip().splitlines()[-1])
    assert rc == (2 if words == ["frobnicate"] else 0), done.stderr
    assert heavy == [], f"iamp {' '.join(words)} imported {heavy}"


def test_each_command_still_builds_its_options_when_chosen():
    for name in ("record", "replay", "inspect", "recover", "export", "eval", "calibrate", "train", "signals", "data"):
        parser = cli.build_parser(name)
        chosen = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices  # noqa: SLF001
        assert len(chosen[name]._actions) > 1, name  # noqa: SLF001 - more than its -h
        others = [n for n in chosen if n != name]
        assert all(len(chosen[n]._actions) == 1 for n in others), name  # noqa: SLF001 - the others: -h only


def test_recording_and_sequence_take_one_or_more_values_and_repeat_in_every_tool():
    """`iamp train --sequence 002 --sequence 019` kept only 019, `iamp eval --sequence 002 019` was an error: each
    tool took one of the two forms. Every tool takes both, and keeps every value."""
    for tool in ("eval", "calibrate", "train"):
        required = ["--out", "x.json"] if tool == "calibrate" else []
        args = cli.build_parser(tool).parse_args([tool, *required, "--sequence", "002", "019", "--sequence", "003", "--recording", "a", "--recording", "b", "c"])
        assert args.sequence == ["002", "019", "003"] and args.recording == ["a", "b", "c"], tool
