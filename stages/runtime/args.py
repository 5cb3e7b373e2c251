"""The command line of a stage and its Zenoh session: flags, parameters, input bindings, logging, start-up.

Every stage takes the same flags (``build_parser``): ``--node-id``,
``--run-id``, ``--params-json``/``--set`` (parameters), ``--inputs-json``/
``--input`` (bindings ``port -> node/output``), the queue and stamp-window
bounds, ``--stats-period``, ``--log-level``, ``--await-nodes`` and the
network flags (``add_network_args``: ``--mode/--connect/--listen/--config``).
Sessions are peers on ``tcp/127.0.0.1`` with multicast scouting off and
explicit endpoints (``make_zenoh_config``). ``start_stage`` is the start-up
every stage binding shares (``run_stage`` and replay's ``main``): parse the
command line, set up logging, check the ids, build the config; exit code 2
for a bad command line or config.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import re
import signal
import socket
import sys
import threading
import time
from dataclasses import dataclass
from typing import Any, Callable, Iterable, Mapping

import zenoh

from bus_schemas import keys

from stages.lib.base import ConfigError
from stages.runtime.ports import MAX_NICE, StageSpec

EXIT_OK = 0
EXIT_CRASH = 1
EXIT_USAGE = 2

DEFAULT_LISTEN = "tcp/127.0.0.1:0"


LOG_LEVELS = ("DEBUG", "INFO", "WARNING", "ERROR", "CRITICAL")


def check_runtime_args(args: argparse.Namespace) -> None:
    """The runtime's numeric flags within their ranges (``ConfigError`` naming the flag): a queue of at least one message
    and a positive payload bound, a positive stamp window and NodeStats period (0 would publish stats on every loop)."""
    if args.queue_size < 1:
        raise ConfigError(f"--queue-size {args.queue_size}: must be >= 1")
    max_age = getattr(args, "max_age_s", 0.0)
    if not (math.isfinite(max_age) and max_age >= 0):
        raise ConfigError(f"--max-age-s {max_age}: must be a finite number >= 0 (0: inputs are not bounded in age)")
    for flag, value in (("--queue-mib", args.queue_mib), ("--stamp-window-s", args.stamp_window_s), ("--stats-period", args.stats_period)):
        if not (math.isfinite(value) and value > 0):
            raise ConfigError(f"{flag} {value}: must be a finite number > 0")
    nice = getattr(args, "nice", 0)
    if not 0 <= nice <= MAX_NICE:
        raise ConfigError(f"--nice {nice}: must be 0 (as started) to {MAX_NICE} (the lowest priority)")


#: set by the launcher in each node's environment: its own pid (``watch_launcher``)
LAUNCHER_PID_ENV = "IAMP_LAUNCHER_PID"
#: how often a launched node looks whether its launcher is still there (s)
LAUNCHER_WATCH_S = 0.5


def watch_launcher(log: logging.Logger, environ: Mapping[str, str] | None = None, interval_s: float = LAUNCHER_WATCH_S) -> threading.Thread | None:
    """A node the launcher started (``IAMP_LAUNCHER_PID`` in its environment) stops when the launcher is gone: killed
    hard (SIGKILL, a crash, an OOM kill), it can stop nothing, and its nodes went on running, recording and holding
    their ports with nobody to read their logs. Once the node's parent is no longer that pid it logs one line and
    sends itself SIGTERM, so it stops as on Ctrl-C (a recorder finishes its file). A node started by hand (no such
    variable) is left alone. Returns the watching thread (None where there is nothing to watch)."""
    value = (os.environ if environ is None else environ).get(LAUNCHER_PID_ENV, "")
    if not value:
        return None
    try:
        launcher = int(value)
    except ValueError:
        log.warning("%s=%r is no process id: this node does not watch for its launcher", LAUNCHER_PID_ENV, value)
        return None

    def watch() -> None:
        while os.getppid() == launcher:
            time.sleep(interval_s)
        log.warning("the launcher (pid %d) is gone: stopping (the nodes of a run do not outlive their launcher)", launcher)
        os.kill(os.getpid(), signal.SIGTERM)

    thread = threading.Thread(target=watch, name="launcher-watch", daemon=True)
    thread.start()
    return thread


def apply_nice(n: int, log: logging.Logger) -> None:
    """Lower this process's CPU priority by ``n`` (before any thread starts: the threads take it over); a platform
    without ``os.nice`` says so once and runs as it is."""
    if n <= 0:
        return
    try:
        os.nice(n)
    except (AttributeError, OSError) as exc:
        log.warning("--nice %d not applied (%s): the node runs at its start priority", n, exc)


def add_network_args(parser: argparse.ArgumentParser) -> None:
    """The zenoh-python network flags, shared by stages and tools."""
    g = parser.add_argument_group("network")
    g.add_argument("--mode", choices=["peer", "client"], default="peer", help="zenoh mode (default peer)")
    g.add_argument("--connect", action="append", default=[], metavar="ENDPOINT", help="endpoint to connect to, e.g. tcp/127.0.0.1:7447")
    g.add_argument("--listen", action="append", default=[], metavar="ENDPOINT", help=f"endpoint to listen on (default {DEFAULT_LISTEN})")
    g.add_argument("--config", metavar="FILE", help="zenoh JSON5 config file; the flags above override it")


# where in zenoh's Rust source an error was raised (" at /root/.cargo/git/checkouts/zenoh-.../orchestrator.rs:447."): of no
# use to whoever reads the line
_RUST_SOURCE_RE = re.compile(r"\s+at\s+\S+\.rs:\d+(?::\d+)?\.?")


def _zenoh_reason(exc: BaseException) -> str:
    """The first line of a zenoh error, without the Rust source paths zenoh appends, short enough for a log line."""
    text = _RUST_SOURCE_RE.sub("", str(exc)).strip()
    return (text.splitlines()[0] if text else type(exc).__name__)[:300]


def endpoint_address(endpoint: str) -> tuple[str, str, int] | None:
    """(protocol, host, port) of a zenoh endpoint such as ``tcp/127.0.0.1:7447`` or ``tcp/[::1]:7447`` (its ``?``
    parameters and ``#`` configuration left out); None for one that is not ``<protocol>/<host>:<port>``."""
    base = endpoint.split("#", 1)[0].split("?", 1)[0]
    proto, sep, addr = base.partition("/")
    host, colon, port = addr.rpartition(":")
    if not sep or not colon or not host or not port.isdigit():
        return None
    return proto, host[1:-1] if host.startswith("[") and host.endswith("]") else host, int(port)


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port free on ``host`` now (the OS's pick; another process may take it before it is used)."""
    with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return s.getsockname()[1]


def concrete_listen(endpoints: Iterable[str]) -> list[str]:
    """``endpoints`` with each ``tcp/HOST:0`` given a free port of HOST: zenoh would pick one too, but this zenoh cannot
    tell which, and whoever connects needs it (the launcher's hub; ``iamp replay --listen tcp/127.0.0.1:0``)."""
    out = []
    for ep in endpoints:
        address = endpoint_address(ep)
        if address is not None and address[0] == "tcp" and address[2] == 0:
            host = address[1]
            ep = f"tcp/{'[' + host + ']' if ':' in host else host}:{free_port(host)}" + ep[len(ep.split("#", 1)[0].split("?", 1)[0]):]
        out.append(ep)
    return out


def _tcp_listening(endpoint: str, timeout_s: float = 1.0) -> bool | None:
    """Whether something accepts TCP connections at a ``tcp/`` endpoint (None: another protocol, cannot tell)."""
    address = endpoint_address(endpoint)
    if address is None or address[0] != "tcp":
        return None
    try:
        with socket.create_connection(address[1:], timeout=timeout_s):
            return True
    except OSError:
        return False


def _config_user(conf: zenoh.Config) -> str | None:
    """The user of the config's ``transport/auth/usrpwd`` when it has a user and a password, else None."""
    try:
        user = json.loads(conf.get_json("transport/auth/usrpwd/user"))
        password = json.loads(conf.get_json("transport/auth/usrpwd/password"))
    except Exception:  # noqa: BLE001 - a zenoh build without the key: no credentials known
        return None
    return user if isinstance(user, str) and user and password else None


USRPWD_HINT = '{transport: {auth: {usrpwd: {user: "...", password: "..."}}}}'


def refusal_reason(connect: list[str], conf: zenoh.Config, config_file: str | None) -> str:
    """One line for a client session that got a link to none of its ``--connect`` endpoints (zenoh says only "Unable to
    connect to any of [...]", the same for both causes): nothing listens there, or the router there refused this
    session, which with bus auth (``[bus.auth]``) means wrong or missing credentials; what to fix in either case."""
    probed = {ep: _tcp_listening(ep) for ep in connect}
    up = [ep for ep, listening in probed.items() if listening]
    if not up and all(listening is False for listening in probed.values()):
        return (f"cannot join the bus: nothing listens at --connect {' '.join(connect)}: start the launcher or router there first,"
                " or fix the address")
    where = f"--connect {' '.join(up)}" if up else f"--connect {' '.join(connect)}"
    what = "refused this session" if up else "refused this session (or nothing listens there)"
    user = _config_user(conf)
    if config_file and user:
        fix = (f"the user/password in --config {config_file} (transport/auth/usrpwd, user {user!r}) are not accepted there:"
               " use the run's [bus.auth] user and password (a router without auth refuses a session with credentials too)")
    elif config_file:
        fix = (f"--config {config_file} has no transport/auth/usrpwd user and password: add the run's [bus.auth] user and"
               f" password ({USRPWD_HINT})")
    else:
        fix = (f"this session has no credentials: give --config FILE, a 0600 JSON5 file {USRPWD_HINT} with the run's [bus.auth]"
               " user and password")
    return f"cannot join the bus: the router at {where} {what}: {fix if up else 'if it asks for credentials, ' + fix}"


def make_zenoh_config(mode: str = "peer", connect: Iterable[str] = (), listen: Iterable[str] = (), config_file: str | None = None) -> zenoh.Config:
    """The session's configuration; ``ConfigError`` for a ``--config`` file that is missing or that zenoh cannot read."""
    if config_file:
        try:
            conf = zenoh.Config.from_file(config_file)
        except Exception as exc:  # zenoh.ZError for a missing file, bad JSON5 or TOML, unknown keys or values
            raise ConfigError(f"--config {config_file}: not a zenoh configuration zenoh can read: {_zenoh_reason(exc)}") from None
    else:
        conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(mode))
    conf.insert_json5("scouting/multicast/enabled", "false")
    connect = list(connect)
    listen = list(listen) or ([DEFAULT_LISTEN] if mode == "peer" else [])
    for flag, endpoints in (("--connect", connect), ("--listen", listen)):
        if not endpoints:
            continue
        try:
            conf.insert_json5(f"{flag[2:]}/endpoints", json.dumps(endpoints))
        except Exception as exc:  # zenoh.ZError: an endpoint zenoh cannot parse
            raise ConfigError(f"{flag} {' '.join(endpoints)}: not a zenoh endpoint (expected <protocol>/<address>:<port>, e.g."
                              f" tcp/127.0.0.1:7447): {_zenoh_reason(exc)}") from None
    return conf


def open_session(mode: str = "peer", connect: Iterable[str] = (), listen: Iterable[str] = (), config_file: str | None = None) -> zenoh.Session:
    """Open a zenoh session with the project's defaults (loopback, no multicast); ``ConfigError`` where zenoh refuses
    the configuration or an endpoint (a bad ``--connect``/``--listen``, a port in use)."""
    connect, listen = list(connect), list(listen)
    conf = make_zenoh_config(mode, connect, listen, config_file)
    try:
        return zenoh.open(conf)
    except Exception as exc:  # zenoh.ZError: bad endpoint, address in use, ...
        if mode == "client" and connect and "connect" in str(exc).lower():  # "Unable to connect to any of [...]"
            raise ConfigError(refusal_reason(connect, conf, config_file)) from None
        raise ConfigError(f"cannot open the zenoh session (mode {mode}, listen {list(listen) or 'default'}, connect {list(connect) or 'none'}): "
                          f"{_zenoh_reason(exc)}") from None


def session_from_args(args: argparse.Namespace) -> zenoh.Session:
    return open_session(args.mode, args.connect, args.listen, args.config)


def parse_set(items: list[str]) -> dict[str, Any]:
    import tomllib

    out: dict[str, Any] = {}
    for item in items:
        if "=" not in item:
            raise ConfigError(f"--set {item!r}: expected key=value")
        k, v = item.split("=", 1)
        try:
            out[k.strip()] = tomllib.loads(f"x = {v}")["x"]
        except tomllib.TOMLDecodeError:
            out[k.strip()] = v
    return out


def build_parser(spec: StageSpec) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=f"python -m {spec.stage}", description=(sys.modules[spec.stage].__doc__ or "").split("\n")[0] if spec.stage in sys.modules else None)
    default_id = spec.stage.rsplit(".", 1)[-1]
    p.add_argument("--node-id", default=default_id, help=f"node id (default {default_id})")
    p.add_argument("--run-id", default="demo", help="run id: keys live under iamp/<run>/ (default demo)")
    p.add_argument("--params-json", default="{}", help="parameters as a JSON object (the launcher passes them)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override one parameter (TOML value)")
    p.add_argument("--inputs-json", default=None, help='input bindings as JSON {"port": "node/output"}')
    p.add_argument("--input", action="append", default=[], metavar="PORT=NODE/OUTPUT", help="bind one input")
    p.add_argument("--queue-size", type=int, default=256, help="bounded queue length of each input (default 256 messages)")
    p.add_argument("--queue-mib", type=float, default=64.0, help="bounded queue size of each input in MiB of payload (default 64)")
    p.add_argument("--max-age-s", type=float, default=0.0,
                   help="skip a joined input that waited longer than this many seconds in the queue where a newer one of its"
                        " port is queued (stale_drops; default 0: off; the live pipeline sets it)")
    p.add_argument(
        "--stamp-window-s",
        type=float,
        default=60.0,
        help="reject inputs stamped more than this many seconds ahead of the newest accepted stamp (default 60)",
    )
    p.add_argument("--stats-period", type=float, default=1.0, help="seconds between NodeStats (default 1)")
    p.add_argument("--nice", type=int, default=spec.nice_default, metavar="N",
                   help=f"lower this node's CPU priority by N (0-19, os.nice) before it starts (default {spec.nice_default})")
    p.add_argument("--log-level", default="INFO", type=str.upper, choices=LOG_LEVELS, help="DEBUG, INFO (default), WARNING, ERROR or CRITICAL")
    p.add_argument(
        "--await-nodes",
        default="",
        metavar="ID,ID",
        help="wait until these nodes' liveliness tokens are visible before the first publish (the launcher passes a source every "
        "other node, an operator the nodes that read its outputs)",
    )
    add_network_args(p)
    return p


