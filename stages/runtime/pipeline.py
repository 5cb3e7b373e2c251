"""Pipeline descriptors: load a TOML file, substitute variables, validate.

A descriptor is data (dora-style) and is fully validated before anything is
spawned::

    name = "hybrid"
    [vars]
    SPEED = 1.0
    [bus]
    run_id = "demo"            # keys live under iamp/<run_id>/
    mode = "peer"
    listen = ["tcp/127.0.0.1:0"]   # the launcher's hub; 0 = a free port
    connect = []                   # a remote router to join, if any
    [bus.auth]                     # optional: Zenoh user/password authentication on every link
    user = "iamp"
    password_env = "IAMP_BUS_PASSWORD"   # or password = "..." (then keep the file private)
    [[nodes]]
    id = "corridors"
    stage = "stages.corridors"
    inputs = { track_frame = "source/track_frame", scene = "source/scene" }
    params = { }
    restart = true                 # default: the stage's (true for operators and the recorder, false for sources)
    queue_size = 256               # optional
    max_age_s = 1.0                # optional: skip joined inputs that waited longer (a newer one queued); live pipelines

Outputs of processes that the launcher does not start (a live tracker) are
declared with their schema so that edges to them can be checked::

    [external]
    "tracker/track_frame" = "iamp.TrackFrame"

``${VAR}`` (from ``[vars]`` or ``--var``) is the only substitution; a whole
string ``"${VAR}"`` takes the variable's type. A ``--var`` that the file
neither declares in ``[vars]`` nor uses is an error (a misspelt name would
otherwise be ignored). An input ``port = "node/output"``
names the key suffix ``iamp/<run>/node/output`` literally. Stage modules expose
``SPEC`` (a ``stages.runtime.StageSpec``); types are not restated here: each
edge must join outputs and inputs of the same message schema.
"""

from __future__ import annotations

import copy
import importlib
import json
import math
import os
import re
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from bus_schemas import keys

from stages.lib.base import ConfigError
from stages.runtime.ports import MAX_NICE

TOP_KEYS = {"name", "vars", "bus", "nodes", "description", "external"}
BUS_KEYS = {"run_id", "mode", "listen", "connect", "auth"}
AUTH_KEYS = {"user", "password", "password_env"}
PASSWORD_IN_FILE = "the pipeline file"  # BusAuth.source of a literal [bus.auth] password
SECRET_PARAMS = {"stages.viewer": ("token",)}  # node parameters never printed nor put on a command line
NODE_KEYS = {"id", "stage", "inputs", "outputs", "params", "restart", "queue_size", "max_age_s", "description", "nice"}
_VAR_RE = re.compile(r"\$\{([A-Za-z_][A-Za-z0-9_]*)\}")


class PipelineError(ConfigError):
    """A descriptor that cannot run; the message says what to fix."""


@dataclass(frozen=True)
class BusAuth:
    """Zenoh user/password authentication (``transport/auth/usrpwd``) for every session of a run."""

    user: str
    password: str = field(repr=False)
    source: str  # where the password came from, for messages: "password_env IAMP_BUS_PASSWORD" or "password"

    def describe(self) -> str:
        return f"usrpwd(user={self.user}, password from {self.source})"


def parse_auth(value: Any, where: str) -> BusAuth | None:
    """``[bus.auth]`` -> ``BusAuth``; a message that says what to fix for anything else."""
    if value is None:
        return None
    if not isinstance(value, dict):
        raise PipelineError(f"{where}: [bus] auth must be a table: [bus.auth] user = \"...\", password_env = \"NAME\"")
    bad = sorted(set(value) - AUTH_KEYS)
    if bad:
        raise PipelineError(f"{where}: unknown key(s) in [bus.auth]: {', '.join(bad)}; known: {', '.join(sorted(AUTH_KEYS))}")
    user = value.get("user")
    if not isinstance(user, str) or not user.strip():
        raise PipelineError(f"{where}: [bus.auth] user must be a non-empty string (the Zenoh user name every node authenticates with)")
    if any(c in user for c in ":\n\r") or user != user.strip():
        raise PipelineError(f"{where}: [bus.auth] user {user!r} must not contain ':', line breaks or surrounding spaces")
    has_pw, has_env = "password" in value, "password_env" in value
    if has_pw == has_env:
        raise PipelineError(f"{where}: [bus.auth] needs exactly one of password_env = \"NAME\" (an environment variable) or password = \"...\"")
    if has_env:
        name = value["password_env"]
        if not isinstance(name, str) or not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", name):
            raise PipelineError(f"{where}: [bus.auth] password_env must name an environment variable, got {name!r}")
        password, source = os.environ.get(name, ""), f"${name}"
        if not password:
            raise PipelineError(f"{where}: [bus.auth] password_env = {name!r}: set the environment variable {name} to the bus password")
    else:
        password, source = value["password"], PASSWORD_IN_FILE
        if not isinstance(password, str) or not password:
            raise PipelineError(f"{where}: [bus.auth] password must be a non-empty string (or use password_env = \"NAME\")")
    if any(c in password for c in "\n\r"):
        raise PipelineError(f"{where}: [bus.auth] the password ({source}) must not contain line breaks")
    return BusAuth(user=user, password=password, source=source)


