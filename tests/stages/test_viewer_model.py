"""The viewer's pure helpers (``stages.viewer.model``) that the browser test does not reach."""

from __future__ import annotations

import datetime

from stages.viewer.model import WALL_CLOCK_FROM_NS, stamp_text


def test_a_stamp_reads_as_recording_time_or_as_the_utc_time_of_a_live_trackers_wall_clock():
    assert stamp_text(0) == "t = 0.0 s"
    assert stamp_text(12_345_000_000) == "t = 12.3 s"
    assert stamp_text(WALL_CLOCK_FROM_NS - 1).startswith("t = ")
    wall = 1_796_510_259_325_833_659
    when = datetime.datetime.fromtimestamp(wall // 10**9, datetime.timezone.utc)
    assert stamp_text(wall) == f"{when:%H:%M:%S}.3 UTC" == "22:37:39.3 UTC"


def _reference_place(labels, owners, boxes, probabilities):
    """``place_labels_off_boxes`` one spot, one box and one taken label at a time: the code before it was vectorised
    (at 72 vehicles with standing cars side by side a frame's labels took ~100 ms of the viewer's draw)."""
    import math

    import numpy as np

    from stages.viewer import model as m

    index = {int(t): i for i, t in enumerate(boxes.track_ids)}
    taken = [boxes.id_label_position(i)[:2] for i in range(len(boxes))]
    out = list(labels)
    order = sorted(range(len(labels)), key=lambda j: -probabilities[j] if math.isfinite(probabilities[j]) else math.inf)
    centres = boxes.centres_m[:, :2]
    reach = 0.5 * np.hypot(boxes.sizes_m[:, 0], boxes.sizes_m[:, 1])

    def free(spot, near):
        (x, y), (ax, ay) = spot
        ends = ((x, y), (x + m._LABEL_TEXT_M * ax, y + m._LABEL_TEXT_M * ay))
        return (not any(boxes.contains(int(k), xy, m.LABEL_CLEARANCE_M / 2.0) for k in near for xy in ends)
                and all(math.hypot(x - t[0], y - t[1]) >= m.LABEL_SPACING_M for t in taken))

    for j in order:
        lab, i = labels[j], index.get(int(owners[j]))
        if i is None or not boxes.contains(i, lab.position_m[:2], m.LABEL_CLEARANCE_M):
            continue
        spots = m.off_box_spots(boxes, i)
        far_m = max(math.hypot(xy[0] - centres[i, 0], xy[1] - centres[i, 1]) for xy, _a in spots) + m._LABEL_TEXT_M + m.LABEL_CLEARANCE_M
        near = np.nonzero(np.hypot(*(centres - centres[i]).T) <= far_m + reach)[0]
        (x, y), away = next((spot for spot in spots if free(spot, near)), spots[0])
        taken.append((x, y))
        out[j] = m.Label(lab.name, lab.text, (x, y, lab.position_m[2]), m._anchor_away(*away))
    return out


def test_labels_placed_off_the_boxes_at_once_as_one_at_a_time():
    """The vectorised placement puts every label where the one-at-a-time code did: 80 cars, many standing side by side
    and some on top of one another (as a superimposed dense recording has them), three corridors each."""
    import dataclasses

    import numpy as np

    from testkit import samples
    from stages.viewer.model import Label, object_boxes, place_labels_off_boxes

    rng = np.random.default_rng(7)
    n = 80
    x = np.concatenate([np.arange(40) * 5.5, rng.uniform(0, 200, n - 40)])  # a queue, then scattered
    y = np.concatenate([np.zeros(40), rng.uniform(-30, 30, n - 40)])
    x[60:70], y[60:70] = x[:10] + 0.3, y[:10]  # stacked on the queue's first cars
    frame = dataclasses.replace(samples.track_frame(n), track_ids=np.arange(100, 100 + n, dtype=np.int64), agent_types=np.ones(n, np.uint8),
                                x_m=x, y_m=y, vx_mps=np.zeros(n), vy_mps=np.zeros(n), yaw_rad=rng.uniform(-0.2, 0.2, n),
                                length_m=np.full(n, 4.5), width_m=np.full(n, 1.9))
    boxes = object_boxes(frame)
    labels, owners, probs = [], [], []
    for k in range(n):
        for c, p in enumerate((0.6, 0.3, 0.1)):
            labels.append(Label(f"/corridors/p/c{100 + k}_{c}", f"p={p:.2f}", (x[k] + rng.uniform(-1, 1), y[k], 0.5), "center"))
            owners.append(100 + k)
            probs.append(p)
    got = place_labels_off_boxes(labels, owners, boxes, probs)
    want = _reference_place(labels, owners, boxes, probs)
    assert sum(g.position_m != lab.position_m for g, lab in zip(got, labels)) > n  # most labels were on their boxes and moved
    assert got == want
