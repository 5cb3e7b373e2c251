"""Tracked objects of one frame (``iamp.TrackFrame``) and the scene they live in."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Annotated, ClassVar

import numpy as np

from ._wire import Array, Message, Range, register
from .common import HEADER_WALL_UPGRADE, COORD_OR_NAN, MAX_SPEED_MPS, NON_NEG_INT, VEL_OR_NAN, Header

F64 = Annotated[np.ndarray, Array("float64", ("n",))]
N_OBJ = ("n",)
# a size no road user has (0, negative, 1 km) is no size: unknown, and the stages use the agent type's default
SIZE = Range(0.01, 100.0, nan=True, clear=True, unit="m")


@register
@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class TrackFrame(Message):
    """All objects of one frame, column-wise: every array has shape ``(n,)``.

    ``agent_types`` holds ``AgentType`` values (uint8). Positions are metres in
    the scene's local map frame (x east, y north), velocities m/s in the same
    frame, yaw in radians from the x axis. ``scene_id`` names the ``SceneInfo``
    (map + projection) the positions refer to.

    Ranges, checked at decoding (``ROWS = "n"``: an object with a value out
    of range is dropped from the frame, recorded): track ids >= 0; positions
    within +-1e6 m or NaN (unknown: the corridors stage marks the object
    BAD_STATE). Reported evidence out of range is cleared to NaN (unknown)
    instead, because the stages derive it otherwise: velocity components
    beyond +-150 m/s, yaw beyond +-100 rad, sizes outside 0.01..100 m.
    """

    SCHEMA: ClassVar[str] = "iamp.TrackFrame"
    VERSION: ClassVar[int] = 2  # v2: Header.source_wall_ns
    UPGRADES: ClassVar[dict[int, Any]] = {1: HEADER_WALL_UPGRADE}  # v1 reads as v2 with source_wall_ns 0 (unknown)
    # about 70 B per object (9 arrays) + 150 B: 1 MiB is about 15,000 objects (measured 104-221 B/object at <= 5 objects)
    MAX_BYTES: ClassVar[int] = 1 * 1024 * 1024
    ROWS: ClassVar[str] = "n"

    header: Header
    scene_id: str
    track_ids: Annotated[np.ndarray, Array("int64", N_OBJ), NON_NEG_INT]
    agent_types: Annotated[np.ndarray, Array("uint8", N_OBJ)]
    x_m: Annotated[np.ndarray, Array("float64", N_OBJ), COORD_OR_NAN]
    y_m: Annotated[np.ndarray, Array("float64", N_OBJ), COORD_OR_NAN]
    vx_mps: Annotated[np.ndarray, Array("float64", N_OBJ), Range(-MAX_SPEED_MPS, MAX_SPEED_MPS, nan=True, clear=True, unit="m/s")]
    vy_mps: Annotated[np.ndarray, Array("float64", N_OBJ), Range(-MAX_SPEED_MPS, MAX_SPEED_MPS, nan=True, clear=True, unit="m/s")]
    yaw_rad: Annotated[np.ndarray, Array("float64", N_OBJ), Range(-100.0, 100.0, nan=True, clear=True, unit="rad")]
    length_m: Annotated[np.ndarray, Array("float64", N_OBJ), SIZE]
    width_m: Annotated[np.ndarray, Array("float64", N_OBJ), SIZE]

    def __len__(self) -> int:
        return int(self.track_ids.shape[0])


#: the values of ``SceneInfo.clock``
SCENE_CLOCKS = ("recording", "wall", "sensor", "unknown")


def _scene_add_clock(body: object) -> object:
    """A v3 SceneInfo body made a v4 one: ``clock`` "unknown" (anything not a map goes on, for the decoder to reject)."""
    if isinstance(body, dict) and "clock" not in body:
        body = {**body, "clock": "unknown"}
    return body


@register
@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class SceneInfo(Message):
    """What a stage needs to load the same map as the source.

    Published by the source before its first frame and answered to queries
    (latched), so a stage that starts or restarts late still gets it.
    ``scene_id`` is a content hash of the map file, projection and origin.
    ``map_name`` is a bare file name (``k729_2022-03-16.osm``), never a path:
    every stage looks it up in the ``maps/`` folder of its own local data
    folder (its ``data`` parameter) and loads it only when that file's sha256
    equals ``map_sha256``. Nothing on the bus names a file to open.
    ``projection`` names the projection of the map into the positions' frame
    (docs/wire.md, "Frames"). ``clock`` says what the stamps of the scene's
    frames (``Header.stamp_ns``) count: ``"recording"`` (a recording's own
    time, from its start; not the wall clock), ``"wall"`` (Unix ns: a live
    tracker stamping with the wall clock, or a player with ``clock =
    "wall"``), ``"sensor"`` (a tracker's own clock of another epoch) or
    ``"unknown"`` (a publisher that does not say; every scene before v4).
    v2: ``map_path`` (an absolute path on the publishing host) became ``map_name``.
    v4: ``clock``.
    """

    SCHEMA: ClassVar[str] = "iamp.SceneInfo"
    VERSION: ClassVar[int] = 4  # v3: Header.source_wall_ns; v4: clock
    # v2 reads as v4 with source_wall_ns 0 (unknown) and clock "unknown"; v3 with clock "unknown"
    UPGRADES: ClassVar[dict[int, Any]] = {2: lambda body: _scene_add_clock(HEADER_WALL_UPGRADE(body)), 3: lambda body: _scene_add_clock(body)}
    # strings and a few numbers (measured 417 B)
    MAX_BYTES: ClassVar[int] = 64 * 1024

    header: Header
    scene_id: str
    recording: str
    location_id: str
    map_name: str
    map_sha256: str
    projection: str
    origin_lat_deg: Annotated[float, Range(-90.0, 90.0, unit="deg")]
    origin_lon_deg: Annotated[float, Range(-180.0, 180.0, unit="deg")]
    frame_rate_hz: Annotated[float, Range(0.01, 1000.0, unit="Hz")]
    speed_limit_mps: Annotated[float, Range(0.0, MAX_SPEED_MPS, nan=True, unit="m/s")]
    n_frames: Annotated[int, NON_NEG_INT]
    clock: str = "unknown"
