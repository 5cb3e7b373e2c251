"""Situations of ``iamp eval --situations FILE.toml``: named time windows of recordings, as the paper's Table I.

A situation is a time window of one recording (optionally of one of its
sequences) with a description; the evaluation reports, per situation and
mode, its windows, mADE, mFDE and the time per prediction step, and the
number of vehicles seen and the duration played in it. The file::

    [[situation]]
    name = "A"                      # optional; default the recording, then the window
    recording = "k729_2022-03-16"   # required
    sequence = "003"                # optional; default every sequence of the recording
    start = 0.0                     # s of sequence time (the files' timestamp_ms), optional: default the start
    end = 30.0                      # s, optional: default the end
    description = "queue at the signal, then discharge"

Without the file every recording is one situation (named after it, whole).
Windows count in a situation when their instant lies in [start, end].
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass
from pathlib import Path

from stages.lib.datasets.model import same_sequence_id

_KEYS = {"name", "recording", "sequence", "start", "end", "description"}


@dataclass(frozen=True, slots=True)
class Situation:
    name: str
    recording: str
    sequence: str = ""  # "": every sequence
    start_s: float = 0.0
    end_s: float = math.inf
    description: str = ""

    def contains(self, recording: str, sequence: str, stamp_ns: int) -> bool:
        if recording != self.recording or (self.sequence and not same_sequence_id(sequence, self.sequence)):
            return False
        return self.start_s - 1e-6 <= stamp_ns * 1e-9 <= self.end_s + 1e-6

    def window_text(self) -> str:
        seq = f"sequence {self.sequence}" if self.sequence else "all sequences"
        if self.start_s <= 0 and math.isinf(self.end_s):
            return f"{seq}, whole"
        end = "end" if math.isinf(self.end_s) else f"{self.end_s:g} s"
        return f"{seq}, {self.start_s:g} s to {end}"

    def as_dict(self) -> dict:
        return {"name": self.name, "recording": self.recording, "sequence": self.sequence or None, "start_s": self.start_s,
                "end_s": None if math.isinf(self.end_s) else self.end_s, "description": self.description}


def whole_recordings(recordings) -> tuple[Situation, ...]:
    """One situation per recording (the default)."""
    return tuple(Situation(name=r, recording=r, description=f"recording {r}, every sequence") for r in recordings)


def load_situations(path: Path) -> tuple[Situation, ...]:
    """Read a situations file; a malformed one raises ValueError naming the entry and what to fix."""
    try:
        data = tomllib.loads(Path(path).read_text())
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise ValueError(f"--situations {path}: {exc}") from exc
    entries = data.get("situation")
    if not isinstance(entries, list) or not entries:
        raise ValueError(f"--situations {path}: expected one or more [[situation]] tables")
    out, names = [], set()
    for i, e in enumerate(entries):
        where = f"--situations {path}: situation {i + 1}"
        if not isinstance(e, dict):
            raise ValueError(f"{where}: expected a [[situation]] table with keys {sorted(_KEYS)}, got {type(e).__name__} {e!r}")
        unknown = set(e) - _KEYS
        if unknown:
            raise ValueError(f"{where}: unknown keys {sorted(unknown)}; expected {sorted(_KEYS)}")
        if not isinstance(e.get("recording"), str) or not e["recording"]:
            raise ValueError(f"{where}: 'recording' (a recording name) is required")
        try:
            start = float(e.get("start", 0.0))
            end = float(e.get("end", math.inf))
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{where}: start/end must be seconds: {exc}") from exc
        if not (math.isfinite(start) and end > start):
            raise ValueError(f"{where}: need a finite start and end > start (got {start}, {end})")
        seq = str(e.get("sequence", ""))
        name = str(e.get("name") or (f"{e['recording']}" + (f"/{seq}" if seq else "") + (f" {start:g}-{end:g} s" if "end" in e or "start" in e else "")))
        if name in names:
            raise ValueError(f"{where}: name {name!r} used twice")
        names.add(name)
        out.append(Situation(name=name, recording=e["recording"], sequence=seq, start_s=start, end_s=end,
                             description=str(e.get("description", ""))))
    return tuple(out)


__all__ = ["Situation", "load_situations", "whole_recordings"]
