"""``iamp eval --report``: the report built on a slice of the embedded scenario, read back from its text, its JSON and the
matplotlib objects of its figures (never from pixels)."""

from __future__ import annotations

import json
import re
import shutil

import pytest
from matplotlib.colors import to_hex

from stages import cli
from stages.lib.datasets import DEFAULT_RECORDING, DEFAULT_SEQUENCE
from stages.offline import figures as fg
from stages.offline.report import QUANTITATIVE_HEAD, fmt
from stages.offline.situations import load_situations

MODES = ("hybrid", "baseline", "corridor_cv", "cv")
SITUATIONS = f"""
[[situation]]
name = "A"
recording = "{DEFAULT_RECORDING}"
sequence = "{DEFAULT_SEQUENCE}"
start = 0.0
end = 4.0
description = "the first seconds of sequence {DEFAULT_SEQUENCE}"

[[situation]]
name = "whole"
recording = "{DEFAULT_RECORDING}"
description = "every sequence played"

[[situation]]
name = "B | none"
recording = "{DEFAULT_RECORDING}"
sequence = "999"
description = "a sequence this run does not play: no frame, counted"
"""


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    """One real ``iamp eval --report --json`` run; every figure it saves is kept (``figures.save`` wrapped)."""
    tmp = tmp_path_factory.mktemp("report")
    situations = tmp / "situations.toml"
    situations.write_text(SITUATIONS)
    kept: dict[str, object] = {}
    original = fg.save

    def keeping(fig, directory, stem, formats=("png", "svg"), dpi=100):
        kept[stem] = fig
        return original(fig, directory, stem, formats, dpi)

    mp = pytest.MonkeyPatch()
    mp.setattr(fg, "save", keeping)
    try:
        code = cli.main(["eval", "--recording", DEFAULT_RECORDING, "--sequence", DEFAULT_SEQUENCE, "--max-frames", "60", "--stride", "0.8",
                         "--mode", *MODES, "--situations", str(situations), "--report", str(tmp / "rep"), "--json", str(tmp / "eval.json"),
                         "--no-progress", "--dpi", "40"])
    finally:
        mp.undo()
    assert code == 0
    return tmp / "rep", json.loads((tmp / "eval.json").read_text()), kept


def _table_after(text: str, head: list[str]) -> list[list[str]]:
    line = "| " + " | ".join(head) + " |"
    lines = text.splitlines()
    start = lines.index(line) + 2
    rows = []
    for row in lines[start:]:
        if not row.startswith("|"):
            break
        rows.append([c.strip().strip("*").replace("\\|", "|") for c in re.split(r"(?<!\\)\|", row.strip()[1:-1])])
    return rows


def test_quantitative_table_equals_the_json_of_the_same_run(built):
    folder, data, _ = built
    text = (folder / "report.md").read_text()
    assert text.splitlines()[0].startswith("# ") and "iamp eval " in text and "--report" in text, "the command sits at the top"
    rows = _table_after(text, QUANTITATIVE_HEAD)
    names = [s["name"] for s in data["situations"]]
    assert names == ["A", "whole", "B | none"], "a | in a name is escaped in the table, not a column of its own"
    assert len(rows) == len(names) * len(MODES)
    situation = None
    for row in rows:
        situation = row[0] or situation
        mode = row[1]
        stats = data["modes"][mode]["by_situation"][situation]
        assert int(row[2].replace(",", "")) == stats["windows"]
        assert row[3] == fmt(stats["time_per_step_ms"], 1)  # "–" for the situation without a frame
        assert row[4] == fmt(stats["mADE_m"]) and row[5] == fmt(stats["mFDE_m"])
        assert (row[4] == "–") == (situation == "B | none")
    assert [r[1] for r in rows[: len(MODES)]] == list(MODES)
    # the report's own copy of the JSON is the same run's
    assert json.loads((folder / "eval.json").read_text())["modes"]["hybrid"]["overall"] == data["modes"]["hybrid"]["overall"]


