"""One vehicle's bad input never costs the frame: real frames of the embedded K729 sequence 019 with bad vehicles added.

The frame (4.1 s into sequence 019) comes from TrackPlayer → CorridorBuilder →
RelationExtractor → IntentionFilter on the embedded map, as the evaluation
runs them: four cars, 5720 following 5711 and 5761 following 5720 and 5753.
Copies of car 5711 with new track ids carry one bad input each; the real
cars' predictions must be exactly those of the frame without the copies,
the copies fall back (``pair_fallback_*``) or are left out (``pair_failed``,
``vehicle_failed``), each with its issue.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

import bus_schemas as bs
from stages.corridors import SceneMaps
from stages.lib.datasets import DEFAULT_DATA_DIR, load_recording
from stages.intentions import IntentionsConfig
from stages.offline.intentions_eval import chain_frames, run_filter
from stages.markov_prediction import MarkovPredictionConfig, MarkovPredictor

pytestmark = pytest.mark.skipif(
    not (DEFAULT_DATA_DIR / "maps").is_dir(), reason=f"embedded TAF-BW data not found at {DEFAULT_DATA_DIR}"
)

FRAME = 41  # sequence 019: cars 5711, 5720, 5753, 5761, all matched
SOURCE = 5711  # the car the bad copies are made of
REAL = (5711, 5720, 5753, 5761)
FAR, FAST, SHORT, NAN_RELATION, NAN_CURVATURE, OUTSIDE, RAISES, FAILS = range(90001, 90009)


@pytest.fixture(scope="module")
def item():
    scene_maps = SceneMaps()
    recording = load_recording(DEFAULT_DATA_DIR, "k729_2022-03-16", ("019",))
    frames = chain_frames(recording, recording.sequences[0], scene_maps)[: FRAME + 1]
    frames, _ = run_filter(frames, IntentionsConfig(), scene_maps)
    item = frames[FRAME]
    matched = {v.track_id for v in item.corridor_set.vehicles if v.status == bs.MatchStatus.MATCHED and v.corridors}
    assert matched == set(REAL)
    return item


@pytest.fixture(scope="module")
def config(item):
    x, y = np.asarray(item.frame.x_m), np.asarray(item.frame.y_m)
    extent = (float(x.min()) - 150.0, float(y.min()) - 150.0, float(x.max()) + 150.0, float(y.max()) + 150.0)
    return MarkovPredictionConfig(grid_extent_m=extent)  # the stage's defaults (intention weights, particle boxes), a fixed grid


@pytest.fixture(scope="module")
def stencils(config):
    return MarkovPredictor(config).stencils


def _vehicle(item, track_id: int) -> bs.VehicleCorridors:
    return next(v for v in item.corridor_set.vehicles if v.track_id == track_id)


def _copy(item, track_id: int, **changes) -> tuple[bs.VehicleCorridors, bs.VehicleBelief]:
    """Car SOURCE under a new track id (its corridors and belief too), with ``changes`` to its VehicleCorridors."""
    vehicle = dataclasses.replace(_vehicle(item, SOURCE), track_id=track_id, **changes)
    belief = next(b for b in item.belief.vehicles if b.track_id == SOURCE)
    return vehicle, dataclasses.replace(belief, track_id=track_id)


def _nan_relation(relation: bs.CorridorRelations, track_id: int) -> bs.CorridorRelations:
    """Every float field and float array of ``relation`` NaN (the leader id kept), one NaN conflict influencing."""
    changes = {}
    for f in dataclasses.fields(relation):
        value = getattr(relation, f.name)
        if isinstance(value, float):
            changes[f.name] = math.nan
        elif isinstance(value, np.ndarray) and value.dtype.kind == "f":
            changes[f.name] = np.full(value.shape, np.nan)
    nan1 = np.array([np.nan])
    conflict = dict(
        conflict_track_ids=np.array([SOURCE], np.int64), conflict_corridor_ids=np.array([relation.corridor_id], np.int64),
        conflict_kinds=np.ones(1, np.uint8), conflict_s_m=nan1, conflict_other_s_m=nan1, conflict_x_m=nan1, conflict_y_m=nan1,
        conflict_distance_m=nan1, conflict_other_distance_m=nan1, conflict_other_speed_mps=nan1, conflict_time_s=nan1,
        conflict_other_time_s=nan1, conflict_priority=np.array([-1], np.int8), influencing_index=0,
    )
    return dataclasses.replace(relation, **{**changes, **conflict}, track_id=track_id)


def _bad_frame(item):
    """The frame's inputs with the bad copies added: (corridor_set, relation_set, belief)."""
    source = _vehicle(item, SOURCE)
    first = source.corridors[0]
    short = dataclasses.replace(first, **_cut(first, first.vehicle_s_m - 1.0, first.vehicle_s_m + 1.5))
    copies = [
        _copy(item, FAR),
        _copy(item, FAST, speed_mps=60.0),
        _copy(item, SHORT, corridors=(short,)),
        _copy(item, NAN_RELATION),
        _copy(item, NAN_CURVATURE, corridors=tuple(dataclasses.replace(c, curvature_1pm=np.full(c.s_m.shape, np.nan)) for c in source.corridors)),
    ]
    vehicles = [v for v, _ in copies]
    beliefs = [b for _, b in copies]
    far = beliefs[0]
    on = {c.corridor_id: c.vehicle_s_m for c in source.corridors}
    beliefs[0] = dataclasses.replace(far, corridors=tuple(dataclasses.replace(c, s_mean_m=on[c.corridor_id] + 150.0) for c in far.corridors))
    relations = [_nan_relation(r, NAN_RELATION) for r in item.relation_set.relations if r.track_id == 5720]
    relations = [dataclasses.replace(r, corridor_id=c.corridor_id) for r, c in zip(relations, source.corridors)]
    cs = dataclasses.replace(item.corridor_set, vehicles=item.corridor_set.vehicles + tuple(vehicles))
    rs = dataclasses.replace(item.relation_set, relations=item.relation_set.relations + tuple(relations))
    belief = dataclasses.replace(item.belief, vehicles=item.belief.vehicles + tuple(beliefs))
    return cs, rs, belief


