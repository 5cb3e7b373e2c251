"""Dependencies point one way, read from the folders (the layout in README "Layout").

Every import of every module is resolved (absolute and relative, at module
level and inside functions) and checked against the layer its file lives in:

- ``bus_schemas/``: numpy, msgpack and the standard library only;
- ``stages/lib/``: pure libraries; never a stage, the runtime, the offline
  tools, zenoh, mcap or viser;
- ``stages/<stage>/``: a process stage; it may use ``stages/lib`` and
  ``bus_schemas``, and ``stages/runtime`` only in its binding
  (``__main__.py``), except the recorder and replay, whose cores are bus
  tools; never another stage (replay and the Foxglove exporter read the
  recorder's files through ``stages.recorder.inspect``), never the offline tools;
- ``stages/runtime/``: the runtime and the launcher; never a stage's code
  or the offline tools (stages are started by module name; the launcher
  reads the recorder's files with ``stages.recorder.inspect`` to summarise
  them);
- ``stages/offline/``: evaluation and training; stage cores and libraries,
  never the runtime or zenoh;
- only ``stages/runtime`` imports zenoh, only the recorder and replay
  import mcap, only the viewer imports viser, only ``stages/foxglove_bridge``
  imports foxglove (foxglove-sdk: the live bridge and ``iamp export
  foxglove``, which writes with the SDK's own MCAP writer and reads
  recordings through the recorder's reader, so mcap keeps its home), only
  the offline figures (``stages/offline/figures.py``, for ``iamp eval
  --figures/--report``; the bench scripts draw through it too) import
  matplotlib, so no process stage ever loads it; no import cycle anywhere.
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
STAGES = ("ar_inference", "corridors", "foxglove_bridge", "grid_fusion", "intentions", "markov_prediction", "recorder", "relations", "replay", "tracks_source", "viewer")
RECORDING_READERS = ("replay", "foxglove_bridge")  # stages that read recordings with stages.recorder.inspect
BUS_TOOL_STAGES = ("recorder", "replay")  # their cores talk to the bus themselves


def _module_of(path: Path) -> str:
    parts = list(path.relative_to(REPO).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _package_of(path: Path) -> str:
    mod = _module_of(path)
    return mod if path.name == "__init__.py" else mod.rsplit(".", 1)[0]


def _imports(path: Path) -> set[str]:
    """Every module ``path`` imports, as absolute dotted names (relative imports resolved)."""
    tree = ast.parse(path.read_text(), filename=str(path))
    out: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = _package_of(path).split(".")
                base = base[: len(base) - (node.level - 1)]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            out.add(mod)
            out.update(f"{mod}.{a.name}" for a in node.names)  # "from pkg import module"
    return out


def _sources() -> list[Path]:
    files = [*(REPO / "bus_schemas").rglob("*.py"), *(REPO / "stages").rglob("*.py"), REPO / "launch.py"]
    return sorted(f for f in files if "__pycache__" not in f.parts)


def _layer(path: Path) -> str:
    rel = path.relative_to(REPO).parts
    if rel[0] == "bus_schemas":
        return "bus_schemas"
    if rel[0] == "launch.py":
        return "launch"
    if len(rel) == 2:
        return "stages-top"  # stages/__init__.py, stages/cli.py
    if rel[1] in ("lib", "runtime", "offline"):
        return rel[1]
    if rel[1] in STAGES:
        return "stage"
    return "other"


def _stage_of(path: Path) -> str:
    return path.relative_to(REPO).parts[1]


def _top(name: str) -> str:
    return name.split(".")[0]


def _under(name: str, prefix: str) -> bool:
    return name == prefix or name.startswith(prefix + ".")


def _existing(name: str) -> bool:
    """Whether ``name`` is one of our modules (``from pkg import Name`` also yields pkg.Name, which is no module)."""
    parts = name.split(".")
    base = REPO.joinpath(*parts)
    return base.with_suffix(".py").exists() or (base / "__init__.py").exists()


def test_every_file_is_in_a_known_layer():
    others = [f.relative_to(REPO).as_posix() for f in _sources() if _layer(f) == "other"]
    assert not others, f"files outside the layers of the layout: {others}"


def test_bus_schemas_depend_on_numpy_and_msgpack_only():
    stdlib = set(sys.stdlib_module_names)
    for f in (REPO / "bus_schemas").rglob("*.py"):
        extra = {_top(m) for m in _imports(f)} - stdlib - {"numpy", "msgpack", "bus_schemas"}
        assert not extra, f"{f.relative_to(REPO)} imports {sorted(extra)}"


@pytest.mark.parametrize("heavy,homes", [("zenoh", ("stages/runtime/",)), ("mcap", ("stages/recorder/", "stages/replay/")), ("viser", ("stages/viewer/",)),
                                         ("foxglove", ("stages/foxglove_bridge/",)), ("matplotlib", ("stages/offline/figures.py",))])
def test_each_heavy_library_has_one_home(heavy, homes):
    users = [f.relative_to(REPO).as_posix() for f in _sources() if any(_top(m) == heavy for m in _imports(f))]
    assert users and all(u.startswith(homes) for u in users), f"{heavy} imported outside {homes}: {users}"


def test_libraries_import_no_stage_runtime_offline_or_bus_library():
    for f in _sources():
        if _layer(f) != "lib":
            continue
        for m in _imports(f):
            bad = _top(m) in ("zenoh", "mcap", "viser", "foxglove") or _under(m, "stages.runtime") or _under(m, "stages.offline")
            bad |= any(_under(m, f"stages.{s}") for s in STAGES) or m == "stages.cli"
            assert not bad, f"{f.relative_to(REPO)} (library) imports {m}"


def test_stages_use_libraries_not_each_other_and_the_runtime_only_in_their_binding():
    for f in _sources():
        if _layer(f) != "stage":
            continue
        own = _stage_of(f)
        for m in _imports(f):
            for other in STAGES:
                if other != own and _under(m, f"stages.{other}"):
                    allowed = own in RECORDING_READERS and _under(m, "stages.recorder.inspect")
                    assert allowed, f"{f.relative_to(REPO)} (stage {own}) imports stage {other}: {m}"
            assert not _under(m, "stages.offline"), f"{f.relative_to(REPO)} imports the offline tools: {m}"
            if _under(m, "stages.runtime") and f.name != "__main__.py":
                assert own in BUS_TOOL_STAGES, f"{f.relative_to(REPO)}: only a stage's binding (__main__.py) imports the runtime, got {m}"


def test_runtime_and_offline_keep_to_their_side():
    for f in _sources():
        layer = _layer(f)
        for m in _imports(f):
            if layer == "runtime":
                assert not _under(m, "stages.offline"), f"{f.relative_to(REPO)} imports {m}"
                core_of_a_stage = any(_under(m, f"stages.{s}") for s in STAGES)
                # the launcher summarises the recorder's files at the end of a run with the recorder's reader
                allowed = f.name == "launcher.py" and _under(m, "stages.recorder.inspect")
                assert allowed or not core_of_a_stage, f"{f.relative_to(REPO)} (runtime) imports a stage: {m} (stages are started by module name)"
            if layer == "offline":
                assert not (_under(m, "stages.runtime") or _top(m) == "zenoh"), f"{f.relative_to(REPO)} (offline) imports {m}"


def test_offline_tools_do_not_pull_in_zenoh():
    """``iamp eval`` and ``iamp train`` never load the bus (it once came in through the tracks source)."""
    import subprocess

    code = ("import sys, stages.offline.evaluation, stages.offline.train.fit, stages.offline.intentions_eval;"
            " print('zenoh' in sys.modules, 'matplotlib' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=REPO)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "False False", "zenoh never; matplotlib only when figures are drawn (imported lazily)"


def test_no_import_cycles():
    graph: dict[str, set[str]] = {}
    for f in _sources():
        mod = _module_of(f)
        deps = {m for m in _imports(f) if _top(m) in ("stages", "bus_schemas") and _existing(m)}
        graph[mod] = {d for d in deps if d != mod and not mod.startswith(d + ".")}  # a module importing its own package's __init__ is no cycle
    # packages re-export their modules: pkg -> pkg.mod is structure, not a dependency back
    state: dict[str, int] = {}
    stack: list[str] = []
    cycles: list[list[str]] = []

    def visit(n: str) -> None:
        state[n] = 1
        stack.append(n)
        for d in sorted(graph.get(n, ())):
            if d.startswith(n + "."):
                continue
            if state.get(d) == 1:
                cycles.append(stack[stack.index(d):] + [d])
            elif d not in state:
                visit(d)
        stack.pop()
        state[n] = 2

    for n in sorted(graph):
        if n not in state:
            visit(n)
    assert not cycles, "import cycles: " + "; ".join(" -> ".join(c) for c in cycles[:5])


def test_no_sys_path_patches():
    """The project is installed (make setup): nothing edits sys.path to find it."""
    files = [*_sources(), *(REPO / "tests").rglob("*.py"), *(REPO / "bench").rglob("*.py"), *(REPO / "testkit").rglob("*.py")]
    offenders = [f.relative_to(REPO).as_posix() for f in files if "__pycache__" not in f.parts and "sys.path" in f.read_text() and f.name != "test_dependencies.py"]
    assert not offenders, offenders
