"""Nothing from the bus names a file: the map-using stages find the scene's map by name in their own data folder.

A ``SceneInfo`` naming ``/etc/passwd``-like paths (absolute, ``../..``, a name
that exists only outside the data folder) makes no stage open that file: each
path is a FIFO the test creates outside the data folder, so a stage that
opened it for reading would block; the stages run in a worker thread and a
thread still blocked after the timeout fails the test (the FIFO is then
opened for writing to let it go). A map of another sha256 is reported once
and not resolved again per frame; an oversized (sparse) file is refused
before it is hashed.
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
import shutil
import sys
import threading
from pathlib import Path

import pytest

from bus_schemas import Header, SceneInfo, TrackFrame
from stages.corridors import CorridorBuilder, CorridorsConfig, SceneMaps
from stages.lib.maps import scene as map_scene
from stages.lib.datasets import DEFAULT_DATA_DIR, DEFAULT_RECORDING, load_recording
from stages.intentions import IntentionFilter, IntentionsConfig
from stages.relations import RelationExtractor, RelationsConfig
from stages.tracks_source.core import TrackPlayer, TracksSourceConfig, file_sha256

REPO = Path(__file__).resolve().parents[2]
MAP_NAME = f"{DEFAULT_RECORDING}.osm"

pytestmark = pytest.mark.skipif(not (DEFAULT_DATA_DIR / "maps" / MAP_NAME).is_file(), reason="embedded TAF-BW map not found")


@pytest.fixture(scope="module")
def played():
    """The source's own SceneInfo and the first frames of the embedded sequence."""
    recording = load_recording(DEFAULT_DATA_DIR, DEFAULT_RECORDING, ["013"])
    player = TrackPlayer(
        TracksSourceConfig(recording=recording.name), recording,
        map_sha256=file_sha256(recording.map_path), run_id="t", producer="source",
    )
    scene, frames = None, []
    for _stamp, result in player:
        scene = result.outputs.get("scene", scene)
        frames.append(result.outputs["track_frame"])
        if len(frames) == 4:
            break
    return scene, frames


@pytest.fixture()
def layout(tmp_path):
    """``tmp/data/maps/<map>`` (a copy of the embedded map) and FIFOs outside the data folder."""
    data = tmp_path / "deep" / "data"
    (data / "maps").mkdir(parents=True)
    shutil.copyfile(DEFAULT_DATA_DIR / "maps" / MAP_NAME, data / "maps" / MAP_NAME)
    outside = tmp_path / "etc"
    outside.mkdir()
    fifos = [outside / "passwd", outside / MAP_NAME.replace(".osm", "_x.osm")]
    for f in fifos:
        os.mkfifo(f)
    return data, outside, fifos


def _hostile_names(data: Path, outside: Path) -> list[str]:
    rel = os.path.relpath(outside / "passwd", data / "maps")
    return [
        str(outside / "passwd"),  # absolute
        rel,  # ../../../etc/passwd, relative to the maps folder
        "../../../etc/passwd",
        "..",
        MAP_NAME.replace(".osm", "_x.osm"),  # a plain name that exists only outside the data folder
        "passwd",
        f"x\n[launch] kind=no_map map {outside}/passwd unusable: forged",  # a forged log line
    ]


def _in_thread(fn, fifos, timeout_s: float = 60.0):
    """``fn()`` in a worker thread; fails (and frees the thread) if it is still running after the timeout: it opened a FIFO."""
    box: dict = {}

    def work():
        try:
            box["result"] = fn()
        except BaseException as exc:  # noqa: BLE001 - re-raised in the test thread
            box["error"] = exc

    t = threading.Thread(target=work, daemon=True)
    t.start()
    t.join(timeout_s)
    if t.is_alive():
        for f in fifos:  # let a blocked reader go: open the write end and close it (EOF)
            try:
                os.close(os.open(f, os.O_WRONLY | os.O_NONBLOCK))
            except OSError:
                pass
        t.join(10)
        pytest.fail("a stage opened a FIFO named by the scene (it blocked reading it)")
    if "error" in box:
        raise box["error"]
    return box["result"]


