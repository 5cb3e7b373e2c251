"""``examples/planner_subscriber.py``: a planner's reader of the predictions (plain zenoh, msgpack, numpy) against the
running default pipeline, and its decoding of real payloads against the project's own decoders.

docs/wire.md documents the wire format for readers in other languages with that script as its reference; this test
keeps the two honest: the script runs against a real pipeline over Zenoh, and its functions read every listed cell of
real MotionGrids and every corridor of real CorridorPredictions as ``bus_schemas`` decodes them.
"""

from __future__ import annotations

import runpy
import signal
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np

import bus_schemas as bs
from stages.runtime import BusClient
from testkit.helpers import endpoint, free_port, kill_all, python_env, wait_until
from tests.integration.test_launch_run import Launch

REPO = Path(__file__).resolve().parents[2]
EXAMPLE = REPO / "examples" / "planner_subscriber.py"


def test_the_planner_example_reads_the_running_pipeline_as_the_project_decodes_it(tmp_path):
    port = free_port()
    hub = endpoint(port)
    run = Launch("--no-viewer", "--no-record", "--listen", hub, "--speed", "2", "--stop-after", "60", "--run-id", "plan", cwd=tmp_path)
    raw: dict[str, list[bytes]] = {"motion_grid": [], "corridor_predictions": []}
    lock = threading.Lock()

    def keep(key: str, data: bytes) -> None:
        with lock:
            raw[key.rsplit("/", 1)[-1]].append(bytes(data))

    try:
        run.wait_line(r"^\[launch\] all \d+ nodes alive; starting sources")
        with BusClient(connect=[hub]) as bus:
            for output in raw:
                bus.subscribe(f"iamp/plan/markov_prediction/{output}", keep)
            done = subprocess.run([sys.executable, str(EXAMPLE), hub, "plan"], cwd=tmp_path, env=python_env(), capture_output=True,
                                  text=True, timeout=120)
            wait_until(lambda: all(len(v) >= 5 for v in raw.values()), 60, "MotionGrids and CorridorPredictions on the bus")
        run.proc.send_signal(signal.SIGINT)
        assert run.wait() == 0, run.text()[-3000:]
    finally:
        kill_all([run.proc])
    out = done.stdout
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    assert "scene k733_2018-05-02: origin" in out and "projection scaled_mercator, stamps on the recording clock" in out, out[:2000]
    frames = [line for line in out.splitlines() if line.startswith("frame ")]
    assert len(frames) == 5 and all("hybrid" in f and "ms after the source published it" in f and "2 s ahead" in f for f in frames), frames
    assert any(line.startswith("  vehicle ") and "corridors; most probable" in line for line in out.splitlines()), out[:3000]

    example = runpy.run_path(str(EXAMPLE))
    cells = 0
    for payload in raw["motion_grid"]:
        grid = bs.MotionGrid.decode(payload)
        schema, version, body = example["unpack"](payload)
        assert (schema, version) == ("iamp.MotionGrid", example["VERSIONS"]["iamp.MotionGrid"])
        for k, step in enumerate(grid.steps):
            x = grid.origin_x_m + (step.cols + 0.5) * grid.cell_m
            y = grid.origin_y_m + (step.rows + 0.5) * grid.cell_m
            got = [example["occupancy"](body, k, float(a), float(b)) for a, b in zip(x, y)]
            assert got == step.values.tolist()
            cells += len(got)
    assert cells > 100
    for payload in raw["corridor_predictions"]:
        preds = bs.CorridorPredictions.decode(payload)
        by_vehicle = example["vehicles"](example["unpack"](payload)[2], 4)
        want: dict[int, list] = {}
        for p in preds.predictions:
            want.setdefault(p.track_id, []).append((p.corridor_id, p.probability, float(p.mean_x_m[4]), float(p.mean_y_m[4])))
        assert by_vehicle.keys() == want.keys()
        for track, corridors in want.items():
            np.testing.assert_array_equal(np.array(by_vehicle[track], dtype=float), np.array(corridors, dtype=float))
            assert abs(sum(c[1] for c in corridors) - 1.0) < 1e-5, "a vehicle's corridor probabilities sum to 1"
