"""Offline evaluation (``iamp eval``): the prediction modes against ground truth, in-process (docs/method.md §9).

Runs source → corridors → relations → intentions, ar_inference →
markov_prediction as plain cores, no bus: ``TrackPlayer`` plays each
sequence of each recording (fresh cores per sequence, maps and the AR model
loaded once), the corridors, relations and intentions cores see every frame
(their continuity state is as on the bus; the particle filter is seeded with
``--seed``), the ar_inference core adds every frame to its feature
histories and predicts at the evaluated instants, every mode's
``MarkovPredictor`` observes every frame (the measured acceleration) and
predicts at the evaluated instants: the frames at multiples of ``stride_s``
from the sequence's first stamp. The chain up to intentions is
``stages.offline.chain.Chain`` and the ground truth ``stages.offline.truth``,
the same as ``iamp train``'s (the AR training set) and the intentions
evaluation's.

Modes: ``hybrid`` (AR distributions replace λ; ``--model`` picks the
weights, default the shipped ones), ``baseline`` (rule-based λ), ``cv``,
``corridor_cv``. Corridor weights (``--corridor-weights``): ``intentions``
(default: the DBN's P(R = c)) or ``uniform``; the same weights for every
mode with corridors.

Windows. At an instant, every vehicle (``AgentType.is_vehicle``; TAF-BW has
cars only) whose track has ground truth at exactly t + k·τ, k = 1..K, and
that the corridors stage matched (so every mode predicts it). Vehicles
without a full future or unmatched are counted in ``skipped``. Every mode is
evaluated on the same windows.

Nothing in the data stops the evaluation (only a bad command line or
configuration: exit 2). What it leaves out is counted in ``skipped`` by
reason, with the first occurrence in ``skipped_examples``, and listed under
the table: windows ``no_full_future``, ``not_matched``,
``no_prediction_<mode>`` (the mode left the vehicle out), ``score_error_<mode>``
and ``prediction_error_<mode>`` (the predictor raised: the instant's windows
are scored for no mode); frames ``<stage>_error_frames`` (a core raised on
the frame: without corridors the frame is skipped, without relations,
beliefs or AR profiles it is predicted without them); and
``unreadable_sequences`` (a sequence whose files cannot be read); situations
``situations_without_frames`` (a ``--situations`` window that held no frame:
a sequence that is not there, or a window past the recording). Each mode's
``issues`` counts its predictor's issues by kind (fallback pairs among them).

Metrics per window (K = 10 steps of 0.4 s):

- ADE_c, FDE_c of each corridor's probability-weighted mean position
  (``FramePrediction.mean_xy_m``; a step whose mass has all left the corridor
  keeps the last finite mean, counted in ``nan_means``);
  ``mADE_m``/``mFDE_m``: minimum over the vehicle's corridors, each
  minimised separately (the paper's oracle); ``wADE_m``/``wFDE_m``: the
  corridor-probability-weighted mean of ADE_c/FDE_c;
- ``coverage90``: share of (vehicle, step) pairs whose true position lies in
  a cell of the 90 % highest-probability region of that vehicle's grid at
  that step (the vehicle's own grid, corridors weighted, not the fused
  one; all occupied cells when the grid holds less than 90 %);
- ``coverage50``: the same with the 50 % highest-probability region (a
  calibrated grid holds the truth in about half of the pairs);
- ``route_top1``: share of route windows where the corridor the car really
  followed has the highest weight (a k-way tie counts 1/k); a route window
  has at least two corridors, one of which holds the true 4 s future within
  2 m laterally while the runner-up is at least 0.5 m worse (before the
  branch the future does not tell routes apart: those windows do not count;
  ``truth.followed_corridor`` and ``truth.route_decision``, the rule of
  ``iamp train`` and the intentions evaluation);
  ``route_windows`` counts them (0 for ``cv``, which has one line);
- ``nll``: mean over (vehicle, step) of −ln max(G(cell of the true position),
  ``nll_floor``), in nats, G the probability of the ``grid_cell_m`` cell
  (a discrete probability, not a density); the floor (1e-6 by default, so
  a miss costs 13.8 nats) keeps it finite when the truth falls outside the
  predicted cells.

In ``--json`` a split without windows has ``windows`` 0 and null metrics.

The grids used here are the centre-point grids at t_k (``grid_distribution =
"point"``, docs/method.md §9 "for calibration"); the stage publishes interval
occupancy by default. ``frame_ms_*`` is the wall time of one
``MarkovPredictor.process`` call (all vehicles of the frame, grid included;
corridors and relations excluded). Splits: ``by_speed.slow`` (speed at t ≤
2 m/s), ``by_speed.fast`` (> 2 m/s), ``by_recording.<name>``,
``by_manoeuvre.<class>``: the class of the window's TRUE future
(``truth.manoeuvre_class``, from positions only: ``stands``, ``turns``,
``brakes``, ``accelerates`` (starting included), ``keeps_speed``, the first
that applies), each with the statistics of the other splits.

Along/cross-track split (``along_track_m``, ``cross_track_m`` per mode,
``overall`` and ``by_manoeuvre.<class>``, at ``1s``…``4s``: the nearest
prediction step, its time in ``t_s``, a tie going to the later step: 1.2 s
and 3.2 s with 0.4 s steps): the error (predicted mean − truth) of the same
corridor mean mADE scores (the one with the smallest ADE), split along the
true direction of travel at that step (``truth.along_track_directions``:
the central difference of the true positions, backward at the last step;
where the truth moves less than 0.2 m around that time, the direction from
the start position) and across it, so that along² + cross² is the squared
error the ADE uses at that step. ``along_track_m``: ``mean`` (signed, + =
the prediction is ahead of the truth) and ``rms``; ``cross_track_m``:
``mean_abs``, ``rms`` and ``mean_left`` (signed, + = left of the truth). A
step without a direction (the truth within 0.2 m of the start as well: most
standing cars) counts in ``cross_track_m`` only, with its whole error; ``n``
says how many windows each figure has. The table adds windows and mADE per
class and the along-track bias at 4 s per class.

Calibration and horizon (additive keys per mode): ``calibration`` — per
speed split (``overall``, ``slow``, ``fast``) the coverage of the
highest-probability regions at ``levels`` 10 %…90 % (the rule of
``coverage90``, which equals the 90 % entry), the reliability diagram of
``--report``; ``error_by_step_m`` — per split the mean displacement error at
each prediction step (``t_s``) of the corridor mADE scores (its mean over
the steps is mADE).

Situations (``--situations FILE.toml``, ``stages.offline.situations``; by
default every recording is one): ``situations`` lists them with the
vehicles seen and the duration played in each; per mode ``by_situation.<name>``
has the statistics of a split plus ``time_per_step_ms`` (the mean wall time
of one prediction of all vehicles of the frame at the situation's instants,
hybrid's AR inference included: the paper's "time") and ``instants``.

Figures (``figures_dir``, ``--figures DIR``; ``stages.offline.figures``,
matplotlib, PNG and SVG), for each recording at its instant with the most
moving windows (start speed > 2 m/s), then the most windows: ``grid_4s_<mode>_<recording>`` for hybrid and baseline (the fused
centre-point grid at the last step as a heat map with a log colour bar over
the car lanelets, vehicles at t, the scored vehicles' corridors),
``means_<recording>`` (the paper's comparison: hybrid blue, baseline red,
each corridor's mean positions with opacity = its probability, ground truth
black; the legend gives the instant's mADE/mFDE per mode), and
``accel_<recording>_<seq>_car<id>_<ms>ms`` for one or two cars (the
drawn instant's car whose true acceleration varies most, the recording's
hardest braking car): the paper's acceleration-distribution figure (the 10
distributions as grey intensity, the AR output red, the true acceleration
blue). ``figures.txt`` names the instants and describes each file.
``--report DIR`` writes these with the report (``stages.offline.report``).
"""

from __future__ import annotations

import collections
import dataclasses
import json
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from bus_schemas import AgentType, CorridorSet, MatchStatus, RelationSet, SceneInfo, TrackFrame

from stages.lib.base import ConfigError, check_output, json_safe, progress_bar

from stages.corridors import SceneMaps
from stages.lib.kinematic_state import Consistency, EstimatorConfig, consistency_of, disagreement_line
from stages.lib.datasets import DEFAULT_DATA_DIR, DatasetError, Recording, default_recordings, discover, find_recording, load_ref
from stages.lib.datasets.model import same_sequence_id
from stages.lib.datasets.report import LoadReport, report_lines
from stages.lib.markov import load_or_build_stencils
from stages.markov_prediction import FramePrediction, MarkovPredictionConfig, MarkovPredictor
from stages.markov_prediction.core import grid_config
from stages.markov_prediction.rasterise import GridFrame, highest_density_threshold
from stages.markov_prediction.spread import resolve as spread_file
from stages.intentions import IntentionsConfig
from stages.offline.chain import Chain
from stages.offline.truth import (
    MANOEUVRES,
    ROUTE_MAX_ERROR_M,
    ROUTE_TIE_M,
    STAMP_TOL_NS,
    along_track_directions,
    followed_corridor,
    future_accelerations,
    future_positions,
    ground_truth,
    manoeuvre_class,
    route_credit,
    route_decision,
)
from stages.offline.signal_split import SIGNAL_KEYS, signal_keys
from stages.tracks_source.core import file_sha256
from stages.offline.situations import Situation, whole_recordings
from stages.offline.eval_args import CORRIDOR_WEIGHTS, EVAL_MODES, add_arguments  # (the command line's options: a light module)

