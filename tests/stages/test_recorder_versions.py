"""The recorder and payloads of an older schema version: one this build upgrades is known, not ``unrecognised_payload``.

In-process (``McapRecorder.handle``) with a real MCAP file: no bus is needed
to decide what a payload is.
"""

from __future__ import annotations

import msgpack
import numpy as np

from bus_schemas import Header, TrackFrame
from bus_schemas._wire import unpack_envelope
from stages.recorder.core import McapRecorder, RecorderConfig
from stages.recorder.inspect import read_messages

STAMP_NS = 1_700_000_000_000_000_000


def _frame(i: int) -> TrackFrame:
    n = 3
    return TrackFrame(
        header=Header(run_id="v", frame_index=i, stamp_ns=STAMP_NS + i * 100_000_000, producer="source", source_wall_ns=STAMP_NS + 5),
        scene_id="s", track_ids=np.arange(n, dtype=np.int64), agent_types=np.ones(n, np.uint8),
        x_m=np.zeros(n), y_m=np.zeros(n), vx_mps=np.zeros(n), vy_mps=np.zeros(n), yaw_rad=np.zeros(n),
        length_m=np.full(n, 4.5), width_m=np.full(n, 1.9),
    )


def _as_version(payload: bytes, version: int, drop_wall: bool) -> bytes:
    """The payload re-enveloped as ``version`` (the previous version had no ``header.source_wall_ns``)."""
    envelope = msgpack.unpackb(payload, raw=False)
    if drop_wall:
        envelope["body"]["header"].pop("source_wall_ns", None)
    envelope["v"] = version
    return msgpack.packb(envelope, use_bin_type=True)


def test_an_older_version_the_build_upgrades_is_recorded_without_an_issue_and_an_unknown_one_is_counted(tmp_path):
    assert TrackFrame.UPGRADES, "TrackFrame has no older version to test with"
    old = min(TrackFrame.UPGRADES)
    current = _frame(0).encode()
    upgradable = _as_version(_frame(1).encode(), old, drop_wall=True)
    unknown = _as_version(_frame(2).encode(), TrackFrame.VERSION + 7, drop_wall=False)
    # the old payload really decodes (upgraded) in this build, the unknown one does not
    assert TrackFrame.decode(upgradable).header.source_wall_ns == 0
    path = tmp_path / "versions.mcap"
    recorder = McapRecorder(RecorderConfig(path=str(path)), "v")
    try:
        issues = {name: recorder.handle(f"iamp/v/source/{name}", payload, STAMP_NS + k)
                  for k, (name, payload) in enumerate((("current", current), ("old", upgradable), ("unknown", unknown)))}
    finally:
        recorder.close()
    assert issues["current"] is None
    assert issues["old"] is None
    assert [i.kind for i in issues["unknown"]] == ["unrecognised_payload"]
    assert recorder.unrecognised == 1 and recorder.old_versions == 1 and recorder.messages == 3
    got = {m.topic.rsplit("/", 1)[-1]: m for m in read_messages(str(path))}
    assert got["old"].data == upgradable  # byte for byte
    assert unpack_envelope(got["old"].data)[1] == old
    assert got["old"].publish_time_ns == STAMP_NS + 100_000_000  # the header's stamp, as for a current payload
    assert got["unknown"].publish_time_ns == STAMP_NS + 2  # unknown: the receive time
    assert got["current"].schema == "iamp.TrackFrame" and got["old"].schema == ""
