"""Mode ``hybrid``: the Markov chain driven by the AR model's acceleration distributions λ(k) (docs/method.md §8.5).

Reads the frame's ``AccelerationProfiles`` (``read``), gives each pair its
λ(0..K-1) (``pair_input``; a pair without one holds its measured
acceleration), starts the chain from λ(0) and after step k applies
Γ = colnorm(diag(λ(k+1)) Ψ), λ(k+1)·1ᵀ (``hybrid_input`` "direct"), or, with
``hybrid_speed_restriction``, λ(k+1) as the preference the baseline's
λ_speed cuts per state. With ``hybrid_rules``, λ_AR(k) is the preference
inside the baseline's whole rule set (speed, leader, crossing; its
``_BaselineInputs`` with ``ar_lam``), and ``hybrid_rules_standing`` "rules"
keeps the rules' own preference for standing vehicles: an experiment, off by
default (docs/evaluation.md: no gain on the held-out location). With
``hybrid_stop_mixture`` (an experiment, off by default) a moving pair's λ_AR(k) is mixed with a
braking input by the intentions stage's P(stop) on its corridor
(``stop_mixture``; docs/method.md §8.5). Two more experiments, off by default (docs/evaluation.md: chosen on
K729, worse on the held-out K733): ``hybrid_speed_restriction_curves`` false cuts λ_AR(k) by the speed limit
alone (``speed_profiles``; ``hybrid_curve_factors``, the default, scales the curvature by a factor the stage
chooses online by back testing, ``curve_choice.py``, ``MarkovPredictor.curve_factor``), and ``hybrid_initial_input`` "measured" starts a moving pair from its measured
acceleration instead of λ_AR(0) (``_stack_inputs``); "blend" from a normal at the precision-weighted mean of
λ_AR(0) and the measured acceleration, each weighted by 1/σ² (σ_a: the standard error of the measured slope),
with the model's spread (``blend_initial``; docs/evaluation.md).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from scipy.special import ndtr

from bus_schemas import AccelerationProfiles
from stages.lib.base import Issue
from stages.lib.markov import InputMatrix, InputReplaced, gamma_from_priority, kernels
from stages.markov_prediction import priority as pr
from stages.markov_prediction.chain import InputPriority
from stages.markov_prediction.modes.base import ChainInputs, InputModel, Messages, Pair, Predictor
from stages.markov_prediction.modes.baseline import Baseline, _BaselineInputs, speed_profiles, speed_restriction


class Hybrid(InputModel):
    """λ(k) per pair from the ar_inference stage; no leader or crossing restriction (the model saw those features)."""

    def read(self, messages: Messages, issues: list[Issue]) -> dict[tuple[int, int], np.ndarray] | None:
        """Per (track, corridor), λ(0..K-1) as a (K, M) array; None when the profiles are missing or unusable."""
        return _profiles(self.predictor, messages.acceleration_profiles, messages.stamp_ns, issues)

    def pair_input(self, track_id: int, corridor_id: int, data: Any, issues: list[Issue]) -> np.ndarray | None:
        if data is None:
            return None
        lam = data.get((track_id, corridor_id))
        if lam is None:
            issues.append(Issue("no_acceleration_profile", track_id, f"corridor {corridor_id}: no AR profile, measured acceleration held"))
        return lam

    def prepare_pairs(self, pairs: list[Pair]) -> None:
        """The compiled λ_speed of the pairs (``_compiled_speed``), made before their AR profiles come; ``start`` takes
        it when it gets these very pairs (the chain's batch: none screened out), else makes its own."""
        self._ahead = None
        if pairs and self._compiled_speed_applies():
            self._ahead = (list(pairs), [q.s_first_m for q in pairs], _compiled_speed(self.predictor, pairs))

    def _compiled_speed_applies(self) -> bool:
        cfg = self.predictor.config
        return not cfg.hybrid_rules and cfg.hybrid_speed_restriction and kernels.available() and cfg.backend in ("numpy", "cuda")

    def start(self, pairs: list[Pair], issues: list[Issue]) -> ChainInputs:
        p = self.predictor
        if p.config.hybrid_rules:  # λ_AR(k) as the preference inside the baseline's whole rule set
            if getattr(self, "_rules", None) is None:
                self._rules = Baseline(p)
            return _BaselineInputs(self._rules, pairs, issues, ar_lam=_stack_inputs(p, pairs, issues))
        lam_speed = None
        ahead = getattr(self, "_ahead", None)
        if p.config.hybrid_speed_restriction:
            if self._compiled_speed_applies():
                if ahead is not None and len(ahead[0]) == len(pairs) and all(a is q for a, q in zip(ahead[0], pairs)) \
                        and ahead[1] == [q.s_first_m for q in pairs]:
                    lam_speed, self._ahead = ahead[2], None  # prepare_pairs' (made for these very pairs, not used yet)
                else:  # (another batch, e.g. the curve choice's back test: prepare_pairs' is kept for its own pairs)
                    lam_speed = _compiled_speed(p, pairs)
            if lam_speed is None:
                lam_speed = speed_restriction(p, pairs)
        return _HybridInputs(p, pairs, lam_speed, issues)


class _HybridInputs(ChainInputs):
    def __init__(self, p: Predictor, pairs: list[Pair], lam_speed: np.ndarray | kernels.SpeedRestriction | None,
                 issues: list[Issue]) -> None:
        cfg = p.config
        self.lam = _stack_inputs(p, pairs, issues)
        self.with_interval = cfg.grid_distribution == "interval"
        lam = self.lam
        self.steps: list = []
        if lam_speed is not None:  # every step's preference λ(k+1) / max λ(k+1) at once (the same numbers as step by step)
            prefs = lam[:, 1:] / np.maximum(lam[:, 1:].max(axis=2, keepdims=True), 1e-12)
            prefs32 = prefs.astype(np.float32)
        for k in range(cfg.n_steps):
            if k + 1 >= cfg.n_steps:
                self.steps.append(None)  # the input after the last step does not change any output
            elif lam_speed is not None:
                pref = prefs[:, k]
                if isinstance(lam_speed, kernels.SpeedRestriction):  # compiled (kernels.SpeedRestriction): λ_speed filled on demand
                    pref = prefs32[:, k]
                    at_states = lambda b, v, s, pref=pref: lam_speed.priority_at_states(pref, b, v, s, cfg.forbid_threshold)  # noqa: E731
                    window = lambda lo, hi: lam_speed.full()[..., lo:hi]  # noqa: E731
                elif kernels.available():  # the same numbers, compiled (kernels.priority_at_states): no gather, no per-input passes
                    pref = prefs32[:, k]
                    at_states = lambda b, v, s, pref=pref: kernels.priority_at_states(lam_speed, pref, b, v, s, cfg.forbid_threshold)  # noqa: E731
                    window = lambda lo, hi: lam_speed[..., lo:hi]  # noqa: E731
                else:
                    at_states = lambda b, v, s, pref=pref: pr.combine_with_preference(lam_speed[b, :, v, s], pref[b], cfg.forbid_threshold)  # noqa: E731
                    window = lambda lo, hi: lam_speed[..., lo:hi]  # noqa: E731
                self.steps.append(InputPriority(  # built on the step's active s-window only, or on its occupied states
                    weights=lambda lo, hi, pref=pref, window=window: pr.combine_with_preference(window(lo, hi), pref, cfg.forbid_threshold),
                    at_states=at_states,
                    # compiled (kernels.SpeedRestriction): the propagator runs the whole chain in one call
                    # (chain.PriorityPropagator); either form: the torch backend builds λ on its device from it
                    restriction=lam_speed, preference=prefs32[:, k],
                    forbid_threshold=cfg.forbid_threshold,
                ))
            elif cfg.hybrid_input == "direct":
                self.steps.append(InputReplaced(probs=lam[:, k + 1]))
            else:
                self.steps.append(InputMatrix(gamma=gamma_from_priority(lam[:, k + 1], p.psi)))

    def initial(self) -> np.ndarray:
        return self.lam[:, 0]

    def step(self, k: int, marginals):
        return self.steps[k]

    def fixed_steps(self) -> list:
        return self.steps


def _compiled_speed(p: Predictor, pairs: list[Pair]) -> kernels.SpeedRestriction | None:
    """λ_speed of the pairs compiled, computed only at the states the chain visits (the numpy backend asks for no
    others): the numbers of ``speed_restriction``; None where a profile np.interp would read differently (not
    increasing: ``speed_restriction``, the numpy definition, then)."""
    adm, cells, weights = speed_profiles(p, pairs)
    try:
        return kernels.SpeedRestriction([q.s_m for q in pairs], adm, cells, p.v_centres, p.a_centres, weights, p.config.tau_s)
    except ValueError:
        return None


def _stack_inputs(p: Predictor, pairs: list[Pair], issues: list[Issue]) -> np.ndarray:
    """λ(0..K-1) of every pair as (B, K, M); a pair without a profile holds its measured acceleration; with
    ``hybrid_initial_input`` "measured" or "blend" a moving pair's λ(0) is its measured input or ``blend_initial``;
    with ``hybrid_start_accel_mps2`` > 0 a standing pair's (the part of its mixture that starts) is ``start_inputs``."""
    measured = p.measured_inputs(pairs)
    lam = np.stack([q.input_probs if q.input_probs is not None else np.repeat(measured[b][None], p.config.n_steps, axis=0)
                    for b, q in enumerate(pairs)])
    standing = np.array([q.start_rate_hz > 0 for q in pairs])
    shifted = [b for b, q in enumerate(pairs) if q.accel_shift_mps2 != 0.0 and q.input_probs is not None and not standing[b]]
    if shifted:  # hybrid_accel_shifts: the AR distributions of the moving pairs moved by the online choice's shift
        lam = lam.copy()
        edges = p.grid.input_edges()
        for b in shifted:
            lam[b] = shift_inputs(lam[b], pairs[b].accel_shift_mps2, edges)
    if p.config.hybrid_initial_input == "measured" and not np.all(standing):
        lam = lam.copy()
        lam[~standing, 0] = measured[~standing]
    elif p.config.hybrid_initial_input == "blend" and not np.all(standing):
        lam = lam.copy()
        edges = p.grid.input_edges()
        for b, q in enumerate(pairs):
            if not standing[b] and q.input_probs is not None:  # a pair without a profile holds its measurement already
                lam[b, 0] = blend_initial(edges, lam[b, 0], q.a_fit_mps2, q.a_fit_se_mps2, q.track_id, issues)
    elif p.config.hybrid_initial_input == "adaptive" and not np.all(standing) and getattr(p, "initial_blend", None) is not None:
        lam = adaptive_initial(p.initial_blend, p._history, p.grid.input_edges(), pairs, lam, standing, issues)
    if p.config.hybrid_stop_mixture:
        lam = stop_mixture(p, pairs, lam, standing)
    if p.config.hybrid_start_accel_mps2 > 0 and np.any(standing):
        lam = lam.copy()
        lam[standing] = start_inputs(p.grid.input_edges(), p.config.hybrid_start_accel_mps2, p.config.hybrid_start_sigma_mps2)[None, None]
    return lam


def shift_inputs(probs: np.ndarray, shift_mps2: float, edges: np.ndarray) -> np.ndarray:
    """(..., M) input distributions over equal cells (``edges``) moved by ``shift_mps2``: each cell's mass goes to its
    centre + shift, split linearly between the two cells around that point; mass beyond the end cells folds into them
    (as the AR stage folds its tails). The mean moves by the shift unless mass folds; the total is kept."""
    probs = np.asarray(probs, dtype=np.float64)
    edges = np.asarray(edges, dtype=np.float64)
    m = probs.shape[-1]
    width = float(edges[-1] - edges[0]) / m
    if not (math.isfinite(shift_mps2) and width > 0) or shift_mps2 == 0.0:
        return probs
    pos = np.arange(m) + shift_mps2 / width  # each cell's new place, in cells
    lo = np.floor(pos)
    frac = pos - lo
    out = np.zeros_like(probs)
    for target, weight in ((lo, 1.0 - frac), (lo + 1.0, frac)):
        idx = np.clip(target, 0, m - 1).astype(np.intp)
        for j in range(m):  # (a cell's two targets may fold onto one end cell: summed)
            out[..., idx[j]] += probs[..., j] * weight[j]
    return out


def stop_mixture(p: Predictor, pairs: list[Pair], lam: np.ndarray, standing: np.ndarray) -> np.ndarray:
    """(1 − P(stop))·λ_AR(k) + P(stop)·(a braking input that stops the pair at its stop position or behind its leader)
    for every moving pair with a P(stop) of the intentions stage (``hybrid_stop_mixture``)."""
    cfg = p.config
    edges = p.grid.input_edges()
    out = lam
    for b, q in enumerate(pairs):
        if standing[b] or not (q.p_stop > 0) or q.v0_mps <= cfg.standstill_speed_mps:
            continue
        d = q.stop_distance_m if np.isfinite(q.stop_distance_m) else np.inf
        rel = q.relation
        if rel is not None and rel.leader_track_id >= 0 and np.isfinite(rel.leader_gap_m):
            d = min(d, float(rel.leader_gap_m) - cfg.hybrid_stop_gap_m)
        a = 3.0 if d <= 0.5 else float(np.clip(q.v0_mps**2 / (2.0 * d), 0.5, 3.0)) if np.isfinite(d) else 0.5
        if out is lam:
            out = lam.copy()
        w = float(min(q.p_stop, 1.0))
        out[b] = (1.0 - w) * lam[b] + w * start_inputs(edges, -a, cfg.hybrid_start_sigma_mps2)[None]
    return out


def cell_moments(edges: np.ndarray, probs: np.ndarray) -> tuple[float, float]:
    """(mean, σ) of the density that is uniform inside each input cell with the cell's probability: the cell
    centres' mean and variance plus each cell's own width²/12 (σ > 0 even with all the mass in one cell)."""
    centres, spread = _cell_table(edges)
    probs = np.asarray(probs, dtype=np.float64) / float(np.sum(probs))
    mean = float(probs @ centres)
    return mean, float(np.sqrt(probs @ ((centres - mean) ** 2 + spread)))


_CELL_TABLES: dict[bytes, tuple[np.ndarray, np.ndarray]] = {}


def _cell_table(edges: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The cells' centres and width²/12 of ``edges`` (read only; kept per distinct edges: a chain has one set)."""
    edges = np.asarray(edges, dtype=np.float64)
    key = edges.tobytes()
    found = _CELL_TABLES.get(key)
    if found is None:
        centres, widths = 0.5 * (edges[1:] + edges[:-1]), np.diff(edges)
        found = (centres, widths**2 / 12.0)
        for a in found:
            a.flags.writeable = False
        if len(_CELL_TABLES) >= 64:  # (a bound for callers that make up edges)
            _CELL_TABLES.clear()
        _CELL_TABLES[key] = found
    return found


def precision_blend(mu_m: float, sigma_m: float, a: float, sigma_a: float) -> tuple[float, float]:
    """The Gaussian product of N(mu_m, sigma_m²) and N(a, sigma_a²): (mean, σ), mean = (mu_m/σ_m² + a/σ_a²) /
    (1/σ_m² + 1/σ_a²), σ = (1/σ_m² + 1/σ_a²)^-½. Both σ must be finite and > 0."""
    w_m, w_a = 1.0 / sigma_m**2, 1.0 / sigma_a**2
    return (w_m * mu_m + w_a * a) / (w_m + w_a), float(1.0 / np.sqrt(w_m + w_a))


def blend_initial(edges: np.ndarray, lam0: np.ndarray, a: float, sigma_a: float, track_id: int, issues: list[Issue]) -> np.ndarray:
    """``hybrid_initial_input`` "blend": λ(0) of a moving pair from the model's first distribution ``lam0`` (its mean
    μ_m and σ_m, ``cell_moments``) and the measured acceleration ``a`` with its standard error ``sigma_a``
    (``MarkovPredictor.measured_acceleration``): a normal at the precision-weighted mean (``precision_blend``) with
    the model's spread σ_m (the product's σ is the uncertainty of the mean, below both; the chain needs the spread
    of the input), over the input cells as ``start_inputs``. A noisy measurement leaves ~the model's mean, a
    precise one ~the measurement. No measurement (NaN, NaN: a young track) keeps ``lam0``; a non-finite
    acceleration or a standard error that is not finite and > 0 keeps it too, as issue ``bad_measured_acceleration``."""
    if math.isnan(a) and math.isnan(sigma_a):
        return lam0
    if not (math.isfinite(a) and math.isfinite(sigma_a) and sigma_a > 0):
        issues.append(Issue("bad_measured_acceleration", track_id, f"measured acceleration {a} ± {sigma_a} m/s²: AR λ(0) kept"))
        return lam0
    mu_m, sigma_m = cell_moments(edges, lam0)
    mean, _ = precision_blend(mu_m, sigma_m, a, sigma_a)
    return start_inputs(edges, mean, sigma_m)


def adaptive_initial(learnt, histories, edges: np.ndarray, pairs: list[Pair], lam: np.ndarray, standing: np.ndarray,
                     issues: list[Issue]) -> np.ndarray:
    """``hybrid_initial_input`` "adaptive": each moving pair with a profile and a measured acceleration a starts from a
    normal of the model's spread σ_m at μ_m + w·(a − μ_m), w the weight ``learnt`` (``initial_blend.OnlineInitialBlend``)
    has learnt from the records whose window ended by this frame's stamp (resolved here from the vehicles' speed
    ``histories``, not when a speed comes in: the frame's outputs do not depend on whether a later frame was observed
    first); 0: λ(0) of the model kept. Each such vehicle is then recorded once for this frame (μ_m the mean over its
    pairs). Pairs without a measurement keep the model's λ(0); a measurement that is not finite, issue
    ``bad_measured_acceleration`` (once per vehicle)."""
    if pairs:
        learnt.resolve(histories, max(q.stamp_ns for q in pairs))
    w = learnt.weight
    out = lam if w <= 0.0 else lam.copy()
    means: dict[int, tuple[int, float, list[float]]] = {}  # track -> (stamp, a, the μ_m of its pairs)
    bad: set[int] = set()
    for b, q in enumerate(pairs):
        if standing[b] or q.input_probs is None:
            continue
        a = q.a_fit_mps2
        if math.isnan(a) and math.isnan(q.a_fit_se_mps2):  # no measurement yet (a young track)
            continue
        if not math.isfinite(a):
            if q.track_id not in bad:
                bad.add(q.track_id)
                issues.append(Issue("bad_measured_acceleration", q.track_id, f"measured acceleration {a} m/s²: AR λ(0) kept"))
            continue
        mu_m, sigma_m = cell_moments(edges, lam[b, 0])
        means.setdefault(q.track_id, (q.stamp_ns, a, []))[2].append(mu_m)
        if w > 0.0:
            out[b, 0] = start_inputs(edges, mu_m + w * (a - mu_m), sigma_m)
    for track_id, (stamp, a, mus) in means.items():
        learnt.record(track_id, stamp, a, mus[0] if len(mus) == 1 else float(np.mean(mus)))  # (the mean of one is itself)
    return out


def start_inputs(edges: np.ndarray, accel_mps2: float, sigma_mps2: float) -> np.ndarray:
    """(M,): a normal of mean ``accel_mps2`` and σ ``sigma_mps2`` over the input cells of ``edges`` (tails folded)."""
    cdf = ndtr((np.asarray(edges, dtype=np.float64) - accel_mps2) / sigma_mps2)
    cdf[0], cdf[-1] = 0.0, 1.0
    probs = np.diff(cdf)
    return probs / probs.sum()


def _profiles(p, profiles: AccelerationProfiles | None, stamp: int, issues: list[Issue]) -> dict[tuple[int, int], np.ndarray] | None:
    cfg, grid = p.config, p.grid
    if profiles is None:
        issues.append(Issue("no_acceleration_profiles", -1, "hybrid mode without acceleration_profiles: every pair falls back to its measured acceleration"))
        return None
    if int(profiles.header.stamp_ns) != stamp:
        issues.append(Issue("stamp_mismatch", -1, f"acceleration_profiles stamp {profiles.header.stamp_ns} != corridor_set stamp {stamp}: ignored"))
        return None
    edges = grid.input_edges()
    if profiles.input_edges_mps2.shape != edges.shape or not np.allclose(profiles.input_edges_mps2, edges, atol=1e-6):
        issues.append(Issue("bad_profile", -1, f"acceleration_profiles input edges {np.round(profiles.input_edges_mps2, 3).tolist()} != the chain's {edges.tolist()}: ignored"))
        return None
    if abs(profiles.chunk_s - cfg.tau_s) > 1e-6:
        issues.append(Issue("bad_profile", -1, f"acceleration_profiles chunk_s {profiles.chunk_s} != tau_s {cfg.tau_s}: ignored"))
        return None
    together = _profiles_together(profiles.profiles, grid.n_inputs, cfg.n_steps, issues)
    if together is not None:
        return together
    out: dict[tuple[int, int], np.ndarray] = {}
    for prof in profiles.profiles:
        probs = np.asarray(prof.input_probs, dtype=np.float64)
        if probs.ndim != 2 or probs.shape[1] != grid.n_inputs or probs.shape[0] < 1:
            issues.append(Issue("bad_profile", prof.track_id, f"corridor {prof.corridor_id}: input_probs shape {probs.shape}: pair falls back"))
            continue
        if not np.all(np.isfinite(probs)) or np.any(probs < 0) or np.any(probs.sum(axis=1) <= 0):
            issues.append(Issue("bad_profile", prof.track_id, f"corridor {prof.corridor_id}: input_probs not a distribution: pair falls back"))
            continue
        probs = probs / probs.sum(axis=1, keepdims=True)
        if probs.shape[0] < cfg.n_steps:  # a shorter profile holds its last distribution
            probs = np.vstack([probs, np.repeat(probs[-1:], cfg.n_steps - probs.shape[0], axis=0)])
        out[(prof.track_id, prof.corridor_id)] = probs[: cfg.n_steps]
    return out


def _profiles_together(profiles, n_inputs: int, n_steps: int, issues: list[Issue]) -> dict[tuple[int, int], np.ndarray] | None:
    """``_profiles``' loop over the profiles done on all of them at once when they have one shape (K', M), K' ≥ 1: the
    same checks, issues (in profile order) and numbers (each row normalised by its own sum, a short profile's last row
    held); None (the loop then runs) when the shapes differ."""
    if not profiles:
        return None
    arrays = [np.asarray(prof.input_probs, dtype=np.float64) for prof in profiles]
    shape = arrays[0].shape
    if len(shape) != 2 or shape[1] != n_inputs or shape[0] < 1 or any(a.shape != shape for a in arrays[1:]):
        return None
    probs = np.stack(arrays)  # (P, K', M)
    sums = probs.sum(axis=2, keepdims=True)
    good = np.isfinite(probs).all(axis=(1, 2)) & ~(probs < 0).any(axis=(1, 2)) & ~(sums[..., 0] <= 0).any(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):  # (the rows of profiles left out)
        probs = probs / sums
    if shape[0] < n_steps:  # a shorter profile holds its last distribution
        probs = np.concatenate([probs, np.repeat(probs[:, -1:], n_steps - shape[0], axis=1)], axis=1)
    probs = probs[:, :n_steps]
    out: dict[tuple[int, int], np.ndarray] = {}
    for n, prof in enumerate(profiles):
        if not good[n]:
            issues.append(Issue("bad_profile", prof.track_id, f"corridor {prof.corridor_id}: input_probs not a distribution: pair falls back"))
            continue
        out[(prof.track_id, prof.corridor_id)] = probs[n]
    return out