SLOW_SPEED_MPS = 2.0
#: the along/cross-track split at these horizons (s), each at the nearest prediction step (a tie: the later step).
TRACK_HORIZONS_S = (1.0, 2.0, 3.0, 4.0)
#: nominal levels of the highest-probability regions whose coverage ``calibration`` reports (the reliability diagram).
COVERAGE_LEVELS = (0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9)


def _status_name(status) -> str:
    """A corridor set's match status in words (``off_map``...), or its number where it is none of ours."""
    try:
        return MatchStatus(int(status)).name.lower()
    except (TypeError, ValueError):
        return f"status {status!r}"


@dataclass(frozen=True, kw_only=True)
class EvalConfig:
    """What to evaluate and how (see the module docstring)."""

    data_dir: Path = DEFAULT_DATA_DIR
    recordings: tuple[str, ...] = ()
    sequences: tuple[str, ...] = ()
    modes: tuple[str, ...] = EVAL_MODES
    stride_s: float = 0.4
    max_frames_per_sequence: int = 0
    corridor_weights: str = "intentions"
    intentions_params: tuple[tuple[str, Any], ...] = ()
    ar_params: tuple[tuple[str, Any], ...] = ()
    backend: str = "numpy"
    device: str = "cpu"
    coverage_level: float = 0.9
    nll_floor: float = 1e-6
    progress: bool = True
    figures_dir: Path | None = None
    params: tuple[tuple[str, Any], ...] = ()
    model_path: Path | None = None
    seed: int = 0
    situations: tuple[Situation, ...] = ()  # empty: every recording is one situation
    signals: bool = True  # play recordings with their signal phases (False: --signals off, as without them)

    def __post_init__(self) -> None:
        unknown = [m for m in self.modes if m not in EVAL_MODES]
        if unknown or not self.modes:
            raise ValueError(f"modes {unknown or '(none)'}: expected one or several of {', '.join(EVAL_MODES)}")
        if self.corridor_weights not in CORRIDOR_WEIGHTS:
            raise ValueError(f"corridor_weights = {self.corridor_weights!r}: expected one of {', '.join(CORRIDOR_WEIGHTS)}")
        if not (math.isfinite(self.stride_s) and self.stride_s > 0):
            raise ValueError(f"stride_s = {self.stride_s!r}: must be > 0")
        if not (0 < self.coverage_level < 1) or not (0 < self.nll_floor < 1):
            raise ValueError("coverage_level and nll_floor must lie in (0, 1)")


# --------------------------------------------------------------------------- accumulation


@dataclass(slots=True)
class _Stats:
    """Sums over windows of one (mode, split)."""

    windows: int = 0
    made: float = 0.0
    mfde: float = 0.0
    wade: float = 0.0
    wfde: float = 0.0
    steps: int = 0
    covered: int = 0
    covered50: int = 0
    nll: float = 0.0
    route_windows: int = 0
    route_hits: float = 0.0

    def add(self, w: "_WindowResult") -> None:
        self.windows += 1
        self.made += w.made
        self.mfde += w.mfde
        self.wade += w.wade
        self.wfde += w.wfde
        self.steps += w.steps
        self.covered += w.covered
        self.covered50 += w.covered50
        self.nll += w.nll
        if w.route_hit is not None:
            self.route_windows += 1
            self.route_hits += w.route_hit

    def summary(self) -> dict[str, float | int]:
        n, k = max(self.windows, 1), max(self.steps, 1)
        nan = float("nan")
        return {
            "windows": self.windows,
            "mADE_m": self.made / n if self.windows else nan,
            "mFDE_m": self.mfde / n if self.windows else nan,
            "wADE_m": self.wade / n if self.windows else nan,
            "wFDE_m": self.wfde / n if self.windows else nan,
            "coverage50": self.covered50 / k if self.steps else nan,
            "coverage90": self.covered / k if self.steps else nan,
            "nll": self.nll / k if self.steps else nan,
            "route_top1": self.route_hits / self.route_windows if self.route_windows else nan,
            "route_windows": self.route_windows,
        }


@dataclass(frozen=True, slots=True)
class _WindowResult:
    made: float
    mfde: float
    wade: float
    wfde: float
    steps: int
    covered: int
    nll: float
    covered50: int = 0
    route_hit: float | None = None
    error_xy: np.ndarray | None = None  # (K, 2) predicted mean − truth of the corridor mADE scores (the smallest ADE)
    covered_levels: np.ndarray | None = None  # (len(COVERAGE_LEVELS),) steps inside each level's highest-probability region


@dataclass(slots=True)
class _Calibration:
    """Sums of one (mode, speed split) for ``calibration`` and ``error_by_step_m``."""

    windows: int = 0
    steps: int = 0
    covered: np.ndarray = field(default_factory=lambda: np.zeros(len(COVERAGE_LEVELS), np.int64))
    error_sum: np.ndarray | None = None  # (K,) summed |error| of the mADE corridor at each step

    def add(self, w: "_WindowResult") -> None:
        if w.covered_levels is None or w.error_xy is None:
            return
        self.windows += 1
        self.steps += w.steps
        self.covered += w.covered_levels
        err = np.hypot(w.error_xy[:, 0], w.error_xy[:, 1])
        self.error_sum = err.copy() if self.error_sum is None else self.error_sum + err

    def coverage(self) -> list[float]:
        return [float(c) / self.steps if self.steps else float("nan") for c in self.covered]

    def error_by_step(self, n_steps: int) -> list[float]:
        if self.error_sum is None or not self.windows:
            return [float("nan")] * n_steps
        return [float(e) / self.windows for e in self.error_sum]


@dataclass(slots=True)
class _TrackSplit:
    """Sums of the along/cross-track errors of one (mode, group) at the horizons ``TRACK_HORIZONS_S``."""

    along_n: np.ndarray = field(default_factory=lambda: np.zeros(len(TRACK_HORIZONS_S), np.int64))
    along_sum: np.ndarray = field(default_factory=lambda: np.zeros(len(TRACK_HORIZONS_S)))
    along_sq: np.ndarray = field(default_factory=lambda: np.zeros(len(TRACK_HORIZONS_S)))
    cross_n: np.ndarray = field(default_factory=lambda: np.zeros(len(TRACK_HORIZONS_S), np.int64))
    cross_abs: np.ndarray = field(default_factory=lambda: np.zeros(len(TRACK_HORIZONS_S)))
    cross_sum: np.ndarray = field(default_factory=lambda: np.zeros(len(TRACK_HORIZONS_S)))
    cross_sq: np.ndarray = field(default_factory=lambda: np.zeros(len(TRACK_HORIZONS_S)))

    def add(self, along: np.ndarray, cross: np.ndarray) -> None:
        """One window's errors at the horizons: along (NaN where the direction is undefined), cross (left positive)."""
        ok = np.isfinite(along)
        self.along_n += ok
        self.along_sum += np.where(ok, along, 0.0)
        self.along_sq += np.where(ok, along, 0.0) ** 2
        self.cross_n += 1
        self.cross_abs += np.abs(cross)
        self.cross_sum += cross
        self.cross_sq += cross**2

    def summary(self, steps: list[int], tau_s: float) -> tuple[dict[str, Any], dict[str, Any]]:
        along, cross = {}, {}
        nan = float("nan")
        for h, (horizon, k) in enumerate(zip(TRACK_HORIZONS_S, steps)):
            key, t_s = f"{horizon:g}s", round((k + 1) * tau_s, 6)
            na, nc = int(self.along_n[h]), int(self.cross_n[h])
            along[key] = {"t_s": t_s, "n": na, "mean": self.along_sum[h] / na if na else nan,
                          "rms": math.sqrt(self.along_sq[h] / na) if na else nan}
            cross[key] = {"t_s": t_s, "n": nc, "mean_abs": self.cross_abs[h] / nc if nc else nan,
                          "rms": math.sqrt(self.cross_sq[h] / nc) if nc else nan,
                          "mean_left": self.cross_sum[h] / nc if nc else nan}
        return along, cross