def parse_bindings(spec: StageSpec, args: argparse.Namespace) -> dict[str, str]:
    """Input bindings port -> 'node/output', checked against the spec (wildcard inputs take none)."""
    raw: dict[str, str] = json.loads(args.inputs_json) if args.inputs_json else {}
    if not isinstance(raw, dict):
        raise ConfigError("--inputs-json must be a JSON object {port: 'node/output'}")
    for item in args.input:
        if "=" not in item:
            raise ConfigError(f"--input {item!r}: expected PORT=NODE/OUTPUT")
        p, ref = item.split("=", 1)
        raw[p.strip()] = ref.strip()
    for port, ref in raw.items():
        if port not in spec.inputs:
            raise ConfigError(f"{spec.stage}: unknown input port {port!r}; known: {', '.join(spec.inputs) or '(none)'}")
        if spec.inputs[port].pattern is not None:
            raise ConfigError(f"{spec.stage}: input {port} is a wildcard input on iamp/<run>/{spec.inputs[port].pattern}; it takes no binding")
        parts = str(ref).split("/")
        if len(parts) != 2:
            raise ConfigError(f"{spec.stage}: input {port} = {ref!r}: expected 'node/output'")
        keys.check_name(parts[0], "node id")
        keys.check_name(parts[1], "output name")
    missing = [p for p, port in spec.inputs.items() if p not in raw and port.needs_binding]
    if missing and spec.kind == "operator":
        raise ConfigError(f"{spec.stage}: input port(s) {', '.join(missing)} not bound; use --input PORT=NODE/OUTPUT")
    return raw


