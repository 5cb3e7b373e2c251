"""``MarkovPredictor.prepare``: the pairs built before the acceleration profiles come and the chain run before the
intentions stage's belief comes give, with ``update`` on the whole set after them, the outputs of ``update`` alone,
byte for byte, on real frames; nothing runs where the chain reads the belief, and a prepared phase is used only for
its own messages."""

from __future__ import annotations

import collections
import dataclasses

import numpy as np

import pytest

from stages.ar_inference import ARInference, ARInferenceConfig
from stages.corridors import SceneMaps
from stages.intentions import IntentionsConfig
from stages.lib.datasets import DEFAULT_DATA_DIR, load_recording
from stages.lib.datasets.superimpose import build_dense
from stages.lib.markov import MarkovGridConfig, load_or_build_stencils
from stages.markov_prediction import MarkovPredictionConfig, MarkovPredictor
from stages.markov_prediction import core as markov_core
from stages.markov_prediction.modes import hybrid as hybrid_mode
from stages.offline.chain import chain_frames

EARLY = frozenset({"intention_belief"})


@pytest.fixture(scope="module")
def frames(tmp_path_factory):
    """The stage's input sets of 25 frames of about 18 vehicles superimposed from the embedded K729 scenario
    (``build_dense``): moving and standing cars, several corridors each."""
    out_dir = tmp_path_factory.mktemp("dense")
    built = build_dense(DEFAULT_DATA_DIR, "k729_2022-03-16", 18, out_dir)
    recording = load_recording(out_dir, built.name)
    ar = ARInference(ARInferenceConfig(), producer="ar_inference")
    out = []
    for item in chain_frames(recording, recording.sequences[0], SceneMaps(data=out_dir), intentions=IntentionsConfig(), max_frames=40):
        profiles = ar.process(item.corridor_set, item.relation_set, item.frame, item.scene)[0]
        out.append({"corridor_set": item.corridor_set, "relation_set": item.relation_set, "scene": item.scene,
                    "track_frame": item.frame, "intention_belief": item.belief, "acceleration_profiles": profiles})
    return out[15:]


@pytest.fixture(scope="module")
def stencils():
    return load_or_build_stencils(MarkovGridConfig())


def _encoded(result):
    return ({k: m.encode() for k, m in result.outputs.items()},
            collections.Counter((i.kind, i.agent_id, i.detail) for i in result.issues))


def _without_belief(inputs):
    return {k: v for k, v in inputs.items() if k != "intention_belief"}


@pytest.mark.parametrize("mode", ["hybrid", "corridor_cv"])
def test_prepare_then_update_gives_the_outputs_of_update_alone(frames, stencils, mode, monkeypatch):
    alone = MarkovPredictor(MarkovPredictionConfig(mode=mode), stencils=stencils)
    early = MarkovPredictor(MarkovPredictionConfig(mode=mode), stencils=stencils)
    assert not early.chain_reads_belief
    phases = collections.Counter()
    for name in ("_chain_phase", "_pairs_phase"):
        real = getattr(MarkovPredictor, name)
        monkeypatch.setattr(MarkovPredictor, name, lambda self, *a, _real=real, _name=name, **k: phases.update([(_name, self)]) or _real(self, *a, **k))
    speed, testing = [], []
    real_speed = hybrid_mode._compiled_speed
    monkeypatch.setattr(hybrid_mode, "_compiled_speed", lambda p, pairs: (None if testing else speed.append(p)) or real_speed(p, pairs))
    real_back_test = MarkovPredictor._back_test  # (the online curve choice's own chains are not the frame's)
    monkeypatch.setattr(MarkovPredictor, "_back_test", lambda self, *a: testing.append(1) or real_back_test(self, *a) or testing.clear())
    weighted = 0
    for n, inputs in enumerate(frames):
        want = _encoded(alone.update(inputs))
        before = phases.copy()
        if n % 2:  # as the runtime offers it: the pairs once the corridors are in, the chain once all but the belief are
            head = {k: inputs[k] for k in ("corridor_set", "scene", "track_frame")}
            assert early.prepare(head, EARLY | {"acceleration_profiles", "relation_set"}) is True
            assert early.prepare({**head, "relation_set": inputs["relation_set"]}, EARLY | {"acceleration_profiles"}) is False  # done
        assert early.prepare(_without_belief(inputs), EARLY) is True
        result = early.update(inputs)
        # each phase ran once for the frame: update used the prepared ones, did not run them again
        assert phases[("_chain_phase", early)] == before[("_chain_phase", early)] + 1
        assert phases[("_pairs_phase", early)] == before[("_pairs_phase", early)] + 1
        assert _encoded(result) == want
        assert not [i for i in result.issues if i.kind == "curve_choice_failed"]
        # the corridor weights are the belief's, renormalised over the predicted corridors (set after the chain)
        belief = {(v.track_id, c.corridor_id): c.probability for v in inputs["intention_belief"].vehicles for c in v.corridors}
        by_track = collections.defaultdict(dict)
        for p in result.outputs["corridor_predictions"].predictions:
            by_track[p.track_id][p.corridor_id] = p.probability
        for track, got in by_track.items():
            raw = {c: belief[(track, c)] for c in got}
            assert got == pytest.approx({c: w / sum(raw.values()) for c, w in raw.items()}, abs=1e-12)
            weighted += len(got) > 1 and max(got.values()) > 0.6
    assert weighted > 0  # some vehicles' weights are far from uniform
    if mode == "hybrid":  # λ_speed made once per frame (ahead, with the pairs) where no pair is screened out of the chain
        assert 0 < speed.count(early) <= len(frames) + 2


