"""``FoxgloveConfig``: the parameters of the live Foxglove bridge (package docstring)."""

from __future__ import annotations

from dataclasses import dataclass

from stages.lib.base import ConfigMixin

DEFAULT_PORT = 8765  # Foxglove's default WebSocket port


@dataclass(frozen=True, kw_only=True)
class FoxgloveConfig(ConfigMixin):
    host: str = "127.0.0.1"
    port: int = DEFAULT_PORT  # 0: a free port; a busy one moves to a free one
    data: str = ""  # folder whose maps/ holds the scene's map; "": the embedded stages/data/taf-bw
    grid_step: str = "max"  # max, all, or a step time in seconds
    message_backlog: int = 1024

    def __post_init__(self) -> None:
        if not self.host.strip():
            raise ValueError("host must not be empty (127.0.0.1 keeps the server on this machine)")
        if not 0 <= self.port <= 65535:
            raise ValueError(f"port = {self.port}: expected 0 (a free port) to 65535")
        if self.message_backlog < 1:
            raise ValueError(f"message_backlog = {self.message_backlog}: must be >= 1")
        from stages.foxglove_bridge.scene import parse_grid_step

        try:
            parse_grid_step(self.grid_step)
        except ValueError as exc:
            raise ValueError(f"grid_step: {exc}") from None
