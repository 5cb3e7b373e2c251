"""The embedded default scenario: TAF-BW K729, sequence 013 (see stages/data/taf-bw/ATTRIBUTION.md)."""

from __future__ import annotations

from pathlib import Path

DEFAULT_DATA_DIR = Path(__file__).resolve().parents[2] / "data" / "taf-bw"
"""``stages/data/taf-bw`` of the repository, resolved from this package's location."""

DEFAULT_RECORDING = "k729_2022-03-16"
DEFAULT_SEQUENCE = "013"