def _no_reader(fifos) -> None:
    """No process holds any FIFO open for reading now (opening the write end without blocking fails with ENXIO)."""
    for f in fifos:
        with pytest.raises(OSError):
            os.close(os.open(f, os.O_WRONLY | os.O_NONBLOCK))


def _run_stages(scene: SceneInfo, frames: list[TrackFrame], data: Path) -> dict[str, list[list]]:
    """Corridors, relations and intentions over the frames with one SceneMaps on ``data``; issues per stage per frame."""
    maps = SceneMaps(CorridorsConfig(data=str(data)))
    corridors = CorridorBuilder(CorridorsConfig(data=str(data)), scene_maps=maps)
    relations = RelationExtractor(RelationsConfig(data=str(data)))  # its own SceneMaps from its data parameter
    intentions = IntentionFilter(IntentionsConfig(data=str(data)))
    out: dict[str, list[list]] = {"corridors": [], "relations": [], "intentions": []}
    for frame in frames:
        rc = corridors.update({"track_frame": frame, "scene": scene})
        assert "corridor_set" in rc.outputs  # the stage goes on
        cs = rc.outputs["corridor_set"]
        rr = relations.update({"track_frame": frame, "corridor_set": cs, "scene": scene})
        assert "relation_set" in rr.outputs
        ri = intentions.update({"track_frame": frame, "corridor_set": cs, "relation_set": rr.outputs["relation_set"], "scene": scene})
        assert "intention_belief" in ri.outputs
        out["corridors"].append(rc.issues)
        out["relations"].append(rr.issues)
        out["intentions"].append(ri.issues)
    return out


def test_a_scene_naming_paths_outside_the_data_folder_opens_no_file(played, layout):
    scene, frames = played
    data, outside, fifos = layout
    for name in _hostile_names(data, outside):
        hostile = dataclasses.replace(scene, scene_id=hashlib.sha256(name.encode()).hexdigest()[:16], map_name=name)
        frames_h = [dataclasses.replace(f, scene_id=hostile.scene_id) for f in frames[:3]]
        issues = _in_thread(lambda: _run_stages(hostile, frames_h, data), fifos)
        _no_reader(fifos)
        for stage, per_frame in issues.items():
            problems = [i for frame_issues in per_frame for i in frame_issues if i.kind in ("map_problem", "map_sha256_mismatch")]
            assert len(problems) == 1, (stage, name, problems)  # one clear issue, once
            assert problems[0].detail.split(":")[0] in ("map_name_invalid", "map_not_found"), problems[0].detail
            assert "\n" not in problems[0].detail  # the name is quoted: no forged log line
            no_map = [i for frame_issues in per_frame for i in frame_issues if i.kind == "no_map"]
            assert len(no_map) == len(frames_h)  # the stage goes on, every vehicle off the map
            assert all("<invalid map name>" in i.detail or name in i.detail for i in no_map)
            assert all("\n" not in i.detail for i in no_map)


def test_the_viewer_opens_no_file_named_by_the_scene(played, layout):
    from stages.viewer.model import load_map_geometry

    scene, _frames = played
    data, outside, fifos = layout
    for name in _hostile_names(data, outside):
        hostile = dataclasses.replace(scene, scene_id="hostile", map_name=name)
        geometry = _in_thread(lambda: load_map_geometry(hostile, str(data)), fifos)
        _no_reader(fifos)
        assert geometry.n_car_lanelets == 0 and geometry.n_other_lanelets == 0
        assert len(geometry.problems) == 1 and geometry.problems[0].split(":")[0] in ("map_name_invalid", "map_not_found")
    good = load_map_geometry(scene, str(data))
    assert good.n_car_lanelets == 32 and good.n_other_lanelets == 37, good.problems
    wrong = load_map_geometry(dataclasses.replace(scene, map_sha256="0" * 64), str(data))
    assert wrong.n_car_lanelets == 0 and wrong.problems[0].startswith("map_sha256_mismatch")


def test_a_fifo_or_symlink_inside_the_maps_folder_is_refused_without_blocking(played, layout):
    scene, _frames = played
    data, outside, fifos = layout
    os.mkfifo(data / "maps" / "fifo.osm")
    os.symlink(outside / "passwd", data / "maps" / "link.osm")
    for name in ("fifo.osm", "link.osm"):
        path, problem = _in_thread(lambda: map_scene.local_map_file(data, dataclasses.replace(scene, map_name=name)), fifos)
        assert path is None and problem.startswith("map_unreadable") and "not a regular file" in problem


