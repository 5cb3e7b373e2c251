"""Run many command-line scripts' ``__main__`` in one child process and report each one's exit code and output.

``python -m testkit.script_batch < cases.json`` reads a JSON list of ``[script, [args...]]`` and prints one JSON list
of ``{"code", "stdout", "stderr"}``, one per case, in order. Each script runs as ``python SCRIPT ARGS`` would run it
(``runpy.run_path`` as ``__main__``, ``sys.argv`` set; where scripts import modules beside them, as
``python SCRIPT`` lets them, the caller puts their folder on ``PYTHONPATH``), its output captured; a ``SystemExit`` gives its code, any other
exception code 1 with its traceback in ``stderr``. For the tests of how scripts treat bad command lines, which fail
before their work: a process per case spent most of its second or two starting Python and importing numpy, torch
and the stages again.
"""

from __future__ import annotations

import contextlib
import io
import json
import runpy
import sys
import traceback


def run_case(script: str, args: list[str]) -> dict:
    out, err = io.StringIO(), io.StringIO()
    argv = sys.argv
    sys.argv = [script, *args]
    code = 0
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                runpy.run_path(script, run_name="__main__")
            except SystemExit as exc:
                code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
                if exc.code is not None and not isinstance(exc.code, int):
                    print(exc.code, file=sys.stderr)
            except BaseException:  # noqa: BLE001 - reported as the script's traceback
                traceback.print_exc()
                code = 1
    finally:
        sys.argv = argv
    return {"code": code, "stdout": out.getvalue(), "stderr": err.getvalue()}


def main() -> int:
    cases = json.load(sys.stdin)
    results = [run_case(script, list(args)) for script, args in cases]
    sys.stdout.write(json.dumps(results))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
