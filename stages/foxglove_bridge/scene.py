"""Bus messages -> Foxglove schemas: the scene that the exporter writes and the live bridge serves.

``FoxgloveScene`` takes our decoded bus messages one by one (``add(topic,
message, log_time_ns)``) in the order they were recorded or received and
logs their Foxglove form on ``foxglove`` channels of one ``foxglove.Context``
(an MCAP writer or a WebSocket server is the sink, opened on that context by
the caller). Results are joined to their track frames by ``header.stamp_ns``
here, as the viewer does: a corridor set waits for the predictions of its
stamp (its lines' widths are their probabilities), a belief for the frame of
its stamp (its texts sit at the vehicles).

Foxglove topics (``<node>`` is the producing node of the bus key,
``iamp/<run>/<node>/<port>``):

- ``/map`` ``foxglove.SceneUpdate``: the lanelet map, car lanelet bounds and
  the others' outlines as ``LinePrimitive`` line lists (once per scene);
- ``/tf`` ``foxglove.FrameTransform``: ``world`` -> ``map`` (identity; every
  entity is in ``map``, metres of the scene, x east, y north);
- ``/objects`` ``foxglove.SceneUpdate``: one cube per object coloured by its
  type, with its track id as a text;
- ``/<node>/corridors`` ``foxglove.SceneUpdate``: every vehicle's corridors as
  centrelines, thickness 0.15 + 1.2 * P(route) m, labelled ``p=...``;
- ``/<node>/means`` ``foxglove.SceneUpdate``: the predicted mean of every
  corridor at every step (a line through them, a sphere at each step; blue
  for mode hybrid, red for baseline, else black);
- ``/<node>/motion_grid`` ``foxglove.Grid``: the motion grid (float32 field
  ``occupancy``) of the chosen step, or the maximum over steps
  (``grid_step="max"``), or one topic ``/<node>/motion_grid/<t>s`` per step
  (``grid_step="all"``); cropped to the cells above zero;
- ``/<node>/vehicles`` ``foxglove.SceneUpdate``: per vehicle of an
  ``IntentionBelief`` a text ``P(stop)`` and its top route (manoeuvre, P);
- ``/<node>/coverage`` ``foxglove.Log``: a line each time what the node's
  motion grids cover changes: a shard's own vehicles only, a shard missing
  from a fused frame (``MotionGrid.shard``, ``missing_shards``), whole again;
- ``/stats/<node>`` JSON (schema ``iamp.NodeStatsPlot``): the node's
  ``NodeStats`` flattened to numbers (processing and latency percentiles,
  queue depth, every counter) for Foxglove's Plot panel.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

import foxglove
from foxglove import channels as fch
from foxglove import messages as fm

from bus_schemas import CorridorPredictions, CorridorSet, IntentionBelief, Manoeuvre, MotionGrid, NodeStats, SceneInfo, TrackFrame, coverage

FRAME_ID = "map"
# RGB 0-1 by AgentType value (the viewer's palette)
TYPE_COLOURS: dict[int, tuple[float, float, float]] = {
    0: (0.59, 0.59, 0.59),
    1: (0.12, 0.56, 1.0),
    2: (0.0, 0.27, 0.78),
    3: (0.43, 0.27, 0.9),
    4: (0.0, 0.78, 0.78),
    5: (0.0, 0.63, 0.31),
    6: (0.9, 0.24, 0.78),
}
TYPE_HEIGHTS_M: dict[int, float] = {1: 1.5, 2: 3.0, 3: 3.0, 4: 1.2, 5: 1.2, 6: 1.8}
TYPE_DEFAULT_SIZE_M: dict[int, tuple[float, float]] = {0: (1.0, 1.0), 1: (4.5, 1.8), 2: (8.0, 2.5), 3: (12.0, 2.5), 4: (2.0, 0.8), 5: (1.8, 0.6), 6: (0.6, 0.6)}
MODE_COLOURS = {"hybrid": (0.12, 0.35, 1.0), "baseline": (0.9, 0.12, 0.12)}  # the means, as the viewer's compare view; other modes black
CORRIDOR_THICKNESS_M = (0.15, 1.2)  # thickness = a + b * P(route)
GRID_STEPS = ("max", "all")  # besides a step time in seconds
_KEEP_STAMPS = 64  # frames and corridor sets kept for the stamp join (and stamps of messages waiting for theirs)
_NO_CORRIDORS = "predictions without the corridor set of their stamp"
_NO_FRAME = "belief without the track frame of its stamp"

STATS_SCHEMA = {
    "type": "object",
    "title": "iamp.NodeStatsPlot",
    "properties": {
        "node_id": {"type": "string"},
        "stage": {"type": "string"},
        "uptime_s": {"type": "number"},
        "proc_ms_p50": {"type": "number"},
        "proc_ms_p95": {"type": "number"},
        "proc_ms_max": {"type": "number"},
        "latency_ms_p50": {"type": "number"},
        "latency_ms_p95": {"type": "number"},
        "e2e_ms_p50": {"type": "number"},
        "e2e_ms_p95": {"type": "number"},
        "queue_depth": {"type": "integer"},
        "counters": {"type": "object", "additionalProperties": {"type": "integer"}},
        "issues": {"type": "object", "additionalProperties": {"type": "integer"}},
        "errors": {"type": "object", "additionalProperties": {"type": "integer"}},
    },
}


def parse_grid_step(value: str) -> str | float:
    """``max``, ``all`` or a step time in seconds (> 0); ValueError otherwise."""
    text = str(value).strip().lower()
    if text in GRID_STEPS:
        return text
    t = float(text)
    if not (math.isfinite(t) and t > 0):
        raise ValueError(f"grid step {value!r}: expected max, all or a time in seconds > 0")
    return t


def node_of(topic: str) -> str:
    """The producing node of a bus key ``iamp/<run>/<node>/<port>`` (``_stats/<node>``: the node)."""
    parts = topic.split("/")
    if len(parts) >= 4 and parts[2] == "_stats":
        return parts[3]
    return parts[2] if len(parts) >= 4 else (parts[-1] or "unknown")


def timestamp(ns: int) -> fm.Timestamp:
    ns = max(int(ns), 0)
    return fm.Timestamp(sec=ns // 1_000_000_000, nsec=ns % 1_000_000_000)


def _colour(rgb: tuple[float, float, float], a: float = 1.0) -> fm.Color:
    return fm.Color(r=float(rgb[0]), g=float(rgb[1]), b=float(rgb[2]), a=float(a))


def _pose(x: float = 0.0, y: float = 0.0, z: float = 0.0, yaw: float = 0.0) -> fm.Pose:
    return fm.Pose(position=fm.Vector3(x=float(x), y=float(y), z=float(z)), orientation=fm.Quaternion(x=0.0, y=0.0, z=math.sin(yaw / 2.0), w=math.cos(yaw / 2.0)))


def _points(xy: np.ndarray, z: float) -> list[fm.Point3]:
    return [fm.Point3(x=float(x), y=float(y), z=z) for x, y in xy]


def _line_list(polylines: list[np.ndarray], colour: fm.Color, thickness: float, z: float) -> fm.LinePrimitive | None:
    """Polylines as one line list (pairs of points), world-size thickness."""
    pts: list[fm.Point3] = []
    for line in polylines:
        line = np.asarray(line, dtype=float).reshape(-1, 2)
        line = line[np.all(np.isfinite(line), axis=1)]
        for a, b in zip(line[:-1], line[1:]):
            pts += [fm.Point3(x=float(a[0]), y=float(a[1]), z=z), fm.Point3(x=float(b[0]), y=float(b[1]), z=z)]
    if not pts:
        return None
    return fm.LinePrimitive(type=fm.LinePrimitiveLineType.LineList, pose=_pose(), thickness=thickness, scale_invariant=False, points=pts, color=colour)


@dataclass
class SceneCounts:
    """What ``FoxgloveScene`` logged, per Foxglove topic, and what it could not use."""

    logged: dict[str, int] = field(default_factory=dict)
    skipped: dict[str, int] = field(default_factory=dict)  # reason -> count
    unheard: int = 0  # messages not built: nobody (no client, no file) listened on their channel
    map_problems: list[str] = field(default_factory=list)

    def log(self, topic: str) -> None:
        self.logged[topic] = self.logged.get(topic, 0) + 1

    def skip(self, reason: str, count: int = 1) -> None:
        if count:
            self.skipped[reason] = self.skipped.get(reason, 0) + count


def map_lines(scene: SceneInfo, data: str | None) -> tuple[list[np.ndarray], list[np.ndarray], list[str]]:
    """The scene's lanelet bounds (car lanelets, others) in the scene frame, found by name in ``data``/maps and checked by sha256."""
    from stages.lib import maps

    projection = maps.resolve_projection("auto", scene)
    path, problem = maps.local_map_file(data, scene)
    if path is None:
        return [], [], [problem]
    try:
        lanelets, problems = maps.lanelet_bounds(path, scene.origin_lat_deg, scene.origin_lon_deg, projection)
    except Exception as exc:  # noqa: BLE001 - a map that does not load is drawn as nothing, with its reason
        return [], [], [f"map_load_failed: {type(exc).__name__}: {exc}"]
    if lanelets is None:
        return [], [], [p.detail for p in problems] or ["map did not load"]
    car = [b for x in lanelets if x.is_car for b in (x.left_bound_m, x.right_bound_m)]
    other = [b for x in lanelets if not x.is_car for b in (x.left_bound_m, x.right_bound_m)]
    return car, other, []


