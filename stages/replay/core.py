"""The replay stage's core and binding (documented in ``stages/replay/__init__.py``)."""

from __future__ import annotations

import argparse
import collections
import itertools
import logging
import signal
import sys
import threading
import time
import traceback
from dataclasses import dataclass, field
from typing import Callable, Iterator

from bus_schemas import REGISTRY, SceneInfo, SchemaError, TrackFrame, keys, restamp_source_wall
from bus_schemas._wire import peek_schema

from stages.lib.base import ConfigError, ConfigMixin
from stages.recorder.inspect import ReadReport, RecordingError, read_messages, recording_run_id, summary_counts
from stages.runtime import (CLOSE_LINGER_S, EXIT_CRASH, EXIT_OK, EXIT_USAGE, BusClient, NodeContext, Port, StageSpec, StatsReporter, add_network_args,
                            on_stop_signals, setup_logging, start_stage)
from stages.runtime.args import concrete_listen
from stages.runtime.pacing import AWAIT_NODES_S, FIRST_ACK_GRACE_S, MAX_SPEED_WINDOW, Consumers, Pacer, parse_speed_value  # noqa: F401 (MAX_SPEED_WINDOW: for tests)

_MATCH_POLL_S = 0.01
_MATCH_LOOKAHEAD = 1000  # keys of the first this many messages are checked for a matching subscriber
# Stamps that nodes ack: those of messages with a header, except the latched scene (queried, never joined or acked).
_PACED_SCHEMAS = frozenset(
    name for name, cls in REGISTRY.items() if "header" in getattr(cls, "__dataclass_fields__", {}) and name != SceneInfo.SCHEMA
)


#: What replay counts in its ``NodeStats`` (``_stats/<node>``) besides the runtime's counters: ``processed`` and
#: ``published``, the messages replayed; ``skipped`` (and by reason: keys of another layout, infrastructure keys, keys of
#: nodes not selected); ``damaged_chunks``/``damaged_bytes``, the unreadable chunks passed over; ``truncated_file`` 1 once
#: the file ended before its footer.
SKIP_REASONS = ("foreign_key", "infrastructure", "other_node")
REPLAY_COUNTERS = ("skipped", *(f"skipped.{r}" for r in SKIP_REASONS), "damaged_chunks", "damaged_bytes", "truncated_file")


def sync_stats(stats: StatsReporter, player: "RecordingPlayer") -> None:
    """The player's skip and damage counters into the replay's ``NodeStats``."""
    for reason, n in player.skipped.items():
        stats.set(f"skipped.{reason}", n)
    stats.set("skipped", sum(player.skipped.values()))
    stats.set("damaged_chunks", player.report.damaged_chunks)
    stats.set("damaged_bytes", player.report.damaged_bytes)
    stats.set("truncated_file", int(player.report.truncated))


@dataclass(frozen=True, kw_only=True)
class ReplayConfig(ConfigMixin):
    """What to replay and how fast (see the module docstring)."""

    path: str = ""
    speed: float | str = 1.0
    run_id_from_file: bool = False
    include_infra: bool = False
    wait_for_subscribers_s: float = 10.0
    nodes: tuple[str, ...] = ()
    # the node whose MotionGrids the pipeline's viewer shows (replay.toml's GRIDS): a warning where the recording has
    # none of it but another node's (a sharded run's are grid_fusion's); "": no such check
    shown_grids: str = "markov_prediction"

    def __post_init__(self) -> None:
        if not self.path:
            raise ValueError("path is required: the MCAP file to replay")
        parse_speed_value(self.speed)  # raises ValueError
        if self.wait_for_subscribers_s < 0:
            raise ValueError(f"wait_for_subscribers_s must be >= 0, got {self.wait_for_subscribers_s}")
        for n in self.nodes:
            keys.check_name(n, "node id")


def parse_speed(text: str) -> float | str:
    """``max`` or a positive number, as given on a command line."""
    if text == "max":
        return "max"
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"speed must be a number > 0 or 'max', got {text!r}") from None
    if not value > 0:
        raise argparse.ArgumentTypeError(f"speed must be a number > 0 or 'max', got {text!r}")
    return value


