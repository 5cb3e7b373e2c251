"""Grid fusion stage: merges the MotionGrids (and CorridorPredictions) of ``markov_prediction`` shards, frame by frame.

``markov_prediction`` with ``shard = "i/n"`` predicts only the vehicles
whose id hashes to shard i (CRC-32 of the id, ``stages.lib.grid_fusion``);
this stage takes the shards' ``motion_grid`` on ``grid_0`` … ``grid_3`` and
their ``corridor_predictions`` on ``predictions_0`` … ``predictions_3``
(bind as many as there are shards, the same index for one shard's two
outputs; the runtime binds ``tick`` to every node's NodeStats, which run the
core at least once per stats period) and publishes, per frame (``header.stamp_ns``), ``motion_grid`` =
1 − Π_shards (1 − G_shard) on the union of their lattices and
``corridor_predictions`` = all shards' predictions. The shards may run on
other machines (README, "Spreading stages over machines").

A frame is published as soon as every shard that is up has delivered it. A
shard that has sent nothing for ``shard_timeout_s`` (1 s; killed, stalled,
unreachable; one never heard from: for that long after the first message of
any shard) is down: frames are then published with the other shards'
vehicles only, each such frame counted as an issue ``shard_missing`` (its
detail names the shards), instead of the frame being held back; a shard
that comes back is waited for again. A frame that some shard that is up
has not delivered while ``max_pending_frames`` (20) newer ones wait is
published as it is (also ``shard_missing``), so a shard that skips a frame
(its queue dropped it) costs that frame its vehicles, not the stream.
Inputs of an older stamp than the last published one are dropped
(``late_shard_frame``); grids that cannot be fused with the frame's others
(other cell size, steps, distribution or scene) are left out
(``incompatible_grid``).

The core is pure (``GridFusion``); ``__main__`` binds it to the runtime.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Callable, Mapping

from bus_schemas import CorridorPredictions, Header, MotionGrid
from stages.lib.base import ConfigMixin, Issue, StageResult
from stages.lib.grid_fusion import compatible, fuse_motion_grids, merge_predictions

#: Shard input ports: grid_i and predictions_i for i in 0..MAX_SHARDS-1.
MAX_SHARDS = 4


@dataclass(frozen=True, kw_only=True)
class GridFusionConfig(ConfigMixin):
    """Parameters of the grid_fusion stage (package docstring)."""

    shard_timeout_s: float = 1.0
    max_pending_frames: int = 20

    def __post_init__(self) -> None:
        if not self.shard_timeout_s > 0:
            raise ValueError(f"shard_timeout_s = {self.shard_timeout_s}: must be positive")
        if self.max_pending_frames < 1:
            raise ValueError(f"max_pending_frames = {self.max_pending_frames}: must be at least 1")


@dataclass
class _Frame:
    grids: dict[int, MotionGrid] = field(default_factory=dict)
    predictions: dict[int, CorridorPredictions] = field(default_factory=dict)


class GridFusion:
    """Per-stamp buffer of the shards' outputs; ``update`` publishes the oldest frame that is ready (package docstring)."""

    def __init__(self, config: GridFusionConfig, shards: list[int], *, producer: str = "grid_fusion",
                 clock: Callable[[], float] = time.monotonic) -> None:
        if not shards:
            raise ValueError("grid_fusion: no shard input bound (bind grid_0 ... grid_3)")
        self.config = config
        self.shards = sorted(shards)
        self.producer = producer
        self.clock = clock
        self.started: float | None = None  # the first message from any shard: a shard not heard from yet is up until a timeout after it
        self.last_seen: dict[int, float] = {}
        self.frames: dict[int, _Frame] = {}
        self.last_published = -1
        self._seen: dict[tuple[str, int], int] = {}  # (kind, shard) -> newest stamp taken
        self._label: dict[int, str] = {}  # shard input -> its messages' ``shard`` ("i/n")

    def _up(self, now: float) -> list[int]:
        """Shards heard from within the timeout; one never heard from counts as up until a timeout after the first message."""
        limit = self.config.shard_timeout_s
        return [s for s in self.shards if now - self.last_seen.get(s, self.started if self.started is not None else now) < limit]

    def update(self, inputs: Mapping[str, Any]) -> StageResult:
        issues: list[Issue] = []
        now = self.clock()
        for shard in self.shards:
            for kind, port in (("grid", f"grid_{shard}"), ("predictions", f"predictions_{shard}")):
                msg = inputs.get(port)
                if msg is None:
                    continue
                stamp = int(msg.header.stamp_ns)
                if self._seen.get((kind, shard), -1) >= stamp:
                    continue  # the same latest value again
                self._seen[(kind, shard)] = stamp
                self.last_seen[shard] = now
                if getattr(msg, "shard", ""):
                    self._label[shard] = msg.shard
                if self.started is None:
                    self.started = now
                if stamp <= self.last_published:
                    issues.append(Issue("late_shard_frame", -1, f"shard {shard} {kind} of stamp {stamp} after that frame was published: dropped"))
                    continue
                frame = self.frames.setdefault(stamp, _Frame())
                (frame.grids if kind == "grid" else frame.predictions)[shard] = msg
        return self._publish(now, issues)

    def _publish(self, now: float, issues: list[Issue]) -> StageResult:
        if not self.frames:
            return StageResult(issues=issues)
        up = set(self._up(now))
        stamp = min(self.frames)
        frame = self.frames[stamp]
        have = set(frame.grids)
        complete = up <= have and all(s in frame.predictions for s in have if f"predictions_{s}" in self._bound_predictions)
        if not complete and len(self.frames) <= self.config.max_pending_frames:
            return StageResult(issues=issues)
        del self.frames[stamp]
        self.last_published = stamp
        missing = [s for s in self.shards if s not in have]
        if missing:
            issues.append(Issue("shard_missing", -1, f"stamp {stamp}: no grid from shard(s) {missing} "
                                f"({'down' if not set(missing) & up else 'late'}): published with shard(s) {sorted(have)} only"))
        outputs: dict[str, Any] = {}
        if have:
            first = min(have)
            good = [first]
            for s in sorted(have - {first}):
                why = compatible(frame.grids[first], frame.grids[s])
                if why:
                    issues.append(Issue("incompatible_grid", -1, f"stamp {stamp}: shard {s}'s grid left out: {why}"))
                else:
                    good.append(s)
            grids = [frame.grids[s] for s in good]
            h = grids[0].header
            # every shard carries the source frame's publish time; the earliest, should they ever differ
            wall = min((g.header.source_wall_ns for g in grids if g.header.source_wall_ns), default=0)
            header = Header(run_id=h.run_id, frame_index=h.frame_index, stamp_ns=h.stamp_ns, producer=self.producer, source_wall_ns=wall)
            # the message says whose vehicles it lacks (a consumer cannot tell a missing shard from an empty road)
            outputs["motion_grid"] = fuse_motion_grids(grids, header, self._labels(s for s in self.shards if s not in good))
            parts = [frame.predictions[s] for s in sorted(frame.predictions)]
            if parts:
                outputs["corridor_predictions"] = merge_predictions(
                    parts, header, self._labels(s for s in self.shards if s not in frame.predictions))
        return StageResult(outputs=outputs, issues=issues)

    def _labels(self, shards) -> tuple[str, ...]:
        """The ``missing_shards`` labels ("i/n") of shard inputs: as the shard's messages name it, else i of the bound count."""
        return tuple(self._label.get(s) or f"{s}/{len(self.shards)}" for s in shards)

    _bound_predictions: frozenset[str] = frozenset()


def make(config: GridFusionConfig, input_keys: Mapping[str, str], producer: str) -> GridFusion:
    """The core for the bound inputs: one shard per bound ``grid_i``."""
    shards = sorted(int(p.split("_")[1]) for p in input_keys if p.startswith("grid_"))
    core = GridFusion(config, shards, producer=producer)
    core._bound_predictions = frozenset(p for p in input_keys if p.startswith("predictions_"))
    return core


__all__ = ["INPUTS", "MAX_SHARDS", "OUTPUTS", "SPEC", "GridFusion", "GridFusionConfig", "main", "make"]

_BINDING = ("SPEC", "INPUTS", "OUTPUTS", "main", "make_core")


def __getattr__(name: str):
    """The binding lives in ``__main__.py``; importing it pulls in the runtime (zenoh) only when asked."""
    if name in _BINDING:
        from stages.grid_fusion import __main__ as binding

        return getattr(binding, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
