"""What every stage core shares: issues, results and config parsing.

Pure: no zenoh, no msgpack, no wall clock. Cores return ``StageResult``; the
runtime publishes the outputs and logs and counts the issues.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import math
import os
import tempfile
import types
import typing
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import numpy as np


@dataclass(frozen=True, slots=True)
class Issue:
    """One agent (or input) a core could not handle; the others still were.

    ``kind`` is a short snake_case category that the runtime counts by
    (``nan_state``, ``off_map``, ``unknown_type`` ...); ``agent_id`` is the
    track id or -1 when the issue concerns no single agent.
    """

    kind: str
    agent_id: int
    detail: str


@dataclass(slots=True)
class StageResult:
    """Outputs of one core update, keyed by output port name, plus issues.

    An output missing from ``outputs`` is simply not published this time.
    """

    outputs: dict[str, Any] = field(default_factory=dict)
    issues: list[Issue] = field(default_factory=list)


class ConfigError(ValueError):
    """A pipeline parameter that is unknown or of the wrong type."""


def check_output(path: str | Path | None, flag: str, *, folder: bool = False) -> None:
    """Before a long run: that ``path`` (a file, or with ``folder`` a folder) can be written, so that a bad output
    flag fails at once and not after the work, which it would lose. Creates the folder the file goes in (``folder``:
    the folder itself) and raises ``ConfigError`` naming ``flag`` where it cannot, where the folder is not writable (a
    temporary file is made in it and removed), where the file exists and is not writable, or where a file is to be
    written over a folder. None: nothing to check."""
    if path is None:
        return
    path = Path(path)
    target = path if folder else path.parent
    if folder and path.exists() and not path.is_dir():
        raise ConfigError(f"{flag} {path}: is a file, not a folder")
    try:
        target.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ConfigError(f"{flag} {path}: cannot create the folder {target} ({exc.strerror or exc})") from None
    if not target.is_dir():
        raise ConfigError(f"{flag} {path}: {target} is not a folder")
    if not folder and path.is_dir():
        raise ConfigError(f"{flag} {path}: is a folder; expected a file name")
    if not os.access(target, os.W_OK | os.X_OK):
        raise ConfigError(f"{flag} {path}: the folder {target} is not writable")
    if not folder and path.exists() and not os.access(path, os.W_OK):
        raise ConfigError(f"{flag} {path}: the file exists and is not writable")
    try:  # what os.access cannot tell (a read-only or special file system such as /sys, root's rights): a real file
        with tempfile.TemporaryFile(dir=target):
            pass
    except OSError as exc:
        raise ConfigError(f"{flag} {path}: cannot write in the folder {target} ({exc.strerror or exc})") from None


def check_output_arg(parser: "argparse.ArgumentParser", path: str | Path | None, flag: str, *, folder: bool = False) -> None:
    """``check_output`` for a script's parsed argument: its failure is the parser's usage error (message, exit 2)."""
    try:
        check_output(path, flag, folder=folder)
    except ConfigError as exc:
        parser.error(str(exc))


@contextlib.contextmanager
def atomic_write(path: str | Path) -> typing.Iterator[typing.BinaryIO]:
    """A binary file handle whose contents become ``path`` only when the block ends without an exception: written to
    a file of its own beside ``path`` (folders created; the permissions of any new file), flushed to disk, then
    renamed over ``path``. Two writers of one path at once (two trainings building one cached data set) each write
    their own file and the last rename wins; a reader never sees half a file; a failure leaves ``path`` as it was and
    no temporary file behind."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f"{path.name}.{os.getpid()}.{uuid.uuid4().hex[:12]}.tmp")
    try:
        with open(tmp, "xb") as handle:
            yield handle
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def _type_ok(value: Any, tp: Any) -> tuple[bool, Any]:
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        for a in typing.get_args(tp):
            ok, v = _type_ok(value, a)
            if ok:
                return True, v
        return False, value
    if tp is type(None):
        return value is None, value
    if tp is Any:
        return True, value
    if origin is typing.Literal:
        return value in typing.get_args(tp), value
    if origin in (tuple, list):
        if not isinstance(value, (list, tuple)):
            return False, value
        args = typing.get_args(tp)
        elem = args[0] if args else Any
        out = []
        for v in value:
            ok, vv = _type_ok(v, elem)
            if not ok:
                return False, value
            out.append(vv)
        return True, tuple(out) if origin is tuple else out
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            return False, value
        return True, float(value)
    if tp is int:
        return (type(value) is int), value
    if tp is bool:
        return (type(value) is bool), value
    if tp is str:
        return isinstance(value, str), value
    if isinstance(tp, type):
        return isinstance(value, tp), value
    return True, value


