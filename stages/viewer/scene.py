"""The viewer core: keeps the input sets and draws them in a viser scene (the only viser user).

``ViewerApp.update`` runs on the runtime's loop and only stores the
input set (cheap, so the runtime's queue never backs up); a render thread
draws the set the side panel selects, at most ``max_render_hz`` times a
second, always the newest one: sets that arrived in between are counted as
skipped. GUI callbacks run on viser's threads and only change the
``ViewState`` and wake the render thread.
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import io
import logging
import math
import threading
import time
from typing import Any, Callable, Mapping

import numpy as np
import viser

from bus_schemas import NodeStats
from stages.lib.base import Issue, StageResult

from stages.viewer.config import ViewerConfig
from stages.viewer.guard import HandshakeGuard, new_token
from stages.viewer.guard import installed as guard_installed
from stages.viewer.model import (
    ALL_VEHICLES,
    CAR_LANELET_FILL,
    MEAN_AT_STEP_COLOUR,
    MEAN_COLOUR,
    TRUTH_COLOUR,
    TYPE_COLOURS,
    Z_TRUTH,
    FrameHistory,
    InputSet,
    MapGeometry,
    ViewState,
    box_meshes,
    corridor_lines,
    grid_mesh,
    load_map_geometry,
    matched_vehicles,
    mean_points,
    object_boxes,
    polyline_segments,
    stamp_text,
    step_index,
)
from stages.viewer.panels import COMPARE_TRUTH_COLOUR, OnlineMADE, mode_colour, stages_markdown, vehicle_panel

CAMERA_FOV_RAD = math.radians(30.0)  # narrow: the top-down view is nearly orthographic
ASSUMED_ASPECT = 1280 / 900
STEP_MIN_S, STEP_MAX_S, STEP_S = 0.4, 4.0, 0.4
#: Above this the runtime's latency (receive wall time minus header stamp) compares recording time with the wall clock.
PLAUSIBLE_LATENCY_MS = 60_000.0
# results that came earlier in the run but not for this long of frames are called out in the status: a stopped stage
STALLED_AFTER_S = 5.0
# a node's stats row older than this (a live node sends them about once a second) is marked silent
STATS_STALE_S = 5.0
# each of the two steps of closing (drawing, the web server) waits at most this long: both within the launcher's 5 s
CLOSE_TIMEOUT_S = 1.5
_TYPE_NAMES = {0: "unknown", 1: "car", 2: "truck", 3: "bus", 4: "motorcycle", 5: "bicycle", 6: "pedestrian"}


class StatsBoard:
    """The latest ``NodeStats`` of every node of the run (filled by ``update`` from the wildcard ``stats`` input, read by the render thread)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._latest: dict[str, NodeStats] = {}
        self._received: dict[str, float] = {}  # node -> monotonic time its newest NodeStats came

    def put(self, stats: NodeStats) -> None:
        with self._lock:
            self._latest[stats.node_id] = stats
            self._received[stats.node_id] = time.monotonic()

    def received_at(self, node_id: str) -> float:
        """Monotonic time the node's newest NodeStats came (stats come about once a second from a live node)."""
        with self._lock:
            return self._received.get(node_id, time.monotonic())

    def snapshot(self) -> dict[str, NodeStats]:
        with self._lock:
            return dict(self._latest)


@dataclasses.dataclass
class DrawCounters:
    drawn: int = 0
    skipped: int = 0
    received_at_last_draw: int = 0
    draw_ms: collections.deque = dataclasses.field(default_factory=lambda: collections.deque(maxlen=200))
    age_ms: collections.deque = dataclasses.field(default_factory=lambda: collections.deque(maxlen=200))  # frame's arrival to its draw with results
    e2e_ms: collections.deque = dataclasses.field(default_factory=lambda: collections.deque(maxlen=200))  # source's publish (wall) to the draw


