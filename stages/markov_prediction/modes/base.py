"""The contract between ``MarkovPredictor``'s chain loop and a mode: the ``InputModel``, and the ``Pair`` it works on.

A mode says how the acceleration input enters the prediction; the loop
(``core.MarkovPredictor``) builds the pairs, runs the chain (or the
closed-form constant speed), the fallbacks and the outputs, and asks the
mode only the questions below. Every hook but ``start`` has a default.
"""

from __future__ import annotations

import math
from abc import ABC
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar, Protocol

import numpy as np

from bus_schemas import AccelerationProfiles, CorridorRelations, IntentionBelief, RelationSet, TrackFrame
from stages.lib.base import Issue

if TYPE_CHECKING:
    from stages.lib.markov import MarkovGridConfig, StepMarginals
    from stages.lib.markov.propagate import InputTransition
    from stages.markov_prediction.config import MarkovPredictionConfig


@dataclass(slots=True, eq=False)
class Pair:
    """One vehicle-corridor pair of a frame, with what the chain needs (corridor arc lengths in m)."""

    track_id: int
    corridor_id: int
    probability: float
    s_m: np.ndarray
    x_m: np.ndarray
    y_m: np.ndarray
    heading_rad: np.ndarray
    curvature_1pm: np.ndarray
    speed_limit_mps: float
    s0_m: float
    v0_mps: float
    a0_mps2: float
    s_first_m: float
    length_m: float
    width_m: float
    d0_m: float = 0.0
    sigma_a0_mps2: float = 0.5
    start_rate_hz: float = 0.0  # > 0: the vehicle stands; it starts at this rate (standstill mixture)
    relation: CorridorRelations | None = None
    half_width_s_m: float = 0.0  # > 0: the initial box's half-widths from the DBN's particles (initial_box "particles")
    half_width_v_mps: float = 0.0
    input_probs: np.ndarray | None = None  # (K, M) hybrid mode: λ(0..K-1) from the AR model
    measured_v_mps: float = math.nan  # the vehicle's speed before clipping to [0, v_max] (a faster one is not chained)
    speed_noise_mps: float = 0.0  # scatter of its measured speeds (MarkovPredictor.speed_noise); read by a spread with speed_noise_gain
    p_stop: float = math.nan  # the intentions stage's P(stop | this corridor), NaN without a belief
    stamp_ns: int = 0  # the frame's stamp (hybrid_initial_input "adaptive" records its pairs by it)
    curve_factor: float = 1.0  # hybrid: the factor of the curvature in its speed restriction (0: the limit alone)
    accel_shift_mps2: float = 0.0  # hybrid: added to the acceleration of its AR input distributions (hybrid_accel_shifts)
    speed_lead_s: float = 0.0  # hybrid: a moving pair's chain starts at v0 + speed_lead_s · accel_est_mps2 (hybrid_speed_leads_s)
    accel_est_mps2: float = math.nan  # the corridors stage's estimated acceleration of the vehicle (NaN: none)
    stop_distance_m: float = math.nan  # ... and the distance to the stop position on it
    # hybrid_initial_input "blend": the unshrunk slope of its speeds and the slope's standard error (NaN: no measurement)
    a_fit_mps2: float = math.nan
    a_fit_se_mps2: float = math.nan

    @property
    def end_s_m(self) -> float:
        return float(self.s_m[-1])

    def stay_probability(self, t_s: float | np.ndarray):
        """Weight of the standstill part at t (0 for a moving vehicle)."""
        if self.start_rate_hz <= 0:
            return 0.0 if np.ndim(t_s) == 0 else np.zeros(np.shape(t_s))
        return np.exp(-self.start_rate_hz * np.asarray(t_s, dtype=np.float64))


def stay_probabilities(pairs: list[Pair], t_s: np.ndarray) -> np.ndarray:
    """``Pair.stay_probability`` of every pair at the times ``t_s`` (T,), as one (B, T) array (the same numbers)."""
    rates = np.array([p.start_rate_hz for p in pairs], dtype=np.float64).reshape(-1, 1)
    t = np.asarray(t_s, dtype=np.float64).reshape(1, -1)
    return np.where(rates > 0, np.exp(-rates * t), 0.0)


