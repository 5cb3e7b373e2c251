"""``iamp eval`` on a data folder whose map is unusable: exit 2 with the map's problem in one line, no table."""

from __future__ import annotations

import shutil

import pytest

from stages import cli
from stages.lib.datasets import DEFAULT_DATA_DIR, DEFAULT_RECORDING

pytestmark = pytest.mark.skipif(not (DEFAULT_DATA_DIR / "maps").is_dir(), reason=f"embedded TAF-BW data not found at {DEFAULT_DATA_DIR}")

ARGS = ["--recording", DEFAULT_RECORDING, "--sequence", "019", "--mode", "cv", "--max-frames", "5", "--no-progress"]


@pytest.mark.parametrize(
    "content",
    [
        "",  # empty file
        "this is not OSM XML <<<",
        "<?xml version='1.0'?><osm version='0.6'><node id='-1' lat='48.0' lon='8.0'/></osm>",  # parses, no lanelets
    ],
    ids=["empty", "garbage", "no-lanelets"],
)
def test_an_unusable_map_is_an_error_with_the_problem_in_one_line(tmp_path, capsys, content):
    data = tmp_path / "taf-bw"
    shutil.copytree(DEFAULT_DATA_DIR, data)
    osm = data / "maps" / f"{DEFAULT_RECORDING}.osm"
    assert osm.is_file()
    osm.write_text(content)
    code = cli.main(["eval", "--data", str(data), *ARGS])
    captured = capsys.readouterr()
    assert code == 2, captured.out[-2000:]
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1, captured.err
    assert lines[0].startswith("iamp eval: error: ") and f"{DEFAULT_RECORDING}.osm" in lines[0] and "unusable" in lines[0], lines[0]
    assert "mADE" not in captured.out, "no all-NaN table"


def test_the_embedded_map_still_evaluates(capsys):
    assert cli.main(["eval", *ARGS]) == 0
    assert "cv" in capsys.readouterr().out
