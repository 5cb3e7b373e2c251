"""Merge the MotionGrids and CorridorPredictions of ``markov_prediction`` shards of one frame (pure; docs: stages/grid_fusion).

A shard predicts the vehicles whose id hashes to it (``shard_of``: CRC-32
of the decimal id, stable across processes and machines, unlike Python's
``hash``). Its MotionGrid is the fused grid of its own vehicles, so the
grid of all vehicles is again 1 − Π_shards (1 − G_shard), cell by cell, on
the union of the shards' grids (every grid lies on the lattice of multiples
of ``cell_m``, so cells line up). Cells below a shard's ``min_value`` were
not sent, so a fused cell can differ from the one-process grid by at most
the sum of the shards' ``min_value``.
"""

from __future__ import annotations

import dataclasses
import math
import zlib
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from bus_schemas import CorridorPredictions, GridStep, Header, MotionGrid

_CLIP = 1e-7


def shard_of(track_id: int, n_shards: int) -> int:
    """The shard (0 .. n−1) of a vehicle: CRC-32 of its decimal id modulo n."""
    return zlib.crc32(str(int(track_id)).encode("ascii")) % int(n_shards)


def parse_shard(text: str) -> tuple[int, int] | None:
    """``"i/n"`` -> (i, n) with 0 <= i < n; "" -> None (no sharding). Raises ValueError on anything else."""
    if not text:
        return None
    try:
        i_text, n_text = text.split("/")
        i, n = int(i_text), int(n_text)
    except ValueError:
        raise ValueError(f"shard = {text!r}: expected \"i/n\" with 0 <= i < n, e.g. \"0/2\"") from None
    if not (n >= 1 and 0 <= i < n):
        raise ValueError(f"shard = {text!r}: expected \"i/n\" with 0 <= i < n, e.g. \"0/2\"")
    return i, n


#: parameters of how a markov_prediction runs, not what it predicts (the numbers do not depend on them): shards may differ there
_HOW_NOT_WHAT = frozenset({"kernel_threads", "backend", "device", "stencil_cache_dir"})


def check_shard_sources(sources: Mapping[str, tuple[str, Any]]) -> None:
    """``ValueError`` where the shards bound to a grid_fusion node would not add up to every vehicle once (its
    ``StageSpec.check_sources``; ``sources``: port -> (source node, its configuration, None for one the pipeline does
    not start)): shard i's ``motion_grid`` and ``corridor_predictions`` on ``grid_i`` and ``predictions_i`` (one node
    for both), each a markov_prediction with ``shard = "i/n"``, one n for all, every i of 0 .. n-1 bound (a shard
    run elsewhere counts by its port), and the shards alike in every other parameter but those of how they run
    (``_HOW_NOT_WHAT``: threads, backend, device). A copy-paste slip (two shards "0/2") passed and ran with half the
    vehicles never predicted and the other half fused with themselves, every line of the run clean."""
    ports: dict[int, dict[str, tuple[str, Any]]] = {}
    for port, source in sources.items():
        kind, _, index = port.partition("_")
        if kind in ("grid", "predictions") and index.isdigit():
            ports.setdefault(int(index), {})[kind] = source
    counts: set[int] = set()
    local: list[tuple[str, Any]] = []
    for i, bound in sorted(ports.items()):
        nodes = {node for node, _config in bound.values()}
        if len(nodes) > 1:
            raise ValueError(f"grid_{i} and predictions_{i} come from {' and '.join(sorted(nodes))}: bind both to one shard's outputs")
        node, config = next(iter(bound.values()))
        if config is None:  # run elsewhere: known by its port only
            continue
        shard = parse_shard(getattr(config, "shard", "") or "")
        if shard is None:
            raise ValueError(f"grid_{i} comes from {node}, which has no shard: set shard = \"{i}/N\" on it (N shards in all)")
        if i >= shard[1]:
            raise ValueError(f"grid_{i} comes from {node}, a shard of {shard[1]}: {shard[1]} shards go on grid_0 .. "
                             f"grid_{shard[1] - 1} (and predictions_0 .. predictions_{shard[1] - 1})")
        if shard[0] != i:
            raise ValueError(f"grid_{i} comes from {node}, whose shard is \"{shard[0]}/{shard[1]}\": bind shard i's outputs to "
                             f"grid_i and predictions_i (or set shard = \"{i}/{shard[1]}\" on {node})")
        counts.add(shard[1])
        local.append((node, config))
    if len(counts) > 1:
        raise ValueError(f"its shards count {' and '.join(str(c) for c in sorted(counts))} shards in all: give them one n (\"i/n\")")
    if counts:
        n = counts.pop()
        unbound = sorted(set(range(n)) - set(ports))
        beyond = sorted(set(ports) - set(range(n)))
        if unbound or beyond:
            what = (f"shard(s) {', '.join(f'{i}/{n}' for i in unbound)} not bound (grid_i, predictions_i)" if unbound
                    else f"grid_{beyond[0]} is past {n} shards")
            raise ValueError(f"{what}: the vehicles of a shard not bound are never predicted")
    if len(local) > 1:
        first, first_config = local[0]
        base = dataclasses.asdict(dataclasses.replace(first_config, shard=""))
        for node, config in local[1:]:
            other = dataclasses.asdict(dataclasses.replace(config, shard=""))
            differ = sorted(k for k in base if base[k] != other.get(k) and k not in _HOW_NOT_WHAT)
            if differ:
                raise ValueError(f"shards {first} and {node} differ in {', '.join(differ)} "
                                 f"({', '.join(f'{k} = {base[k]!r} / {other[k]!r}' for k in differ[:3])}): the shards of one grid must be alike")


