"""The launcher's restart budget (launch.RestartBudget) on an injected clock: no processes, no waiting."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from stages.runtime import launcher as launch
from stages.runtime.launcher import MAX_RESTARTS, RESTART_RESET_S, RestartBudget


class Clock:
    def __init__(self) -> None:
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


def crash_after(budget: RestartBudget, clock: Clock, ran_s: float) -> bool:
    """The node (re)starts, runs ``ran_s`` and dies: may it be restarted?"""
    budget.started()
    clock.t += ran_s
    return budget.take()


def test_a_node_that_keeps_dying_fast_uses_up_its_budget():
    clock = Clock()
    b = RestartBudget(limit=5, reset_after_s=60.0, clock=clock)
    assert [crash_after(b, clock, 1.0) for _ in range(6)] == [True] * 5 + [False]
    assert b.used == 5 and b.resets == 0


def test_a_node_that_ran_healthy_long_enough_gets_its_budget_back():
    clock = Clock()
    b = RestartBudget(limit=5, reset_after_s=60.0, clock=clock)
    for _ in range(4):
        assert crash_after(b, clock, 2.0)
    assert b.used == 4
    # it then runs 60 s without dying: the death after that starts a fresh budget
    assert crash_after(b, clock, 60.0)
    assert b.last_reset and b.resets == 1 and b.used == 1 and b.last_ran_s == pytest.approx(60.0)
    for _ in range(4):
        assert crash_after(b, clock, 59.9)  # just short of healthy: no reset
        assert not b.last_reset
    assert b.used == 5
    assert not crash_after(b, clock, 30.0)  # 5 fast deaths since the reset: stop
    # many deaths, each after a long healthy run, never stop the run
    b2 = RestartBudget(limit=2, reset_after_s=10.0, clock=clock)
    assert all(crash_after(b2, clock, 10.0) for _ in range(50))
    assert b2.used == 1 and b2.resets == 49


def test_reset_after_zero_never_gives_the_budget_back_and_limit_zero_never_restarts():
    clock = Clock()
    b = RestartBudget(limit=2, reset_after_s=0.0, clock=clock)
    assert [crash_after(b, clock, 1e6) for _ in range(3)] == [True, True, False]
    assert b.resets == 0
    assert not crash_after(RestartBudget(limit=0, reset_after_s=60.0, clock=clock), clock, 1e6)


def test_the_launcher_settings_and_their_defaults():
    args = launch.build_parser().parse_args([])
    assert args.max_restarts == MAX_RESTARTS == 5 and args.restart_reset_s == RESTART_RESET_S == 60.0
    args = launch.build_parser().parse_args(["--max-restarts", "2", "--restart-reset-s", "5"])
    assert (args.max_restarts, args.restart_reset_s) == (2, 5.0)
    assert launch.main(["--max-restarts", "-1", "--no-viewer"]) == 2
    assert "--restart-reset-s" in launch.build_parser().format_help()