class FoxgloveScene:
    """Turns bus messages into Foxglove messages on channels of ``context`` (module docstring)."""

    def __init__(self, context: foxglove.Context, *, data: str | None = None, grid_step: str | float = "max") -> None:
        self.context = context
        self.data = data or None
        self.grid_step = grid_step if isinstance(grid_step, float) else parse_grid_step(grid_step)
        self.counts = SceneCounts()
        self._channels: dict[str, Any] = {}
        self._frames: dict[int, TrackFrame] = {}
        self._corridor_sets: dict[tuple[str, int], CorridorSet] = {}
        # what came before the message it is drawn with (a recorder logs messages as they arrive, so a prediction can
        # precede its frame's corridor set): held until it comes, by stamp; dropped and counted when never
        self._waiting_predictions: dict[int, list[tuple[str, CorridorPredictions]]] = {}
        self._waiting_beliefs: dict[int, list[tuple[str, IntentionBelief]]] = {}
        self._map_scene_id: str | None = None
        self._map_update: fm.SceneUpdate | None = None
        self._coverage: dict[str, str] = {}  # node -> what its last grid lacked ("" whole)

    # ------------------------------------------------------------------ channels
    def _channel(self, topic: str, make: Callable[..., Any]) -> Any:
        ch = self._channels.get(topic)
        if ch is None:
            ch = self._channels[topic] = make(topic, context=self.context)
        return ch

    def _log(self, topic: str, make: Callable[..., Any], msg: Any, log_time_ns: int) -> None:
        """Log ``msg`` on ``topic``; ``msg`` a function that builds it: built only where the channel has a sink (a client
        subscribed to it, an MCAP file): with no Foxglove client the live bridge built every frame's entities for
        nobody, a quarter of a core at 72 vehicles."""
        channel = self._channel(topic, make)
        if callable(msg):
            if not channel.has_sinks():
                self.counts.unheard += 1
                return
            msg = msg()
        channel.log(msg, log_time=int(log_time_ns))
        self.counts.log(topic)

    def topics(self) -> list[str]:
        return sorted(self._channels)

    # ------------------------------------------------------------------ input
    def add(self, topic: str, message: Any, log_time_ns: int) -> None:
        """One decoded bus message, received on bus key ``topic`` at ``log_time_ns``."""
        if isinstance(message, TrackFrame):
            self.add_frame(message, log_time_ns)
        elif isinstance(message, SceneInfo):
            self.add_scene(message, log_time_ns)
        elif isinstance(message, CorridorSet):
            self.add_corridor_set(node_of(topic), message, log_time_ns)
        elif isinstance(message, CorridorPredictions):
            self.add_predictions(node_of(topic), message, log_time_ns)
        elif isinstance(message, MotionGrid):
            self.add_grid(node_of(topic), message, log_time_ns)
        elif isinstance(message, IntentionBelief):
            self.add_belief(node_of(topic), message, log_time_ns)
        elif isinstance(message, NodeStats):
            self.add_stats(message, log_time_ns)
        else:
            self.counts.skip(f"not shown: {type(message).__name__}")

    @staticmethod
    def _keep(store: dict, key: Any, value: Any) -> None:
        store[key] = value
        while len(store) > _KEEP_STAMPS:
            store.pop(next(iter(store)))

    def _wait(self, store: dict, stamp: int, item: Any, reason: str) -> None:
        store.setdefault(stamp, []).append(item)
        while len(store) > _KEEP_STAMPS:  # what never found its partner
            self.counts.skip(reason, len(store.pop(next(iter(store)))))

    def finish(self) -> None:
        """The end of the input (an export's last message): what still waits for its partner is counted as left out."""
        for store, reason in ((self._waiting_predictions, _NO_CORRIDORS), (self._waiting_beliefs, _NO_FRAME)):
            for items in store.values():
                self.counts.skip(reason, len(items))
            store.clear()

    def add_scene(self, scene: SceneInfo, log_time_ns: int) -> None:
        """The map of a new scene (once per scene id), and the ``world`` -> ``map`` transform."""
        if scene.scene_id == self._map_scene_id:
            return
        self._map_scene_id = scene.scene_id
        car, other, problems = map_lines(scene, self.data)
        self.counts.map_problems += problems
        ts = timestamp(scene.header.stamp_ns)
        lines = [x for x in (
            _line_list(car, _colour((0.8, 0.8, 0.82)), 0.12, 0.0),
            _line_list(other, _colour((0.55, 0.55, 0.6)), 0.08, 0.0),
        ) if x is not None]
        entity = fm.SceneEntity(timestamp=ts, frame_id=FRAME_ID, id="lanelets", lifetime=None, frame_locked=True, lines=lines,
                                metadata=[fm.KeyValuePair(key="map_name", value=scene.map_name), fm.KeyValuePair(key="scene_id", value=scene.scene_id)])
        self._map_update = fm.SceneUpdate(entities=[entity])
        self._log("/map", fch.SceneUpdateChannel, self._map_update, log_time_ns)
        tf = fm.FrameTransform(timestamp=ts, parent_frame_id="world", child_frame_id=FRAME_ID, translation=fm.Vector3(), rotation=fm.Quaternion(w=1.0))
        self._log("/tf", fch.FrameTransformChannel, tf, log_time_ns)

    def open_map_channels(self) -> None:
        """Create ``/map`` and ``/tf`` before any message (the live bridge, before its server starts): a client then
        finds them advertised when it connects instead of being told while it subscribes to the others (in CI a
        client that connected before the first SceneInfo now and then got ``/tf`` but never ``/map``)."""
        self._channel("/map", fch.SceneUpdateChannel)
        self._channel("/tf", fch.FrameTransformChannel)

    def relog_map(self, log_time_ns: int) -> None:
        """Log the map and transform again (a live client that joined late has not seen them)."""
        if self._map_update is not None:
            self._log("/map", fch.SceneUpdateChannel, self._map_update, log_time_ns)
            tf = fm.FrameTransform(timestamp=timestamp(log_time_ns), parent_frame_id="world", child_frame_id=FRAME_ID, translation=fm.Vector3(), rotation=fm.Quaternion(w=1.0))
            self._log("/tf", fch.FrameTransformChannel, tf, log_time_ns)

    def add_frame(self, frame: TrackFrame, log_time_ns: int) -> None:
        stamp = int(frame.header.stamp_ns)
        self._keep(self._frames, stamp, frame)
        self._log("/objects", fch.SceneUpdateChannel, lambda: fm.SceneUpdate(entities=[objects_entity(frame)]), log_time_ns)
        for node, belief in self._waiting_beliefs.pop(stamp, ()):
            self._log_belief(node, belief, frame, log_time_ns)

    def add_corridor_set(self, node: str, corridor_set: CorridorSet, log_time_ns: int) -> None:
        stamp = int(corridor_set.header.stamp_ns)
        self._keep(self._corridor_sets, (node, stamp), corridor_set)
        for pred_node, pred in self._waiting_predictions.pop(stamp, ()):
            self._log(f"/{pred_node}/corridors", fch.SceneUpdateChannel,
                      lambda pred=pred: fm.SceneUpdate(entities=[corridors_entity(corridor_set, pred, timestamp(stamp))]), log_time_ns)

    def add_predictions(self, node: str, pred: CorridorPredictions, log_time_ns: int) -> None:
        stamp = int(pred.header.stamp_ns)
        ts = timestamp(stamp)
        corridor_set = next((cs for (n, s), cs in reversed(list(self._corridor_sets.items())) if s == stamp), None)
        if corridor_set is not None:
            self._log(f"/{node}/corridors", fch.SceneUpdateChannel, lambda: fm.SceneUpdate(entities=[corridors_entity(corridor_set, pred, ts)]),
                      log_time_ns)
        else:
            self._wait(self._waiting_predictions, stamp, (node, pred), _NO_CORRIDORS)
        self._log(f"/{node}/means", fch.SceneUpdateChannel, lambda: fm.SceneUpdate(entities=[means_entity(pred, ts)]), log_time_ns)

    def add_grid(self, node: str, grid: MotionGrid, log_time_ns: int) -> None:
        self._log_coverage(node, grid, log_time_ns)
        if grid.n_rows <= 0 or grid.n_cols <= 0 or not grid.steps:
            self.counts.skip("empty motion grid")
            return
        times = np.asarray(grid.step_times_s, dtype=float)
        if self.grid_step == "all":
            for k, t in enumerate(times):
                self._log(f"/{node}/motion_grid/{t:.1f}s", fch.GridChannel, lambda k=k: grid_message(grid, k), log_time_ns)
            return
        k = None if self.grid_step == "max" else _step_index(times, float(self.grid_step))
        if k is not None and times[k] < float(self.grid_step) - 1e-6:  # beyond the horizon: its last step, counted
            self.counts.skip(f"grid step {float(self.grid_step):g} s beyond the grids' last step: the last one shown instead")
        self._log(f"/{node}/motion_grid", fch.GridChannel, lambda: grid_message(grid, k), log_time_ns)

    def _log_coverage(self, node: str, grid: MotionGrid, log_time_ns: int) -> None:
        """``/<node>/coverage``: a Log line each time what the node's grids cover changes (a shard's vehicles only, a
        shard missing from a fused frame, whole again): an empty area of such a grid may hold vehicles nobody predicted."""
        what = coverage(grid)
        if what == self._coverage.get(node, ""):
            return
        self._coverage[node] = what
        level = fm.LogLevel.Warning if what else fm.LogLevel.Info
        text = f"motion grid: {what}: other vehicles not predicted" if what else "motion grid: every vehicle of the frame again"
        self._log(f"/{node}/coverage", fch.LogChannel,
                  lambda: fm.Log(timestamp=timestamp(int(grid.header.stamp_ns)), level=level, message=text, name=node), log_time_ns)

    def add_belief(self, node: str, belief: IntentionBelief, log_time_ns: int) -> None:
        stamp = int(belief.header.stamp_ns)
        frame = self._frames.get(stamp)
        if frame is None:
            self._wait(self._waiting_beliefs, stamp, (node, belief), _NO_FRAME)
            return
        self._log_belief(node, belief, frame, log_time_ns)

    def _log_belief(self, node: str, belief: IntentionBelief, frame: TrackFrame, log_time_ns: int) -> None:
        self._log(f"/{node}/vehicles", fch.SceneUpdateChannel,
                  lambda: fm.SceneUpdate(entities=[belief_entity(belief, frame, timestamp(belief.header.stamp_ns))]), log_time_ns)

    def add_stats(self, stats: NodeStats, log_time_ns: int) -> None:
        topic = f"/stats/{stats.node_id}"
        self._log(topic, lambda t, context: foxglove.Channel(t, schema=STATS_SCHEMA, message_encoding="json", context=context),
                  lambda: stats_dict(stats), log_time_ns)


