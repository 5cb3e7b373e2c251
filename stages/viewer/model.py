"""The viewer's pure part: kept input sets, which one a view shows, and the geometry to draw.

Nothing here knows viser, the bus or the wall clock: the frame history is
indexed by message stamps, the view state is plain data, and every drawing
primitive (boxes, segments, points, the heat-map quads) comes back as numpy
arrays that ``scene.py`` hands to viser as they are.
"""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass, field
from typing import Mapping

import numpy as np

from bus_schemas import AccelerationProfiles, AgentType, CorridorPredictions, CorridorSet, IntentionBelief, MatchStatus, MotionGrid, SceneInfo, TrackFrame, coverage

# --------------------------------------------------------------------------- colours (RGB, 0-255)

TYPE_COLOURS: dict[int, tuple[int, int, int]] = {
    int(AgentType.UNKNOWN): (150, 150, 150),
    int(AgentType.CAR): (30, 144, 255),
    int(AgentType.TRUCK): (0, 70, 200),
    int(AgentType.BUS): (110, 70, 230),
    int(AgentType.MOTORCYCLE): (0, 200, 200),
    int(AgentType.BICYCLE): (0, 160, 80),
    int(AgentType.PEDESTRIAN): (230, 60, 200),
}
#: Box heights and footprints for objects whose size the tracker does not report.
TYPE_HEIGHTS_M: dict[int, float] = {1: 1.5, 2: 3.0, 3: 3.0, 4: 1.2, 5: 1.2, 6: 1.8}
TYPE_DEFAULT_SIZE_M: dict[int, tuple[float, float]] = {0: (1.0, 1.0), 1: (4.5, 1.8), 2: (8.0, 2.5), 3: (12.0, 2.5), 4: (2.0, 0.8), 5: (1.8, 0.6), 6: (0.6, 0.6)}
CAR_LANELET_FILL = (88, 88, 96)
CAR_LANELET_BORDER = (200, 200, 205)
OTHER_LANELET_OUTLINE = (150, 150, 160)
CORRIDOR_COLOUR = (170, 225, 255)
MEAN_COLOUR = (20, 20, 20)
MEAN_AT_STEP_COLOUR = (255, 255, 255)
TRUTH_COLOUR = (130, 255, 0)

# Heat ramp for occupancy: dark red -> red -> orange -> light yellow, alpha rising with it.
_RAMP_T = np.array([0.0, 0.35, 0.7, 1.0])
_RAMP_RGB = np.array([[150, 0, 0], [255, 40, 0], [255, 160, 0], [255, 255, 90]], dtype=float)
_RAMP_ALPHA = (120.0, 250.0)

# z of each layer above the ground plane, m (the view is top-down; higher draws on top)
Z_MAP = 0.0
Z_OUTLINES = 0.01
Z_CORRIDORS = 0.03
Z_GRID = 0.05
Z_TRUTH = 0.08
Z_MEANS = 0.10


# --------------------------------------------------------------------------- input sets and their history

#: The inputs that arrive apart from the track frames and are joined to them here, by stamp.
PART_PORTS: dict[str, type] = {
    "corridor_set": CorridorSet,
    "corridor_predictions": CorridorPredictions,
    "motion_grid": MotionGrid,
    # the compare view and the selected-vehicle panel (panels.py)
    "compare_predictions": CorridorPredictions,
    "intention_belief": IntentionBelief,
    "acceleration_profiles": AccelerationProfiles,
}


@dataclass(frozen=True, slots=True, eq=False)
class InputSet:
    """What the viewer knows of one source stamp: the track frame and whichever later results have arrived for it."""

    stamp_ns: int
    frame_index: int
    track_frame: TrackFrame
    scene: SceneInfo | None = None
    corridor_set: CorridorSet | None = None
    predictions: CorridorPredictions | None = None
    grid: MotionGrid | None = None
    complete: bool = True  # every kind of result that is arriving at all is here
    compare: CorridorPredictions | None = None  # a second mode's predictions of the same frame (compare pipeline)
    belief: IntentionBelief | None = None
    profiles: AccelerationProfiles | None = None

    @property
    def mode(self) -> str:
        for msg in (self.predictions, self.grid):
            if msg is not None:
                return msg.mode
        return "-"

    @property
    def coverage(self) -> str:
        """"" when the predictions shown cover every vehicle of the frame; else what they lack (``bus_schemas.coverage``:
        a shard's own output, or a fused frame with shards missing), for the side panel."""
        what = coverage(self.grid, self.predictions)
        return f"predictions: {what}: other vehicles not predicted" if what else ""

    def horizon_s(self, default_s: float) -> float:
        for msg in (self.predictions, self.grid):
            if msg is not None and len(msg.step_times_s):
                return float(msg.step_times_s[-1])
        return default_s


