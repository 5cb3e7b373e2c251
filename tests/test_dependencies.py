"""Dependencies point one way (STYLE.md): each heavy library has one home."""

from __future__ import annotations

import ast
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def _imports(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(), filename=str(path))
    out: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.update(a.name.split(".")[0] for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.add(node.module.split(".")[0])
    return out


def _sources() -> list[Path]:
    files = list((REPO / "bus_schemas").rglob("*.py")) + list((REPO / "stages").rglob("*.py")) + [REPO / "launch.py"]
    return [f for f in files if f.exists()]


def test_bus_schemas_depend_on_numpy_and_msgpack_only():
    allowed = {"numpy", "msgpack", "bus_schemas", "__future__", "dataclasses", "enum", "typing", "types", "math", "re", "contextvars"}
    for f in (REPO / "bus_schemas").rglob("*.py"):
        extra = _imports(f) - allowed
        assert not extra, f"{f.relative_to(REPO)} imports {sorted(extra)}"


def test_zenoh_only_in_runtime():
    users = [f.relative_to(REPO).as_posix() for f in _sources() if "zenoh" in _imports(f)]
    assert users == ["stages/runtime.py"], users


def test_mcap_only_in_recorder_replay_inspect():
    users = [f.relative_to(REPO).as_posix() for f in _sources() if "mcap" in _imports(f)]
    assert all(any(w in u for w in ("recorder", "replay", "inspect")) for u in users), users


def test_viser_only_in_viewer():
    users = [f.relative_to(REPO).as_posix() for f in _sources() if "viser" in _imports(f)]
    assert all("viewer" in u for u in users), users


def test_cores_do_not_import_the_bus():
    """Stage cores and the map/dataset/markov packages never import zenoh, msgpack or the runtime."""
    pure = [p for p in (REPO / "stages").rglob("*.py") if p.parent.name in ("datasets", "markov") or p.name in ("maps.py", "_core.py")]
    for f in pure:
        imps = _imports(f)
        assert not imps & {"zenoh", "msgpack", "mcap", "viser"}, f"{f.relative_to(REPO)} imports {sorted(imps & {'zenoh', 'msgpack', 'mcap', 'viser'})}"
        src = f.read_text()
        assert "stages.runtime" not in src and "from .runtime" not in src and "from ..runtime" not in src, f"{f.relative_to(REPO)} uses the runtime"
