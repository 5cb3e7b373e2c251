"""bench/velocity_robustness.py's ``rate_half`` variant: a recording as a tracker at half its frame rate would give it."""

from __future__ import annotations

import csv

from bench.velocity_robustness import thin_track_file, write_variant
from stages.lib.datasets import DEFAULT_DATA_DIR, DEFAULT_RECORDING, load_recording


def test_every_other_frame_is_left_out_and_the_loader_reads_half_the_rate(tmp_path):
    src = tmp_path / "vehicle_tracks_000.csv"
    rows = [["track_id", "frame_id", "timestamp_ms", "x"]]
    rows += [[str(track), str(k), str(100 * k), "1.0"] for k in range(3, 13) for track in (1, 2) if not (track == 2 and k < 6)]
    with src.open("w", newline="") as fh:
        csv.writer(fh).writerows(rows)
    assert thin_track_file(src, tmp_path / "out.csv") == 9  # of 17 rows: frames 4, 6, ..., 12
    kept = list(csv.reader((tmp_path / "out.csv").open()))
    assert kept[0] == rows[0]
    assert sorted({int(r[2]) for r in kept[1:]}) == [300, 500, 700, 900, 1100]  # from the first stamp, every other frame
    assert {r[0] for r in kept[1:] if int(r[2]) >= 700} == {"1", "2"}

    out = tmp_path / "data"
    left_out = write_variant(DEFAULT_DATA_DIR, DEFAULT_RECORDING, out, "rate_half")
    given, thinned = load_recording(DEFAULT_DATA_DIR, DEFAULT_RECORDING), load_recording(out, DEFAULT_RECORDING)
    assert left_out > 0
    for a, b in zip(given.sequences, thinned.sequences):
        assert b.frame_rate_hz == a.frame_rate_hz / 2
        assert abs(b.n_rows - a.n_rows / 2) < 0.02 * a.n_rows
