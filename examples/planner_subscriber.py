"""Read hybrid-iamp's predictions from your own process, as a planner would: plain zenoh, msgpack and numpy only.

It uses nothing of this project (no ``bus_schemas``), so it doubles as the reference for a C++ or Rust reader of the
wire format documented in docs/wire.md. Run a pipeline, note its hub endpoint, then::

    python launch.py --no-viewer --listen tcp/127.0.0.1:7447          # prints "[launch] pipeline ...: run=demo hub=..."
    python examples/planner_subscriber.py tcp/127.0.0.1:7447 demo      # in a second shell

For a few frames it prints how late the frame's MotionGrid came, the occupancy probability under each vehicle's
predicted mean at 2 s, and every vehicle's corridors with their probabilities and mean positions at 2 s.
"""

from __future__ import annotations

import math
import sys
import threading
import time

import msgpack
import numpy as np

#: the schema versions this reader was written for (docs/wire.md, "Versions")
VERSIONS = {"iamp.SceneInfo": 4, "iamp.MotionGrid": 3, "iamp.CorridorPredictions": 3}


def unpack(payload: bytes) -> tuple[str, int, dict]:
    """The envelope ``{"schema", "v", "body"}`` of one message: (schema, version, body)."""
    envelope = msgpack.unpackb(payload, raw=False)
    return envelope["schema"], envelope["v"], envelope["body"]


def array(field: list) -> np.ndarray:
    """An array field, ``[dtype name, shape, bytes]``: little-endian, C order."""
    dtype, shape, data = field
    return np.frombuffer(data, dtype=np.dtype(dtype).newbyteorder("<")).reshape(shape)


def occupancy(grid: dict, k: int, x_m: float, y_m: float) -> float:
    """The MotionGrid's probability at map point (x, y) in step ``k`` (0 where the cell is not listed).

    Cell (row, col) covers x in [origin_x + col * cell, origin_x + (col + 1) * cell), y likewise from origin_y (row 0
    is the southern edge); a step lists its cells sorted by row, then column."""
    col = math.floor((x_m - grid["origin_x_m"]) / grid["cell_m"])
    row = math.floor((y_m - grid["origin_y_m"]) / grid["cell_m"])
    step = grid["steps"][k]
    keys = array(step["rows"]).astype(np.int64) * grid["n_cols"] + array(step["cols"])
    i = int(np.searchsorted(keys, row * grid["n_cols"] + col))
    return float(array(step["values"])[i]) if i < keys.size and keys[i] == row * grid["n_cols"] + col else 0.0


def vehicles(predictions: dict, k: int) -> dict[int, list[tuple[int, float, float, float]]]:
    """Per track id its corridors at step ``k``: (corridor id, probability, mean x, mean y); NaN where no mass is left."""
    out: dict[int, list] = {}
    for p in predictions["predictions"]:
        out.setdefault(p["track_id"], []).append(
            (p["corridor_id"], p["probability"], float(array(p["mean_x_m"])[k]), float(array(p["mean_y_m"])[k])))
    return out


def main(hub: str, run: str, frames: int = 5, horizon_s: float = 2.0) -> int:
    import zenoh

    config = zenoh.Config()
    config.insert_json5("mode", '"client"')
    config.insert_json5("connect/endpoints", f'["{hub}"]')
    pending: dict[int, dict[str, dict]] = {}  # frame stamp -> schema -> body
    lock, done, shown_scene = threading.Lock(), threading.Event(), threading.Event()
    shown = [0]

    def on_scene(payload: bytes) -> None:
        schema, version, scene = unpack(payload)
        with lock:
            if shown_scene.is_set() or VERSIONS.get(schema) != version:
                return
            shown_scene.set()
        print(f"scene {scene['recording']}: origin {scene['origin_lat_deg']}, {scene['origin_lon_deg']} deg,"
              f" projection {scene['projection']}, stamps on the {scene['clock']} clock (docs/wire.md, \"Frames\", \"Time\")")

    def on_sample(sample) -> None:
        if str(sample.key_expr).endswith("/scene"):
            on_scene(sample.payload.to_bytes())
            return
        schema, version, body = unpack(sample.payload.to_bytes())
        if VERSIONS.get(schema) != version:
            print(f"skipping {schema} v{version}: this reader knows v{VERSIONS.get(schema)}", file=sys.stderr)
            return
        if body.get("shard"):  # a shard's own output (sharded pipelines): only its vehicles; grid_fusion's has the frame's
            return
        with lock:
            parts = pending.setdefault(body["header"]["stamp_ns"], {})
            parts[schema] = body
            if len(parts) < 2 or done.is_set():
                return
            del pending[body["header"]["stamp_ns"]]
        grid, predictions = parts["iamp.MotionGrid"], parts["iamp.CorridorPredictions"]
        times = array(grid["step_times_s"])
        k = int(np.argmin(np.abs(times - horizon_s)))
        header = grid["header"]
        late = f"{(time.time_ns() - header['source_wall_ns']) / 1e6:.0f} ms after the source published it" if header["source_wall_ns"] else "lateness unknown"
        print(f"frame {header['frame_index']} (stamp {header['stamp_ns']} ns), {grid['mode']}: {late}; step {k} = {times[k]:g} s ahead")
        missing = sorted(set(grid.get("missing_shards", ())) | set(predictions.get("missing_shards", ())))
        if missing:  # a fused frame without some shard's vehicles: an empty cell there is not a free one
            print(f"  WARNING: shard(s) {', '.join(missing)} missing from this frame: their vehicles are not predicted")
        for track, corridors in sorted(vehicles(predictions, k).items()):
            best = max(corridors, key=lambda c: c[1])
            print(f"  vehicle {track}: {len(corridors)} corridors; most probable {best[0]} p={best[1]:.2f} at ({best[2]:.1f}, {best[3]:.1f}) m,"
                  f" grid there {occupancy(grid, k, best[2], best[3]):.3f}" if math.isfinite(best[2]) else f"  vehicle {track}: no mass left")
        shown[0] += 1
        if shown[0] >= frames:
            done.set()

    session = zenoh.open(config)
    try:
        # subscribe first, then ask: the scene is published once before the first frame and answered to queries
        # after that (latched), so one of the two gets it whenever this starts
        subscribers = [session.declare_subscriber(f"iamp/{run}/*/{output}", on_sample) for output in ("scene", "motion_grid", "corridor_predictions")]
        for reply in session.get(f"iamp/{run}/*/scene", timeout=2.0):
            if reply.ok is not None:
                on_scene(reply.ok.payload.to_bytes())
        if not done.wait(60.0):
            print("no complete frame within 60 s: is the pipeline running, and are hub and run id right?", file=sys.stderr)
            return 1
        del subscribers
        return 0
    finally:
        session.close()  # before exit: a session left open with callbacks can hang the interpreter


if __name__ == "__main__":
    if len(sys.argv) != 3:
        print(__doc__.split("\n\n")[1].strip(), file=sys.stderr)
        print("usage: planner_subscriber.py HUB_ENDPOINT RUN_ID", file=sys.stderr)
        raise SystemExit(2)
    raise SystemExit(main(sys.argv[1], sys.argv[2]))