# --------------------------------------------------------------------------- message builders


def objects_entity(frame: TrackFrame) -> fm.SceneEntity:
    """Every object with a finite position as a cube coloured by type, with its id as a text above it."""
    cubes, texts = [], []
    for i in range(len(frame.track_ids)):
        x, y = float(frame.x_m[i]), float(frame.y_m[i])
        if not (math.isfinite(x) and math.isfinite(y)):
            continue
        t = int(frame.agent_types[i])
        dl, dw = TYPE_DEFAULT_SIZE_M.get(t, TYPE_DEFAULT_SIZE_M[0])
        length, width = float(frame.length_m[i]), float(frame.width_m[i])
        length = length if math.isfinite(length) and length > 0.1 else dl
        width = width if math.isfinite(width) and width > 0.1 else dw
        height = TYPE_HEIGHTS_M.get(t, 1.5)
        yaw = float(frame.yaw_rad[i]) if math.isfinite(float(frame.yaw_rad[i])) else 0.0
        rgb = TYPE_COLOURS.get(t, TYPE_COLOURS[0])
        cubes.append(fm.CubePrimitive(pose=_pose(x, y, height / 2.0, yaw), size=fm.Vector3(x=length, y=width, z=height), color=_colour(rgb, 0.9)))
        texts.append(fm.TextPrimitive(pose=_pose(x, y, height + 0.5), billboard=True, font_size=14.0, scale_invariant=True, color=_colour((1, 1, 1)), text=str(int(frame.track_ids[i]))))
    return fm.SceneEntity(timestamp=timestamp(frame.header.stamp_ns), frame_id=FRAME_ID, id="objects", cubes=cubes, texts=texts,
                          metadata=[fm.KeyValuePair(key="frame_index", value=str(frame.header.frame_index))])


