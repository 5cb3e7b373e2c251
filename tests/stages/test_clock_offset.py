"""A live tracker stamps its frames with its own clock (wall-clock ns, ~1.8e18), a recording from 0: the stages must
predict the same either way. Only differences of stamps mean anything; an absolute stamp as float64 loses its last
8 bits, and a least-squares fit over such times depended on when the clock started (the corridors stage's
acceleration and markov_prediction's speed lines, by ~1e-7 m/s²)."""

from __future__ import annotations

import dataclasses

import bus_schemas as bs
from stages.ar_inference import ARInference, ARInferenceConfig
from stages.corridors import CorridorBuilder, CorridorsConfig, SceneMaps
from stages.intentions import IntentionFilter, IntentionsConfig
from stages.lib.datasets.defaults import DEFAULT_DATA_DIR
from stages.lib.datasets.loader import load_recording
from stages.markov_prediction import MarkovPredictionConfig, MarkovPredictor
from stages.relations import RelationExtractor, RelationsConfig
from stages.tracks_source.core import TrackPlayer, TracksSourceConfig

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
    recording = load_recording(DEFAULT_DATA_DIR, RECORDING)
    maps = SceneMaps()
    player = TrackPlayer(TracksSourceConfig(recording=RECORDING), recording, map_sha256="", run_id="clock", producer="source")
    corridors = CorridorBuilder(CorridorsConfig(), scene_maps=maps)
    relations = RelationExtractor(RelationsConfig(), scene_maps=maps)
    intentions = IntentionFilter(IntentionsConfig(), producer="intentions", scene_maps=maps)
    ar = ARInference(ARInferenceConfig.from_params({}, where="test"), producer="ar_inference")
    markov = MarkovPredictor(MarkovPredictionConfig.from_params({"mode": "hybrid", "corridor_weights": "intentions"}, where="test"),
                             producer="markov_prediction")
    scene, out = None, []
    for n, (_stamp, result) in enumerate(player):
        if n >= FRAMES:
            break
        if "scene" in result.outputs:
            scene = _restamped(result.outputs["scene"], offset_ns)
        frame = _restamped(result.outputs["track_frame"], offset_ns)
        corridor_set = corridors.process(frame, scene)[0]
        relation_set = relations.process(frame, corridor_set, scene)[0]
        belief = intentions.process(frame, corridor_set, relation_set, scene)[0]
        profiles = ar.process(corridor_set, relation_set, frame, scene)[0]
        result = markov.update({"corridor_set": corridor_set, "relation_set": relation_set, "scene": scene, "track_frame": frame,
                                "intention_belief": belief, "acceleration_profiles": profiles})
        markov.idle()
        out.append({name: _bytes_without_stamp(msg) for name, msg in (
            ("corridor_set", corridor_set), ("relation_set", relation_set), ("intention_belief", belief),
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
