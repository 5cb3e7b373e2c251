"""The embedded data: TAF-BW K729 (default recording, sequence 013) and K733 (the launcher's busy default run); see stages/data/taf-bw/ATTRIBUTION.md."""

from __future__ import annotations

from pathlib import Path

DEFAULT_DATA_DIR = Path(__file__).resolve().parents[2] / "data" / "taf-bw"
"""``stages/data/taf-bw`` of the repository, resolved from this package's location."""

FULL_DATA_ENV = "IAMP_TAF_BW"
"""Environment variable naming a folder of the full TAF-BW recordings (laid out like ``stages/data/taf-bw``):
tests and bench scripts use it when set, and skip or fall back to the embedded scenario when not."""


def full_data_dir() -> Path | None:
    """The folder ``$IAMP_TAF_BW`` names, if it holds recordings; else None."""
    import os

    value = os.environ.get(FULL_DATA_ENV, "")
    path = Path(value).expanduser().resolve() if value else None
    return path if path is not None and (path / "recorded_trackfiles").is_dir() else None


DEFAULT_RECORDING = "k729_2022-03-16"
DEFAULT_SEQUENCE = "013"


def default_recordings(data_dir: str | Path, discovered: list[str]) -> list[str]:
    """The recordings an offline tool reads when none is named: in the embedded folder the default one (K729; K733 is
    embedded for the launcher's default run only), in any other folder all of ``discovered``."""
    if Path(data_dir).expanduser().resolve() == DEFAULT_DATA_DIR.resolve() and DEFAULT_RECORDING in discovered:
        return [DEFAULT_RECORDING]
    return list(discovered)