@dataclass(slots=True)
class _ModeAccumulator:
    overall: _Stats = field(default_factory=_Stats)
    slow: _Stats = field(default_factory=_Stats)
    fast: _Stats = field(default_factory=_Stats)
    by_recording: dict[str, _Stats] = field(default_factory=lambda: collections.defaultdict(_Stats))
    by_manoeuvre: dict[str, _Stats] = field(default_factory=lambda: {m: _Stats() for m in MANOEUVRES})
    track_overall: _TrackSplit = field(default_factory=_TrackSplit)
    track_by_manoeuvre: dict[str, _TrackSplit] = field(default_factory=lambda: {m: _TrackSplit() for m in MANOEUVRES})
    frame_ms: list[float] = field(default_factory=list)
    vehicles: list[int] = field(default_factory=list)
    calibration: dict[str, _Calibration] = field(default_factory=lambda: {k: _Calibration() for k in ("overall", "slow", "fast")})
    by_situation: dict[str, _Stats] = field(default_factory=lambda: collections.defaultdict(_Stats))
    situation_ms: dict[str, list] = field(default_factory=lambda: collections.defaultdict(list))  # per situation: time per step
    nan_means: int = 0
    issues: collections.Counter = field(default_factory=collections.Counter)  # the predictor's issues by kind
    by_signal: dict[str, _Stats] = field(default_factory=lambda: {k: _Stats() for k in SIGNAL_KEYS})  # stages.offline.signal_split


@dataclass(slots=True)
class _Figure:
    """An instant drawn by ``--figures`` / ``--report`` (one per recording: the most moving cars, then the most windows)."""

    n_windows: int
    n_moving: int  # windows starting above SLOW_SPEED_MPS: the instant drawn has the most, then the most windows
    recording: str
    sequence: str
    stamp_ns: int
    scene: SceneInfo
    scene_maps: SceneMaps
    predictions: dict[str, FramePrediction]
    truths: dict[int, np.ndarray]
    starts: dict[int, tuple[float, float]]
    frame: TrackFrame | None = None
    corridor_set: CorridorSet | None = None
    scores: dict[str, dict[str, float]] = field(default_factory=dict)  # per mode: mADE_m, mFDE_m, windows at this instant


# --------------------------------------------------------------------------- the evaluation


