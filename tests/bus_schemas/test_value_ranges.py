"""Issue 13 item 2: every schema states its value ranges; out-of-range values never reach a core.

The values the issue found silently accepted (an infinite speed, a width of
-5, a stamp of 2**64-1, beliefs of 1e308) and their neighbours, edited into
real encoded payloads, each decoded the way a stage decodes them.
"""

from __future__ import annotations

import math

import msgpack
import numpy as np
import pytest

import bus_schemas as bs
from bus_schemas._wire import OutOfRangeRecord, Range
from bus_schemas.errors import OutOfRange
from testkit.samples import SAMPLES


def _env(schema: str) -> dict:
    return msgpack.unpackb(SAMPLES[schema]().encode(), raw=False)


def _pack(env: dict) -> bytes:
    return msgpack.packb(env, use_bin_type=True)


def _f64(values) -> list:
    a = np.asarray(values, dtype="<f8")
    return ["float64", [a.size], a.tobytes()]


def test_every_sample_decodes_with_nothing_dropped():
    for name, make in SAMPLES.items():
        report: list = []
        bs.decode(make().encode(), report=report)
        assert report == [], name


def test_a_stamp_beyond_int64_or_negative_rejects_the_message():
    for stamp in (2**64 - 1, 2**63, -1):
        env = _env("iamp.TrackFrame")
        env["body"]["header"]["stamp_ns"] = stamp
        with pytest.raises(OutOfRange, match="header.stamp_ns"):
            bs.TrackFrame.decode(_pack(env))


def test_an_infinite_speed_and_a_negative_width_are_cleared_to_unknown_not_passed_on():
    env = _env("iamp.TrackFrame")
    env["body"]["vx_mps"] = _f64([3.0, math.inf, 1e308, -2.0])
    env["body"]["width_m"] = _f64([1.9, -5.0, 0.0, 1.8])
    report: list = []
    msg = bs.TrackFrame.decode(_pack(env), report=report)
    assert len(msg) == 4  # evidence cleared, objects kept: positions are fine
    assert msg.vx_mps[0] == 3.0 and np.isnan(msg.vx_mps[1:3]).all() and msg.vx_mps[3] == -2.0
    assert msg.width_m[0] == 1.9 and np.isnan(msg.width_m[1:3]).all()
    assert {(r.action, r.field, r.count) for r in report} == {("cleared", "iamp.TrackFrame.vx_mps", 2), ("cleared", "iamp.TrackFrame.width_m", 2)}


def test_an_object_with_an_infinite_position_is_dropped_from_every_column():
    env = _env("iamp.TrackFrame")
    env["body"]["x_m"] = _f64([10.0, math.inf, 12.0, 1e7])
    report: list = []
    msg = bs.TrackFrame.decode(_pack(env), report=report)
    assert msg.track_ids.tolist() == [100, 102]
    assert msg.x_m.tolist() == [10.0, 12.0] and msg.y_m.shape == (2,) and msg.agent_types.shape == (2,)
    assert report == [OutOfRangeRecord("dropped", "iamp.TrackFrame", 2, "2 of 4 objects with a value out of range")]
    nan_pos = _env("iamp.TrackFrame")
    nan_pos["body"]["y_m"] = _f64([np.nan, -5.5, -6.0, -6.5])
    assert len(bs.TrackFrame.decode(_pack(nan_pos))) == 4  # NaN is "unknown": the corridors stage marks it BAD_STATE


def test_beliefs_of_1e308_drop_that_vehicle_only():
    env = _env("iamp.IntentionBelief")
    vehicles = env["body"]["vehicles"]
    assert len(vehicles) >= 1
    bad = dict(vehicles[0], p_stop=1e308)
    env["body"]["vehicles"] = [bad, *vehicles]
    report: list = []
    msg = bs.IntentionBelief.decode(_pack(env), report=report)
    assert len(msg.vehicles) == len(vehicles)
    assert len(report) == 1 and report[0].action == "dropped" and report[0].field == "iamp.IntentionBelief.vehicles"
    assert "p_stop" in report[0].detail and "1e+308" in report[0].detail
    for field, value in (("probability", -0.5), ("probability", math.nan), ("s_std_m", -1.0)):
        env2 = _env("iamp.IntentionBelief")
        env2["body"]["vehicles"][0]["corridors"][0][field] = value
        report = []
        msg = bs.IntentionBelief.decode(_pack(env2), report=report)
        assert len(msg.vehicles) == len(env2["body"]["vehicles"]) - 1, field
        assert f"corridors[].{field}" in report[0].detail


def test_a_vehicle_with_an_infinite_corridor_point_is_dropped_from_the_corridor_set():
    env = _env("iamp.CorridorSet")
    n = len(env["body"]["vehicles"])
    corr = next(v for v in env["body"]["vehicles"] if v["corridors"])["corridors"][0]
    x = np.frombuffer(corr["x_m"][2], "<f8").copy()
    x[0] = math.inf
    corr["x_m"] = ["float64", [x.size], x.tobytes()]
    report: list = []
    msg = bs.CorridorSet.decode(_pack(env), report=report)
    assert len(msg.vehicles) == n - 1 and report[0].field == "iamp.CorridorSet.vehicles"


def test_grid_geometry_out_of_range_rejects_the_grid():
    for field, value in (("cell_m", -1.0), ("cell_m", math.inf), ("n_rows", -3), ("origin_x_m", math.nan)):
        env = _env("iamp.MotionGrid")
        env["body"][field] = value
        with pytest.raises(OutOfRange, match=field):
            bs.MotionGrid.decode(_pack(env))


def test_range_semantics():
    r = Range(0.0, 1.0)
    assert r.bad(np.array([0.0, 1.0, 0.5])).tolist() == [False, False, False]
    assert r.bad(np.array([-0.1, 1.1, np.nan, np.inf])).tolist() == [True, True, True, True]
    assert Range(nan=True).bad(np.array([np.nan, np.inf, -np.inf, 1e300])).tolist() == [False, True, True, False]
    assert Range(0, 10).bad_scalar(2**80) and not Range(0, 10).bad_scalar(3)
    assert bs.json_schema(bs.TrackFrame)["properties"]["header"]["properties"]["stamp_ns"].get("minimum") == 0


def test_any_bad_agrees_with_the_mask_for_every_dtype_and_range() -> None:
    """``Range.any_bad`` (two reductions, the decoder's fast check) == ``Range.bad(v).any()``."""
    rng = np.random.default_rng(7)
    ranges = [Range(), Range(lo=0.0), Range(hi=5.0), Range(lo=-1.0, hi=1.0), Range(lo=0.0, nan=True), Range(hi=3.0, nan=True, clear=True)]
    specials = [np.nan, np.inf, -np.inf, 0.0, -1.0, 1.0, 5.0, 5.5, -1.5]
    checked = 0
    for r in ranges:
        for dtype in ("float64", "float32", "int64", "int8", "uint8", "bool"):
            for size in (0, 1, 3, 17):
                for _ in range(20):
                    if dtype.startswith("float"):
                        v = rng.choice(specials, size=size).astype(dtype) if rng.random() < 0.5 else rng.uniform(-2, 6, size).astype(dtype)
                    elif dtype == "bool":
                        v = rng.random(size) < 0.5
                    else:
                        v = rng.integers(-3 if dtype in ("int64", "int8") else 0, 7, size).astype(dtype)
                    assert r.any_bad(v) == bool(r.bad(v).any()), (r, dtype, v)
                    checked += 1
    assert checked == len(ranges) * 6 * 4 * 20
