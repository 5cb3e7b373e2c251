"""The dataset player core, in-process, and its command line failing early."""

from __future__ import annotations

import csv
import dataclasses
import itertools
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from bus_schemas import SceneInfo, TrackFrame
from stages.lib.base import ConfigError
from stages.lib.datasets import DEFAULT_DATA_DIR, DEFAULT_RECORDING
from stages.tracks_source import OUTPUTS, SPEC
from stages.tracks_source.core import TrackPlayer, TracksSourceConfig, resolve_selection, scene_id_of

REPO = Path(__file__).resolve().parents[2]
IND_SMALL = REPO / "tests/fixtures/ind_small"
TRACKS_DIR = DEFAULT_DATA_DIR / "recorded_trackfiles" / DEFAULT_RECORDING
WHERE = "node player (stages.tracks_source)"


def distinct_stamps_ms(*sequence_ids: str) -> list[list[int]]:
    """Per sequence, the sorted distinct timestamp_ms of its file (read independently)."""
    out = []
    for sid in sequence_ids:
        with (TRACKS_DIR / f"vehicle_tracks_{sid}.csv").open(newline="") as fh:
            out.append(sorted({int(r["timestamp_ms"]) for r in csv.DictReader(fh)}))
    return out


def play(config: TracksSourceConfig, run_id: str = "test", producer: str = "player") -> list:
    return list(TrackPlayer.open(config, run_id=run_id, producer=producer))


def test_default_scenario_plays_sequence_013_scene_first() -> None:
    sel = resolve_selection(TracksSourceConfig())
    assert (sel.data_dir, sel.recording, sel.sequences) == (DEFAULT_DATA_DIR, DEFAULT_RECORDING, ("013",))

    items = play(TracksSourceConfig())
    (stamps_ms,) = distinct_stamps_ms("013")
    assert len(items) == len(stamps_ms) == 1123

    first_stamp, first = items[0]
    scene = first.outputs["scene"]
    assert isinstance(scene, SceneInfo)
    assert list(first.outputs) == ["scene", "track_frame"]
    assert all("scene" not in r.outputs for _, r in items[1:])
    assert scene.recording == DEFAULT_RECORDING and scene.location_id == "K729"
    # "auto" configured: K729's measured projection is named
    assert scene.clock == "recording" and scene.projection == "utm" and scene.n_frames == 1123 and scene.frame_rate_hz == 10.0
    assert scene.map_name == "k729_2022-03-16.osm" and "/" not in scene.map_name  # a name in the maps folder, never a path
    assert len(scene.scene_id) == 16
    assert scene.scene_id == scene_id_of(scene.map_sha256, "auto", scene.origin_lat_deg, scene.origin_lon_deg)

    frames = [r.outputs["track_frame"] for _, r in items]
    assert all(isinstance(f, TrackFrame) for f in frames)
    assert [f.header.frame_index for f in frames] == list(range(len(frames)))
    stamps = np.array([s for s, _ in items])
    assert np.all(np.diff(stamps) > 0)
    np.testing.assert_array_equal(stamps, np.array(stamps_ms) * 1_000_000)
    assert all(f.header.stamp_ns == s for f, s in zip(frames, stamps))
    assert {(f.header.run_id, f.header.producer, f.scene_id) for f in frames} == {("test", "player", scene.scene_id)}
    assert first_stamp == scene.header.stamp_ns == frames[0].header.stamp_ns
    assert sum(len(f) for f in frames) == 3537  # every row of the file, once

    for f in frames[:50]:
        n = len(f)
        assert f.track_ids.dtype == np.int64 and f.agent_types.dtype == np.uint8
        for name in ("x_m", "y_m", "vx_mps", "vy_mps", "yaw_rad", "length_m", "width_m"):
            arr = getattr(f, name)
            assert arr.dtype == np.float64 and arr.shape == (n,), name
            assert np.all(np.isfinite(arr)), name
    assert not first.issues  # k729 013 needs no skip and no repair


def test_encode_decode_round_trip() -> None:
    items = play(TracksSourceConfig())
    busiest = max((r for _, r in items), key=lambda r: len(r.outputs["track_frame"]))
    for result in (items[0][1], busiest):
        for port, msg in result.outputs.items():
            back = OUTPUTS[port].schema.decode(msg.encode())
            assert type(back) is type(msg)
            for f in dataclasses.fields(msg):
                mine, theirs = getattr(msg, f.name), getattr(back, f.name)
                if isinstance(mine, np.ndarray):
                    assert theirs.dtype == mine.dtype and theirs.shape == mine.shape, f.name
                    np.testing.assert_array_equal(theirs, mine, err_msg=f.name)
                else:
                    assert theirs == mine, f.name
    assert len(busiest.outputs["track_frame"]) > 5


def test_sequences_play_back_to_back_with_increasing_stamps() -> None:
    seqs = ("002", "019", "022")
    items = play(TracksSourceConfig(sequences=seqs, speed="max"))
    per_seq = distinct_stamps_ms(*seqs)
    assert len(items) == sum(len(s) for s in per_seq)
    stamps = np.array([s for s, _ in items])
    assert np.all(np.diff(stamps) > 0)
    assert [r.outputs["track_frame"].header.frame_index for _, r in items] == list(range(len(items)))
    # each sequence starts one frame period (100 ms) after the previous one ended
    boundary = len(per_seq[0])
    assert stamps[boundary] - stamps[boundary - 1] == 100_000_000
    assert stamps[0] == per_seq[0][0] * 1_000_000  # the first keeps its own stamps
    # one scene: same map, projection and origin for all three
    assert sum("scene" in r.outputs for _, r in items) == 1


