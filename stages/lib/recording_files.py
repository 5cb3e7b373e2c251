"""Names of recording files: the default path of a run and its split files (``run.mcap``, ``run.001.mcap``, ...).

Shared by the recorder (which writes them) and the launcher (which restarts a
killed recorder into the next split); plain paths, no MCAP.
"""

from __future__ import annotations

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
