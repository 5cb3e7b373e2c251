"""What a stage declares: its ports (``Port``), its ``StageSpec``, the ``NodeContext`` its core gets, and the core protocols.

Input ports come in four kinds; the node loop (``node.py``) treats them so:

- **joined** (the default, ``Port(Schema)``): part of the bounded join on
  ``header.stamp_ns``; the core runs once per complete set of joined inputs;
- **latched** (``Port(Schema, latched=True)``, for an input bound to a
  latched output such as the scene): queried at start, not joined; updates
  wait until it has arrived, then the core sees its latest value with every
  update;
- **latest-value** (``Port(Schema, latest=True)``): not joined, not
  queried; the node keeps only the newest decoded message of the port and
  the core sees it with every update, from the first one on (absent from
  the inputs until then). It never holds an update back;
- **wildcard** (``Port(Schema, pattern="_stats/*")``): bound by the runtime
  itself to the key expression ``iamp/<run>/<pattern>`` (never by a
  pipeline or ``--input``). The core sees ``inputs[port]``: a read-only
  mapping from each full key (``iamp/<run>/_stats/corridors``) to the newest
  message decoded on it, from the first message on (absent until then). Like
  a latest-value port it is not joined and never holds an update back; at
  most ``max_keys`` keys are kept (new keys beyond are dropped and counted
  as ``rejected_keys``), so a flood of invented keys cannot grow the node.

Updates are triggered by complete joined sets; a stage with no joined input
bound (only latched, latest-value or wildcard ones) is run on every message
of its non-latched inputs instead.

On outputs only ``latched`` means something: the last payload is kept and
answered to queries, so a stage that (re)starts late still gets it.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any, Callable, Iterator, Mapping, Protocol

from bus_schemas import keys
from bus_schemas._wire import Message

from stages.lib.base import Issue, StageResult

#: Default bound on the keys a wildcard input keeps.
WILDCARD_MAX_KEYS = 1024


@dataclass(frozen=True, slots=True)
class Port:
    """A named input or output carrying one message class (the kinds: module docstring).

    ``latched``: an output whose last value is kept and answered to queries;
    an input that takes such an output, queried at start and not joined.
    ``latest``: an input that is not joined; the core sees its newest value.
    ``pattern``: a wildcard input on ``iamp/<run>/<pattern>``; the core sees
    ``{key: newest message}`` (at most ``max_keys`` keys).
    ``optional``: an input that a pipeline may leave unbound.
    """

    schema: type[Message]
    latched: bool = False
    optional: bool = False
    latest: bool = False
    pattern: str | None = None
    max_keys: int = WILDCARD_MAX_KEYS

    def __post_init__(self) -> None:
        if self.latest and self.latched:
            raise ValueError("Port: latest=True and latched=True exclude each other (a latched input already gives the latest value, and waits for it)")
        if self.pattern is not None:
            if self.latched or self.latest:
                raise ValueError("Port: a wildcard (pattern) input cannot also be latched or latest (it always gives the newest value per key)")
            check_pattern(self.pattern)
            if self.max_keys < 1:
                raise ValueError(f"Port: max_keys must be >= 1, got {self.max_keys}")

    @property
    def joined(self) -> bool:
        """Whether this input takes part in the stamp join."""
        return not (self.latched or self.latest or self.pattern is not None)

    @property
    def needs_binding(self) -> bool:
        """Whether a pipeline must bind this input (wildcard inputs are bound by the runtime)."""
        return self.pattern is None and not self.optional

    def kind_label(self) -> str:
        """``latched``, ``latest``, ``wildcard`` or ``""`` (joined), for listings."""
        return "latched" if self.latched else "latest" if self.latest else "wildcard" if self.pattern is not None else ""


def check_pattern(pattern: str) -> str:
    """A wildcard port's pattern: chunks relative to ``iamp/<run>/``, each a name, ``*`` or ``**``."""
    chunks = str(pattern).split("/")
    if not pattern or any(not c for c in chunks):
        raise ValueError(f"Port: pattern {pattern!r}: expected chunks such as '_stats/*' (relative to iamp/<run>/, no empty chunk)")
    for c in chunks:
        if c in ("*", "**") or c in keys.INFRA_CHUNKS:
            continue
        keys.check_name(c, "pattern chunk")
    return pattern


def pattern_key(run_id: str, pattern: str) -> str:
    """The key expression a wildcard input subscribes to."""
    return f"{keys.ROOT}/{keys.check_run_id(run_id)}/{check_pattern(pattern)}"


class OperatorCore(Protocol):
    def update(self, inputs: Mapping[str, Message]) -> StageResult: ...


class SourceCore(Protocol):
    def __iter__(self) -> Iterator[tuple[int, StageResult]]: ...


class RawSinkCore(Protocol):
    def handle(self, key: str, payload: bytes, recv_ns: int) -> list[Issue] | None: ...

    def close(self) -> None: ...


@dataclass(frozen=True)
class NodeContext:
    """What a core factory gets besides its config."""

    run_id: str
    node_id: str
    stage: str
    log: logging.Logger
    input_keys: Mapping[str, str] = field(default_factory=dict)
    output_keys: Mapping[str, str] = field(default_factory=dict)


#: the largest niceness (Linux's lowest CPU priority) of ``StageSpec.nice_default``, a pipeline's ``nice`` and
#: ``--nice``; a node only ever lowers its own priority, which needs no privilege
MAX_NICE = 19


@dataclass(frozen=True)
class StageSpec:
    """Everything the runtime needs to know about a stage.

    ``kind`` is ``"source"`` (no inputs; the core is iterable and yields
    ``(stamp_ns, StageResult)``), ``"operator"`` (the core has ``update``) or
    ``"raw_sink"`` (no typed inputs; receives every payload of the run as raw
    bytes: the recorder).

    ``preflight(config)``, where a stage has one, checks what its start would
    fail on at once (an input file or recording that is not there, an output
    that must not be replaced) without doing the work: the launcher runs it
    for every node before any starts (and for ``--check``), so that such a
    mistake is one line and exit 2, not a run torn down seconds later. It
    raises ``ConfigError``.

    ``check_sources(sources)``, where a stage has one, checks how a pipeline
    binds it, beyond each port's schema: ``sources`` maps each bound input
    port to (the source node's id, its configuration; None for an
    ``[external]`` output). The pipeline loader calls it (so ``--check`` and
    every launch); it raises ``ValueError`` saying what to fix (grid_fusion:
    shards that add up to every vehicle once).

    ``nice_default`` is the CPU niceness (0-19, ``os.nice``) a node of the
    stage takes before it starts, unless the pipeline or ``--nice`` says
    otherwise: 10 for the observers (viewer, Foxglove bridge), whose
    decoding and drawing must not take CPU from the prediction stages when
    the cores are short (on 2 cores the viewer cost the MotionGrid 1-3 ms at
    p50 at 18 vehicles with no page open, the lower priority about half of
    it back: docs/performance.md, "Session 45"); 0 for the rest.
    """

    stage: str
    config_cls: type
    make_core: Callable[[Any, NodeContext], Any]
    inputs: Mapping[str, Port]
    outputs: Mapping[str, Port]
    kind: str = "operator"
    restart_default: bool = True
    nice_default: int = 0
    preflight: Callable[[Any], None] | None = None
    check_sources: Callable[[Mapping[str, tuple[str, Any]]], None] | None = None