def corridors_entity(corridor_set: CorridorSet, pred: CorridorPredictions, ts: fm.Timestamp) -> fm.SceneEntity:
    """Every vehicle's corridors, thickness by P(route), with a ``p=`` text at the far end."""
    probs = {(p.track_id, p.corridor_id): float(p.probability) for p in pred.predictions}
    lines, texts = [], []
    for v in corridor_set.vehicles:
        n = len(v.corridors)
        for c in v.corridors:
            p = probs.get((v.track_id, c.corridor_id), 1.0 / n if n else 0.0)
            xy = np.stack([c.x_m, c.y_m], axis=1)
            xy = xy[np.all(np.isfinite(xy), axis=1)]
            if len(xy) < 2:
                continue
            lines.append(fm.LinePrimitive(type=fm.LinePrimitiveLineType.LineStrip, pose=_pose(), thickness=CORRIDOR_THICKNESS_M[0] + CORRIDOR_THICKNESS_M[1] * p,
                                          scale_invariant=False, points=_points(xy, 0.03), color=_colour((0.67, 0.88, 1.0), 0.35 + 0.6 * p)))
            texts.append(fm.TextPrimitive(pose=_pose(float(xy[-1, 0]), float(xy[-1, 1]), 0.2), billboard=True, font_size=12.0, scale_invariant=True,
                                          color=_colour((0.67, 0.88, 1.0)), text=f"{v.track_id}: p={p:.2f}"))
    return fm.SceneEntity(timestamp=ts, frame_id=FRAME_ID, id="corridors", lines=lines, texts=texts)


