"""Signalised stop lines in the viewer, coloured by their group's current phase (issue 17).

``load_stop_lines(scene, data)`` finds the scene's KML lane file in the
viewer's data folder (``<data>/recorded_trackfiles/<recording>/*.kml``, as
the relations stage does), matches it to the scene's map
(``stages.lib.maps.signals``) and returns each matched stop line across its
lanelet with its group (a lane with two groups: the line split in two).
``stop_line_segments(lines, state)`` colours them by the newest
``SignalState``: red (red), orange (red-amber), amber, green, grey (unknown,
dark, or no state). Without a lane file there are no lines and nothing is
drawn.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from bus_schemas import SceneInfo, SignalPhase, SignalState
from stages.viewer.model import Segments

PHASE_COLOURS: dict[SignalPhase, tuple[int, int, int]] = {
    SignalPhase.RED: (220, 30, 30),
    SignalPhase.RED_AMBER: (240, 120, 20),
    SignalPhase.AMBER: (250, 190, 0),
    SignalPhase.GREEN: (30, 200, 60),
}
UNKNOWN_COLOUR = (150, 150, 150)
Z_STOP_LINE_M = 0.12


@dataclass(frozen=True, slots=True)
class StopLine:
    start_m: tuple[float, float]
    end_m: tuple[float, float]
    group: int


def load_stop_lines(scene: SceneInfo, data: str | None = None) -> tuple[list[StopLine], tuple[str, ...]]:
    """The scene's signalised stop lines ([] without a lane file), and problems met."""
    from stages.lib.datasets.signals import lane_file_for, read_kml_lanes
    from stages.lib.maps import data_folder, load_map, local_map_file, resolve_projection
    from stages.lib.maps.signals import match_lanes

    lane_file = lane_file_for(data_folder(data), scene.recording)
    if lane_file is None:
        return [], ()
    path, problem = local_map_file(data, scene)
    if path is None:
        return [], (problem,)
    try:
        projection = resolve_projection("auto", scene)
        road_map, _ = load_map(path, scene.origin_lat_deg, scene.origin_lon_deg, projection)
        smap = match_lanes(road_map, read_kml_lanes(lane_file), projection, scene.origin_lat_deg, scene.origin_lon_deg)
    except Exception as exc:  # noqa: BLE001 - no stop lines, once per scene
        return [], (f"stop lines not drawn: {type(exc).__name__}: {exc}",)
    out: list[StopLine] = []
    for lane in smap.matched:
        if not lane.signalised or lane.stop_lanelet_id is None:
            continue
        info = road_map.lanelet(lane.stop_lanelet_id)
        xy = info.centreline.to_xy(lane.stop_s_m)[0]
        h = float(info.centreline.heading_at(lane.stop_s_m))
        nx, ny = -math.sin(h) * 0.5 * info.width_m, math.cos(h) * 0.5 * info.width_m
        groups = lane.signal_groups
        for k, g in enumerate(groups):
            a, b = -1 + 2 * k / len(groups), -1 + 2 * (k + 1) / len(groups)
            out.append(StopLine((xy[0] + a * nx, xy[1] + a * ny), (xy[0] + b * nx, xy[1] + b * ny), int(g)))
    return out, ()


def stop_line_segments(lines: list[StopLine], state: SignalState | None) -> Segments:
    """The stop lines as segments coloured by their group's phase in ``state`` (grey without one)."""
    if not lines:
        return Segments.empty()
    points = np.array([[(*l.start_m, Z_STOP_LINE_M), (*l.end_m, Z_STOP_LINE_M)] for l in lines], dtype=np.float32)
    colours = np.empty(points.shape, dtype=np.uint8)
    for i, line in enumerate(lines):
        phase = state.phase_of(line.group)[0] if state is not None else SignalPhase.UNKNOWN
        colours[i] = PHASE_COLOURS.get(phase, UNKNOWN_COLOUR)
    return Segments(points, colours)


__all__ = ["PHASE_COLOURS", "StopLine", "load_stop_lines", "stop_line_segments"]