@dataclass(frozen=True, slots=True)
class Messages:
    """The frame's messages besides the corridor set, as given (their stamps not checked)."""

    stamp_ns: int
    relation_set: RelationSet | None
    track_frame: TrackFrame | None
    intention_belief: IntentionBelief | None
    acceleration_profiles: AccelerationProfiles | None


@dataclass(frozen=True, slots=True)
class Vehicle:
    """A matched vehicle's measured state, as the loop builds its pairs from it."""

    message: Any  # the VehicleCorridors
    corridors: list  # its usable corridors
    frame: TrackFrame | None
    row: int | None  # its row in ``frame`` (same stamp), or None
    v0_mps: float  # speed clipped to [0, v_max]
    a0_mps2: float
    length_m: float
    width_m: float


class Predictor(Protocol):
    """What a mode reads of the ``MarkovPredictor`` it belongs to."""

    config: MarkovPredictionConfig
    grid: MarkovGridConfig
    n_s: int  # s-cells of a pair's window
    v_centres: np.ndarray
    a_centres: np.ndarray
    step_times_s: np.ndarray
    preference: np.ndarray  # the free-driving preference q, largest entry 1
    psi: np.ndarray

    def measured_inputs(self, pairs: list[Pair]) -> np.ndarray:
        """(B, M): a normal distribution around each pair's measured acceleration."""


class ChainInputs(ABC):
    """One frame's inputs of a chain mode: λ(0) and the input transition after each step, for the pairs of ``start``."""

    #: the chain also computes the interval distributions Υ([0, τ])
    with_interval: bool = False

    def initial(self) -> np.ndarray:
        """(B, M): the input distribution at t_0 of every pair."""
        raise NotImplementedError

    def step(self, k: int, marginals: StepMarginals) -> InputTransition | None:
        """The input transition Γ after step k (None: identity) for the pairs of the pass being run, given its marginals."""
        raise NotImplementedError

    def fixed_steps(self) -> list[InputTransition | None] | None:
        """The input transitions of every step of the first pass when none depends on the marginals (the propagator
        may then run the pass in one compiled call), else None (``step`` is called step by step)."""
        return None

    def rerun(self, arrays: dict[str, np.ndarray]) -> np.ndarray | None:
        """After a pass, with the frame's arrays so far (position, velocity, interval; standstill mixed in): the pair
        indices to propagate once more (``step`` then serves that pass), or None when the frame is done."""
        return None


class InputModel(ABC):
    """One mode, built once per predictor (``MarkovPredictor.model``); ``modes.MODELS`` maps the mode name to it."""

    #: the mode runs the Markov chain; False: the loop predicts constant speed along each pair's line (closed form)
    chain: ClassVar[bool] = True

    def __init__(self, predictor: Predictor) -> None:
        self.predictor = predictor

    def read(self, messages: Messages, issues: list[Issue]) -> Any:
        """Read what the mode needs of the frame's messages, before the pairs are built; the result goes to ``pair_input``."""
        return None

    def vehicle_pairs(self, vehicle: Vehicle) -> list[Pair] | None:
        """The vehicle's pairs when the mode places them itself (``cv``: one straight line); None: one per corridor."""
        return None

    def pair_input(self, track_id: int, corridor_id: int, data: Any, issues: list[Issue]) -> np.ndarray | None:
        """(K, M) input distributions λ(0..K-1) of one pair from ``read``'s data (``Pair.input_probs``), or None."""
        return None

    def prepare_pairs(self, pairs: list[Pair]) -> None:
        """What the mode can compute of the frame's pairs before their inputs and relations are known (their
        corridors, boxes and sizes are), for ``start`` to use when it gets these very pairs; nothing by default."""

    def start(self, pairs: list[Pair], issues: list[Issue]) -> ChainInputs:
        """A chain mode's inputs for this frame's pairs (B ≥ 1, every one the chain can take)."""
        raise NotImplementedError(f"{type(self).__name__} does not run the chain")