class Evaluation:
    """Runs the cores over the selected recordings and accumulates the metrics per mode."""

    def __init__(self, config: EvalConfig) -> None:
        self.config = config
        self.scene_maps = SceneMaps(data=config.data_dir)  # maps by name from the evaluated data folder
        self._estimators: dict[str, list] = {}  # per recording: the corridors stage's state estimator of each sequence
        mode_configs = {
            mode: MarkovPredictionConfig.from_params(
                {
                    **dict(config.params),
                    "mode": mode,
                    "backend": config.backend if mode in ("baseline", "hybrid") else "numpy",
                    "device": config.device if mode in ("baseline", "hybrid") else "cpu",
                    "corridor_weights": config.corridor_weights,
                    "grid_distribution": "point",
                },
                where="iamp eval --set",
            )
            for mode in config.modes
        }
        first = mode_configs[config.modes[0]]  # --set applies to every mode: one grid, one set of stencils
        # (in the folder --set stencil_cache_dir names, as the stage would: it was ignored here)
        stencils = load_or_build_stencils(grid_config(first), first.stencil_cache_dir or None) if {"baseline", "hybrid"} & set(config.modes) else None
        self.predictors = {
            mode: MarkovPredictor(mode_config, producer=f"eval-{mode}", stencils=stencils) for mode, mode_config in mode_configs.items()
        }
        self.acc = {mode: _ModeAccumulator() for mode in config.modes}
        self.intentions_config = IntentionsConfig.from_params({"seed": config.seed, **dict(config.intentions_params)}, where="iamp eval --set-intentions")
        self.ar_config = None
        if "hybrid" in config.modes:
            from stages.ar_inference import ARInferenceConfig

            self.ar_config = ARInferenceConfig.from_params(  # over the chain's input cells unless --set-ar says otherwise
                {"model": str(config.model_path) if config.model_path else "", "device": config.device, **first.input_cells(),
                 **dict(config.ar_params)},
                where="iamp eval --model/--set-ar",
            )
            cells = {k: getattr(self.ar_config, k) for k in first.input_cells()}
            if cells != first.input_cells():  # the profiles' cells must be the chain's (the launcher refuses such a pipeline too)
                differ = ", ".join(f"{k} = {cells[k]!r} (--set-ar) but {v!r} (--set)" for k, v in first.input_cells().items() if cells[k] != v)
                raise ConfigError(f"the AR profiles' input cells differ from the chain's: {differ}; set them for both,"
                                  " e.g. --set n_inputs=12 --set-ar n_inputs=12")
        self.intentions_ms: list[float] = []
        self.ar_ms: list[float] = []
        self.ar_examples: list[dict[str, Any]] = []
        self.skipped: collections.Counter[str] = collections.Counter()
        self.load_reports: dict[str, LoadReport] = {}  # per recording: the rows its loader skipped, flagged or repaired
        self.stage_issues: collections.Counter[str] = collections.Counter()  # "stage:kind" -> issues the cores flagged
        self.stage_issue_examples: dict[str, str] = {}
        self.skip_examples: dict[str, str] = {}  # per reason, the first occurrence (printed under the table)
        self.instants = 0
        self.figures: dict[str, _Figure] = {}  # per recording: the instant with the most windows
        self.signal_split = False  # some window had signal phases (by_signal in the report)
        self.recordings: list[str] = []
        #: per mode, per recording: what its predictor had learnt online at the end of that recording (``MarkovPredictor.learnt``)
        self.learnt_by_recording: dict[str, dict[str, dict[str, Any]]] = {}
        self.situations: tuple[Situation, ...] = tuple(config.situations)
        self.situation_seen: dict[str, dict[str, Any]] = {}  # per situation: vehicles seen, frames played, frame period
        self.tau_s = self.predictors[config.modes[0]].config.tau_s
        n_steps = self.predictors[config.modes[0]].config.n_steps
        # the nearest prediction step to each horizon (0-based; a tie goes to the later step)
        self.track_steps = [min(max(int(math.floor(h / self.tau_s + 0.5 + 1e-9)), 1), n_steps) - 1 for h in TRACK_HORIZONS_S]

    # ----- data ---------------------------------------------------------------------

    def _load(self) -> list[Recording]:
        """The selected recordings, sequence by sequence: one whose files cannot be read is left out and counted
        (``unreadable_sequences``). A data folder, recording or sequence that is not there raises ``DatasetError``
        (a bad command line)."""
        cfg = self.config
        refs = {ref.name: ref for ref in discover(cfg.data_dir)}
        out = []
        for name in list(cfg.recordings) or default_recordings(cfg.data_dir, list(refs)):
            ref = refs.get(name) or find_recording(cfg.data_dir, name)
            wanted = list(dict.fromkeys(cfg.sequences)) or list(ref.sequence_ids)
            for want in wanted:
                if not any(same_sequence_id(s, want) for s in ref.sequence_ids):
                    raise DatasetError(f"recording {name}: no track file for sequence {want!r}; available: {', '.join(ref.sequence_ids)}")
            parts = []
            for want in wanted:
                try:
                    parts.append(load_ref(ref, (want,), display_root=Path(cfg.data_dir)))
                except DatasetError as exc:
                    self._skip("unreadable_sequences", f"{name} sequence {want}: {exc}")
            if parts:
                report = parts[0].report.merged(*(p.report for p in parts[1:]))
                out.append(dataclasses.replace(parts[0], sequences=tuple(s for p in parts for s in p.sequences), report=report))
                self.load_reports[name] = report
        return out

    def _stage_issues(self, stage: str, issues: list) -> None:
        """Count what a core of the chain flagged (a position jump, a restarted track, a car off the map): the oddities
        of the data, as a stage on the bus counts them in its NodeStats."""
        for issue in issues:
            key = f"{stage}:{issue.kind}"
            self.stage_issues[key] += 1
            self.stage_issue_examples.setdefault(key, f"agent {issue.agent_id}: {issue.detail}")

    def _model_provenance(self) -> dict[str, Any]:
        """Hybrid's model by name and hash (``model_name``), the recordings it was trained on as its file says
        (``model_trained_on``) and those of this evaluation among them (``model_in_sample``: hybrid's figures there are
        in-sample, optimistic); nothing without mode hybrid."""
        model = getattr(self, "_ar_model", None)
        if self.ar_config is None or model is None:
            return {}
        trained = [str(r) for r in ((getattr(model, "metadata", {}) or {}).get("recordings") or [])]
        out = {"model_name": self._ar_model_name, "model_trained_on": trained, "model_in_sample": [r for r in self.recordings if r in trained]}
        mismatch = self._spread_model_mismatch()
        if mismatch:
            out["warnings"] = [mismatch]
        return out

    def _grids_provenance(self) -> dict[str, Any]:
        """``grids``: which spread the scored grids carry (``spread_calibration``, ``spread_online``: calibrated by
        default, raw with ``spread_calibration = ""``), the recordings the table was fitted on as its file says
        (``spread_fitted_on``) and those of this evaluation among them (``spread_in_sample``: coverage and NLL there
        are in-sample, optimistic; means and mADE do not depend on the spread)."""
        if not self.predictors:
            return {}
        cfg = next(iter(self.predictors.values())).config
        out: dict[str, Any] = {"spread_calibration": cfg.spread_calibration, "spread_online": bool(cfg.spread_online),
                               "spread_fitted_on": [], "spread_in_sample": []}
        if cfg.spread_calibration:
            fitted: set[str] = set()
            for predictor in self.predictors.values():
                try:
                    fitted.update(str(r) for r in (_spread_table(predictor).get("fitted_on", {}) or {}).get("recordings") or [])
                except (AttributeError, TypeError):
                    continue  # (the stage itself refused a bad file before this)
            out["spread_fitted_on"] = sorted(fitted)
            out["spread_in_sample"] = [r for r in self.recordings if r in fitted]
        return {"grids": out}

    def _spread_model_mismatch(self) -> str:
        """'' unless hybrid reads a spread table (``spread_calibration = FILE``) that ``iamp calibrate`` fitted with other
        AR weights than the ones scored: hybrid's spread belongs to its model (the table was applied without a word)."""
        hybrid = self.predictors.get("hybrid")
        table = hybrid.config.spread_calibration if hybrid is not None else ""
        if not table:
            return ""
        try:
            data = _spread_table(hybrid)
            fitted = data.get("fitted_on", {}) if "hybrid" in data.get("modes", {}) else {}
        except (AttributeError, TypeError):
            return ""
        sha = str(fitted.get("model_sha256") or "")
        ours = str(self._ar_model_name).rpartition("@")[2]
        if not sha or not ours or sha.startswith(ours):
            return ""
        return (f"spread_calibration = {table}{' (the default)' if table == 'shipped' else ''}: fitted with AR weights"
                f" {fitted.get('model', '?')} (sha256 {sha[:12]}), scored with {self._ar_model_name}: hybrid's coverage and NLL are"
                " those of another model's spread (the online spread corrects part of it); fit a table for these weights with"
                " `iamp calibrate --model` and pass it with --set spread_calibration=FILE")

    def _skip(self, reason: str, detail: str, count: int = 1) -> None:
        """Count ``count`` things skipped for ``reason``; the first one's ``detail`` is kept for the table."""
        self.skipped[reason] += count
        self.skip_examples.setdefault(reason, detail)

    def run(self) -> dict[str, Any]:
        recordings = self._load()
        usable = [rec for rec in recordings if rec.map_path is not None]
        if recordings and not usable:  # nothing to evaluate: the command line named the wrong data
            raise DatasetError(f"recording {recordings[0].name} has no map: expected maps/{recordings[0].name}.osm in {self.config.data_dir}")
        for rec in recordings:
            if rec.map_path is None:  # one recording of several without its map: counted, the others evaluated
                self._skip("recordings_without_map", f"{rec.name}: expected maps/{rec.name}.osm in {self.config.data_dir}")
        recordings = usable
        total = 0
        for rec in recordings:
            for seq in rec.sequences:
                total += seq.n_frames if not self.config.max_frames_per_sequence else min(seq.n_frames, self.config.max_frames_per_sequence)
        if not self.situations:
            self.situations = whole_recordings([rec.name for rec in recordings])
        known = {rec.name for rec in recordings}
        for sit in self.situations:
            if sit.recording not in known:
                raise DatasetError(f"situation {sit.name!r}: recording {sit.recording!r} is not evaluated; evaluated: {', '.join(sorted(known))}")
            self.situation_seen[sit.name] = {"vehicles": set(), "frames": 0, "seconds": 0.0}
        bar = progress_bar(total, self.config.progress, unit="frame", desc="iamp eval")
        try:
            for i, rec in enumerate(recordings):
                if i:  # each recording as a stage started on it: what was learnt online belongs to the one before
                    for predictor in self.predictors.values():
                        predictor.forget_location()
                self.recordings.append(rec.name)
                sha = file_sha256(rec.map_path) if rec.map_path is not None else ""
                for seq in rec.sequences:
                    self._sequence(rec, seq, sha, bar)
                for mode, predictor in self.predictors.items():
                    learnt = predictor.learnt()
                    if learnt:
                        self.learnt_by_recording.setdefault(mode, {})[rec.name] = learnt
        finally:
            bar.close()
        for sit in self.situations:  # a window that holds no frame (a typo in its sequence, or past the recording's end)
            if not self.situation_seen[sit.name]["frames"]:
                self._skip("situations_without_frames", f"situation {sit.name!r}: no frame of {sit.recording} in {sit.window_text()}")
        return self.report()

    def _sequence(self, rec: Recording, seq, map_sha256: str, bar) -> None:
        cfg = self.config
        needs_belief = any(p.config.corridor_weights == "intentions" or p.config.initial_box == "particles"
                           or (p.config.mode == "hybrid" and p.config.hybrid_stop_mixture) for p in self.predictors.values())
        chain = Chain(
            rec, seq, self.scene_maps, intentions=self.intentions_config if needs_belief else None, max_frames=cfg.max_frames_per_sequence,
            map_sha256=map_sha256, on_error=lambda stage, where, exc: self._skip(f"{stage}_error_frames", f"{where}: {type(exc).__name__}: {exc}"),
            run_id="eval", producer="eval", signals=cfg.signals, on_issues=self._stage_issues,
        )
        ar = None
        if self.ar_config is not None:
            from stages.ar_inference import ARInference

            ar = ARInference(self.ar_config, producer="eval", model=getattr(self, "_ar_model", None))
            self._ar_model = ar.model  # loaded once, shared by the sequences
            self._ar_model_name = getattr(self, "_ar_model_name", None) or ar.model_name
        for predictor in self.predictors.values():
            predictor.reset()
        self._estimators.setdefault(rec.name, []).append(chain.corridors.estimator)
        truth = ground_truth(seq)
        tau_ns = int(round(self.predictors[cfg.modes[0]].config.tau_s * 1e9))
        n_steps = self.predictors[cfg.modes[0]].config.n_steps
        stride_ns = int(round(cfg.stride_s * 1e9))
        first = int(seq.stamp_ns[0]) if seq.n_rows else 0
        situations = [s for s in self.situations if s.recording == rec.name and (not s.sequence or same_sequence_id(seq.id, s.sequence))]
        period_s = 1.0 / seq.frame_rate_hz if seq.frame_rate_hz > 0 else 0.0
        # hybrid_profiles "previous": the AR stage predicts at every frame, as on the bus, for the chains of the next
        lagged = [p for p in self.predictors.values() if getattr(p, "previous_profiles", False)]
        for item in chain:
            bar.update(1)
            inside = [s.name for s in situations if s.contains(rec.name, seq.id, item.stamp_ns)]
            for name in inside:
                seen = self.situation_seen[name]
                seen["frames"] += 1
                seen["seconds"] += period_s
                seen["vehicles"].update((seq.id, int(t)) for t, a in zip(item.frame.track_ids.tolist(), item.frame.agent_types.tolist())
                                        if AgentType(int(a)).is_vehicle)
            if item.corridor_set is None:
                continue  # no corridors: nothing to predict in this frame
            stamp, frame, scene, corridor_set, relation_set, belief = item.stamp_ns, item.frame, item.scene, item.corridor_set, item.relation_set, item.belief
            where = f"{rec.name} sequence {seq.id} stamp_ns {stamp}"
            if item.intentions_ms is not None:
                self.intentions_ms.append(item.intentions_ms)
            offset = stamp - first
            if offset % stride_ns > STAMP_TOL_NS and stride_ns - offset % stride_ns > STAMP_TOL_NS:  # (jittered stamps too)
                for predictor in self.predictors.values():
                    predictor.observe(corridor_set)
                if ar is not None and lagged:  # hybrid_profiles "previous": the next instant's chain reads this frame's
                    got = self._guarded("ar_inference_error_frames", where, lambda: ar.process(corridor_set, relation_set, frame, scene))
                    if got:
                        self._stage_issues("ar_inference", got[1])
                    for predictor in lagged:
                        predictor.remember_profiles(got[0] if got else None)
                elif ar is not None:
                    self._guarded("ar_inference_error_frames", where, lambda: ar.observe(corridor_set, relation_set, frame))
                continue
            profiles = None
            ar_ms = 0.0
            if ar is not None:
                t0 = time.perf_counter()
                got = self._guarded("ar_inference_error_frames", where, lambda: ar.process(corridor_set, relation_set, frame, scene))
                profiles = got[0] if got else None
                if got:  # what the model did with the frame (nan_prediction, pairs_capped, ...): counted as the bus counts it
                    self._stage_issues("ar_inference", got[1])
                ar_ms = (time.perf_counter() - t0) * 1e3
                self.ar_ms.append(ar_ms)
            keys = None
            if item.signal_state is not None:  # the recording has phases: the window's signal state at its start
                self.signal_split = True
                keys = signal_keys(relation_set, belief)
            self._instant(rec.name, seq.id, stamp, frame, corridor_set, relation_set, scene, truth, tau_ns, n_steps, belief, profiles,
                          situations=inside, ar_ms=ar_ms, signal_keys=keys)

    def _guarded(self, reason: str, where: str, call):
        """``call()``, or None when it raises: a core failing on one frame is counted under ``reason``, not fatal."""
        try:
            return call()
        except Exception as exc:  # noqa: BLE001 - a data condition never ends the evaluation
            self._skip(reason, f"{where}: {type(exc).__name__}: {exc}")
            return None

    def _instant(self, recording, sequence_id, stamp, frame, corridor_set: CorridorSet, relation_set: RelationSet | None,
                 scene, truth, tau_ns, n_steps, belief=None, profiles=None, situations=(), ar_ms: float = 0.0,
                 signal_keys=None) -> None:
        self.instants += 1
        windows: dict[int, tuple[np.ndarray, float]] = {}
        manoeuvres: dict[int, tuple[str, np.ndarray]] = {}  # per window: the true future's class, its along-track directions
        statuses = {v.track_id: v for v in corridor_set.vehicles}
        for row, track_id in enumerate(frame.track_ids.tolist()):
            if not AgentType(int(frame.agent_types[row])).is_vehicle:
                continue
            future = future_positions(truth.get(track_id), stamp, tau_ns, n_steps)
            if future is None:
                self._skip("no_full_future", f"{recording} sequence {sequence_id} stamp_ns {stamp} track {track_id}: its track ends"
                                             f" or has a gap within the next {n_steps * tau_ns * 1e-9:g} s")
                continue
            vehicle = statuses.get(track_id)
            if vehicle is None or vehicle.status != MatchStatus.MATCHED or not vehicle.corridors:
                status = "not in the corridor set" if vehicle is None else (
                    "matched, no corridor" if vehicle.status == MatchStatus.MATCHED else _status_name(vehicle.status))
                self._skip("not_matched", f"{recording} sequence {sequence_id} stamp_ns {stamp} track {track_id}: {status}")
                continue
            # the start-speed split uses the speed estimated from positions, as every mode does
            windows[track_id] = (future, float(vehicle.speed_mps))
            start = (float(frame.x_m[row]), float(frame.y_m[row]))  # the recorded position at t, that of the truth's track
            if not (math.isfinite(start[0]) and math.isfinite(start[1])):
                start = tuple(future[0])  # not reached on matched vehicles; keeps a bad row from stopping the evaluation
            manoeuvres[track_id] = (manoeuvre_class(start, future, tau_ns * 1e-9), along_track_directions(start, future))
        predictions: dict[str, FramePrediction] = {}
        where = f"{recording} sequence {sequence_id} stamp_ns {stamp}"
        for mode, predictor in self.predictors.items():
            t0 = time.perf_counter()
            try:
                prediction, issues = predictor.process(
                    corridor_set, relation_set, scene, frame, intention_belief=belief, acceleration_profiles=profiles if mode == "hybrid" else None
                )
            except Exception as exc:  # noqa: BLE001 - counted; the instant's windows are then scored for no mode
                self._skip(f"prediction_error_{mode}", f"{where}: {type(exc).__name__}: {exc}", len(windows))
                continue
            ms = (time.perf_counter() - t0) * 1e3
            self.acc[mode].frame_ms.append(ms)
            for name in situations:  # the paper's time per step: the whole prediction, the AR model's included
                self.acc[mode].situation_ms[name].append(ms + (ar_ms if mode == "hybrid" else 0.0))
            self.acc[mode].vehicles.append(len({p.track_id for p in prediction.pairs}))
            self.acc[mode].issues.update(i.kind for i in issues)
            predictions[mode] = prediction
        if len(predictions) < len(self.predictors):
            return  # every mode is scored on the same windows
        scores: dict[str, list[_WindowResult]] = {}
        for mode, prediction in predictions.items():
            acc = self.acc[mode]
            scores[mode] = []
            if mode == "hybrid" and profiles is not None:
                self._collect_accel_examples(recording, sequence_id, stamp, windows, statuses, truth, profiles, prediction)
            for track_id, (future, speed) in windows.items():
                try:
                    result = self._score(prediction, track_id, future, acc, statuses[track_id])
                except Exception as exc:  # noqa: BLE001
                    self._skip(f"score_error_{mode}", f"{where} track {track_id}: {type(exc).__name__}: {exc}")
                    continue
                if result is None:
                    self._skip(f"no_prediction_{mode}", f"{where} track {track_id}: no corridor prediction for it")
                    continue
                acc.overall.add(result)
                (acc.slow if speed <= SLOW_SPEED_MPS else acc.fast).add(result)
                acc.by_recording[recording].add(result)
                acc.calibration["overall"].add(result)
                acc.calibration["slow" if speed <= SLOW_SPEED_MPS else "fast"].add(result)
                for name in situations:
                    acc.by_situation[name].add(result)
                scores[mode].append(result)
                manoeuvre, directions = manoeuvres[track_id]
                acc.by_manoeuvre[manoeuvre].add(result)
                if signal_keys is not None:
                    acc.by_signal[signal_keys.get(track_id, "unknown")].add(result)
                if result.error_xy is not None:
                    along, cross = _along_cross(result.error_xy[self.track_steps], directions[self.track_steps])
                    acc.track_overall.add(along, cross)
                    acc.track_by_manoeuvre[manoeuvre].add(along, cross)
        current = self.figures.get(recording)
        n_moving = sum(1 for _f, v in windows.values() if v > SLOW_SPEED_MPS)
        if windows and scene is not None and (current is None or (n_moving, len(windows)) > (current.n_moving, current.n_windows)):
            rows = {int(t): i for i, t in enumerate(frame.track_ids)}
            self.figures[recording] = _Figure(
                n_windows=len(windows),
                n_moving=n_moving,
                recording=recording,
                sequence=sequence_id,
                stamp_ns=stamp,
                scene=scene,
                scene_maps=self.scene_maps,
                predictions=predictions,
                truths={t: f for t, (f, _) in windows.items()},
                starts={t: (float(frame.x_m[rows[t]]), float(frame.y_m[rows[t]])) for t in windows},
                frame=frame,
                corridor_set=corridor_set,
                scores={m: {"windows": len(r), "mADE_m": float(np.mean([w.made for w in r])) if r else float("nan"),
                            "mFDE_m": float(np.mean([w.mfde for w in r])) if r else float("nan")} for m, r in scores.items()},
            )

    def _collect_accel_examples(self, recording, sequence_id, stamp, windows, statuses, truth, profiles, prediction) -> None:
        """Keep, per window, the AR profile of the corridor the car followed and its true acceleration (the figure)."""
        by_pair = profiles.by_pair()
        for track_id, (future, _speed) in windows.items():
            vehicle = statuses[track_id]
            members = [b for b, p in enumerate(prediction.pairs) if p.track_id == track_id]
            corridors = [c for c in vehicle.corridors if any(prediction.pairs[b].corridor_id == c.corridor_id for b in members)]
            if not corridors:
                continue
            index, error, _second = followed_corridor(corridors, future)
            profile = by_pair.get((track_id, corridors[index].corridor_id))
            true_accel = future_accelerations(truth.get(track_id), stamp, int(round(profiles.step_s * 1e9)),
                                              profile.accel_mps2.shape[0] if profile is not None else 0)
            if profile is None or error > ROUTE_MAX_ERROR_M or true_accel is None:
                continue
            self.ar_examples.append({
                "recording": recording, "sequence": sequence_id, "track_id": track_id, "stamp_ns": stamp,
                "true": true_accel, "ar": np.asarray(profile.accel_mps2, np.float64), "probs": np.asarray(profile.input_probs, np.float64),
                "edges": np.asarray(profiles.input_edges_mps2, np.float64), "step_s": profiles.step_s, "chunk_s": profiles.chunk_s,
            })

    def _score(self, prediction: FramePrediction, track_id: int, future: np.ndarray, acc: _ModeAccumulator, vehicle) -> _WindowResult | None:
        cfg = self.config
        members = [b for b, p in enumerate(prediction.pairs) if p.track_id == track_id]
        if not members:
            return None
        ade, fde, weights, errors = [], [], [], []
        for b in members:
            means = prediction.mean_xy_m[b]
            bad = ~np.all(np.isfinite(means), axis=1)
            if np.any(bad):
                acc.nan_means += int(bad.sum())
                means = _fill_forward(means, prediction.pairs[b])
            errors.append(means - future)
            err = np.hypot(*(means - future).T)
            ade.append(float(err.mean()))
            fde.append(float(err[-1]))
            weights.append(prediction.pairs[b].probability)
        w = np.asarray(weights)
        w = w / w.sum() if w.sum() > 0 else np.full(len(weights), 1.0 / len(weights))
        grid = prediction.vehicle_grids.get(track_id)
        frame = prediction.grid_frame
        cells_true = frame.flat_index(future[:, 0], future[:, 1])
        covered, covered50, nll = 0, 0, 0.0
        covered_levels = np.zeros(len(COVERAGE_LEVELS), np.int64)
        for k in range(future.shape[0]):
            cells, values = grid.step(k, frame.n_cells) if grid is not None else (np.zeros(0, np.int64), np.zeros(0))
            value = 0.0
            if cells_true[k] >= 0 and cells.size:
                i = int(np.searchsorted(cells, cells_true[k]))
                if i < cells.size and cells[i] == cells_true[k]:
                    value = float(values[i])
            if value > 0 and value >= highest_density_threshold(values, cfg.coverage_level):
                covered += 1
            if value > 0 and value >= highest_density_threshold(values, 0.5):
                covered50 += 1
            if value > 0:
                covered_levels += value >= _region_thresholds(values)
            nll -= math.log(max(value, cfg.nll_floor))
        return _WindowResult(
            made=min(ade), mfde=min(fde), wade=float(np.dot(w, ade)), wfde=float(np.dot(w, fde)),
            steps=future.shape[0], covered=covered, nll=nll, covered50=covered50, route_hit=_route_hit(prediction, members, w, vehicle, future),
            error_xy=errors[int(np.argmin(ade))], covered_levels=covered_levels,
        )

    # ----- results ------------------------------------------------------------------

    def report(self) -> dict[str, Any]:
        cfg = self.config
        modes: dict[str, Any] = {}
        for mode, acc in self.acc.items():
            times = np.asarray(acc.frame_ms) if acc.frame_ms else np.full(1, np.nan)
            modes[mode] = {
                "overall": acc.overall.summary(),
                "by_speed": {"slow": acc.slow.summary(), "fast": acc.fast.summary()},
                "by_recording": {name: acc.by_recording[name].summary() for name in self.recordings},
                "by_manoeuvre": {m: acc.by_manoeuvre[m].summary() for m in MANOEUVRES},
                "frame_ms_median": float(np.median(times)),
                "frame_ms_p95": float(np.percentile(times, 95)),
                "vehicles_per_frame_mean": float(np.mean(acc.vehicles)) if acc.vehicles else float("nan"),
                "frames": len(acc.frame_ms),
                "nan_means": acc.nan_means,
                "issues": dict(sorted(acc.issues.items())),
            }
            along, cross = acc.track_overall.summary(self.track_steps, self.tau_s)
            split = {m: acc.track_by_manoeuvre[m].summary(self.track_steps, self.tau_s) for m in MANOEUVRES}
            modes[mode]["along_track_m"] = {"overall": along, "by_manoeuvre": {m: a for m, (a, _) in split.items()}}
            modes[mode]["cross_track_m"] = {"overall": cross, "by_manoeuvre": {m: c for m, (_, c) in split.items()}}
            n_steps = self.predictors[mode].config.n_steps
            # what hybrid learnt online (initial_blend, curve_choice, accel_shift, speed_lead): of the last recording at the
            # top level, and of each recording in learnt_by_recording (every recording starts afresh: run)
            modes[mode].update(self.predictors[mode].learnt())
            if mode in self.learnt_by_recording:
                modes[mode]["learnt_by_recording"] = self.learnt_by_recording[mode]
            modes[mode]["calibration"] = {
                "levels": list(COVERAGE_LEVELS),
                **{split: {"coverage": c.coverage(), "steps": c.steps} for split, c in acc.calibration.items()},
            }
            modes[mode]["error_by_step_m"] = {
                "t_s": [round((k + 1) * self.tau_s, 6) for k in range(n_steps)],
                **{split: {"mean": c.error_by_step(n_steps), "windows": c.windows} for split, c in acc.calibration.items()},
            }
            modes[mode]["by_situation"] = {}
            for sit in self.situations:
                ms = acc.situation_ms.get(sit.name, [])
                modes[mode]["by_situation"][sit.name] = {
                    **acc.by_situation[sit.name].summary(),
                    "time_per_step_ms": float(np.mean(ms)) if ms else float("nan"),
                    "instants": len(ms),
                }
            if self.signal_split:
                modes[mode]["by_signal"] = {k: acc.by_signal[k].summary() for k in SIGNAL_KEYS}
            if mode == "hybrid" and self.ar_ms:
                modes[mode]["ar_inference_ms_median"] = float(np.median(self.ar_ms))
                modes[mode]["ar_inference_ms_p95"] = float(np.percentile(self.ar_ms, 95))
        return {
            "data": str(cfg.data_dir),
            "recordings": self.recordings,
            "stride_s": cfg.stride_s,
            "corridor_weights": cfg.corridor_weights,
            "backend": cfg.backend,
            "device": cfg.device,
            "params": {k: v for k, v in cfg.params},
            "seed": cfg.seed,
            "instants": self.instants,
            "skipped": dict(sorted(self.skipped.items())),
            "skipped_examples": dict(sorted(self.skip_examples.items())),
            "load_report": {name: rep.as_dict() for name, rep in self.load_reports.items()},
            "stage_issues": {k: {"count": n, "first": self.stage_issue_examples.get(k, "")} for k, n in sorted(self.stage_issues.items())},
            "velocity_consistency": {name: self.velocity_consistency(name).as_dict() for name in self.recordings},
            "state_filter": {name: self.state_filter(name) for name in self.recordings},
            "intentions_ms_median": float(np.median(self.intentions_ms)) if self.intentions_ms else None,
            "model": str(self.ar_config.model) if self.ar_config is not None else None,
            **self._model_provenance(),
            **self._grids_provenance(),
            "situations": [
                {**sit.as_dict(), "vehicles": len(self.situation_seen.get(sit.name, {}).get("vehicles", ())),
                 "duration_s": round(self.situation_seen.get(sit.name, {}).get("seconds", 0.0), 3),
                 "frames": self.situation_seen.get(sit.name, {}).get("frames", 0)}
                for sit in self.situations
            ],
            "metrics": {
                "coverage50": "share of (vehicle, step) pairs whose true position is in the 50% highest-probability cells of the vehicle's centre-point grid",
                "coverage90": f"share of (vehicle, step) pairs whose true position is in the {cfg.coverage_level:.0%} highest-probability cells of the vehicle's centre-point grid",
                "nll": f"mean -ln max(P(true cell), {cfg.nll_floor:g}) over (vehicle, step), nats, {self.predictors[cfg.modes[0]].config.grid_cell_m} m cells",
                "mADE_m": "min over corridors of the ADE of the probability-weighted mean position",
                "wADE_m": "corridor-probability-weighted mean of the ADE",
                "calibration": "per speed split, the share of (vehicle, step) pairs whose true position is in the highest-probability"
                               " region of each nominal level (levels), the rule of coverage90",
                "error_by_step_m": "per speed split, the mean displacement error at each prediction step (t_s) of the corridor mADE scores",
                "by_situation": "per situation (situations), the statistics of a split plus time_per_step_ms: the mean wall time of one"
                                " prediction of all vehicles of the frame at the situation's instants (hybrid: AR inference included)",
            },
            "manoeuvre_classes": _MANOEUVRE_NOTE,
            "along_cross_track": _TRACK_NOTE,
            "modes": modes,
        }

    def velocity_consistency(self, recording: str) -> Consistency:
        """Reported vs position-implied velocity over the tracks of a recording (all its sequences)."""
        estimators = self._estimators.get(recording, [])
        config = estimators[0].config if estimators else EstimatorConfig()
        return consistency_of((d for e in estimators for d in e.decided), config)

    def state_filter(self, recording: str) -> list[dict[str, Any]]:
        """Per sequence of a recording: the state filter published at its end and the bank's back test."""
        return [e.backtest() for e in self._estimators.get(recording, [])]

    def write_figures(self, directory: Path, formats: tuple[str, ...] = ("png", "svg"), dpi: int = 100,
                      keep: dict[str, Any] | None = None) -> list[Path]:
        """The figures of the module docstring, one instant per recording; returns the files written (none without an
        instant). ``self.figure_index`` lists them (kind, recording, mode, stem, caption); ``keep``, when given, receives
        each matplotlib Figure by stem (the tests read the objects)."""
        from stages.offline import figures as fg

        directory.mkdir(parents=True, exist_ok=True)
        self.figure_index = []
        written: list[Path] = []

        def emit(fig, stem: str, **entry) -> None:
            written.extend(fg.save(fig, directory, stem, formats, dpi))
            self.figure_index.append({"stem": stem, **entry})
            if keep is not None:
                keep[stem] = fig

        paper = [m for m in ("hybrid", "baseline") if m in self.config.modes] or list(self.config.modes)
        lines = []
        for recording in self.recordings:
            fig = self.figures.get(recording)
            if fig is None:
                lines.append(f"{recording}: no instant with a full-future window, no figure")
                continue
            where = (f"{recording} sequence {fig.sequence} at t = {fig.stamp_ns * 1e-9:.1f} s ({fig.n_windows} vehicles with a full 4 s future,"
                     f" {fig.n_moving} above 2 m/s)")
            lines.append(f"{recording}: instant {where}, stamp_ns {fig.stamp_ns}")
            for mode in paper:
                emit(fg.grid_figure(fig, mode), f"grid_4s_{mode}_{recording}", kind="grid", recording=recording, mode=mode,
                     caption=f"Motion grid of {mode} at 4 s, {where}: the fused centre-point grid at the last step (log colour scale) "
                             "over the car lanelets; vehicles at t (scored ones blue, with their ids) and the corridors of the scored vehicles dashed.")
            emit(fg.comparison_figure(fig, paper), f"means_{recording}", kind="means", recording=recording, mode=" ".join(paper),
                 caption=f"Predicted mean positions every 0.4 s to 4 s of {', '.join(paper)} against the ground truth (black), {where}; "
                         "one line per corridor, its opacity the corridor's probability; the legend gives this instant's mADE/mFDE.")
            for e in self._accel_choice(recording, fig):
                err = float(np.abs(e["ar"] - e["true"]).mean())
                emit(fg.accel_figure(e), f"accel_{e['recording']}_{e['sequence']}_car{e['track_id']}_{e['stamp_ns'] // 1_000_000}ms",
                     kind="accel", recording=recording, mode="hybrid",
                     caption=f"AR acceleration distributions of car {e['track_id']}, {recording} sequence {e['sequence']} at t = "
                             f"{e['stamp_ns'] * 1e-9:.1f} s ({e['why']}): the {e['probs'].shape[0]} normal distributions over the input "
                             f"cells as grey intensity, the AR output red, the true acceleration blue; mean |AR - true| {err:.2f} m/s2.")
        text = ["instants (one per recording: the one with the most scored cars above 2 m/s, then the most scored cars):", *lines, "", "files:"]
        text += [f"{e['stem']}: {e['caption']}" for e in self.figure_index]
        (directory / "figures.txt").write_text("\n".join(text) + "\n")
        return written

    def _accel_choice(self, recording: str, fig: _Figure | None) -> list[dict[str, Any]]:
        """Up to two cars of a recording for the acceleration figure: the car of the drawn instant whose true acceleration
        varies most, and the hardest braking car of the recording (physically plausible truths only: K733's tracker
        jitter gives "true" accelerations of +-10 m/s2 that say nothing about the model)."""
        examples = [e for e in self.ar_examples if e["recording"] == recording and np.abs(e["true"]).max() <= 4.0]
        chosen: list[dict[str, Any]] = []
        at = [e for e in examples if fig is not None and e["stamp_ns"] == fig.stamp_ns and e["sequence"] == fig.sequence]
        if at:
            chosen.append({**max(at, key=lambda e: float(np.ptp(e["true"]))), "why": "the drawn instant's car whose true acceleration varies most"})
        rest = [e for e in examples if all(e["track_id"] != c["track_id"] or e["sequence"] != c["sequence"] for c in chosen)]
        if rest:
            chosen.append({**min(rest, key=lambda e: float(e["true"].min())), "why": "the recording's hardest braking car"})
        return chosen


