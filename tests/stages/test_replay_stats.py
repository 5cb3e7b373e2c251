"""Replay publishes its own NodeStats on ``iamp/<run>/_stats/<node>``, as every other node does.

Before, ``stages.replay`` (node ``source`` in ``stages/pipelines/replay.toml``) published none: the viewer's Stages
table and a recording of a replayed run had no row for the source, and its skipped and damaged counters were only in
its log. A recording with a recorded NodeStats (an infrastructure key, not replayed), a key of another layout and a
damaged chunk is replayed by ``python -m stages.replay`` (as the launcher starts it) into a session of this test.
"""

from __future__ import annotations

import json
import re
import threading
from pathlib import Path

from mcap.reader import make_reader

from testkit import helpers as h

from bus_schemas import NodeStats, keys
from stages.recorder.core import McapRecorder, RecorderConfig
from stages.recorder.inspect import ReadReport, read_messages
from stages.runtime import BusClient
from test_mcap import STAMP0_NS, make_frame, make_scene

N_FRAMES = 60
RUN = "t5"


def write_recording(path: Path) -> Path:
    """Scene, N_FRAMES frames in small chunks, one recorded NodeStats and one key of no iamp layout."""
    with McapRecorder(RecorderConfig(path=str(path), chunk_size_bytes=1500), "t1") as rec:
        rec.handle(keys.data_key("t1", "source", "scene"), make_scene("t1").encode(), STAMP0_NS)
        for i in range(N_FRAMES):
            rec.handle(keys.data_key("t1", "source", "track_frame"), make_frame(i, "t1").encode(), STAMP0_NS + 1 + 2 * i)
        stats = NodeStats(run_id="t1", node_id="corridors", stage="stages.corridors", pid=1, uptime_s=1.0, counters={}, issues_by_kind={},
                          errors_by_kind={}, proc_ms_p50=0.0, proc_ms_p95=0.0, proc_ms_max=0.0, latency_ms_p50=0.0, latency_ms_p95=0.0,
                          queue_depth=0, last_stamp_ns=0)
        rec.handle(keys.stats_key("t1", "corridors"), stats.encode(), STAMP0_NS + 2 * N_FRAMES)
        rec.handle("elsewhere/some/topic", b"not ours", STAMP0_NS + 2 * N_FRAMES + 1)
    return path


def damage_a_middle_chunk(path: Path) -> int:
    """Flip bytes inside the compressed data of the middle chunk (its framing intact); returns its length on disk."""
    with open(path, "rb") as f:
        chunks = sorted(make_reader(f).get_summary().chunk_indexes, key=lambda c: c.chunk_start_offset)
    assert len(chunks) >= 10
    chunk = chunks[len(chunks) // 2]
    data = bytearray(path.read_bytes())
    for i in range(chunk.chunk_start_offset + chunk.chunk_length // 2, chunk.chunk_start_offset + chunk.chunk_length // 2 + 50):
        data[i] ^= 0xFF
    path.write_bytes(bytes(data))
    return chunk.chunk_length


def test_replay_publishes_its_node_stats_with_what_it_replayed_skipped_and_passed_over(tmp_path):
    src = write_recording(tmp_path / "src.mcap")
    damaged_bytes = damage_a_middle_chunk(src)
    report = ReadReport()
    replayable = [m for m in read_messages(str(src), report) if not m.topic.startswith("elsewhere/") and "/_stats/" not in m.topic]
    assert report.damaged_chunks == 1 and 0 < len(replayable) < N_FRAMES + 1

    got: list[NodeStats] = []
    lock = threading.Lock()

    def on_stats(key: str, data: bytes) -> None:
        with lock:
            got.append(NodeStats.decode(data))

    port = h.free_port()
    procs = []
    try:
        with BusClient(listen=[h.endpoint(port)]) as bus:
            bus.subscribe(keys.stats_pattern(RUN), on_stats)
            bus.subscribe(keys.data_key(RUN, "source", "track_frame"), lambda _k, _d: None)  # a subscriber for the replay to find
            rp = h.start_module("stages.replay", "--node-id", "source", "--run-id", RUN, "--connect", h.endpoint(port), "--stats-period", "0.2",
                                "--listen", "tcp/127.0.0.1:0",  # it says the port it got (a reader connects there)
                                "--params-json", json.dumps({"path": str(src), "speed": "max"}), log_dir=tmp_path)
            procs.append(rp)
            rp.wait(timeout=120)
            out = h.output_of(rp)
            assert rp.returncode == 0, out
            assert f"replay finished: messages={len(replayable)}" in out, out
            listening = re.search(r"replay up: .* listening=tcp/127\.0\.0\.1:(\d+)", out)
            assert listening and int(listening.group(1)) > 0, out

            def final():
                with lock:
                    mine = [s for s in got if s.node_id == "source"]
                return next((s for s in mine if s.counters.get("published") == len(replayable)), None)

            stats = h.wait_until(final, 30.0, f"the replay's NodeStats with published={len(replayable)} (got: {[s.counters for s in got][-2:]})\n{out}")
    finally:
        h.kill_all(procs)
    assert stats.stage == "stages.replay" and stats.run_id == RUN
    c = stats.counters
    assert c["processed"] == len(replayable)
    assert c["skipped.infrastructure"] == 1 and c["skipped.foreign_key"] == 1 and c["skipped.other_node"] == 0 and c["skipped"] == 2, c
    assert c["damaged_chunks"] == 1 and c["damaged_bytes"] == damaged_bytes and c["truncated_file"] == 0, c
    assert stats.last_stamp_ns > STAMP0_NS


def test_a_recording_whose_grids_are_another_nodes_says_how_to_show_them(tmp_path, caplog):
    """Found by a new-user probe: a sharded run records its MotionGrids on grid_fusion/motion_grid (and the shards'),
    the replay pipeline's viewer read markov_prediction's, and the replay showed no prediction without a word. Now
    the replay says whose grids the file holds and the ``--var GRIDS=`` that shows them; a file with the shown node's
    grids, or a replay with no viewer to feed (``shown_grids = ""``), says nothing."""
    import logging

    from testkit import samples
    from stages.replay.core import _say_whose_grids

    grid = samples.motion_grid().encode()

    def recording(name: str, nodes: tuple[str, ...]) -> str:
        path = tmp_path / name
        with McapRecorder(RecorderConfig(path=str(path)), "t1") as rec:
            rec.handle(keys.data_key("t1", "source", "track_frame"), make_frame(0, "t1").encode(), STAMP0_NS)
            for k, node in enumerate(nodes):
                rec.handle(keys.data_key("t1", node, "motion_grid"), grid, STAMP0_NS + 1 + k)
        return str(path)

    log = logging.getLogger("iamp.test_replay")
    caplog.set_level(logging.WARNING, logger=log.name)
    sharded = recording("sharded.mcap", ("markov_0", "markov_1", "grid_fusion"))
    _say_whose_grids(sharded, "markov_prediction", log)
    lines = [r.getMessage() for r in caplog.records if r.name == log.name]
    assert len(lines) == 1 and "grid_fusion, markov_0, markov_1, not markov_prediction" in lines[0], lines
    assert lines[0].endswith(f"launch.py replay --var FILE={sharded} --var GRIDS=grid_fusion")
    caplog.clear()
    _say_whose_grids(sharded, "grid_fusion", log)  # told: nothing to say
    _say_whose_grids(recording("plain.mcap", ("markov_prediction",)), "markov_prediction", log)
    assert not [r for r in caplog.records if r.name == log.name]
