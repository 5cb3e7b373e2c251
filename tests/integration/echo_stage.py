"""A test stage on the real runtime: echoes AccelerationProfiles (a message with a 2-D array field).

    python tests/integration/echo_stage.py --node-id echo --run-id R --input profiles=src/profiles --connect ENDPOINT

Every frame it echoes carries one issue (kind ``echoed``, agent 7), so the
runtime's issue episodes show in its log. Used by
``tests/integration/test_hostile_payloads_on_the_bus.py``,
``tests/integration/test_await_consumers.py`` and
``tests/integration/test_stale_inputs.py`` (``--set delay_s=S``: a stage
slower than its input), through ``start`` (the stage as a process, its
output to a log file) and ``profiles_payload`` (a good input).
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import msgpack

from bus_schemas import AccelerationProfiles
from stages.lib.base import ConfigMixin, Issue, StageResult
from stages.runtime import NodeContext, Port, StageSpec, run_stage
from testkit.helpers import REPO, default_log_dir, endpoint, python_env
from testkit.samples import SAMPLES


@dataclass(frozen=True)
class EchoConfig(ConfigMixin):
    delay_s: float = 0.0  # each frame takes this long (a stage slower than its input: tests/integration/test_stale_inputs.py)


class EchoCore:
    def __init__(self, delay_s: float = 0.0) -> None:
        self.delay_s = delay_s

    def update(self, inputs):
        if self.delay_s > 0:
            time.sleep(self.delay_s)
        msg = inputs["profiles"]
        return StageResult(outputs={"profiles": msg}, issues=[Issue("echoed", 7, f"frame {msg.header.frame_index}")])


def make_core(config: EchoConfig, ctx: NodeContext) -> EchoCore:
    return EchoCore(config.delay_s)


SPEC = StageSpec(
    stage="tests.integration.echo_stage",
    config_cls=EchoConfig,
    make_core=make_core,
    inputs={"profiles": Port(AccelerationProfiles)},
    outputs={"profiles": Port(AccelerationProfiles)},
)


def start(port: int, run_id: str, *extra: str) -> subprocess.Popen:
    """This stage as a process (node ``echo``, input ``profiles`` <- ``src/profiles``) connected to 127.0.0.1:``port``,
    with ``extra`` arguments; its output goes to a log file (``proc.log_path``)."""
    fd, log_path = tempfile.mkstemp(prefix="echo-", suffix=".log", dir=default_log_dir())
    args = ["--node-id", "echo", "--run-id", run_id, "--connect", endpoint(port), "--input", "profiles=src/profiles", *extra]
    with os.fdopen(fd, "wb") as log_file:
        proc = subprocess.Popen([sys.executable, str(Path(__file__)), *args], cwd=REPO, env=python_env(), stdout=log_file,
                                stderr=subprocess.STDOUT)
    proc.log_path = log_path  # type: ignore[attr-defined]
    return proc


def profiles_payload(frame_index: int) -> bytes:
    """A good AccelerationProfiles payload (the sample message) of ``frame_index``, stamped 1 s + 0.1 s per frame."""
    env = msgpack.unpackb(SAMPLES["iamp.AccelerationProfiles"]().encode(), raw=False)
    env["body"]["header"]["frame_index"] = frame_index
    env["body"]["header"]["stamp_ns"] = 1_000_000_000 + frame_index * 100_000_000
    return msgpack.packb(env, use_bin_type=True)


if __name__ == "__main__":
    raise SystemExit(run_stage(SPEC))