class FrameHistory:
    """Track frames of the last ``history_s`` seconds of stamps, and the results of other stages joined to them by stamp.

    The runtime delivers every track frame, each with the latest corridor
    set, predictions and grid that have arrived (those ports take no part in
    its bounded stamp join: the predictions may lag the frames by seconds
    when the machine is busy). ``add`` files each result under its own
    ``header.stamp_ns``, so a frame shows with the results computed from it,
    however late they came. A frame stamp at or before the newest one (a
    source that started over) clears everything first.
    """

    def __init__(self, history_s: float) -> None:
        self.history_ns = int(history_s * 1e9)
        self._frames: list[TrackFrame] = []
        self._stamps: list[int] = []
        self._parts: dict[str, dict[int, object]] = {k: {} for k in PART_PORTS}
        self.scene: SceneInfo | None = None
        self.received = 0
        self.restarts = 0
        # per kind of result: the newest stamp it came for, kept after its parts leave the history (a stage that stops
        # must not look like a run without that stage: `stalled`)
        self._last_part_ns: dict[str, int] = {}

    def add(self, inputs: Mapping[str, object]) -> bool:
        """File one update's inputs; False (nothing filed) without a track frame."""
        frame = inputs.get("track_frame")
        if not isinstance(frame, TrackFrame):
            return False
        scene = inputs.get("scene")
        if isinstance(scene, SceneInfo):
            self.scene = scene
        stamp = int(frame.header.stamp_ns)
        if self._stamps and stamp <= self._stamps[-1]:
            self._frames.clear()
            self._stamps.clear()
            for parts in self._parts.values():
                parts.clear()
            self._last_part_ns.clear()
            self.restarts += 1
        self._frames.append(frame)
        self._stamps.append(stamp)
        self.received += 1
        for kind, tp in PART_PORTS.items():
            msg = inputs.get(kind)
            if isinstance(msg, tp) and msg.header.stamp_ns <= stamp:
                self._parts[kind].setdefault(int(msg.header.stamp_ns), msg)
                self._last_part_ns[kind] = max(self._last_part_ns.get(kind, 0), int(msg.header.stamp_ns))
        cut = bisect.bisect_left(self._stamps, stamp - self.history_ns)
        if cut:
            del self._frames[:cut]
            del self._stamps[:cut]
        oldest = self._stamps[0]
        for parts in self._parts.values():
            for old in [t for t in parts if t < oldest]:
                del parts[old]
        return True

    def __len__(self) -> int:
        return len(self._stamps)

    @property
    def newest_stamp_ns(self) -> int | None:
        return self._stamps[-1] if self._stamps else None

    def stalled(self, after_ns: int) -> dict[str, float]:
        """Kinds of result that came earlier in this run but not for the last ``after_ns`` of frames: kind -> seconds
        since the newest one (a stage stopped, hung or far behind; once its parts have left the history the frames
        would otherwise be shown as if the run had no such stage)."""
        newest = self.newest_stamp_ns
        if newest is None:
            return {}
        return {k: (newest - t) / 1e9 for k, t in sorted(self._last_part_ns.items()) if newest - t > after_ns}

    def expected(self) -> list[str]:
        """The kinds of result that are arriving at all (any of them in the kept window)."""
        return [k for k, parts in self._parts.items() if parts]

    def _set(self, i: int, expected: list[str]) -> InputSet:
        stamp, frame = self._stamps[i], self._frames[i]
        got = {k: self._parts[k].get(stamp) for k in PART_PORTS}
        return InputSet(
            stamp_ns=stamp,
            frame_index=int(frame.header.frame_index),
            track_frame=frame,
            scene=self.scene,
            corridor_set=got["corridor_set"],
            predictions=got["corridor_predictions"],
            grid=got["motion_grid"],
            complete=all(got[k] is not None for k in expected),
            compare=got["compare_predictions"],
            belief=got["intention_belief"],
            profiles=got["acceleration_profiles"],
        )

    def newest_complete_stamp(self) -> int | None:
        expected = self.expected()
        for i in range(len(self._stamps) - 1, -1, -1):
            if all(self._stamps[i] in self._parts[k] for k in expected):
                return self._stamps[i]
        return None

    def at(self, stamp_ns: int, max_lag_ns: int) -> InputSet | None:
        """The newest complete set at or before ``stamp_ns``; the newest frame there instead when that set is more than ``max_lag_ns`` older."""
        i = bisect.bisect_right(self._stamps, stamp_ns) - 1
        if i < 0:
            return None
        expected = self.expected()
        for j in range(i, -1, -1):
            if self._stamps[i] - self._stamps[j] > max_lag_ns:
                break
            if all(self._stamps[j] in self._parts[k] for k in expected):
                return self._set(j, expected)
        return self._set(i, expected)

    def oldest(self) -> InputSet | None:
        return self._set(0, self.expected()) if self._stamps else None

    def frames_between(self, first_ns: int, last_ns: int) -> list[TrackFrame]:
        """The kept frames with stamps in [first_ns, last_ns], oldest first."""
        i0 = bisect.bisect_left(self._stamps, first_ns)
        i1 = bisect.bisect_right(self._stamps, last_ns)
        return self._frames[i0:i1]

    def sets_between(self, first_ns: int, last_ns: int) -> list[InputSet]:
        """The kept input sets with stamps in [first_ns, last_ns], oldest first."""
        expected = self.expected()
        i0 = bisect.bisect_left(self._stamps, first_ns)
        i1 = bisect.bisect_right(self._stamps, last_ns)
        return [self._set(i, expected) for i in range(i0, i1)]

    def true_futures(self, item: InputSet, horizon_s: float) -> tuple[dict[int, np.ndarray], bool]:
        """Where every object of ``item`` really went in the ``horizon_s`` after it.

        Returns {track_id: (k, 2) positions, starting at its position in
        ``item``} and whether the history already reaches the full horizon.
        """
        end = item.stamp_ns + int(horizon_s * 1e9)
        i0 = bisect.bisect_right(self._stamps, item.stamp_ns)
        i1 = bisect.bisect_right(self._stamps, end)
        tracks: dict[int, list[tuple[float, float]]] = {}
        frame = item.track_frame
        for row in range(len(frame)):
            tracks[int(frame.track_ids[row])] = [(float(frame.x_m[row]), float(frame.y_m[row]))]
        for f in self._frames[i0:i1]:
            for row in range(len(f)):
                path = tracks.get(int(f.track_ids[row]))
                if path is not None:
                    path.append((float(f.x_m[row]), float(f.y_m[row])))
        complete = bool(self._stamps) and self._stamps[-1] >= end
        return {tid: np.asarray(p, dtype=np.float64) for tid, p in tracks.items() if len(p) > 1}, complete