def test_situations_count_what_they_hold(built):
    _, data, _ = built
    a, whole, none = data["situations"]
    assert none["frames"] == 0 and data["skipped"]["situations_without_frames"] == 1, "a window with no frame is counted"
    assert "'B | none'" in data["skipped_examples"]["situations_without_frames"]
    assert a["sequence"] == DEFAULT_SEQUENCE and a["end_s"] == 4.0 and whole["end_s"] is None
    assert 0 < a["duration_s"] <= 4.1 and a["vehicles"] >= 1
    for mode in MODES:
        sit = data["modes"][mode]["by_situation"]
        assert sit["whole"]["windows"] == data["modes"][mode]["overall"]["windows"], "one sequence played: whole = all windows"
        assert 0 < sit["A"]["windows"] < sit["whole"]["windows"]
        assert sit["A"]["time_per_step_ms"] > 0


def test_calibration_and_horizon_keys(built):
    _, data, _ = built
    for mode in MODES:
        res = data["modes"][mode]
        cal = res["calibration"]
        assert cal["levels"][4] == 0.5 and cal["levels"][-1] == 0.9
        # the 90 % level follows the rule of coverage90 exactly
        assert cal["overall"]["coverage"][-1] == pytest.approx(res["overall"]["coverage90"])
        cov = cal["overall"]["coverage"]
        assert all(a <= b + 1e-12 for a, b in zip(cov, cov[1:])), "nested regions: coverage grows with the level"
        e = res["error_by_step_m"]
        assert len(e["t_s"]) == 10 and e["overall"]["windows"] == res["overall"]["windows"]
        # the mean over steps of the mADE corridor's error is mADE
        assert sum(e["overall"]["mean"]) / 10 == pytest.approx(res["overall"]["mADE_m"], rel=1e-9)


def test_every_figure_is_written_labelled_and_has_its_legend(built):
    folder, data, kept = built
    recording = DEFAULT_RECORDING
    expected = {"reliability", "error_by_horizon", "by_manoeuvre", "timing", f"grid_4s_hybrid_{recording}", f"grid_4s_baseline_{recording}",
                f"means_{recording}"}
    assert expected <= set(kept)
    accel = [s for s in kept if s.startswith("accel_")]
    assert 1 <= len(accel) <= 2
    text = (folder / "report.md").read_text()
    for stem in kept:
        for ext in ("png", "svg"):
            assert (folder / f"{stem}.{ext}").stat().st_size > 0
        assert f"({stem}.png)" in text, f"{stem} is not shown in the report"
    for stem, fig in kept.items():
        axes = [ax for ax in fig.axes if ax.get_label() != "<colorbar>"]
        assert fig.axes and all(ax.get_xlabel() and ax.get_ylabel() for ax in axes[:1]), stem
        titles = [ax.get_title() for ax in fig.axes] + [fig._suptitle.get_text() if fig._suptitle else ""]
        assert any(titles), f"{stem} has no title"
    def legend(fig) -> list[str]:
        boxes = [ax.get_legend() for ax in fig.axes if ax.get_legend()] + list(fig.legends)
        return [t.get_text() for box in boxes for t in box.get_texts()]

    means = kept[f"means_{recording}"]
    entries = legend(means)
    assert any(e.startswith("hybrid-IAMP") for e in entries) and any(e.startswith("baseline") for e in entries) and "ground truth" in entries
    ax = means.axes[0]
    assert ax.get_xlabel() == "x east (m)" and ax.get_ylabel() == "y north (m)"
    colours = {to_hex(line.get_color()) for line in ax.get_lines()}
    assert {fg.MODE_COLOURS["hybrid"], fg.MODE_COLOURS["baseline"], "#000000"} <= colours, "hybrid blue, baseline red, truth black"
    grid = kept[f"grid_4s_hybrid_{recording}"]
    bars = [a for a in grid.axes if a.get_label() == "<colorbar>"]
    assert len(bars) == 1 and "4.0 s" in bars[0].get_ylabel(), "the grid's colour bar names the horizon"
    assert "car lanelets" in legend(grid) and "Motion grid at 4.0 s" in grid.axes[0].get_title()
    acc = kept[accel[0]]
    assert set(legend(acc)) == {"AR model output $y_t$", "true acceleration"}
    assert acc.axes[0].get_ylabel() == "acceleration (m/s²)" and any(a.get_label() == "<colorbar>" for a in acc.axes)
    for stem in ("reliability", "error_by_horizon", "by_manoeuvre", "timing"):
        entries = legend(kept[stem])
        assert {fg.mode_label(m) for m in MODES} <= {e.split(" (median")[0] for e in entries}, (stem, entries)
    rel = kept["reliability"].axes
    assert len(rel) == 3 and all(a.get_xlabel() == "nominal level of the region" for a in rel)
    assert "calibrated (observed = nominal)" in legend(kept["reliability"])


