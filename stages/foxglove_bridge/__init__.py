"""Foxglove: a live Foxglove WebSocket view of a run, and recordings exported into Foxglove's schemas.

The live sink stage (``python -m stages.foxglove_bridge``; ``launch.py
--foxglove`` adds it to any pipeline as node ``foxglove``) subscribes like
the viewer (``track_frame``, the latched ``scene``, and as latest-value
inputs ``corridor_set``, ``corridor_predictions``, ``motion_grid``,
``intention_belief``, plus every node's ``NodeStats`` through the wildcard
input ``stats``) and serves the scene over the Foxglove WebSocket protocol
(``foxglove-sdk``'s server; subprotocol ``foxglove.sdk.v1``, Foxglove's
current name of ``foxglove.websocket.v1``: the SDK refuses a client that offers only the old name with a bare HTTP
400 and has no hook for the handshake; ``core.HandshakeRefusalNote`` turns its "handshake failed" line into one
that says which subprotocol to use and what to upgrade) on ``host``
(127.0.0.1) and ``port`` (8765, Foxglove's default; a busy port moves to a
free one; 0: a free port). When up it logs one line ``foxglove:
ws://127.0.0.1:PORT`` (the launcher repeats it as ``[launch] foxglove: ...``);
open it in Foxglove with "Open connection" -> Foxglove WebSocket. It
produces nothing on the bus.

The topics and their schemas are those of ``scene.FoxgloveScene`` (``/map``,
``/tf``, ``/objects``, ``/<node>/corridors``, ``/<node>/means``,
``/<node>/motion_grid``, ``/<node>/vehicles``, ``/stats/<node>``); a
client that subscribes to ``/map`` or ``/tf`` gets the map again with the
next frame and again 1, 3, 10 and 30 s later (foxglove-sdk may call its
subscribe callback before the subscription takes messages). Each result is logged once, when a new stamp of it arrives.

``iamp export foxglove RUN.mcap OUT.mcap`` (``export.py``) writes the same
topics into an MCAP file from a recording; it reads recordings with the
recorder's reader (``stages.recorder.inspect``; mcap stays in the recorder
and replay) and writes with ``foxglove-sdk``'s own MCAP writer.

Parameters (``FoxgloveConfig``): ``host``, ``port``, ``data`` (the folder
whose ``maps/`` holds the scene's map; the launcher passes its ``--data``),
``grid_step`` (``max``: the maximum over the grid's steps, ``all``: one topic
per step, or a step time in seconds), ``message_backlog`` (messages buffered
per client before the oldest is dropped).
"""

from __future__ import annotations

from stages.foxglove_bridge.config import FoxgloveConfig

__all__ = ["INPUTS", "OUTPUTS", "SPEC", "FoxgloveConfig", "main"]

_BINDING = ("SPEC", "INPUTS", "OUTPUTS", "main", "make_core")


def __getattr__(name: str):
    """The binding lives in ``__main__.py`` (it imports the runtime): it loads only when asked."""
    if name in _BINDING:
        from stages.foxglove_bridge import __main__ as binding

        return getattr(binding, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