def _type_name(tp: Any) -> str:
    return getattr(tp, "__name__", None) or str(tp).replace("typing.", "")


def config_from_params(cls: type, params: Mapping[str, Any] | None, where: str):
    """Build a frozen config dataclass from a parameter mapping.

    Rejects unknown keys and wrong types with a ``ConfigError`` whose message
    names ``where`` (file and node) and lists the known keys.
    """
    params = dict(params or {})
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    unknown = sorted(k for k in params if k not in fields)
    if unknown:
        raise ConfigError(
            f"{where}: unknown parameter(s) {', '.join(unknown)}; known: {', '.join(sorted(fields)) or '(none)'}"
        )
    kwargs = {}
    for k, v in params.items():
        ok, vv = _type_ok(v, hints[k])
        if not ok:
            raise ConfigError(f"{where}: parameter {k} = {v!r} should be {_type_name(hints[k])}")
        kwargs[k] = vv
    try:
        return cls(**kwargs)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{where}: {exc}") from None


def check_ranges(config: Any, *, positive: tuple[str, ...] = (), non_negative: tuple[str, ...] = ()) -> None:
    """Raise ``ValueError`` naming the field when a number is not finite and > 0 (or >= 0)."""
    for name in positive:
        value = getattr(config, name)
        if not (math.isfinite(value) and value > 0.0):
            raise ValueError(f"{name} = {value!r}: must be > 0")
    for name in non_negative:
        value = getattr(config, name)
        if not (math.isfinite(value) and value >= 0.0):
            raise ValueError(f"{name} = {value!r}: must be >= 0")


class ConfigMixin:
    """Gives a config dataclass ``from_params(mapping, where)``."""

    @classmethod
    def from_params(cls, params: Mapping[str, Any] | None = None, where: str = "params"):
        return config_from_params(cls, params, where)


def isolate(indices: "typing.Iterable[int]", attempt: "typing.Callable[[list[int]], Any]") -> tuple[Any, list[tuple[int, Exception]]]:
    """``attempt(indices)``; when it raises, the indices it raises on alone are found by bisection and left out.

    Returns the result of ``attempt`` on the indices that remain and the
    ``(index, exception)`` of those left out, so that one object's failure
    does not cost a core the rest of its batch. Without a failure this is one
    call of ``attempt``. Indices that raise only together (every half passes)
    are all left out. An ``attempt`` that raises on no index at all (an
    empty batch) is not an object's failure: that exception propagates.
    """
    todo = sorted(indices)
    failed: list[tuple[int, Exception]] = []
    while True:
        try:
            return attempt(todo), failed
        except Exception as exc:  # noqa: BLE001 - any failure of one object is isolated
            if not todo:
                raise
            culprits = _culprits(todo, attempt, exc) or [(i, exc) for i in todo]
            failed.extend(culprits)
            gone = {i for i, _ in culprits}
            todo = [i for i in todo if i not in gone]


def _culprits(group: list[int], attempt, exc: Exception) -> list[tuple[int, Exception]]:
    """The members of ``group`` (on which ``attempt`` raised ``exc``) that make it raise, by bisection."""
    if len(group) == 1:
        return [(group[0], exc)]
    out = []
    middle = len(group) // 2
    for half in (group[:middle], group[middle:]):
        try:
            attempt(half)
        except Exception as sub:  # noqa: BLE001
            out.extend(_culprits(half, attempt, sub))
    return out


class _NoBar:
    """What ``progress_bar`` returns when disabled: the tqdm methods the tools call, doing nothing."""

    def update(self, n: int = 1) -> None:
        pass

    def set_postfix(self, **kwargs: Any) -> None:
        pass

    def close(self) -> None:
        pass


def progress_bar(total: int, enabled: bool, *, unit: str, desc: str):
    """A tqdm bar on stderr (``iamp eval``, ``iamp train``), or a silent stand-in."""
    if not enabled:
        return _NoBar()
    import sys

    from tqdm import tqdm

    return tqdm(total=total, unit=unit, desc=desc, file=sys.stderr, dynamic_ncols=True)


def json_safe(value: Any) -> Any:
    """``value`` as strict JSON: NaN/inf become null, numpy scalars and arrays plain numbers and lists, paths strings."""
    if isinstance(value, dict):
        return {str(k): json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    if isinstance(value, np.ndarray):
        return json_safe(value.tolist())
    if isinstance(value, (np.floating, float)):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, Path):
        return str(value)
    return value