def setup_logging(level: str, node_id: str) -> None:
    logging.basicConfig(
        level=getattr(logging, str(level).upper(), logging.INFO),
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        datefmt="%H:%M:%S",
        stream=sys.stderr,
        force=True,
    )


@dataclass(frozen=True)
class StageStart:
    """What ``start_stage`` read: the parsed flags, the stage's config and its logger."""

    args: argparse.Namespace
    config: Any
    log: logging.Logger


def start_stage(spec: StageSpec, argv: list[str] | None = None, *, bindings: bool = True) -> StageStart | int:
    """Parse the command line, set up logging, check the ids and build the config.

    Returns a ``StageStart``, or the exit code to end with: ``EXIT_OK`` for
    ``--help``, ``EXIT_USAGE`` for a bad command line or config (logged).
    With ``bindings`` the input bindings are checked too (``parse_bindings``;
    ``args.bindings`` then holds them).
    """
    parser = build_parser(spec)
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:
        return EXIT_OK if exc.code == 0 else EXIT_USAGE
    setup_logging(args.log_level, args.node_id)
    log = logging.getLogger(f"iamp.{args.node_id}")
    try:
        keys.check_run_id(args.run_id)
        keys.check_name(args.node_id, "node id")
        check_runtime_args(args)
        params = json.loads(args.params_json)
        if not isinstance(params, dict):
            raise ConfigError("--params-json must be a JSON object")
        params.update(parse_set(args.set))
        config = spec.config_cls.from_params(params, where=f"node {args.node_id} ({spec.stage})")
        args.bindings = parse_bindings(spec, args) if bindings else {}
    except (ConfigError, ValueError, json.JSONDecodeError) as exc:
        log.error("bad configuration: %s", exc)
        return EXIT_USAGE
    apply_nice(args.nice, log)
    watch_launcher(log)
    return StageStart(args=args, config=config, log=log)


def on_stop_signals(handler: Callable[[int], None]) -> None:
    """Call ``handler(signal number)`` on SIGINT, SIGTERM and SIGHUP (the terminal or ssh session that ran it closed: a
    recorder still finishes its file) (only from the main thread; elsewhere nothing is installed)."""
    if threading.current_thread() is not threading.main_thread():
        return
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, lambda signum, _frame: handler(signum))