class ViewerApp:
    """The viewer core handed to the runtime: ``update`` stores, a render thread draws into viser."""

    def __init__(self, config: ViewerConfig, *, run_id: str, log: logging.Logger | None = None, stats: StatsBoard | None = None) -> None:
        self.config = config
        self.run_id = run_id
        self.log = log or logging.getLogger("iamp.viewer")
        self.stats = stats
        self.history = FrameHistory(config.history_s)
        self.view = ViewState(step_s=config.step_s, blend_steps=config.blend_steps, show_ground_truth=config.show_ground_truth)
        self.counters = DrawCounters()
        self.server: viser.ViserServer | None = None
        self.url = ""
        self.token = ""  # what the server asks for ("": none)
        self.guard: HandshakeGuard | None = None
        self.map: MapGeometry | None = None
        self.shown: InputSet | None = None
        self.summary: dict[str, Any] = {}
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._drawn_cv = threading.Condition()
        self._view_version = 0
        self._last_key: tuple | None = None
        self._last_draw_mono = 0.0
        self._last_status_mono = 0.0
        self._labels: dict[str, Any] = {}
        self._arrived: collections.OrderedDict[int, tuple[float, int]] = collections.OrderedDict()  # stamp -> (monotonic arrival, source_wall_ns)
        self._layers: dict[str, Any] = {}
        self._announced_complete = False
        self._thread: threading.Thread | None = None
        self._gui: dict[str, Any] = {}
        self.metrics = OnlineMADE()  # running mADE of two modes (compare pipeline), from the lagged ground truth
        self._zoomed_to_traffic = False
        self._scored_until_ns: int | None = None  # frames up to this stamp have been scored (or could not be)
        self._scored_restarts = 0
        self._panel_key: tuple | None = None

    # ------------------------------------------------------------------ life cycle

    def start(self) -> str:
        """Start the viser server and the render thread; returns the page's URL."""
        cfg = self.config
        logging.getLogger("websockets").setLevel(logging.WARNING)  # viser's server logs every listen/connection at INFO
        token = cfg.effective_token()
        self.token = new_token() if token == "auto" else token
        self.guard = HandshakeGuard(host=cfg.host, token=self.token, origins=cfg.origins, log=self.log)
        with contextlib.redirect_stdout(io.StringIO()), guard_installed(self.guard):  # viser prints a banner; stages log instead
            self.server = viser.ViserServer(host=cfg.host, port=cfg.port, verbose=False)
        port = self.server.get_port()
        if cfg.port and port != cfg.port:
            self.log.warning("viewer: port %d was busy, serving on %d", cfg.port, port)
        self.url = f"http://{cfg.host}:{port}" + (f"/?token={self.token}" if self.token else "")
        scene = self.server.scene
        scene.configure_environment_map(None)
        scene.configure_default_lights(enabled=False, cast_shadow=False)
        scene.add_light_ambient("/light", intensity=math.pi)  # flat colours: diffuse colour × π/π
        self.server.initial_camera.fov = CAMERA_FOV_RAD
        self._build_gui()
        self.server.on_client_connect(self._on_client_connect)
        self.server.on_client_disconnect(lambda client: self.log.info("viewer: client disconnected: id=%d", client.client_id))
        self._thread = threading.Thread(target=self._render_loop, name="viewer-render", daemon=True)
        self._thread.start()
        return self.url

    def close(self) -> None:
        """Stop drawing and the server within ``CLOSE_TIMEOUT_S`` each: a browser that stopped reading (a stalled tab,
        a client that never reads) held the render thread's send and the server's stop past the launcher's 5 s grace,
        and the viewer was killed instead of stopped."""
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout=CLOSE_TIMEOUT_S)
            if self._thread.is_alive():
                self.log.warning("viewer: drawing did not stop within %.1f s (a browser not reading?): left to end with the process", CLOSE_TIMEOUT_S)
        if self.metrics.scores:  # the compare view's figure, for the run's log
            self.log.info("viewer: running mADE at the end: %s", "; ".join(
                f"{mode} {score.made:.2f} m over {score.windows} vehicle windows" for mode, score in sorted(self.metrics.scores.items())
            ) + f" ({self.metrics.frames_scored} frames)")
        if self.server is not None:
            server, self.server = self.server, None
            stopper = threading.Thread(target=server.stop, name="viewer-stop", daemon=True)
            with contextlib.redirect_stdout(io.StringIO()):  # viser prints on stop; process-wide, so only while we wait
                stopper.start()
                stopper.join(timeout=CLOSE_TIMEOUT_S)
            if stopper.is_alive():
                self.log.warning("viewer: the web server did not stop within %.1f s (a browser not reading?): left to end with the process", CLOSE_TIMEOUT_S)

    # ------------------------------------------------------------------ the runtime's side

    def update(self, inputs: Mapping[str, object]) -> StageResult:
        """Keep one input set (a frame with the newest results and NodeStats); the render thread draws it (or a newer one)."""
        stats = inputs.get("stats")  # the wildcard input: {key: NodeStats}, absent until the first
        if self.stats is not None and isinstance(stats, Mapping):
            for msg in stats.values():
                if isinstance(msg, NodeStats):
                    self.stats.put(msg)
        self._keep_signal_state(inputs)
        with self._lock:
            if not self.history.add(inputs):
                return StageResult(issues=[Issue("no_frame", -1, "input set without a track_frame")])
            fh = inputs["track_frame"].header
            self._arrived[fh.stamp_ns] = (time.monotonic(), fh.source_wall_ns)  # for "frame to screen" and "source to screen"
            while len(self._arrived) > 256:
                self._arrived.popitem(last=False)
        self._wake.set()
        return StageResult()

    # ------------------------------------------------------------------ view changes (GUI, tests, figures)

    def set_view(self, **changes: Any) -> None:
        """Change the view as the side panel would (``step_s=4.0``, ``paused=True`` ...); the GUI follows."""
        gui_names = {"vehicle": "vehicle", "step_s": "step", "blend_steps": "blend", "show_grid": "grid", "show_corridors": "corridors",
                     "show_means": "means", "show_labels": "labels", "show_ground_truth": "truth", "paused": "pause", "lookback_s": "lookback"}
        for name, value in changes.items():
            if name not in gui_names:
                raise ValueError(f"unknown view setting {name!r}; known: {', '.join(gui_names)}")
            handle = self._gui.get(gui_names[name])
            if handle is not None:
                handle.value = str(value) if name == "vehicle" else value  # runs the same callback as a click
            else:
                self._change_view(name, value)

    def _change_view(self, name: str, value: Any) -> None:
        with self._lock:
            if name == "paused":
                self.view.paused_at_ns = self.history.newest_complete_stamp() if value else None
            setattr(self.view, name, value)
            self._view_version += 1
        self._wake.set()

    def wait_drawn(self, predicate: Callable[[dict[str, Any]], bool], timeout_s: float) -> dict[str, Any]:
        """Block until the summary of the last draw satisfies ``predicate``; returns it (raises TimeoutError)."""
        deadline = time.monotonic() + timeout_s
        with self._drawn_cv:
            while not predicate(self.summary):
                left = deadline - time.monotonic()
                if left <= 0:
                    raise TimeoutError(f"viewer: no matching draw within {timeout_s:.0f} s; last: {self.summary}")
                self._drawn_cv.wait(left)
            return dict(self.summary)

    def fit_camera(self, bounds_m: tuple[float, float, float, float] | None = None, margin: float = 1.1) -> None:
        """Look straight down on ``bounds_m`` (default: the map) for new clients and every connected one."""
        if self.server is None:
            return
        if bounds_m is None:
            bounds_m = self.map.bounds_m if self.map is not None else (-50.0, -50.0, 50.0, 50.0)
        x0, y0, x1, y1 = bounds_m

        def pose(aspect: float) -> tuple[tuple[float, float, float], tuple[float, float, float], float]:
            cx, cy = (x0 + x1) / 2.0, (y0 + y1) / 2.0
            half = max((y1 - y0) / 2.0, (x1 - x0) / 2.0 / max(aspect, 0.1), 5.0) * margin
            height = half / math.tan(CAMERA_FOV_RAD / 2.0)
            return (cx, cy - 1e-3 * height, height), (cx, cy, 0.0), max(1000.0, 3.0 * height)

        position, look_at, far = pose(ASSUMED_ASPECT)
        cam = self.server.initial_camera
        cam.far = far
        cam.position, cam.look_at, cam.up = position, look_at, (0.0, 0.0, 1.0)
        for client in self.server.get_clients().values():
            try:
                aspect = float(client.camera.aspect)
            except Exception:  # no camera message from this client yet
                aspect = ASSUMED_ASPECT
            position, look_at, far = pose(aspect if math.isfinite(aspect) and aspect > 0 else ASSUMED_ASPECT)
            client.camera.far = far
            client.camera.position = position
            client.camera.look_at = look_at

    def objects_bounds(self, margin_m: float = 25.0) -> tuple[float, float, float, float] | None:
        """The box around the shown objects, ``margin_m`` wider on every side."""
        item = self.shown
        if item is None or not len(item.track_frame):
            return None
        x, y = np.asarray(item.track_frame.x_m), np.asarray(item.track_frame.y_m)
        ok = np.isfinite(x) & np.isfinite(y)
        if not ok.any():
            return None
        return (float(x[ok].min()) - margin_m, float(y[ok].min()) - margin_m, float(x[ok].max()) + margin_m, float(y[ok].max()) + margin_m)

    # ------------------------------------------------------------------ the side panel

    def _build_gui(self) -> None:
        gui = self.server.gui
        gui.configure_theme(control_width="large", show_share_button=False)
        gui.main_panel.dock_right()  # the canvas keeps the rest of the window
        v = self.view
        with gui.add_folder("View"):
            g = self._gui
            g["vehicle"] = gui.add_dropdown("vehicle", (ALL_VEHICLES,), initial_value=ALL_VEHICLES, hint="corridors and means of one vehicle, or of all")
            g["step"] = gui.add_slider("grid step (s)", STEP_MIN_S, STEP_MAX_S, STEP_S, _snap_step(v.step_s), hint="prediction time of the heat map")
            g["blend"] = gui.add_checkbox("blend all steps", v.blend_steps, hint="heat map: maximum over all steps")
            g["grid"] = gui.add_checkbox("heat map", v.show_grid)
            g["corridors"] = gui.add_checkbox("corridors", v.show_corridors)
            g["means"] = gui.add_checkbox("predicted means", v.show_means)
            g["labels"] = gui.add_checkbox("labels", v.show_labels)
            g["truth"] = gui.add_checkbox("ground truth (lag 4 s)", v.show_ground_truth,
                                          hint="show the frame of one horizon ago and where its objects really went")
            g["pause"] = gui.add_checkbox("pause", v.paused, hint="freeze the display (the source keeps playing)")
            g["lookback"] = gui.add_slider("look back (s)", 0.0, float(self.config.history_s), 0.1, 0.0, hint="show an older frame of the kept history")
            fit = gui.add_button("fit view to map")
            fit_objects = gui.add_button("fit view to objects")
        for key, name in (("vehicle", "vehicle"), ("step", "step_s"), ("blend", "blend_steps"), ("grid", "show_grid"), ("corridors", "show_corridors"),
                          ("means", "show_means"), ("labels", "show_labels"), ("truth", "show_ground_truth"), ("pause", "paused"), ("lookback", "lookback_s")):
            self._gui[key].on_update(lambda event, name=name: self._change_view(name, event.target.value))
        fit.on_click(lambda _event: self.fit_camera())
        fit_objects.on_click(lambda _event: self.fit_camera(self.objects_bounds()))
        with gui.add_folder("Run"):
            self._gui["status"] = gui.add_markdown("waiting for the first frame")
        self._build_vehicle_panel_gui(gui)
        with gui.add_folder("Stages"):
            self._gui["stages"] = gui.add_markdown("no stats yet" if self.config.stats else "stats are off (`stats = false`)")
        legend = " · ".join(f"<span style='color:rgb{c}'>■</span> {_TYPE_NAMES[t]}" for t, c in TYPE_COLOURS.items() if t)
        with gui.add_folder("Legend", expand_by_default=False):
            gui.add_markdown(legend + "<br>light blue lines: corridors (p = corridor probability) · black dots: predicted means per step, "
                             "white: at the grid step · heat: occupancy (log scale) · yellow-green: true future")

    def _on_client_connect(self, client: Any) -> None:
        self.log.info("viewer: client connected: id=%d", client.client_id)
        self._wake.set()  # from the idle rate to max_render_hz at once: the newest set drawn now

    def _draw_period_s(self) -> float:
        """1 / ``max_render_hz`` while a browser is connected, else 1 / ``idle_render_hz`` (when slower)."""
        hz = self.config.max_render_hz
        if not self.server.get_clients():
            hz = min(hz, self.config.idle_render_hz)
        return 1.0 / hz

    # ------------------------------------------------------------------ drawing

    def _render_loop(self) -> None:
        while not self._stop.is_set():
            self._wake.wait(timeout=1.0 / self.config.status_hz)
            if self._stop.is_set():
                break
            # at most max_render_hz (idle_render_hz with no browser connected): newer sets pile up meanwhile and the
            # newest wins; a browser that connects while this waits ends the wait (``_wake``)
            while (wait := self._last_draw_mono + self._draw_period_s() - time.monotonic()) > 0 and not self._stop.is_set():
                self._wake.clear()
                if self._wake.wait(min(wait, 1.0 / self.config.status_hz)):
                    continue  # (a new set or a client: the period is looked at again)
                if time.monotonic() - self._last_status_mono >= 1.0 / self.config.status_hz:
                    self._last_status_mono = time.monotonic()
                    self._draw_status_safely()
            self._wake.clear()
            try:
                self._draw()
                if time.monotonic() - self._last_status_mono >= 1.0 / self.config.status_hz:
                    self._last_status_mono = time.monotonic()
                    self._draw_status()
            except Exception:
                self.log.exception("viewer: draw failed (the next set is drawn anew)")
                self._last_key = None

    def _draw_status_safely(self) -> None:
        try:
            self._draw_status()
        except Exception:
            self.log.exception("viewer: status panel failed")

    def _draw(self) -> None:
        with self._lock:
            newest_ns = self.history.newest_stamp_ns
            if newest_ns is None:
                return
            max_lag_ns = int(self.config.max_lag_s * 1e9)
            newest = self.history.at(newest_ns, max_lag_ns)
            horizon_s = newest.horizon_s(self.config.horizon_s)
            view = dataclasses.replace(self.view)
            target = view.target_stamp(newest.stamp_ns, horizon_s)
            item = self.history.at(target, max_lag_ns) or self.history.oldest()
            futures, complete = self.history.true_futures(item, horizon_s) if view.show_ground_truth else ({}, False)
            self._score_compare(newest.stamp_ns, horizon_s)
            received = self.history.received
            arrived = self._arrived.get(item.stamp_ns)
            key = (item.stamp_ns, item.complete, self._view_version, self.history.restarts, len(futures))
        if key == self._last_key:
            return
        t0 = time.perf_counter()
        if not view.paused:
            new = received - self.counters.received_at_last_draw
            self.counters.skipped += max(0, new - 1)
        self.counters.received_at_last_draw = received
        scene_info = item.scene
        if scene_info is not None and (self.map is None or self.map.scene_id != scene_info.scene_id):
            self._draw_map(scene_info)
        summary = self._draw_frame(item, view, futures, complete)
        summary.update(self._draw_compare(item, view, futures))
        self._zoom_to_traffic(item)
        summary["stop_lines"] = self._draw_stop_lines(scene_info)
        dt = (time.perf_counter() - t0) * 1e3
        self.counters.drawn += 1
        self.counters.draw_ms.append(dt)
        if arrived is not None and item.stamp_ns == newest.stamp_ns and not view.paused:
            self.counters.age_ms.append((time.monotonic() - arrived[0]) * 1e3)
            if arrived[1]:
                self.counters.e2e_ms.append((time.time_ns() - arrived[1]) / 1e6)
        self._last_key = key
        self._last_draw_mono = time.monotonic()
        self.shown = item
        summary.update(drawn=self.counters.drawn, skipped=self.counters.skipped, received=received)
        with self._drawn_cv:
            self.summary = summary
            self._drawn_cv.notify_all()
        if not self._announced_complete and all(summary[k] for k in ("objects", "car_lanelets", "corridors", "means", "grid_cells")):
            self._announced_complete = True
            self.log.info(
                "viewer: scene drawn: frame=%d objects=%d car_lanelets=%d other_lanelets=%d corridors=%d means=%d grid_cells=%d step_s=%.1f",
                summary["frame"], summary["objects"], summary["car_lanelets"], summary["other_lanelets"], summary["corridors"],
                summary["means"], summary["grid_cells"], summary["step_s"],
            )

    # ------------------------------------------------------------------ signalised stop lines (stages.viewer.signals)

    def _keep_signal_state(self, inputs: Mapping[str, object]) -> None:
        from bus_schemas import SignalState

        state = inputs.get("signal_state")
        if isinstance(state, SignalState):
            self._signal_state = state

    def _draw_stop_lines(self, scene_info: Any) -> int:
        """Stop lines coloured by the newest SignalState; the lines are found once per scene. Returns how many."""
        from stages.viewer.signals import load_stop_lines, stop_line_segments

        if scene_info is None:
            return 0
        if getattr(self, "_stop_lines_scene", None) != scene_info.scene_id:
            self._stop_lines_scene = scene_info.scene_id
            self._stop_lines, problems = load_stop_lines(scene_info, self.config.data)
            for problem in problems:
                self.log.warning("viewer: %s", problem)
        segments = stop_line_segments(self._stop_lines, getattr(self, "_signal_state", None))
        if len(segments):
            self._layers["stop_lines"] = self.server.scene.add_line_segments("/map/stop_lines", segments.points_m, segments.colours, thickness=0.6)
        else:
            self._remove_layer("stop_lines")
        return len(segments)

    def _draw_map(self, scene_info: Any) -> None:
        geometry = load_map_geometry(scene_info, self.config.data)
        for problem in geometry.problems:
            self.log.warning("viewer: map problem: %s", problem)
        scene = self.server.scene
        with self.server.atomic():
            if len(geometry.car_faces):
                scene.add_mesh_simple("/map/car_lanelets", geometry.car_vertices_m, geometry.car_faces, color=CAR_LANELET_FILL, side="double",
                                      flat_shading=True, cast_shadow=False, receive_shadow=False)
            if len(geometry.car_borders):
                scene.add_line_segments("/map/car_borders", geometry.car_borders.points_m, geometry.car_borders.colours, thickness=0.12)
            if len(geometry.other_outlines):
                scene.add_line_segments("/map/other_lanelets", geometry.other_outlines.points_m, geometry.other_outlines.colours, thickness=0.15)
        first = self.map is None
        self.map = geometry
        self.log.info("viewer: map drawn: scene_id=%s car_lanelets=%d other_lanelets=%d", geometry.scene_id, geometry.n_car_lanelets, geometry.n_other_lanelets)
        if first:
            self.fit_camera()

    def _draw_frame(self, item: InputSet, view: ViewState, futures: dict[int, np.ndarray], complete: bool) -> dict[str, Any]:
        scene = self.server.scene
        vehicle = view.vehicle_id()
        boxes = object_boxes(item.track_frame)
        grid = item.grid
        k = None if (view.blend_steps or grid is None) else step_index(grid.step_times_s, view.step_s)
        heat = grid_mesh(grid, k, scale=self.config.grid_scale, floor=self.config.grid_floor) if (grid is not None and view.show_grid) else None
        lines, p_labels = corridor_lines(item, vehicle, boxes) if view.show_corridors else (None, [])
        k_means = None if view.blend_steps else step_index(item.predictions.step_times_s, view.step_s) if item.predictions is not None else None
        every, chosen = mean_points(item, vehicle, k_means) if (view.show_means and item.compare is None) else (np.zeros((0, 3)), np.zeros((0, 3)))
        truth_colour = COMPARE_TRUTH_COLOUR if item.compare is not None else TRUTH_COLOUR  # the compare view: black truth, as in the paper
        truth = polyline_segments(list(futures.values()), truth_colour, Z_TRUTH) if view.show_ground_truth else None
        with self.server.atomic():
            # one plain mesh per colour (see box_meshes: not an instanced mesh)
            self._sync_meshes("objects/boxes", {"{}_{}_{}".format(*m.colour): (m.vertices_m, m.faces, {"color": m.colour}) for m in box_meshes(boxes)})
            labels = {}
            if view.show_labels:
                for i, tid in enumerate(boxes.track_ids):  # above the box on screen, not on it
                    labels[f"/objects/labels/t{int(tid)}"] = (str(int(tid)), boxes.id_label_position(i), "bottom-center")
                for lab in p_labels:  # a standing car's beside its box (corridor_lines)
                    labels[f"/corridors/p/c{lab.name}"] = (lab.text, lab.position_m, lab.anchor)
            self._sync_labels(labels)
            if lines is not None and len(lines):
                self._layers["corridors"] = scene.add_line_segments("/corridors/lines", lines.points_m, lines.colours, thickness=0.25)
            else:
                self._remove_layer("corridors")
            if len(every):
                self._layers["means"] = scene.add_point_cloud("/predictions/means", every, colors=MEAN_COLOUR, point_size=0.2, point_shape="circle", precision="float32")
            else:
                self._remove_layer("means")
            if len(chosen):
                self._layers["means_at_step"] = scene.add_point_cloud("/predictions/at_step", chosen, colors=MEAN_AT_STEP_COLOUR, point_size=0.5, point_shape="circle", precision="float32")
            else:
                self._remove_layer("means_at_step")
            levels = heat.levels if heat is not None else ()
            self._sync_meshes("grid", {f"level_{i}": (lv.vertices_m, lv.faces, {"color": lv.rgb, "opacity": lv.opacity, "side": "double"})
                                       for i, lv in enumerate(levels)})
            if truth is not None and len(truth):
                self._layers["truth"] = scene.add_line_segments("/truth", truth.points_m, truth.colours, thickness=0.3)
            else:
                self._remove_layer("truth")
        self._update_vehicle_options(matched_vehicles(item.corridor_set), view.vehicle)
        step_s = float(grid.step_times_s[k]) if (grid is not None and k is not None and len(grid.step_times_s)) else -1.0
        return {
            "frame": item.frame_index,
            "stamp_ns": item.stamp_ns,
            "mode": item.mode,
            "objects": len(boxes),
            "object_types": sorted({int(t) for t in boxes.agent_types}),
            "car_lanelets": self.map.n_car_lanelets if self.map else 0,
            "other_lanelets": self.map.n_other_lanelets if self.map else 0,
            "corridors": len(p_labels),
            "means": int(len(every)),
            "grid_cells": heat.cells if heat is not None else 0,
            "grid_max": heat.max_value if heat is not None else 0.0,
            "step_s": step_s,
            "blend": view.blend_steps,
            "truth_tracks": len(futures),
            "truth_complete": complete,
            "paused": view.paused,
        }

    def _sync_meshes(self, prefix: str, meshes: Mapping[str, tuple[np.ndarray, np.ndarray, dict[str, Any]]]) -> None:
        """Draw each of ``meshes`` (name -> vertices, faces, style) as the plain mesh layer ``prefix/name`` and remove
        the layers under ``prefix/`` that are not among them (flat colours: the scene's light is ambient only)."""
        for name, (vertices, faces, style) in meshes.items():
            self._layers[f"{prefix}/{name}"] = self.server.scene.add_mesh_simple(
                f"/{prefix}/{name}", vertices, faces, flat_shading=True, cast_shadow=False, receive_shadow=False, **style
            )
        stale = [k for k in self._layers if k.startswith(prefix + "/") and k[len(prefix) + 1 :] not in meshes]
        for key in stale:
            self._remove_layer(key)

    def _remove_layer(self, name: str) -> None:
        handle = self._layers.pop(name, None)
        if handle is not None:
            handle.remove()

    def _sync_labels(self, wanted: dict[str, tuple[str, tuple[float, float, float], str]]) -> None:
        for name in [n for n in self._labels if n not in wanted]:
            self._labels.pop(name).remove()
        for name, (text, position, anchor) in wanted.items():
            handle = self._labels.get(name)
            if handle is None:
                self._labels[name] = self.server.scene.add_label(name, text, position=position, anchor=anchor, font_screen_scale=0.7, depth_test=False)
            else:
                handle.position = position
                if handle.text != text:
                    handle.text = text
                if handle.anchor != anchor:
                    handle.anchor = anchor

    def _update_vehicle_options(self, vehicles: list[int], selected: str) -> None:
        options = (ALL_VEHICLES, *[str(v) for v in vehicles])
        if selected not in options:
            options = options + (selected,)  # keep a chosen vehicle while it is away
        handle = self._gui["vehicle"]
        if tuple(handle.options) != options:
            handle.options = options

    def _draw_status(self) -> None:
        item, c = self.shown, self.counters
        with self._lock:
            view = dataclasses.replace(self.view)
            received = self.history.received
        stats = self.stats.snapshot() if self.stats is not None else {}
        if item is None:
            self._gui["status"].content = f"**run** {self.run_id} · waiting for the first frame"
        else:
            shown = "paused" if view.paused else "live"
            newest_ns = self.history.newest_stamp_ns or item.stamp_ns
            if not item.complete:
                shown += f", results more than {self.config.max_lag_s:g} s late: frame shown without them"
            if item.coverage:
                shown += f", **{item.coverage}**"
            elif not view.paused and not view.show_ground_truth and not view.lookback_s and newest_ns - item.stamp_ns > 5e8:
                shown += f", results lag the frames by {(newest_ns - item.stamp_ns) / 1e9:.1f} s"
            stalled = self.history.stalled(int(STALLED_AFTER_S * 1e9))
            if stalled:
                oldest = max(stalled.values())
                shown += (f", **no {', '.join(k.replace('_', ' ') for k in stalled)} for {oldest:.0f} s**"
                          " (their stage has stopped, hung or fallen far behind)")
            if view.show_ground_truth:
                shown += f", lagging {item.horizon_s(self.config.horizon_s):.1f} s for ground truth"
            if view.lookback_s:
                shown += f", {view.lookback_s:.1f} s back"
            draw_ms = float(np.median(c.draw_ms)) if c.draw_ms else 0.0
            # measured only on draws of the newest frame: while the view lags (ground truth, look back, pause) the
            # figures of before would stand as if current
            lagging = view.paused or view.show_ground_truth or bool(view.lookback_s)
            age = f"{float(np.median(c.age_ms)):.0f} ms" if c.age_ms and not lagging else "–"
            e2e = f"{float(np.median(c.e2e_ms)):.0f} ms" if c.e2e_ms and not lagging else "–"
            s = self.summary
            self._gui["status"].content = "\n\n".join([
                f"**run** {self.run_id} · **frame** {item.frame_index} · {stamp_text(item.stamp_ns)} · **mode** {item.mode}",
                f"showing: {shown}",
                f"sets received {received} · drawn {c.drawn} · skipped {c.skipped}",
                f"draw {draw_ms:.0f} ms · frame to screen {age} (p50) · source to screen {e2e} (p50) · ≤ {self.config.max_render_hz:g} Hz",
                f"objects {s.get('objects', 0)} · corridors {s.get('corridors', 0)} · grid "
                + ("all steps" if view.blend_steps else f"{s['step_s']:.1f} s" if s.get("step_s", -1) >= 0 else "–")
                + f": {s.get('grid_cells', 0)} cells, max {s.get('grid_max', 0):.2f}",
            ])
        self._draw_vehicle_panel(view)
        if stats:
            now = time.monotonic()
            silent = {node_id: now - self.stats.received_at(node_id) for node_id in stats}
            self._gui["stages"].content = stages_markdown(stats, {n: a for n, a in silent.items() if a >= STATS_STALE_S}, PLAUSIBLE_LATENCY_MS)


    # ------------------------------------------------------------------ compare view, selected vehicle, initial zoom (panels.py)

    def _build_vehicle_panel_gui(self, gui: Any) -> None:
        with gui.add_folder("Compare"):
            self._gui["compare"] = gui.add_markdown("one prediction mode (pipelines/compare.toml runs two)")
        with gui.add_folder("Selected vehicle"):
            self._gui["vehicle_md"] = gui.add_markdown("choose a vehicle in View → vehicle")
            self._gui["vehicle_ar"] = gui.add_image(np.full((14, 14, 3), 255, np.uint8), label="AR acceleration distributions, next 4 s", format="png", visible=False)

    def _score_compare(self, newest_ns: int, horizon_s: float) -> None:
        """Score the frames whose future is now known on both modes' predictions (called with the lock held)."""
        ready_ns = newest_ns - int(round(horizon_s * 1e9))
        if self.history.restarts != self._scored_restarts:  # a source that started over: its stamps begin anew
            self._scored_restarts, self._scored_until_ns = self.history.restarts, None
        if self._scored_until_ns is not None and ready_ns <= self._scored_until_ns:
            return
        first_ns = -1 if self._scored_until_ns is None else self._scored_until_ns + 1
        for s in self.history.sets_between(max(first_ns, 0), ready_ns):
            if s.predictions is not None and s.compare is not None:
                frames = self.history.frames_between(s.stamp_ns, s.stamp_ns + int(round(horizon_s * 1e9)) + int(2e8))
                self.metrics.score(s.stamp_ns, s.predictions, s.compare, frames)
        self._scored_until_ns = ready_ns

    def _draw_compare(self, item: InputSet, view: ViewState, futures: dict[int, np.ndarray]) -> dict[str, Any]:
        """Both modes' predicted means as lines in their colours (blue hybrid, red baseline); the truth is drawn black by ``_draw_frame``."""
        scene = self.server.scene
        vehicle = view.vehicle_id()
        drawn = {}
        for name, pred in (("first", item.predictions), ("second", item.compare)):
            layer = f"compare_{name}"
            if item.compare is None or pred is None or not view.show_means:
                self._remove_layer(layer)
                continue
            lines = []
            for p in pred.predictions:
                if vehicle is not None and p.track_id != vehicle:
                    continue
                lines.append(np.stack([p.mean_x_m, p.mean_y_m], axis=1))
            segs = polyline_segments(lines, mode_colour(pred.mode), Z_TRUTH + 0.01)
            if len(segs):
                self._layers[layer] = scene.add_line_segments(f"/compare/{name}", segs.points_m, segs.colours, thickness=0.35)
            else:
                self._remove_layer(layer)
            drawn[f"compare_{pred.mode}_segments"] = len(segs)
        return drawn

    def _zoom_to_traffic(self, item: InputSet) -> None:
        """Once, with ``initial_view = "traffic"``, when 3 s of frames have come: look down on where the traffic of those seconds was.

        The box holds the 10th to 90th percentiles of every object position of
        those frames, 15 m wider on every side and at least 70 m across: the
        junction's traffic, not a parked car at the map's edge.
        """
        if self._zoomed_to_traffic or self.config.initial_view != "traffic" or self.map is None:
            return
        with self._lock:
            oldest = self.history.oldest()
            newest_ns = self.history.newest_stamp_ns
            if oldest is None or newest_ns is None or newest_ns - oldest.stamp_ns < 3_000_000_000:
                return
            frames = self.history.frames_between(oldest.stamp_ns, oldest.stamp_ns + 3_000_000_000)
        xs = np.concatenate([np.asarray(f.x_m, dtype=float) for f in frames]) if frames else np.zeros(0)
        ys = np.concatenate([np.asarray(f.y_m, dtype=float) for f in frames]) if frames else np.zeros(0)
        ok = np.isfinite(xs) & np.isfinite(ys)
        self._zoomed_to_traffic = True
        if not ok.any():
            return
        x0, x1 = np.percentile(xs[ok], [10, 90])
        y0, y1 = np.percentile(ys[ok], [10, 90])
        cx, cy, half = (x0 + x1) / 2, (y0 + y1) / 2, max(x1 - x0 + 30.0, y1 - y0 + 30.0, 70.0) / 2
        self.fit_camera((cx - half, cy - half, cx + half, cy + half), margin=1.0)
        self.log.info("viewer: zoomed onto the traffic: centre=(%.0f, %.0f) m, %.0f m across", cx, cy, 2 * half)

    def _draw_vehicle_panel(self, view: ViewState) -> None:
        """The compare line and the selected vehicle's corridors, P(route), P(stop), AR distributions and true future."""
        item = self.shown
        if item is None:
            return
        if item.compare is not None or self.metrics.scores:
            self._gui["compare"].content = self.metrics.line() + "<br>lines: predicted means of each corridor per mode · black: the true future"
        vehicle = view.vehicle_id()
        if vehicle is None:
            if self._panel_key is not None:
                self._gui["vehicle_md"].content = "choose a vehicle in View → vehicle"
                self._gui["vehicle_ar"].visible = False
                self._panel_key = None
            return
        with self._lock:
            horizon_s = item.horizon_s(self.config.horizon_s)
            frames = self.history.frames_between(item.stamp_ns, item.stamp_ns + int(round(horizon_s * 1e9)) + int(2e8))
        key = (vehicle, item.stamp_ns, len(frames))
        if key == self._panel_key:
            return
        self._panel_key = key
        from stages.viewer.panels import truth_at

        pred = item.predictions
        times = np.asarray(pred.step_times_s, dtype=float) if pred is not None else np.zeros(0)
        truth = truth_at(frames, item.stamp_ns, times).get(vehicle) if len(times) else None
        text, image = vehicle_panel(vehicle, pred, item.belief, item.profiles, truth, truth is not None)
        # the image first: a reader that sees the new text sees its image too
        if image is not None:
            self._gui["vehicle_ar"].image = image
            self._gui["vehicle_ar"].visible = True
        else:
            self._gui["vehicle_ar"].visible = False
        self._gui["vehicle_md"].content = text


def _snap_step(step_s: float) -> float:
    return float(min(STEP_MAX_S, max(STEP_MIN_S, round(math.ceil(step_s / STEP_S - 1e-6) * STEP_S, 6))))
