"""``iamp data superimpose``: dense recordings from time-shifted copies of real tracks (stages/lib/datasets/superimpose.py)."""

from __future__ import annotations

import csv

import numpy as np
import pytest

from stages.cli import main as iamp
from stages.lib.datasets import DEFAULT_DATA_DIR, load_recording
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
    assert result.vehicles_mean == pytest.approx(2 * len(src.rows) / (src.duration_ms / src.frame_ms), rel=0.02)


def test_build_dense_reaches_the_target_and_the_cli_writes_it(tmp_path, capsys):
    result = build_dense(DEFAULT_DATA_DIR, REC, 8.0, tmp_path / "a", shift_s=0.0)
    assert len(result.layers) >= 2 and 5.0 <= result.vehicles_mean <= 12.0
    assert iamp(["data", "superimpose", "--data", str(DEFAULT_DATA_DIR), "--recording", REC, "--vehicles", "8", "--shift-s", "0",
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
    # the partial copy writes whole tracks, about its share of the source's rows, under fresh ids
    half = superimpose(sources, [Layer(first, 0.0, share=0.5)], tmp_path, "half", duration_s=src.duration_ms / 1000, map_path=map_path)
    rows = _rows(tmp_path / "recorded_trackfiles" / "half" / "vehicle_tracks_000.csv")
    _ids, track_rows = np.unique(src.track_ids.astype(str), return_counts=True)
    assert 0.5 * len(src.rows) <= len(rows) < 0.5 * len(src.rows) + track_rows.max()  # whole tracks until the share is reached
    it, ix, iy = (src.columns.index(c) for c in ("timestamp_ms", "x", "y"))
    source_of = {(int(row[it]), row[ix], row[iy]): tid for row, tid in zip(src.rows, src.track_ids)}
    kept_sources = {source_of[(int(r["timestamp_ms"]), r["x"], r["y"])] for r in rows}
    whole = sum(int((src.track_ids == tid).sum()) for tid in kept_sources)
    assert whole == len(rows)  # every kept source track is written whole
    assert half.vehicles_mean == pytest.approx(len(rows) / (src.duration_ms / src.frame_ms), rel=0.02)
    # the same layer picks the same tracks (a hash of the id, not a random draw)
    again = superimpose(sources, [Layer(first, 0.0, share=0.5)], tmp_path / "b", "half", duration_s=src.duration_ms / 1000, map_path=map_path)
    assert again.n_rows == half.n_rows
    assert "| 0 | " in (tmp_path / "ATTRIBUTION.md").read_text() and "0.50 |" in (tmp_path / "ATTRIBUTION.md").read_text()
