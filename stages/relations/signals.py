"""Corridor to signal: each pair's next signalised stop line and its group's current phase (RelationSet v2).

The stop lines come from the recording's KML lane file, found in the stage's
local data folder by the scene's recording name
(``<data>/recorded_trackfiles/<recording>/*.kml``, like the map by its name)
and matched to the scene's road map once per scene
(``stages.lib.maps.signals.match_lanes``, with the map's projection and
origin). The phases come from the newest ``SignalState`` (input
``signal_state``); one more than ``max_state_age_s`` from the frame's stamp
is not used (phase UNKNOWN, one ``signal_state_stale`` issue per frame). A
scene without a lane file, or no ``SignalState`` at all, leaves every pair's
``signal_*`` fields at their defaults: no stop line, phase UNKNOWN, as before
v2.
"""

from __future__ import annotations

import math
from pathlib import Path

from bus_schemas import Corridor, SceneInfo, SignalPhase, SignalState
from stages.lib.base import Issue
from stages.lib.datasets.signals import lane_file_for, read_kml_lanes
from stages.lib.maps import RoadMap
from stages.lib.maps.signals import SignalMap, match_lanes

#: a vehicle whose front is more than this past a stop line has passed it
PASSED_MARGIN_M = 1.0
MAX_STATE_AGE_S = 0.5


class SignalStops:
    """The signal map of each scene (cached by scene id) and the per-pair signal fields."""

    def __init__(self, data_dir: Path, *, max_state_age_s: float = MAX_STATE_AGE_S) -> None:
        self.data_dir = Path(data_dir)
        self.max_state_age_s = max_state_age_s
        self._maps: dict[str, SignalMap | None] = {}

    def lane_file(self, scene: SceneInfo) -> Path | None:
        return lane_file_for(self.data_dir, scene.recording)

    def signal_map(self, scene: SceneInfo | None, road_map: RoadMap | None, projection, issues: list[Issue]) -> SignalMap | None:
        if scene is None or road_map is None:
            return None
        if scene.scene_id not in self._maps:
            smap = None
            path = self.lane_file(scene)
            if path is not None:
                try:
                    lanes = read_kml_lanes(path)
                    smap = match_lanes(road_map, lanes, projection, scene.origin_lat_deg, scene.origin_lon_deg)
                    issues.append(Issue("signal_map", -1, f"{path.name}: {len(smap.matched)} of {len(smap.lanes)} lanes matched, "
                                        f"{len(smap.signal_groups)} signal groups on the map"))
                except Exception as exc:  # noqa: BLE001 - a bad lane file costs the signal relation, not the stage
                    issues.append(Issue("signal_map_failed", -1, f"{path.name}: {type(exc).__name__}: {exc}"))
            self._maps[scene.scene_id] = smap
            while len(self._maps) > 32:
                self._maps.pop(next(iter(self._maps)))
        return self._maps[scene.scene_id]

    def usable_state(self, state: SignalState | None, stamp_ns: int, issues: list[Issue]) -> SignalState | None:
        if state is None:
            return None
        if abs(int(state.header.stamp_ns) - int(stamp_ns)) > self.max_state_age_s * 1e9:
            issues.append(Issue("signal_state_stale", -1, f"signal_state stamp {state.header.stamp_ns} vs frame {stamp_ns}: phases unknown"))
            return None
        return state

    @staticmethod
    def fields(smap: SignalMap | None, corridor: Corridor, length_m: float, state: SignalState | None) -> dict:
        """The ``signal_*`` fields of one pair (empty: the defaults, no stop line)."""
        if smap is None or not math.isfinite(corridor.vehicle_s_m):
            return {}
        front = corridor.vehicle_s_m + 0.5 * (length_m if math.isfinite(length_m) and length_m > 0 else 4.5)
        for stop in smap.corridor_stops(corridor.lanelet_ids, corridor.lanelet_start_s_m):
            if stop.s_m + PASSED_MARGIN_M < front:
                continue
            phase, held = (SignalPhase.UNKNOWN, math.nan) if state is None else state.phase_of(stop.signal_group)
            return {
                "signal_group": int(stop.signal_group),
                "signal_stop_s_m": float(stop.s_m),
                "signal_distance_m": float(stop.s_m - corridor.vehicle_s_m),
                "signal_phase": phase,
                "signal_held_s": held if math.isfinite(held) and 0.0 <= held <= 1e6 else math.nan,
            }
        return {}


__all__ = ["MAX_STATE_AGE_S", "PASSED_MARGIN_M", "SignalStops"]