# --------------------------------------------------------------------------- what the user chose


ALL_VEHICLES = "all"


@dataclass(slots=True)
class ViewState:
    """The choices of the side panel; the renderer draws what they select."""

    vehicle: str = ALL_VEHICLES  # "all" or a track id
    step_s: float = 1.0
    blend_steps: bool = False
    show_grid: bool = True
    show_corridors: bool = True
    show_means: bool = True
    show_labels: bool = True
    show_ground_truth: bool = False
    paused: bool = False
    paused_at_ns: int | None = None  # the newest stamp when pause was pressed
    lookback_s: float = 0.0

    def vehicle_id(self) -> int | None:
        try:
            return int(self.vehicle)
        except ValueError:
            return None

    def target_stamp(self, newest_ns: int, horizon_s: float) -> int:
        """The stamp to show: the newest complete one (or the one paused at), minus the look-back and, with ground truth on, the horizon."""
        anchor = self.paused_at_ns if self.paused and self.paused_at_ns is not None else newest_ns
        lag_s = self.lookback_s + (horizon_s if self.show_ground_truth else 0.0)
        return anchor - int(round(lag_s * 1e9))


#: stamps from this on (ns, 1973-03) are taken for a wall clock (Unix ns: a live tracker's), below for a recording's
#: time from about 0 (``stamp_text``)
WALL_CLOCK_FROM_NS = 10**17


