"""Two markov_prediction shards and grid_fusion as separate processes, every one a Zenoh client of a router process.

The router is ``python -m stages.runtime.router`` (a Zenoh session in router
mode: zenohd is not on PyPI). The test publishes the embedded scenario's
stage inputs (computed in-process), one frame at a time, to an unsharded
markov_prediction, shards 0/2 and 1/2 and grid_fusion; no two processes
are peers, so everything goes through the router. It checks that the fused
MotionGrid equals the unsharded one within the shards' ``min_value``, then
SIGKILLs shard 1 and checks that frames keep coming with shard 0's vehicles
only, counted as ``shard_missing`` in grid_fusion's NodeStats.
"""

from __future__ import annotations

import json
import signal

import pytest

import bus_schemas as bs
from stages.ar_inference import ARInference, ARInferenceConfig
from stages.corridors import SceneMaps
from stages.intentions import IntentionsConfig
from stages.lib.datasets import DEFAULT_DATA_DIR, load_recording
from stages.lib.grid_fusion import shard_of
from stages.offline.chain import chain_frames
from testkit.helpers import endpoint, free_port, kill_all, output_of, start_module, stop_process, wait_until

RUN = "shardtest"
N_BEFORE, N_AFTER = 4, 3


def _dense(grid):
    ox, oy = int(round(grid.origin_x_m / grid.cell_m)), int(round(grid.origin_y_m / grid.cell_m))
    return {(k, ox + int(c), oy + int(r)): float(v) for k, s in enumerate(grid.steps) for r, c, v in zip(s.rows, s.cols, s.values)}


def _inputs():
    recording = load_recording(DEFAULT_DATA_DIR, "k729_2022-03-16", ("019",))
    items = chain_frames(recording, recording.sequences[0], SceneMaps(), intentions=IntentionsConfig(), max_frames=58)
    ar = ARInference(ARInferenceConfig(), producer="ar_inference")
    out = []
    for n, item in enumerate(items):
        profiles = ar.process(item.corridor_set, item.relation_set, item.frame, item.scene)[0]
        if n >= 10 and {shard_of(v.track_id, 2) for v in item.corridor_set.vehicles if v.corridors} == {0, 1}:
            out.append((item, profiles))
        if len(out) == N_BEFORE + N_AFTER:
            return out
    pytest.fail("the embedded sequence 019 has too few frames with vehicles in both shards")