def _region_thresholds(values: np.ndarray) -> np.ndarray:
    """``highest_density_threshold(values, level)`` for every level of ``COVERAGE_LEVELS`` (one sort)."""
    ordered = np.sort(values)[::-1]
    n = np.searchsorted(np.cumsum(ordered), np.asarray(COVERAGE_LEVELS), side="left")
    return ordered[np.minimum(n, ordered.size - 1)]


def _route_hit(prediction: FramePrediction, members: list[int], weights: np.ndarray, vehicle, future: np.ndarray) -> float | None:
    """route_top1 of one window (``stages.offline.truth.route_credit``: 1 when the followed corridor has the highest
    weight, 1/k for a k-way tie, 0 when not); None when the window does not count (fewer than two corridors, or the
    true future does not single one out: ``truth.route_decision``)."""
    by_id = {c.corridor_id: c for c in vehicle.corridors}
    corridors = [by_id.get(prediction.pairs[b].corridor_id) for b in members]
    if len(corridors) < 2 or any(c is None for c in corridors):
        return None
    followed = followed_corridor(corridors, future)
    if route_decision(followed, ROUTE_MAX_ERROR_M, ROUTE_TIE_M) is not None:
        return None
    return route_credit(weights, followed.index)


_MANOEUVRE_NOTE = (
    "by_manoeuvre: the class of the TRUE future of each window (stages.offline.truth.manoeuvre_class, from positions only),"
    " first that applies: stands (no future position >= 1 m from the start), turns (end vs start heading of the path > 30 deg),"
    " brakes / accelerates (speed over the last vs the first 0.8 s lower / higher by more than min(2 m/s, 30 % of the higher),"
    " at least 1 m/s), keeps_speed"
)
_TRACK_NOTE = (
    "along_track_m / cross_track_m: the error (predicted mean minus truth) of the corridor mADE scores (the smallest ADE),"
    " at 1/2/3/4 s (t_s: the nearest prediction step), split along the true direction of travel (the central difference of"
    " the true positions, backward at the last step; standing, < 0.2 m: the direction from the start) and across it;"
    " along mean: signed, + = ahead of the truth; cross mean_abs, rms, mean_left (+ = left of the truth); along^2 + cross^2"
    " = the squared error of the ADE; a step without a direction counts only in cross (the whole error), so along n <= cross n"
)


