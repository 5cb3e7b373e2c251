"""The live Foxglove bridge builds a message only for a channel somebody listens on.

Found by a new-user probe of a busy junction: with no Foxglove client connected, the live bridge turned every
frame's objects, corridors, means, grid and beliefs into Foxglove entities for nobody (a quarter of a core at 72
vehicles, on a 2-core machine whose prediction stages were already short of CPU). ``FoxgloveScene`` now builds a
message only where its channel has a sink: a client subscribed to it, or the MCAP file of ``iamp export foxglove``.
Real foxglove-sdk contexts: one with no sink, one with an MCAP writer, one with a WebSocket server and no client.
"""

from __future__ import annotations

import pytest

from testkit import samples

foxglove = pytest.importorskip("foxglove")
from stages.foxglove_bridge.scene import FoxgloveScene  # noqa: E402


def _feed(scene: FoxgloveScene) -> None:
    frame = samples.track_frame(3)
    scene.add("iamp/r/source/track_frame", frame, 1)
    scene.add("iamp/r/corridors/corridor_set", samples.corridor_set(), 2)
    scene.add("iamp/r/markov_prediction/corridor_predictions", samples.corridor_predictions(), 3)
    scene.add("iamp/r/markov_prediction/motion_grid", samples.motion_grid(), 4)
    scene.add("iamp/r/_stats/corridors", samples.node_stats(), 5)


def test_nobody_listening_nothing_built_and_a_file_gets_everything(tmp_path):
    idle = FoxgloveScene(foxglove.Context())
    _feed(idle)
    assert idle.counts.logged == {} and idle.counts.unheard >= 4
    server_context = foxglove.Context()
    server = foxglove.start_server(context=server_context, host="127.0.0.1", port=0)
    try:
        served = FoxgloveScene(server_context)
        _feed(served)
        assert served.counts.logged == {} and served.counts.unheard == idle.counts.unheard  # a server, but no client
    finally:
        server.stop()
    file_context = foxglove.Context()
    writer = foxglove.open_mcap(str(tmp_path / "x.mcap"), context=file_context)
    try:
        exported = FoxgloveScene(file_context)
        _feed(exported)
    finally:
        writer.close()
    assert exported.counts.unheard == 0
    assert {"/objects", "/markov_prediction/means", "/markov_prediction/motion_grid", "/stats/corridors"} <= set(exported.counts.logged)
    assert sum(exported.counts.logged.values()) >= idle.counts.unheard
