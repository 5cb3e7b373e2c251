"""Kinematics from positions, and the repair of implausible reported values.

Why: what a tracker reports about velocity and heading is not always what its
positions say. Measured on the TAF-BW subset (see ``tests/stages/test_datasets.py``):

- k733: the reported velocity is the backward difference of the positions
  with the sign inverted (anti-parallel to the motion in 99.5 % of samples
  faster than 2 m/s); ``psi_rad`` is known only modulo pi (``arctan(dy/dx)``:
  it points backwards whenever the object moves towards -x, 34 % of those
  samples); and
  the first frame of a track has ``v = 0`` and ``psi_rad = 0`` although the
  object is already moving.
- k729: velocity and yaw agree with the positions; the tracker holds the
  position for about three frames at a track start while the velocity ramps
  up. Those reported values are right and are kept.

``derive_kinematics`` estimates velocity and acceleration of one track from
its positions by local least-squares polynomial fits over ``2 * half_window +
1`` samples (Savitzky-Golay on the real, possibly irregular, time stamps; the
window is shifted, not shrunk, at the ends of the track): degree 1 for the
velocity (in a centred window of evenly spaced samples the same as degree 2,
and it does not extrapolate a parabola at the track ends), degree 2 for the
acceleration. With 2 samples it falls back to the finite difference; with 1 it
returns NaN.

Two checks decide per sequence, from its moving samples (derived and
reported speed at least ``orientation_speed_mps``; at least
``min_orientation_samples`` of them), whether a whole file has a convention
problem. A real dataset has few vehicles reversing, so the shares are far
from what a sign or quadrant error gives:

- ``velocity_sign_inverted``: more than half of the reported velocities point
  against the derived ones (cosine < -0.5).
- ``yaw_modulo_pi``: at least ``yaw_flip_share`` of the valid yaws point
  against the derived motion (cosine < -0.5).

``repair_track`` then applies these rules to one track, in this order, and
returns masks of what it changed so the loader can count every repair.
Rules 1 and 3 change reported velocities from positions that include the
future (a centred fit, a whole sequence), so they run only with
``RepairRule(repair_velocity=True)``: by default the loader leaves reported
velocities as the tracker gave them (NaN aside) and the stages' causal
estimator (``stages.lib.kinematic_state``) checks, calibrates and fuses them —
a repaired file would leak future positions into the first seconds of every
track (measured: zeroing K733's first second of velocities "improved" hybrid
mADE by 9 % through this repair).

1. ``velocity_sign_flipped`` (only when the sequence has inverted
   velocities): every reported velocity is negated.
2. ``velocity_nan``: a non-finite reported velocity is replaced by the derived
   one (0 for a single-sample track).
3. ``start_velocity``: in the leading run of frames whose reported speed is
   below ``zero_speed_mps``, every frame whose derived speed is at least
   ``moving_speed_mps`` gets the derived velocity. The run ends at the first
   frame with a reported speed at or above ``zero_speed_mps``; later frames
   keep their reported values even when they disagree with the positions.
4. ``yaw``: a yaw is invalid when it is non-finite, or when it is exactly 0.0
   in the leading run of exactly-zero yaws (the k733 default). An invalid yaw
   becomes the direction of the derived velocity when the derived speed is at
   least ``moving_speed_mps`` (``yaw_from_motion``); otherwise the nearest
   valid yaw of the track (the next one for the leading run, else the
   previous one: ``yaw_from_neighbour``). A leading exact-zero yaw with no
   valid yaw to take from stays 0.0 (it may be right); a non-finite one
   becomes 0.0 (``yaw_defaulted``).
5. ``yaw_flipped`` (only when the sequence's yaw is known modulo pi): each
   yaw becomes yaw or yaw + pi, whichever is closer to the derived motion
   where the object moves at ``orientation_speed_mps`` or more (stricter
   than ``moving_speed_mps``: k733 positions of standing cars jitter at up
   to about 1 m/s), else to the resolved yaw of the previous frame (the
   first moving one for the leading frames). A track that never moves that
   fast keeps its yaws. A yaw already repaired by rule 4 is counted under
   rule 4 only.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, slots=True, kw_only=True)
class RepairRule:
    """Thresholds of the repair rules (see the module docstring).

    ``zero_speed_mps``: a reported speed below it counts as "not moving";
    ``moving_speed_mps``: a derived speed at or above it counts as moving;
    ``orientation_speed_mps``: speed from which a direction of motion is
    trusted to decide conventions and resolve yaw modulo pi;
    ``min_orientation_samples``: fewer such samples in a sequence decide
    nothing; ``yaw_flip_share``: share of backward yaws from which a sequence's
    yaw counts as known modulo pi; ``half_window``: samples either side in
    the derivative fit.
    """

    zero_speed_mps: float = 0.1
    moving_speed_mps: float = 0.5
    repair_velocity: bool = False
    half_window: int = 2
    orientation_speed_mps: float = 2.0
    min_orientation_samples: int = 20
    yaw_flip_share: float = 0.2

    def __post_init__(self) -> None:
        if not (0 <= self.zero_speed_mps < self.moving_speed_mps):
            raise ValueError("need 0 <= zero_speed_mps < moving_speed_mps")
        if self.half_window < 1:
            raise ValueError("half_window must be >= 1")


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class Kinematics:
    """Derived velocity and acceleration of one track, arrays ``(n,)`` float64."""

    vx_mps: np.ndarray
    vy_mps: np.ndarray
    ax_mps2: np.ndarray
    ay_mps2: np.ndarray

    @property
    def speed_mps(self) -> np.ndarray:
        return np.hypot(self.vx_mps, self.vy_mps)


def derive_kinematics(t_s: np.ndarray, x_m: np.ndarray, y_m: np.ndarray, *, half_window: int = 2) -> Kinematics:
    """Velocity and acceleration of one track from its positions.

    ``t_s`` must be strictly increasing (seconds), ``x_m``/``y_m`` finite, all
    of shape ``(n,)``. Local polynomial fits over ``w = min(2 * half_window +
    1, n)`` samples, centred where the track allows (see the module docstring).
    """
    t = np.asarray(t_s, dtype=np.float64)
    x = np.asarray(x_m, dtype=np.float64)
    y = np.asarray(y_m, dtype=np.float64)
    n = t.shape[0]
    if not (x.shape == y.shape == (n,)):
        raise ValueError("t_s, x_m and y_m must have the same shape (n,)")
    if n == 0:
        empty = np.zeros(0)
        return Kinematics(vx_mps=empty, vy_mps=empty.copy(), ax_mps2=empty.copy(), ay_mps2=empty.copy())
    if n == 1:
        nan = np.full(1, np.nan)
        return Kinematics(vx_mps=nan, vy_mps=nan.copy(), ax_mps2=nan.copy(), ay_mps2=nan.copy())
    if np.any(np.diff(t) <= 0):
        raise ValueError("t_s must be strictly increasing")
    w = min(2 * half_window + 1, n)
    starts = np.clip(np.arange(n) - half_window, 0, n - w)
    idx = starts[:, None] + np.arange(w)[None, :]  # (n, w)
    tau = t[idx] - t[:, None]  # (n, w), time relative to the sample being estimated
    xs, ys = x[idx], y[idx]
    # velocity: degree 1 (the same as degree 2 in a centred even window, and robust
    # in the shifted windows at the track ends, where a parabola extrapolates)
    c1x, c1y = _local_fit(tau, xs, ys, 1)
    if w >= 3:
        c2x, c2y = _local_fit(tau, xs, ys, 2)
        ax, ay = 2.0 * c2x[:, 2], 2.0 * c2y[:, 2]
    else:
        ax, ay = np.zeros(n), np.zeros(n)
    return Kinematics(vx_mps=c1x[:, 1].copy(), vy_mps=c1y[:, 1].copy(), ax_mps2=ax, ay_mps2=ay)


def _local_fit(tau: np.ndarray, xs: np.ndarray, ys: np.ndarray, degree: int) -> tuple[np.ndarray, np.ndarray]:
    """Polynomial coefficients ``(n, degree + 1)`` of x and y over each window (least squares)."""
    vander = tau[..., None] ** np.arange(degree + 1)  # (n, w, degree + 1)
    pinv = np.linalg.pinv(vander)  # (n, degree + 1, w)
    return np.einsum("nkw,nw->nk", pinv, xs), np.einsum("nkw,nw->nk", pinv, ys)


def _moving_cosines(ax: np.ndarray, ay: np.ndarray, bx: np.ndarray, by: np.ndarray, rule: RepairRule) -> np.ndarray | None:
    """Cosines between vectors a and b where both are at least ``orientation_speed_mps`` long."""
    na, nb = np.hypot(ax, ay), np.hypot(bx, by)
    ok = np.isfinite(na) & np.isfinite(nb) & (na >= rule.orientation_speed_mps) & (nb >= rule.orientation_speed_mps)
    if np.count_nonzero(ok) < rule.min_orientation_samples:
        return None
    return (ax[ok] * bx[ok] + ay[ok] * by[ok]) / (na[ok] * nb[ok])


def velocity_sign_inverted(
    vx_mps: np.ndarray, vy_mps: np.ndarray, derived_vx_mps: np.ndarray, derived_vy_mps: np.ndarray, rule: RepairRule = RepairRule()
) -> bool:
    """True when most moving reported velocities of a sequence point against the derived ones."""
    cos = _moving_cosines(np.asarray(vx_mps), np.asarray(vy_mps), np.asarray(derived_vx_mps), np.asarray(derived_vy_mps), rule)
    return cos is not None and float(np.mean(cos < -0.5)) > 0.5


def yaw_modulo_pi(yaw_rad: np.ndarray, derived_vx_mps: np.ndarray, derived_vy_mps: np.ndarray, rule: RepairRule = RepairRule()) -> bool:
    """True when at least ``yaw_flip_share`` of a sequence's valid moving yaws point against the motion.

    Exactly-zero yaws are left out (they are the k733 default at track starts).
    """
    yaw = np.asarray(yaw_rad, dtype=np.float64)
    valid = np.isfinite(yaw) & (yaw != 0.0)
    safe = np.where(valid, yaw, 0.0)  # no cos/sin of a non-finite yaw
    ux = np.where(valid, np.cos(safe), np.nan) * rule.orientation_speed_mps
    uy = np.where(valid, np.sin(safe), np.nan) * rule.orientation_speed_mps
    cos = _moving_cosines(ux, uy, np.asarray(derived_vx_mps), np.asarray(derived_vy_mps), rule)
    return cos is not None and float(np.mean(cos < -0.5)) >= rule.yaw_flip_share


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class TrackRepair:
    """Repaired velocity and yaw of one track, and boolean masks ``(n,)`` of what changed."""

    vx_mps: np.ndarray
    vy_mps: np.ndarray
    yaw_rad: np.ndarray
    velocity_sign_flipped: np.ndarray
    velocity_nan: np.ndarray
    start_velocity: np.ndarray
    yaw_from_motion: np.ndarray
    yaw_from_neighbour: np.ndarray
    yaw_defaulted: np.ndarray
    yaw_flipped: np.ndarray


def repair_track(
    t_s: np.ndarray,
    x_m: np.ndarray,
    y_m: np.ndarray,
    vx_mps: np.ndarray,
    vy_mps: np.ndarray,
    yaw_rad: np.ndarray,
    rule: RepairRule = RepairRule(),
    *,
    derived: Kinematics | None = None,
    flip_velocity: bool = False,
    resolve_yaw: bool = False,
) -> TrackRepair:
    """Apply the repair rules of the module docstring to one track (sorted by time).

    ``derived`` (from ``derive_kinematics``) is computed when not given;
    ``flip_velocity`` and ``resolve_yaw`` are the sequence-level decisions of
    ``velocity_sign_inverted`` and ``yaw_modulo_pi``.
    """
    vx = np.array(vx_mps, dtype=np.float64)
    vy = np.array(vy_mps, dtype=np.float64)
    yaw = np.array(yaw_rad, dtype=np.float64)
    n = vx.shape[0]
    kin = derived if derived is not None else derive_kinematics(t_s, x_m, y_m, half_window=rule.half_window)
    dvx = np.nan_to_num(kin.vx_mps, nan=0.0)
    dvy = np.nan_to_num(kin.vy_mps, nan=0.0)
    moving = np.hypot(dvx, dvy) >= rule.moving_speed_mps

    finite_v = np.isfinite(vx) & np.isfinite(vy)
    velocity_sign_flipped = finite_v & ((vx != 0.0) | (vy != 0.0)) if flip_velocity else np.zeros(n, dtype=bool)
    vx[velocity_sign_flipped] *= -1.0
    vy[velocity_sign_flipped] *= -1.0

    velocity_nan = ~finite_v
    vx[velocity_nan] = dvx[velocity_nan]
    vy[velocity_nan] = dvy[velocity_nan]

    start_velocity = np.zeros(n, dtype=bool)
    lead = _leading_run(np.hypot(vx, vy) < rule.zero_speed_mps) if rule.repair_velocity else 0
    start_velocity[:lead] = moving[:lead] & ~velocity_nan[:lead]
    vx[start_velocity] = dvx[start_velocity]
    vy[start_velocity] = dvy[start_velocity]
    velocity_sign_flipped &= ~start_velocity  # counted once, as replaced

    nonfinite_yaw = ~np.isfinite(yaw)
    invalid = nonfinite_yaw.copy()
    invalid[: _leading_run(yaw == 0.0)] = True
    yaw_from_motion = invalid & moving
    new_yaw = yaw.copy()
    new_yaw[yaw_from_motion] = np.arctan2(dvy[yaw_from_motion], dvx[yaw_from_motion])
    yaw_from_neighbour = np.zeros(n, dtype=bool)
    yaw_defaulted = np.zeros(n, dtype=bool)
    valid_idx = np.flatnonzero(~invalid)
    for i in np.flatnonzero(invalid & ~moving).tolist():
        if valid_idx.size:
            src = valid_idx[0] if i < valid_idx[0] else valid_idx[valid_idx < i][-1]
            new_yaw[i] = yaw[src]
            yaw_from_neighbour[i] = True
        elif nonfinite_yaw[i]:
            new_yaw[i] = 0.0
            yaw_defaulted[i] = True
    unchanged = np.isfinite(yaw) & np.isclose(new_yaw, yaw, rtol=0.0, atol=1e-9)
    yaw_from_motion &= ~unchanged
    yaw_from_neighbour &= ~unchanged

    yaw_flipped = np.zeros(n, dtype=bool)
    if resolve_yaw and np.any(np.hypot(dvx, dvy) >= rule.orientation_speed_mps):
        new_yaw, yaw_flipped = _resolve_modulo_pi(new_yaw, dvx, dvy, np.hypot(dvx, dvy) >= rule.orientation_speed_mps)
        yaw_flipped &= ~(yaw_from_motion | yaw_from_neighbour | yaw_defaulted)  # counted once, as their first repair
    return TrackRepair(
        vx_mps=vx,
        vy_mps=vy,
        yaw_rad=new_yaw,
        velocity_sign_flipped=velocity_sign_flipped,
        velocity_nan=velocity_nan,
        start_velocity=start_velocity,
        yaw_from_motion=yaw_from_motion,
        yaw_from_neighbour=yaw_from_neighbour,
        yaw_defaulted=yaw_defaulted,
        yaw_flipped=yaw_flipped,
    )


def _wrap(angle_rad: np.ndarray | float) -> np.ndarray:
    """Angles in [-pi, pi)."""
    return (np.asarray(angle_rad) + np.pi) % (2.0 * np.pi) - np.pi


def _resolve_modulo_pi(yaw: np.ndarray, dvx: np.ndarray, dvy: np.ndarray, moving: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Choose yaw or yaw + pi per frame: towards the motion, else continuous with the previous frame."""
    out = yaw.copy()
    flipped = np.zeros(yaw.shape[0], dtype=bool)
    motion = np.arctan2(dvy, dvx)
    first_moving = int(np.flatnonzero(moving)[0])
    order = list(range(first_moving, yaw.shape[0])) + list(range(first_moving - 1, -1, -1))
    for i in order:
        if moving[i]:
            ref = motion[i]
        else:
            ref = out[i - 1] if i > first_moving else out[i + 1]
        if np.cos(yaw[i] - ref) < 0.0:
            out[i] = float(_wrap(yaw[i] + np.pi))
            flipped[i] = True
    return out, flipped


def _leading_run(mask: np.ndarray) -> int:
    """Length of the run of True at the start of ``mask``."""
    false = np.flatnonzero(~mask)
    return int(false[0]) if false.size else int(mask.shape[0])
