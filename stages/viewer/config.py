"""``ViewerConfig``: every parameter of the viewer stage, with units and defaults."""

from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass

from stages.lib.base import ConfigMixin

GRID_SCALES = ("log", "linear")
INITIAL_VIEWS = ("traffic", "map")
TOKEN_ENV = "IAMP_VIEWER_TOKEN"  # the token when the ``token`` parameter is empty (the launcher passes it so)
_TOKEN_RE = re.compile(r"[A-Za-z0-9_-]{16,256}")
_ORIGIN_RE = re.compile(r"https?://(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9.-]+)(:[0-9]{1,5})?/?")


@dataclass(frozen=True, kw_only=True)
class ViewerConfig(ConfigMixin):
    """Parameters of the viewer stage (package docstring)."""

    host: str = "127.0.0.1"
    port: int = 8080  # 0: a free port
    max_render_hz: float = 10.0
    # while no browser is connected: the server-side scene is kept this fresh (a page that opens gets it at once and
    # the next draw right after); drawing at max_render_hz for nobody cost a third of a core at 72 vehicles
    idle_render_hz: float = 1.0
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
    token: str = ""  # "": none (or $IAMP_VIEWER_TOKEN); "auto": a fresh random one; else at least 16 of A-Z a-z 0-9 _ -
    origins: tuple[str, ...] = ()  # page origins allowed besides http://127.0.0.1|localhost|HOST:PORT, e.g. "http://myhost:8080"
    initial_view: str = "traffic"  # the camera at start: "traffic" (zoomed onto the objects of the first frame) or "map" (the whole map)
    data: str = ""  # local data folder whose maps/ holds the scene's map (by name, checked by sha256); "": the embedded stages/data/taf-bw

    def __post_init__(self) -> None:
        if not self.host.strip():
            raise ValueError("host must not be empty (127.0.0.1 keeps the viewer on this machine)")
        if not 0 <= self.port <= 65535:
            raise ValueError(f"port = {self.port}: expected 0 (a free port) to 65535")
        for name in ("max_render_hz", "idle_render_hz", "history_s", "horizon_s", "max_lag_s", "step_s", "status_hz"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f"{name} = {value!r}: must be > 0")
        if self.grid_scale not in GRID_SCALES:
            raise ValueError(f"grid_scale = {self.grid_scale!r}: expected one of {', '.join(GRID_SCALES)}")
        if self.initial_view not in INITIAL_VIEWS:
            raise ValueError(f"initial_view = {self.initial_view!r}: expected one of {', '.join(INITIAL_VIEWS)}")
        if not 0.0 < self.grid_floor < 1.0:
            raise ValueError(f"grid_floor = {self.grid_floor!r}: expected 0 < grid_floor < 1")
        for where, value in (("token", self.token), (f"${TOKEN_ENV}", os.environ.get(TOKEN_ENV, ""))):
            if value and value != "auto" and not _TOKEN_RE.fullmatch(value):
                raise ValueError(f"{where}: expected \"auto\" or 16 to 256 characters of A-Z a-z 0-9 _ - (got {len(value)} characters)")
        for origin in self.origins:
            if not _ORIGIN_RE.fullmatch(origin):
                raise ValueError(f"origins: {origin!r} is not a page origin such as \"http://myhost:8080\" (scheme, host, port; no path)")

    def effective_token(self) -> str:
        """The token the server asks for: the parameter, else $IAMP_VIEWER_TOKEN; "" for none. "auto" stays "auto"."""
        return self.token or os.environ.get(TOKEN_ENV, "")