@dataclass(frozen=True, slots=True)
class Outgoing:
    """One payload to publish: recorded receive time, key to publish on, bytes, and header stamp.

    ``stamp_ns`` is the header's ``stamp_ns`` (the recorder keeps it as the
    MCAP publish time) for messages whose stamp nodes ack (those with a
    header, except the latched ``SceneInfo``), else None.
    """

    log_time_ns: int
    key: str
    data: bytes
    stamp_ns: int | None = None
    schema: str = ""


class RecordingPlayer:
    """The recording as the sequence of payloads to publish, filtered and re-homed.

    ``run_id`` None keeps the recorded keys; otherwise every key is moved
    under ``run_id``. Keys that are not of the ``iamp/<run>/<node>/<output>``
    layout are skipped and counted, like infrastructure keys (unless
    ``include_infra``) and keys of nodes not in ``config.nodes``. After
    iterating, ``report`` says whether the file was truncated.
    """

    def __init__(self, config: ReplayConfig, run_id: str | None) -> None:
        self.config = config
        self.file_run_id = recording_run_id(config.path)  # raises RecordingError for a bad file
        self.run_id = keys.check_run_id(run_id) if run_id is not None else None
        self.report = ReadReport()
        self.skipped: collections.Counter[str] = collections.Counter()
        self.nodes_seen: set[str] = set()  # the node ids of the recording's data keys (what --node may name)

    @property
    def target_run_id(self) -> str | None:
        return self.run_id or self.file_run_id

    def __iter__(self) -> Iterator[Outgoing]:
        wanted = set(self.config.nodes)
        for msg in read_messages(self.config.path, self.report):
            try:
                parts = keys.parse_key(msg.topic)
            except keys.KeyFormatError:
                self.skipped["foreign_key"] += 1
                continue
            if parts.output == keys.ALIVE or (parts.is_infrastructure and not self.config.include_infra):
                self.skipped["infrastructure"] += 1
                continue
            self.nodes_seen.add(parts.node_id)
            if wanted and parts.node_id not in wanted:
                self.skipped["other_node"] += 1
                continue
            key = msg.topic if self.run_id is None else keys.replace_run(msg.topic, self.run_id)
            schema = msg.schema or _envelope_schema(msg.data)
            stamp = msg.publish_time_ns if schema in _PACED_SCHEMAS else None
            yield Outgoing(msg.log_time_ns, key, msg.data, stamp, schema)


def _envelope_schema(data: bytes) -> str:
    """The schema a payload's envelope names ('' if it is none of ours).

    A channel without an MCAP schema holds payloads of an older version this
    build reads (the recorder describes only the current one) or payloads it
    could not read: for the former, pacing and the scene's latching go by the
    envelope, as for a current recording (before, such a file went out unpaced
    and its scene unlatched, and a stage that missed the scene's one put lost
    the frames beyond its join window).
    """
    try:
        name, _version = peek_schema(data)
    except SchemaError:
        return ""
    return name if name in REGISTRY else ""


class WallRestamper:
    """Recorded ``Header.source_wall_ns`` values mapped to the replay's own wall clock.

    A recorded wall stamp is the recorded run's source publish time: replayed
    as it is, every end-to-end figure would be the recording's age. The first
    payload met with a given recorded stamp (the source frame, published
    first) gets the wall clock now; every later payload of that stamp (the
    stages' recorded outputs of that frame) the same value, so the replayed
    outputs keep their recorded delay behind their frame. Payloads with no
    wall stamp (recordings older than the field) go out unchanged: unknown.
    """

    def __init__(self, keep: int = 4096) -> None:
        self._map: "collections.OrderedDict[int, int]" = collections.OrderedDict()
        self._keep = keep

    def __call__(self, data: bytes, key: str = "") -> bytes:
        try:
            return restamp_source_wall(data, self._wall_for, where=key)
        except Exception:  # noqa: BLE001 - a payload the stages will reject anyway goes out as recorded
            return data

    def _wall_for(self, recorded: int) -> int:
        new = self._map.get(recorded)
        if new is None:
            new = self._map[recorded] = time.time_ns()
            while len(self._map) > self._keep:
                self._map.popitem(last=False)
        return new