@pytest.mark.timeout(300)
def test_two_shards_through_a_router_equal_one_and_degrade_when_one_dies():
    from stages.runtime import BusClient

    frames = _inputs()
    port = free_port()
    router = start_module("stages.runtime.router", "--listen", endpoint(port))
    procs = [router]
    try:
        wait_until(lambda: "router listening on" in output_of(router), 60, "the router")
        net = ["--mode", "client", "--connect", endpoint(port), "--stats-period", "0.2"]
        ins = [x for p in ("corridor_set", "relation_set", "scene", "track_frame", "intention_belief", "acceleration_profiles")
               for x in ("--input", f"{p}=src/{p}")]
        for node, shard in (("m_all", ""), ("m0", "0/2"), ("m1", "1/2")):
            procs.append(start_module("stages.markov_prediction", "--node-id", node, "--run-id", RUN, *net, *ins,
                                      "--params-json", json.dumps({"mode": "hybrid", "shard": shard})))
        fusion_ins = [x for i in (0, 1) for x in ("--input", f"grid_{i}=m{i}/motion_grid", "--input", f"predictions_{i}=m{i}/corridor_predictions")]
        procs.append(start_module("stages.grid_fusion", "--node-id", "fusion", "--run-id", RUN, *net, *fusion_ins,
                                  "--params-json", json.dumps({"shard_timeout_s": 3.0})))
        m1 = procs[3]
        with BusClient(mode="client", connect=[endpoint(port)]) as bus:
            got: dict[str, dict[int, bs.MotionGrid]] = {"m_all": {}, "m0": {}, "fusion": {}}
            preds: dict[int, bs.CorridorPredictions] = {}
            stats: dict[str, bs.NodeStats] = {}
            for node in got:
                bus.subscribe(f"iamp/{RUN}/{node}/motion_grid", lambda k, d, node=node: got[node].__setitem__(bs.MotionGrid.decode(d).header.stamp_ns, bs.MotionGrid.decode(d)))
            bus.subscribe(f"iamp/{RUN}/fusion/corridor_predictions", lambda k, d: preds.__setitem__(bs.CorridorPredictions.decode(d).header.stamp_ns, bs.CorridorPredictions.decode(d)))
            bus.subscribe(f"iamp/{RUN}/_stats/fusion", lambda k, d: stats.__setitem__("fusion", bs.NodeStats.decode(d)))
            wait_until(lambda: {"m_all", "m0", "m1", "fusion"} <= bus.alive_now(f"iamp/{RUN}/_alive/*", 0.5), 120, "the nodes' liveliness")
            scene = frames[0][0].scene
            bus.declare_queryable(f"iamp/{RUN}/src/scene", lambda: scene.encode())
            put = {p: bus.publisher(f"iamp/{RUN}/src/{p}") for p in ("scene", "corridor_set", "relation_set", "track_frame", "intention_belief", "acceleration_profiles")}
            put["scene"](scene.encode())

            def send(item, profiles):
                put["track_frame"](item.frame.encode())
                put["corridor_set"](item.corridor_set.encode())
                put["relation_set"](item.relation_set.encode())
                put["intention_belief"](item.belief.encode())
                put["acceleration_profiles"](profiles.encode())
                return int(item.corridor_set.header.stamp_ns)

            for item, profiles in frames[:N_BEFORE]:
                stamp = send(item, profiles)
                try:
                    wait_until(lambda: stamp in got["fusion"] and stamp in got["m_all"], 120, f"the grids of stamp {stamp}")
                except AssertionError as exc:
                    raise AssertionError(f"{exc}\n" + "\n".join(f"--- {p.args[2:5]}\n{output_of(p)[-1500:]}" for p in procs)) from None
                one, fused = _dense(got["m_all"][stamp]), _dense(got["fusion"][stamp])
                tolerance = 2 * got["m_all"][stamp].min_value + 1e-6
                bad = [k for k in set(one) | set(fused) if abs(one.get(k, 0.0) - fused.get(k, 0.0)) > tolerance]
                assert one and not bad, (len(bad), len(one), output_of(procs[-1])[-2000:])
                wait_until(lambda: stamp in preds, 30, "the merged predictions")
                all_tracks = {v.track_id for v in item.corridor_set.vehicles if v.corridors}
                assert {p.track_id for p in preds[stamp].predictions} == all_tracks
                # whose vehicles each message covers: the shards say which they are, the fused frame lacks none
                assert [got[n][stamp].shard for n in ("m_all", "m0", "fusion")] == ["", "0/2", ""]
                assert got["fusion"][stamp].missing_shards == () and preds[stamp].missing_shards == ()
            assert stats.get("fusion") is None or not stats["fusion"].issues_by_kind.get("shard_missing")

            m1.send_signal(signal.SIGKILL)
            m1.wait()
            for item, profiles in frames[N_BEFORE:]:
                stamp = send(item, profiles)
                wait_until(lambda: stamp in got["fusion"] and stamp in got["m0"], 60, f"the fused grid of stamp {stamp} without shard 1")
                only0 = _dense(got["m0"][stamp])
                fused = _dense(got["fusion"][stamp])
                assert fused == pytest.approx(only0, abs=1e-6)  # shard 0's vehicles, nothing waits for shard 1
                assert got["fusion"][stamp].missing_shards == ("1/2",)  # and the message says so, on the bus
                wait_until(lambda: stamp in preds, 30, "the merged predictions")
                assert preds[stamp].missing_shards == ("1/2",)
                assert {p.track_id for p in preds[stamp].predictions} == {v.track_id for v in item.corridor_set.vehicles
                                                                          if v.corridors and shard_of(v.track_id, 2) == 0}
            wait_until(lambda: stats.get("fusion") and stats["fusion"].issues_by_kind.get("shard_missing", 0) >= N_AFTER, 30,
                       "grid_fusion counting the frames without shard 1")
        for proc in procs:
            if proc is not m1:
                assert stop_process(proc) == 0, output_of(proc)[-3000:]
    finally:
        kill_all(procs)