def test_an_oversized_map_is_refused_before_it_is_hashed(played, layout, monkeypatch):
    scene, _frames = played
    data, _outside, _fifos = layout
    big = data / "maps" / "big.osm"
    with big.open("wb") as fh:  # sparse: 300 MB that take no disk
        fh.truncate(300 * 1024 * 1024)
    hashed = []
    real_sha256 = hashlib.sha256
    monkeypatch.setattr(map_scene.hashlib, "sha256", lambda *a, **k: hashed.append(a) or real_sha256(*a, **k))
    path, problem = map_scene.local_map_file(data, dataclasses.replace(scene, map_name="big.osm"))
    assert path is None and problem.startswith("map_too_large") and not hashed
    builder = CorridorBuilder(CorridorsConfig(data=str(data)))
    big_scene = dataclasses.replace(scene, scene_id="big", map_name="big.osm")
    kinds = [i.kind for i in builder.process(dataclasses.replace(_frame0(played), scene_id="big"), big_scene)[1]]
    assert kinds.count("map_problem") == 1 and not hashed


def _frame0(played) -> TrackFrame:
    return played[1][0]


def test_a_scene_of_another_hash_is_reported_once_and_not_resolved_again(played, layout, monkeypatch):
    scene, frames = played
    data, _outside, _fifos = layout
    calls = []
    real = map_scene.local_map_file
    monkeypatch.setattr(map_scene, "local_map_file", lambda *a, **k: calls.append(a) or real(*a, **k))
    other = dataclasses.replace(scene, scene_id="otherhash", map_sha256="0" * 64)
    maps = SceneMaps(CorridorsConfig(data=str(data)))
    builder = CorridorBuilder(CorridorsConfig(data=str(data)), scene_maps=maps)
    mismatches, no_map = 0, 0
    for k, frame in enumerate(frames * 3):
        republished = dataclasses.replace(other, header=Header(run_id="t", frame_index=k, stamp_ns=k, producer="source"))
        later = dataclasses.replace(frame.header, stamp_ns=k * 100_000_000)  # (the frames again, later: not late ones)
        result = builder.update({"track_frame": dataclasses.replace(frame, header=later, scene_id="otherhash"), "scene": republished})
        assert "corridor_set" in result.outputs
        mismatches += [i.kind for i in result.issues].count("map_sha256_mismatch")
        no_map += [i.kind for i in result.issues].count("no_map")
    assert mismatches == 1 and no_map == len(frames) * 3
    assert len(calls) == 1  # hashed once, never per frame
    # another builder on the same SceneMaps (a restarted stage core, the eval's shared cache) does not resolve it again
    second = CorridorBuilder(CorridorsConfig(data=str(data)), scene_maps=maps)
    second.process(dataclasses.replace(frames[0], scene_id="otherhash"), other)
    assert len(calls) == 1
    # a publisher cycling through scenes does not grow the cache without bound (nor makes it resolve one scene twice in a row)
    for k in range(3 * SceneMaps.MAX_ENTRIES):
        maps.get(dataclasses.replace(other, scene_id=f"s{k}", origin_lat_deg=float(k)))
    assert len(maps._maps) <= SceneMaps.MAX_ENTRIES
    # the source's own scene (its hash) loads from the same folder
    builder = CorridorBuilder(CorridorsConfig(data=str(data)))
    _, issues = builder.process(frames[0], scene)
    corridor_set, more = builder.process(frames[1], scene)  # (a car first seen with a reported zero is pending one frame)
    assert not [i for i in issues + more if i.kind in ("no_map", "map_problem", "map_sha256_mismatch")], issues + more
    assert any(v.corridors for v in corridor_set.vehicles)


