"""The viewer's scene objects: where the ``p=`` labels of a standing car go, and the "Stages" panel's layout.

A standing car's corridors have their last predicted mean where the car is,
so their ``p=`` labels were drawn on the car's box (unreadable). The viewer
(in-process, its viser server on 127.0.0.1) draws a made-up frame: a car
standing in a queue (one car right ahead, one in the lane to its left) with
two corridors, and a moving car; the test reads the label handles of the
viser scene (no pixels). The "Stages" panel was an eight-column table that
the narrow side panel squeezed; it is read from the panel's markdown.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import re

import numpy as np
import pytest

import bus_schemas as bs
from testkit import samples
from testkit.helpers import free_port, wait_until

pytest.importorskip("viser")

from stages.viewer.config import ViewerConfig  # noqa: E402
from stages.viewer.model import LABEL_SPACING_M  # noqa: E402
from stages.viewer.scene import ViewerApp  # noqa: E402

STANDING, AHEAD, BESIDE, MOVING = 100, 101, 102, 103
# x east, y north; the standing car heads east in a queue: one car 1.5 m ahead, one in the lane to its left (north)
POSITIONS = {STANDING: (10.0, -5.0), AHEAD: (16.0, -5.0), BESIDE: (10.0, -1.75), MOVING: (-40.0, 20.0)}


def frame() -> bs.TrackFrame:
    ids = list(POSITIONS)
    n = len(ids)
    return dataclasses.replace(
        samples.track_frame(n), track_ids=np.array(ids, np.int64), agent_types=np.ones(n, np.uint8),
        x_m=np.array([POSITIONS[t][0] for t in ids]), y_m=np.array([POSITIONS[t][1] for t in ids]),
        vx_mps=np.array([0.0, 0.0, 0.0, 8.0]), vy_mps=np.zeros(n), yaw_rad=np.zeros(n), length_m=np.full(n, 4.5), width_m=np.full(n, 1.9))


def corridor(cid: int, xy: np.ndarray, vehicle_s_m: float) -> bs.Corridor:
    s = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(xy, axis=0).T))])
    heading = np.arctan2(*np.gradient(xy, axis=0)[:, ::-1].T)
    m = len(s)
    return dataclasses.replace(samples.corridor_set().vehicles[0].corridors[0], corridor_id=cid, x_m=xy[:, 0].copy(), y_m=xy[:, 1].copy(), s_m=s,
                               heading_rad=heading, curvature_1pm=np.zeros(m), width_m=np.full(m, 3.25), extension_start_s_m=float(s[-1]),
                               vehicle_s_m=vehicle_s_m, vehicle_d_m=0.0)


def inputs() -> dict:
    f = frame()
    x0, y0 = POSITIONS[STANDING]
    straight = np.stack([np.arange(x0 - 5.0, x0 + 40.0, 0.5), np.full(90, y0)], axis=1)
    turn = np.concatenate([straight[:30], np.stack([np.full(60, x0 + 10.0), y0 + 0.5 * np.arange(1, 61)], axis=1)])
    mx, my = POSITIONS[MOVING]
    road = np.stack([np.arange(mx - 5.0, mx + 60.0, 0.5), np.full(130, my)], axis=1)
    vehicles = (
        dataclasses.replace(samples.corridor_set().vehicles[0], track_id=STANDING, corridors=(corridor(1, straight, 5.0), corridor(2, turn, 5.0)), standing=True),
        dataclasses.replace(samples.corridor_set().vehicles[0], track_id=MOVING, corridors=(corridor(3, road, 5.0),)),
    )
    cs = bs.CorridorSet(header=f.header, scene_id=f.scene_id, vehicles=vehicles)
    base = samples.corridor_predictions()
    template = base.predictions[0]
    k = len(base.step_times_s)

    def pred(tid: int, cid: int, p: float, xs: np.ndarray, ys: np.ndarray) -> bs.CorridorPrediction:
        return dataclasses.replace(template, track_id=tid, corridor_id=cid, probability=p, mean_x_m=xs, mean_y_m=ys, x_at_mean_s_m=xs, y_at_mean_s_m=ys)

    stand_x, stand_y = np.full(k, x0), np.full(k, y0)  # a standing car: every step's mean where it stands
    preds = (pred(STANDING, 1, 0.75, stand_x, stand_y), pred(STANDING, 2, 0.25, stand_x, stand_y),
             pred(MOVING, 3, 1.0, mx + np.array([3.2, 6.4, 9.6]), np.full(k, my)))
    cp = dataclasses.replace(base, header=f.header, scene_id=f.scene_id, predictions=preds)
    return {"track_frame": f, "corridor_set": cs, "corridor_predictions": cp}


def node_stats(node_id: str, **kw) -> bs.NodeStats:
    return dataclasses.replace(samples.node_stats(), node_id=node_id, stage=f"stages.{node_id}", **kw)


@pytest.fixture
def app():
    a = ViewerApp(ViewerConfig(port=free_port(), stats=True), run_id="labels", log=logging.getLogger("iamp.viewer"))
    from stages.viewer.scene import StatsBoard

    a.stats = StatsBoard()
    a.start()
    try:
        yield a
    finally:
        a.close()


def test_a_standing_cars_probability_labels_sit_beside_its_box_not_on_it(app):
    sets = inputs()
    app.update(sets)
    app.wait_drawn(lambda s: s.get("corridors") == 3, 30)
    labels = {name: (h.text, tuple(float(v) for v in h.position), h.anchor) for name, h in app._labels.items()}
    standing = {n: v for n, v in labels.items() if n.startswith(f"/corridors/p/c{STANDING}_")}
    assert sorted(t for t, _p, _a in standing.values()) == ["p=0.25", "p=0.75"], labels
    spots = [p[:2] for _t, p, _a in standing.values()]
    ids = [p[:2] for n, (_t, p, _a) in labels.items() if n.startswith("/objects/labels/t")]
    x0, y0 = POSITIONS[STANDING]
    for (x, y) in spots:
        assert not any(abs(x - bx) <= 4.5 / 2 and abs(y - by) <= 1.9 / 2 for bx, by in POSITIONS.values()), f"label at {(x, y)} on a box"  # yaw 0
        assert math.hypot(x - x0, y - y0) <= 0.5 * math.hypot(4.5, 1.9) + 2 * LABEL_SPACING_M, "beside its own car, not far off"
        assert all(math.hypot(x - a, y - b) >= LABEL_SPACING_M - 1e-9 for a, b in ids), "clear of the id labels"
    assert math.dist(*spots) >= LABEL_SPACING_M - 1e-9, "the two labels apart"
    # beside the car (heading east): the text grows away from it, up from a label north of it, down from one south of it
    for _t, (x, y, _z), anchor in standing.values():
        assert abs(y - y0) > 1.9 / 2 and anchor == ("bottom-center" if y > y0 else "top-center"), (x, y, anchor)
    # a moving car's label stays at its last predicted mean
    (moving,) = [v for n, v in labels.items() if n.startswith(f"/corridors/p/c{MOVING}_")]
    assert moving[0] == "p=1.00" and moving[1][:2] == pytest.approx((POSITIONS[MOVING][0] + 9.6, POSITIONS[MOVING][1])) and moving[2] == "bottom-center"


def test_the_stages_panel_is_two_short_lines_a_node_not_an_eight_column_table(app):
    for node in ("corridors", "markov_prediction"):
        app.stats.put(node_stats(node, counters={"issues": 3, "decode_errors": 0, "core_errors": 0, "queue_drops": 2, "join_drops": 0}))
    app.update(inputs())
    # no table; per node a name line and a counts line, each short enough for the side panel
    content = wait_until(lambda: "markov_prediction" in app._gui["stages"].content and app._gui["stages"].content, 30, "the Stages panel")
    assert "|" not in content, content
    blocks = content.split("\n\n")
    assert len(blocks) == 3 and blocks[-1].startswith("ms: processing"), content
    for block, node in zip(blocks, ("corridors", "markov_prediction")):
        lines = block.split("<br>")
        assert len(lines) == 2 and lines[0].startswith(f"**{node}** · 1.5/3 ms · e2e 22/48 ms"), block
        assert lines[1] == "lat 2 ms · q 0 · iss 3 · err 0 · **drop 2**", block
        assert all(len(re.sub(r"\*\*", "", line)) <= 50 for line in lines), block