@dataclass(slots=True)
class ReplaySummary:
    published: int = 0
    keys: int = 0
    duration_s: float = 0.0
    matched: bool = False
    stopped: bool = False
    truncated: bool = False
    skipped: dict[str, int] = field(default_factory=dict)

    def line(self) -> str:
        skipped = ",".join(f"{k}:{v}" for k, v in sorted(self.skipped.items())) or "0"
        return (
            f"messages={self.published} keys={self.keys} duration_s={self.duration_s:.3f} "
            f"skipped={skipped} truncated_file={str(self.truncated).lower()}"
        )


def watch_consumers(bus: BusClient, run_id: str, node_id: str, *, acks: bool) -> Consumers:
    """The run's live nodes (and, with ``acks``, their ``Progress``) as the runtime's sources follow them, on ``bus``."""
    consumers = Consumers(node_id)
    if acks:
        bus.subscribe(keys.ack_pattern(run_id), lambda _key, data: consumers.on_ack_payload(data))
    bus.watch_alive(keys.alive_pattern(run_id), consumers.on_alive)
    # the watcher's history may come late; a query tells who is alive now
    consumers.add_alive(bus.alive_now(keys.alive_pattern(run_id), timeout_s=2.0))
    return consumers


def play(
    player: RecordingPlayer,
    bus: BusClient,
    *,
    speed: float | str,
    wait_for_subscribers_s: float,
    stop: threading.Event,
    log: logging.Logger,
    node_id: str = "replay",
    consumers: Consumers | None = None,
    expected: tuple[str, ...] = (),
    stats: StatsReporter | None = None,
) -> ReplaySummary:
    """Publish the player's messages on ``bus``, paced by ``speed``; stops early when ``stop`` is set.

    First it declares publishers for the keys among the first
    ``_MATCH_LOOKAHEAD`` messages and waits until a subscriber matches any of
    them (at most ``wait_for_subscribers_s``, then it warns and goes on).
    Pacing is the runtime's (``stages.runtime.pacing.Pacer``) on the
    recorded receive times, or at ``max`` on the acks of ``consumers``
    (followed here on the target run when None), with a grace of
    ``FIRST_ACK_GRACE_S`` for nodes that never ack (tools), except the
    ``expected`` ones (the awaited pipeline nodes), waited for as long as
    one behind. ``stats``, when given, counts every message published, and
    at the end the player's skipped and damaged counters (the replay's
    ``NodeStats``; ``run_replay``'s reporter copies them in before each of
    its messages too).
    """
    summary = ReplaySummary()
    publishers: dict[str, Callable[[bytes], None]] = {}
    latched: dict[str, bytes] = {}
    items = iter(player)
    head = list(itertools.islice(items, _MATCH_LOOKAHEAD))
    t_start = time.monotonic()
    if head:
        as_fast = speed == "max"
        if as_fast and player.target_run_id:
            consumers = consumers or watch_consumers(bus, player.target_run_id, node_id, acks=True)
        else:
            consumers = None  # a fixed speed, or keys of no run: nobody to wait for
        pacer = Pacer(speed, consumers, stop, log, first_ack_grace_s=FIRST_ACK_GRACE_S, expected=expected)
        matchers = []
        for item in head:
            if item.key not in publishers:
                publishers[item.key], matching = bus.publisher_with_matching(item.key)
                matchers.append(matching)
        deadline = time.monotonic() + wait_for_subscribers_s
        while not any(m() for m in matchers) and not stop.is_set() and time.monotonic() < deadline:
            stop.wait(_MATCH_POLL_S)
        summary.matched = any(m() for m in matchers)
        if not summary.matched and not stop.is_set():
            log.warning("no subscriber after %.1f s, publishing anyway: keys=%s", wait_for_subscribers_s, ",".join(sorted(publishers)))
        t_start = time.monotonic()
        walls = WallRestamper()
        for msg in itertools.chain(head, items):
            if not pacer.before(msg.log_time_ns, msg.stamp_ns):
                break
            t0 = time.perf_counter()
            pub = publishers.get(msg.key)
            if pub is None:
                pub = publishers[msg.key] = bus.publisher(msg.key, block=True)
            if msg.schema == SceneInfo.SCHEMA:
                # latched, as the source's scene port: a stage that (re)starts late queries it
                if msg.key not in latched:
                    bus.declare_queryable(msg.key, lambda k=msg.key: latched.get(k))
                latched[msg.key] = walls(msg.data, msg.key)
                pub(latched[msg.key])
            else:
                pub(walls(msg.data, msg.key))
            summary.published += 1
            if stats is not None:
                stats.processed((time.perf_counter() - t0) * 1e3, msg.stamp_ns)
        if as_fast and not stop.is_set():
            pacer.drain(abort=stop.is_set)
    summary.stopped = stop.is_set()
    summary.duration_s = time.monotonic() - t_start
    summary.keys = len(publishers)
    summary.truncated = player.report.truncated
    summary.skipped = dict(player.skipped)
    if stats is not None:
        sync_stats(stats, player)
    return summary


