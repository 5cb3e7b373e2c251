"""Issue 13 over the real bus: hostile payloads published to a running stage are counted, and it goes on.

A real stage process (``echo_stage.py``, on the real runtime) subscribed on
loopback Zenoh gets a good AccelerationProfiles, then the ``[0, 2**63]``
shaped payload that ended markov_prediction, garbage, deep nesting and an
oversized payload, then another good one. It must echo both good ones, count
every bad one in NodeStats, still be running, log each kind of problem once
and log its issue episode once at stop.
"""

from __future__ import annotations

import msgpack

import bus_schemas as bs
from testkit.helpers import endpoint, free_port, kill_all, output_of, stop_process, wait_until
from tests.integration.echo_stage import profiles_payload
from tests.integration.echo_stage import start as start_echo

RUN = "hostile"
KEY_IN = f"iamp/{RUN}/src/profiles"


def _huge_dim(frame_index: int) -> bytes:
    """An empty 2-D input_probs of shape [0, 2**63] (its k arrays emptied too, so every dim agrees)."""
    env = msgpack.unpackb(profiles_payload(frame_index), raw=False)
    p = env["body"]["profiles"][0]
    p["chunk_mean_mps2"] = ["float32", [0], b""]
    p["chunk_sigma_mps2"] = ["float32", [0], b""]
    p["input_probs"] = ["float32", [0, 2**63], b""]
    return msgpack.packb(env, use_bin_type=True)


def test_hostile_payloads_are_counted_and_the_stage_processes_the_next_good_message():
    pack = msgpack.packb
    head = b"\x83" + pack("schema") + pack("iamp.AccelerationProfiles") + pack("v") + pack(1) + pack("body")
    oversized = head + b"\xc6" + (5 * 1024 * 1024).to_bytes(4, "big") + b"\0" * (5 * 1024 * 1024)  # a 5 MiB bin body
    assert len(oversized) > bs.AccelerationProfiles.MAX_BYTES
    bad = [_huge_dim(1), b"\x93not an envelope", b"\x93not an envelope", b"\x83" + b"\x91" * 100_000 + b"\xc0", oversized]
    port = free_port()
    got: list[int] = []
    stats: list[bs.NodeStats] = []
    from stages.runtime import BusClient

    with BusClient(listen=[endpoint(port)]) as bus:
        bus.subscribe(f"iamp/{RUN}/echo/profiles", lambda k, d: got.append(bs.AccelerationProfiles.decode(d).header.frame_index))
        bus.subscribe(f"iamp/{RUN}/_stats/echo", lambda k, d: stats.append(bs.NodeStats.decode(d)))
        stage = start_echo(port, RUN, "--stats-period", "0.2")
        try:
            wait_until(lambda: "echo" in bus.alive_now(f"iamp/{RUN}/_alive/*", 0.5), 60, "echo liveliness")
            put = bus.publisher(KEY_IN)
            put(profiles_payload(0))
            wait_until(lambda: got == [0], 30, "the first echo")
            for data in bad:
                put(data)
            put(profiles_payload(2))
            try:
                wait_until(lambda: len(got) == 2, 30, "the echo after the hostile payloads")
            except AssertionError as exc:
                raise AssertionError(f"{exc}; exit code {stage.poll()}, stage output:\n{output_of(stage)[-3000:]}") from None
            assert got == [0, 2]
            wait_until(lambda: stats and stats[-1].counters["decode_errors"] == len(bad), 30, "stats with every hostile payload counted")
            s = stats[-1]
            assert s.errors_by_kind == {"MalformedPayload": 4, "PayloadTooLarge": 1}, s.errors_by_kind
            assert s.counters["processed"] == 2 and s.counters["core_errors"] == 0
            assert s.counters["issues"] == 2 and s.issues_by_kind == {"echoed": 2}
            assert stage.poll() is None, output_of(stage)[-3000:]  # still running
            assert stop_process(stage) == 0
        finally:
            kill_all([stage])
    log = output_of(stage)
    lines = log.splitlines()
    dropped = [ln for ln in lines if "dropped message:" in ln]
    # one line per kind of problem: the first MalformedPayload (the issue 13 payload) and the PayloadTooLarge
    assert len(dropped) == 2, dropped
    assert (
        f"dropped message: reason=MalformedPayload key={KEY_IN} detail=iamp.AccelerationProfiles.profiles[0].input_probs on {KEY_IN}: "
        "array shape [0, 9223372036854775808] is not a list of ints in 0..2147483647"
    ) in dropped[0]
    assert f"dropped message: reason=PayloadTooLarge key={KEY_IN} detail=iamp.AccelerationProfiles payload on {KEY_IN} has" in dropped[1]
    assert "(AccelerationProfiles.MAX_BYTES)" in dropped[1]
    assert f"not shown at stop: 3 more of kind decode:MalformedPayload:{KEY_IN}" in log
    # the echoed issue: one line when it started, one at stop (it never ended), none per frame
    assert sum("issue: kind=echoed agent=7" in ln for ln in lines) == 1
    assert "issue open at stop: kind=echoed agent=7 frames=2 first_stamp_ns=1000000000 last_stamp_ns=1200000000 duration_s=0.2" in log
    assert "Traceback" not in log
