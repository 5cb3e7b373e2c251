"""Online spread: the grids widened, as the vehicles move on, until their 90 % regions hold where the vehicles went.

A spread table (``spread.py``, ``iamp calibrate``) belongs to the location
and the model it was fitted on; on another location the grids of fast cars
held the truth in their 90 % region in only 0.81 of the windows (docs/evaluation.md,
"Online spread"). This widens them from what the stage sees
anyway, causally: every ``stride_s`` it keeps each predicted vehicle's grid
(its start-speed band and the step grids, references, no copies); when a
later ``TrackFrame`` has that vehicle at one of the prediction's step times
(within half a frame), it checks whether the vehicle's cell lies in the
``target`` highest-probability region of that step's grid (the rule of
``iamp eval``'s coverage90) and moves the band's extra spread c[band]
(m/s, one for all steps) by ``rate_mps`` · (missed − (1 − target)): up by
rate·target on a miss, down by rate·(1 − target) on a hit, so that it
settles where the region misses a share 1 − target of the checks (a
stochastic-approximation quantile tracker). c stays in [0, ``max_mps``]: the
spread is never narrowed below the table's (or the chain's own).

The grids of band b are blurred at step k by σ_k = √(table_k² + (c[b]·t_k)²)
(``sigmas``; t_k the step's time): the extra spread grows with the horizon
as an error in speed does. Round, or along each corridor with
``spread_shape = "along"`` (``spread.blur_along``); the checks are the same. One c per band, not per step: the checks of all
steps together reach the target (as ``iamp eval`` counts coverage90 over the
steps); per step, the early steps, which the chain already spreads enough,
were widened too and the grids' NLL rose (docs/evaluation.md, "Online spread"). Only
vehicles starting faster than ``min_speed_mps`` (2 m/s, the slow/fast split)
are widened and checked: a standing or slow car's misses are starts and
stops, which an isotropic blur does not model (widening them raised the slow
cars' NLL on both locations while their coverage was already 0.91-0.92). The mean positions (``CorridorPredictions``,
mADE) do not change. What it learnt is kept across ``reset`` (it belongs to
the location and the tracker, not to a track); the kept predictions are not.

Counted for the stop summary and the tests: ``checks`` and ``misses`` per
band, and the current ``extra_mps`` table.
"""

from __future__ import annotations

import collections
import math
from dataclasses import dataclass, field

import numpy as np

from stages.markov_prediction.rasterise import GridFrame, SparseGrid, highest_density_threshold

#: start-speed bands (m/s, the upper edges of all but the last) when no spread table gives them: standing, slow, fast
DEFAULT_BANDS_MPS = (0.5, 2.0)


@dataclass(slots=True)
class _Kept:
    stamp_ns: int
    frame: GridFrame
    grids: dict[int, tuple[int, SparseGrid]]  # track id -> (band, grid)
    done: set = field(default_factory=set)  # the steps already checked


