"""Tracked objects of one frame (``iamp.TrackFrame``) and the scene they live in."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, ClassVar

import numpy as np

from ._wire import Array, Message, register
from .common import Header

F64 = Annotated[np.ndarray, Array("float64", ("n",))]


@register
@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class TrackFrame(Message):
    """All objects of one frame, column-wise: every array has shape ``(n,)``.

    ``agent_types`` holds ``AgentType`` values (uint8). Positions are metres in
    the scene's local map frame (x east, y north), velocities m/s in the same
    frame, yaw in radians from the x axis. ``scene_id`` names the ``SceneInfo``
    (map + projection) the positions refer to.
    """

    SCHEMA: ClassVar[str] = "iamp.TrackFrame"
    VERSION: ClassVar[int] = 1
    # about 70 B per object (9 arrays) + 150 B: 1 MiB is about 15,000 objects (measured 104-221 B/object at <= 5 objects)
    MAX_BYTES: ClassVar[int] = 1 * 1024 * 1024

    header: Header
    scene_id: str
    track_ids: Annotated[np.ndarray, Array("int64", ("n",))]
    agent_types: Annotated[np.ndarray, Array("uint8", ("n",))]
    x_m: F64
    y_m: F64
    vx_mps: F64
    vy_mps: F64
    yaw_rad: F64
    length_m: F64
    width_m: F64

    def __len__(self) -> int:
        return int(self.track_ids.shape[0])


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
    v2: ``map_path`` (an absolute path on the publishing host) became ``map_name``.
    """

    SCHEMA: ClassVar[str] = "iamp.SceneInfo"
    VERSION: ClassVar[int] = 2
    # strings and a few numbers (measured 417 B)
    MAX_BYTES: ClassVar[int] = 64 * 1024

    header: Header
    scene_id: str
    recording: str
    location_id: str
    map_name: str
    map_sha256: str
    projection: str
    origin_lat_deg: float
    origin_lon_deg: float
    frame_rate_hz: float
    speed_limit_mps: float
    n_frames: int
