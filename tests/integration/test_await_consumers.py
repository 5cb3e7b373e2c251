"""An operator holds its first publish until the nodes that read its outputs are visible on the bus.

A put made before a subscriber's declaration has reached the publishing
session is routed to nobody and lost: under load, a stage's first frames
went missing at the recorder although the source had waited for every node
(the source seeing the recorder says nothing about what the stage's own
session sees). The launcher passes every operator ``--await-nodes`` with the
nodes that read it (the recorder reads all); the operator waits for their
liveliness tokens, in its own session, before it handles its first input set.
"""

from __future__ import annotations

import bus_schemas as bs
from bus_schemas import keys
from stages.runtime import launcher
from stages.runtime.pipeline import load_pipeline
from testkit.helpers import endpoint, free_port, kill_all, output_of, stop_process, wait_until
from tests.integration.echo_stage import profiles_payload
from tests.integration.echo_stage import start as start_echo

RUN = "awaits"


def test_the_launcher_tells_each_operator_to_await_the_nodes_that_read_it():
    args = launcher.build_parser().parse_args(["hybrid", "--no-viewer", "--record", "x.mcap"])
    pipeline = load_pipeline(launcher.resolve_pipeline_arg("hybrid"), edit=launcher.make_editor(args))
    run = launcher.Launcher(pipeline, "tcp/127.0.0.1:1", args)

    def awaited(node_id: str) -> set[str]:
        cmd = run.command(next(n for n in pipeline.nodes if n.id == node_id))
        return set(cmd[cmd.index("--await-nodes") + 1].split(",")) if "--await-nodes" in cmd else set()

    assert awaited("source") == {"corridors", "relations", "intentions", "ar_inference", "markov_prediction", "recorder"}
    assert awaited("corridors") == {"relations", "intentions", "ar_inference", "markov_prediction", "recorder"}
    assert awaited("intentions") == {"markov_prediction", "recorder"}
    assert awaited("markov_prediction") == {"recorder"}
    assert awaited("recorder") == set()  # it publishes nothing that a node reads


def test_an_operator_publishes_nothing_until_the_awaited_node_is_visible_then_everything_queued():
    port = free_port()
    got: list[int] = []
    received: list[int] = [0]  # the echo node's own count of the inputs it took in (its NodeStats)
    from stages.runtime import BusClient

    with BusClient(listen=[endpoint(port)]) as bus:
        bus.subscribe(f"iamp/{RUN}/echo/profiles", lambda k, d: got.append(bs.AccelerationProfiles.decode(d).header.frame_index))
        bus.subscribe(keys.stats_key(RUN, "echo"), lambda k, d: received.__setitem__(0, bs.NodeStats.decode(d).counters.get("received", 0)))
        stage = start_echo(port, RUN, "--await-nodes", "sink", "--stats-period", "0.2")
        try:
            wait_until(lambda: "echo" in bus.alive_now(f"iamp/{RUN}/_alive/*", 0.5), 60, "echo liveliness")
            put = bus.publisher(f"iamp/{RUN}/src/profiles")
            put(profiles_payload(0))
            put(profiles_payload(1))
            # the negative check waits on evidence, not a fixed span: the node reports both inputs received (its stats
            # go out after any echo it would have published for them), and the awaited node is not visible
            wait_until(lambda: received[0] >= 2, 30, "the echo node's NodeStats counting both inputs received")
            assert got == [], output_of(stage)[-2000:]
            bus.declare_token(f"iamp/{RUN}/_alive/sink")
            wait_until(lambda: len(got) == 2, 30, "both echoes once the awaited node is visible")
            assert got == [0, 1]
            assert stop_process(stage) == 0
        finally:
            kill_all([stage])
    assert "nodes not visible" not in output_of(stage)
