"""``launch.py --connect ENDPOINT``: the launcher says whether its hub reached the extra endpoint.

Every node links to the hub (the launcher's own session), so a node's own check ("no link after 5 s to --connect")
stays quiet when the extra endpoint is dead: before, a run told to join a remote router where nothing listened said
nothing at all. Now the launcher warns once, naming the endpoint, and the run goes on; an endpoint that is there gets
one "hub linked" line and no warning. A run of one node (the recorder), stopped with SIGINT.
"""

from __future__ import annotations

import re
import signal
from pathlib import Path

from testkit.helpers import endpoint, free_port, kill_all
from stages.runtime import BusClient
from test_launch_run import Launch

RUN = "connectrun"
WARNING = r"^\[launch\] warning: no link after 5 s to --connect "


def _pipeline(tmp_path: Path) -> Path:
    path = tmp_path / "connect.toml"
    path.write_text(f'name = "connect"\n[bus]\nrun_id = "{RUN}"\n[[nodes]]\nid = "recorder"\nstage = "stages.recorder"\n'
                    f'params = {{ path = "{tmp_path / "run.mcap"}" }}\n')
    return path


def test_the_launcher_warns_once_when_its_hub_has_no_link_to_an_extra_connect_endpoint(tmp_path):
    dead = endpoint(free_port())  # nothing listens there
    run = Launch(str(_pipeline(tmp_path)), "--connect", dead, cwd=tmp_path)
    try:
        run.wait_line(r"^\[launch\] all 1 nodes alive; starting sources")
        run.wait_line(WARNING + re.escape(dead) + r": nothing listens there, or it refused the hub")
        assert run.proc.poll() is None, "the run must go on without the extra endpoint"
        run.proc.send_signal(signal.SIGINT)
        assert run.wait() == 0, run.text()[-4000:]
    finally:
        kill_all([run.proc])
    lines = run.text().splitlines()
    assert len([line for line in lines if re.search(WARNING, line)]) == 1, run.text()[-4000:]
    assert not [line for line in lines if "hub linked to --connect" in line]


def test_an_extra_connect_endpoint_that_is_there_gets_a_linked_line_and_no_warning(tmp_path):
    port = free_port()
    there = endpoint(port)
    with BusClient(mode="router", listen=[there]):
        run = Launch(str(_pipeline(tmp_path)), "--connect", there, cwd=tmp_path)
        try:
            run.wait_line(r"^\[launch\] hub linked to --connect " + re.escape(there) + "$")
            run.wait_line(r"^\[launch\] all 1 nodes alive; starting sources")
            run.proc.send_signal(signal.SIGINT)
            assert run.wait() == 0, run.text()[-4000:]
        finally:
            kill_all([run.proc])
    assert not re.search(WARNING, run.text(), re.MULTILINE), run.text()[-4000:]


def test_a_link_lost_and_back_mid_run_is_said_once_each(tmp_path):
    """Found by a new-user probe: a router stopped for 12 s mid-run and started again; the stages beyond it went
    without the run's messages and recovered, and the launcher said nothing of either."""
    port = free_port()
    there = endpoint(port)
    router = BusClient(mode="router", listen=[there])
    run = Launch(str(_pipeline(tmp_path)), "--connect", there, cwd=tmp_path)
    try:
        run.wait_line(r"^\[launch\] hub linked to --connect " + re.escape(there) + "$")
        router.close()
        run.wait_line(r"^\[launch\] warning: the hub lost its link to --connect " + re.escape(there) + ": ")
        router = BusClient(mode="router", listen=[there])
        run.wait_line(r"^\[launch\] hub linked to --connect " + re.escape(there) + r" again after \d+ s without it$", timeout_s=60)
        run.proc.send_signal(signal.SIGINT)
        assert run.wait() == 0, run.text()[-4000:]
    finally:
        kill_all([run.proc])
        router.close()
    lines = run.text().splitlines()
    assert len([line for line in lines if "lost its link" in line]) == 1, run.text()[-4000:]
    assert not re.search(WARNING, run.text(), re.MULTILINE), run.text()[-4000:]
