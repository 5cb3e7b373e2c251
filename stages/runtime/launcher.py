"""Launch a hybrid-iamp pipeline: validate, spawn, supervise, shut down cleanly.

    python launch.py                              # the shipped hybrid pipeline on the embedded scenario
    python launch.py baseline --stop-after 20 --record run.mcap
    python launch.py my_pipeline.toml             # a pipeline file of your own
    python launch.py --check | --describe         # validate only / print the resolved pipeline

A pipeline is a TOML file, or the name of one shipped in ``stages/pipelines``
(``hybrid``, ``baseline``, ``replay``, ``live``).

Every node runs as its own process (``python -m <stage>``); its output lines
are prefixed with ``[node-id]``. The launcher opens the bus hub (a Zenoh peer
on 127.0.0.1) that every node connects to, waits for every node's liveliness
token before starting the sources, restarts nodes that die (``restart =
true``, the default for processing nodes and the recorder), and stops
everything with SIGINT -> SIGTERM -> SIGKILL.

Supervision: a node gets ``--max-restarts`` restarts (default 5); one that
has run ``--restart-reset-s`` seconds (default 60; 0: never) since its last
start when it dies gets its budget back, so only a node that keeps dying
stops the run. A killed recorder is restarted into the next split file
(``run.mcap``, ``run.001.mcap``, ``run.002.mcap``, ...) while prediction goes
on; the torn split reads with ``iamp inspect`` and ``iamp recover`` rewrites
it into a finished file.
When the sources end (or after ``--stop-after``), nodes are stopped in
dataflow order so each drains what it has; the recorder stops last and
finishes its MCAP file.

With ``[bus.auth]`` in the pipeline file, the launcher writes a Zenoh config
(``transport/auth/usrpwd``: user, password, the dictionary of accepted
users) and the dictionary into a fresh private folder (0700, files 0600),
passes ``--config FILE`` to every node and opens its own hub with it, so
every link of the run is authenticated and no password is on a command line;
the folder is removed when the run ends. The nodes are then clients of the
hub (a router) and connect to it alone: the hub joins the extra ``--connect``
endpoints for them (a client links to one router only). A viewer ``token`` reaches the
viewer through ``IAMP_VIEWER_TOKEN`` in its environment, not its command line.

Exit codes: 0 clean run, 1 a node failed (the first failing code is
reported), 2 bad command line or pipeline file, or an unusable map (the
corridors stage reports it; the run stops at once with the map's problem).
Without a dataset player (``live``) the map comes from the tracker's
SceneInfo, a message rather than this run's configuration: an unusable one
is one line per report and the run goes on, waiting for a scene it can load.
"""

from __future__ import annotations

import argparse
import collections
import datetime as _dt
import json
import math
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any, Mapping

from stages.lib.base import ConfigError
from stages.runtime.args import LAUNCHER_PID_ENV, LOG_LEVELS, concrete_listen
from stages.runtime.pipeline import BusAuth, Pipeline, PipelineError, load_pipeline

PIPELINES_DIR = Path(__file__).resolve().parents[1] / "pipelines"
"""The pipelines shipped with the package (``stages/pipelines/*.toml``)."""
DEFAULT_PIPELINE = PIPELINES_DIR / "hybrid.toml"
SOURCE_STAGES = {"stages.tracks_source"}
RECORDER_STAGE = "stages.recorder"
REPLAY_STAGE = "stages.replay"
MAP_STAGES = {"stages.corridors", "stages.relations", "stages.intentions", "stages.viewer", "stages.foxglove_bridge"}  # each gets the source's data folder
VIEWER_STAGE = "stages.viewer"
MARKOV_STAGE = "stages.markov_prediction"
#: ``--calibrated-grids`` / ``--raw-grids``: markov_prediction's keys for calibrated grids (its defaults, named for a
#: pipeline file that sets others) and for raw ones (``stages.markov_prediction.config.RAW_GRIDS``; docs/evaluation.md,
#: "Calibrated grids")
CALIBRATED_GRIDS = {"spread_calibration": "shipped", "spread_online": True}
RAW_GRIDS = {"spread_calibration": "", "spread_online": False}
VIEWER_URL_RE = re.compile(r"viewer: (https?://\S+)\s*$")
FOXGLOVE_STAGE = "stages.foxglove_bridge"
FOXGLOVE_URL_RE = re.compile(r"foxglove: (wss?://\S+)\s*$")
# --foxglove binds the bridge's inputs to the outputs of the nodes of these stages (the first of each)
FOXGLOVE_BINDINGS = {
    "track_frame": ("stages.tracks_source", "track_frame"),
    "scene": ("stages.tracks_source", "scene"),
    "corridor_set": ("stages.corridors", "corridor_set"),
    "corridor_predictions": ("stages.markov_prediction", "corridor_predictions"),
    "motion_grid": ("stages.markov_prediction", "motion_grid"),
    "intention_belief": ("stages.intentions", "intention_belief"),
}
# The corridors stage's issue line for a map it cannot use (stages/corridors/core.py, issue kind no_map):
# nothing can be matched or predicted, so the run stops with exit 2 and this text.
CORRIDORS_STAGE = "stages.corridors"
MAP_UNUSABLE_RE = re.compile(r"kind=no_map\b.*?\b(map \S+ unusable: .*?)\s*$")
EXIT_UNUSABLE_MAP = 2
VIEWER_TOKEN_ENV = "IAMP_VIEWER_TOKEN"  # stages.viewer.config.TOKEN_ENV
MAX_RESTARTS = 5
RESTART_RESET_S = 60.0  # a node that ran this long without dying gets its restart budget back
STOP_ESCALATION_S = 5.0

_print_lock = threading.Lock()


def say(line: str, tag: str = "launch") -> None:
    with _print_lock:
        try:
            sys.stdout.write(f"[{tag}] {line}\n")
            sys.stdout.flush()
        except (OSError, ValueError):  # the terminal is gone (SIGHUP): the run still stops every node as it should
            pass


