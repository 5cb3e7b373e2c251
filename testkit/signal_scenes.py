"""Synthetic recordings on the real K733 map with the real signal timing (tests/fixtures/taf_bw_signals).

``signal_recording(tmp_dir, cars)`` copies the fixture (map, lane file,
meta row, the recording's trimmed signal phases) into ``tmp_dir`` and writes
``vehicle_tracks_000.csv`` with the given cars, each a ``Car`` driving a
lanelet path of the map with a speed profile over time. The tracks' clock
is the signal file's: a car at ``t_s`` sees the phases at ``t_s``.

Real timing used by the tests (group 7: lane 44, the south-west approach
lanelet -103632, straight on to -103592, -103644; stop line at about 40.3 m
on -103632): red 19.8-91.8 s, red-amber 91.8-92.8 s, green 92.8-103.8 s.
"""

from __future__ import annotations

import math
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np

FIXTURE = Path(__file__).resolve().parents[1] / "tests" / "fixtures" / "taf_bw_signals"
RECORDING = "k733_2020-09-15"
ORIGIN = (49.005306, 8.4374089)
SW_STRAIGHT = (-103632, -103592, -103644)  # lane 44 -> lane 5, signal group 7
GROUP = 7
RED_S = (19.8, 91.8)
GREEN_ONSET_S = 92.8


@dataclass(frozen=True)
class Car:
    """A car on ``path`` from ``t0_s`` for ``duration_s``: arc length s(t) from a piecewise-constant acceleration.

    ``phases`` is a list of (duration_s, acceleration_mps2); the speed never goes below 0.
    """

    track_id: int
    path: tuple[int, ...]
    t0_s: float
    s0_m: float
    v0_mps: float
    phases: tuple[tuple[float, float], ...]
    length_m: float = 4.5
    width_m: float = 1.8

    def profile(self, dt: float = 0.1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        total = sum(d for d, _ in self.phases)
        n = int(round(total / dt)) + 1
        t = np.arange(n) * dt
        s = np.empty(n)
        v = np.empty(n)
        s[0], v[0] = self.s0_m, self.v0_mps
        bounds = np.cumsum([d for d, _ in self.phases])
        for k in range(1, n):
            a = self.phases[min(int(np.searchsorted(bounds, t[k - 1] + 1e-9, side="right")), len(self.phases) - 1)][1]
            v_new = max(v[k - 1] + a * dt, 0.0)
            s[k] = s[k - 1] + 0.5 * (v[k - 1] + v_new) * dt
            v[k] = v_new
        return self.t0_s + t, s, v


def path_centreline(path: tuple[int, ...]):
    from stages.lib.maps import Projection, load_map

    road_map, _ = load_map(FIXTURE / "maps" / f"{RECORDING}.osm", *ORIGIN, Projection.SCALED_MERCATOR)
    return road_map, road_map.path_centreline(path)


def stop_line_s_m(road_map, path: tuple[int, ...] = SW_STRAIGHT) -> float:
    """The stop line's arc length on ``path`` from the lane file match (``stages.lib.maps.signals``)."""
    from stages.lib.datasets.signals import read_kml_lanes
    from stages.lib.maps import Projection
    from stages.lib.maps.signals import match_lanes

    lanes = read_kml_lanes(FIXTURE / "recorded_trackfiles" / RECORDING / "k733_map.kml")
    smap = match_lanes(road_map, lanes, Projection.SCALED_MERCATOR, *ORIGIN)
    starts = np.concatenate([[0.0], np.cumsum([road_map.lanelet(x).length_m for x in path[:-1]])])
    return smap.corridor_stops(np.array(path), starts)[0].s_m


def signal_recording(tmp_dir: Path, cars: list[Car], *, with_phases: bool = True) -> Path:
    """A data folder holding the recording with ``cars``; returns the folder (``--data``)."""
    data = Path(tmp_dir)
    shutil.copytree(FIXTURE, data, dirs_exist_ok=True)
    folder = data / "recorded_trackfiles" / RECORDING
    if not with_phases:
        for p in folder.glob("signal_phases_*.csv"):
            p.unlink()
    centrelines = {}
    rows = []
    for car in cars:
        if car.path not in centrelines:
            centrelines[car.path] = path_centreline(car.path)[1]
        line = centrelines[car.path]
        t, s, v = car.profile()
        xy = line.to_xy(s)
        h = line.heading_at(s)
        for k in range(len(t)):
            rows.append((int(round(t[k] * 1000)), car.track_id, xy[k, 0], xy[k, 1], v[k] * math.cos(h[k]), v[k] * math.sin(h[k]), h[k],
                         car.length_m, car.width_m))
    rows.sort()
    with (folder / "vehicle_tracks_000.csv").open("w") as f:
        f.write("track_id,frame_id,timestamp_ms,agent_type,x,y,vx,vy,psi_rad,length,width\n")
        for ms, tid, x, y, vx, vy, psi, length, width in rows:
            f.write(f"{tid},{ms // 100},{ms},car,{x:.3f},{y:.3f},{vx:.3f},{vy:.3f},{psi:.4f},{length},{width}\n")
    return data


__all__ = ["Car", "FIXTURE", "GREEN_ONSET_S", "GROUP", "RECORDING", "RED_S", "SW_STRAIGHT", "path_centreline", "signal_recording", "stop_line_s_m"]