def means_entity(pred: CorridorPredictions, ts: fm.Timestamp) -> fm.SceneEntity:
    """Each corridor's predicted means over the steps: a line through them and a small sphere at each step."""
    lines, spheres = [], []
    colour = _colour(MODE_COLOURS.get(pred.mode, (0.05, 0.05, 0.05)))
    for p in pred.predictions:
        xy = np.stack([p.mean_x_m, p.mean_y_m], axis=1)
        xy = xy[np.all(np.isfinite(xy), axis=1)]
        if not len(xy):
            continue
        if len(xy) >= 2:
            lines.append(fm.LinePrimitive(type=fm.LinePrimitiveLineType.LineStrip, pose=_pose(), thickness=0.1, points=_points(xy, 0.1), color=colour))
        for x, y in xy:
            spheres.append(fm.SpherePrimitive(pose=_pose(float(x), float(y), 0.1), size=fm.Vector3(x=0.5, y=0.5, z=0.5), color=colour))
    return fm.SceneEntity(timestamp=ts, frame_id=FRAME_ID, id=f"means/{pred.mode}", lines=lines, spheres=spheres,
                          metadata=[fm.KeyValuePair(key="mode", value=pred.mode)])


def _step_index(times: np.ndarray, step_s: float) -> int:
    later = np.nonzero(times >= step_s - 1e-6)[0]
    return int(later[0]) if len(later) else len(times) - 1


