"""Viewer stage: the live scene in the browser, served by viser on 127.0.0.1 (ARCHITECTURE.md §3, viewer).

Consumes ``track_frame`` (``TrackFrame``) and the latched ``scene``
(``SceneInfo``) and, when the pipeline binds them, ``corridor_set``
(``CorridorSet``), ``corridor_predictions`` (``CorridorPredictions``),
``motion_grid`` (``MotionGrid``), ``compare_predictions`` (a second mode's
``CorridorPredictions``: the compare view), ``intention_belief``
(``IntentionBelief``) and ``acceleration_profiles``
(``AccelerationProfiles``: the selected-vehicle panel), and every node's ``NodeStats`` on
``iamp/<run>/_stats/*`` (the wildcard input ``stats``, bound by the
runtime). It produces nothing on the bus. The results are
latest-value inputs (``Port(latest=True)``): they take no part in the
runtime's stamp join (16 stamps, 2 s), which would drop every frame once
the predictions lag by more, as they do on a busy machine, and never hold a
frame back; the core gets the newest of each with every frame and joins
them to their frames by stamp itself (``model.FrameHistory``). Run
it alone with ``python -m stages.viewer``; when up it logs one line
``viewer: http://127.0.0.1:PORT`` (the launcher repeats it as
``[launch] viewer: ...``).

What the page shows, top-down (x east, y north, metres of the scene):

- the lanelet map (``stages.lib.maps``, loaded as the corridors stage loads it):
  car lanelets as filled dark polygons with light borders, the other
  lanelets (walkways, crosswalks, bike lanes) outlined;
- every object as a box sized by the track (or by its type's default),
  coloured by its type, with its track id as a label;
- the corridors of the chosen vehicle (or of all) as light blue
  centrelines, each labelled with its probability ``p`` where its
  prediction ends; a standing car's labels, whose prediction ends where the
  car stands, go beside its box instead of on it
  (``model.place_labels_off_boxes``);
- the predicted mean position of every corridor at every step (small black
  dots) and at the chosen step (white dots);
- the motion grid of the chosen step (0.4 … 4.0 s; a time between two steps
  shows the step whose interval holds it: 1.0 s shows the step ending at
  1.2 s) or of all steps blended (their maximum) as a heat map: an RGBA
  image on the ground, transparent below ``grid_floor``, log (or linear) in
  the occupancy;
- with "ground truth" on, the display lags by the horizon (4 s): it shows the
  frame of 4 s ago with its predictions and the tracks' true paths since.
  The viewer keeps ``history_s`` of frames and results for this and for
  the "look back" slider.

The compare view (``compare_predictions`` bound, ``pipelines/compare.toml``):
the predicted means of both modes as lines, blue hybrid and red baseline
(``panels.MODE_COLOURS``), over the true future in black, and the running
mADE of each mode from the lagged ground truth (``panels.OnlineMADE``: every
frame whose horizon has passed, scored on the vehicles both modes predicted).

The selected vehicle (View -> vehicle): its corridors with P(route), route and
P(stop) (intentions), P(stop) of the vehicle, the AR acceleration
distributions of its most probable corridor for the next 4 s (a heat image:
one row per 0.4 s step, columns -3 … 2 m/s²) and, once known (ground truth
on), its true future with each corridor's ADE (``panels.vehicle_panel``).

Side panel: run, frame, stamp, mode, what is shown (live, paused, lagging;
in a sharded pipeline, a shard's vehicles only or a shard missing from the
fused frame: ``MotionGrid.shard``, ``missing_shards``),
frames received, drawn and skipped, the draw time and the time from a
frame's arrival to its drawing with its results (and from the source's
publish of the frame, "source to screen", when it carries a wall stamp),
and per node (from the
``NodeStats`` on ``iamp/<run>/_stats/*``, as the newest of each with every
frame, on the stage's one session) processing time p50/p95, end-to-end
latency p50/p95 (``e2e_ms_*``: the source's publish of the frame to the
node's publish of its result; "–" for an old recording without wall
stamps), latency,
queue depth, issues, errors (decode + core) and drops (queue + join), two
short lines per node with a legend (``panels.stages_markdown``; an
eight-column table did not fit the side panel). "pause" freezes the display; the source keeps playing (it has no control
key to listen to).

Keeping up: ``update`` only files the inputs; a render thread draws at
most ``max_render_hz`` times a second while a browser is connected (at
most ``idle_render_hz`` while none is: drawing for nobody at 10 Hz took a
third of a core at 72 vehicles, and the prediction stages lost half their
frames to it on 2 cores; a page that opens gets the scene kept on the
server and the newest set at once) and always the newest complete set
(the newest frame whose results have all arrived), counting the frames that
were never drawn as skipped (the runtime's queue in front drops the oldest
entries when full). When the results lag, the side panel says by how much;
when they are more than ``max_lag_s`` late (or stop), the newest frame is
shown without them.

Parameters (``ViewerConfig``):

- ``host`` "127.0.0.1", ``port`` 8080 (0: a free port; a busy port moves
  to the next free one, and the logged URL says which);
- ``max_render_hz`` 10, ``status_hz`` 2: draw and side-panel rates;
  ``idle_render_hz`` 1: the draw rate while no browser is connected;
- ``history_s`` 20: input sets kept for ground truth and looking back;
- ``horizon_s`` 4: the ground truth shown when predictions do not say
  their horizon;
- ``max_lag_s`` 15 (stamp time): results later than this are not waited
  for;
- ``step_s`` 1.0, ``blend_steps`` false, ``show_ground_truth`` false: the
  view at start;
- ``grid_scale`` "log" (or "linear"), ``grid_floor`` 1e-3: the heat map;
- ``stats`` true: show the run's ``NodeStats`` (false: the panel leaves
  them out; the runtime still subscribes);
- ``initial_view`` "traffic": the page opens on the whole map and, once 3 s
  of frames have come, zooms onto the traffic of those seconds (10th-90th
  percentile box of the positions, 15 m around, at least 70 m); "map" keeps
  the whole map;
- ``token`` "" (none; or ``$IAMP_VIEWER_TOKEN``), ``"auto"`` (a fresh random
  one) or 16+ characters of ``A-Z a-z 0-9 _ -``: the page URL then carries
  ``?token=...`` (the logged URL has it) and requests without it get 403;
- ``origins`` []: page origins allowed besides ``http://127.0.0.1:PORT``,
  ``http://localhost:PORT`` and ``http://HOST:PORT``.
- ``data`` "": the local data folder whose ``maps/`` holds the scene's map
  (the launcher passes its ``--data``; "" the embedded ``stages/data/taf-bw``). The
  map is found by the scene's ``map_name`` there and drawn only when its
  sha256 matches; no path from the bus is opened (see ``stages.corridors``).

Access (``guard.py``): a websocket handshake or request whose ``Origin`` is
not the page's own is refused with 403 before any scene data; one without
``Origin`` (not a browser) is let through. The check wraps viser's
``process_request`` for the time its server starts (``guard.installed``),
without changing viser.
"""

from __future__ import annotations

from stages.viewer.config import ViewerConfig

__all__ = ["INPUTS", "OUTPUTS", "SPEC", "ViewerApp", "ViewerConfig", "main"]

_BINDING = ("SPEC", "INPUTS", "OUTPUTS", "main", "make_core")


def __getattr__(name: str):
    """The binding lives in ``__main__.py`` and viser in ``scene.py``: both load only when asked."""
    if name in _BINDING:
        from stages.viewer import __main__ as binding

        return getattr(binding, name)
    if name == "ViewerApp":
        from stages.viewer.scene import ViewerApp

        return ViewerApp
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
