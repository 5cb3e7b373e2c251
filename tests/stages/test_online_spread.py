"""The online spread (``stages/markov_prediction/online_spread.py``): the extra spread of a start-speed band moves up on a
miss and down on a hit so that it settles where 1 − target of the checks miss, only at the prediction's step times,
only for vehicles starting faster than the minimum speed; and, in the stage on real frames, it widens the grids of
moving vehicles while their mean positions stay as they were."""

from __future__ import annotations

import numpy as np

import pytest

from stages.lib.datasets import DEFAULT_DATA_DIR
from stages.lib.markov import MarkovGridConfig, load_or_build_stencils
from stages.markov_prediction import RAW_GRIDS, MarkovPredictionConfig, MarkovPredictor
from stages.markov_prediction.online_spread import OnlineSpread
from stages.markov_prediction.rasterise import GridFrame, SparseGrid

TAU_NS = 400_000_000
STEPS = 0.4 * np.arange(1, 11)
FRAME = GridFrame(0.0, 0.0, 1.0, 100, 100)  # 100 x 100 cells of 1 m from (0, 0)


def _point_grid(x: float, y: float) -> SparseGrid:
    """All mass in the cell of (x, y) at every step."""
    cell = int(FRAME.flat_index(np.array([x]), np.array([y]))[0])
    keys = np.arange(STEPS.size, dtype=np.int64) * FRAME.n_cells + cell
    return SparseGrid(keys, np.ones(STEPS.size))


def _spread(**kw) -> OnlineSpread:
    return OnlineSpread(STEPS, **{"rate_mps": 0.1, "max_mps": 1.0, **kw})


def test_a_miss_widens_and_a_hit_narrows_by_the_rates():
    s = _spread()
    s.update(0, {}, FRAME, {1: _point_grid(10.5, 10.5), 2: _point_grid(50.5, 50.5)}, {1: 5.0, 2: 5.0})
    # at the first step time: vehicle 1 where predicted (hit), vehicle 2 20 m off (miss)
    made = s.update(TAU_NS, {1: (10.2, 10.7), 2: (70.0, 50.5)}, None, {}, {})
    assert made == 2
    fast = s.band(5.0)
    assert s.extra_mps[fast] == pytest.approx(0.1 * 0.9)  # the hit first, at 0: it stays 0 (never below); then the miss
    s.update(2 * TAU_NS, {1: (10.5, 10.5)}, None, {}, {})  # vehicle 1 where predicted at step 2: down by rate·(1 − target)
    assert s.extra_mps[fast] == pytest.approx(0.1 * 0.9 - 0.1 * 0.1)
    assert s.checks[fast] == 3 and s.misses[fast] == 1
    np.testing.assert_allclose(s.extra_sigmas(5.0), s.extra_mps[fast] * STEPS)


def test_nine_hits_and_a_miss_leave_it_where_it_was():
    s = _spread()
    s.extra_mps[:] = 0.5
    grids = {t: _point_grid(10.5 + t, 10.5) for t in range(10)}
    s.update(0, {}, FRAME, grids, {t: 5.0 for t in grids})
    s.update(TAU_NS, {t: (10.5 + t if t else 40.0, 10.5) for t in grids}, None, {}, {})  # track 0 missed, the 9 others hit
    assert s.extra_mps[s.band(5.0)] == pytest.approx(0.5, abs=1e-12)


