"""A stage slower than its input, with ``--max-age-s`` (the live pipeline's ``max_age_s``), over a real Zenoh hub.

Session 42's probe fed 200 vehicles to ``launch.py live`` and found the stages 14 s behind: each worked through its
queue of old frames. Here a real stage process takes 0.1 s a frame while its input comes ten times as fast: with a
0.3 s age bound it skips what waited longer (counted, ``stale_drops``), works on its freshest frames and never on one
older than the bound plus a frame, and the last frame sent is always echoed.
"""

from __future__ import annotations

import time

import bus_schemas as bs
from bus_schemas import keys
from testkit.helpers import endpoint, free_port, kill_all, output_of, stop_process, wait_until
from tests.integration.echo_stage import profiles_payload
from tests.integration.echo_stage import start as start_echo

RUN = "stale"
FRAMES = 40


def test_a_stage_behind_its_input_skips_stale_frames_counted_and_echoes_the_newest():
    port = free_port()
    got: list[tuple[int, float]] = []  # (frame, seconds from its put to its echo)
    sent: dict[int, float] = {}
    stats: list[bs.NodeStats] = []
    from stages.runtime import BusClient

    with BusClient(listen=[endpoint(port)]) as bus:
        bus.subscribe(f"iamp/{RUN}/echo/profiles", lambda k, d: got.append(
            (f := bs.AccelerationProfiles.decode(d).header.frame_index, time.monotonic() - sent[f])))
        bus.subscribe(keys.stats_key(RUN, "echo"), lambda k, d: stats.append(bs.NodeStats.decode(d)))
        stage = start_echo(port, RUN, "--max-age-s", "0.3", "--set", "delay_s=0.1", "--stats-period", "0.2")
        try:
            wait_until(lambda: "echo" in bus.alive_now(f"iamp/{RUN}/_alive/*", 0.5), 60, "echo liveliness")
            put = bus.publisher(f"iamp/{RUN}/src/profiles")
            for i in range(FRAMES):  # 100 Hz for 0.4 s: ten frames for each one the stage can handle
                sent[i] = time.monotonic()
                put(profiles_payload(i))
                time.sleep(0.01)
            wait_until(lambda: got and got[-1][0] == FRAMES - 1, 30, "the last frame echoed")
            wait_until(lambda: stats and stats[-1].counters.get("received", 0) == FRAMES and stats[-1].counters.get("processed", 0) == len(got),
                       30, "the node's stats after its last frame")
            assert stop_process(stage) == 0
        finally:
            kill_all([stage])
    c = stats[-1].counters
    frames = [f for f, _ in got]
    assert frames == sorted(frames) and frames[-1] == FRAMES - 1, frames
    assert c["stale_drops"] > 0 and c["stale_drops.profiles"] == c["stale_drops"], c
    assert c["stale_drops"] + len(got) == FRAMES and c["queue_drops"] == 0 and c["join_drops"] == 0, (c, frames)
    # a frame waited at most the bound in the queue, then one frame's work before it, and its own: never the 4 s
    # that working through every frame would take
    assert max(age for _, age in got) < 0.3 + 3 * 0.1 + 0.5, got
    assert "input older than 0.30 s skipped: port=profiles" in output_of(stage), output_of(stage)[-2000:]
