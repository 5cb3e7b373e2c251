"""``ViewerConfig``: every parameter of the viewer stage, with units and defaults."""

from __future__ import annotations

import math
from dataclasses import dataclass

from stages._core import ConfigMixin

GRID_SCALES = ("log", "linear")


@dataclass(frozen=True, kw_only=True)
class ViewerConfig(ConfigMixin):
    """Parameters of the viewer stage (package docstring)."""

    host: str = "127.0.0.1"
    port: int = 8080  # 0: a free port
    max_render_hz: float = 10.0
    history_s: float = 20.0
    horizon_s: float = 4.0  # ground-truth future shown (the prediction horizon)
    max_lag_s: float = 15.0  # results later than this (in stamp time): the newest frame shows without them
    step_s: float = 1.0  # the grid step shown at start
    blend_steps: bool = False
    show_ground_truth: bool = False
    grid_scale: str = "log"
    grid_floor: float = 1e-3  # occupancy below this is transparent
    stats: bool = True  # show the NodeStats of every node of the run
    status_hz: float = 2.0  # side panel refresh

    def __post_init__(self) -> None:
        if not self.host.strip():
            raise ValueError("host must not be empty (127.0.0.1 keeps the viewer on this machine)")
        if not 0 <= self.port <= 65535:
            raise ValueError(f"port = {self.port}: expected 0 (a free port) to 65535")
        for name in ("max_render_hz", "history_s", "horizon_s", "max_lag_s", "step_s", "status_hz"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f"{name} = {value!r}: must be > 0")
        if self.grid_scale not in GRID_SCALES:
            raise ValueError(f"grid_scale = {self.grid_scale!r}: expected one of {', '.join(GRID_SCALES)}")
        if not 0.0 < self.grid_floor < 1.0:
            raise ValueError(f"grid_floor = {self.grid_floor!r}: expected 0 < grid_floor < 1")