class OnlineSpread:
    """The extra spread per start-speed band and step, learnt from the vehicles' later positions (module docstring)."""

    def __init__(self, step_times_s: np.ndarray, *, bands_mps: tuple[float, ...] = DEFAULT_BANDS_MPS, target: float = 0.9,
                 rate_mps: float = 0.05, max_mps: float = 1.5, min_speed_mps: float = 2.0, stride_s: float = 0.4,
                 tolerance_s: float = 0.05) -> None:
        if not (0.0 < target < 1.0):
            raise ValueError(f"spread_online_target = {target}: must lie in (0, 1)")
        if not (rate_mps > 0 and max_mps > 0 and stride_s > 0 and tolerance_s > 0):
            raise ValueError("spread_online_rate_mps, spread_online_max_mps, the stride and the tolerance must be > 0")
        self.step_times_s = np.asarray(step_times_s, dtype=np.float64)
        self.bands_mps = tuple(float(b) for b in bands_mps)
        self.target, self.rate_mps, self.max_mps = float(target), float(rate_mps), float(max_mps)
        self.min_speed_mps = float(min_speed_mps)
        self._stride_ns = int(round(stride_s * 1e9))
        self._tolerance_ns = int(round(tolerance_s * 1e9))
        self._step_ns = np.round(self.step_times_s * 1e9).astype(np.int64)
        n_bands = len(self.bands_mps) + 1
        #: c[band] (m/s): the extra spread's growth per second of horizon
        self.extra_mps = np.zeros(n_bands)
        self.checks = np.zeros(n_bands, np.int64)
        self.misses = np.zeros(n_bands, np.int64)
        self._kept: collections.deque[_Kept] = collections.deque()
        self._last_kept_ns: int | None = None

    def band(self, speed_mps: float) -> int:
        return int(np.searchsorted(np.asarray(self.bands_mps), speed_mps, side="left")) if math.isfinite(speed_mps) else 0

    def extra_sigmas(self, speed_mps: float) -> np.ndarray:
        """(n_steps,) the extra σ (m) of a vehicle of this start speed: c[band]·t_k (0 at or below ``min_speed_mps``)."""
        if not speed_mps > self.min_speed_mps:
            return np.zeros(self.step_times_s.size)
        return float(self.extra_mps[self.band(speed_mps)]) * self.step_times_s

    def max_sigma_m(self) -> float:
        """The widest extra σ it can ever give (the grid's margin keeps a blur of it on the grid)."""
        return float(self.max_mps * self.step_times_s.max()) if self.step_times_s.size else 0.0

    def reset(self) -> None:
        """Forget the kept predictions (a new sequence: their vehicles are gone); the extra spread stays."""
        self._kept.clear()
        self._last_kept_ns = None

    def update(self, stamp_ns: int, positions: dict[int, tuple[float, float]], frame: GridFrame | None,
               grids: dict[int, SparseGrid], speeds_mps: dict[int, float]) -> int:
        """One frame: check the kept predictions against ``positions`` (track id -> x, y of this stamp), then keep this
        frame's ``grids`` (track id -> grid, start speeds ``speeds_mps``) when ``stride_s`` has passed since the last
        kept. Returns the number of checks made."""
        stamp = int(stamp_ns)
        if self._last_kept_ns is not None and stamp < self._last_kept_ns:
            self.reset()  # time went back: the kept predictions say nothing about these positions
        made = self._check(stamp, positions)
        horizon = int(self._step_ns[-1]) + self._tolerance_ns if self._step_ns.size else 0
        while self._kept and stamp - self._kept[0].stamp_ns > horizon:
            self._kept.popleft()
        if frame is not None and grids and (self._last_kept_ns is None or stamp - self._last_kept_ns >= self._stride_ns - self._tolerance_ns):
            moving = {t: g for t, g in grids.items() if speeds_mps.get(t, math.nan) > self.min_speed_mps}
            self._kept.append(_Kept(stamp, frame, {t: (self.band(speeds_mps[t]), g) for t, g in moving.items()}))
            self._last_kept_ns = stamp
        return made

    def _check(self, stamp: int, positions: dict[int, tuple[float, float]]) -> int:
        made = 0
        up, down = self.rate_mps * self.target, self.rate_mps * (1.0 - self.target)
        for kept in self._kept:
            dt = stamp - kept.stamp_ns
            hit = np.flatnonzero(np.abs(self._step_ns - dt) <= self._tolerance_ns)
            for k in hit.tolist():
                if k in kept.done:
                    continue
                kept.done.add(k)
                n_cells = kept.frame.n_cells
                for track, (band, grid) in kept.grids.items():
                    xy = positions.get(track)
                    if xy is None or not (math.isfinite(xy[0]) and math.isfinite(xy[1])):
                        continue
                    cells, values = grid.step(k, n_cells)
                    cell = int(kept.frame.flat_index(np.array([xy[0]]), np.array([xy[1]]))[0])
                    value = 0.0
                    if cell >= 0 and cells.size:
                        i = int(np.searchsorted(cells, cell))
                        if i < cells.size and cells[i] == cell:
                            value = float(values[i])
                    missed = not (value > 0 and value >= highest_density_threshold(values, self.target))
                    c = self.extra_mps[band] + (up if missed else -down)
                    self.extra_mps[band] = min(max(c, 0.0), self.max_mps)
                    self.checks[band] += 1
                    self.misses[band] += int(missed)
                    made += 1
        return made

    def summary(self) -> dict[str, object]:
        """Checks, misses and the extra spread at the last step per band (for the stop summary)."""
        return {"checks": self.checks.tolist(), "misses": self.misses.tolist(),
                "extra_m_last_step": np.round(self.extra_mps * self.step_times_s[-1], 2).tolist() if self.step_times_s.size else []}