def test_prepare_declines_where_the_chain_reads_the_belief_or_more_is_missing(frames, stencils):
    """Nothing where the chain reads the belief; the pairs alone without the profiles; nothing without the sizes."""
    inputs = frames[0]
    baseline = MarkovPredictor(MarkovPredictionConfig(mode="baseline"), stencils=stencils)  # particle boxes
    assert baseline.chain_reads_belief and baseline.prepare(_without_belief(inputs), EARLY) is False
    mixture = MarkovPredictor(MarkovPredictionConfig(mode="hybrid", hybrid_stop_mixture=True), stencils=stencils)
    assert mixture.chain_reads_belief and mixture.prepare(_without_belief(inputs), EARLY) is False
    hybrid = MarkovPredictor(MarkovPredictionConfig(mode="hybrid"), stencils=stencils)
    no_frame = {k: v for k, v in inputs.items() if k not in ("intention_belief", "acceleration_profiles", "track_frame")}
    assert hybrid.prepare(no_frame, EARLY | {"acceleration_profiles", "track_frame"}) is False  # the pairs need the sizes
    assert hybrid.prepare({"scene": inputs["scene"]}, EARLY) is False  # no corridor set
    assert hybrid._prepared is None and hybrid._prepared_pairs is None
    partial = {k: v for k, v in inputs.items() if k not in ("intention_belief", "acceleration_profiles")}
    assert hybrid.prepare(partial, EARLY | {"acceleration_profiles"}) is True  # the pairs ...
    assert hybrid.prepare(partial, EARLY | {"acceleration_profiles"}) is False  # ... once
    assert hybrid._prepared is None and hybrid._prepared_pairs is not None  # not the chain, without the profiles


def test_a_prepared_phase_is_used_only_for_its_own_messages(frames, stencils):
    """A set that is not the prepared one (the prepared set dropped, its stamp superseded) is predicted from its own
    messages: the outputs are those of a predictor that never prepared."""
    alone = MarkovPredictor(MarkovPredictionConfig(mode="hybrid"), stencils=stencils)
    early = MarkovPredictor(MarkovPredictionConfig(mode="hybrid"), stencils=stencils)
    a, b = frames[10], frames[11]
    alone.update(a)
    want = _encoded(alone.update(b))
    assert early.prepare(_without_belief(a), EARLY)
    early.update(a)
    # b's corridor set with a copy of a's other messages would not match either: identity, not equality, is checked
    assert early.prepare(_without_belief(a), EARLY)  # a stale prepared phase of an older set ...
    assert _encoded(early.update(b)) == want  # ... is not used for b
    assert early._prepared is None
    assert markov_core._same_messages(markov_core._frame_args(a), markov_core._frame_args(dict(a)))
    assert not markov_core._same_messages(markov_core._frame_args(a), markov_core._frame_args({**a, "corridor_set": b["corridor_set"]}))


def _by_pair(result):
    return {(p.track_id, p.corridor_id): p for p in result.outputs["corridor_predictions"].predictions}


def _same_prediction(a, b) -> bool:
    """Equal but for the last bits of the points on the map (a batch of other centrelines packs them differently)."""
    return all(np.allclose(getattr(a, f.name), getattr(b, f.name), rtol=0, atol=1e-9, equal_nan=True) for f in dataclasses.fields(a))


