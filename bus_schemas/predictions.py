"""Motion predictions: per (vehicle, corridor) distributions and the fused motion grid (docs/method.md §3.4, §9).

``iamp.CorridorPredictions`` holds, for every vehicle-corridor pair of one
frame, the Markov chain's marginals at the prediction steps t_k = k·τ
(k = 1..K) and the positions derived from them. ``iamp.MotionGrid`` holds the
occupancy of all vehicles fused on one map-frame grid, sparse per step.

Both say which vehicles they cover (v3): ``shard`` is "" for a message that
covers every vehicle of its frame, "i/n" for a ``markov_prediction`` shard's
own output (only the vehicles whose id hashes to shard i of n);
``missing_shards`` lists the shards ("i/n") whose vehicles a fused message
(``grid_fusion``) lacks this frame (down, late, or an incompatible grid). A
consumer that needs the whole scene checks ``shard == "" and not
missing_shards``: an empty area of a partial grid may hold vehicles nobody
predicted.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Annotated, ClassVar

import numpy as np

from ._wire import Array, Message, Range, register
from .common import HEADER_WALL_UPGRADE, COORD, COORD_OR_NAN, DIST_OR_NAN, INT64_MAX, NON_NEG_INT, PROB, Header

F64_K = Annotated[np.ndarray, Array("float64", ("k",))]
POS_K = Annotated[np.ndarray, Array("float64", ("k",)), COORD_OR_NAN]
TIMES_K = Annotated[np.ndarray, Array("float64", ("k",)), Range(0.0, 3600.0, unit="s")]
CELL = Range(1e-6, 1.0e3)


def _add_coverage(body: object) -> object:
    """Body of a v2 CorridorPredictions or MotionGrid made a v3 one, read as a whole frame's (``shard`` "", no
    ``missing_shards``): v2 did not say, so a v2 shard's own output or a fused frame that lacked a shard reads as
    whole too."""
    if isinstance(body, dict):
        return {"shard": "", "missing_shards": [], **body}
    return body


def _v1_to_v3(body: object) -> object:
    return _add_coverage(HEADER_WALL_UPGRADE(body))


#: ``UPGRADES`` of both schemas: v1 reads as v3 with source_wall_ns 0 (unknown), v1 and v2 as a whole frame's
_COVERAGE_UPGRADES: dict[int, Any] = {1: _v1_to_v3, 2: _add_coverage}


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class CorridorPrediction:
    """The prediction of one vehicle along one of its corridors; arrays over the K steps.

    ``corridor_id`` is the CorridorSet's id, or -1 for the Cartesian
    constant-velocity line of mode ``cv`` (a straight line from the vehicle
    along its velocity, with s from the vehicle's position).
    ``probability`` is the corridor's weight P(R = corridor) used for the
    grid: the intentions stage's route probability (uniform over the
    vehicle's corridors with ``corridor_weights = "uniform"``); a vehicle's
    sum to 1.

    Distributions at t_k (time-point marginals):

    - ``s_probs`` ``(K, W) float32``: mass per s-cell of ``ds_m`` (see the
      message); cell j covers corridor arc lengths
      [s_first_m + j·ds, s_first_m + (j+1)·ds). Cells never occupied at any
      step are cropped, so W is at most the Markov window;
    - ``v_probs`` ``(K, N_v) float32``: mass per speed cell of ``dv_mps`` from 0;
    - ``outside_mass`` ``(K,) float32``: mass past the end of the window or of
      the corridor (never renormalised away: s_probs plus outside sums to 1).

    Positions at exactly t_k after the frame's stamp, metres in the map frame
    (docs/wire.md), NaN when no mass is left inside:

    - ``mean_x_m``, ``mean_y_m``: Σ p(s_i)·X_c(s_i) / Σ p(s_i), the
      probability-weighted mean of centreline points, moved by the vehicle's
      lateral offset from the centreline (docs/method.md §3.6, §9.1; the one
      the metrics use);
    - ``mean_s_m``: E[s] over the same cells, and ``x_at_mean_s_m``,
      ``y_at_mean_s_m``: X_c(E[s]) (differs from the mean position on curves).
    """

    track_id: Annotated[int, NON_NEG_INT]
    corridor_id: Annotated[int, Range(-1, INT64_MAX)]
    probability: Annotated[float, PROB]
    vehicle_s_m: Annotated[float, DIST_OR_NAN]
    s_first_m: Annotated[float, DIST_OR_NAN]
    s_probs: Annotated[np.ndarray, Array("float32", ("k", "w")), PROB]
    v_probs: Annotated[np.ndarray, Array("float32", ("k", "nv")), PROB]
    outside_mass: Annotated[np.ndarray, Array("float32", ("k",)), PROB]
    mean_x_m: POS_K
    mean_y_m: POS_K
    mean_s_m: POS_K
    x_at_mean_s_m: POS_K
    y_at_mean_s_m: POS_K


@register
@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class CorridorPredictions(Message):
    """Every vehicle-corridor prediction of one frame (the frame of ``header.stamp_ns``).

    ``mode`` names the predictor: ``hybrid`` (the AR model's acceleration
    distributions drive the Markov chain), ``baseline`` (rule-based Markov
    chain), ``cv`` (Cartesian constant velocity), ``corridor_cv`` (constant
    speed along each corridor). ``step_times_s`` ``(K,)`` are the
    prediction times after the frame (0.4 … 4.0 s by default); ``ds_m`` and
    ``dv_mps`` the cell sizes of ``s_probs`` and ``v_probs``. ``shard`` and
    ``missing_shards`` say whether it covers every vehicle of its frame
    (module docstring).
    """

    SCHEMA: ClassVar[str] = "iamp.CorridorPredictions"
    VERSION: ClassVar[int] = 3  # v3: shard, missing_shards; v2: Header.source_wall_ns
    UPGRADES: ClassVar[dict[int, Any]] = _COVERAGE_UPGRADES
    # measured about 3.5 kB per (vehicle, corridor) prediction (K x W float32): 8 MiB is about 2,300 predictions
    MAX_BYTES: ClassVar[int] = 8 * 1024 * 1024
    # a prediction with a value out of range (probabilities outside [0, 1], inf positions) is dropped, recorded
    DROP_ELEMENTS: ClassVar[tuple[str, ...]] = ("predictions",)

    header: Header
    scene_id: str
    mode: str
    step_times_s: TIMES_K
    ds_m: Annotated[float, CELL]
    dv_mps: Annotated[float, CELL]
    predictions: tuple[CorridorPrediction, ...]
    shard: str = ""  # "": every vehicle of the frame; "i/n": only shard i of n's (module docstring)
    missing_shards: tuple[str, ...] = ()  # the shards ("i/n") whose vehicles this fused frame lacks


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class GridStep:
    """The non-negligible cells of one step, COO: ``rows``, ``cols`` ``(n,) int32`` and ``values`` ``(n,) float32``."""

    rows: Annotated[np.ndarray, Array("int32", ("n",)), Range(0, 2**31 - 1)]
    cols: Annotated[np.ndarray, Array("int32", ("n",)), Range(0, 2**31 - 1)]
    values: Annotated[np.ndarray, Array("float32", ("n",)), PROB]


@register
@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class MotionGrid(Message):
    """Fused occupancy probability of all predicted vehicles on a map-frame grid, one sparse layer per step.

    Cell (row, col) covers x ∈ [origin_x_m + col·cell_m, origin_x_m +
    (col+1)·cell_m) and y ∈ [origin_y_m + row·cell_m, …): row 0 is the
    southern edge. The grid has ``n_rows`` × ``n_cols`` cells; only cells
    above ``min_value`` are listed. Per vehicle n the corridors are weighted
    by their probability and the grid G_n sums to 1 − outside mass; vehicles
    combine as 1 − Π_n (1 − G_n) (docs/method.md §9). ``distribution`` says what
    a step holds: ``interval`` (Υ([0, τ]): the position at a uniformly random
    time of the step ending at t_k) or ``point`` (the position at t_k).
    ``steps`` has one entry per ``step_times_s``, each listing its cells
    sorted by row, then column. A value is the probability mass of vehicle
    centre points, not a footprint (no body size; it depends on ``cell_m``):
    docs/wire.md, "MotionGrid: what a cell holds". ``shard`` and
    ``missing_shards`` say whether it covers every vehicle of its frame
    (module docstring).
    """

    SCHEMA: ClassVar[str] = "iamp.MotionGrid"
    VERSION: ClassVar[int] = 3  # v3: shard, missing_shards; v2: Header.source_wall_ns
    UPGRADES: ClassVar[dict[int, Any]] = _COVERAGE_UPGRADES
    # 12 B per listed cell and step (measured up to 62 kB, 5,069 cells): 16 MiB is about 1.4 million cells
    MAX_BYTES: ClassVar[int] = 16 * 1024 * 1024

    header: Header
    scene_id: str
    mode: str
    distribution: str
    origin_x_m: Annotated[float, COORD]
    origin_y_m: Annotated[float, COORD]
    cell_m: Annotated[float, CELL]
    n_rows: Annotated[int, Range(0, 1_000_000)]
    n_cols: Annotated[int, Range(0, 1_000_000)]
    min_value: Annotated[float, PROB]
    step_times_s: TIMES_K
    steps: tuple[GridStep, ...]
    shard: str = ""  # "": every vehicle of the frame; "i/n": only shard i of n's (module docstring)
    missing_shards: tuple[str, ...] = ()  # the shards ("i/n") whose vehicles this fused frame lacks


def coverage(*messages: "CorridorPredictions | MotionGrid | None") -> str:
    """"" when the predictions ``messages`` (one frame's; None skipped) cover every vehicle of their frame; else what
    they lack, in words: "shard 0/2's vehicles only" (a shard's own output) or "shard 1/2 missing" (a fused frame)."""
    shard = next((m.shard for m in messages if m is not None and m.shard), "")
    if shard:
        return f"shard {shard}'s vehicles only"
    missing = sorted({s for m in messages if m is not None for s in m.missing_shards})
    return f"shard {', '.join(missing)} missing" if missing else ""
