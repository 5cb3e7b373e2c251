"""The viewer's pure helpers (``stages.viewer.model``) that the browser test does not reach."""

from __future__ import annotations

import datetime

from stages.viewer.model import WALL_CLOCK_FROM_NS, stamp_text


def test_a_stamp_reads_as_recording_time_or_as_the_utc_time_of_a_live_trackers_wall_clock():
    assert stamp_text(0) == "t = 0.0 s"
    assert stamp_text(12_345_000_000) == "t = 12.3 s"
    assert stamp_text(WALL_CLOCK_FROM_NS - 1).startswith("t = ")
    wall = 1_796_510_259_325_833_659
    when = datetime.datetime.fromtimestamp(wall // 10**9, datetime.timezone.utc)
    assert stamp_text(wall) == f"{when:%H:%M:%S}.3 UTC" == "22:37:39.3 UTC"
