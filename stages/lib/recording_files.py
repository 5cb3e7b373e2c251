"""Names of recording files: the default path of a run and its split files (``run.mcap``, ``run.001.mcap``, ...).

Shared by the recorder (which writes them) and the launcher (which restarts a
killed recorder into the next split); plain paths, no MCAP. ``put_in_place``:
a file written under a temporary name (``iamp recover``, ``iamp export``)
moved to its own name with the permissions of a newly created file.
"""

from __future__ import annotations

import os
import re
import time
from datetime import datetime, timezone
from pathlib import Path


def default_path(run_id: str, now_ns: int | None = None) -> Path:
    """``runs/<run>-<UTC yyyymmdd-hhmmss>.mcap`` under the current directory."""
    now = datetime.fromtimestamp((now_ns if now_ns is not None else time.time_ns()) / 1e9, tz=timezone.utc)
    return Path("runs") / f"{run_id}-{now.strftime('%Y%m%d-%H%M%S')}.mcap"


def split_path(base: str | Path, index: int) -> Path:
    """The file of split ``index`` of a recording: 0 is ``base`` (``run.mcap``), then ``run.001.mcap``, ``run.002.mcap``, ..."""
    base = Path(base)
    if index == 0:
        return base
    suffix = base.suffix or ".mcap"
    return base.with_name(f"{base.stem if base.suffix else base.name}.{index:03d}{suffix}")


def split_paths(base: str | Path, since_s: float | None = None) -> list[tuple[int, Path]]:
    """The splits of ``base`` on disk as ``(index, path)``, by index; with ``since_s`` only files modified since then (epoch s)."""
    base = Path(base)
    stem, suffix = (base.stem, base.suffix) if base.suffix else (base.name, ".mcap")
    rx = re.compile(re.escape(stem) + r"\.(\d{3,})" + re.escape(suffix) + "$")
    found = [(0, base)] if base.is_file() else []
    if base.parent.is_dir():
        for p in base.parent.iterdir():
            m = rx.match(p.name)
            if m and int(m.group(1)) > 0 and p.is_file():
                found.append((int(m.group(1)), p))
    if since_s is not None:
        found = [(i, p) for i, p in found if p.stat().st_mtime >= since_s]
    return sorted(found)


def put_in_place(tmp: str | Path, dst: str | Path) -> None:
    """Move ``tmp`` (made by ``tempfile.mkstemp``: mode 0600) onto ``dst`` with the mode a file created there would have
    (0666 less the process's umask, as the recorder's own files), so that a recovered or exported recording is as
    readable as the recording it came from."""
    mask = os.umask(0)
    os.umask(mask)
    os.chmod(tmp, 0o666 & ~mask)
    os.replace(tmp, dst)
