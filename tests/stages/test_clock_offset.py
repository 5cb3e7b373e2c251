"""A live tracker stamps its frames with its own clock (wall-clock ns, ~1.8e18), a recording from 0: the stages must
predict the same either way. Only differences of stamps mean anything; an absolute stamp as float64 loses its last
8 bits, and a least-squares fit over such times depended on when the clock started (the corridors stage's
acceleration and markov_prediction's speed lines, by ~1e-7 m/s²)."""

from __future__ import annotations

import dataclasses

import bus_schemas as bs
from stages.ar_inference import ARInference, ARInferenceConfig
from stages.corridors import SceneMaps
from stages.intentions import IntentionsConfig
from stages.lib.datasets.defaults import DEFAULT_DATA_DIR
from stages.lib.datasets.loader import load_recording
from stages.markov_prediction import MarkovPredictionConfig, MarkovPredictor
from stages.offline.chain import Chain

RECORDING = "k733_2018-05-02"  # the busy default scenario, whose tracker's velocities the stages do not trust
#: 6 s of frames: before markov_prediction's online choices can resolve any sample (they sample vehicles by a hash of
#: the stamp, so after that the chosen values may switch at other frames on another clock: by design)
FRAMES = 60
WALL_CLOCK_NS = 1_796_510_259_325_833_659  # 2026-12-05T22:37:39Z


def _restamped(msg, offset_ns: int):
    return dataclasses.replace(msg, header=dataclasses.replace(msg.header, stamp_ns=msg.header.stamp_ns + offset_ns))


def _bytes_without_stamp(msg) -> bytes:
    return dataclasses.replace(msg, header=dataclasses.replace(msg.header, stamp_ns=0)).encode()


def _play(offset_ns: int) -> list[dict[str, bytes]]:
    """The offline chain (corridors, relations, intentions) on the recording's frames moved by ``offset_ns``, then
    ar_inference and markov_prediction (with its idle work) as on the bus."""
    recording = load_recording(DEFAULT_DATA_DIR, RECORDING)
    chain = Chain(recording, recording.sequences[0], SceneMaps(), intentions=IntentionsConfig(), max_frames=FRAMES,
                  frame_hook=lambda frame: _restamped(frame, offset_ns))
    ar = ARInference(ARInferenceConfig.from_params({}, where="test"), producer="ar_inference")
    markov = MarkovPredictor(MarkovPredictionConfig.from_params({"mode": "hybrid", "corridor_weights": "intentions"}, where="test"),
                             producer="markov_prediction")
    out = []
    for item in chain:
        profiles = ar.process(item.corridor_set, item.relation_set, item.frame, item.scene)[0]
        result = markov.update({"corridor_set": item.corridor_set, "relation_set": item.relation_set, "scene": item.scene,
                                "track_frame": item.frame, "intention_belief": item.belief, "acceleration_profiles": profiles})
        markov.idle()
        out.append({name: _bytes_without_stamp(msg) for name, msg in (
            ("corridor_set", item.corridor_set), ("relation_set", item.relation_set), ("intention_belief", item.belief),
            ("acceleration_profiles", profiles), ("corridor_predictions", result.outputs["corridor_predictions"]),
            ("motion_grid", result.outputs["motion_grid"]))})
    return out


def test_every_stage_predicts_the_same_on_a_wall_clock_as_from_zero():
    from_zero, on_wall_clock = _play(0), _play(WALL_CLOCK_NS)
    assert len(from_zero) == len(on_wall_clock) == FRAMES
    moving = [bs.decode(f["corridor_set"]) for f in from_zero]
    assert any(abs(v.accel_mps2) > 0.05 for cs in moving for v in cs.vehicles), "no vehicle with a fitted acceleration: the test would not see the fit"
    for name in from_zero[0]:
        differing = [k for k, (a, b) in enumerate(zip(from_zero, on_wall_clock)) if a[name] != b[name]]
        assert not differing, f"{name} differs on the wall clock at frames {differing[:10]}"