def resolve_pipeline_arg(arg: str) -> str:
    """A pipeline file as given, or the shipped ``stages/pipelines/<arg>.toml`` when ``arg`` is a bare name that is no file here."""
    shipped = PIPELINES_DIR / f"{arg}.toml"
    if not Path(arg).exists() and "/" not in arg and not arg.endswith(".toml") and shipped.is_file():
        return str(shipped)
    return arg


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="launch.py", description="Run a hybrid-iamp pipeline (default: the shipped hybrid pipeline on the embedded scenario).")
    names = ", ".join(sorted(p.stem for p in PIPELINES_DIR.glob("*.toml")))
    p.add_argument("pipeline", nargs="?", default=str(DEFAULT_PIPELINE), help=f"pipeline TOML file, or the name of a shipped one ({names}; default hybrid)")
    p.add_argument("--check", action="store_true", help="validate the pipeline and exit (0 ok, 2 error)")
    p.add_argument("--describe", action="store_true", help="print the resolved nodes, keys, schemas and parameters, then exit")
    p.add_argument("--stop-after", type=float, metavar="SECONDS", help="stop the run cleanly this many seconds after the sources start (their loading included: a"
                   " recording takes a second or two before its first frame)")
    p.add_argument("--set", action="append", default=[], metavar="NODE.KEY=VALUE", help="override a node parameter (TOML value)")
    p.add_argument("--var", action="append", default=[], metavar="NAME=VALUE", help="set a ${NAME} variable of the pipeline file")
    p.add_argument("--record", metavar="FILE.mcap", help="record the run to this MCAP file (default: runs/<run>-<time>.mcap)")
    p.add_argument("--overwrite", action="store_true", help="let the recorder replace an existing --record file (and its split files); without it such a file stops the launcher before any node starts")
    p.add_argument("--no-record", action="store_true", help="leave the recorder out")
    p.add_argument("--no-viewer", action="store_true", help="leave the viewer out")
    p.add_argument("--linger", action="store_true", help="when the sources finish (a replay, a recording played), keep every node up,"
                   " the viewer on the last frames, until Ctrl-C or --stop-after, instead of ending the run")
    grids = p.add_mutually_exclusive_group()
    grids.add_argument("--calibrated-grids", action="store_true",
                       help="calibrated motion grids on every markov_prediction node (its default, spread_calibration = \"shipped\","
                            " spread_online = true; for a pipeline file that sets other values): the shipped spread table and the online"
                            " spread, so that the 90 %% region holds the truth in about 90 %% of cases")
    grids.add_argument("--raw-grids", action="store_true",
                       help="raw motion grids on every markov_prediction node (spread_calibration = \"\", spread_online = false): the"
                            " chain's own distributions, over-confident for moving cars (their 90 %% region holds the truth in 40-65 %%"
                            " of cases) and cheaper (README, \"Where it stands\")")
    p.add_argument("--foxglove", action="store_true", help="add the live Foxglove bridge (node foxglove): the scene on a Foxglove WebSocket, ws://127.0.0.1:PORT printed")
    p.add_argument("--data", metavar="PATH", help="data folder laid out like stages/data/taf-bw (default: the embedded scenario); in a pipeline without a"
                   " dataset player (live) the folder whose maps/ the stages load the tracker's map from")
    p.add_argument("--recording", metavar="NAME", help="recording to play from --data")
    p.add_argument("--speed", metavar="X|max", help="playback speed factor of the source (a dataset player or a recording's replay), or 'max'")
    p.add_argument("--run-id", help="run id (keys under iamp/<run>/); default from the pipeline file")
    p.add_argument("--connect", action="append", default=[], metavar="ENDPOINT", help="join a remote Zenoh router/peer as well")
    p.add_argument("--listen", metavar="ENDPOINT", help="the hub endpoint (default from the pipeline, tcp/127.0.0.1:<free port>)")
    p.add_argument("--startup-timeout", type=float, default=90.0, metavar="SECONDS", help="how long to wait for a node's liveliness while it does no work: one that uses CPU (compiling its kernels at a first"
                        " start) is waited for up to 10 times as long (default 90)")
    p.add_argument("--log-level", default="INFO", type=str.upper, choices=LOG_LEVELS, help="log level passed to every node: DEBUG, INFO (default), WARNING, ERROR or CRITICAL")
    p.add_argument("--max-restarts", type=int, default=MAX_RESTARTS, metavar="N", help=f"restarts a node gets before its death stops the run (default {MAX_RESTARTS})")
    p.add_argument(
        "--restart-reset-s",
        type=float,
        default=RESTART_RESET_S,
        metavar="SECONDS",
        help=f"a node that ran this long since its last start gets its restarts back when it dies (default {RESTART_RESET_S:g}; 0: never)",
    )
    return p


def _toml_value(text: str) -> Any:
    import tomllib

    try:
        return tomllib.loads(f"x = {text}")["x"]
    except tomllib.TOMLDecodeError:
        return text


def parse_overrides(items: list[str]) -> dict[str, dict[str, Any]]:
    out: dict[str, dict[str, Any]] = {}
    for item in items:
        if "=" not in item or "." not in item.split("=", 1)[0]:
            raise PipelineError(f"--set {item!r}: expected NODE.KEY=VALUE")
        lhs, rhs = item.split("=", 1)
        node, key = lhs.split(".", 1)
        out.setdefault(node.strip(), {})[key.strip()] = _toml_value(rhs.strip())
    return out


def default_record_path(run_id: str) -> str:
    stamp = _dt.datetime.now(_dt.timezone.utc).strftime("%Y%m%d-%H%M%S")
    return str(Path("runs") / f"{run_id}-{stamp}.mcap")


def foxglove_node(nodes: list[dict]) -> dict:
    """The Foxglove bridge node that ``--foxglove`` adds: the viewer's inputs (where the pipeline has a viewer), and the outputs of the first node of each producing stage."""
    viewer = next((n for n in nodes if n.get("stage") == VIEWER_STAGE), None)
    wanted = (*FOXGLOVE_BINDINGS, "compare_predictions")  # the bridge's inputs (stages/foxglove_bridge/__main__.py)
    inputs = {k: v for k, v in (viewer.get("inputs", {}) if viewer is not None else {}).items() if k in wanted}
    for port, (stage, output) in FOXGLOVE_BINDINGS.items():
        node = next((n for n in nodes if n.get("stage") == stage), None)
        if node is not None and port not in inputs:
            inputs[port] = f"{node['id']}/{output}"
    if "track_frame" not in inputs:
        raise PipelineError(f"--foxglove: the pipeline has no viewer node nor dataset source node ({', '.join(sorted(SOURCE_STAGES))}) to take track frames from")
    return {"id": "foxglove", "stage": FOXGLOVE_STAGE, "inputs": inputs, "params": {}}


