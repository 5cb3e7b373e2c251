"""Plane geometry of the map library: angles, polylines, centrelines, polygons.

Numpy (and the numba kernel of `kernels` for the windowed projection), no lanelet2: `wrap_angle_rad`, Frenet projection onto a polyline
(`project_to_polyline`, `FrenetPoints`), the smoothed `Centreline` with arc
length, heading and curvature, and the segment and polygon helpers the road
map and the conflict search share. Stages use these directly for corridors.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from stages.lib.maps import kernels


def _frozen(array: np.ndarray) -> np.ndarray:
    out = np.array(array, dtype=np.float64, copy=True)
    out.flags.writeable = False
    return out


def wrap_angle_rad(angle_rad):
    """Wrap angles to [-pi, pi)."""
    return (np.asarray(angle_rad) + np.pi) % (2.0 * np.pi) - np.pi


@dataclass(frozen=True, slots=True, eq=False)
class FrenetPoints:
    """Projections of n points onto a polyline, arrays of shape (n,) float64.

    `d_m` is the signed lateral offset, positive to the left of the direction of
    travel; `heading_rad` is the polyline's heading at `s_m`. Points beyond
    either end project onto the straight extension of the end segment, so `s_m`
    can be negative or exceed the length.
    """

    s_m: np.ndarray
    d_m: np.ndarray
    heading_rad: np.ndarray


def project_to_polyline(
    points_m,
    polyline_m,
    s_m=None,
    heading_rad=None,
    *,
    s_hint_m=None,
    window_m: float | None = None,
) -> FrenetPoints:
    """Project points (n, 2) onto a polyline (m, 2), vectorised over points and segments.

    `s_m` (m,) is the polyline's arc length (computed if absent) and
    `heading_rad` (m,) its heading, interpolated at the foot point when given
    (else the segment's direction). With `s_hint_m` (scalar or (n,)) and
    `window_m`, only segments within `window_m` of the hint are candidates,
    which keeps projections continuous at joins and on tight curves; a point
    with no candidate falls back to all segments.
    """
    points = np.atleast_2d(np.asarray(points_m, dtype=np.float64))
    line = np.asarray(polyline_m, dtype=np.float64)
    if line.ndim != 2 or line.shape[0] < 2 or line.shape[1] != 2:
        raise ValueError("polyline_m must have shape (m >= 2, 2)")
    if s_m is not None and s_hint_m is not None and window_m is not None:
        windowed = _project_in_window(points, line, np.asarray(s_m, np.float64), s_hint_m, float(window_m), heading_rad)
        if windowed is not None:
            return windowed
    seg = np.diff(line, axis=0)
    seg_len = np.hypot(seg[:, 0], seg[:, 1])
    arc = np.concatenate([[0.0], np.cumsum(seg_len)]) if s_m is None else np.asarray(s_m, np.float64)
    seg_len2 = np.maximum(seg_len**2, 1e-18)
    n_seg = len(seg)
    lower = np.zeros(n_seg)
    upper = np.ones(n_seg)
    lower[0] = -np.inf
    upper[-1] = np.inf
    hints = None
    if s_hint_m is not None and window_m is not None:
        hints = np.broadcast_to(np.asarray(s_hint_m, np.float64), (len(points),))
    n_pts = len(points)
    out_s = np.empty(n_pts)
    out_d = np.empty(n_pts)
    out_seg = np.empty(n_pts, dtype=np.int64)
    chunk = max(1, 2_000_000 // max(n_seg, 1))
    for start in range(0, n_pts, chunk):
        p = points[start : start + chunk]
        rel = p[:, None, :] - line[None, :-1, :]
        t = np.clip((rel * seg[None]).sum(axis=2) / seg_len2[None], lower[None], upper[None])
        foot = line[None, :-1, :] + t[..., None] * seg[None]
        dist2 = ((p[:, None, :] - foot) ** 2).sum(axis=2)
        if hints is not None:
            h = hints[start : start + chunk, None]
            outside = (arc[None, 1:] < h - window_m) | (arc[None, :-1] > h + window_m)
            masked = np.where(outside, np.inf, dist2)
            usable = np.isfinite(masked).any(axis=1)
            dist2 = np.where(usable[:, None], masked, dist2)
        j = dist2.argmin(axis=1)
        rows = np.arange(len(p))
        tj = t[rows, j]
        out_s[start : start + chunk] = arc[j] + tj * seg_len[j]
        ux, uy = seg[j, 0] / np.sqrt(seg_len2[j]), seg[j, 1] / np.sqrt(seg_len2[j])
        rx, ry = rel[rows, j, 0], rel[rows, j, 1]
        out_d[start : start + chunk] = ux * ry - uy * rx
        out_seg[start : start + chunk] = j
    if heading_rad is None:
        heading = np.arctan2(seg[out_seg, 1], seg[out_seg, 0])
    else:
        unwrapped = np.unwrap(np.asarray(heading_rad, np.float64))
        heading = wrap_angle_rad(np.interp(out_s, arc, unwrapped))
    return FrenetPoints(s_m=out_s, d_m=out_d, heading_rad=heading)


def project_in_window(points_m, polyline_m, s_m, s_hint_m, window_m: float) -> tuple[np.ndarray, np.ndarray]:
    """(s, d) (n,) of `project_to_polyline(points, polyline, s_m, s_hint_m=..., window_m=...)`, without the heading.

    For the hot loops (a vehicle on each of its routes, conflict points on
    lane-change corridors): the compiled kernel is called directly, with
    `project_to_polyline` where it declines; the values are the same bit for bit.
    With `window_m` = inf (any finite hint) every segment is in every window:
    the (s, d) of `project_to_polyline(points, polyline, s_m)` without hints,
    bit for bit (the same arithmetic per segment, the first nearest wins).
    """
    points = np.atleast_2d(np.asarray(points_m, dtype=np.float64))
    line = np.asarray(polyline_m, dtype=np.float64)
    arc = np.asarray(s_m, dtype=np.float64)
    hints = np.array(np.broadcast_to(np.asarray(s_hint_m, np.float64), (len(points),)))  # a writable copy: one kernel signature
    if line.ndim == 2 and line.shape[0] >= 2 and line.shape[1] == 2:
        found = kernels.project_window(points, line, arc, hints, window_m)
        if found is not None:
            return found[0], found[1]
    fr = project_to_polyline(points, line, arc, s_hint_m=hints, window_m=window_m)
    return fr.s_m, fr.d_m


def _project_in_window(points, line, arc, s_hint_m, window_m: float, heading_rad, *, compiled: bool = True) -> FrenetPoints | None:
    """`project_to_polyline` with hints, measuring only the segments within each point's window; None where it can't.

    On a non-decreasing arc the segments within the window of a hint are one
    range [lo, hi) (by searchsorted); each point is measured against its own
    range (padded to the longest, the padding masked) with the same arithmetic
    per segment as the general path (the end segments extended), so the
    nearest segment and the result are the same bit for bit. None (the caller
    takes the general path) for non-finite hints, an arc of another shape or
    decreasing, or a point with no segment in its window (the general path
    falls back to every segment for it). With `compiled` (and numba) the
    numba kernel `kernels.project_window` does the same arithmetic point by
    point (the numpy code below is its reference and its fallback).
    """
    n_seg = len(line) - 1
    n_pts = len(points)
    hints = np.broadcast_to(np.asarray(s_hint_m, np.float64), (n_pts,))
    found = kernels.project_window(points, line, arc, np.array(hints), window_m) if compiled else None
    if found is not None:  # the same arithmetic, compiled (stages.lib.maps.kernels)
        out_s, out_d, j = found
        if heading_rad is None:
            sj = line[j + 1] - line[j]
            heading = np.arctan2(sj[:, 1], sj[:, 0])
        else:
            heading = wrap_angle_rad(np.interp(out_s, arc, np.unwrap(np.asarray(heading_rad, np.float64))))
        return FrenetPoints(s_m=out_s, d_m=out_d, heading_rad=heading)
    if not n_pts or n_seg < 2 or arc.shape != (n_seg + 1,) or not np.isfinite(hints).all() or not (arc[1:] >= arc[:-1]).all():
        return None
    lo = np.searchsorted(arc[1:], hints - window_m, side="left")
    hi = np.searchsorted(arc[:-1], hints + window_m, side="right")
    if (lo >= hi).any():
        return None
    width = int((hi - lo).max())
    idx = lo[:, None] + np.arange(width)[None, :]  # (n, width) segment indices, beyond hi masked below
    pad = idx >= hi[:, None]
    idx = np.minimum(idx, n_seg - 1)
    start = line[idx]  # (n, width, 2)
    seg = line[idx + 1] - start
    seg_len = np.hypot(seg[..., 0], seg[..., 1])
    seg_len2 = np.maximum(seg_len**2, 1e-18)
    lower = np.where(idx == 0, -np.inf, 0.0)
    upper = np.where(idx == n_seg - 1, np.inf, 1.0)
    rel = points[:, None, :] - start
    t = np.clip((rel * seg).sum(axis=2) / seg_len2, lower, upper)
    foot = start + t[..., None] * seg
    dist2 = ((points[:, None, :] - foot) ** 2).sum(axis=2)
    h = hints[:, None]
    outside = pad | (arc[idx + 1] < h - window_m) | (arc[idx] > h + window_m)
    masked = np.where(outside, np.inf, dist2)
    if not np.isfinite(masked).any(axis=1).all():
        return None
    j = masked.argmin(axis=1)
    rows = np.arange(n_pts)
    sj = seg[rows, j]
    out_s = arc[idx[rows, j]] + t[rows, j] * seg_len[rows, j]
    ux, uy = sj[:, 0] / np.sqrt(seg_len2[rows, j]), sj[:, 1] / np.sqrt(seg_len2[rows, j])
    out_d = ux * rel[rows, j, 1] - uy * rel[rows, j, 0]
    if heading_rad is None:
        heading = np.arctan2(sj[:, 1], sj[:, 0])
    else:
        unwrapped = np.unwrap(np.asarray(heading_rad, np.float64))
        heading = wrap_angle_rad(np.interp(out_s, arc, unwrapped))
    return FrenetPoints(s_m=out_s, d_m=out_d, heading_rad=heading)


@dataclass(frozen=True, slots=True, eq=False)
class Centreline:
    """A resampled, lightly smoothed centreline; arrays (n,) float64, read-only.

    `s_m` is the cumulative arc length from 0, `heading_rad` the direction of
    travel and `curvature_1pm` its derivative along s (positive to the left).
    """

    x_m: np.ndarray
    y_m: np.ndarray
    s_m: np.ndarray
    heading_rad: np.ndarray
    curvature_1pm: np.ndarray

    @classmethod
    def from_points(cls, points_m, step_m: float = 0.5, smoothing_m: float = 1.0) -> Centreline:
        """Resample a polyline (m >= 2, 2) to about `step_m` and smooth it.

        The smoothing is a Gaussian of standard deviation `smoothing_m` over a
        point-reflected extension, so both end points stay where they are and
        consecutive lanelets still meet.
        """
        raw = np.asarray(points_m, dtype=np.float64)[:, :2]
        keep = np.concatenate([[True], np.hypot(*np.diff(raw, axis=0).T) > 1e-9])
        raw = raw[keep]
        if len(raw) < 2:
            raise ValueError("a centreline needs two distinct points")
        raw_s = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(raw, axis=0).T))])
        n = max(2, int(math.ceil(raw_s[-1] / step_m)) + 1)
        s = np.linspace(0.0, raw_s[-1], n)
        pts = np.column_stack([np.interp(s, raw_s, raw[:, 0]), np.interp(s, raw_s, raw[:, 1])])
        sigma = smoothing_m / (raw_s[-1] / (n - 1))
        radius = min(int(math.ceil(3.0 * sigma)), n - 1)
        if sigma > 0.0 and radius >= 1:
            kernel = np.exp(-0.5 * (np.arange(-radius, radius + 1) / sigma) ** 2)
            kernel /= kernel.sum()
            head = 2.0 * pts[0] - pts[radius:0:-1]
            tail = 2.0 * pts[-1] - pts[-2 : -radius - 2 : -1]
            padded = np.concatenate([head, pts, tail])
            pts = np.column_stack([np.convolve(padded[:, k], kernel, mode="valid") for k in range(2)])
        return cls.from_resampled(pts)

    @classmethod
    def from_resampled(cls, points_m) -> Centreline:
        """Build from points that are already dense and smooth (no resampling)."""
        pts = np.asarray(points_m, dtype=np.float64)
        s = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(pts, axis=0).T))])
        dx = np.gradient(pts[:, 0], s) if len(s) > 2 else np.full(len(s), pts[-1, 0] - pts[0, 0])
        dy = np.gradient(pts[:, 1], s) if len(s) > 2 else np.full(len(s), pts[-1, 1] - pts[0, 1])
        heading = np.unwrap(np.arctan2(dy, dx))
        curvature = np.gradient(heading, s) if len(s) > 2 else np.zeros(len(s))
        return cls(
            x_m=_frozen(pts[:, 0]),
            y_m=_frozen(pts[:, 1]),
            s_m=_frozen(s),
            heading_rad=_frozen(wrap_angle_rad(heading)),
            curvature_1pm=_frozen(curvature),
        )

    @property
    def length_m(self) -> float:
        return float(self.s_m[-1])

    @property
    def points_m(self) -> np.ndarray:
        """(n, 2) float64 copy of the points."""
        return np.column_stack([self.x_m, self.y_m])

    def heading_at(self, s_m) -> np.ndarray:
        return wrap_angle_rad(np.interp(s_m, self.s_m, np.unwrap(self.heading_rad)))

    def to_xy(self, s_m, d_m=0.0) -> np.ndarray:
        """Points (n, 2) at arc lengths `s_m` and left offsets `d_m`; straight beyond the ends."""
        s = np.atleast_1d(np.asarray(s_m, dtype=np.float64))
        d = np.broadcast_to(np.asarray(d_m, dtype=np.float64), s.shape)
        heading = self.heading_at(s)
        x = np.interp(s, self.s_m, self.x_m)
        y = np.interp(s, self.s_m, self.y_m)
        for beyond, s_end, idx in ((s < 0.0, 0.0, 0), (s > self.length_m, self.length_m, -1)):
            h = self.heading_rad[idx]
            x = np.where(beyond, self.x_m[idx] + (s - s_end) * math.cos(h), x)
            y = np.where(beyond, self.y_m[idx] + (s - s_end) * math.sin(h), y)
        return np.column_stack([x - d * np.sin(heading), y + d * np.cos(heading)])

    def project(self, points_m, *, s_hint_m=None, window_m: float | None = None) -> FrenetPoints:
        """Frenet coordinates of points (n, 2); see `project_to_polyline`."""
        return project_to_polyline(
            points_m, self.points_m, self.s_m, self.heading_rad, s_hint_m=s_hint_m, window_m=window_m
        )


def concatenate_centrelines(centrelines: Sequence[Centreline]) -> Centreline:
    """Join the centrelines of a lanelet sequence into one, dropping repeated join points."""
    parts = [centrelines[0].points_m]
    for line in centrelines[1:]:
        pts = line.points_m
        if np.hypot(*(pts[0] - parts[-1][-1])) < 1e-6:
            pts = pts[1:]
        if len(pts):
            parts.append(pts)
    return Centreline.from_resampled(np.concatenate(parts))



def _polygon_area_m2(polygon: np.ndarray) -> float:
    x, y = polygon[:, 0], polygon[:, 1]
    return 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))


def _distance_to_polyline_m(points: np.ndarray, line: np.ndarray) -> np.ndarray:
    seg = np.diff(line, axis=0)
    len2 = np.maximum((seg**2).sum(axis=1), 1e-18)
    rel = points[:, None, :] - line[None, :-1, :]
    t = np.clip((rel * seg[None]).sum(axis=2) / len2[None], 0.0, 1.0)
    diff = rel - t[..., None] * seg[None]
    return np.sqrt((diff**2).sum(axis=2).min(axis=1))


def segment_intersections(line_a: np.ndarray, line_b: np.ndarray):
    """All intersections of two polylines, every segment pair at once.

    Returns (i, j, t, u): segment indices on a and b and the fractions along
    those segments, arrays of equal length.
    """
    a0, r = line_a[:-1], np.diff(line_a, axis=0)
    b0, q = line_b[:-1], np.diff(line_b, axis=0)
    denom = r[:, None, 0] * q[None, :, 1] - r[:, None, 1] * q[None, :, 0]
    diff = b0[None, :, :] - a0[:, None, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (diff[..., 0] * q[None, :, 1] - diff[..., 1] * q[None, :, 0]) / denom
        u = (diff[..., 0] * r[:, None, 1] - diff[..., 1] * r[:, None, 0]) / denom
    hit = (np.abs(denom) > 1e-12) & (t >= 0.0) & (t <= 1.0) & (u >= 0.0) & (u <= 1.0)
    i, j = np.nonzero(hit)
    return i, j, t[i, j], u[i, j]

