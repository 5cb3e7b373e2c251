"""``kernel_threads``: the hybrid chain's compiled call (``kernels.speed_priority_run``) and the vehicle grids' compiled
call (``frame_kernels.footprint_grids``) on several threads give the single-thread numbers bit for bit on real frames,
and the knob is validated."""

from __future__ import annotations

import pytest

from stages.lib.base import ConfigError
from stages.lib.markov import MarkovGridConfig, frame_kernels, kernels, load_or_build_stencils, psi_matrix
from stages.markov_prediction import MarkovPredictionConfig, MarkovPredictor
from stages.markov_prediction.chain import PriorityPropagator
from testkit.chain_messages import dense_frames_with_profiles


@pytest.mark.parametrize("bad", [0, -2])
def test_kernel_threads_is_validated(bad):
    with pytest.raises(ConfigError, match="kernel_threads = .*integer >= 1"):
        MarkovPredictionConfig.from_params({"kernel_threads": bad}, where="test")
    for wrong in (1.5, "2", True):
        with pytest.raises(ConfigError, match="kernel_threads"):
            MarkovPredictionConfig.from_params({"kernel_threads": wrong}, where="test")
    with pytest.raises(ValueError, match="kernel_threads"):
        PriorityPropagator(load_or_build_stencils(MarkovGridConfig()), psi_matrix(MarkovGridConfig().input_centres_mps2()),
                           kernel_threads=bad)
    assert MarkovPredictionConfig.from_params({"kernel_threads": 1}, where="test").kernel_threads == 1


@pytest.fixture(scope="module")
def frames(tmp_path_factory):
    """Frames of about 36 vehicles superimposed from the embedded K729 scenario (``build_dense``): batches of several
    blocks of pairs for the compiled chain."""
    return dense_frames_with_profiles(36, 25, tmp_path_factory.mktemp("dense"), lambda n: n >= 10 and n % 5 == 0)


@pytest.mark.skipif(not kernels.available(), reason="numba does not import")
def test_threaded_chain_equals_the_single_thread_chain_on_real_frames(frames, monkeypatch):
    stencils = load_or_build_stencils(MarkovGridConfig())
    calls = []
    real = kernels.speed_priority_run

    def spy(*args, threads=1, **kw):
        calls.append((args[0][0].shape[0], threads))
        return real(*args, threads=threads, **kw)

    monkeypatch.setattr(kernels, "speed_priority_run", spy)
    grid_calls = []
    real_grids = frame_kernels.footprint_grids

    def grids_spy(*args, threads=1, **kwargs):
        grid_calls.append((len(args[11]), threads))
        return real_grids(*args, threads=threads, **kwargs)

    monkeypatch.setattr(frame_kernels, "footprint_grids", grids_spy)
    runs = []
    real_runs = frame_kernels._footprint_grids
    monkeypatch.setattr(frame_kernels, "_footprint_grids", lambda *args: runs.append(len(args[13]) - 1) or real_runs(*args))  # args[13]: ptr
    outputs = {}
    for threads in (1, 2, 3):
        predictor = MarkovPredictor(MarkovPredictionConfig(mode="hybrid", kernel_threads=threads), stencils=stencils)
        outputs[threads] = []
        for item, profiles in frames:
            prediction, _issues = predictor.process(item.corridor_set, item.relation_set, item.scene, item.frame,
                                                    intention_belief=item.belief, acceleration_profiles=profiles)
            h = item.corridor_set.header
            outputs[threads].append((prediction.corridor_predictions(h, item.corridor_set.scene_id).encode(),
                                     prediction.motion_grid(h, item.corridor_set.scene_id).encode()))
    assert {t for _, t in calls} == {1, 2, 3}
    assert max(n for n, _ in calls) > 3 * kernels._LANES  # batches of several blocks: the threads share them out
    assert {t for _, t in grid_calls} == {1, 2, 3} and max(n for n, _ in grid_calls) > 3  # vehicles to share out
    assert len(runs) > len(grid_calls)  # some calls were split into runs on several threads
    assert outputs[2] == outputs[1] and outputs[3] == outputs[1]


@pytest.fixture(scope="module")
def every_frame(tmp_path_factory):
    """Every one of the first 25 frames of ``frames``' recording, in order (standing vehicles stay or start from one to
    the next)."""
    return dense_frames_with_profiles(36, 25, tmp_path_factory.mktemp("dense_all"), lambda n: True)


@pytest.mark.skipif(not kernels.available(), reason="numba does not import")
def test_pairs_that_surely_stay_skip_the_chain_and_the_bytes_stay(every_frame, monkeypatch):
    """A standing vehicle whose stay probability is 1 in float32 at every step (its start rate ~0: no leader, or a
    standing one) has its chain weighed by exactly 0 (``_mix_standstill``): the compiled call leaves it out (zeros,
    no mass-conservation warning), and the MotionGrid and CorridorPredictions bytes are those of running it."""
    stencils = load_or_build_stencils(MarkovGridConfig())
    real = kernels.speed_priority_run
    skipped = []

    def spy(*args, skip=None, **kw):
        out = real(*args, skip=skip, **kw)
        if skip is not None and skip.any():
            skipped.append(int(skip.sum()))
            assert not out[0][skip].any() and not out[1][skip].any() and not out[3][skip].any()  # no mass, none outside
            assert (out[-1][~skip] > 0.5).all()  # the others ran
        return out

    monkeypatch.setattr(kernels, "speed_priority_run", spy)

    def outputs():
        predictor = MarkovPredictor(MarkovPredictionConfig(mode="hybrid"), stencils=stencils)
        got = []
        for item, profiles in every_frame:
            prediction, issues = predictor.process(item.corridor_set, item.relation_set, item.scene, item.frame,
                                                   intention_belief=item.belief, acceleration_profiles=profiles)
            h = item.corridor_set.header
            got.append((prediction.corridor_predictions(h, item.corridor_set.scene_id).encode(),
                        prediction.motion_grid(h, item.corridor_set.scene_id).encode(), sorted(i.kind for i in issues)))
        return got

    with_skip = outputs()
    assert sum(skipped) >= 5  # the frames hold such vehicles
    real_run = PriorityPropagator.run
    monkeypatch.setattr(PriorityPropagator, "run", lambda self, *a, skip=None, **kw: real_run(self, *a, **kw))  # every pair run
    skipped.clear()
    assert outputs() == with_skip and not skipped


def test_one_worker_pool_whatever_the_thread_counts_asked():
    """A pool per thread count (``min(kernel_threads, blocks)`` changes from frame to frame) kept every size asked for,
    each with its threads; with ``kernel_threads = 1000`` a new user's probe saw the stage grow. One pool now, grown
    when more are asked, and never more threads than the machine's cores."""
    import os
    import threading

    from stages.lib.markov import kernels

    def run(n_threads):
        seen = set()
        kernels._on_threads(50, lambda i: seen.add(threading.current_thread().name), n_threads)
        return seen

    for n in (2, 3, 2, 64, 3):
        assert len(run(n)) <= min(n, os.cpu_count())
    assert list(kernels._pools) == [0]
    assert kernels._pools[0]._max_workers <= os.cpu_count() - 1 or os.cpu_count() == 1