def make_editor(args: argparse.Namespace):
    """Apply --data/--recording/--speed/--record/--no-viewer/--run-id to the raw descriptor."""

    def edit(raw: dict) -> None:
        nodes = raw.setdefault("nodes", [])
        if args.run_id:
            raw.setdefault("bus", {})["run_id"] = args.run_id
        if getattr(args, "foxglove", False) and not any(n.get("stage") == FOXGLOVE_STAGE for n in nodes):
            nodes.append(foxglove_node(nodes))
        for flag, keys in (("calibrated_grids", CALIBRATED_GRIDS), ("raw_grids", RAW_GRIDS)):
            if not getattr(args, flag, False):
                continue
            markov = [n for n in nodes if n.get("stage") == MARKOV_STAGE]
            if not markov:
                raise PipelineError(f"--{flag.replace('_', '-')}: the pipeline has no markov_prediction node")
            for n in markov:  # a --set of either key still wins: overrides come after this edit
                n.setdefault("params", {}).update(keys)
        if args.no_viewer:
            raw["nodes"] = nodes = [n for n in nodes if n.get("stage") != VIEWER_STAGE]
        if args.no_record:
            raw["nodes"] = nodes = [n for n in nodes if n.get("stage") != RECORDER_STAGE]
        sources = [n for n in nodes if n.get("stage") in SOURCE_STAGES]
        speed = args.speed
        replays = [n for n in nodes if n.get("stage") == REPLAY_STAGE]
        if speed is not None and not sources and replays:  # a recording's replay plays at --speed too
            for n in replays:
                n.setdefault("params", {})["speed"] = _speed_value(speed)
            speed = None
        if args.data is not None and not Path(args.data).is_dir():  # before any node starts (each would fail on it)
            raise PipelineError(f"--data {args.data}: no such folder (expected a data folder laid out like stages/data/taf-bw:"
                                " maps/<recording>.osm and recorded_trackfiles/<recording>/)")
        for flag, key, value in (("--data", "data", args.data), ("--recording", "recording", args.recording), ("--speed", "speed", speed)):
            if value is None:
                continue
            if not sources:
                if key == "data":
                    continue  # no player (a live tracker's pipeline): the folder is only where the map stages find the maps (below)
                raise PipelineError(f"{flag}: the pipeline has no dataset source node ({', '.join(sorted(SOURCE_STAGES))})")
            if key == "speed":
                value = _speed_value(value)
            for n in sources:
                n.setdefault("params", {})[key] = str(Path(value).resolve()) if key == "data" else value
                if key == "recording" and args.data is None:
                    pass
        if args.data is not None and args.recording is None:
            for n in sources:  # another data folder: do not keep the default scenario's recording and sequence choice
                n.setdefault("params", {}).pop("sequences", None)
                n["params"].pop("recording", None)
        # the stages that load the map read it from the source's data folder (by name, checked by sha256), never from a bus path
        data = next((n["params"]["data"] for n in sources if isinstance(n.get("params"), dict) and n["params"].get("data")), None)
        if data is None and not sources and args.data is not None:
            data = str(Path(args.data).resolve())
        if data is not None:
            for n in nodes:
                if n.get("stage") in MAP_STAGES:
                    params = n.setdefault("params", {})
                    if args.data is not None or not params.get("data"):
                        params["data"] = data
        if not args.no_record:
            recs = [n for n in nodes if n.get("stage") == RECORDER_STAGE]
            if not recs and args.record:
                recs = [{"id": "recorder", "stage": RECORDER_STAGE, "params": {}}]
                nodes.append(recs[0])
            for n in recs:
                params = n.setdefault("params", {})
                if args.record:
                    params["path"] = args.record
                if getattr(args, "overwrite", False):
                    params["overwrite"] = True
                if not params.get("path"):
                    params["path"] = default_record_path(raw.get("bus", {}).get("run_id", raw.get("name", "demo")))

    return edit


def _speed_value(value: str) -> float | str:
    if value == "max":
        return value
    try:
        return float(value)
    except ValueError:
        raise PipelineError(f"--speed {value!r}: expected a number > 0 or 'max'") from None


def preflight(pipeline: Pipeline) -> None:
    """What the run would fail on at once, checked before any node starts (and by ``--check``): each stage's own
    ``StageSpec.preflight`` (a recording or replay file that is not there, a recording file that would be replaced), and
    a recorder writing the file a replay reads. Raises ``PipelineError``."""
    replayed = {Path(n.params["path"]).resolve(): n.id for n in pipeline.nodes if n.stage == REPLAY_STAGE and n.params.get("path")}
    for n in pipeline.nodes:
        if n.stage == RECORDER_STAGE and n.params.get("path") and Path(n.params["path"]).resolve() in replayed:
            raise PipelineError(f"node {n.id}: records into {n.params['path']}, the file node {replayed[Path(n.params['path']).resolve()]}"
                                " replays: choose another --record path")
        check = getattr(n.spec, "preflight", None)
        if check is not None:
            try:
                check(n.config)
            except ConfigError as exc:
                flag = " (--record)" if n.stage == RECORDER_STAGE else ""
                raise PipelineError(f"node {n.id}{flag}: {exc}") from None


def resolve_hub(pipeline: Pipeline, override: str | None) -> str:
    ep = override or (pipeline.listen[0] if pipeline.listen else "tcp/127.0.0.1:0")
    return concrete_listen([ep])[0]


class RestartBudget:
    """The restarts a node has left: ``limit``, all given back once it has run ``reset_after_s`` without dying.

    ``started()`` marks a (re)start; ``take()``, on a death, says whether the
    node may be restarted and counts it. ``clock`` (monotonic seconds) is
    injectable, so the policy is tested without waiting.
    """

    def __init__(self, limit: int = MAX_RESTARTS, reset_after_s: float = RESTART_RESET_S, clock: Any = time.monotonic) -> None:
        self.limit = limit
        self.reset_after_s = reset_after_s
        self.clock = clock
        self.used = 0
        self.resets = 0
        self.started_at: float | None = None
        self.last_ran_s = 0.0  # how long the node had run when it last died
        self.last_reset = False  # whether the last take() gave the budget back

    def started(self) -> None:
        self.started_at = self.clock()

    def take(self) -> bool:
        self.last_ran_s = 0.0 if self.started_at is None else self.clock() - self.started_at
        self.last_reset = bool(self.used and self.reset_after_s > 0 and self.last_ran_s >= self.reset_after_s)
        if self.last_reset:
            self.used = 0
            self.resets += 1
        if self.used >= self.limit:
            return False
        self.used += 1
        return True