def stamp_text(stamp_ns: int) -> str:
    """A frame's stamp for the status line: ``t = 12.3 s`` on a recording's clock, the UTC time of day on a wall clock
    (``22:37:39.3 UTC``: a live tracker stamps with Unix ns, which as seconds say nothing)."""
    if stamp_ns < WALL_CLOCK_FROM_NS:
        return f"t = {stamp_ns / 1e9:.1f} s"
    seconds, tenths = divmod(int(stamp_ns) // 100_000_000, 10)
    h, rest = divmod(seconds % 86_400, 3600)
    return f"{h:02d}:{rest // 60:02d}:{rest % 60:02d}.{tenths} UTC"


def step_index(step_times_s: np.ndarray, step_s: float) -> int:
    """Index of the first prediction step at or after ``step_s`` (its interval [t_k − τ, t_k] holds ``step_s``); the last if none."""
    times = np.asarray(step_times_s, dtype=float)
    if not len(times):
        return 0
    later = np.nonzero(times >= step_s - 1e-6)[0]
    return int(later[0]) if len(later) else len(times) - 1


# --------------------------------------------------------------------------- objects


@dataclass(frozen=True, slots=True)
class Boxes:
    """Oriented boxes on the ground: centres (n, 3), quaternions wxyz (n, 4), sizes (n, 3) and colours (n, 3) uint8."""

    track_ids: np.ndarray
    agent_types: np.ndarray
    centres_m: np.ndarray
    wxyzs: np.ndarray
    sizes_m: np.ndarray
    colours: np.ndarray

    def __len__(self) -> int:
        return int(self.track_ids.shape[0])

    def yaw_rad(self, i: int) -> float:
        w, _x, _y, z = self.wxyzs[i]
        return float(2.0 * math.atan2(z, w))

    def contains(self, i: int, xy: tuple[float, float], margin_m: float = 0.0) -> bool:
        """Whether the point ``xy`` lies on box ``i``'s footprint grown by ``margin_m`` on every side."""
        yaw = self.yaw_rad(i)
        dx, dy = xy[0] - float(self.centres_m[i, 0]), xy[1] - float(self.centres_m[i, 1])
        along, across = dx * math.cos(yaw) + dy * math.sin(yaw), -dx * math.sin(yaw) + dy * math.cos(yaw)
        return abs(along) <= self.sizes_m[i, 0] / 2.0 + margin_m and abs(across) <= self.sizes_m[i, 1] / 2.0 + margin_m

    def id_label_position(self, i: int) -> tuple[float, float, float]:
        """Where the track id label of box ``i`` sits: north of the box (above it on screen), not on it."""
        north_m = 0.5 * float(np.hypot(self.sizes_m[i, 0], self.sizes_m[i, 1])) + 0.8
        return (float(self.centres_m[i, 0]), float(self.centres_m[i, 1]) + north_m, float(self.sizes_m[i, 2]) + 0.3)


def object_boxes(frame: TrackFrame) -> Boxes:
    """Every object of the frame with a finite position as a box, coloured by its type."""
    x, y = np.asarray(frame.x_m, dtype=float), np.asarray(frame.y_m, dtype=float)
    keep = np.isfinite(x) & np.isfinite(y)
    types = np.asarray(frame.agent_types, dtype=np.int64)[keep]
    yaw = np.nan_to_num(np.asarray(frame.yaw_rad, dtype=float)[keep])
    length = np.asarray(frame.length_m, dtype=float)[keep]
    width = np.asarray(frame.width_m, dtype=float)[keep]
    default = np.array([TYPE_DEFAULT_SIZE_M.get(int(t), TYPE_DEFAULT_SIZE_M[0]) for t in types], dtype=float).reshape(-1, 2)
    length = np.where(np.isfinite(length) & (length > 0.1), length, default[:, 0])
    width = np.where(np.isfinite(width) & (width > 0.1), width, default[:, 1])
    height = np.array([TYPE_HEIGHTS_M.get(int(t), 1.5) for t in types], dtype=float)
    centres = np.stack([x[keep], y[keep], height / 2.0], axis=1) if len(types) else np.zeros((0, 3))
    wxyzs = np.stack([np.cos(yaw / 2.0), np.zeros_like(yaw), np.zeros_like(yaw), np.sin(yaw / 2.0)], axis=1) if len(types) else np.zeros((0, 4))
    colours = np.array([TYPE_COLOURS.get(int(t), TYPE_COLOURS[0]) for t in types], dtype=np.uint8).reshape(-1, 3)
    return Boxes(
        track_ids=np.asarray(frame.track_ids, dtype=np.int64)[keep],
        agent_types=types,
        centres_m=centres,
        wxyzs=wxyzs,
        sizes_m=np.stack([length, width, height], axis=1) if len(types) else np.zeros((0, 3)),
        colours=colours,
    )


#: A unit cube centred on the origin: 8 vertices, 12 triangles (scaled per instance).
CUBE_VERTICES = np.array([[x, y, z] for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (-0.5, 0.5)], dtype=np.float32)
CUBE_FACES = np.array(
    [[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1], [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]],
    dtype=np.uint32,
)


@dataclass(frozen=True, slots=True)
class BoxMesh:
    """Boxes of one colour as one plain triangle mesh: vertices (8n, 3) float32 in metres, faces (12n, 3) uint32."""

    colour: tuple[int, int, int]
    vertices_m: np.ndarray
    faces: np.ndarray


def box_meshes(boxes: Boxes) -> list[BoxMesh]:
    """The boxes as plain meshes, one per colour, each box's corners placed in the world.

    The viewer draws these rather than one instanced (batched) mesh: in
    headless chromium (SwiftShader WebGL2) viser's instanced draw failed with
    ``GL_INVALID_OPERATION: glDrawElementsInstanced: Vertex shader input type
    does not match the type of the bound vertex attribute`` after the first
    frames, and the boxes vanished while their labels stayed. A few hundred
    vertices per frame cost nothing as a plain mesh.
    """
    n = len(boxes)
    if n == 0:
        return []
    yaw = 2.0 * np.arctan2(boxes.wxyzs[:, 3], boxes.wxyzs[:, 0])
    c, s = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
    local = CUBE_VERTICES[None, :, :].astype(float) * boxes.sizes_m[:, None, :]  # (n, 8, 3)
    world = np.empty_like(local)
    world[..., 0] = c * local[..., 0] - s * local[..., 1] + boxes.centres_m[:, 0, None]
    world[..., 1] = s * local[..., 0] + c * local[..., 1] + boxes.centres_m[:, 1, None]
    world[..., 2] = local[..., 2] + boxes.centres_m[:, 2, None]
    out = []
    for colour in np.unique(boxes.colours, axis=0):
        idx = np.nonzero(np.all(boxes.colours == colour, axis=1))[0]
        faces = CUBE_FACES[None, :, :] + (8 * np.arange(len(idx), dtype=np.uint32))[:, None, None]
        out.append(BoxMesh(colour=tuple(int(v) for v in colour), vertices_m=world[idx].reshape(-1, 3).astype(np.float32), faces=faces.reshape(-1, 3).astype(np.uint32)))
    return out


# --------------------------------------------------------------------------- corridors and predictions


@dataclass(frozen=True, slots=True)
class Label:
    """A text in the scene; ``anchor`` (viser's) is the point of the text that sits at ``position_m``."""

    name: str
    text: str
    position_m: tuple[float, float, float]
    anchor: str = "bottom-center"


#: A probability label moved off its vehicle's box keeps this gap to every box (m).
LABEL_CLEARANCE_M = 0.6
#: Labels moved off a box keep at least this distance from each other and from every id label (m).
LABEL_SPACING_M = 2.0
_LABEL_RINGS = 3
_LABEL_TEXT_M = 1.0  # how far a label's text reaches from its anchor, about, at the usual zoom (it is drawn at a fixed screen size)


def _anchor_away(dx: float, dy: float) -> str:
    """The anchor that makes a label grow in direction (dx, dy) on the screen (north is up): away from its box."""
    if abs(dy) >= abs(dx):
        return "bottom-center" if dy >= 0 else "top-center"
    return "center-left" if dx > 0 else "center-right"


def off_box_spots(boxes: Boxes, i: int) -> list[tuple[tuple[float, float], tuple[float, float]]]:
    """Places for labels beside box ``i``, first choice first, each with the direction (unit) away from the box: beside
    its front corners (along its heading, which is the corridor direction of a matched car; away = sideways), beside
    it, ahead of it (away = ahead), beside its rear corners, behind it; each ring ``LABEL_SPACING_M`` further out
    than the one before."""
    cx, cy = float(boxes.centres_m[i, 0]), float(boxes.centres_m[i, 1])
    yaw = boxes.yaw_rad(i)
    f, left = (math.cos(yaw), math.sin(yaw)), (-math.sin(yaw), math.cos(yaw))
    half_l = boxes.sizes_m[i, 0] / 2.0 + LABEL_CLEARANCE_M
    half_w = boxes.sizes_m[i, 1] / 2.0 + LABEL_CLEARANCE_M
    spots = []
    for ring in range(_LABEL_RINGS):
        out = ring * LABEL_SPACING_M
        for a, b in ((half_l, half_w + out), (half_l, -half_w - out), (0.0, half_w + out), (0.0, -half_w - out),
                     (half_l + out, 0.0), (-half_l, half_w + out), (-half_l, -half_w - out), (-half_l - out, 0.0)):
            away = (math.copysign(1.0, b) * left[0], math.copysign(1.0, b) * left[1]) if b else (math.copysign(1.0, a) * f[0], math.copysign(1.0, a) * f[1])
            spots.append(((cx + a * f[0] + b * left[0], cy + a * f[1] + b * left[1]), away))
    return spots


def place_labels_off_boxes(labels: list[Label], owners: list[int], boxes: Boxes, probabilities: list[float] | None = None) -> list[Label]:
    """Move each label that lies on its own vehicle's box (``owners``: the track id per label) beside it.

    A standing car's corridors have their last predicted mean where the car
    is, so their ``p=`` labels were drawn on its box, unreadable. Such a label
    goes to the first of ``off_box_spots`` that lies on no box of the frame
    (with ``LABEL_CLEARANCE_M / 2`` to spare), nor does its text as it
    grows away from the box (about ``_LABEL_TEXT_M``), and is
    ``LABEL_SPACING_M`` from every id label and every label moved before it
    (the most probable corridor first, by ``probabilities``); its anchor
    makes the text grow away from the box (sideways beside it, forward
    ahead of it). When no spot is free it takes the first one. Labels off
    their box stay.
    """
    index = {int(t): i for i, t in enumerate(boxes.track_ids)}
    taken = [boxes.id_label_position(i)[:2] for i in range(len(boxes))]
    out = list(labels)
    p = probabilities if probabilities is not None else [0.0] * len(labels)
    order = sorted(range(len(labels)), key=lambda j: -p[j] if math.isfinite(p[j]) else math.inf)

    n = len(boxes)
    centres = boxes.centres_m[:, :2].astype(np.float64) if n else np.zeros((0, 2))
    reach = 0.5 * np.hypot(boxes.sizes_m[:, 0], boxes.sizes_m[:, 1]) if n else np.zeros(0)
    # per box, what ``Boxes.contains`` computes (its yaw's cos and sin, its half sizes): every spot of a label against
    # every box near it at once (at 72 vehicles, with standing cars side by side, the spots were tried one at a time
    # against each box and each label taken, and a frame's labels took ~100 ms)
    yaws = [boxes.yaw_rad(i) for i in range(n)]
    cos_b, sin_b = np.array([math.cos(y) for y in yaws]), np.array([math.sin(y) for y in yaws])
    half_l, half_w = (boxes.sizes_m[:, 0] / 2.0, boxes.sizes_m[:, 1] / 2.0) if n else (np.zeros(0), np.zeros(0))
    margin = LABEL_CLEARANCE_M / 2.0

    def first_free(spots: list[tuple[tuple[float, float], tuple[float, float]]], near: np.ndarray) -> int:
        """The index of the first spot whose text lies on no box of ``near`` and which is ``LABEL_SPACING_M`` from every
        label taken, else 0."""
        pts = np.array([((x, y), (x + _LABEL_TEXT_M * ax, y + _LABEL_TEXT_M * ay)) for (x, y), (ax, ay) in spots])  # (S, 2, 2)
        dx = pts[:, :, None, 0] - centres[near, 0]
        dy = pts[:, :, None, 1] - centres[near, 1]
        along = dx * cos_b[near] + dy * sin_b[near]
        across = -dx * sin_b[near] + dy * cos_b[near]
        on_box = ((np.abs(along) <= half_l[near] + margin) & (np.abs(across) <= half_w[near] + margin)).any(axis=(1, 2))
        t = np.array(taken, dtype=np.float64).reshape(-1, 2)
        spaced = (np.hypot(pts[:, 0, None, 0] - t[:, 0], pts[:, 0, None, 1] - t[:, 1]) >= LABEL_SPACING_M).all(axis=1)
        free = np.flatnonzero(~on_box & spaced)
        return int(free[0]) if free.size else 0

    for j in order:
        lab, i = labels[j], index.get(int(owners[j]))
        if i is None or not boxes.contains(i, lab.position_m[:2], LABEL_CLEARANCE_M):
            continue
        spots = off_box_spots(boxes, i)
        far_m = max(math.hypot(xy[0] - centres[i, 0], xy[1] - centres[i, 1]) for xy, _a in spots) + _LABEL_TEXT_M + LABEL_CLEARANCE_M
        near = np.nonzero(np.hypot(*(centres - centres[i]).T) <= far_m + reach)[0]  # the boxes a spot could touch
        (x, y), away = spots[first_free(spots, near)]
        taken.append((x, y))
        out[j] = Label(lab.name, lab.text, (x, y, lab.position_m[2]), _anchor_away(*away))
    return out


@dataclass(frozen=True, slots=True)
class Segments:
    """Line segments (n, 2, 3) with per-point colours (n, 2, 3) uint8."""

    points_m: np.ndarray
    colours: np.ndarray

    def __len__(self) -> int:
        return int(self.points_m.shape[0])

    @staticmethod
    def empty() -> Segments:
        return Segments(np.zeros((0, 2, 3), dtype=np.float32), np.zeros((0, 2, 3), dtype=np.uint8))


def polyline_segments(polylines: list[np.ndarray], colour: tuple[int, int, int], z_m: float) -> Segments:
    """Join each (k, 2) polyline's consecutive points into segments at height ``z_m``."""
    parts = []
    for line in polylines:
        line = np.asarray(line, dtype=float)
        line = line[np.all(np.isfinite(line), axis=1)]
        if len(line) < 2:
            continue
        pts = np.concatenate([line, np.full((len(line), 1), z_m)], axis=1)
        parts.append(np.stack([pts[:-1], pts[1:]], axis=1))
    if not parts:
        return Segments.empty()
    points = np.concatenate(parts).astype(np.float32)
    colours = np.broadcast_to(np.asarray(colour, dtype=np.uint8), points.shape).copy()
    return Segments(points, colours)


def corridor_probabilities(predictions: CorridorPredictions | None) -> dict[tuple[int, int], float]:
    if predictions is None:
        return {}
    return {(p.track_id, p.corridor_id): float(p.probability) for p in predictions.predictions}


def matched_vehicles(corridor_set: CorridorSet | None) -> list[int]:
    """Track ids that have corridors, sorted."""
    if corridor_set is None:
        return []
    return sorted(v.track_id for v in corridor_set.vehicles if v.status == MatchStatus.MATCHED and v.corridors)


def corridor_lines(item: InputSet, vehicle: int | None, boxes: Boxes | None = None) -> tuple[Segments, list[Label]]:
    """The corridors of one vehicle (or all) as centreline segments, and a probability label per corridor.

    The label sits where the corridor's prediction has its mean at the last
    step (the far end of the heat map), else at the corridor's end; a label
    that would lie on its own vehicle's box (a standing car) is moved beside
    the box (``place_labels_off_boxes``; ``boxes``: the frame's, default
    ``object_boxes(item.track_frame)``).
    """
    if item.corridor_set is None:
        return Segments.empty(), []
    probs = corridor_probabilities(item.predictions)
    last_mean: dict[tuple[int, int], tuple[float, float]] = {}
    if item.predictions is not None:
        for p in item.predictions.predictions:
            ok = np.isfinite(p.mean_x_m) & np.isfinite(p.mean_y_m)
            if ok.any():
                k = int(np.nonzero(ok)[0][-1])
                last_mean[(p.track_id, p.corridor_id)] = (float(p.mean_x_m[k]), float(p.mean_y_m[k]))
    lines, labels, owners, label_p = [], [], [], []
    for v in item.corridor_set.vehicles:
        if vehicle is not None and v.track_id != vehicle:
            continue
        n = len(v.corridors)
        for c in v.corridors:
            lines.append(np.stack([c.x_m, c.y_m], axis=1))
            key = (v.track_id, c.corridor_id)
            p = probs.get(key, 1.0 / n if n else math.nan)
            at = last_mean.get(key)
            if at is None and len(c.x_m):
                at = (float(c.x_m[-1]), float(c.y_m[-1]))
            if at is not None:
                labels.append(Label(f"{v.track_id}_{c.corridor_id & 0xFFFFFFFF:x}", f"p={p:.2f}", (at[0], at[1], Z_MEANS)))
                owners.append(int(v.track_id))
                label_p.append(float(p))
    if labels:
        labels = place_labels_off_boxes(labels, owners, boxes if boxes is not None else object_boxes(item.track_frame), label_p)
    return polyline_segments(lines, CORRIDOR_COLOUR, Z_CORRIDORS), labels


def mean_points(item: InputSet, vehicle: int | None, k: int | None) -> tuple[np.ndarray, np.ndarray]:
    """Predicted mean positions: every step's (n, 3), and the chosen step ``k``'s (m, 3) (none when blending)."""
    if item.predictions is None:
        return np.zeros((0, 3)), np.zeros((0, 3))
    every, chosen = [], []
    for p in item.predictions.predictions:
        if vehicle is not None and p.track_id != vehicle:
            continue
        xy = np.stack([p.mean_x_m, p.mean_y_m], axis=1)
        ok = np.all(np.isfinite(xy), axis=1)
        every.append(xy[ok])
        if k is not None and k < len(xy) and ok[k]:
            chosen.append(xy[k : k + 1])

    def lift(parts: list[np.ndarray]) -> np.ndarray:
        if not parts:
            return np.zeros((0, 3))
        xy = np.concatenate(parts)
        return np.concatenate([xy, np.full((len(xy), 1), Z_MEANS)], axis=1)

    return lift(every), lift(chosen)


# --------------------------------------------------------------------------- the motion grid as an image


@dataclass(frozen=True, slots=True)
class HeatLevel:
    """The cells of one colour level of the heat map as flat quads on the ground: vertices (4n, 3) float32, faces (2n, 3) uint32."""

    rgb: tuple[int, int, int]
    opacity: float
    vertices_m: np.ndarray
    faces: np.ndarray


@dataclass(frozen=True, slots=True)
class HeatMesh:
    """The heat map of one grid step as a few plain meshes, one per colour level."""

    levels: tuple[HeatLevel, ...]
    cells: int  # cells above the floor (visible)
    max_value: float


def grid_values(grid: MotionGrid, k: int | None) -> np.ndarray:
    """The dense (n_rows, n_cols) occupancy of step ``k``, or the maximum over all steps for None."""
    dense = np.zeros((grid.n_rows, grid.n_cols), dtype=np.float32)
    steps = grid.steps if k is None else grid.steps[k : k + 1]
    for step in steps:
        rows, cols = np.asarray(step.rows, dtype=np.int64), np.asarray(step.cols, dtype=np.int64)
        ok = (rows >= 0) & (rows < grid.n_rows) & (cols >= 0) & (cols < grid.n_cols)
        np.maximum.at(dense, (rows[ok], cols[ok]), np.asarray(step.values, dtype=np.float32)[ok])
    return dense


def heat_t(values: np.ndarray, *, scale: str = "log", floor: float = 1e-3) -> np.ndarray:
    """Where occupancies in [0, 1] lie on the heat ramp, 0..1 (log or linear in the value from ``floor`` up)."""
    v = np.clip(np.nan_to_num(np.asarray(values, dtype=float)), 0.0, 1.0)
    if scale == "log":
        t = (np.log10(np.maximum(v, floor)) - math.log10(floor)) / -math.log10(floor)
    else:
        t = (v - floor) / (1.0 - floor)
    return np.clip(t, 0.0, 1.0)


def ramp_rgba(t: np.ndarray) -> np.ndarray:
    """RGBA uint8 of the heat ramp at positions ``t`` in [0, 1] (dark red, translucent -> yellow, nearly opaque)."""
    t = np.asarray(t, dtype=float)
    out = np.empty(t.shape + (4,), dtype=np.uint8)
    for ch in range(3):
        out[..., ch] = np.interp(t, _RAMP_T, _RAMP_RGB[:, ch]).round().astype(np.uint8)
    out[..., 3] = (_RAMP_ALPHA[0] + (_RAMP_ALPHA[1] - _RAMP_ALPHA[0]) * t).round().astype(np.uint8)
    return out


def heat_colours(values: np.ndarray, *, scale: str = "log", floor: float = 1e-3) -> np.ndarray:
    """RGBA uint8 for occupancies in [0, 1]: transparent below ``floor``, then the heat ramp (log or linear in the value)."""
    v = np.clip(np.nan_to_num(np.asarray(values, dtype=float)), 0.0, 1.0)
    out = ramp_rgba(heat_t(v, scale=scale, floor=floor))
    out[..., 3] = np.where(v >= floor, out[..., 3], 0)
    return out


#: Colour levels of the heat map (the ramp quantised: one mesh each).
HEAT_LEVELS = 16


def grid_mesh(grid: MotionGrid, k: int | None, *, scale: str = "log", floor: float = 1e-3, levels: int = HEAT_LEVELS, z_m: float = 0.05) -> HeatMesh | None:
    """The grid of step ``k`` (None: all steps blended by their maximum) as heat-map quads on the ground.

    Each cell at or above ``floor`` is one square (row 0 at the grid's
    south edge, ``origin_y_m``), coloured by its level: the heat ramp cut
    into ``levels`` bands, each band one plain mesh with the ramp's colour
    and opacity at the band's middle.

    Not an image: a viser image's texture is decoded asynchronously in the
    browser while its new size and position apply at once, so a client that
    falls behind (software WebGL) showed the previous frame's heat stretched
    over the new frame's extent, off the road. Meshes update in one step.
    """
    if grid.n_rows <= 0 or grid.n_cols <= 0 or not grid.steps:
        return None
    dense = grid_values(grid, k)
    rows, cols = np.nonzero(dense >= floor)
    max_value = float(dense.max()) if dense.size else 0.0
    if not len(rows):
        return HeatMesh(levels=(), cells=0, max_value=max_value)
    band = np.minimum((heat_t(dense[rows, cols], scale=scale, floor=floor) * levels).astype(np.int64), levels - 1)
    x0 = grid.origin_x_m + cols * grid.cell_m
    y0 = grid.origin_y_m + rows * grid.cell_m
    corners = np.stack(
        [np.stack([x0, y0], 1), np.stack([x0 + grid.cell_m, y0], 1), np.stack([x0 + grid.cell_m, y0 + grid.cell_m], 1), np.stack([x0, y0 + grid.cell_m], 1)], axis=1
    )  # (n, 4, 2)
    colours = ramp_rgba((np.arange(levels) + 0.5) / levels)  # each band's colour: the ramp at its middle
    out = []
    for b in np.unique(band):
        idx = np.nonzero(band == b)[0]
        rgb = tuple(int(c) for c in colours[b, :3])
        opacity = colours[b, 3] / 255.0
        verts = np.concatenate([corners[idx], np.full((len(idx), 4, 1), z_m)], axis=2).reshape(-1, 3).astype(np.float32)
        base = (4 * np.arange(len(idx), dtype=np.uint32))[:, None, None]
        faces = (np.array([[0, 1, 2], [0, 2, 3]], dtype=np.uint32)[None] + base).reshape(-1, 3)
        out.append(HeatLevel(rgb=rgb, opacity=float(opacity), vertices_m=verts, faces=faces))
    return HeatMesh(levels=tuple(out), cells=int(len(rows)), max_value=max_value)


# --------------------------------------------------------------------------- the map


def strip_mesh(left_m: np.ndarray, right_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Triangles filling the area between a lanelet's left and right bound.

    Both bounds are resampled to the same number of points by their relative
    arc length, then each pair of neighbouring point pairs is one quad
    (two triangles). Returns vertices (2n, 2) and faces (2(n-1), 3).
    """

    def resample(line: np.ndarray, n: int) -> np.ndarray:
        seg = np.hypot(*np.diff(line, axis=0).T)
        s = np.concatenate([[0.0], np.cumsum(seg)])
        if s[-1] <= 0:
            return np.repeat(line[:1], n, axis=0)
        u = np.linspace(0.0, s[-1], n)
        return np.stack([np.interp(u, s, line[:, 0]), np.interp(u, s, line[:, 1])], axis=1)

    left, right = np.asarray(left_m, dtype=float), np.asarray(right_m, dtype=float)
    n = max(len(left), len(right), 2)
    left, right = resample(left, n), resample(right, n)
    vertices = np.concatenate([left, right])
    i = np.arange(n - 1)
    faces = np.concatenate([np.stack([i, n + i, n + i + 1], axis=1), np.stack([i, n + i + 1, i + 1], axis=1)])
    return vertices, faces


@dataclass(frozen=True, slots=True)
class MapGeometry:
    """What the viewer draws of a lanelet map: car lanelets filled, the others outlined."""

    scene_id: str
    car_vertices_m: np.ndarray  # (v, 3) float32
    car_faces: np.ndarray  # (f, 3) uint32
    car_borders: Segments
    other_outlines: Segments
    n_car_lanelets: int
    n_other_lanelets: int
    bounds_m: tuple[float, float, float, float]  # x_min, y_min, x_max, y_max
    problems: tuple[str, ...] = field(default=())


def build_map_geometry(scene_id: str, car_bounds: list[tuple[np.ndarray, np.ndarray]], other_bounds: list[tuple[np.ndarray, np.ndarray]], problems: tuple[str, ...] = ()) -> MapGeometry:
    """Meshes and outlines from (left, right) bound pairs of the car lanelets and of the others."""
    verts, faces, offset, borders = [], [], 0, []
    for left, right in car_bounds:
        v, f = strip_mesh(left, right)
        verts.append(v)
        faces.append(f + offset)
        offset += len(v)
        borders += [left, right]
    others = [line for pair in other_bounds for line in pair]
    every = [np.asarray(p, dtype=float) for pair in car_bounds + other_bounds for p in pair if len(p)]
    if every:
        allp = np.concatenate(every)
        bounds = (float(allp[:, 0].min()), float(allp[:, 1].min()), float(allp[:, 0].max()), float(allp[:, 1].max()))
    else:
        bounds = (-50.0, -50.0, 50.0, 50.0)
    if verts:
        v2 = np.concatenate(verts)
        car_vertices = np.concatenate([v2, np.full((len(v2), 1), Z_MAP)], axis=1).astype(np.float32)
        car_faces = np.concatenate(faces).astype(np.uint32)
    else:
        car_vertices, car_faces = np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint32)
    return MapGeometry(
        scene_id=scene_id,
        car_vertices_m=car_vertices,
        car_faces=car_faces,
        car_borders=polyline_segments(borders, CAR_LANELET_BORDER, Z_OUTLINES),
        other_outlines=polyline_segments(others, OTHER_LANELET_OUTLINE, Z_OUTLINES),
        n_car_lanelets=len(car_bounds),
        n_other_lanelets=len(other_bounds),
        bounds_m=bounds,
        problems=problems,
    )


def load_map_geometry(scene: SceneInfo, data: str | None = None) -> MapGeometry:
    """The scene's map as the corridors stage loads it (same file, projection and origin), plus its other lanelets.

    The file is found as the corridors stage finds it (``local_map_file``): by
    the scene's map name inside ``<data>/maps`` (default the embedded
    ``stages/data/taf-bw``), checked by size and sha256 before it is parsed; a path
    from the bus is never opened. A map that cannot be used gives an empty
    geometry with its problem (drawn once per scene by the caller).
    """
    from stages.lib.maps import load_map, local_map_file, resolve_projection

    projection = resolve_projection("auto", scene)
    path, problem = local_map_file(data, scene)
    if path is None:
        return build_map_geometry(scene.scene_id, [], [], (problem,))
    try:
        road_map, found = load_map(path, scene.origin_lat_deg, scene.origin_lon_deg, projection)
    except Exception as exc:  # noqa: BLE001 - a map that fails to load draws nothing, once
        return build_map_geometry(scene.scene_id, [], [], (f"map_load_failed: {type(exc).__name__}: {exc}",))
    problems = tuple(f"{p.kind.name.lower()}: {p.detail}" for p in found)
    if road_map is None:
        return build_map_geometry(scene.scene_id, [], [], problems or ("map did not load",))
    car = [(road_map.lanelet(i).left_bound_m, road_map.lanelet(i).right_bound_m) for i in road_map.lanelet_ids]
    others, more = _other_lanelet_bounds(scene, projection, path)
    return build_map_geometry(scene.scene_id, car, others, problems + more)


def _other_lanelet_bounds(scene: SceneInfo, projection, path) -> tuple[list[tuple[np.ndarray, np.ndarray]], tuple[str, ...]]:
    """Bounds of the lanelets that are not car lanelets (walkways, crosswalks, bike lanes), in the scene frame.

    ``RoadMap`` keeps car lanelets only, so this reads the file once more
    (``path``, the checked local file) with ``maps.lanelet_bounds``, projected
    and shifted exactly as ``maps.load_map`` does.
    """
    from stages.lib import maps

    try:
        lanelets, problems = maps.lanelet_bounds(path, scene.origin_lat_deg, scene.origin_lon_deg, projection)
    except Exception as exc:  # a map we cannot read twice still draws its car lanelets
        return [], (f"other lanelets not drawn: {exc}",)
    if lanelets is None:
        return [], tuple(f"other lanelets not drawn: {p.detail}" for p in problems)
    out = [(x.left_bound_m, x.right_bound_m) for x in lanelets if not x.is_car and len(x.left_bound_m) >= 2 and len(x.right_bound_m) >= 2]
    return out, ()
