"""Fixtures shared by the stage tests."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="module")
def frames():
    """The markov_prediction inputs of the first 120 frames of K729's longest sequence (the embedded data), from the real
    upstream stages (``stages.offline.chain``)."""
    from stages.corridors import SceneMaps
    from stages.intentions import IntentionsConfig
    from stages.lib.datasets import DEFAULT_DATA_DIR, load_recording
    from stages.offline.chain import chain_frames

    recording = load_recording(DEFAULT_DATA_DIR, "k729_2022-03-16")
    seq = max(recording.sequences, key=lambda q: q.n_rows)
    return [{"corridor_set": i.corridor_set, "relation_set": i.relation_set, "scene": i.scene, "track_frame": i.frame,
             "intention_belief": i.belief} for i in chain_frames(recording, seq, SceneMaps(), intentions=IntentionsConfig(), max_frames=120)
            if i.corridor_set is not None]