def _write_private(path: Path, text: str) -> None:
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(text)


def write_auth_config(auth: BusAuth) -> tuple[Path, Path]:
    """A private folder (0700) with the Zenoh config (usrpwd) and its dictionary (0600 each); returns (folder, config file)."""
    folder = Path(tempfile.mkdtemp(prefix="iamp-bus-auth-"))
    dictionary = folder / "users.txt"
    _write_private(dictionary, f"{auth.user}:{auth.password}\n")
    config = folder / "zenoh.json5"
    usrpwd = {"user": auth.user, "password": auth.password, "dictionary_file": str(dictionary)}
    _write_private(config, json.dumps({"transport": {"auth": {"usrpwd": usrpwd}}}, indent=2) + "\n")
    return folder, config


#: Thread pools of the numeric libraries (OpenBLAS, OpenMP: numpy, scipy, torch) a node starts with, unless the
#: environment already sets them: one thread each. A pipeline runs a process per stage; with the libraries'
#: default of one thread per core, every process's pool spins on every core and they preempt each other
#: (measured on 2 cores, 18 vehicles: the AR model's 160-pair forward 24 ms with 2 threads under load, 0.7 ms
#: with 1; README "Performance"). Set OMP_NUM_THREADS etc. before ``launch.py`` to give the nodes more.
THREAD_ENV = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def single_threaded_env(environ: Mapping[str, str]) -> dict[str, str]:
    """``environ`` with every ``THREAD_ENV`` variable it does not set set to "1"."""
    env = dict(environ)
    for name in THREAD_ENV:
        env.setdefault(name, "1")
    return env


class Child:
    def __init__(self, node: Any, cmd: list[str], budget: RestartBudget | None = None) -> None:
        self.node = node
        self.cmd = cmd
        self.env: dict[str, str] = {}  # added to the launcher's environment (secrets that must not be on the command line)
        self.proc: subprocess.Popen | None = None
        self.budget = budget or RestartBudget()
        # a condition in the node's output (an unusable map): it ends the run where the map is the run's own (a dataset
        # player or replay); in a live run it is said and cleared (``supervise``)
        self.fatal: str | None = None
        self.finished = False  # a source that ended on its own, or a node we stopped
        self.exit_code: int | None = None

    @property
    def restarts(self) -> int:
        return self.budget.used

    def start(self) -> None:
        self.budget.started()
        self.proc = subprocess.Popen(
            self.cmd,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            cwd=os.getcwd(),
            # (the nodes import the installed package; each stops when this process is gone: args.watch_launcher)
            env={k: v for k, v in {**single_threaded_env(os.environ), **self.env, "PYTHONUNBUFFERED": "1",
                                   LAUNCHER_PID_ENV: str(os.getpid()), "PYTHONPATH": code_path(os.environ)}.items()
                 if k != "PYTHONPATH" or v},
            start_new_session=True,  # a Ctrl-C at the terminal reaches the launcher only; it stops children in order
            text=True,
            bufsize=1,
        )
        threading.Thread(target=self._pump, args=(self.proc,), daemon=True).start()

    def _pump(self, proc: subprocess.Popen) -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            say(line.rstrip("\n"), self.node.id)
            if self.node.stage == VIEWER_STAGE and (url := VIEWER_URL_RE.search(line)):
                say(f"viewer: {url.group(1)}")  # the one line to open in a browser
            if self.node.stage == FOXGLOVE_STAGE and (url := FOXGLOVE_URL_RE.search(line)):
                say(f"foxglove: {url.group(1)}")  # open in Foxglove: Open connection -> Foxglove WebSocket
            if self.node.stage == CORRIDORS_STAGE and self.fatal is None and (bad := MAP_UNUSABLE_RE.search(line)):
                self.fatal = bad.group(1)  # the supervisor stops the run

    def poll(self) -> int | None:
        return None if self.proc is None else self.proc.poll()

    def stop(self, up: bool = True) -> int | None:
        """SIGINT, then SIGTERM after 5 s, then SIGKILL after 5 s more. A node not ``up`` (no liveliness token seen yet:
        still importing or starting) gets SIGTERM first: before its handlers are in, that ends it without a word, where
        SIGINT would print a KeyboardInterrupt traceback from whatever module it was importing."""
        if self.proc is None or self.proc.poll() is not None:
            return self.poll()
        steps = ((signal.SIGINT, STOP_ESCALATION_S), (signal.SIGTERM, STOP_ESCALATION_S), (signal.SIGKILL, 10.0))
        for sig, wait in steps if up else steps[1:]:
            try:
                self.proc.send_signal(sig)
            except ProcessLookupError:
                break
            try:
                self.proc.wait(timeout=wait)
                break
            except subprocess.TimeoutExpired:
                if sig != signal.SIGKILL:
                    say(f"node {self.node.id} still running after {signal.Signals(sig).name}; escalating")
        return self.proc.poll()


def describe_code(code: int) -> str:
    if code < 0:
        try:
            return f"signal {signal.Signals(-code).name}"
        except ValueError:
            return f"signal {-code}"
    return f"exit code {code}"


#: the share of recorded frames without a MotionGrid above which the end of a run says where they went and what to do
LOSS_TO_EXPLAIN = 0.05
DROP_COUNTERS = ("queue_drops", "stale_drops", "join_drops")


