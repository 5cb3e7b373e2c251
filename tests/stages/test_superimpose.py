"""``iamp data superimpose``: dense recordings from time-shifted copies of real tracks (stages/lib/datasets/superimpose.py)."""

from __future__ import annotations

import csv
import shutil

import numpy as np
import pytest

from bus_schemas.common import VEHICLE_TYPE_VALUES
from stages.cli import main as iamp
from stages.lib.datasets import DEFAULT_DATA_DIR, load_recording
from stages.lib.datasets import DatasetError
from stages.lib.datasets.model import agent_type_from_name
from stages.lib.datasets import superimpose as superimpose_module
from stages.lib.datasets.superimpose import Layer, build_dense, plan_layers, read_sources, superimpose

REC = "k729_2022-03-16"


def _rows(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def test_layers_are_shifted_copies_with_fresh_ids(tmp_path):
    map_path, sources = read_sources(DEFAULT_DATA_DIR, REC, ["013"])
    src = sources[0]
    period_s = src.duration_ms / 1000
    result = superimpose(sources, [Layer(0, 0.0), Layer(0, 3.0)], tmp_path, "two", duration_s=period_s, map_path=map_path,
                         licence_dir=DEFAULT_DATA_DIR)
    assert (tmp_path / "maps" / "two.osm").is_file() and (tmp_path / "LICENSE").is_file()
    rows = _rows(tmp_path / "recorded_trackfiles" / "two" / "vehicle_tracks_000.csv")
    assert len(rows) == 2 * len(src.rows)
    # the first layer is the source itself, row for row, under new ids
    source_rows = {(int(r[src.columns.index("timestamp_ms")]), r[src.columns.index("x")], r[src.columns.index("y")]) for r in src.rows}
    written = {(int(r["timestamp_ms"]), r["x"], r["y"]) for r in rows}
    assert source_rows <= written
    # the second is shifted 3 s back, circularly: a source row at t >= 3 s is written at t - 3 s
    t_col, x_col = src.columns.index("timestamp_ms"), src.columns.index("x")
    late = [r for r in src.rows if int(r[t_col]) >= 3000]
    assert late and all((int(r[t_col]) - 3000, r[x_col], r[src.columns.index("y")]) in written for r in late)
    # fresh ids: no id holds two rows at one time, and the layers do not share ids
    keys = [(r["track_id"], r["timestamp_ms"]) for r in rows]
    assert len(keys) == len(set(keys))
    n_source_ids = len(set(src.track_ids))
    assert result.n_tracks > n_source_ids  # two layers, wrap-split tracks count twice
    rec = load_recording(tmp_path, "two")
    seq = rec.sequences[0]
    frames, counts = np.unique(seq.frame_index, return_counts=True)
    src_rec = load_recording(DEFAULT_DATA_DIR, REC, ["013"])
    assert counts.max() > np.unique(src_rec.sequences[0].frame_index, return_counts=True)[1].max()
    # vehicles per frame count rows of a vehicle type only: K729's vehicle track files hold pedestrians too
    n_vehicle_rows = int(np.count_nonzero(src.vehicle))
    assert 0 < n_vehicle_rows < len(src.rows)
    assert result.vehicles_mean == pytest.approx(2 * n_vehicle_rows / (src.duration_ms / src.frame_ms), rel=0.02)
    # as the stages count them: the loader's agent types
    n_frames = int(round(result.duration_s * 1000 / src.frame_ms))
    loaded_vehicles = np.count_nonzero(np.isin(seq.agent_type, list(VEHICLE_TYPE_VALUES)))
    assert result.vehicles_mean == pytest.approx(loaded_vehicles / n_frames, rel=0.02)


def test_build_dense_reaches_the_target_and_the_cli_writes_it(tmp_path, capsys):
    result = build_dense(DEFAULT_DATA_DIR, REC, 8.0, tmp_path / "a", shift_s=40.0)  # one round: the shift moves nothing
    assert len(result.layers) >= 2 and 5.0 <= result.vehicles_mean <= 12.0
    assert iamp(["data", "superimpose", "--data", str(DEFAULT_DATA_DIR), "--recording", REC, "--vehicles", "8", "--shift-s", "40",
                 "--out", str(tmp_path / "b"), "--name", "dense"]) == 0
    assert "recording dense" in capsys.readouterr().out
    assert load_recording(tmp_path / "b", "dense").sequences[0].n_rows > 0
    assert iamp(["data", "superimpose", "--data", str(DEFAULT_DATA_DIR), "--recording", REC, "--vehicles", "0", "--out", str(tmp_path / "c")]) == 2
    assert iamp(["data", "superimpose", "--data", str(tmp_path / "none"), "--recording", REC, "--vehicles", "6", "--out", str(tmp_path / "c")]) == 2
    for flag, value in (("--shift-s", "nan"), ("--vehicles", "inf"), ("--duration-s", "nan")):  # NaN passed "< 0" and crashed later
        argv = ["data", "superimpose", "--data", str(DEFAULT_DATA_DIR), "--recording", REC, "--vehicles", "6", "--out", str(tmp_path / "c"), flag, value]
        assert iamp(argv) == 2, flag
        assert "must be finite" in capsys.readouterr().err


def test_a_partial_last_layer_makes_the_mean_hit_the_target(tmp_path):
    """Whole copies overshoot (K733: four copies for N = 18 held 19.8 a frame); the rest of the target is a share of one more copy's tracks."""
    map_path, sources = read_sources(DEFAULT_DATA_DIR, REC)
    first = max((i for i, s in enumerate(sources) if s.kind == "vehicle"), key=lambda i: len(set(sources[i].track_ids)))
    src = sources[first]
    target = 1.5 * src.mean_per_frame()  # whole copies while they fit, then part of one
    layers = plan_layers(sources, target, shift_s=0.0, duration_s=src.duration_ms / 1000)
    assert [l.share for l in layers[:-1]] == [1.0] * (len(layers) - 1) and 0.0 < layers[-1].share < 1.0
    assert sum(sources[l.source].mean_per_frame() * l.share for l in layers) == pytest.approx(target, rel=1e-6)
    # the partial copy writes whole tracks, about its share of the source's vehicle rows, under fresh ids
    half = superimpose(sources, [Layer(first, 0.0, share=0.5)], tmp_path, "half", duration_s=src.duration_ms / 1000, map_path=map_path)
    rows = _rows(tmp_path / "recorded_trackfiles" / "half" / "vehicle_tracks_000.csv")
    ids, inverse = np.unique(src.track_ids.astype(str), return_inverse=True)
    track_vehicle_rows = np.bincount(inverse, weights=src.vehicle)
    n_vehicle = int(np.count_nonzero(src.vehicle))
    kept_vehicle = sum(agent_type_from_name(r["agent_type"]).is_vehicle for r in rows)
    assert 0.5 * n_vehicle <= kept_vehicle < 0.5 * n_vehicle + track_vehicle_rows.max()  # whole tracks until the share is reached
    it, ix, iy = (src.columns.index(c) for c in ("timestamp_ms", "x", "y"))
    source_of = {(int(row[it]), row[ix], row[iy]): tid for row, tid in zip(src.rows, src.track_ids)}
    kept_sources = {source_of[(int(r["timestamp_ms"]), r["x"], r["y"])] for r in rows}
    whole = sum(int((src.track_ids == tid).sum()) for tid in kept_sources)
    assert whole == len(rows)  # every kept source track is written whole
    assert half.vehicles_mean == pytest.approx(kept_vehicle / (src.duration_ms / src.frame_ms), rel=0.02)
    # the same layer picks the same tracks (a hash of the id, not a random draw)
    again = superimpose(sources, [Layer(first, 0.0, share=0.5)], tmp_path / "b", "half", duration_s=src.duration_ms / 1000, map_path=map_path)
    assert again.n_rows == half.n_rows
    assert "| 0 | " in (tmp_path / "ATTRIBUTION.md").read_text() and "0.50 |" in (tmp_path / "ATTRIBUTION.md").read_text()


# Command-line checks (``iamp data superimpose``): one short K729 sequence copied into tmp_path, so that a run takes
# well under a second and a command that writes where it must not can only harm the copy.


@pytest.fixture
def small_data(tmp_path):
    """A data folder of K729 sequence 013 (112 s): maps/, recorded_trackfiles/k729.../, LICENSE."""
    src = tmp_path / "src"
    (src / "maps").mkdir(parents=True)
    (src / "recorded_trackfiles" / REC).mkdir(parents=True)
    shutil.copyfile(DEFAULT_DATA_DIR / "maps" / f"{REC}.osm", src / "maps" / f"{REC}.osm")
    for name in ("meta_data.csv", "vehicle_tracks_013.csv"):
        shutil.copyfile(DEFAULT_DATA_DIR / "recorded_trackfiles" / REC / name, src / "recorded_trackfiles" / REC / name)
    if (DEFAULT_DATA_DIR / "LICENSE").is_file():
        shutil.copyfile(DEFAULT_DATA_DIR / "LICENSE", src / "LICENSE")
    return src


def _snapshot(folder):
    """Every file under ``folder`` with its bytes."""
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def _cli(data, out, *more):
    return iamp(["data", "superimpose", "--data", str(data), "--recording", REC, "--out", str(out), *more])


def _one_line_refusal(capsys, *words):
    out, err = capsys.readouterr()
    assert err.startswith("iamp data superimpose: ") and err.count("\n") == 1 and "Traceback" not in err, err
    for word in words:
        assert word in err, err
    return err


@pytest.mark.parametrize("out, name", [
    ("src", REC),  # the tester's case: it deleted the source's tracks, then SameFileError
    ("src", "other"),  # --out = --data: the source's LICENSE and map folder are in the output
    ("src/recorded_trackfiles", None),  # holds the source recording
    ("src/recorded_trackfiles/" + REC + "/dense", None),  # lies in it
    ("src/maps", None),  # holds the source map
])
def test_an_output_overlapping_the_source_is_refused_and_the_source_kept(small_data, tmp_path, capsys, out, name):
    before, existed = _snapshot(small_data), (tmp_path / out).exists()
    argv = ["--vehicles", "5", "--shift-s", "30"] + (["--name", name] if name else [])
    assert _cli(small_data, tmp_path / out, *argv) == 2
    _one_line_refusal(capsys, "--out")
    assert _snapshot(small_data) == before and (tmp_path / out).exists() == existed
    with pytest.raises(DatasetError, match="--out"):  # the library refuses it too
        build_dense(small_data, REC, 5.0, tmp_path / out, name=name, shift_s=30.0)


@pytest.mark.parametrize("name", ["../../escape", "a/b", "", ".", "..", ".hidden", "a\\b", "x" * 201])
def test_a_name_must_be_a_plain_folder_name(small_data, tmp_path, capsys, name):
    out = tmp_path / "deep" / "out"
    assert _cli(small_data, out, "--vehicles", "2", "--shift-s", "30", "--name", name) == 2
    _one_line_refusal(capsys, "--name", "plain folder name")
    assert not out.exists() and sorted(p.name for p in tmp_path.iterdir()) == ["src"]  # nothing written, outside or in
    with pytest.raises(DatasetError, match="plain folder name"):
        build_dense(small_data, REC, 2, out, name=name, shift_s=30.0)


@pytest.mark.parametrize("flags, words", [
    (["--duration-s", "1e9"], ["--duration-s", "86400"]),
    (["--duration-s", "86401"], ["--duration-s", "86400"]),
    (["--vehicles", "1e6"], ["--vehicles", "1000"]),
    (["--vehicles", "1001"], ["--vehicles", "1000"]),
    (["--vehicles", "1000", "--duration-s", "3000"], ["vehicle-seconds"]),
    (["--shift-s", "1e300"], ["--shift-s", "86400"]),
])
def test_requests_beyond_the_limits_are_refused_before_any_work(small_data, tmp_path, capsys, monkeypatch, flags, words):
    """--duration-s 1e9 ran for many minutes and --vehicles 1e6 built 50 000 tracks: refused at once (``build_dense``
    must not even start) with the limit named; the caps are in --help."""
    def not_called(*_a, **_k):
        raise AssertionError("build_dense ran")
    monkeypatch.setattr(superimpose_module, "build_dense", not_called)
    argv = {"--vehicles": "5", "--shift-s": "30"}
    for flag, value in zip(flags[::2], flags[1::2]):
        argv[flag] = value
    assert _cli(small_data, tmp_path / "out", *[w for kv in argv.items() for w in kv]) == 2
    _one_line_refusal(capsys, *words)
    assert not (tmp_path / "out").exists()
    monkeypatch.undo()
    with pytest.raises(DatasetError, match=words[-1]):  # the library refuses them too
        build_dense(small_data, REC, float(argv["--vehicles"]), tmp_path / "lib", shift_s=float(argv["--shift-s"]),
                    duration_s=float(argv["--duration-s"]) if "--duration-s" in argv else None)
    assert iamp(["data", "superimpose", "--help"]) == 0
    help_text = " ".join(capsys.readouterr().out.split())
    assert "at most 1000" in help_text and "at most 86400 s (a day)" in help_text and "vehicle-seconds" in help_text


@pytest.mark.parametrize("shift", ["0", "-5", "0.0"])
def test_a_shift_that_is_not_positive_is_refused(small_data, tmp_path, capsys, shift):
    """--shift-s 0 stacked every copy on the others (one sequence: each copy of it, vehicle on vehicle)."""
    assert _cli(small_data, tmp_path / "out", "--vehicles", "5", "--shift-s", shift) == 2
    _one_line_refusal(capsys, "--shift-s", "positive")
    assert not (tmp_path / "out").exists()


def test_copies_that_would_coincide_are_refused(small_data, tmp_path, capsys):
    """Not only 0: a shift of the sequence's length (112.3 s) wraps each copy onto the first, as does a shift rounding to
    0 frames; ``superimpose`` refuses any two layers of one sequence at one circular shift."""
    map_path, sources = read_sources(small_data, REC)
    period_s = sources[0].duration_ms / 1000
    for layers in ([Layer(0, 0.0), Layer(0, period_s)], [Layer(0, 3.0), Layer(0, 3.0 + period_s, share=0.5)], [Layer(0, 0.0), Layer(0, 0.01)]):
        with pytest.raises(DatasetError, match="would coincide"):
            superimpose(sources, layers, tmp_path / "lib", "x", duration_s=period_s, map_path=map_path)
    assert not (tmp_path / "lib").exists()
    assert _cli(small_data, tmp_path / "out", "--vehicles", "5", "--shift-s", f"{period_s:g}") == 2
    _one_line_refusal(capsys, "coincide")


def test_the_default_name_shows_the_vehicles_as_given(small_data, tmp_path, capsys):
    """--vehicles 0.5 named the recording -dense0."""
    assert _cli(small_data, tmp_path / "out", "--vehicles", "0.5", "--shift-s", "30") == 0
    assert f"recording {REC}-dense0.5," in capsys.readouterr().out
    assert [p.name for p in (tmp_path / "out" / "recorded_trackfiles").iterdir()] == [f"{REC}-dense0.5"]
    assert (tmp_path / "out" / "maps" / f"{REC}-dense0.5.osm").is_file()
    default_name = superimpose_module.default_name
    assert default_name(REC, 18.0) == default_name(REC, 18) == f"{REC}-dense18"  # whole numbers as before
    assert default_name(REC, 12.5) == f"{REC}-dense12.5"


def test_a_failed_or_interrupted_build_leaves_the_old_output_whole(small_data, tmp_path, monkeypatch):
    """The old tracks were deleted before the new ones were built: a failure or Ctrl-C (here: in the middle of the
    layers) left meta_data.csv without tracks. Now the new recording is built in a temporary folder, moved into
    place when complete, and the temporary folder is removed whatever happens."""
    out = tmp_path / "out"
    assert _cli(small_data, out, "--vehicles", "4", "--shift-s", "30", "--name", "dense") == 0
    (out / "recorded_trackfiles" / "dense" / "signal_phases_000.csv").write_text("kept\n")  # not ours: carried over
    before = _snapshot(out)
    calls = []

    def interrupted(src, layer):
        calls.append(layer)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return None
    monkeypatch.setattr(superimpose_module, "_kept_rows", interrupted)
    with pytest.raises(KeyboardInterrupt):
        build_dense(small_data, REC, 6.0, out, name="dense", shift_s=20.0)
    assert _snapshot(out) == before
    assert not [p for p in out.iterdir() if p.name.startswith(".")]  # no temporary folder
    monkeypatch.undo()
    # a complete build replaces the tracks and keeps the files it does not write, as before
    result = build_dense(small_data, REC, 6.0, out, name="dense", shift_s=20.0)
    assert result.out_dir == out and result.vehicles_mean > 4.5
    folder = out / "recorded_trackfiles" / "dense"
    assert sorted(p.name for p in folder.iterdir()) == ["meta_data.csv", "signal_phases_000.csv", "vehicle_tracks_000.csv"]
    assert (folder / "signal_phases_000.csv").read_text() == "kept\n"
    assert load_recording(out, "dense").sequences[0].n_rows == result.n_rows
    assert not [p for p in out.iterdir() if p.name.startswith(".")]


def test_a_map_that_cannot_be_moved_into_place_leaves_the_old_recording(small_data, tmp_path, monkeypatch):
    """The map was moved into place before the recording folder: where the recording's move then failed (a read-only
    recorded_trackfiles/), a new map stood beside the old recording. Now the recording goes first, and where the map
    cannot follow, the old recording is put back: the output is as it was."""
    out = tmp_path / "out"
    assert _cli(small_data, out, "--vehicles", "4", "--shift-s", "30", "--name", "dense") == 0
    before = _snapshot(out)
    real_replace = superimpose_module.os.replace

    def failing(src, dst):
        if str(dst).endswith(".osm"):
            raise PermissionError(13, "Permission denied", str(dst))
        return real_replace(src, dst)

    monkeypatch.setattr(superimpose_module.os, "replace", failing)
    with pytest.raises(PermissionError):
        build_dense(small_data, REC, 6.0, out, name="dense", shift_s=20.0)
    assert _snapshot(out) == before
    assert not [p for p in out.iterdir() if p.name.startswith(".")]


def test_the_command_line_says_what_to_fix_and_leaves_no_folder(small_data, tmp_path, capsys):
    """Found by a new-user probe: a repeated --sequence stacked two copies vehicle on vehicle; an unknown recording
    left the --out folders it had made; a duration or shift under one frame named the wrong cause; a file where
    maps/ goes failed with a traceback after the work."""
    assert _cli(small_data, tmp_path / "o1", "--vehicles", "4", "--sequence", "013", "--sequence", "013") == 2
    _one_line_refusal(capsys, "--sequence 013", "more than once")
    assert not (tmp_path / "o1").exists()
    assert iamp(["data", "superimpose", "--data", str(small_data), "--recording", "nosuch", "--vehicles", "4",
                 "--out", str(tmp_path / "o2" / "deep")]) == 2
    _one_line_refusal(capsys, "nosuch")
    assert not (tmp_path / "o2").exists()
    assert _cli(small_data, tmp_path / "o3", "--vehicles", "4", "--shift-s", "30", "--duration-s", "0.01") == 2
    _one_line_refusal(capsys, "shorter than one frame", "--duration-s")
    assert _cli(small_data, tmp_path / "o3", "--vehicles", "4", "--shift-s", "0.01") == 2
    _one_line_refusal(capsys, "shorter than one frame", "--shift-s")
    (tmp_path / "o4").mkdir()
    (tmp_path / "o4" / "maps").write_text("not a folder\n")
    assert _cli(small_data, tmp_path / "o4", "--vehicles", "4", "--shift-s", "30") == 2
    _one_line_refusal(capsys, "maps", "is a file, not a folder")
    assert sorted(p.name for p in (tmp_path / "o4").iterdir()) == ["maps"]
    (tmp_path / "o5").write_text("a file\n")
    assert _cli(small_data, tmp_path / "o5", "--vehicles", "4", "--shift-s", "30") == 2
    _one_line_refusal(capsys, "--out", "is a file, not a folder")