def test_report_sections_and_provenance(built):
    folder, data, _ = built
    text = (folder / "report.md").read_text()
    for heading in ("## How it was made", "## Situations and quantitative results", "## Calibration", "## Error against horizon",
                    "## By manoeuvre of the true future, along and across the track", "## Compute time",
                    "## The paper's figures, one instant per recording"):
        assert heading in text
    assert re.search(r"matplotlib \d+\.\d+", text) and "numpy" in text and "sha256" in text
    assert "in-sample" in text, "the shipped weights were trained on TAF-BW: the report says hybrid is in-sample"
    curve = data["modes"]["hybrid"]["curve_choice"]  # what hybrid learnt online, in words, as the JSON has it
    assert f"curve factor {curve['factor']:g} of 0, 1, 2 from {curve['samples']:,} back-tested vehicles" in text
    lead = data["modes"]["hybrid"]["speed_lead"]  # the default online speed lead (hybrid_speed_leads_s)
    assert f"speed lead {lead['factor']:g} s of 0, 0.2, 0.4, 0.8 from {lead['samples']:,} back-tested vehicles" in text
    assert f"weight of the measured acceleration in λ(0) {data['modes']['hybrid']['initial_blend']['weight']:.2f}" in text
    for mode in MODES:
        cov = data["modes"][mode]["calibration"]["overall"]["coverage"]
        assert f"| {mode} | all | " + " | ".join(f"{c:.2f}" for c in cov) in text


def test_a_rerun_without_svg_leaves_no_stale_svg(built, tmp_path):
    """A report folder rewritten with --svg no kept the first run's SVGs beside the new PNGs (figures of another run)."""
    folder, data, _ = built
    again = tmp_path / "rep"
    shutil.copytree(folder, again)
    assert (again / "reliability.svg").exists()
    code = cli.main(["eval", "--recording", DEFAULT_RECORDING, "--sequence", DEFAULT_SEQUENCE, "--max-frames", "20", "--stride", "1.6",
                     "--mode", "cv", "--report", str(again), "--svg", "no", "--no-progress", "--dpi", "20"])
    assert code == 0
    assert not list(again.glob("*.svg")), sorted(p.name for p in again.glob("*.svg"))
    assert (again / "reliability.png").exists() and "SVG" not in (again / "report.md").read_text()


def test_bad_situations_file_is_a_usage_error(tmp_path, capsys):
    for text, says in (('situation = [1, 2]\n', "expected a [[situation]] table"), ('situation = "A"\n', "one or more")):
        bad = tmp_path / "not_tables.toml"
        bad.write_text(text)
        with pytest.raises(ValueError, match=re.escape(says)):
            load_situations(bad)
    assert cli.main(["eval", "--dpi", "0", "--no-progress", "--mode", "cv"]) == 2
    assert "--dpi" in capsys.readouterr().err
    bad = tmp_path / "bad.toml"
    bad.write_text('[[situation]]\nrecording = "k729_2022-03-16"\nstart = 5\nend = 2\n')
    with pytest.raises(ValueError, match="end > start"):
        load_situations(bad)
    assert cli.main(["eval", "--situations", str(bad), "--no-progress", "--mode", "cv"]) == 2
    missing = tmp_path / "other.toml"
    missing.write_text('[[situation]]\nrecording = "nowhere"\n')
    assert cli.main(["eval", "--situations", str(missing), "--no-progress", "--mode", "cv", "--max-frames", "5"]) == 2
    assert "nowhere" in capsys.readouterr().err