@pytest.mark.parametrize("where", ["_finish_geometry", "_finish_grids"])
@pytest.mark.parametrize("prepared", [True, False])
def test_a_vehicle_whose_outputs_raise_is_left_out_alone(frames, stencils, where, prepared, monkeypatch):
    """The outputs' weight-free part runs in the chain phase now: a pair whose outputs raise there or in the grids
    still costs only its own vehicle (``pair_failed``), with or without ``prepare``; the others' predictions are
    those of a clean run."""
    inputs = frames[5]
    want = _by_pair(MarkovPredictor(MarkovPredictionConfig(mode="hybrid"), stencils=stencils).update(inputs))
    failing = sorted({track for track, _ in want})[1]
    real = getattr(MarkovPredictor, where)

    def broken(self, pairs, *args):
        if any(p.track_id == failing for p in pairs):
            raise FloatingPointError("stand-in for a failure in the outputs")
        return real(self, pairs, *args)

    monkeypatch.setattr(MarkovPredictor, where, broken)
    predictor = MarkovPredictor(MarkovPredictionConfig(mode="hybrid"), stencils=stencils)
    if prepared:
        assert predictor.prepare(_without_belief(inputs), EARLY)
    result = predictor.update(inputs)
    got = _by_pair(result)
    assert {k for k in want if k[0] != failing} == set(got)
    assert all(_same_prediction(got[k], want[k]) for k in got)
    lost = [i for i in result.issues if i.kind == "pair_failed"]
    assert lost and {i.agent_id for i in lost} == {failing} and "stand-in" in lost[0].detail


@pytest.mark.parametrize("initial", ["blend", "adaptive"])
def test_the_next_frame_prepared_first_changes_nothing(frames, stencils, initial):
    """On the bus the pairs of frame n + 1 may be built (its vehicles' speeds observed) before frame n's chain has run
    (its profiles late): frame n's outputs are still those of frames taken in order."""
    # "blend", "adaptive": λ(0) from the speeds observed as well (the slope of each vehicle's recent speeds); "adaptive"
    # also learns its weight from the speeds that followed earlier records (here over 0.3 s, from the first record on)
    config = MarkovPredictionConfig(mode="hybrid", hybrid_initial_input=initial)
    in_order, ahead = MarkovPredictor(config, stencils=stencils), MarkovPredictor(config, stencils=stencils)
    for p in (in_order, ahead):
        if p.initial_blend is not None:
            p.initial_blend.min_records, p.initial_blend.window_s = 1, 0.3
    for inputs in frames[:3]:
        in_order.update(inputs)
        ahead.update(inputs)
    heads = [{k: f[k] for k in ("corridor_set", "scene", "track_frame")} for f in frames]
    for n in range(3, 12):
        want = _encoded(in_order.update(frames[n]))
        assert ahead.prepare(heads[n + 1], EARLY | {"acceleration_profiles", "relation_set"})  # frame n + 1's pairs, then ...
        assert _encoded(ahead.update(frames[n])) == want  # ... frame n
    assert any(v.speed_mps > 1.0 for v in frames[11]["corridor_set"].vehicles)  # moving vehicles (measured accelerations)
    if initial == "adaptive":  # it did learn, the same in both orders
        learnt = in_order.initial_blend.summary()
        assert learnt["resolved"] > 0 and learnt["weight"] > 0 and learnt == ahead.initial_blend.summary()


def test_work_ahead_on_a_later_set_is_not_taken_for_a_replay_started_again(frames, stencils):
    """``prepare`` on a set seconds ahead (under load the runtime offers the newest incomplete set while an earlier one
    waits for its belief) moved the stage's newest stamp, so the earlier set's ``update`` looked like a replay started
    again: every track reset (``stamp_went_back``), 44 times in a 12-minute run at 4x. A real restart still resets."""
    config = MarkovPredictionConfig(mode="hybrid")
    p = MarkovPredictor(config, stencils=stencils)
    stamp = lambda inputs: int(inputs["corridor_set"].header.stamp_ns)  # noqa: E731
    later = frames[-1]
    assert stamp(later) - stamp(frames[1]) > config.track_timeout_s * 1e9
    kinds = lambda result: [i.kind for i in result.issues]  # noqa: E731
    assert "stamp_went_back" not in kinds(p.update(frames[0]))
    assert p.prepare(_without_belief(later), EARLY) is True
    assert "stamp_went_back" not in kinds(p.update(frames[1]))
    assert "stamp_went_back" not in kinds(p.update(later))
    assert "stamp_went_back" in kinds(p.update(frames[2]))  # finished later's frame, then one 2 s before it: a restart
