"""Round trips, strict decoding and golden payloads of the bus schemas."""

from __future__ import annotations

import sys
from pathlib import Path

import dataclasses

import msgpack
import numpy as np
import pytest

import bus_schemas as bs
from bus_schemas import keys
from testkit.samples import SAMPLES, track_frame

GOLDEN = Path(__file__).resolve().parent / "golden"


def _repack(data: bytes, mutate) -> bytes:
    env = msgpack.unpackb(data, raw=False)
    mutate(env)
    return msgpack.packb(env, use_bin_type=True)


@pytest.mark.parametrize("schema", sorted(SAMPLES))
def test_round_trip_is_exact(schema):
    msg = SAMPLES[schema]()
    data = msg.encode()
    back = bs.decode(data)
    assert type(back) is type(msg)
    assert back.encode() == data


def test_every_registered_schema_has_a_sample_and_a_golden_file():
    assert set(bs.REGISTRY) == set(SAMPLES), "add a sample (testkit/samples.py) for every new schema"
    for schema, cls in bs.REGISTRY.items():
        assert (GOLDEN / f"{schema}.v{cls.VERSION}.msgpack").exists(), f"run tests/bus_schemas/make_golden.py for {schema}"


@pytest.mark.parametrize("path", sorted(GOLDEN.glob("*.msgpack")), ids=lambda p: p.name)
def test_golden_payloads_keep_decoding(path):
    data = path.read_bytes()
    schema, version = bs.peek_schema(data)
    cls = bs.REGISTRY[schema]
    if version != cls.VERSION and version not in cls.UPGRADES:
        with pytest.raises(bs.WrongVersion):
            bs.decode(data)
        return
    if version != cls.VERSION:
        # an older version this build still reads (old recordings replay): what it held, with today's new fields unknown
        msg = bs.decode(data)
        assert type(msg) is cls
        assert msg.encode() == _as_of_old_version(SAMPLES[schema](), version).encode()
        return
    msg = bs.decode(data)
    assert msg.encode() == data
    # the golden file equals what today's sample encodes to: the format did not drift
    assert SAMPLES[schema]().encode() == data


def _as_of_old_version(msg, version: int):
    """Today's sample with the fields that the upgrades from ``version`` fill in set as they fill them (wall stamp 0,
    e2e NaN, a scene's clock "unknown", predictions of a whole frame)."""
    if isinstance(msg, (bs.MotionGrid, bs.CorridorPredictions)):
        msg = dataclasses.replace(msg, shard="", missing_shards=())
        if version >= 2:  # v2 had the wall stamp
            return msg
    if isinstance(msg, bs.NodeStats):
        return dataclasses.replace(msg, e2e_ms_p50=float("nan"), e2e_ms_p95=float("nan"))
    if isinstance(msg, bs.SceneInfo):
        msg = dataclasses.replace(msg, clock="unknown")
        if version >= 3:  # v3 had the wall stamp
            return msg
    return dataclasses.replace(msg, header=dataclasses.replace(msg.header, source_wall_ns=0))


def test_header_wall_stamp_defaults_to_unknown_and_is_range_checked():
    h = bs.Header(run_id="r", frame_index=0, stamp_ns=1, producer="p")
    assert h.source_wall_ns == 0
    data = _repack(track_frame().encode(), lambda e: e["body"]["header"].__setitem__("source_wall_ns", -5))
    with pytest.raises(bs.MalformedPayload, match="source_wall_ns"):
        bs.TrackFrame.decode(data)
    # an old version (v1, no wall stamp) still decodes, with 0; a v1 body carrying an unknown field is still rejected
    v1 = _repack(track_frame().encode(), lambda e: (e.__setitem__("v", 1), e["body"]["header"].pop("source_wall_ns")))
    assert bs.TrackFrame.decode(v1).header.source_wall_ns == 0
    bad = _repack(v1, lambda e: e["body"]["header"].__setitem__("extra", 1))
    with pytest.raises(bs.MalformedPayload, match="extra"):
        bs.TrackFrame.decode(bad)


def test_a_field_with_a_default_may_be_left_out_and_reads_as_its_default():
    # README, "Predicting from a live tracker": source_wall_ns "0 if unknown", clock "unknown" if left out; a tracker
    # writing msgpack itself need not send them. A field without a default is still required, and a misspelt
    # optional one is still an unknown field
    frame = _repack(track_frame().encode(), lambda e: e["body"]["header"].pop("source_wall_ns"))
    assert bs.TrackFrame.decode(frame).header.source_wall_ns == 0
    scene = SAMPLES["iamp.SceneInfo"]()
    assert scene.clock != "unknown"
    decoded = bs.SceneInfo.decode(_repack(scene.encode(), lambda e: e["body"].pop("clock")))
    assert decoded.clock == "unknown" and decoded.map_sha256 == scene.map_sha256
    with pytest.raises(bs.MalformedPayload, match="unknown field"):
        bs.SceneInfo.decode(_repack(scene.encode(), lambda e: (e["body"].pop("clock"), e["body"].__setitem__("clok", "wall"))))
    with pytest.raises(bs.MalformedPayload, match="missing field"):
        bs.TrackFrame.decode(_repack(track_frame().encode(), lambda e: e["body"]["header"].pop("stamp_ns")))