def readable_password_warning(path: Path, auth: BusAuth | None) -> str | None:
    """The warning for a pipeline file that holds the bus password itself (``[bus.auth] password = "..."``) while other
    users may read it (group or others have read permission: mode & 0o044); None otherwise. It warns, the run goes on."""
    if auth is None or auth.source != PASSWORD_IN_FILE:
        return None
    try:
        mode = path.stat().st_mode & 0o777
    except OSError:
        return None
    if not mode & 0o044:
        return None
    return (f"{path} holds the bus password ([bus.auth] password) and other users can read it (mode {mode:04o}): chmod 600 {path},"
            " or put the password in an environment variable named by [bus.auth] password_env = \"NAME\" instead")


def public_params(stage: str, params: dict[str, Any]) -> dict[str, Any]:
    """``params`` with secret values (the viewer's token) replaced by ``"***"``, for printing."""
    secret = SECRET_PARAMS.get(stage, ())
    return {k: ("***" if k in secret and v else v) for k, v in params.items()}


@dataclass
class NodeDesc:
    id: str
    stage: str
    spec: Any
    inputs: dict[str, str]
    params: dict[str, Any]
    config: Any
    restart: bool
    queue_size: int | None
    description: str = ""
    max_age_s: float | None = None  # an operator's inputs bounded in age (``--max-age-s``), None: not
    nice: int = 0  # the node's CPU niceness (``--nice``): the pipeline's ``nice``, else its stage's ``nice_default``

    @property
    def kind(self) -> str:
        return self.spec.kind


@dataclass
class Pipeline:
    name: str
    path: str
    run_id: str
    mode: str
    listen: list[str]
    connect: list[str]
    nodes: list[NodeDesc]
    warnings: list[str] = field(default_factory=list)
    external: dict[str, str] = field(default_factory=dict)
    auth: BusAuth | None = None

    def node(self, node_id: str) -> NodeDesc:
        for n in self.nodes:
            if n.id == node_id:
                return n
        raise KeyError(node_id)

    def output_key(self, node_id: str, output: str) -> str:
        return keys.data_key(self.run_id, node_id, output)

    def topo_order(self) -> list[NodeDesc]:
        """Nodes ordered so that every node comes after the nodes feeding it."""
        done: list[NodeDesc] = []
        seen: set[str] = set()
        remaining = list(self.nodes)
        while remaining:
            progressed = False
            for n in list(remaining):
                deps = {ref.split("/")[0] for ref in n.inputs.values() if ref not in self.external}
                if deps <= seen | {n.id}:
                    done.append(n)
                    seen.add(n.id)
                    remaining.remove(n)
                    progressed = True
            if not progressed:  # a cycle: keep file order for the rest
                done.extend(remaining)
                break
        return done

    def describe(self) -> str:
        lines = [f"pipeline {self.name} ({self.path})", f"  bus: run_id={self.run_id} mode={self.mode} listen={self.listen} connect={self.connect}"
                 + (f" auth={self.auth.describe()}" if self.auth else "")]
        for n in self.topo_order():
            lines.append(f"  node {n.id}: stage={n.stage} kind={n.kind} restart={str(n.restart).lower()}"
                         + (f" queue_size={n.queue_size}" if n.queue_size else "") + (f" max_age_s={n.max_age_s:g}" if n.max_age_s else "")
                         + (f" nice={n.nice}" if n.nice else ""))
            for port, ref in n.inputs.items():
                p = n.spec.inputs[port]
                lines.append(f"    in  {port:<14} <- iamp/{self.run_id}/{ref}  [{p.schema.SCHEMA} v{p.schema.VERSION}{', ' + p.kind_label() if p.kind_label() else ''}]")
            for port, p in n.spec.inputs.items():
                if p.pattern is not None:  # bound by the runtime
                    lines.append(f"    in  {port:<14} <- iamp/{self.run_id}/{p.pattern}  [{p.schema.SCHEMA} v{p.schema.VERSION}, wildcard]")
            for port, p in n.spec.outputs.items():
                lines.append(f"    out {port:<14} -> {self.output_key(n.id, port)}  [{p.schema.SCHEMA} v{p.schema.VERSION}{', latched' if p.latched else ''}]")
            lines.append(f"    params {json.dumps(public_params(n.stage, n.params), sort_keys=True)}")
        for w in self.warnings:
            lines.append(f"  warning: {w}")
        return "\n".join(lines)


