"""Issue 13 item 5 over the real bus: a SceneInfo naming a file outside the data folder opens nothing.

A real corridors stage process (``python -m stages.corridors``, data folder
a copy of the embedded one) gets a SceneInfo whose ``map_name`` is the
absolute path of a FIFO outside that folder, then frames: it must not open
the FIFO (no reader ever holds it open; a blocking open would also hang the
stage, so frames would not come back), report one ``map_problem`` and go on
publishing CorridorSets. Then a scene of another sha256: one
``map_sha256_mismatch``, and the stage still answers every frame.
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import sys
from pathlib import Path

import pytest

import bus_schemas as bs
from testkit.helpers import endpoint, free_port, kill_all, output_of, start_module, stop_process, wait_until

from stages.lib.datasets import DEFAULT_DATA_DIR, DEFAULT_RECORDING, load_recording
from stages.tracks_source.core import TrackPlayer, TracksSourceConfig, file_sha256

RUN = "maphostile"
pytestmark = pytest.mark.skipif(not (DEFAULT_DATA_DIR / "maps").is_dir(), reason=f"embedded TAF-BW data not found at {DEFAULT_DATA_DIR}")


def _scene_and_frames(n: int):
    recording = load_recording(DEFAULT_DATA_DIR, DEFAULT_RECORDING, ["013"])
    player = TrackPlayer(TracksSourceConfig(recording=recording.name), recording, map_sha256=file_sha256(recording.map_path), run_id=RUN, producer="src")
    scene, frames = None, []
    for _stamp, result in player:
        scene = result.outputs.get("scene", scene)
        frames.append(result.outputs["track_frame"])
        if len(frames) == n:
            return scene, frames
    raise AssertionError("sequence too short")


def _reader_holds(fifo: Path) -> bool:
    try:
        os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))
    except OSError:
        return False
    return True


def test_a_scene_naming_a_file_outside_the_data_folder_opens_nothing_and_the_stage_goes_on(tmp_path):
    data = tmp_path / "data"
    (data / "maps").mkdir(parents=True)
    shutil.copyfile(DEFAULT_DATA_DIR / "maps" / f"{DEFAULT_RECORDING}.osm", data / "maps" / f"{DEFAULT_RECORDING}.osm")
    outside = tmp_path / "etc"
    outside.mkdir()
    fifo = outside / "passwd"
    os.mkfifo(fifo)
    scene, frames = _scene_and_frames(6)
    hostile = dataclasses.replace(scene, scene_id="hostile0000000000", map_name=str(fifo))
    wrong_hash = dataclasses.replace(scene, scene_id="wronghash0000000", map_sha256="0" * 64)
    port = free_port()
    got: list[int] = []
    from stages.runtime import BusClient

    with BusClient(listen=[endpoint(port)]) as bus:
        bus.subscribe(f"iamp/{RUN}/corridors/corridor_set", lambda k, d: got.append(bs.CorridorSet.decode(d).header.frame_index))
        scenes_received: list[int] = [0]  # the stage's own count of scenes, from its NodeStats

        def on_stats(_key: str, data: bytes) -> None:
            scenes_received[0] = bs.NodeStats.decode(data).counters.get("received.scene", 0)

        bus.subscribe(f"iamp/{RUN}/_stats/corridors", on_stats)
        stage = start_module(
            "stages.corridors", "--node-id", "corridors", "--run-id", RUN, "--connect", endpoint(port),
            "--input", "track_frame=src/track_frame", "--input", "scene=src/scene", "--params-json", json.dumps({"data": str(data)}),
            "--stats-period", "0.2",
        )
        try:
            wait_until(lambda: "corridors" in bus.alive_now(f"iamp/{RUN}/_alive/*", 0.5), 60, "corridors liveliness")
            put_scene, put_frame = bus.publisher(f"iamp/{RUN}/src/scene"), bus.publisher(f"iamp/{RUN}/src/track_frame")
            for k, (sc, part) in enumerate(((hostile, frames[:3]), (wrong_hash, frames[3:]))):
                put_scene(sc.encode())
                # a frame may overtake its scene on the wire: send the frames once the stage has the scene
                wait_until(lambda: scenes_received[0] >= k + 1, 60, f"the stage received scene {k + 1}")
                for frame in part:
                    put_frame(dataclasses.replace(frame, scene_id=sc.scene_id).encode())
                try:
                    wait_until(lambda: len(got) == 3 * (k + 1), 60, "a CorridorSet for every frame")
                except AssertionError as exc:
                    raise AssertionError(f"{exc}; got {got}; stage output:\n{output_of(stage)[-3000:]}") from None
                assert not _reader_holds(fifo)
            assert stage.poll() is None, output_of(stage)[-3000:]
            assert stop_process(stage) == 0
        finally:
            kill_all([stage])
    log = output_of(stage)
    problems = [ln for ln in log.splitlines() if "issue: kind=map_problem" in ln]
    assert len(problems) == 1 and "map_name_invalid" in problems[0], log[-3000:]  # once, not per frame
    assert sum("issue: kind=map_sha256_mismatch" in ln for ln in log.splitlines()) == 1, log[-3000:]
    assert "Traceback" not in log
    assert not _reader_holds(fifo)
