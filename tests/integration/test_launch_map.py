"""launch.py on a data folder whose map is unusable: the run stops at once with exit 2 and the map's problem."""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

import pytest

from test_launch_run import Launch

from stages.lib.datasets import DEFAULT_DATA_DIR, DEFAULT_RECORDING

pytestmark = pytest.mark.skipif(not (DEFAULT_DATA_DIR / "maps").is_dir(), reason=f"embedded TAF-BW data not found at {DEFAULT_DATA_DIR}")


def test_an_unusable_map_stops_the_run_with_exit_2_and_says_why(tmp_path):
    data = tmp_path / "taf-bw"
    shutil.copytree(DEFAULT_DATA_DIR, data)
    osm = data / "maps" / f"{DEFAULT_RECORDING}.osm"
    osm.write_text("this is not OSM XML <<<")
    run = Launch("--data", str(data), "--recording", DEFAULT_RECORDING, "--speed", "2", "--no-viewer", "--no-record", "--run-id", "badmap", cwd=tmp_path)
    try:
        code = run.wait(180)  # no --stop-after: it stops by itself
    finally:
        run.proc.kill()
    out = run.text()
    assert code == 2, out[-4000:]
    stop = [line for line in out.splitlines() if line.startswith("[launch] stopping the run: corridors reports map ")]
    assert len(stop) == 1 and f"map {osm.name} unusable: " in stop[0] and "lanelet2 could not read" in stop[0], out[-4000:]
    assert "[launch] run ended: exit code 2" in out
    assert "all sources finished" not in out, "stopped at once, not at the end of the data"