def _cut(corridor: bs.Corridor, lo: float, hi: float) -> dict:
    keep = (corridor.s_m >= lo) & (corridor.s_m <= hi)
    arrays = ("x_m", "y_m", "s_m", "heading_rad", "curvature_1pm", "width_m")
    return {a: np.asarray(getattr(corridor, a))[keep] for a in arrays} | {"extension_start_s_m": float(hi)}


def _predict(config, stencils, item, corridor_set, relation_set, belief, patch=None):
    predictor = MarkovPredictor(config, stencils=stencils)
    if patch is not None:
        patch(predictor)
    return predictor.process(corridor_set, relation_set, item.scene, item.frame, intention_belief=belief)


def _by_pair(prediction):
    return {(p.track_id, p.corridor_id): b for b, p in enumerate(prediction.pairs)}


def _assert_real_cars_unchanged(clean, dirty):
    """The real cars' pairs of ``dirty`` are those of ``clean`` (arrays, means, grids) to float32 rounding.

    The chain runs all pairs of a frame as one float32 batch; a batch that also
    holds the fallback vehicles is laid out differently, so BLAS may sum in
    another order (differences of ~1e-8, seen with numpy 2.4). Anything a bad
    vehicle really did to a real car would be orders of magnitude larger.
    """
    a, b = _by_pair(clean), _by_pair(dirty)
    real = [k for k in a if k[0] in REAL]
    assert real and all(k in b for k in real)
    for key in real:
        i, j = a[key], b[key]
        for name in ("position_probs", "interval_probs", "velocity_probs", "outside_mass", "mean_xy_m", "mean_s_m", "xy_at_mean_s_m"):
            np.testing.assert_allclose(getattr(clean, name)[i], getattr(dirty, name)[j], rtol=1e-5, atol=1e-7, err_msg=f"{name} of {key}")
    assert clean.grid_frame == dirty.grid_frame
    for track in REAL:
        for k in range(clean.step_times_s.shape[0]):
            ca, va = clean.vehicle_grids[track].step(k, clean.grid_frame.n_cells)
            cb, vb = dirty.vehicle_grids[track].step(k, dirty.grid_frame.n_cells)
            np.testing.assert_array_equal(ca, cb)
            np.testing.assert_allclose(va, vb, rtol=1e-5, atol=1e-7)


