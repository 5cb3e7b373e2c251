"""The scene-map cache: a scene's map found in the local data folder, checked, loaded once.

A ``SceneInfo`` names its map only by name (and sha256), projection and
origin; `local_map_file` finds and checks the file in ``<data>/maps`` without
ever opening a path from the bus, `resolve_projection` picks the projection,
and `SceneMaps` loads each (map, projection, origin) once for every stage
that shares it (corridors, relations, intentions, the viewer's file lookup).
"""

from __future__ import annotations

import collections
import hashlib
import os
import re
import stat
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Callable, TypeVar

from stages.lib.maps.projection import Projection, parse_projection, projection_for_location
from stages.lib.maps.road_map import RoadMap, load_map

if TYPE_CHECKING:
    from bus_schemas import SceneInfo

T = TypeVar("T")
DEFAULT_RESAMPLE_STEP_M = 0.5  # the centreline step of `CorridorsConfig` and of `load_map`


@dataclass(frozen=True, slots=True, eq=False)
class SceneMap:
    """A loaded scene map; `road_map` None if it could not load (then `problems` say why).

    `derived` keeps what a stage builds from the road map (the corridors
    stage's lanelet index and route cache) with the entry, so every user of
    the cache builds it once per map.
    """

    road_map: RoadMap | None
    problems: tuple[str, ...]
    projection: Projection
    _derived: dict = field(default_factory=dict, repr=False)

    def derived(self, key, build: Callable[[RoadMap], T]) -> T | None:
        """``build(road_map)`` once per `key` for this entry (later calls return the first result); None without a road map."""
        if self.road_map is None:
            return None
        if key not in self._derived:
            self._derived[key] = build(self.road_map)
        return self._derived[key]


def resolve_projection(configured: str, scene: SceneInfo) -> Projection:
    """The configured projection, else the scene's, else the measured one for its location."""
    for value in (configured, scene.projection):
        chosen = parse_projection(value)
        if chosen not in (Projection.AUTO, Projection.UNKNOWN):
            return chosen
    return projection_for_location(scene.location_id)


MAP_MAX_BYTES = 256 * 1024 * 1024  # a local map file larger than this is refused before it is hashed
_MAP_NAME_RE = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]{0,199}")


def data_folder(data: str | os.PathLike | None) -> Path:
    """A stage's local data folder: ``data`` if given, else the embedded ``stages/data/taf-bw``."""
    from stages.lib.datasets import DEFAULT_DATA_DIR

    return Path(data).expanduser() if data else DEFAULT_DATA_DIR


def shown_map_name(scene: SceneInfo) -> str:
    """The scene's map name for logs and issues: the name if it is a valid one, else ``<invalid map name>``."""
    name = scene.map_name
    return name if isinstance(name, str) and _MAP_NAME_RE.fullmatch(name) and ".." not in name else "<invalid map name>"


def local_map_file(data: str | os.PathLike | None, scene: SceneInfo, *, max_bytes: int = MAP_MAX_BYTES) -> tuple[Path | None, str]:
    """The file of the scene's map in the local data folder, checked: ``(path, "")`` or ``(None, problem)``.

    ``scene.map_name`` is only a name: it must be a plain file name (no path
    separator, no ``..``) and equal one of the entries of ``<data>/maps``; no
    path from the bus is ever opened. The file must be a regular file of at
    most ``max_bytes``; when the scene names a ``map_sha256`` the file's
    digest must equal it (checked before anything parses the file). The
    problem starts with ``map_sha256_mismatch`` for a digest that differs.
    """
    name = scene.map_name
    if not isinstance(name, str) or not _MAP_NAME_RE.fullmatch(name) or ".." in name:
        return None, f"map_name_invalid: the scene names {name[:80]!r}, expected a plain file name in the maps folder"
    folder = data_folder(data) / "maps"
    try:
        entries = set(os.listdir(folder))
    except OSError as error:
        return None, f"map_not_found: no maps folder {folder} ({error.strerror})"
    if name not in entries:
        return None, f"map_not_found: {name} is not in the local maps folder {folder}"
    path = folder / name
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
    except OSError as error:
        return None, f"map_unreadable: {path} ({error.strerror})"
    try:
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode):
            return None, f"map_unreadable: {path} is not a regular file"
        if info.st_size > max_bytes:
            return None, f"map_too_large: {path} has {info.st_size} bytes, at most {max_bytes} are read"
        if scene.map_sha256:
            digest = hashlib.sha256()
            with os.fdopen(os.dup(fd), "rb") as fh:
                for block in iter(lambda: fh.read(1 << 20), b""):
                    digest.update(block)
            if digest.hexdigest() != scene.map_sha256:
                return None, f"map_sha256_mismatch: local {name} has {digest.hexdigest()[:12]}, the scene names {scene.map_sha256[:12]}: not loaded"
    except OSError as error:
        return None, f"map_unreadable: {path} ({error.strerror})"
    finally:
        os.close(fd)
    return path, ""



