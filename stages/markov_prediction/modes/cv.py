"""Mode ``cv``: Cartesian constant velocity, one straight line per vehicle along its velocity (``CV_LINE_ID``).

The line is the vehicle's only "corridor"; the prediction on it is
``corridor_cv.constant_speed``, like mode ``corridor_cv``'s.
"""

from __future__ import annotations

import math

import numpy as np

from stages.markov_prediction.modes.base import InputModel, Pair, Vehicle


#: The Cartesian constant-velocity line of mode ``cv`` has this corridor id.
CV_LINE_ID = -1


class CartesianCV(InputModel):
    """Closed form on one line per vehicle: from its position along its velocity (the corridor's heading when unknown)."""

    chain = False

    def vehicle_pairs(self, vehicle: Vehicle) -> list[Pair]:
        cfg = self.predictor.config
        v, corridor, frame, row, v0 = vehicle.message, vehicle.corridors[0], vehicle.frame, vehicle.row, vehicle.v0_mps
        heading = float(np.interp(corridor.vehicle_s_m, corridor.s_m, np.unwrap(corridor.heading_rad)))
        x0, y0 = _corridor_point(corridor, corridor.vehicle_s_m, corridor.vehicle_d_m)
        if row is not None and math.isfinite(frame.x_m[row]) and math.isfinite(frame.y_m[row]):
            x0, y0 = float(frame.x_m[row]), float(frame.y_m[row])
            vx, vy = float(v.vx_mps), float(v.vy_mps)  # estimated from positions (corridors stage)
            if math.isfinite(vx) and math.isfinite(vy):
                v0 = float(np.clip(math.hypot(vx, vy), 0.0, cfg.v_max_mps))
                if math.hypot(vx, vy) > 0.5:
                    heading = math.atan2(vy, vx)
        behind = cfg.window_behind_m
        s = np.arange(0.0, behind + cfg.window_cells * cfg.ds_m + cfg.ds_m, 0.5)
        return [Pair(
            track_id=v.track_id,
            corridor_id=CV_LINE_ID,
            probability=1.0,
            s_m=s,
            x_m=x0 + (s - behind) * math.cos(heading),
            y_m=y0 + (s - behind) * math.sin(heading),
            heading_rad=np.full(s.shape, heading),
            curvature_1pm=np.zeros(s.shape),
            speed_limit_mps=cfg.v_max_mps,
            s0_m=behind,
            v0_mps=v0,
            a0_mps2=vehicle.a0_mps2,
            s_first_m=0.0,
            length_m=vehicle.length_m,
            width_m=vehicle.width_m,
        )]


def _corridor_point(corridor, s_m: float, d_m: float) -> tuple[float, float]:
    heading = float(np.interp(s_m, corridor.s_m, np.unwrap(corridor.heading_rad)))
    x = float(np.interp(s_m, corridor.s_m, corridor.x_m))
    y = float(np.interp(s_m, corridor.s_m, corridor.y_m))
    d = d_m if math.isfinite(d_m) else 0.0
    return x - d * math.sin(heading), y + d * math.cos(heading)
