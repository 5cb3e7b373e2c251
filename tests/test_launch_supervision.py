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


class _Clock:
    """time.monotonic and time.sleep of the launcher's wait, on a clock of the test's (sleeping advances it)."""

    def __init__(self) -> None:
        self.t = 0.0

    def monotonic(self) -> float:
        return self.t

    def sleep(self, dt: float) -> None:
        self.t += dt


class _Node:
    """A started node that never comes up: its process is there (``poll`` None), its CPU time is ``cpu``'s."""

    def __init__(self) -> None:
        self.proc = type("P", (), {"pid": 4242})()

    @staticmethod
    def poll():
        return None


def test_the_start_waits_for_a_node_that_works_and_says_for_whom_it_waits(capsys, monkeypatch):
    """At a first start on a machine the stages compile their kernels: a new user's cold start on 2 cores took
    markov_prediction past the fixed 90 s and the launcher gave up on it, having said nothing for 90 s. The start
    timeout now counts only while the awaited node does no work (its CPU time stands still), and a line every
    ``progress_s`` names the nodes awaited with their CPU time; a node that idles is still given up on, and one that
    works for ever at ``STARTUP_CAP_FACTOR`` times the timeout. On the test's own clock: nothing here depends on the
    machine's speed."""
    from stages.runtime.pipeline import load_pipeline

    hybrid = load_pipeline(Path(launch.PIPELINES_DIR) / "hybrid.toml")
    run = launch.Launcher(hybrid, "tcp/127.0.0.1:1", launch.build_parser().parse_args(["hybrid"]))
    run.children = {"markov_prediction": _Node()}
    clock = _Clock()
    monkeypatch.setattr(launch.time, "monotonic", clock.monotonic)
    monkeypatch.setattr(launch.time, "sleep", clock.sleep)
    work_s = [40.0]  # it uses CPU for the first 40 s (compiling), then idles (hangs before coming up)
    monkeypatch.setattr(launch, "_cpu_seconds", lambda pid: min(clock.t, work_s[0]))
    assert run.wait_alive(["markov_prediction"], timeout=5.0) == ["markov_prediction"]
    assert 40.0 <= clock.t <= 47.0  # not given up after 5 s while it worked; given up about 5 s after it stopped
    out = capsys.readouterr().out
    assert out.count("waiting for markov_prediction (") == 3 and "s of CPU) to come up" in out and "compiles the stages' kernels" in out
    # one that works for ever: given up at 10 times the timeout
    clock.t, work_s[0] = 0.0, float("inf")
    assert run.wait_alive(["markov_prediction"], timeout=5.0) == ["markov_prediction"]
    assert launch.STARTUP_CAP_FACTOR * 5.0 <= clock.t <= launch.STARTUP_CAP_FACTOR * 5.0 + 1.0
    # a node that exits ends the wait at once
    monkeypatch.setattr(_Node, "poll", staticmethod(lambda: 1))
    clock.t = 0.0
    assert run.wait_alive(["markov_prediction"], timeout=30.0) == ["markov_prediction"] and clock.t < 1.0


def test_the_end_of_an_overloaded_run_says_where_the_frames_went_and_what_to_do(capsys):
    """A new user's probe at 72 vehicles: "predicted: ... 48 (4.1 %)" and a pointer to ten long stop lines, whose
    counters covered a restarted node's last run only. The launcher keeps every node's NodeStats (a restart's counters
    added to the run before) and, where more than 5 % of the frames have no grid, names the drops, the slowest stages
    and, at real time, what to do."""
    import dataclasses

    from testkit.samples import node_stats

    stats = launch.RunStats()

    def put(node, pid, p50, **counters):
        msg = dataclasses.replace(node_stats(), node_id=node, pid=pid, proc_ms_p50=p50, proc_ms_p95=3 * p50,
                                  counters={"processed": 100, **counters})
        stats.on_stats(f"iamp/r/_stats/{node}", msg.encode())

    put("corridors", 1, 37.0)
    put("markov_prediction", 2, 87.0, queue_drops=300, join_drops=100)
    put("markov_prediction", 3, 80.0, queue_drops=247, join_drops=169)  # restarted: a new pid, counters from 0
    put("intentions", 4, 47.0, stale_drops=30)
    stats.on_stats("iamp/r/_stats/x", b"not a message")  # said once, counted, left out
    stats.on_stats("iamp/r/_stats/x", b"nor this")
    assert stats.counters("markov_prediction")["queue_drops"] == 547 and stats.runs["markov_prediction"] == 2
    line = stats.diagnosis(paced=False)
    assert line.startswith("where the frames went: input sets dropped: markov_prediction 547 queue, 269 join (over its 2 runs);"
                           " intentions 30 stale; slowest: markov_prediction 80 ms a set at p50 (240 at p95), intentions 47 ms")
    assert "--no-viewer" in line and "launch.py sharded" in line and "--speed max" in line
    assert "--speed max" not in stats.diagnosis(paced=True)  # paced: the advice for real time does not apply
    assert stats.unreadable == 2 and "(2 NodeStats messages unreadable)" in line
    assert capsys.readouterr().out.count("warning: a NodeStats message on iamp/r/_stats/x does not read") == 1
    per_topic = {"iamp/r/source/track_frame": 1000, "iamp/r/markov_prediction/motion_grid": 41}
    assert launch.lost_share(per_topic) == pytest.approx(0.959) and launch.lost_share({}) == 0.0


def test_the_nodes_run_the_launchers_own_code():
    """The nodes start as ``python -m stages.X`` in the caller's folder: a second checkout's ``launch.py`` ran its
    launcher with the nodes of the package the interpreter had installed (a new user's probe). The launcher puts the
    folder of its own ``stages`` first on the nodes' ``PYTHONPATH``."""
    import os

    root = str(Path(launch.__file__).resolve().parents[2])
    assert launch.code_path({}) == root
    assert launch.code_path({"PYTHONPATH": os.pathsep.join(["/x", root, "/y"])}) == os.pathsep.join([root, "/x", "/y"])


def test_a_launcher_pid_that_is_no_number_is_said_and_not_watched(caplog):
    import logging

    from stages.runtime.args import LAUNCHER_PID_ENV, watch_launcher

    log = logging.getLogger("iamp.test_watch")
    assert watch_launcher(log, {}) is None and not caplog.records
    with caplog.at_level(logging.WARNING, logger=log.name):
        assert watch_launcher(log, {LAUNCHER_PID_ENV: "abc"}) is None
    assert [r.getMessage() for r in caplog.records] == [f"{LAUNCHER_PID_ENV}='abc' is no process id: this node does not watch for its launcher"]