class RunStats:
    """Every node's NodeStats over the run, as the launcher hears them (``iamp/<run>/_stats/*``), a restarted node's
    counters added up over its runs (each run counts from 0; its own last line at stop covers its last run only)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.last: dict[str, Any] = {}
        self._carried: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)
        self.runs: collections.Counter[str] = collections.Counter()
        self.unreadable = 0  # NodeStats messages that did not decode: said once, counted, left out of the figures

    def on_stats(self, key: str, data: bytes) -> None:
        from bus_schemas import NodeStats, SchemaError

        try:
            msg = NodeStats.decode(data)
        except SchemaError as exc:
            with self._lock:
                self.unreadable += 1
                first = self.unreadable == 1
            if first:
                say(f"warning: a NodeStats message on {key} does not read ({exc}): such messages are left out of the"
                    " end-of-run figures (counted there)")
            return
        with self._lock:
            prev = self.last.get(msg.node_id)
            if prev is None or prev.pid != msg.pid:
                self.runs[msg.node_id] += 1
                if prev is not None:
                    self._carried[msg.node_id].update(prev.counters)
            self.last[msg.node_id] = msg

    def counters(self, node_id: str) -> collections.Counter:
        with self._lock:
            last = self.last.get(node_id)
            return self._carried[node_id] + collections.Counter(last.counters if last is not None else {})

    def diagnosis(self, paced: bool) -> str:
        """Where the frames without a grid went (the nodes' drops), the slowest stage, and, where the stages could not
        keep up at real time, what to do; '' where no node says anything."""
        with self._lock:
            nodes = dict(self.last)
        totals = {n: self.counters(n) for n in nodes}
        drops = {n: {k: totals[n][k] for k in DROP_COUNTERS if totals[n][k]} for n in nodes}
        drops = {n: d for n, d in sorted(drops.items(), key=lambda kv: -sum(kv[1].values())) if d}
        working = {n: m for n, m in nodes.items() if math.isfinite(m.proc_ms_p50) and m.counters.get("processed", 0)}
        if not drops and not working:
            return ""
        parts = []
        if drops:
            parts.append("input sets dropped: " + "; ".join(
                f"{n} " + ", ".join(f"{v} {k.split('_')[0]}" for k, v in d.items())
                + (f" (over its {self.runs[n]} runs)" if self.runs[n] > 1 else "") for n, d in drops.items()))
        if working:
            slow = sorted(working.items(), key=lambda kv: -kv[1].proc_ms_p50)[:2]
            parts.append("slowest: " + ", ".join(f"{n} {m.proc_ms_p50:.0f} ms a set at p50 ({m.proc_ms_p95:.0f} at p95)" for n, m in slow))
        line = "where the frames went: " + "; ".join(parts) + (f" ({self.unreadable} NodeStats messages unreadable)" if self.unreadable else "")
        if drops and not paced:
            line += ("; more than this machine keeps up with at real time: leave the viewer out (--no-viewer), play fewer"
                     " vehicles, spread markov_prediction over shards on more cores or machines (launch.py sharded; README,"
                     " \"Spreading stages over machines\"), or play at --speed max to handle every frame (not real time)")
        return line


class Launcher:
    def __init__(self, pipeline: Pipeline, hub: str, args: argparse.Namespace) -> None:
        self.p = pipeline
        self.hub = hub
        self.args = args
        self.children: dict[str, Child] = {}
        self.stop_requested = threading.Event()
        self.stats = RunStats()  # every node's NodeStats as heard: the end of the run says where lost frames went
        self.first_failure: int | None = None
        self.alive: set[str] = set()
        self._alive_lock = threading.Lock()
        self.bus = None
        self.auth_dir: Path | None = None
        self.zenoh_config: str | None = None  # with [bus.auth]: the private config every session opens with
        self.started_wall_s = time.time()  # files of this run (split recordings) are newer
        self._closing = threading.Event()  # set when the run ends, before the hub's session closes

    def secret_env(self, node: Any) -> dict[str, str]:
        """Secrets of a node that go through its environment, not its command line (the viewer's token)."""
        if node.stage == VIEWER_STAGE and node.params.get("token"):
            return {VIEWER_TOKEN_ENV: str(node.params["token"])}
        return {}

    def command(self, node: Any, params: dict[str, Any] | None = None) -> list[str]:
        if node.stage == VIEWER_STAGE:  # its token goes through the environment (secret_env)
            params = {k: v for k, v in (node.params if params is None else params).items() if k != "token"}
        cmd = [
            sys.executable,
            "-m",
            node.stage,
            "--node-id",
            node.id,
            "--run-id",
            self.p.run_id,
            "--params-json",
            json.dumps(node.params if params is None else params),
            "--mode",
            self.node_mode,
            "--connect",
            self.hub,
            "--log-level",
            self.args.log_level,
        ]
        for ep in self.node_extra_connect:
            cmd += ["--connect", ep]
        if self.zenoh_config:
            cmd += ["--config", self.zenoh_config]
        if node.inputs:
            cmd += ["--inputs-json", json.dumps(node.inputs)]
        if node.kind == "source":
            others = [n.id for n in self.p.nodes if n.kind != "source"]
        else:
            # an operator's outputs are lost to a consumer whose subscription it does not see yet: it waits for the nodes
            # that read them (the recorder reads all) before its first publish, as a source waits for everyone
            others = [n.id for n in self.p.nodes if n.id != node.id and n.kind != "source" and node.spec.outputs
                      and (n.kind == "raw_sink" or any(ref.split("/", 1)[0] == node.id for ref in n.inputs.values()))]
        if others:
            cmd += ["--await-nodes", ",".join(others)]
        if node.queue_size:
            cmd += ["--queue-size", str(node.queue_size)]
        if node.max_age_s and not self.paced_at_max:
            cmd += ["--max-age-s", repr(node.max_age_s)]
        cmd += ["--nice", str(getattr(node, "nice", 0))]  # (0 too: a node started as it is, whatever its stage's default)
        return cmd

    @property
    def paced_at_max(self) -> bool:
        """Every source of the pipeline plays at ``max`` (paced by the nodes' acks, a few frames in flight): its frames
        are all handled however long each takes, so no input is skipped for its age (``max_age_s`` is for a source at
        real time, or N times it, whose frames come whether the stages keep up or not)."""
        sources = [n for n in self.p.nodes if n.kind == "source"]
        return bool(sources) and all(getattr(n.config, "speed", None) == "max" for n in sources)

    def _on_alive(self, node_id: str, alive: bool) -> None:
        with self._alive_lock:
            (self.alive.add if alive else self.alive.discard)(node_id)

    def wait_alive(self, ids: list[str], timeout: float, progress_s: float = 15.0) -> list[str]:
        """Wait until the nodes ``ids`` are alive; returns those that are not (a node that exited ends the wait at once,
        as does a stop request). ``timeout`` counts while no missing node works: a node whose process is using CPU
        (compiling its kernels at a first start on a machine: over a minute on 2 cores, past the old fixed 90 s) is
        waited for, up to ``STARTUP_CAP_FACTOR`` times ``timeout``; every ``progress_s`` one line says who is awaited."""
        t0 = last_said = last_looked = time.monotonic()
        deadline, cap = t0 + timeout, t0 + STARTUP_CAP_FACTOR * timeout
        cpu: dict[str, float | None] = {}  # each missing node's CPU time when last looked at (once a second)
        while not self.stop_requested.is_set():
            now = time.monotonic()
            with self._alive_lock:
                missing = [i for i in ids if i not in self.alive]
            if not missing:
                return []
            for i in missing:
                if self.children[i].poll() is not None:
                    return missing
            if now - last_looked >= 1.0 or not cpu:
                last_looked = now
                used = {i: _cpu_seconds(self.children[i].proc.pid) for i in missing if self.children[i].proc is not None}
                if any(v is not None and cpu.get(i) is not None and v > cpu[i] + 0.1 for i, v in used.items()):
                    deadline = min(max(deadline, now + timeout), cap)  # working: the idle time starts again
                cpu = used
            if now - last_said >= progress_s:
                last_said = now
                busy = ", ".join(f"{i} ({v:.0f} s of CPU)" if v is not None else i for i, v in cpu.items())
                say(f"waiting for {busy} to come up ({now - t0:.0f} s; a first start on a machine compiles the stages' kernels,"
                    " a minute or more on 2 cores)")
            if now >= deadline:
                break
            time.sleep(0.05)
        with self._alive_lock:
            return [i for i in ids if i not in self.alive]

    def spawn(self, node: Any) -> None:
        child = self.children.get(node.id) or Child(node, self.command(node), RestartBudget(self.args.max_restarts, self.args.restart_reset_s))
        self.children[node.id] = child
        child.env = self.secret_env(node)
        child.start()

    def run(self) -> int:
        from stages.runtime import BusClient
        from bus_schemas import keys

        order = self.p.topo_order()
        sources = [n for n in order if n.kind == "source"]
        others = [n for n in order if n.kind != "source"]
        say(f"pipeline {self.p.name}: run={self.p.run_id} hub={self.hub} nodes={','.join(n.id for n in order)}")
        for n in order:
            if n.stage == RECORDER_STAGE:
                say(f"recording to {Path(n.params.get('path')).resolve()}")
        extra = self.extra_connect
        if self.p.auth is not None:
            self.auth_dir, config = write_auth_config(self.p.auth)
            self.zenoh_config = str(config)
            say(f"bus auth: {self.p.auth.describe()}; every node gets --config {config} (mode 0600)")
            if extra:
                say(f"bus auth with --connect {' '.join(extra)}: the nodes are Zenoh clients, which link to one router only, so they"
                    f" join the hub alone and the hub (a router) links to {' '.join(extra)} for them; that router must accept the"
                    " run's [bus.auth] user and password (README: Spreading stages over machines)")
        try:
            self.bus = BusClient(mode=self.hub_mode, listen=[self.hub], connect=extra, config_file=self.zenoh_config)
        except BaseException:
            self._remove_auth_dir()
            raise
        if extra:
            threading.Thread(target=self._watch_extra_links, args=(extra,), daemon=True).start()
        self.bus.watch_alive(keys.alive_pattern(self.p.run_id), self._on_alive)
        self.bus.subscribe(keys.stats_pattern(self.p.run_id), self.stats.on_stats)
        for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):  # SIGHUP: the terminal or ssh session closed
            signal.signal(sig, lambda *_: self.stop_requested.set())
        try:
            for n in others:
                self.spawn(n)
            missing = self.wait_alive([n.id for n in others], self.args.startup_timeout)
            if missing and self.stop_requested.is_set():
                say(f"stop requested while starting (not up yet: {', '.join(missing)})")
                return self.shutdown(order)
            if missing:
                dead = [f"{i} ({describe_code(self.children[i].poll())})" for i in missing if self.children[i].poll() is not None]
                say(f"nodes not alive after start: {', '.join(missing)}" + (f"; exited: {', '.join(dead)}" if dead else f" (waited {self.args.startup_timeout:.0f} s)"))
                codes = [self.children[i].poll() for i in missing if self.children[i].poll() not in (None, 0)]
                self.first_failure = codes[0] if codes and codes[0] > 0 else 1
                return self.shutdown(order)
            say(f"all {len(others)} nodes alive; starting sources: {', '.join(n.id for n in sources) or '(none)'}")
            for n in sources:
                self.spawn(n)
            t_start = time.monotonic()
            return self.supervise(order, sources, t_start)
        finally:
            self._closing.set()
            self.bus.close()
            self._remove_auth_dir()

    def _watch_extra_links(self, endpoints: list[str]) -> None:
        """One line when the hub links to each extra connect endpoint, and one warning if, ``LINK_CHECK_S`` after the
        start, it still has no link to some of them: every node links to the hub, so the nodes' own check (the same
        grace) stays quiet while the run is cut off from the remote router or peer it was told to join. Then, for the
        whole run, one warning when a link is lost (the router stopped, the network cut: the nodes beyond it went
        without this run's messages and nothing said so but their ``no input for`` lines) and one line when it is back."""
        from stages.runtime.node import LINK_CHECK_S

        deadline = time.monotonic() + LINK_CHECK_S
        eps = list(dict.fromkeys(endpoints))
        linked: dict[str, bool] = {ep: False for ep in eps}
        ever: set[str] = set()
        lost_at: dict[str, float] = {}
        warned = False
        while not self._closing.wait(0.1 if len(ever) < len(eps) and not warned else 1.0):
            try:
                now_linked = {ep: self.bus.linked_to(ep) for ep in eps}
            except Exception:  # noqa: BLE001 - the session closing
                return
            now = time.monotonic()
            for ep in eps:
                if now_linked[ep] and not linked[ep]:
                    if ep in lost_at:
                        say(f"hub linked to --connect {ep} again after {now - lost_at.pop(ep):.0f} s without it")
                    else:
                        say(f"hub linked to --connect {ep}" + (" (after all)" if warned else ""))
                    ever.add(ep)
                elif linked[ep] and not now_linked[ep]:
                    lost_at[ep] = now
                    say(f"warning: the hub lost its link to --connect {ep}: what runs beyond it gets nothing of this run until it is"
                        " back (zenoh keeps trying; a line says when)")
                linked[ep] = now_linked[ep]
            pending = [ep for ep in eps if ep not in ever]
            if pending and not warned and now >= deadline:
                warned = True
                say(f"warning: no link after {LINK_CHECK_S:.0f} s to --connect {' '.join(pending)}: nothing listens there, or it refused"
                    " the hub (a router with bus auth that does not take the run's credentials?); the nodes have the hub, so the run"
                    " goes on without it, and zenoh keeps trying")

    @property
    def extra_connect(self) -> list[str]:
        """The endpoints to join besides the hub: the pipeline's ``[bus] connect`` and ``--connect``."""
        return list(dict.fromkeys(self.p.connect + self.args.connect))

    @property
    def node_extra_connect(self) -> list[str]:
        """What each node connects to besides the hub: the extra endpoints, except with bus auth. Then every node is a
        Zenoh client, and a client links to one router only, the first of its endpoints that takes it (measured: the
        hub, listed first, 10 of 10), so a remote router in its list could only compete with the hub for it. The hub
        links to the extra endpoints itself and forwards for every node."""
        return [] if self.p.auth is not None else self.extra_connect

    _lingering = False  # --linger: the sources finished and the run waits for Ctrl-C

    @property
    def hub_mode(self) -> str:
        """The launcher's own session: a peer, or with bus auth a router. Zenoh's peers open their links to one another
        both ways at once, and with usrpwd such a pair is refused at random (eclipse-zenoh/zenoh#2577: OpenSyn ->
        Close(INVALID)); a run then had every node alive to the launcher but 0 frames processed (1 in 4 runs here,
        3 in 7 of another tester's). With auth every node is a client of this router, which forwards everything."""
        return "router" if self.p.auth is not None else "peer"

    @property
    def node_mode(self) -> str:
        return "client" if self.p.auth is not None else self.p.mode

    def _remove_auth_dir(self) -> None:
        if self.auth_dir is not None:
            shutil.rmtree(self.auth_dir, ignore_errors=True)
            self.auth_dir = None

    def supervise(self, order: list[Any], sources: list[Any], t_start: float) -> int:
        while True:
            if self.stop_requested.is_set():
                say("stop requested")
                return self.shutdown(order)
            if self.args.stop_after is not None and time.monotonic() - t_start >= self.args.stop_after:
                say(f"--stop-after {self.args.stop_after:g} s reached")
                return self.shutdown(order)
            for nid, c in list(self.children.items()):
                if c.fatal is not None and not sources:
                    # no dataset player: the scene is a live tracker's message, not this run's configuration, so a map
                    # it names that cannot be loaded never ends the run: one line per report, and the stages wait for
                    # a scene they can load
                    say(f"{nid} reports {c.fatal}: the tracker's SceneInfo names a map this run cannot load (its maps/"
                        " folder: --data); the stages predict nothing until it publishes one they can, under a new scene_id;"
                        " the run goes on")
                    c.fatal = None
                elif c.fatal is not None:
                    say(f"stopping the run: {nid} reports {c.fatal}")
                    self.first_failure = EXIT_UNUSABLE_MAP
                    return self.shutdown(order)
                if c.finished:
                    continue
                code = c.poll()
                if code is None:
                    continue
                if c.node.kind == "source" and code == 0:
                    c.finished = True
                    say(f"source {nid} finished")
                    continue
                say(f"node {nid} died ({describe_code(code)})")
                if c.node.restart and code != 2 and c.budget.take():
                    if c.budget.last_reset:
                        say(f"{nid} had run {c.budget.last_ran_s:.0f} s since its last start (>= {c.budget.reset_after_s:g} s): restart budget reset")
                    say(f"restarting {nid} ({c.restarts}/{c.budget.limit})")
                    if c.node.stage == RECORDER_STAGE:
                        self.next_split(c)
                    c.start()
                    continue
                if c.node.restart and code != 2:
                    why = f"each run shorter than {c.budget.reset_after_s:g} s" if c.budget.reset_after_s > 0 else "--restart-reset-s 0: never given back"
                    say(f"{nid} used its {c.budget.limit} restarts ({why})")
                self.first_failure = code if code > 0 else 1
                c.finished = True
                say(f"stopping the run because {nid} failed")
                return self.shutdown(order)
            if sources and all(self.children[s.id].finished for s in sources):
                if not getattr(self.args, "linger", False):
                    say("all sources finished; draining")
                    return self.shutdown(order)
                if not self._lingering:  # the viewer (and the rest) stay up on the last frames until Ctrl-C
                    self._lingering = True
                    say("all sources finished; --linger: every node stays up (the viewer on the last frames) until Ctrl-C")
            time.sleep(0.05)

    def next_split(self, c: Child) -> None:
        """Point a recorder that died at the split after the last one this run wrote (run.mcap -> run.001.mcap -> ...)."""
        from stages.lib.recording_files import split_path, split_paths

        base = c.node.params.get("path")
        written = split_paths(base, since_s=self.started_wall_s - 1.0)
        index = written[-1][0] + 1 if written else int(c.node.params.get("split_index", 0))
        c.cmd = self.command(c.node, {**c.node.params, "split_index": index})
        say(f"recording goes on in {split_path(base, index).resolve()}" + (f" ({written[-1][1].name} is torn: `iamp recover` writes a finished copy)" if written else ""))

    def shutdown(self, order: list[Any]) -> int:
        """Stop sources first, then the rest in dataflow order; raw sinks last."""
        sinks = [n for n in order if n.kind == "raw_sink"]
        rest = [n for n in order if n.kind != "raw_sink"]
        for n in rest + sinks:
            c = self.children.get(n.id)
            if c is None or c.proc is None:
                continue
            up = n.id in self.alive
            code = c.stop(up)
            if not up and code == -signal.SIGTERM:  # ended before it came up, as asked: not a failure to stop
                code = 0
            if code not in (0, None) and not c.finished and self.first_failure is None:
                # a non-zero code on our own SIGINT is a failure to stop cleanly
                say(f"node {n.id} stopped with {describe_code(code)}")
                self.first_failure = code if code > 0 else 1
            c.finished = True
        for n in sinks:
            if n.stage == RECORDER_STAGE:
                self.report_recording(n.params.get("path"))
        code = self.first_failure or 0
        say(f"run ended: exit code {code}")
        return code

    def report_recording(self, path: str | None) -> None:
        """One line per split file this run wrote."""
        from stages.lib.recording_files import split_paths

        files = [p for _, p in split_paths(path, since_s=self.started_wall_s - 1.0)] if path else []
        if not files:
            say(f"recording {path}: no file written")
            return
        per_topic: collections.Counter[str] = collections.Counter()
        for f in files:
            try:
                from stages.recorder.inspect import inspect, summary_counts

                quick = summary_counts(str(f))  # a finished file: its summary's counts (reading it all took 5 s a GB)
                if quick is not None:
                    per_topic.update(quick["per_topic"])
                    say(f"recording saved: {f.resolve()} ({quick['messages']} messages, {quick['channels']} channels)")
                    continue
                info = inspect(str(f))
                per_topic.update({c["topic"]: c["count"] for c in info.get("channels", [])})
                torn = f"; cut short, `iamp recover {f.resolve()}` writes a finished copy" if info.get("truncated") else ""
                say(f"recording saved: {f.resolve()} ({info.get('messages', '?')} messages, {len(info.get('channels', []))} channels{torn})")
            except Exception as exc:  # a report must never turn a good run into a failure
                say(f"recording saved: {f.resolve()} (could not inspect: {exc})")
        line = predicted_line(per_topic)
        if line:
            say(line)
            if lost_share(per_topic) > LOSS_TO_EXPLAIN and (why := self.stats.diagnosis(self.paced_at_max)):
                say(why)


def code_path(environ: Mapping[str, str]) -> str:
    """``PYTHONPATH`` for the nodes: the folder this launcher's own ``stages`` package is in, first, so that the nodes
    run the launcher's code. They start as ``python -m stages.X`` in the caller's folder: another checkout's
    ``launch.py`` ran its launcher with the nodes of whichever package the interpreter or the folder held."""
    import stages

    root = Path(stages.__file__).resolve().parents[1]
    rest = [p for p in environ.get("PYTHONPATH", "").split(os.pathsep) if p and p != str(root)]
    if root.name in ("site-packages", "dist-packages"):  # an install: the nodes find it there anyway (and a whole
        return os.pathsep.join(rest)  # site-packages ahead of the standard library could shadow it)
    return os.pathsep.join([str(root), *rest])


#: ``wait_alive`` waits for a node that keeps using CPU at most this many times ``--startup-timeout``
STARTUP_CAP_FACTOR = 10


def _cpu_seconds(pid: int) -> float | None:
    """The CPU time (user + system, s) process ``pid`` has used, from /proc (None where there is none: not Linux, gone)."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            fields = f.read().rsplit(b")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return None


def _frames_and_grids(per_topic: dict[str, int]) -> tuple[int, dict[str, int]]:
    """The recorded source frames, and the MotionGrids recorded per producing node."""
    frames = sum(n for topic, n in per_topic.items() if topic.endswith("/track_frame"))
    return frames, {topic.split("/")[-2]: n for topic, n in per_topic.items() if topic.endswith("/motion_grid")}


def lost_share(per_topic: dict[str, int]) -> float:
    """The share of the recorded source frames that the node with the fewest MotionGrids has none for (0 without)."""
    frames, grids = _frames_and_grids(per_topic)
    return max(0.0, 1.0 - min(grids.values()) / frames) if frames and grids else 0.0


def predicted_line(per_topic: dict[str, int]) -> str:
    """How many of the recorded source frames got a MotionGrid, per producing node: the frames a loaded machine lost
    (queue, stale and join drops), a restart or a lost link cost showed only in the nodes' counters and logs; a fused
    grid (grid_fusion) counts though a shard's vehicles may be missing from it. '' without frames or grids in the
    recording."""
    frames, grids = _frames_and_grids(per_topic)
    if not frames or not grids:
        return ""
    parts = [f"{node} {n} ({n / frames:.1%})" for node, n in sorted(grids.items())]
    lost = max(frames - n for n in grids.values())
    return (f"predicted: {frames} track frames recorded, MotionGrids of " + ", ".join(parts)
            + (f"; up to {lost} frames without one: the nodes' queue_drops, stale_drops and join_drops above say where, or a node"
               " that restarted or lost its inputs (its 'restarting' and 'no input for' lines)" if lost > 0 else "")
            + ("; grid_fusion publishes a frame with a shard missing too: its shard_missing says how many" if "grid_fusion" in grids else ""))


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.stop_after is not None and not (math.isfinite(args.stop_after) and args.stop_after > 0):
        print(f"launch.py: --stop-after {args.stop_after}: must be a finite number of seconds > 0", file=sys.stderr)
        return 2
    if not (math.isfinite(args.startup_timeout) and args.startup_timeout > 0):
        print(f"launch.py: --startup-timeout {args.startup_timeout}: must be a finite number of seconds > 0", file=sys.stderr)
        return 2
    if args.max_restarts < 0 or not (math.isfinite(args.restart_reset_s) and args.restart_reset_s >= 0):
        print("launch.py: --max-restarts and --restart-reset-s must be >= 0 (and finite)", file=sys.stderr)
        return 2
    try:
        variables = {}
        for item in args.var:
            if "=" not in item:
                raise PipelineError(f"--var {item!r}: expected NAME=VALUE")
            k, v = item.split("=", 1)
            variables[k.strip()] = _toml_value(v.strip())
        pipeline = load_pipeline(resolve_pipeline_arg(args.pipeline), variables=variables, overrides=parse_overrides(args.set), edit=make_editor(args))
        if not args.describe:
            preflight(pipeline)
    except (PipelineError, ConfigError) as exc:
        print(f"launch.py: {exc}", file=sys.stderr)
        return 2
    unread = [w for w in pipeline.warnings if w.endswith(" is not connected to any node")] if args.no_record else []
    for w in pipeline.warnings:
        if w not in unread:
            say(f"warning: {w}")
    if unread:  # what only the recorder read, now left out as asked: not a mistake in the pipeline
        say("without the recorder (--no-record) no node reads " + ", ".join(w.split()[1] for w in unread))
    if args.describe:
        print(pipeline.describe())
        return 0
    if args.check:
        say(f"pipeline {pipeline.path} is valid: {len(pipeline.nodes)} nodes")
        return 0
    hub = resolve_hub(pipeline, args.listen)
    try:
        return Launcher(pipeline, hub, args).run()
    except ConfigError as exc:  # the hub's session: a bad --listen/--connect endpoint, a port in use
        print(f"launch.py: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