def test_a_wall_clock_moves_every_stamp_by_one_offset_from_the_wall_clock_at_the_start() -> None:
    seqs = ("002", "019")
    recorded = play(TracksSourceConfig(sequences=seqs, speed="max"))
    before = time.time_ns()
    wall = play(TracksSourceConfig(sequences=seqs, speed="max", clock="wall"))
    after = time.time_ns()
    assert len(wall) == len(recorded)
    offsets = {ws - rs for (ws, _), (rs, _) in zip(wall, recorded)}
    assert len(offsets) == 1  # the same intervals, so the same pacing and the same frames
    assert before <= wall[0][0] <= after
    assert [r.outputs["track_frame"].header.stamp_ns for _, r in wall] == [s for s, _ in wall]
    assert wall[0][1].outputs["scene"].clock == "wall" and recorded[0][1].outputs["scene"].clock == "recording"  # the scene says so
    with pytest.raises(ValueError, match="clock"):
        TracksSourceConfig(clock="utc")


def test_loop_starts_over_with_increasing_stamps_and_frame_index() -> None:
    player = TrackPlayer.open(TracksSourceConfig(sequences=("019",), loop=True), run_id="test", producer="player")
    n = player.n_frames_per_pass
    items = list(itertools.islice(player, 2 * n + 3))
    stamps = np.array([s for s, _ in items])
    assert np.all(np.diff(stamps) > 0)
    assert [r.outputs["track_frame"].header.frame_index for _, r in items] == list(range(2 * n + 3))
    assert sum("scene" in r.outputs for _, r in items) == 1


def test_load_problems_become_issues_on_the_first_result() -> None:
    items = play(TracksSourceConfig(data=str(IND_SMALL)))  # not the default folder: first recording, all sequences
    first = items[0][1]
    kinds = {i.kind for i in first.issues}
    assert {
        "bad_row_duplicate_frame",
        "bad_row_missing_field",
        "bad_row_non_numeric",
        "bad_row_non_finite_position",
        "bad_row_time_backwards",
        "unknown_agent_type",
        "repaired_size_defaulted",
    } <= kinds
    dup = next(i for i in first.issues if i.kind == "bad_row_duplicate_frame")
    assert dup.agent_id == -1 and dup.detail.startswith("count=1 first=recorded_trackfiles/01/01_tracks.csv:8:")
    assert all(not r.issues for _, r in items[1:])
    scene = first.outputs["scene"]
    assert (scene.recording, scene.location_id, scene.frame_rate_hz) == ("01", "4", 25.0)
    assert len(items) == 60


def test_projection_changes_the_scene_id() -> None:
    a = play(TracksSourceConfig(sequences=("019",)))[0][1].outputs["scene"]
    b = play(TracksSourceConfig(sequences=("019",), projection="utm"))[0][1].outputs["scene"]
    assert a.map_sha256 == b.map_sha256 and a.scene_id != b.scene_id and b.projection == "utm"


@pytest.mark.parametrize(
    "params, message",
    [
        ({"speed": 0}, "speed = 0.0: must be > 0"),
        ({"speed": -2.5}, "speed = -2.5: must be > 0"),
        ({"speed": "fast"}, "speed = 'fast': expected a number > 0 or 'max'"),
        ({"speed": True}, "parameter speed = True should be"),
        ({"loop": "yes"}, "parameter loop = 'yes' should be bool"),
        ({"sequences": "013"}, "parameter sequences = '013' should be"),
        ({"sequences": [13]}, "parameter sequences = [13] should be"),
        ({"projection": ""}, "projection must not be empty"),
        ({"speeed": 2.0}, "unknown parameter(s) speeed; known: clock, data, loop, projection, recording, sequences, signals, speed"),
    ],
)
def test_bad_config_values_name_the_node(params: dict, message: str) -> None:
    with pytest.raises(ConfigError) as exc:
        TracksSourceConfig.from_params(params, where=WHERE)
    assert str(exc.value).startswith(WHERE + ": ")
    assert message in str(exc.value)


def test_good_config_values() -> None:
    cfg = TracksSourceConfig.from_params({"speed": "max", "sequences": ["002", "013"], "loop": True}, where=WHERE)
    assert (cfg.speed, cfg.sequences, cfg.loop) == ("max", ("002", "013"), True)
    assert TracksSourceConfig.from_params({"speed": 2}, where=WHERE).speed == 2.0
    assert SPEC.kind == "source" and SPEC.restart_default is False and SPEC.inputs == {}
    assert OUTPUTS["scene"].latched and not OUTPUTS["track_frame"].latched


def test_missing_data_folder_exits_2_before_any_bus_activity() -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "stages.tracks_source", "--params-json", json.dumps({"data": "/nonexistent"})],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 2, proc.stderr
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, proc.stderr
    assert "ERROR iamp.tracks_source: bad configuration: data folder /nonexistent does not exist" in lines[0]