def compatible(a: MotionGrid, b: MotionGrid) -> str:
    """"" when ``b`` can be fused with ``a``; else why not."""
    if abs(a.cell_m - b.cell_m) > 1e-9:
        return f"cell_m {b.cell_m} != {a.cell_m}"
    if a.step_times_s.shape != b.step_times_s.shape or not np.allclose(a.step_times_s, b.step_times_s):
        return "other step_times_s"
    if a.distribution != b.distribution:
        return f"distribution {b.distribution} != {a.distribution}"
    if a.scene_id != b.scene_id:
        return f"scene {b.scene_id} != {a.scene_id}"
    return ""


def fuse_motion_grids(grids: Sequence[MotionGrid], header: Header, missing_shards: Sequence[str] = ()) -> MotionGrid:
    """1 − Π (1 − G) over ``grids`` (compatible ones, at least one) on the union of their lattices, under ``header``;
    ``missing_shards``: the shards ("i/n") whose vehicles it lacks (with those the inputs already lacked)."""
    if not grids:
        raise ValueError("fuse_motion_grids: no grid")
    first = grids[0]
    for g in grids[1:]:
        why = compatible(first, g)
        if why:
            raise ValueError(f"fuse_motion_grids: {why}")
    cell = float(first.cell_m)
    used = [g for g in grids if any(s.values.size for s in g.steps)] or [first]
    ix = [int(round(g.origin_x_m / cell)) for g in used]
    iy = [int(round(g.origin_y_m / cell)) for g in used]
    x0, y0 = min(ix), min(iy)
    n_cols = max(i + g.n_cols for i, g in zip(ix, used)) - x0
    n_rows = max(i + g.n_rows for i, g in zip(iy, used)) - y0
    min_value = max(float(g.min_value) for g in grids)
    steps = []
    for k in range(len(first.steps)):
        keys, logs = [], []
        for g, gx, gy in zip(used, ix, iy):
            s = g.steps[k]
            keys.append((s.rows.astype(np.int64) + (gy - y0)) * n_cols + (s.cols.astype(np.int64) + (gx - x0)))
            logs.append(np.log1p(-np.clip(s.values.astype(np.float64), 0.0, 1.0 - _CLIP)))
        key = np.concatenate(keys)
        if key.size:
            unique, inverse = np.unique(key, return_inverse=True)
            values = -np.expm1(np.bincount(inverse, weights=np.concatenate(logs)))
        else:
            unique, values = key, np.zeros(0)
        keep = values > min_value
        rows, cols = np.divmod(unique[keep], n_cols)
        steps.append(GridStep(rows=rows.astype(np.int32), cols=cols.astype(np.int32), values=values[keep].astype(np.float32)))
    return MotionGrid(
        header=header, scene_id=first.scene_id, mode=first.mode, distribution=first.distribution,
        origin_x_m=x0 * cell, origin_y_m=y0 * cell, cell_m=cell, n_rows=max(int(n_rows), 1), n_cols=max(int(n_cols), 1),
        min_value=min_value, step_times_s=np.asarray(first.step_times_s, dtype=np.float64), steps=tuple(steps),
        missing_shards=_missing(missing_shards, grids),
    )


def _missing(missing_shards: Sequence[str], parts: Sequence[MotionGrid | CorridorPredictions]) -> tuple[str, ...]:
    """The shards missing from a fused message: those named and those its parts lacked, once each, sorted."""
    return tuple(sorted(set(missing_shards).union(*(p.missing_shards for p in parts))))


def merge_predictions(parts: Sequence[CorridorPredictions], header: Header, missing_shards: Sequence[str] = ()) -> CorridorPredictions:
    """The shards' CorridorPredictions of one frame as one message (predictions concatenated, ordered by track and
    corridor); ``missing_shards`` as in ``fuse_motion_grids``."""
    if not parts:
        raise ValueError("merge_predictions: nothing to merge")
    first = parts[0]
    preds = sorted((p for part in parts for p in part.predictions), key=lambda p: (p.track_id, p.corridor_id))
    return CorridorPredictions(header=header, scene_id=first.scene_id, mode=first.mode, step_times_s=first.step_times_s,
                               ds_m=first.ds_m, dv_mps=first.dv_mps, predictions=tuple(preds),
                               missing_shards=_missing(missing_shards, parts))


__all__ = ["compatible", "fuse_motion_grids", "merge_predictions", "parse_shard", "shard_of"]