def _assert_constant_speed(prediction, b: int, speed_mps: float) -> None:
    """Pair ``b`` is predicted at a constant speed (the particles' mean, close to ``speed_mps``) from its s, exactly."""
    t, s = prediction.step_times_s, prediction.mean_s_m[b]
    v = (s[-1] - s[0]) / (t[-1] - t[0])
    np.testing.assert_allclose(s, prediction.pairs[b].vehicle_s_m + v * t, rtol=1e-9)
    assert abs(v - speed_mps) < 1.0


def _kinds(issues, track_id):
    return {i.kind for i in issues if i.agent_id == track_id}


def test_bad_vehicles_fall_back_and_the_real_cars_are_untouched(config, stencils, item):
    clean, clean_issues = _predict(config, stencils, item, item.corridor_set, item.relation_set, item.belief)
    assert not [i for i in clean_issues if i.kind.startswith("pair_") or i.kind in ("vehicle_failed", "particle_box_rejected")]
    cs, rs, belief = _bad_frame(item)
    dirty, issues = _predict(config, stencils, item, cs, rs, belief)
    _assert_real_cars_unchanged(clean, dirty)
    pairs = _by_pair(dirty)
    source = _vehicle(item, SOURCE)
    t = dirty.step_times_s

    # the observed failure: particles 150 m ahead of the measurement; their box is rejected, the chain starts at the measurement
    assert "particle_box_rejected" in _kinds(issues, FAR)
    for c in source.corridors:
        b = pairs[(FAR, c.corridor_id)]
        assert dirty.pairs[b].vehicle_s_m == pytest.approx(c.vehicle_s_m)
        assert dirty.pairs[b].s_first_m <= c.vehicle_s_m - config.window_behind_m + 1e-9
        np.testing.assert_allclose(dirty.position_probs[b].sum(axis=1) + dirty.outside_mass[b], 1.0, atol=1e-5)
        assert abs(dirty.mean_s_m[b, 0] - c.vehicle_s_m - source.speed_mps * t[0]) < 1.5

    # 60 m/s: above the chain's 20 m/s; constant speed along each corridor at the measured speed
    assert "pair_fallback_speed_above_vmax" in _kinds(issues, FAST)
    for c in source.corridors:
        b = pairs[(FAST, c.corridor_id)]
        np.testing.assert_allclose(dirty.mean_s_m[b], dirty.pairs[b].vehicle_s_m + 60.0 * t)  # from the particles' mean s

    # a corridor of 2.5 m: predicted, all its mass leaves the corridor, reported
    assert "corridor_too_short" in _kinds(issues, SHORT)
    assert dirty.outside_mass[pairs[(SHORT, source.corridors[0].corridor_id)], -1] > 0.99

    # NaN in every relation field: the leader and crossing restrictions are ignored, reported; the chain predicts
    assert "nan_relation" in _kinds(issues, NAN_RELATION)
    for c in source.corridors:
        b = pairs[(NAN_RELATION, c.corridor_id)]
        assert np.all(np.isfinite(dirty.position_probs[b]))
        np.testing.assert_allclose(dirty.position_probs[b].sum(axis=1) + dirty.outside_mass[b], 1.0, atol=1e-5)

    # NaN curvature: not chained, constant speed along the corridor
    assert "pair_fallback_nan_input" in _kinds(issues, NAN_CURVATURE)
    for c in source.corridors:
        _assert_constant_speed(dirty, pairs[(NAN_CURVATURE, c.corridor_id)], source.speed_mps)

    # the published messages carry every pair
    message = dirty.corridor_predictions(item.corridor_set.header, "test")
    assert {(p.track_id, p.corridor_id) for p in message.predictions} == set(pairs)


def _with_copies(item, *track_ids):
    copies = [_copy(item, t) for t in track_ids]
    cs = dataclasses.replace(item.corridor_set, vehicles=item.corridor_set.vehicles + tuple(v for v, _ in copies))
    belief = dataclasses.replace(item.belief, vehicles=item.belief.vehicles + tuple(b for _, b in copies))
    return cs, belief