def _referenced(value: Any) -> set[str]:
    """The names of the ``${NAME}`` variables used anywhere in ``value`` (a descriptor's tables, lists and strings)."""
    if isinstance(value, str):
        return set(_VAR_RE.findall(value))
    if isinstance(value, list):
        return set().union(*(_referenced(v) for v in value))
    if isinstance(value, dict):
        return set().union(*(_referenced(v) for v in value.values()))
    return set()


def _substitute(value: Any, variables: dict[str, Any], where: str) -> Any:
    if isinstance(value, str):
        whole = _VAR_RE.fullmatch(value)
        if whole:
            name = whole.group(1)
            if name not in variables:
                raise PipelineError(f"{where}: unknown variable ${{{name}}}; defined: {', '.join(sorted(variables)) or '(none)'}")
            return copy.deepcopy(variables[name])

        def rep(m: re.Match) -> str:
            if m.group(1) not in variables:
                raise PipelineError(f"{where}: unknown variable ${{{m.group(1)}}}; defined: {', '.join(sorted(variables)) or '(none)'}")
            return str(variables[m.group(1)])

        return _VAR_RE.sub(rep, value)
    if isinstance(value, list):
        return [_substitute(v, variables, where) for v in value]
    if isinstance(value, dict):
        return {k: _substitute(v, variables, f"{where}.{k}") for k, v in value.items()}
    return value


def _load_stage(stage: str, where: str) -> Any:
    if not re.fullmatch(r"stages\.[a-z_][a-z0-9_.]*", stage):
        raise PipelineError(f"{where}: stage {stage!r} is not a module under stages. (e.g. stages.corridors)")
    try:
        mod = importlib.import_module(stage)
    except ModuleNotFoundError as exc:
        raise PipelineError(f"{where}: unknown stage {stage!r} ({exc})") from None
    spec = getattr(mod, "SPEC", None)
    if spec is None:
        raise PipelineError(f"{where}: module {stage} is not a stage (it has no SPEC)")
    return spec


#: Parameters that a node and the node it reads from must agree on where both have them: the chain's input cells
#: (ar_inference's AccelerationProfiles are over markov_prediction's cells, docs/method.md §2.3).
SHARED_PARAMS = ("input_min_mps2", "input_max_mps2", "n_inputs")


