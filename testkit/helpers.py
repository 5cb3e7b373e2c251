"""Shared helpers for tests that run real processes on a real (loopback) Zenoh bus.

Nothing here sleeps for a fixed time: waits poll a condition until a
deadline and fail with a message that says what was awaited.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any, Callable, Iterable, TypeVar

REPO = Path(__file__).resolve().parents[1]
LOG_DIR_ENV = "IAMP_TEST_LOG_DIR"
"""Where ``start_module`` writes its processes' logs when the caller names no folder; ``tests/conftest.py`` sets it to a
folder of pytest's temporary directory (pytest keeps the last three runs' and removes older ones). Unset: the system's
temporary folder."""
T = TypeVar("T")


def free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago (bind to port 0, read it, release it)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def endpoint(port: int) -> str:
    return f"tcp/127.0.0.1:{port}"


def wait_until(predicate: Callable[[], T], timeout_s: float, what: str, interval_s: float = 0.02) -> T:
    """Poll ``predicate`` until it returns something truthy and return that; fail after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() >= deadline:
            raise AssertionError(f"timed out after {timeout_s:.1f} s waiting for {what}")
        time.sleep(interval_s)


class AliveSet:
    """Node ids whose liveliness tokens match ``pattern``, kept current by a liveliness subscriber."""

    def __init__(self, bus: Any, pattern: str) -> None:
        self._lock = threading.Lock()
        self._alive: set[str] = set()
        bus.watch_alive(pattern, self._on_change)

    def _on_change(self, node_id: str, alive: bool) -> None:
        with self._lock:
            (self._alive.add if alive else self._alive.discard)(node_id)

    def __contains__(self, node_id: str) -> bool:
        with self._lock:
            return node_id in self._alive

    def snapshot(self) -> set[str]:
        with self._lock:
            return set(self._alive)

    def wait_for(self, node_ids: Iterable[str], timeout_s: float = 20.0) -> None:
        want = set(node_ids)
        wait_until(lambda: want <= self.snapshot(), timeout_s, f"liveliness of {sorted(want)} (alive: {sorted(self.snapshot())})")


def wait_alive(bus: Any, pattern: str, node_ids: Iterable[str], timeout_s: float = 20.0) -> None:
    """Wait until every node id in ``node_ids`` has a liveliness token matching ``pattern``."""
    AliveSet(bus, pattern).wait_for(node_ids, timeout_s)


def python_env() -> dict[str, str]:
    """The environment for child Python processes: this interpreter's, with the repository importable."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), *[p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p]])
    env["PYTHONUNBUFFERED"] = "1"
    return env


def default_log_dir() -> Path | None:
    """The folder named by ``IAMP_TEST_LOG_DIR`` (created if missing), or None (the system's temporary folder)."""
    named = os.environ.get(LOG_DIR_ENV)
    if not named:
        return None
    path = Path(named)
    path.mkdir(parents=True, exist_ok=True)
    return path


def start_module(module: str, *args: str, log_dir: Path | None = None) -> subprocess.Popen:
    """Start ``python -m module args...`` in the repository root; output goes to a log file.

    The returned process has ``log_path`` (its combined stdout/stderr).
    """
    fd, log_path = tempfile.mkstemp(prefix=f"{module.rsplit('.', 1)[-1]}-", suffix=".log", dir=log_dir or default_log_dir())
    with os.fdopen(fd, "wb") as log_file:
        proc = subprocess.Popen([sys.executable, "-m", module, *args], cwd=REPO, env=python_env(), stdout=log_file, stderr=subprocess.STDOUT)
    proc.log_path = log_path  # type: ignore[attr-defined]
    return proc


def output_of(proc: subprocess.Popen) -> str:
    """What a process started by ``start_module`` has written so far."""
    try:
        return Path(proc.log_path).read_text(errors="replace")  # type: ignore[attr-defined]
    except OSError:
        return ""


def stop_process(proc: subprocess.Popen, sig: int = signal.SIGINT, timeout_s: float = 20.0) -> int:
    """Send ``sig`` and wait for the exit code; SIGKILL (and fail) if it does not exit in time."""
    if proc.poll() is None:
        proc.send_signal(sig)
        try:
            proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
            raise AssertionError(f"process {proc.args} did not exit {timeout_s:.0f} s after signal {sig}:\n{output_of(proc)[-3000:]}")
    return proc.returncode


def kill_all(procs: Iterable[subprocess.Popen], grace_s: float = 10.0) -> None:
    """Teardown: stop whatever is still running of ``procs`` (only processes the test started): SIGTERM, then SIGKILL
    after ``grace_s``. A launcher killed outright left its nodes running (they live in their own sessions): a failed
    test's recorders were found still running ten minutes later."""
    procs = [p for p in procs if p.poll() is None]
    for proc in procs:
        proc.terminate()
    deadline = time.monotonic() + grace_s
    for proc in procs:
        try:
            proc.wait(timeout=max(deadline - time.monotonic(), 0.1))
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def all_command_lines() -> list[str]:
    """The command line of every process on the machine (to check that no secret is on one)."""
    out = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                out.append((entry / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace"))
            except OSError:
                pass
    return out


class RecordingPublisher:
    """Stands in for a zenoh publisher in in-process Node tests: keeps every payload put."""

    def __init__(self) -> None:
        self.sent: list[bytes] = []

    def put(self, data: bytes) -> None:
        self.sent.append(data)