def run_replay(
    config: ReplayConfig,
    *,
    run_id: str | None,
    node_id: str = "replay",
    fallback_run_id: str = "demo",
    mode: str = "peer",
    connect: list[str] | tuple[str, ...] = (),
    listen: list[str] | tuple[str, ...] = (),
    config_file: str | None = None,
    log: logging.Logger | None = None,
    await_nodes: tuple[str, ...] = (),
    stats_period_s: float = 1.0,
) -> int:
    """Open a session, hold a liveliness token, replay, log a summary; returns the exit code.

    ``run_id`` None keeps the recorded run id (the token then lives under it,
    or under ``fallback_run_id`` for a recording without one). Like every
    node, replay publishes its ``NodeStats`` on ``_stats/<node>`` there, every
    ``stats_period_s`` and once more at the end (``REPLAY_COUNTERS``). A
    session that cannot join the bus (nothing listens at ``--connect``, or a
    router refused its credentials) is exit 2 with one line that says why.
    """
    log = log or logging.getLogger(f"iamp.{node_id}")
    try:
        keys.check_name(node_id, "node id")
        player = RecordingPlayer(config, run_id)
    except (RecordingError, ValueError) as exc:
        log.error("bad configuration: %s", exc)
        return EXIT_USAGE
    stop = threading.Event()

    def on_signal(signum: int) -> None:
        if not stop.is_set():
            log.info("stop requested: signal=%s", signal.Signals(signum).name)
        stop.set()

    on_stop_signals(on_signal)
    token_run = player.target_run_id or fallback_run_id
    try:
        listen = concrete_listen(listen)  # a port 0 made concrete: the log line names what a reader connects to
        with BusClient(mode, connect, listen, config_file) as bus:
            bus.declare_token(keys.alive_key(token_run, node_id))
            stats = StatsReporter(bus.publisher(keys.stats_key(token_run, node_id), block=True), token_run, node_id, SPEC.stage,
                                  period_s=stats_period_s, counters=REPLAY_COUNTERS, refresh=lambda: sync_stats(stats, player)).start()
            try:
                return _replay_on(bus, player, config, stats, token_run=token_run, node_id=node_id, stop=stop, log=log, await_nodes=await_nodes,
                                  listening=listen)
            finally:
                stats.close()
                time.sleep(CLOSE_LINGER_S)  # zenoh has no flush: let the last NodeStats leave before the session closes
    except ConfigError as exc:  # the session: nothing listens at --connect, a router refused it, a bad endpoint or --config
        log.error("bad configuration: %s", exc)
        return EXIT_USAGE
    except Exception:
        log.error("crashed:\n%s", traceback.format_exc().rstrip())
        return EXIT_CRASH


