"""The viewer draws for a browser, not for nobody: with no page connected it keeps the scene on the server at most
``idle_render_hz`` times a second; a page that connects gets the newest set drawn at once, and ``max_render_hz``
while it stays.

Found by a new-user probe: at 72 vehicles the render thread drew 10 times a second with no browser open, a third
of a core, and on 2 cores the prediction stages lost half their frames to it. The viewer runs in-process with its
viser server on 127.0.0.1; the page is a real websocket client offering viser's subprotocol, as the page does.
"""

from __future__ import annotations

import dataclasses
import logging
import time

import msgpack
import pytest

from testkit.helpers import free_port, wait_until

viser = pytest.importorskip("viser")
from websockets.sync.client import connect  # noqa: E402

from stages.viewer.config import ViewerConfig  # noqa: E402
from stages.viewer.scene import ViewerApp  # noqa: E402
from test_viewer_labels import inputs  # noqa: E402

#: how long a set stays undrawn to count as "not drawn": at max_render_hz (10) it would be drawn within 0.1 s
UNDRAWN_S = 1.0
#: what a page sends first, its camera: viser counts a client as connected from its first camera message
CAMERA = {"type": "ViewerCameraMessage", "wxyz": [1.0, 0.0, 0.0, 0.0], "position": [0.0, 0.0, 100.0], "fov": 0.9, "near": 0.1,
          "far": 1000.0, "image_height": 600, "image_width": 800, "look_at": [0.0, 0.0, 0.0], "up_direction": [0.0, 0.0, 1.0]}


def at_frame(k: int) -> dict:
    """The labels test's input set as frame ``k`` (each message's header moved there)."""
    out = {}
    for key, msg in inputs().items():
        h = msg.header
        out[key] = dataclasses.replace(msg, header=dataclasses.replace(h, frame_index=k, stamp_ns=h.stamp_ns + (k - h.frame_index) * 100_000_000))
    return out


def drawn_frame(app: ViewerApp) -> int | None:
    return app.summary.get("frame") if app.summary else None


@pytest.fixture
def app():
    a = ViewerApp(ViewerConfig(port=free_port(), stats=False, max_render_hz=10.0, idle_render_hz=0.05),
                  run_id="idle", log=logging.getLogger("iamp.viewer"))
    a.start()
    try:
        yield a
    finally:
        a.close()


def test_no_browser_no_drawing_at_full_rate_and_a_page_gets_the_newest_at_once(app):
    port = app.server.get_port()
    app.update(at_frame(10))
    app.wait_drawn(lambda s: s.get("frame") == 10, 30)  # the first set is drawn (the scene a page will get)
    app.update(at_frame(11))
    time.sleep(UNDRAWN_S)
    assert drawn_frame(app) == 10, "drawn at full rate with no browser connected"
    headers = {"Origin": f"http://127.0.0.1:{port}"}
    with connect(f"ws://127.0.0.1:{port}/", additional_headers=headers, subprotocols=[f"viser-v{viser.__version__}"], open_timeout=20) as ws:
        ws.recv(timeout=20)
        ws.send(msgpack.packb(CAMERA))
        app.wait_drawn(lambda s: s.get("frame") == 11, 10)  # the page connects: the newest set at once, not in 20 s
        app.update(at_frame(12))
        app.wait_drawn(lambda s: s.get("frame") == 12, 10)  # and max_render_hz while it is there
    wait_until(lambda: not app.server.get_clients(), 20, "the page's disconnect")
    app.update(at_frame(13))
    time.sleep(UNDRAWN_S)
    assert drawn_frame(app) == 12, "drawn at full rate after the page left"
    assert app.counters.drawn == 3