def test_track_frame_arrays_keep_dtype_and_values():
    f = track_frame(5)
    g = bs.TrackFrame.decode(f.encode())
    assert len(g) == 5
    assert g.track_ids.dtype == np.int64 and g.agent_types.dtype == np.uint8
    np.testing.assert_array_equal(g.x_m, f.x_m)
    np.testing.assert_array_equal(g.yaw_rad, f.yaw_rad)
    assert g.header == f.header


def test_wrong_version_names_schema_key_and_version():
    data = _repack(track_frame().encode(), lambda e: e.__setitem__("v", 3))
    with pytest.raises(bs.WrongVersion) as ei:
        bs.TrackFrame.decode(data, where="iamp/x/source/track_frame")
    assert str(ei.value) == "iamp.TrackFrame v3 on iamp/x/source/track_frame: this build reads v2 (and v1)"


def test_unknown_schema_and_wrong_schema():
    data = _repack(track_frame().encode(), lambda e: e.__setitem__("schema", "iamp.Nope"))
    with pytest.raises(bs.UnknownSchema):
        bs.decode(data)
    with pytest.raises(bs.WrongSchema):
        bs.SceneInfo.decode(track_frame().encode())


@pytest.mark.parametrize(
    "mutate, needle",
    [
        (lambda e: e["body"].pop("x_m"), "missing field(s) x_m"),
        (lambda e: e["body"].__setitem__("extra", 1), "unknown field(s) extra"),
        (lambda e: e["body"]["header"].__setitem__("stamp_ns", "soon"), "expected int"),
        (lambda e: e["body"].__setitem__("scene_id", 5), "expected str"),
        (lambda e: e["body"].__setitem__("x_m", ["float32", [4], b"\0" * 16]), "dtype"),
        (lambda e: e["body"].__setitem__("x_m", ["float64", [4], b"\0" * 8]), "needs 32 bytes"),
        (lambda e: e["body"].__setitem__("x_m", ["float64", [3], b"\0" * 24]), "dim 'n'"),
        (lambda e: e["body"].__setitem__("x_m", ["object", [4], b"\0" * 32]), "dtype"),
        (lambda e: e["body"].__setitem__("x_m", [1, 2]), "expected an array"),
        (lambda e: e.pop("body"), "envelope"),
    ],
)
def test_malformed_bodies_raise_typed_errors(mutate, needle):
    data = _repack(track_frame().encode(), mutate)
    with pytest.raises(bs.MalformedPayload) as ei:
        bs.TrackFrame.decode(data)
    assert needle in str(ei.value)


@pytest.mark.parametrize("data", [b"", b"\xc1", b"garbage bytes", msgpack.packb([1, 2, 3]), msgpack.packb({1: 2})])
def test_garbage_is_malformed_not_a_crash(data):
    with pytest.raises(bs.MalformedPayload):
        bs.decode(data)


def test_oversized_payload_is_rejected_before_unpacking():
    with pytest.raises(bs.PayloadTooLarge):
        bs.decode(b"\0" * (bs.MAX_PAYLOAD_BYTES + 1))


def test_encode_refuses_wrong_dtype_or_mismatched_lengths():
    f = track_frame(3)
    bad = bs.TrackFrame(**{**{fl.name: getattr(f, fl.name) for fl in dataclasses.fields(f)}, "x_m": np.zeros(3, np.float32)})
    with pytest.raises(TypeError, match="dtype"):
        bad.encode()
    bad = bs.TrackFrame(**{**{fl.name: getattr(f, fl.name) for fl in dataclasses.fields(f)}, "y_m": np.zeros(2)})
    with pytest.raises(TypeError, match="dim 'n'"):
        bad.encode()


def test_enum_values_are_checked():
    data = bs.Header(run_id="r", frame_index=0, stamp_ns=0, producer="p")
    assert data.run_id == "r"
    assert bs.AgentType(6).name == "PEDESTRIAN" and not bs.AgentType.PEDESTRIAN.is_vehicle and bs.AgentType.CAR.is_vehicle


def test_keys_layout_and_checks():
    assert keys.data_key("demo", "corridors", "corridor_set") == "iamp/demo/corridors/corridor_set"
    assert keys.alive_key("demo", "corridors") == "iamp/demo/_alive/corridors"
    assert keys.stats_key("demo", "corridors") == "iamp/demo/_stats/corridors"
    assert keys.run_pattern("demo") == "iamp/demo/**"
    p = keys.parse_key("iamp/demo/_stats/relations")
    assert p.is_infrastructure and p.node_id == "relations"
    assert keys.replace_run("iamp/a/source/track_frame", "b") == "iamp/b/source/track_frame"
    for bad in ("Demo", "de mo", "", "a/b", "_x"):
        with pytest.raises(keys.KeyFormatError):
            keys.data_key(bad, "n", "o")
    with pytest.raises(keys.KeyFormatError):
        keys.data_key("demo", "Corridors", "o")
    with pytest.raises(keys.KeyFormatError):
        keys.parse_key("other/demo/x/y")


def test_json_schema_describes_every_field():
    js = bs.json_schema(bs.TrackFrame)
    assert js["title"] == "iamp.TrackFrame" and js["version"] == 2
    assert set(js["required"]) == {fl.name for fl in dataclasses.fields(bs.TrackFrame)}