def grid_values(grid: MotionGrid, k: int | None) -> np.ndarray:
    """Dense (n_rows, n_cols) float32 occupancy of step ``k`` (None: maximum over steps); row 0 at ``origin_y_m``."""
    dense = np.zeros((grid.n_rows, grid.n_cols), dtype=np.float32)
    for step in grid.steps if k is None else grid.steps[k : k + 1]:
        rows, cols = np.asarray(step.rows, dtype=np.int64), np.asarray(step.cols, dtype=np.int64)
        ok = (rows >= 0) & (rows < grid.n_rows) & (cols >= 0) & (cols < grid.n_cols)
        np.maximum.at(dense, (rows[ok], cols[ok]), np.asarray(step.values, dtype=np.float32)[ok])
    return dense


def grid_message(grid: MotionGrid, k: int | None) -> fm.Grid:
    """One step's (or the maximum's) occupancy as a ``foxglove.Grid``, cropped to the cells above zero (one cell if none)."""
    dense = grid_values(grid, k)
    rows, cols = np.nonzero(dense > 0)
    if len(rows):
        r0, r1, c0, c1 = int(rows.min()), int(rows.max()) + 1, int(cols.min()), int(cols.max()) + 1
    else:
        r0, r1, c0, c1 = 0, 1, 0, 1
    crop = np.ascontiguousarray(dense[r0:r1, c0:c1], dtype="<f4")
    n_cols = crop.shape[1]
    return fm.Grid(
        timestamp=timestamp(grid.header.stamp_ns),
        frame_id=FRAME_ID,
        pose=_pose(grid.origin_x_m + c0 * grid.cell_m, grid.origin_y_m + r0 * grid.cell_m, 0.05),
        column_count=n_cols,
        cell_size=fm.Vector2(x=float(grid.cell_m), y=float(grid.cell_m)),
        row_stride=4 * n_cols,
        cell_stride=4,
        fields=[fm.PackedElementField(name="occupancy", offset=0, type=fm.PackedElementFieldNumericType.Float32)],
        data=crop.tobytes(),
    )


