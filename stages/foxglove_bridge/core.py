"""The live Foxglove bridge's core: a ``foxglove-sdk`` WebSocket server fed by ``FoxgloveScene`` (package docstring)."""

from __future__ import annotations

import logging
import re
import threading
import time
from typing import Any, Mapping

import foxglove

from bus_schemas import CorridorPredictions, CorridorSet, IntentionBelief, MotionGrid, NodeStats, SceneInfo, TrackFrame
from stages.foxglove_bridge.config import FoxgloveConfig
from stages.foxglove_bridge.scene import FoxgloveScene, parse_grid_step
from stages.lib.base import Issue, StageResult

_LATEST = (("corridor_set", CorridorSet), ("corridor_predictions", CorridorPredictions), ("motion_grid", MotionGrid), ("intention_belief", IntentionBelief), ("compare_predictions", CorridorPredictions))


RELOG_AFTER_S = (0.0, 1.0, 3.0, 10.0, 30.0)
"""After a client subscribes to ``/map`` or ``/tf``, the map is logged at the first frame this long after, for each
value: at the next frame, then 1, 3, 10 and 30 s later (a loaded machine can take more than a second to register the
client's subscription; once in CI the client got no map at all with two tries, at 0 and 1 s, and once, in a suite
that ran a third slower than usual, none within 120 s with the tries up to 10 s)."""


