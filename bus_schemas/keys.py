"""Zenoh key expressions of hybrid-iamp, built and checked in one place.

Layout::

    iamp/<run>/<node>/<output>     data published by a node
    iamp/<run>/_alive/<node>       liveliness token of a node
    iamp/<run>/_stats/<node>       periodic NodeStats of a node
    iamp/<run>/_ack/<node>         Progress of a node (last stamp processed)
    iamp/<run>/**                  everything of a run (what the recorder takes)

Run ids are lowercase ``[a-z0-9][a-z0-9_-]*``; node ids and output names are
snake_case ``[a-z][a-z0-9_]*``. Infrastructure chunks start with ``_`` and
can therefore never clash with a node id.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

ROOT = "iamp"
ALIVE = "_alive"
STATS = "_stats"
ACK = "_ack"
INFRA_CHUNKS = (ALIVE, STATS, ACK)

_RUN_RE = re.compile(r"^[a-z0-9][a-z0-9_-]{0,63}$")
_NAME_RE = re.compile(r"^[a-z][a-z0-9_]{0,63}$")


class KeyFormatError(ValueError):
    """A run id, node id, output name or key that does not follow the layout."""


def check_run_id(run_id: str) -> str:
    if not isinstance(run_id, str) or not _RUN_RE.match(run_id):
        raise KeyFormatError(f"run id {run_id!r} is not valid: use lowercase letters, digits, '_' or '-' (at most 64)")
    return run_id


def check_name(name: str, what: str = "name") -> str:
    if not isinstance(name, str) or not _NAME_RE.match(name):
        raise KeyFormatError(f"{what} {name!r} is not valid: use snake_case [a-z][a-z0-9_]* (at most 64)")
    return name


def data_key(run_id: str, node_id: str, output: str) -> str:
    return f"{ROOT}/{check_run_id(run_id)}/{check_name(node_id, 'node id')}/{check_name(output, 'output name')}"


def alive_key(run_id: str, node_id: str) -> str:
    return f"{ROOT}/{check_run_id(run_id)}/{ALIVE}/{check_name(node_id, 'node id')}"


def stats_key(run_id: str, node_id: str) -> str:
    return f"{ROOT}/{check_run_id(run_id)}/{STATS}/{check_name(node_id, 'node id')}"


def ack_key(run_id: str, node_id: str) -> str:
    return f"{ROOT}/{check_run_id(run_id)}/{ACK}/{check_name(node_id, 'node id')}"


def run_pattern(run_id: str) -> str:
    return f"{ROOT}/{check_run_id(run_id)}/**"


def alive_pattern(run_id: str) -> str:
    return f"{ROOT}/{check_run_id(run_id)}/{ALIVE}/*"


def stats_pattern(run_id: str) -> str:
    return f"{ROOT}/{check_run_id(run_id)}/{STATS}/*"


def ack_pattern(run_id: str) -> str:
    return f"{ROOT}/{check_run_id(run_id)}/{ACK}/*"


@dataclass(frozen=True, slots=True)
class KeyParts:
    run_id: str
    node_id: str  # for infrastructure keys: the node the token/stats belong to
    output: str  # output name, or the infrastructure chunk ('_alive', '_stats', '_ack')

    @property
    def is_infrastructure(self) -> bool:
        return self.output in INFRA_CHUNKS


def parse_key(key: str) -> KeyParts:
    """Split a concrete key into its parts; raises ``KeyFormatError`` if it is not ours."""
    parts = str(key).split("/")
    if len(parts) != 4 or parts[0] != ROOT:
        raise KeyFormatError(f"key {key!r} is not of the form {ROOT}/<run>/<node>/<output>")
    _, run_id, a, b = parts
    check_run_id(run_id)
    if a in INFRA_CHUNKS:
        return KeyParts(run_id=run_id, node_id=check_name(b, "node id"), output=a)
    return KeyParts(run_id=run_id, node_id=check_name(a, "node id"), output=check_name(b, "output name"))


def replace_run(key: str, new_run_id: str) -> str:
    """The same key under another run id (used by replay to re-home a recording)."""
    p = parse_key(key)
    if p.is_infrastructure:
        return f"{ROOT}/{check_run_id(new_run_id)}/{p.output}/{p.node_id}"
    return data_key(new_run_id, p.node_id, p.output)