def test_checks_only_at_step_times_and_once_per_step():
    s = _spread()
    s.update(0, {}, FRAME, {1: _point_grid(10.5, 10.5)}, {1: 5.0})
    assert s.update(TAU_NS // 2, {1: (90.0, 90.0)}, None, {}, {}) == 0  # between two step times
    assert s.update(TAU_NS, {1: (90.0, 90.0)}, None, {}, {}) == 1
    assert s.update(TAU_NS, {1: (90.0, 90.0)}, None, {}, {}) == 0  # the same step again
    assert s.update(2 * TAU_NS + 30_000_000, {1: (90.0, 90.0)}, None, {}, {}) == 1  # within the tolerance of step 2
    assert s.update(3 * TAU_NS, {}, None, {}, {}) == 0  # vehicle not in the frame: no check
    assert s.update(4 * TAU_NS, {1: (float("nan"), 1.0)}, None, {}, {}) == 0  # no finite position: no check


def test_bounded_and_never_below_zero():
    s = _spread(max_mps=0.2)
    for n in range(20):  # a miss at every check: up to the bound
        s.update(n * TAU_NS, {1: (90.0, 90.0)}, FRAME, {1: _point_grid(10.5, 10.5)}, {1: 5.0})
    assert s.extra_mps[s.band(5.0)] == pytest.approx(0.2)
    t = 20 * TAU_NS
    s = _spread()
    for n in range(20):  # a hit at every check: stays at 0
        s.update(t + n * TAU_NS, {1: (10.5, 10.5)}, FRAME, {1: _point_grid(10.5, 10.5)}, {1: 5.0})
    assert s.extra_mps.max() == 0.0 and s.checks.sum() > 0


def test_slow_vehicles_are_neither_checked_nor_widened():
    s = _spread(min_speed_mps=2.0)
    s.extra_mps[:] = 0.7
    assert not s.extra_sigmas(1.5).any() and not s.extra_sigmas(2.0).any() and s.extra_sigmas(2.5).all()
    s.update(0, {}, FRAME, {1: _point_grid(10.5, 10.5)}, {1: 1.5})
    assert s.update(TAU_NS, {1: (90.0, 90.0)}, None, {}, {}) == 0


def test_reset_and_time_going_back_forget_the_kept_grids_not_what_was_learnt():
    s = _spread()
    s.update(0, {}, FRAME, {1: _point_grid(10.5, 10.5)}, {1: 5.0})
    s.update(TAU_NS, {1: (90.0, 90.0)}, FRAME, {1: _point_grid(10.5, 10.5)}, {1: 5.0})
    learnt = s.extra_mps.copy()
    assert learnt.max() > 0
    s.reset()
    assert s.update(2 * TAU_NS, {1: (90.0, 90.0)}, None, {}, {}) == 0
    np.testing.assert_array_equal(s.extra_mps, learnt)
    s.update(10 * TAU_NS, {}, FRAME, {1: _point_grid(10.5, 10.5)}, {1: 5.0})
    assert s.update(5 * TAU_NS, {1: (90.0, 90.0)}, None, {}, {}) == 0  # back in time: kept grids dropped


def test_bad_parameters_are_refused():
    with pytest.raises(ValueError, match="spread_online_target"):
        MarkovPredictionConfig(spread_online=True, spread_online_target=1.0)
    with pytest.raises(ValueError, match="spread_online_rate_mps"):
        MarkovPredictionConfig(spread_online=True, spread_online_rate_mps=0.0)


def test_in_the_stage_it_widens_moving_vehicles_grids_and_leaves_their_means(frames, caplog):
    import logging

    caplog.set_level(logging.INFO, logger="test.markov")
    stencils = load_or_build_stencils(MarkovGridConfig())
    plain = MarkovPredictor(MarkovPredictionConfig(mode="corridor_cv", **RAW_GRIDS), stencils=stencils)
    # the 50 % region misses about every other check of a moving car: the extra spread moves from the first
    online = MarkovPredictor(MarkovPredictionConfig(mode="corridor_cv", spread_calibration="", spread_online=True, spread_online_rate_mps=0.5,
                                                    spread_online_target=0.5), stencils=stencils,
                             log=logging.getLogger("test.markov"))
    wider = 0
    for inputs in frames:
        a = plain.update(inputs).outputs
        b = online.update(inputs).outputs
        assert a["corridor_predictions"].encode() == b["corridor_predictions"].encode()  # the means do not move
        wider += int(online.online.extra_mps.max() > 0)
    assert online.online.checks.sum() > 0, "no check made: no moving vehicle seen at a step time"
    assert online.online.misses.sum() > 0 and wider > 0
    said = [r.getMessage() for r in caplog.records if r.name == "test.markov"]
    assert said and said[0].startswith("online spread: checks") and len(said) <= 1 + len(frames) // 300  # one line per 30 s
    # widened, a moving vehicle's grid holds more cells than without
    online.online.extra_mps[:] = 0.5
    last = max(frames, key=lambda f: sum(v.speed_mps > 3.0 for v in f["corridor_set"].vehicles if v.corridors))
    p_plain = plain.process(last["corridor_set"], last["relation_set"], last["scene"], last["track_frame"], intention_belief=last["intention_belief"])[0]
    p_online = online.process(last["corridor_set"], last["relation_set"], last["scene"], last["track_frame"], intention_belief=last["intention_belief"])[0]
    moving = [t for t, v in p_online.start_speeds_mps.items() if v > 2.0]
    assert moving, "no moving vehicle in any frame"
    for t in moving:
        assert p_online.vehicle_grids[t].keys.size > p_plain.vehicle_grids[t].keys.size
    np.testing.assert_array_equal(p_online.mean_xy_m, p_plain.mean_xy_m)


def test_iamp_calibrate_refuses_the_online_spread(tmp_path, capsys):
    """The table is fitted on the grids alone; the online spread widens them at run time, on top."""
    import argparse

    from stages.offline.calibrate import add_arguments, run_cli

    parser = argparse.ArgumentParser()
    add_arguments(parser)
    args = parser.parse_args(["--data", str(DEFAULT_DATA_DIR), "--out", str(tmp_path / "s.json"), "--set", "spread_online=true", "--no-progress"])
    assert run_cli(args) == 2
    assert "spread_online" in capsys.readouterr().err
    assert not (tmp_path / "s.json").exists()


def test_a_failing_online_spread_costs_the_frame_nothing(frames, monkeypatch):
    """The learning is beside the prediction: when it raises, the frame is published as without it, with one issue.
    The learning from a frame's grids is done after its outputs (``idle``, or first thing in the next update), so its
    issue goes out with the next frame's; idle's work gives the same outputs and issues as the next update's."""
    stencils = load_or_build_stencils(MarkovGridConfig())
    plain = MarkovPredictor(MarkovPredictionConfig(mode="corridor_cv", spread_online=True), stencils=stencils)
    broken = MarkovPredictor(MarkovPredictionConfig(mode="corridor_cv", spread_online=True), stencils=stencils)

    def boom(*args, **kwargs):
        raise RuntimeError("kept grid unreadable")

    monkeypatch.setattr(broken.online, "update", boom)
    monkeypatch.setattr(plain.online, "update", lambda *args, **kwargs: 0)  # learns nothing either, raises nothing
    idle = MarkovPredictor(MarkovPredictionConfig(mode="corridor_cv", spread_online=True), stencils=stencils)
    monkeypatch.setattr(idle.online, "update", boom)
    for n, inputs in enumerate(frames[:40]):
        a, b, c = plain.update(inputs), broken.update(inputs), idle.update(inputs)
        idle.idle()  # as the runtime does once a frame's outputs are out
        assert {k: m.encode() for k, m in a.outputs.items()} == {k: m.encode() for k, m in b.outputs.items()}
        assert {k: m.encode() for k, m in c.outputs.items()} == {k: m.encode() for k, m in b.outputs.items()}
        said = [] if n == 0 else ["online_spread_failed"]  # the frame before's learning
        assert [i.kind for i in b.issues if i.kind == "online_spread_failed"] == said
        assert [i.kind for i in c.issues if i.kind == "online_spread_failed"] == said
        assert "online_spread_failed" not in {i.kind for i in a.issues}
