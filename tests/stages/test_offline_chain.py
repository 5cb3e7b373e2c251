"""The offline tools' one chain (``stages.offline.chain``) and one ground truth (``stages.offline.truth``)."""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pytest

import bus_schemas as bs
from stages.corridors import SceneMaps
from stages.intentions import IntentionsConfig
from stages.lib.datasets import DEFAULT_DATA_DIR, DEFAULT_RECORDING, DEFAULT_SEQUENCE, load_recording
from stages.offline.chain import Chain, chain_frames, with_beliefs
from stages.offline.truth import followed_corridor, route_decision

OFFLINE = Path(__file__).resolve().parents[2] / "stages" / "offline"


def test_only_the_chain_builds_the_cores():
    built = re.compile(r"\b(TrackPlayer|CorridorBuilder|RelationExtractor|IntentionFilter)\(")
    offenders = [
        str(path.relative_to(OFFLINE)) for path in OFFLINE.rglob("*.py") if path.name != "chain.py" and built.search(path.read_text())
    ]
    assert offenders == []


def _corridor(cid, y_end):
    s = np.arange(0.0, 60.5, 0.5)
    y = np.where(s > 20.0, (s - 20.0) / 40.0 * y_end, 0.0)
    return bs.Corridor(
        corridor_id=cid, lanelet_ids=np.array([1], np.int64), lanelet_start_s_m=np.array([0.0]), x_m=s.copy(), y_m=y, s_m=s,
        heading_rad=np.zeros_like(s), curvature_1pm=np.zeros_like(s), width_m=np.full(s.shape, 3.5),
        extension_start_s_m=60.0, vehicle_s_m=0.0, vehicle_d_m=0.0, speed_limit_mps=13.9,
    )


def test_followed_corridor_judges_the_positions_on_the_corridor():
    corridors = (_corridor(1, 0.0), _corridor(2, 15.0))
    straight = np.column_stack([np.linspace(4, 40, 10), np.zeros(10)])
    followed = followed_corridor(corridors, straight)
    assert followed.index == 0 and followed.error_m == pytest.approx(0.0, abs=1e-9) and followed.runner_up_m > 2.0
    assert route_decision(followed) is None
    # a car standing at the corridors' start jitters behind it: those positions do not count
    standing = np.array([[-0.3, 0.1], [0.2, -0.1], [-0.2, 0.0]])
    assert followed_corridor(corridors, standing).error_m == pytest.approx(0.1)
    assert route_decision(followed_corridor(corridors, standing)) == "route_tied"  # before the branch
    # beyond the end nothing counts either; too few positions on the corridor: not followed
    beyond = np.column_stack([np.linspace(55, 100, 10), np.full(10, 40.0)])
    assert followed_corridor(corridors, beyond, min_inside=5).error_m == math.inf
    assert route_decision(followed_corridor(corridors, beyond, min_inside=5)) == "followed_no_corridor"


@pytest.fixture(scope="module")
def recording():
    return load_recording(DEFAULT_DATA_DIR, DEFAULT_RECORDING, (DEFAULT_SEQUENCE,))


def test_chain_plays_every_frame_and_beliefs_match_a_separate_filter(recording):
    maps = SceneMaps()
    seq = recording.sequences[0]
    inline = list(Chain(recording, seq, maps, intentions=IntentionsConfig(), max_frames=30))
    assert [f.index for f in inline] == list(range(30))
    assert all(f.corridor_set is not None and f.relation_set is not None and f.belief is not None for f in inline)
    assert all(f.stamp_ns == f.frame.header.stamp_ns for f in inline)
    plain = chain_frames(recording, seq, maps, max_frames=30, map_sha256=None)  # the map file's hash, as Chain by default
    assert all(f.belief is None for f in plain)
    later, ms = with_beliefs(plain, IntentionsConfig(), maps)
    assert len(ms) == 30
    for a, b in zip(inline, later):
        assert a.belief.encode() == b.belief.encode()


def test_chain_reports_a_failing_core_and_goes_on(recording, monkeypatch):
    from stages.relations import RelationExtractor

    def boom(self, *args, **kwargs):
        raise RuntimeError("boom")

    monkeypatch.setattr(RelationExtractor, "process", boom)
    errors = []
    frames = list(Chain(recording, recording.sequences[0], SceneMaps(), intentions=IntentionsConfig(), max_frames=5,
                        on_error=lambda stage, where, exc: errors.append((stage, where, str(exc)))))
    assert len(frames) == 5 and all(f.relation_set is None and f.corridor_set is not None for f in frames)
    assert [e[0] for e in errors] == ["relations"] * 5 and "boom" in errors[0][2] and DEFAULT_RECORDING in errors[0][1]
    with pytest.raises(RuntimeError, match="boom"):
        list(Chain(recording, recording.sequences[0], SceneMaps(), max_frames=5))
