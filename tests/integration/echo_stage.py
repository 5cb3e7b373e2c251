"""A test stage on the real runtime: echoes AccelerationProfiles (a message with a 2-D array field).

    python tests/integration/echo_stage.py --node-id echo --run-id R --input profiles=src/profiles --connect ENDPOINT

Every frame it echoes carries one issue (kind ``echoed``, agent 7), so the
runtime's issue episodes show in its log. Used by
``tests/integration/test_hostile_payloads_on_the_bus.py``.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

from bus_schemas import AccelerationProfiles
from stages.lib.base import ConfigMixin, Issue, StageResult
from stages.runtime import NodeContext, Port, StageSpec, run_stage


@dataclass(frozen=True)
class EchoConfig(ConfigMixin):
    pass


class EchoCore:
    def update(self, inputs):
        msg = inputs["profiles"]
        return StageResult(outputs={"profiles": msg}, issues=[Issue("echoed", 7, f"frame {msg.header.frame_index}")])


def make_core(config: EchoConfig, ctx: NodeContext) -> EchoCore:
    return EchoCore()


SPEC = StageSpec(
    stage="tests.integration.echo_stage",
    config_cls=EchoConfig,
    make_core=make_core,
    inputs={"profiles": Port(AccelerationProfiles)},
    outputs={"profiles": Port(AccelerationProfiles)},
)

if __name__ == "__main__":
    raise SystemExit(run_stage(SPEC))