def test_a_changed_scene_under_the_same_scene_id_is_reported_once_and_the_map_kept(played, layout):
    # a tracker that corrects its map, projection or origin but keeps its scene_id: one issue that says to give the
    # changed scene a new id, the loaded map kept (its vehicles keep their corridors); a new id loads the new scene
    scene, frames = played
    data, _outside, _fifos = layout
    builder = CorridorBuilder(CorridorsConfig(data=str(data)))
    kinds = []
    for k, frame in enumerate(frames * 2):
        sent = scene if k < 2 else dataclasses.replace(scene, map_sha256="0" * 64)
        corridor_set, issues = builder.process(frame, sent)
        kinds += [i.kind for i in issues]
    assert kinds.count("scene_changed_same_id") == 1 and "map_sha256_mismatch" not in kinds, kinds
    assert any(v.corridors for v in corridor_set.vehicles)
    _, issues = builder.process(frames[0], dataclasses.replace(scene, scene_id="fixed", map_sha256="0" * 64))
    assert [i.kind for i in issues].count("map_sha256_mismatch") == 1


def test_the_source_publishes_a_map_name_and_hash_never_a_path(played):
    scene, _frames = played
    assert scene.map_name == MAP_NAME and os.sep not in scene.map_name
    assert scene.map_sha256 == file_sha256(DEFAULT_DATA_DIR / "maps" / MAP_NAME)
    assert not hasattr(scene, "map_path")
    assert SceneInfo.VERSION == 4


def test_the_launcher_gives_every_map_stage_the_source_data_folder(tmp_path):
    from stages.runtime import launcher as launch
    args = launch.build_parser().parse_args(["--data", str(tmp_path), "--no-record"])
    raw = {"nodes": [
        {"id": "source", "stage": "stages.tracks_source", "params": {}},
        {"id": "corridors", "stage": "stages.corridors"},
        {"id": "relations", "stage": "stages.relations"},
        {"id": "intentions", "stage": "stages.intentions", "params": {"data": "/elsewhere"}},
        {"id": "viewer", "stage": "stages.viewer", "params": {"port": 0}},
        {"id": "markov_prediction", "stage": "stages.markov_prediction"},
    ]}
    launch.make_editor(args)(raw)
    by_id = {n["id"]: n.get("params", {}) for n in raw["nodes"]}
    want = str(tmp_path.resolve())
    assert by_id["source"]["data"] == want
    for nid in ("corridors", "relations", "intentions", "viewer"):
        assert by_id[nid]["data"] == want, nid
    assert "data" not in by_id["markov_prediction"]
    # without --data nothing is added: every stage defaults to the embedded stages/data/taf-bw
    raw2 = {"nodes": [{"id": "source", "stage": "stages.tracks_source"}, {"id": "corridors", "stage": "stages.corridors"}]}
    launch.make_editor(launch.build_parser().parse_args(["--no-record"]))(raw2)
    assert "data" not in raw2["nodes"][1].get("params", {})


def test_without_a_player_data_is_where_the_map_stages_find_the_maps_and_recording_is_refused(tmp_path):
    """``launch.py live --data DIR``: the tracker's SceneInfo names a map that the stages look up in DIR/maps; there is no
    player to give the folder to, and nothing to choose a recording or speed for."""
    from stages.runtime import launcher as launch
    from stages.runtime.pipeline import PipelineError

    def live():
        return {"nodes": [{"id": "corridors", "stage": "stages.corridors"}, {"id": "relations", "stage": "stages.relations"},
                          {"id": "markov_prediction", "stage": "stages.markov_prediction"}]}

    raw = live()
    launch.make_editor(launch.build_parser().parse_args(["--data", str(tmp_path), "--no-record"]))(raw)
    by_id = {n["id"]: n.get("params", {}) for n in raw["nodes"]}
    assert by_id["corridors"]["data"] == by_id["relations"]["data"] == str(tmp_path.resolve())
    assert "data" not in by_id["markov_prediction"]
    for flags in (["--recording", "k729_2022-03-16"], ["--speed", "2"]):
        with pytest.raises(PipelineError, match="the pipeline has no dataset source node"):
            launch.make_editor(launch.build_parser().parse_args([*flags, "--no-record"]))(live())
    # a folder that is not there stops the launcher before any node starts (each would fail on it on its own)
    with pytest.raises(PipelineError, match=r"^--data .*nowhere: no such folder"):
        launch.make_editor(launch.build_parser().parse_args(["--data", str(tmp_path / "nowhere"), "--no-record"]))(live())