def _say_whose_grids(path: str, shown: str, log: logging.Logger) -> None:
    """One warning where the recording has MotionGrids, but none of node ``shown``, the one the pipeline's viewer shows
    (a sharded run's are grid_fusion's and its shards': the replay pipeline's viewer showed nothing without a word;
    ``--var GRIDS=`` tells it). From the file's summary section (nothing said for a file without one)."""
    counts = summary_counts(path)
    nodes = set()
    for topic in (counts or {}).get("per_topic", {}):
        try:
            parts = keys.parse_key(topic)
        except keys.KeyFormatError:
            continue
        if parts.output == "motion_grid":
            nodes.add(parts.node_id)
    if nodes and shown not in nodes:
        use = "grid_fusion" if "grid_fusion" in nodes else sorted(nodes)[0]
        log.warning("the recording's MotionGrids come from node(s) %s, not %s%s: the viewer shows none; to show them: "
                    "launch.py replay --var FILE=%s --var GRIDS=%s", ", ".join(sorted(nodes)), shown,
                    " (a sharded run: grid_fusion fuses the shards)" if "grid_fusion" in nodes else "", path, use)


def _replay_on(
    bus: BusClient,
    player: RecordingPlayer,
    config: ReplayConfig,
    stats: StatsReporter,
    *,
    token_run: str,
    node_id: str,
    stop: threading.Event,
    log: logging.Logger,
    await_nodes: tuple[str, ...],
    listening: list[str] | tuple[str, ...] = (),
) -> int:
    """``run_replay`` once its session is open: wait for the awaited nodes, replay, log the summary."""
    consumers = None
    if config.shown_grids:
        _say_whose_grids(config.path, config.shown_grids, log)
    if await_nodes or (config.speed == "max" and player.target_run_id):
        consumers = watch_consumers(bus, token_run, node_id, acks=config.speed == "max" and bool(player.target_run_id))
    if await_nodes:
        # as the runtime's sources: publish only once the consumers' subscriptions are visible
        consumers.await_nodes(await_nodes, AWAIT_NODES_S, stop, log)
    log.info(
        "replay up: path=%s speed=%s run=%s recorded_run=%s listening=%s",
        config.path,
        config.speed,
        player.run_id or "(as recorded)",
        player.file_run_id or "-",
        ",".join(listening) or "-",  # with --listen ...:0 the port it got: what a reader connects to
    )
    summary = play(
        player,
        bus,
        speed=config.speed,
        wait_for_subscribers_s=config.wait_for_subscribers_s,
        stop=stop,
        log=log,
        node_id=node_id,
        consumers=consumers,
        expected=await_nodes,
        stats=stats,
    )
    if player.report.truncated:
        log.warning("recording truncated, replayed up to its last complete chunk: path=%s detail=%s", config.path, player.report.error)
    if player.report.damaged_chunks:
        log.warning(
            "recording damaged, unreadable chunks skipped (their messages not replayed): path=%s damaged_chunks=%d damaged_bytes=%d detail=%s",
            config.path,
            player.report.damaged_chunks,
            player.report.damaged_bytes,
            player.report.damage,
        )
    log.info("replay %s: %s", "stopped" if summary.stopped else "finished", summary.line())
    unknown = sorted(set(config.nodes) - player.nodes_seen)
    if unknown:
        log.warning("--node names nodes the recording does not have: %s; its nodes: %s", ",".join(unknown), ",".join(sorted(player.nodes_seen)) or "none")
    if not summary.published and not summary.stopped:
        why = ("no key of the iamp/<run>/<node>/<output> layout: not a hybrid-iamp recording" if player.skipped.get("foreign_key") and not player.nodes_seen
               else "--node selects none of its nodes" if player.skipped.get("other_node") else "it holds no data message")
        log.error("nothing replayed from %s: %s (skipped: %s)", config.path, why, ",".join(f"{k}:{v}" for k, v in sorted(player.skipped.items())) or "nothing")
        return EXIT_USAGE
    return EXIT_OK