def test_a_box_outside_the_window_or_a_raising_chain_costs_only_that_pair(config, stencils, item):
    clean, _ = _predict(config, stencils, item, item.corridor_set, item.relation_set, item.belief)
    cs, belief = _with_copies(item, OUTSIDE, RAISES, FAILS)

    def patch(predictor):
        pairs, markov, constant = predictor._pairs, predictor._markov, predictor._constant_velocity

        def bad_window(*args):  # OUTSIDE's window placed 500 m ahead of its box
            out = pairs(*args)
            for p in out:
                if p.track_id == OUTSIDE:
                    p.s_first_m += 500.0
            return out

        def bad_chain(group, issues):
            if any(p.track_id in (RAISES, FAILS) for p in group):
                raise FloatingPointError("stand-in for a failure inside the batched propagation")
            return markov(group, issues)

        def bad_constant(group):
            if any(p.track_id == FAILS for p in group):
                raise FloatingPointError("stand-in for a failure of the fallback")
            return constant(group)

        predictor._pairs, predictor._markov, predictor._constant_velocity = bad_window, bad_chain, bad_constant

    dirty, issues = _predict(config, stencils, item, cs, item.relation_set, belief, patch)
    _assert_real_cars_unchanged(clean, dirty)
    pairs = _by_pair(dirty)
    t = dirty.step_times_s
    source = _vehicle(item, SOURCE)
    assert _kinds(issues, OUTSIDE) >= {"pair_fallback_box_outside_window"}
    assert _kinds(issues, RAISES) >= {"pair_fallback_chain_failed"}
    assert "pair_failed" in _kinds(issues, FAILS) and not any(k[0] == FAILS for k in pairs)
    for c in source.corridors:
        for track in (OUTSIDE, RAISES):
            _assert_constant_speed(dirty, pairs[(track, c.corridor_id)], source.speed_mps)
    counts = {}
    for i in issues:
        counts[i.kind] = counts.get(i.kind, 0) + 1
    n = len(source.corridors)
    assert counts["pair_fallback_box_outside_window"] == n and counts["pair_fallback_chain_failed"] == 2 * n and counts["pair_failed"] == n


def test_a_vehicle_whose_pairs_raise_is_left_out(config, stencils, item):
    clean, _ = _predict(config, stencils, item, item.corridor_set, item.relation_set, item.belief)
    cs, belief = _with_copies(item, FAILS)

    def patch(predictor):
        acceleration = predictor._acceleration

        def bad(track_id, stamp_ns):
            if track_id == FAILS:
                raise KeyError("stand-in for a failure while building a vehicle's pairs")
            return acceleration(track_id, stamp_ns)

        predictor._acceleration = bad

    dirty, issues = _predict(config, stencils, item, cs, item.relation_set, belief, patch)
    _assert_real_cars_unchanged(clean, dirty)
    assert [i.kind for i in issues if i.agent_id == FAILS] == ["vehicle_failed"]
    assert not any(p.track_id == FAILS for p in dirty.pairs)


def test_the_window_always_holds_the_initial_box(config, stencils, item):
    """Particles ahead, behind, wide or far: the box passed to initial_state lies whole in the window."""
    predictor = MarkovPredictor(config, stencils=stencils)
    length = predictor.n_s * config.ds_m
    source = _vehicle(item, SOURCE)
    belief = next(b for b in item.belief.vehicles if b.track_id == SOURCE)
    cases = {(0.0, 0.1): False, (40.0, 0.5): False, (-40.0, 0.5): False, (90.0, 0.5): False, (-150.0, 0.5): False,
             (99.0, 0.5): True, (150.0, 0.5): True, (0.0, 30.0): True, (10.0, 200.0): True}  # -> particle box rejected
    for (offset, std), rejected in cases.items():
        changed = dataclasses.replace(belief, corridors=tuple(
            dataclasses.replace(c, s_mean_m=c.s_mean_m + offset, s_std_m=std) for c in belief.corridors))
        cs = dataclasses.replace(item.corridor_set, vehicles=(source,))
        issues = []
        pairs = predictor._pairs(cs, item.frame, 13.89, issues, {SOURCE: {c.corridor_id: c for c in changed.corridors}})
        boxes = predictor._boxes(pairs)
        lower = boxes["s_m"] - boxes["half_width_s_m"]
        upper = boxes["s_m"] + boxes["half_width_s_m"]
        assert np.all(lower >= -1e-9) and np.all(upper <= length + 1e-9), (offset, std, lower, upper)
        assert any(i.kind == "particle_box_rejected" for i in issues) == rejected, (offset, std, issues)
        measured = np.array([c.vehicle_s_m for c in source.corridors])
        s0 = np.array([p.s0_m for p in pairs])
        if rejected:
            np.testing.assert_array_equal(s0, measured)  # the measurement's box instead
        else:
            assert np.all(np.abs(s0 - measured - offset) < 5.0)
