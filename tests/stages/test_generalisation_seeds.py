"""bench/generalisation.py --seeds: the mean and range of each mode's mADE over the seeds, and a bad list exits 2."""

from __future__ import annotations

import pytest

from bench.generalisation import format_seed_spread, main, seed_spread


def _table(hybrid: float, baseline: float | None) -> dict:
    rows = {"hybrid": {split: {"mADE_m": hybrid + i} for i, split in enumerate(("overall", "slow", "fast"))}}
    if baseline is not None:
        rows["baseline"] = {split: {"mADE_m": baseline} for split in ("overall", "slow", "fast")}
    return rows


def test_seed_spread_gives_mean_min_max_per_direction_mode_and_split():
    tables = {0: {"k729-k733": _table(2.7, 3.0)}, 1: {"k729-k733": _table(2.8, 3.0)}, 2: {"k729-k733": _table(2.9, None)}}
    spread = seed_spread(tables)
    h = spread["k729-k733"]["hybrid"]
    assert h["overall"]["values"] == [2.7, 2.8, 2.9]
    assert h["overall"]["mean"] == pytest.approx(2.8) and h["overall"]["min"] == 2.7 and h["overall"]["max"] == 2.9
    assert h["fast"]["mean"] == pytest.approx(4.8)
    b = spread["k729-k733"]["baseline"]["overall"]  # seed 2 ran no baseline: left out of the mean, None in values
    assert b["values"] == [3.0, 3.0, None] and b["mean"] == pytest.approx(3.0)
    assert "k733-k729" not in spread
    text = format_seed_spread(spread)
    assert "=== k729-k733 ===" in text and "2.80 (2.70-2.90)" in text


@pytest.mark.parametrize("seeds", ["", "1,x", "1,1"])
def test_bad_seed_list_exits_2(tmp_path, capsys, seeds):
    data = tmp_path / "taf"
    for name in ("k729_2022-03-16", "k733_2018-05-02"):
        (data / "recorded_trackfiles" / name).mkdir(parents=True)
    assert main(["--data", str(data), "--seeds", seeds, "--json", str(tmp_path / "out.json")]) == 2
    assert "--seeds" in capsys.readouterr().err
