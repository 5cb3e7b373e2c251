"""Traffic-signal state of every signal group at one stamp (``iamp.SignalState``).

Signal states follow SAE J2735 ``MovementPhaseState``, reduced to what a
driver sees: ``SignalPhase``. A dataset's signal-phase file (TAF-BW
``signal_phases_NNN.csv``) and a live traffic-light feed publish the same
message.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import Any, Annotated, ClassVar

import numpy as np

from ._wire import Array, Message, Range, register
from .common import HEADER_WALL_UPGRADE, NON_NEG_INT, Header


class SignalPhase(enum.IntEnum):
    """What a signal group shows. ``RED_AMBER`` (J2735 PRE_MOVEMENT) counts as red for a driver."""

    UNKNOWN = 0
    RED = 1  # STOP_AND_REMAIN (also STOP_THEN_PROCEED)
    RED_AMBER = 2  # PRE_MOVEMENT
    GREEN = 3  # PERMISSIVE_/PROTECTED_MOVEMENT_ALLOWED
    AMBER = 4  # PERMISSIVE_/PROTECTED_CLEARANCE, CAUTION_CONFLICTING_TRAFFIC
    DARK = 5  # signal off

    @property
    def means_stop(self) -> bool:
        """Red, red-amber or amber: a driver who can still stop stops."""
        return self in (SignalPhase.RED, SignalPhase.RED_AMBER, SignalPhase.AMBER)

    @property
    def summary(self) -> str:
        """``red`` (red and red-amber), ``amber``, ``green`` or ``unknown`` (unknown and dark)."""
        if self in (SignalPhase.RED, SignalPhase.RED_AMBER):
            return "red"
        if self is SignalPhase.AMBER:
            return "amber"
        if self is SignalPhase.GREEN:
            return "green"
        return "unknown"


J2735_NAMES: dict[str, SignalPhase] = {
    "UNAVAILABLE": SignalPhase.UNKNOWN,
    "DARK": SignalPhase.DARK,
    "STOP_THEN_PROCEED": SignalPhase.RED,
    "STOP_AND_REMAIN": SignalPhase.RED,
    "PRE_MOVEMENT": SignalPhase.RED_AMBER,
    "PERMISSIVE_MOVEMENT_ALLOWED": SignalPhase.GREEN,
    "PROTECTED_MOVEMENT_ALLOWED": SignalPhase.GREEN,
    "PERMISSIVE_CLEARANCE": SignalPhase.AMBER,
    "PROTECTED_CLEARANCE": SignalPhase.AMBER,
    "CAUTION_CONFLICTING_TRAFFIC": SignalPhase.AMBER,
}
"""J2735 ``MovementPhaseState`` names (upper case, as TAF-BW writes them) -> ``SignalPhase``."""

N_GROUPS = ("g",)
PHASE_VALUES = Range(0, max(int(p) for p in SignalPhase))
HELD_S = Range(0.0, 1.0e6, nan=True, unit="s")


@register
@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class SignalState(Message):
    """The state of every signal group at ``header.stamp_ns``, column-wise (arrays ``(g,)``).

    ``group_ids`` are the signal groups of the junction(s) of the scene
    (``scene_id``); ``phases`` their ``SignalPhase`` values; ``held_s`` how
    long each has shown its phase (NaN: not known, e.g. since before the
    recording started). Ranges (``ROWS = "g"``: a group with a value out of
    range is dropped, recorded): group ids >= 0, phases 0..5, held 0..1e6 s.
    """

    SCHEMA: ClassVar[str] = "iamp.SignalState"
    VERSION: ClassVar[int] = 2  # v2: Header.source_wall_ns
    UPGRADES: ClassVar[dict[int, Any]] = {1: HEADER_WALL_UPGRADE}  # v1 reads as v2 with source_wall_ns 0 (unknown)
    # 17 B per group + ~150 B: a junction has tens of groups (TAF-BW K733: 36, measured 0.8 kB)
    MAX_BYTES: ClassVar[int] = 256 * 1024
    ROWS: ClassVar[str] = "g"

    header: Header
    scene_id: str
    group_ids: Annotated[np.ndarray, Array("int64", N_GROUPS), NON_NEG_INT]
    phases: Annotated[np.ndarray, Array("uint8", N_GROUPS), PHASE_VALUES]
    held_s: Annotated[np.ndarray, Array("float64", N_GROUPS), HELD_S]

    def __len__(self) -> int:
        return int(self.group_ids.shape[0])

    def phase_of(self, group_id: int) -> tuple[SignalPhase, float]:
        """(phase, held_s) of one group; (UNKNOWN, NaN) when the message does not carry it."""
        hit = np.flatnonzero(self.group_ids == int(group_id))
        if hit.size == 0:
            return SignalPhase.UNKNOWN, float("nan")
        i = int(hit[0])
        return SignalPhase(int(self.phases[i])), float(self.held_s[i])