def _along_cross(error_xy: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Along-track (signed, + = ahead) and cross-track (signed, + = left) parts of errors (n, 2) given unit directions
    (n, 2) of the true travel; where a direction is NaN the along part is NaN and the cross part is the whole |error|."""
    ok = np.all(np.isfinite(directions), axis=1)
    u = np.where(ok[:, None], directions, 0.0)
    along = np.where(ok, np.einsum("ij,ij->i", error_xy, u), np.nan)
    cross = np.where(ok, u[:, 0] * error_xy[:, 1] - u[:, 1] * error_xy[:, 0], np.hypot(error_xy[:, 0], error_xy[:, 1]))
    return along, cross


def _fill_forward(means: np.ndarray, pair) -> np.ndarray:
    out = means.copy()
    last = None
    for k in range(out.shape[0]):
        if np.all(np.isfinite(out[k])):
            last = out[k].copy()
        elif last is not None:
            out[k] = last
    if not np.all(np.isfinite(out)):
        finite = out[np.isfinite(out).all(axis=1)]
        out[~np.isfinite(out).all(axis=1)] = finite[0] if finite.size else 0.0
    return out


# --------------------------------------------------------------------------- table


def _spread_table(predictor: MarkovPredictor) -> dict[str, Any]:
    """The spread file a predictor reads (``spread_calibration``, "shipped" resolved for its shape), parsed; {} where it
    reads none or the file does not read (the stage itself refused a bad file before this)."""
    table = predictor.config.spread_calibration
    if not table:
        return {}
    try:
        data = json.loads(spread_file(table, predictor.config.spread_shape).read_text())
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}


def format_table(report: dict[str, Any]) -> str:
    """The printed summary: per mode overall/slow/fast, then timing."""
    head = (f"{'mode':<12} {'split':<8} {'windows':>7} {'mADE':>7} {'mFDE':>7} {'wADE':>7} {'wFDE':>7} {'cov50':>6} {'cov90':>6} {'NLL':>6}"
            f" {'top1':>5} {'routes':>6}")
    lines = [f"WARNING: {w}" for w in report.get("warnings", [])]
    if report.get("model_name"):  # which model scored hybrid, and where its figures are in-sample
        inside = report.get("model_in_sample") or []
        lines.append(f"hybrid's model {report['model_name']}, trained on {', '.join(report.get('model_trained_on') or []) or 'recordings it does not name'}"
                     + (f": IN-SAMPLE on {', '.join(inside)} (hybrid's figures there are optimistic)" if inside else ": every scored recording held out"))
    grids = report.get("grids")
    if grids:  # which spread the coverage and NLL columns are of, and where its table is in-sample
        if not grids.get("spread_calibration"):
            lines.append("grids: raw (spread_calibration = \"\"" + (", online spread on" if grids.get("spread_online") else "")
                         + "): over-confident for moving cars")
        else:
            inside = grids.get("spread_in_sample") or []
            lines.append(f"grids: calibrated (spread table {grids['spread_calibration']}, fitted on {', '.join(grids.get('spread_fitted_on') or []) or 'recordings it does not name'}"
                         + (", online spread on)" if grids.get("spread_online") else ")")
                         + (f": IN-SAMPLE on {', '.join(inside)} (cov50, cov90 and NLL there are optimistic)" if inside else ""))
    lines += [head, "-" * len(head)]
    for mode, res in report["modes"].items():
        for split, stats in (("overall", res["overall"]), ("slow", res["by_speed"]["slow"]), ("fast", res["by_speed"]["fast"])):
            lines.append(
                f"{mode:<12} {split:<8} {stats['windows']:>7d} {stats['mADE_m']:>7.2f} {stats['mFDE_m']:>7.2f}"
                f" {stats['wADE_m']:>7.2f} {stats['wFDE_m']:>7.2f} {stats['coverage50']:>6.2f} {stats['coverage90']:>6.2f} {stats['nll']:>6.2f}"
                f" {stats['route_top1']:>5.2f} {stats['route_windows']:>6d}"
            )
    lines.extend(_manoeuvre_tables(report))
    lines.append("")
    for mode, res in report["modes"].items():
        lines.append(
            f"{mode:<12} frame time median {res['frame_ms_median']:.1f} ms, p95 {res['frame_ms_p95']:.1f} ms,"
            f" {res['vehicles_per_frame_mean']:.1f} vehicles per frame over {res['frames']} frames"
            + (f"; ar_inference median {res['ar_inference_ms_median']:.1f} ms, p95 {res['ar_inference_ms_p95']:.1f} ms"
               if "ar_inference_ms_median" in res else "")
        )
    if report.get("intentions_ms_median") is not None:
        lines.append(f"intentions (every frame) median {report['intentions_ms_median']:.1f} ms; corridor weights {report['corridor_weights']}")
    lines.append(f"instants {report['instants']}; skipped, by reason:" + ("" if report["skipped"] else " nothing"))
    examples = report.get("skipped_examples", {})
    for reason, count in report["skipped"].items():
        lines.append(f"  {reason:<28} {count:>7d}" + (f"  first: {examples[reason]}" if reason in examples else ""))
    for name, rep in report.get("load_report", {}).items():  # rows the loader left out or changed: fewer or other windows
        lines += report_lines(name, rep)
    if report.get("stage_issues"):
        lines.append("issues the stages flagged (frames are still predicted), by stage and kind:")
        for key, v in report["stage_issues"].items():
            lines.append(f"  {key:<40} {v['count']:>7d}  first: {v['first']}")
    for name, figures in report.get("velocity_consistency", {}).items():
        line = disagreement_line(Consistency(**figures), EstimatorConfig())
        if line is not None:
            lines.append(f"{name}: {line}")
    for name, sequences in report.get("state_filter", {}).items():
        if sequences:
            chosen = collections.Counter(f"{seq['accel_noise_m2ps3']:g}" for seq in sequences)
            longest = max(sequences, key=lambda seq: seq["samples"])
            rms = ", ".join(f"{q}: {v:.2f}" for q, v in longest["rms_m"].items())
            lines.append(
                f"{name}: state filter accel noise (m2/s3) published at the end, by sequence: "
                + ", ".join(f"{q} x{n}" for q, n in sorted(chosen.items(), key=lambda kv: float(kv[0])))
                + f"; back test rms of the longest ({longest['samples']} samples): {rms} m"
            )
    lines += _signal_table(report)
    return "\n".join(lines)


def _signal_table(report: dict[str, Any]) -> list[str]:
    """mADE / windows per signal state at the window start (recordings with signal phases only)."""
    modes = report["modes"]
    if not modes or not all("by_signal" in res for res in modes.values()):
        return []
    lines = ["", "by signal state at the window start (the car's group): mADE m (windows)",
             f"{'mode':<12} " + " ".join(f"{k:>16}" for k in SIGNAL_KEYS)]
    for mode, res in modes.items():
        cells = [f"{res['by_signal'][k]['mADE_m']:>7.2f} ({res['by_signal'][k]['windows']:>5d})" for k in SIGNAL_KEYS]
        lines.append(f"{mode:<12} " + " ".join(f"{c:>16}" for c in cells))
    return lines


_SHORT = {"stands": "stands", "turns": "turns", "brakes": "brakes", "accelerates": "accel", "keeps_speed": "keeps"}


def _manoeuvre_tables(report: dict[str, Any]) -> list[str]:
    """The two compact tables by manoeuvre of the true future: windows and mADE; along-track bias at 4 s."""
    modes = report["modes"]
    if not modes or not all("by_manoeuvre" in res for res in modes.values()):
        return []
    classes = [m for m in MANOEUVRES if m in next(iter(modes.values()))["by_manoeuvre"]]
    first = next(iter(modes.values()))
    cols = "".join(f" {_SHORT.get(m, m):>7}" for m in classes)
    lines = ["", f"{'by manoeuvre (true future)':<26} {'all':>7}{cols}"]
    lines.append(f"{'windows':<26} {first['overall']['windows']:>7d}" + "".join(f" {first['by_manoeuvre'][m]['windows']:>7d}" for m in classes))
    for mode, res in modes.items():
        lines.append(f"{'mADE ' + mode:<26} {res['overall']['mADE_m']:>7.2f}" + "".join(f" {res['by_manoeuvre'][m]['mADE_m']:>7.2f}" for m in classes))
    lines.append("")
    lines.append(f"{'along-track bias at 4 s (m, + ahead)':<36} {'all':>7}{cols}   (windows with a direction of travel at 4 s)")
    for mode, res in modes.items():
        along = res.get("along_track_m")
        if not along:
            continue
        cells = [along["overall"]["4s"]["mean"]] + [along["by_manoeuvre"][m]["4s"]["mean"] for m in classes]
        lines.append(f"{mode:<36}" + "".join(f" {v:>7.2f}" for v in cells))
    return lines


# --------------------------------------------------------------------------- command line


def eval_config(args) -> EvalConfig:
    """The ``EvalConfig`` of parsed ``add_arguments`` options (ValueError on bad ones)."""
    situations = ()
    if getattr(args, "situations", None) is not None:
        from stages.offline.situations import load_situations

        situations = load_situations(args.situations)
    return EvalConfig(
        situations=situations,
        params=_key_values(args.set, "--set"),
        intentions_params=_key_values(args.set_intentions, "--set-intentions"),
        ar_params=_key_values(args.set_ar, "--set-ar"),
        model_path=args.model,
        seed=args.seed,
        data_dir=args.data,
        recordings=tuple(args.recording),
        sequences=tuple(args.sequence),
        modes=tuple(dict.fromkeys(args.mode)),
        stride_s=args.stride,
        max_frames_per_sequence=max(args.max_frames, 0),
        corridor_weights=args.corridor_weights,
        backend=args.backend,
        device=args.device,
        progress=not args.no_progress,
        figures_dir=args.figures,
        signals=args.signals == "on",
    )


def run_cli(args) -> int:
    try:
        check_output(args.json, "--json")  # the outputs' places first: a bad one must not cost the run
        check_output(args.figures, "--figures", folder=True)
        check_output(getattr(args, "report", None), "--report", folder=True)
        evaluation = Evaluation(eval_config(args))
        report = evaluation.run()
    except ValueError as exc:  # DatasetError and bad options
        sys.stderr.write(f"iamp eval: error: {exc}\n")
        return 2
    print(format_table(report))
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(json_safe(report), indent=2, allow_nan=False))
        print(f"wrote {args.json}")
    formats = ("png", "svg") if getattr(args, "svg", "yes") == "yes" else ("png",)
    dpi = int(getattr(args, "dpi", 100))  # the parser keeps it in DPI_RANGE
    if args.figures is not None:
        for path in evaluation.write_figures(args.figures, formats, dpi):
            print(f"wrote {path}")
    if getattr(args, "report", None) is not None:
        from stages.offline.report import write_report

        command = "iamp " + " ".join(_quote(a) for a in getattr(args, "argv", ["eval"]))
        path = write_report(evaluation, report, args.report, command, formats=formats, dpi=dpi)
        print(f"wrote {path}")
    return 0


def _quote(arg: str) -> str:
    """A command-line word as a shell would need it; the development data folder as ``$IAMP_TAF_BW`` when it is that."""
    import os
    import shlex

    data = os.environ.get("IAMP_TAF_BW")
    if data and arg.rstrip("/") == data.rstrip("/"):
        return "$IAMP_TAF_BW"
    return shlex.quote(arg)


def _key_values(items, flag: str) -> tuple[tuple[str, Any], ...]:
    """KEY=VALUE options, values parsed as JSON where they parse."""
    out = []
    for item in items:
        key, sep, value = item.partition("=")
        if not sep:
            raise ValueError(f"{flag} {item!r}: expected KEY=VALUE")
        try:
            out.append((key.strip(), json.loads(value)))
        except json.JSONDecodeError:
            out.append((key.strip(), value))
    return tuple(out)




# --------------------------------------------------------------------------- progress and figures




def evaluate(config: EvalConfig) -> dict[str, Any]:
    """Run an evaluation and return its report (the dict written by ``--json``)."""
    evaluation = Evaluation(config)
    report = evaluation.run()
    if config.figures_dir is not None:
        evaluation.write_figures(config.figures_dir)
    return report


__all__ = ["EVAL_MODES", "EvalConfig", "Evaluation", "add_arguments", "eval_config", "evaluate", "format_table", "run_cli"]