class _Listener:
    """Asks for the map again when a client subscribes to it (the protocol has no latching).

    foxglove-sdk may call ``on_subscribe`` before the client's subscription takes messages (the callback runs
    before the client's sink is registered with the channel), so a map logged at once can be lost; it is logged at
    the next frame and again at each later time of ``RELOG_AFTER_S`` (``relog_due``)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._due: list[float] = []  # time.monotonic() at which to log the map again

    def on_subscribe(self, client: Any, channel: Any) -> None:
        if getattr(channel, "topic", "") in ("/map", "/tf"):
            now = time.monotonic()
            with self._lock:
                self._due += [now + after for after in RELOG_AFTER_S]

    def on_unsubscribe(self, client: Any, channel: Any) -> None:
        """Nothing to do (foxglove-sdk logs an error for a listener without it when a client leaves)."""

    def relog_due(self, now: float) -> bool:
        """True (once per due time, several due ones at once counting once) when the map should be logged again."""
        with self._lock:
            if not any(t <= now for t in self._due):
                return False
            self._due = [t for t in self._due if t > now]
            return True


class RepeatFilter(logging.Filter):
    """Collapses the SDK's repeated log lines (``foxglove.*`` loggers): a client that stopped reading and then left got
    one ERROR line per message still queued for it (127 in one second). The first line of a kind (logger, level, text
    with its numbers left out) passes; the same kind within ``window_s`` is counted, and the next one after it passes
    saying how many were held back. One record is decided once: on a root logger with several handlers (each with this
    filter) every handler gets the same answer (the second handler used to take the first one's pass for a repeat)."""

    def __init__(self, prefix: str = "foxglove", window_s: float = 10.0, clock=time.monotonic) -> None:
        super().__init__()
        self.prefix, self.window_s, self.clock = prefix, window_s, clock
        self._kinds: dict[tuple, list] = {}  # kind -> [time it last passed, held back since]

    def filter(self, record: logging.LogRecord) -> bool:
        if not record.name.startswith(self.prefix):
            return True
        decided = getattr(record, "_iamp_repeat_passes", None)
        if decided is not None:  # the same record at the next handler: the same answer (it counted once)
            return decided
        passes = self._decide(record)
        record._iamp_repeat_passes = passes
        return passes

    def _decide(self, record: logging.LogRecord) -> bool:
        kind = (record.name, record.levelno, re.sub(r"\d+", "#", str(record.msg)))
        now = self.clock()
        seen = self._kinds.get(kind)
        if seen is not None and now - seen[0] < self.window_s:
            seen[1] += 1
            return False
        held = seen[1] if seen is not None else 0
        if len(self._kinds) > 256:  # many kinds (a text with other changing parts): forget the old ones
            self._kinds.clear()
        self._kinds[kind] = [now, 0]
        if held:
            record.msg = f"{record.getMessage()} ({held} more like it in the {self.window_s:g} s before)"
            record.args = ()
        return True


SUBPROTOCOL = "foxglove.sdk.v1"
"""The WebSocket subprotocol foxglove-sdk's server accepts (0.30 also takes ``foxglove.sdk.v1.1``); the same messages as
the old ``foxglove.websocket.v1``, which it refuses."""

_HANDSHAKE_FAILED = re.compile(r"^Dropping client (\S+): handshake failed$")


def _sdk_version() -> str:
    try:
        from importlib.metadata import version

        return version("foxglove-sdk")
    except Exception:  # noqa: BLE001 - only for the text
        return "?"


class HandshakeRefusalNote(logging.Filter):
    """Says what a refused WebSocket handshake most likely means, in place of the SDK's bare line.

    foxglove-sdk answers a client that does not offer ``foxglove.sdk.v1`` (older Foxglove and Lichtblick releases offer
    only ``foxglove.websocket.v1``) with HTTP 400 "Missing expected sec-websocket-protocol header" and logs "Dropping
    client ADDR: handshake failed" (ERROR, ``foxglove.websocket.server``). It has no hook for the handshake: the
    response cannot be changed and the subprotocols the client offered are not told. This filter, on that logger,
    rewrites the line into one WARNING that names the client, the subprotocol this server speaks and what to upgrade;
    ``RepeatFilter`` then collapses a client's retries."""

    def __init__(self) -> None:
        super().__init__()
        self.sdk_version = _sdk_version()
        self.refused = 0

    def filter(self, record: logging.LogRecord) -> bool:
        m = _HANDSHAKE_FAILED.match(record.getMessage())
        if m is None:
            return True
        self.refused += 1
        record.msg = (f"foxglove: client {m.group(1)} refused at the WebSocket handshake (HTTP 400; foxglove-sdk {self.sdk_version} "
                      f"does not say why nor what the client offered): this server speaks the subprotocol {SUBPROTOCOL} only, "
                      f"so a client that offers only foxglove.websocket.v1 (an older Foxglove app or Lichtblick) must be upgraded "
                      f"(README, Foxglove: Foxglove app version needed); a request that is not a WebSocket upgrade is refused the same way")
        record.args = ()
        record.levelno, record.levelname = logging.WARNING, logging.getLevelName(logging.WARNING)
        return True


def install_handshake_note(logger_name: str = "foxglove.websocket.server") -> HandshakeRefusalNote:
    """A ``HandshakeRefusalNote`` on the SDK's server logger: once per process."""
    logger = logging.getLogger(logger_name)
    found = next((f for f in logger.filters if isinstance(f, HandshakeRefusalNote)), None)
    if found is not None:
        return found
    note = HandshakeRefusalNote()
    logger.addFilter(note)
    return note


def install_repeat_filter() -> RepeatFilter:
    """A ``RepeatFilter`` on every handler of the root logger (where the SDK's records end up): once per process."""
    for handler in logging.getLogger().handlers:
        found = next((f for f in handler.filters if isinstance(f, RepeatFilter)), None)
        if found is not None:
            return found
    flt = RepeatFilter()
    for handler in logging.getLogger().handlers:
        handler.addFilter(flt)
    return flt


class FoxgloveBridge:
    """Serves the run's scene on a Foxglove WebSocket; ``update`` logs what is new in one input set."""

    def __init__(self, config: FoxgloveConfig, *, run_id: str, node_id: str = "foxglove", log: logging.Logger | None = None, topic_keys: Mapping[str, str] | None = None) -> None:
        self.config = config
        self.run_id = run_id
        self.log = log or logging.getLogger(f"iamp.{node_id}")
        install_repeat_filter()
        self.handshake_note = install_handshake_note()
        self.context = foxglove.Context()
        self.scene = FoxgloveScene(self.context, data=config.data or None, grid_step=parse_grid_step(config.grid_step))
        self.topic_keys = dict(topic_keys or {})  # input port -> bus key (names the Foxglove topics by producing node)
        self._listener = _Listener()
        self._last: dict[str, int] = {}
        self._stats_seen: dict[str, float] = {}
        self.server: Any = None
        self.port = 0

    def start(self) -> str:
        """Start the server; returns its ``ws://`` URL."""
        self.scene.open_map_channels()
        kwargs = dict(name=f"hybrid-iamp {self.run_id}", host=self.config.host, context=self.context,
                      server_listener=self._listener, message_backlog_size=self.config.message_backlog)
        try:
            self.server = foxglove.start_server(port=self.config.port, **kwargs)
        except Exception as exc:  # noqa: BLE001 - a busy port moves to a free one
            if self.config.port == 0:
                raise
            self.log.warning("foxglove: port %d not available (%s); taking a free port", self.config.port, exc)
            self.server = foxglove.start_server(port=0, **kwargs)
        self.port = int(self.server.port)
        return f"ws://{self.config.host}:{self.port}"

    def close(self) -> None:
        if self.server is not None:
            self.server.stop()
            self.server = None
            logged = self.scene.counts.logged
            self.log.info("foxglove: logged /map %d times, /tf %d, %d messages in all on %d topics; %d not built, no client subscribed",
                          logged.get("/map", 0), logged.get("/tf", 0), sum(logged.values()), len(logged), self.scene.counts.unheard)

    def _key(self, port: str, default_node: str) -> str:
        return self.topic_keys.get(port, f"iamp/{self.run_id}/{default_node}/{port}")

    def update(self, inputs: Mapping[str, object]) -> StageResult:
        now = time.time_ns()
        frame = inputs.get("track_frame")
        if not isinstance(frame, TrackFrame):
            return StageResult(issues=[Issue("no_frame", -1, "input set without a track_frame")])
        scene = inputs.get("scene")
        if isinstance(scene, SceneInfo):
            self.scene.add_scene(scene, now)
        if self._listener.relog_due(time.monotonic()):
            self.scene.relog_map(now)
        self.scene.add_frame(frame, now)
        for port, cls in _LATEST:
            msg = inputs.get(port)
            if isinstance(msg, cls) and self._last.get(port) != msg.header.stamp_ns:
                self._last[port] = int(msg.header.stamp_ns)
                self.scene.add(self._key(port, port), msg, now)
        stats = inputs.get("stats")
        if isinstance(stats, Mapping):
            for msg in stats.values():
                if isinstance(msg, NodeStats) and self._stats_seen.get(msg.node_id) != msg.uptime_s:
                    self._stats_seen[msg.node_id] = msg.uptime_s
                    self.scene.add_stats(msg, now)
        return StageResult()