def belief_text(v: Any) -> str:
    """``P(stop) 0.31 | left 0.72``: the vehicle's stop probability and its most probable route."""
    top = max(v.corridors, key=lambda c: c.probability, default=None)
    route = f"{Manoeuvre(int(top.manoeuvre)).name.lower()} {top.probability:.2f}" if top is not None else "no route"
    return f"P(stop) {v.p_stop:.2f} | {route}"


def belief_entity(belief: IntentionBelief, frame: TrackFrame, ts: fm.Timestamp) -> fm.SceneEntity:
    where = {int(t): (float(x), float(y)) for t, x, y in zip(frame.track_ids, frame.x_m, frame.y_m)}
    texts = []
    for v in belief.vehicles:
        at = where.get(int(v.track_id))
        if at is None or not (math.isfinite(at[0]) and math.isfinite(at[1])):
            continue
        texts.append(fm.TextPrimitive(pose=_pose(at[0], at[1] - 2.5, 2.0), billboard=True, font_size=12.0, scale_invariant=True, color=_colour((1.0, 0.85, 0.3)), text=belief_text(v)))
    return fm.SceneEntity(timestamp=ts, frame_id=FRAME_ID, id="beliefs", texts=texts)


def stats_dict(stats: NodeStats) -> dict[str, Any]:
    def num(x: float) -> float | None:
        return float(x) if math.isfinite(x) else None

    return {
        "node_id": stats.node_id,
        "stage": stats.stage,
        "uptime_s": num(stats.uptime_s),
        "proc_ms_p50": num(stats.proc_ms_p50),
        "proc_ms_p95": num(stats.proc_ms_p95),
        "proc_ms_max": num(stats.proc_ms_max),
        "latency_ms_p50": num(stats.latency_ms_p50),
        "latency_ms_p95": num(stats.latency_ms_p95),
        "e2e_ms_p50": num(stats.e2e_ms_p50),
        "e2e_ms_p95": num(stats.e2e_ms_p95),
        "queue_depth": int(stats.queue_depth),
        "counters": {k: int(v) for k, v in stats.counters.items()},
        "issues": {k: int(v) for k, v in stats.issues_by_kind.items()},
        "errors": {k: int(v) for k, v in stats.errors_by_kind.items()},
    }


def stats_json(stats: NodeStats) -> str:
    return json.dumps(stats_dict(stats))
