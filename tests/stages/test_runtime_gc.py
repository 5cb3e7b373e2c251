"""The nodes' garbage-collector settings (``stages.runtime.node.gc_freeze``, ``IAMP_GC_FREEZE``) and the hop trace's GC clock."""

from __future__ import annotations

import gc
import json
import logging

from stages.runtime.node import GC_FREEZE_ENV, gc_freeze, gc_freeze_enabled
from stages.runtime.trace import TRACE_ENV, HopTrace

LOG = logging.getLogger("iamp.test_gc")


def test_gc_freeze_is_on_unless_switched_off_and_a_bad_value_is_logged_and_keeps_it_on(monkeypatch, caplog):
    monkeypatch.delenv(GC_FREEZE_ENV, raising=False)
    assert gc_freeze_enabled(LOG)
    for value, want in (("1", True), ("on", True), ("0", False), ("OFF", False), ("no", False), ("false", False)):
        monkeypatch.setenv(GC_FREEZE_ENV, value)
        assert gc_freeze_enabled(LOG) is want, value
    monkeypatch.setenv(GC_FREEZE_ENV, "maybe")
    with caplog.at_level(logging.WARNING, logger=LOG.name):
        assert gc_freeze_enabled(LOG)
    assert f"{GC_FREEZE_ENV}='maybe'" in caplog.text


def test_gc_freeze_moves_the_objects_out_of_the_collectors_reach():
    try:
        keep = [[i] for i in range(1000)]  # tracked containers
        n = gc_freeze()
        assert n == gc.get_freeze_count() >= len(keep)
        gc.collect()  # a full collection still runs, over what was made since, and leaves the frozen ones alone
        assert gc.get_freeze_count() == n
    finally:
        gc.unfreeze()
    assert gc.get_freeze_count() == 0


def test_the_hop_trace_is_off_without_its_variable_and_times_collections_when_on(tmp_path, monkeypatch):
    monkeypatch.delenv(TRACE_ENV, raising=False)
    assert HopTrace.from_env("n", "stages.x", {}) is None
    monkeypatch.setenv(TRACE_ENV, str(tmp_path / "t"))
    trace = HopTrace.from_env("n", "stages.x", {"a": "up/out"})
    assert trace is not None
    pauses = trace.gc.pause_ns
    gc.collect()
    assert trace.gc.pause_ns > pauses and trace.gc.by_gen[2][0] >= 1
    trace.write({"stamp": 1})
    trace.close()
    lines = [json.loads(x) for x in (tmp_path / "t" / "n.jsonl").read_text().splitlines()]
    assert lines[0]["inputs"] == {"a": "up/out"} and lines[1] == {"stamp": 1}
    assert lines[-1]["gc"]["2"][0] >= 1  # the last line: collections per generation, as JSON
    trace.write({"stamp": 2})  # after close: ignored, not an error
    assert len((tmp_path / "t" / "n.jsonl").read_text().splitlines()) == 3