# --------------------------------------------------------------------------- binding


class _NotAStageCore:
    """Replay publishes on recorded keys, not on ports, so ``run_stage`` cannot drive it; ``main`` does."""

    def __init__(self, config: ReplayConfig, ctx: NodeContext) -> None:
        self.player = RecordingPlayer(config, None if config.run_id_from_file else ctx.run_id)

    def __iter__(self):
        raise RuntimeError("stages.replay runs through its own main(), not runtime.run_stage")


def preflight(config: ReplayConfig) -> None:
    """The launcher's check before any node starts (``StageSpec.preflight``): the file is there and is a recording."""
    try:
        recording_run_id(config.path)
    except RecordingError as exc:
        raise ConfigError(f"path: {exc}") from None


SPEC = StageSpec(
    stage="stages.replay",
    config_cls=ReplayConfig,
    make_core=_NotAStageCore,
    inputs={},
    # what a replayed tracks source publishes, so that pipelines can bind to "<replay node>/track_frame"
    outputs={"track_frame": Port(TrackFrame), "scene": Port(SceneInfo, latched=True)},
    kind="source",
    restart_default=False,
    preflight=preflight,
)


def main(argv: list[str] | None = None) -> int:
    """``python -m stages.replay --params-json '{"path": ...}'``: what the launcher spawns."""
    start = start_stage(SPEC, argv, bindings=False)  # the start-up of every stage (flags, parameters, logging)
    if isinstance(start, int):
        return start
    args, config, log = start.args, start.config, start.log
    return run_replay(
        config,
        run_id=None if config.run_id_from_file else args.run_id,
        node_id=args.node_id,
        fallback_run_id=args.run_id,
        mode=args.mode,
        connect=args.connect,
        listen=args.listen,
        config_file=args.config,
        log=log,
        await_nodes=tuple(n for n in args.await_nodes.split(",") if n),
        stats_period_s=args.stats_period,
    )


def add_cli_arguments(parser: argparse.ArgumentParser) -> None:
    """Flags of ``iamp replay``."""
    parser.add_argument("file", metavar="FILE.mcap", help="recording to replay")
    parser.add_argument("--speed", type=parse_speed, default=1.0, help="time scale (2 = twice as fast) or 'max' (default 1)")
    parser.add_argument("--run-id", default=None, help="publish under this run id (default: the recorded run id)")
    parser.add_argument("--node-id", default="replay", help="node id of the liveliness token (default replay)")
    parser.add_argument("--node", action="append", default=[], metavar="NODE", help="replay only the keys of this recorded node (repeatable)")
    parser.add_argument("--include-infra", action="store_true", help="also replay _stats/_ack keys")
    parser.add_argument("--wait-for-subscribers-s", type=float, default=10.0, help="wait this long for a subscriber first (default 10)")
    parser.add_argument("--log-level", default="INFO")
    add_network_args(parser)


def run_cli(args: argparse.Namespace) -> int:
    """``iamp replay`` on parsed arguments."""
    setup_logging(args.log_level, args.node_id)
    log = logging.getLogger(f"iamp.{args.node_id}")
    try:
        config = ReplayConfig(
            path=args.file,
            speed=args.speed,
            run_id_from_file=args.run_id is None,
            include_infra=args.include_infra,
            wait_for_subscribers_s=args.wait_for_subscribers_s,
            nodes=tuple(args.node),
            shown_grids="",  # (no viewer of its own: whose grids a reader takes is the reader's)
        )
    except ValueError as exc:
        log.error("bad configuration: %s", exc)
        return EXIT_USAGE
    return run_replay(
        config,
        run_id=args.run_id,
        node_id=args.node_id,
        mode=args.mode,
        connect=args.connect,
        listen=args.listen,
        config_file=args.config,
        log=log,
    )


if __name__ == "__main__":
    sys.exit(main())