class SceneMaps:
    """Loads and caches scene maps (one lanelet2 load per map, hash, projection and origin).

    The map comes from ``<data>/maps`` (``data``: the stage's local data
    folder, default the embedded ``stages/data/taf-bw``), found by the scene's map
    name and checked against its sha256 (``local_map_file``); a map that is
    missing, too large, of another hash or that fails to load is cached as a
    ``SceneMap`` without ``road_map`` and its problems, never retried.
    Share one between stages to load each map once (the coverage bench).

    ``config`` is the corridors stage's ``CorridorsConfig`` or any object with
    ``data`` and ``resample_step_m`` (the centreline step the map is built
    with; default 0.5 m); it is kept as ``config`` (None if not given) because
    the corridors stage builds its route caches with that config's route
    options.
    """

    MAX_ENTRIES = 32  # maps (or failures) kept; a publisher cycling through scenes cannot grow the cache without bound

    def __init__(self, config=None, *, data: str | os.PathLike | None = None) -> None:
        self.config = config
        self.resample_step_m = float(getattr(config, "resample_step_m", DEFAULT_RESAMPLE_STEP_M))
        self.data_dir = data_folder(data if data is not None else getattr(config, "data", ""))
        self._maps: collections.OrderedDict[tuple, SceneMap] = collections.OrderedDict()

    def get(self, scene: SceneInfo, configured_projection: str = "auto") -> SceneMap:
        projection = resolve_projection(configured_projection, scene)
        # the scene id is a hash of (map sha256, projection, origin): keyed by what it hashes, so equal scenes share one load
        key = (scene.map_name, scene.map_sha256, projection, scene.origin_lat_deg, scene.origin_lon_deg, self.resample_step_m)
        found = self._maps.get(key)
        if found is None:
            try:
                found = self._load(scene, projection)
            except Exception as error:  # noqa: BLE001 - a map that fails to load is a cached problem, not a crash per frame
                found = SceneMap(None, (f"map_load_failed: {type(error).__name__}: {error}",), projection)
            self._maps[key] = found
            while len(self._maps) > self.MAX_ENTRIES:
                self._maps.popitem(last=False)
        else:
            self._maps.move_to_end(key)
        return found

    def _load(self, scene: SceneInfo, projection: Projection) -> SceneMap:
        problems: list[str] = []
        path, problem = local_map_file(self.data_dir, scene)
        if path is None:
            return SceneMap(None, (problem,), projection)
        road_map, found = load_map(
            path, scene.origin_lat_deg, scene.origin_lon_deg, projection, resample_step_m=self.resample_step_m
        )
        problems.extend(f"{p.kind.name.lower()}: {p.detail}" for p in found)
        if road_map is None or not road_map.lanelet_ids:
            return SceneMap(None, tuple(problems) or ("no car lanelets",), projection)
        return SceneMap(road_map, tuple(problems), projection)