def load_pipeline(
    path: str | Path,
    *,
    variables: dict[str, Any] | None = None,
    overrides: dict[str, dict[str, Any]] | None = None,
    edit: Any = None,
) -> Pipeline:
    """Read and validate a descriptor.

    ``overrides`` maps node id to parameter overrides (``--set node.key=v``).
    ``edit`` is an optional callable ``edit(raw_dict)`` applied after variable
    substitution and before validation (the launcher's --data/--record flags).
    """
    path = Path(path)
    where = str(path)
    try:
        raw = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise PipelineError(f"pipeline file {path} does not exist") from None
    except IsADirectoryError:
        raise PipelineError(f"pipeline file {path} is a folder; expected a pipeline TOML file (shipped: stages/pipelines/*.toml)") from None
    except UnicodeDecodeError:
        raise PipelineError(f"{where}: not a text file, so not a pipeline TOML file (a recording? `python launch.py replay --var FILE={path}` plays one)") from None
    except OSError as exc:
        raise PipelineError(f"pipeline file {path}: cannot be read ({exc.strerror or exc})") from None
    except tomllib.TOMLDecodeError as exc:
        raise PipelineError(f"{where}: not valid TOML: {exc}") from None
    unknown = sorted(set(raw) - TOP_KEYS)
    if unknown:
        raise PipelineError(f"{where}: unknown top-level key(s) {', '.join(unknown)}; known: {', '.join(sorted(TOP_KEYS))}")
    var_table = dict(raw.get("vars", {}))
    known = set(var_table) | _referenced(raw)
    stray = sorted(set(variables or {}) - known)
    if stray:  # a misspelt --var would otherwise be ignored, and the run go on without it
        raise PipelineError(f"{where}: no variable {', '.join(stray)} in this pipeline (--var); its variables: {', '.join(sorted(known)) or '(none)'}")
    var_table.update(variables or {})
    raw = {k: v for k, v in raw.items() if k != "vars"}
    raw = _substitute(raw, var_table, where)
    if isinstance(raw.get("external"), dict):  # its keys name outputs ("${GRIDS}/motion_grid"): variables there too
        raw["external"] = {_substitute(k, var_table, f"{where}: [external]"): v for k, v in raw["external"].items()}
    if edit is not None:
        edit(raw)
    bus = raw.get("bus", {})
    bad = sorted(set(bus) - BUS_KEYS)
    if bad:
        raise PipelineError(f"{where}: unknown key(s) in [bus]: {', '.join(bad)}; known: {', '.join(sorted(BUS_KEYS))}")
    run_id = bus.get("run_id", raw.get("name", "demo"))
    try:
        keys.check_run_id(run_id)
    except ValueError as exc:
        raise PipelineError(f"{where}: [bus] {exc}") from None
    mode = bus.get("mode", "peer")
    if mode not in ("peer", "client"):
        raise PipelineError(f"{where}: [bus] mode must be 'peer' or 'client', got {mode!r}")
    listen = list(bus.get("listen", ["tcp/127.0.0.1:0"]))
    connect = list(bus.get("connect", []))
    auth = parse_auth(bus.get("auth"), where)
    nodes_raw = raw.get("nodes")
    if not isinstance(nodes_raw, list) or not nodes_raw:
        raise PipelineError(f"{where}: no [[nodes]] defined")

    overrides = {k: dict(v) for k, v in (overrides or {}).items()}
    nodes: list[NodeDesc] = []
    ids: set[str] = set()
    for i, nd in enumerate(nodes_raw):
        nwhere = f"{where}: node #{i + 1}"
        if not isinstance(nd, dict):
            raise PipelineError(f"{nwhere}: must be a table")
        nid = nd.get("id")
        if not isinstance(nid, str):
            raise PipelineError(f"{nwhere}: missing 'id'")
        try:
            keys.check_name(nid, "node id")
        except ValueError as exc:
            raise PipelineError(f"{nwhere}: {exc}") from None
        nwhere = f"{where}: node {nid}"
        if nid in ids:
            raise PipelineError(f"{nwhere}: duplicate node id {nid!r}")
        ids.add(nid)
        bad = sorted(set(nd) - NODE_KEYS)
        if bad:
            raise PipelineError(f"{nwhere}: unknown key(s) {', '.join(bad)}; known: {', '.join(sorted(NODE_KEYS))}")
        stage = nd.get("stage")
        if not isinstance(stage, str):
            raise PipelineError(f"{nwhere}: missing 'stage' (a module such as stages.corridors)")
        spec = _load_stage(stage, nwhere)
        params = dict(nd.get("params", {}))
        params.update(overrides.pop(nid, {}))
        try:
            config = spec.config_cls.from_params(params, where=nwhere)
        except ConfigError as exc:
            raise PipelineError(str(exc)) from None
        inputs = nd.get("inputs", {})
        if not isinstance(inputs, dict):
            raise PipelineError(f"{nwhere}: 'inputs' must be a table {{port = \"node/output\"}}")
        declared_outputs = nd.get("outputs")
        if declared_outputs is not None:
            missing = sorted(set(declared_outputs) - set(spec.outputs))
            if missing:
                raise PipelineError(
                    f"{nwhere}: declares output(s) {', '.join(missing)} that stage {stage} does not have; it has: {', '.join(spec.outputs) or '(none)'}"
                )
        restart = nd.get("restart", spec.restart_default)
        if not isinstance(restart, bool):
            raise PipelineError(f"{nwhere}: 'restart' must be true or false")
        qs = nd.get("queue_size")
        if qs is not None and (type(qs) is not int or qs < 1):
            raise PipelineError(f"{nwhere}: 'queue_size' must be a positive integer")
        age = nd.get("max_age_s")
        if age is not None and (type(age) not in (int, float) or not math.isfinite(age) or age <= 0):
            raise PipelineError(f"{nwhere}: 'max_age_s' must be a number of seconds > 0")
        if age is not None and spec.kind != "operator":
            raise PipelineError(f"{nwhere}: 'max_age_s' applies to processing stages only (stage {stage} is a {spec.kind})")
        nice = nd.get("nice", spec.nice_default)
        if type(nice) is not int or not 0 <= nice <= MAX_NICE:
            raise PipelineError(f"{nwhere}: 'nice' must be an integer from 0 (as started) to {MAX_NICE} (the lowest CPU priority), got {nice!r}")
        nodes.append(NodeDesc(nid, stage, spec, dict(inputs), params, config, restart, qs, nd.get("description", ""),
                              float(age) if age is not None else None, nice))

    if overrides:
        raise PipelineError(f"{where}: --set names unknown node(s) {', '.join(sorted(overrides))}; nodes: {', '.join(n.id for n in nodes)}")

    external = raw.get("external", {})
    if not isinstance(external, dict):
        raise PipelineError(f"{where}: [external] must map \"node/output\" to a schema name")
    from bus_schemas import REGISTRY

    for ref, schema in external.items():
        if ref.count("/") != 1 or schema not in REGISTRY:
            raise PipelineError(
                f"{where}: [external] {ref!r} = {schema!r}: expected \"node/output\" = one of {', '.join(sorted(REGISTRY))}"
            )
        if ref.split("/")[0] in ids:
            raise PipelineError(f"{where}: [external] {ref!r} names node {ref.split('/')[0]!r}, which the pipeline starts itself")

    by_id = {n.id: n for n in nodes}
    used_outputs: set[tuple[str, str]] = set()
    for n in nodes:
        nwhere = f"{where}: node {n.id}"
        for port, ref in n.inputs.items():
            if port not in n.spec.inputs:
                raise PipelineError(f"{nwhere}: stage {n.stage} has no input port {port!r}; its inputs: {', '.join(n.spec.inputs) or '(none)'}")
            if n.spec.inputs[port].pattern is not None:
                raise PipelineError(f"{nwhere}: input {port} is a wildcard input on iamp/<run>/{n.spec.inputs[port].pattern}; the runtime binds it, remove it from inputs")
            if not isinstance(ref, str) or ref.count("/") != 1:
                raise PipelineError(f"{nwhere}: input {port} = {ref!r}: expected \"node/output\"")
            src_id, out = ref.split("/")
            if ref in external:
                if external[ref] != n.spec.inputs[port].schema.SCHEMA:
                    raise PipelineError(f"{nwhere}: input {port} wants {n.spec.inputs[port].schema.SCHEMA} but external {ref} carries {external[ref]}")
                continue
            if src_id not in by_id:
                raise PipelineError(f"{nwhere}: input {port} = {ref!r}: does node {src_id!r} exist? nodes: {', '.join(by_id)}")
            src = by_id[src_id]
            if out not in src.spec.outputs:
                raise PipelineError(
                    f"{nwhere}: input {port} = {ref!r}: does node {src_id} declare output {out!r}? it has: {', '.join(src.spec.outputs) or '(none)'}"
                )
            want, have = n.spec.inputs[port], src.spec.outputs[out]
            if want.schema.SCHEMA != have.schema.SCHEMA:
                raise PipelineError(
                    f"{nwhere}: input {port} wants {want.schema.SCHEMA} but {ref} carries {have.schema.SCHEMA}"
                )
            shared = [k for k in SHARED_PARAMS if hasattr(n.config, k) and hasattr(src.config, k) and getattr(n.config, k) != getattr(src.config, k)]
            if shared:
                raise PipelineError(f"{nwhere}: input {port} = {ref!r}: " + ", ".join(
                    f"{k} = {getattr(n.config, k)!r} here but {getattr(src.config, k)!r} in {src_id}" for k in shared)
                    + " (a message over other cells would be ignored): set them alike on both nodes")
            used_outputs.add((src_id, out))
        if n.kind == "operator":
            missing = [p for p, port in n.spec.inputs.items() if p not in n.inputs and port.needs_binding]
            if missing:
                raise PipelineError(f"{nwhere}: input port(s) {', '.join(missing)} not connected (add inputs = {{ {missing[0]} = \"node/output\" }})")
    for n in nodes:  # the stage's own rules on how it is bound (StageSpec.check_sources)
        check = getattr(n.spec, "check_sources", None)
        if check is not None:
            sources = {port: (ref.split("/")[0], None if ref in external else by_id[ref.split("/")[0]].config) for port, ref in n.inputs.items()}
            try:
                check(sources)
            except ValueError as exc:
                raise PipelineError(f"{where}: node {n.id}: {exc}") from None
    warnings = []
    exposed = readable_password_warning(path, auth)
    if exposed:
        warnings.append(exposed)
    has_raw_sink = any(n.kind == "raw_sink" for n in nodes)
    for n in nodes:
        for out in n.spec.outputs:
            if (n.id, out) not in used_outputs and not has_raw_sink:
                warnings.append(f"output {n.id}/{out} is not connected to any node")
    return Pipeline(
        name=str(raw.get("name", path.stem)), path=str(path), run_id=run_id, mode=mode, listen=listen, connect=connect, nodes=nodes, warnings=warnings,
        external=dict(external), auth=auth,
    )
