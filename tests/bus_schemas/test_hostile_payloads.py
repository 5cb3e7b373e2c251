"""Hostile payloads (issue 13): decoding raises only typed ``SchemaError``s, whatever the bytes.

A seeded, bounded fuzz over the golden payloads (byte and structure
mutations) and targeted payloads: the ``[0, 2**63]`` shape that ended
markov_prediction, negative and huge dims, wrong dtype strings, byte lengths
that do not match, deep nesting, unreadable envelopes and 64 MB payloads.
"""

from __future__ import annotations

import sys
from pathlib import Path

import msgpack
import pytest

import bus_schemas as bs
from bus_schemas import _wire
from testkit.mutations import golden_payloads, mutated_payloads, targeted_payloads

FUZZ_N = 20_000
FUZZ_SEED = 13


def _decode_every_way(data: bytes) -> list[BaseException | None]:
    """Decode ``data`` through every entry point a stage or tool uses; return what each raised (None: decoded)."""
    out: list[BaseException | None] = []
    calls = [lambda: bs.decode(data, where="iamp/t/x/y"), lambda: bs.peek_schema(data), lambda: _wire.unpack_envelope(data),
             lambda: _wire.peek_header(data)]
    calls += [lambda cls=cls: cls.decode(data, where="iamp/t/x/y") for cls in (bs.TrackFrame, bs.AccelerationProfiles, bs.MotionGrid)]
    for call in calls:
        try:
            call()
            out.append(None)
        except Exception as exc:  # noqa: BLE001 - collected and asserted on below
            out.append(exc)
    return out


def _untyped(results: list[BaseException | None]) -> list[BaseException]:
    return [r for r in results if r is not None and not isinstance(r, bs.SchemaError)]


def test_fuzzed_golden_payloads_raise_only_schema_errors():
    bad = []
    typed = 0
    for how, data in mutated_payloads(FUZZ_N, seed=FUZZ_SEED):
        results = _decode_every_way(data)
        typed += sum(isinstance(r, bs.SchemaError) for r in results)
        bad += [(how, data[:80], repr(e)) for e in _untyped(results)]
    assert not bad, f"{len(bad)} untyped exceptions, first: {bad[:3]}"
    assert typed > FUZZ_N  # the mutations do reach the checks


@pytest.mark.parametrize("name, data", list(targeted_payloads(big=False)), ids=lambda v: v if isinstance(v, str) else "")
def test_targeted_payloads_raise_only_schema_errors(name, data):
    results = _decode_every_way(data)
    assert not _untyped(results), (name, _untyped(results))
    assert isinstance(results[0], bs.SchemaError), (name, "a hostile payload decoded")
    # messages stay short enough for one log line, whatever the payload held
    assert all(len(str(r)) < 1000 for r in results if r is not None), name


def test_the_issue_13_payload_names_schema_and_field():
    data = dict(targeted_payloads(big=False))["shape [0, 2**63]"]
    with pytest.raises(bs.MalformedPayload) as ei:
        bs.AccelerationProfiles.decode(data, where="iamp/demo/ar_inference/acceleration_profiles")
    msg = str(ei.value)
    assert "iamp.AccelerationProfiles.profiles[0].input_probs on iamp/demo/ar_inference/acceleration_profiles" in msg
    assert "9223372036854775808" in msg


def test_an_empty_array_next_to_a_modest_dim_still_decodes():
    """Zero-size arrays with a real other dim (K steps, no cells) are valid and must stay so."""
    env = msgpack.unpackb(dict(golden_payloads())["iamp.AccelerationProfiles.v2.msgpack"], raw=False)
    p = env["body"]["profiles"][0]
    p["chunk_mean_mps2"] = ["float32", [0], b""]
    p["chunk_sigma_mps2"] = ["float32", [0], b""]
    p["input_probs"] = ["float32", [0, 10], b""]
    msg = bs.decode(msgpack.packb(env, use_bin_type=True))
    assert msg.profiles[0].input_probs.shape == (0, 10)


def test_big_payloads_are_rejected_before_unpacking(monkeypatch):
    """64 MB payloads: held to the schema's MAX_BYTES (or the ceiling) before msgpack sees a byte."""

    def no_unpack(*a, **k):
        raise AssertionError("msgpack.unpackb was called on an oversized payload")

    big = [(n, d) for n, d in targeted_payloads(big=True) if "64 MiB" in n]
    assert len(big) == 5
    monkeypatch.setattr(_wire.msgpack, "unpackb", no_unpack)
    for name, data in big:
        with pytest.raises(bs.PayloadTooLarge) as ei:
            bs.decode(data, where="iamp/t/x/y")
        assert "limit" in str(ei.value), name
        for cls in (bs.TrackFrame, bs.MotionGrid):
            with pytest.raises(bs.SchemaError):
                cls.decode(data)
    tf = dict(big)["TrackFrame 64 MiB of empty maps"]
    with pytest.raises(bs.PayloadTooLarge, match=r"iamp.TrackFrame payload on k has 67108\d+ bytes, limit 1048576 \(TrackFrame.MAX_BYTES\)"):
        bs.decode(tf, where="k")


def test_every_schema_states_a_limit_that_fits_its_golden_payload_and_the_ceiling():
    for name, data in golden_payloads():
        schema, _v = bs.peek_schema(data)
        cls = bs.REGISTRY[schema]
        assert len(data) * 100 < cls.MAX_BYTES <= bs.MAX_PAYLOAD_BYTES, name
    for cls in bs.REGISTRY.values():
        assert "MAX_BYTES" in vars(cls), f"{cls.__name__} should state its MAX_BYTES"


def test_a_payload_one_byte_over_its_limit_is_too_large_and_at_the_limit_is_not():
    env = msgpack.unpackb(dict(golden_payloads())["iamp.Progress.v1.msgpack"], raw=False)
    base = len(msgpack.packb(env, use_bin_type=True))
    for extra, ok in ((bs.Progress.MAX_BYTES - base, True), (bs.Progress.MAX_BYTES - base + 1, False)):
        data = msgpack.packb(env, use_bin_type=True) + b"\0" * extra  # trailing bytes: size is checked first
        with pytest.raises(bs.PayloadTooLarge if not ok else bs.MalformedPayload):
            bs.decode(data)


def test_wrong_schema_is_known_from_the_head_without_unpacking(monkeypatch):
    data = dict(golden_payloads())["iamp.MotionGrid.v2.msgpack"]
    monkeypatch.setattr(_wire.msgpack, "unpackb", lambda *a, **k: (_ for _ in ()).throw(AssertionError("unpacked")))
    with pytest.raises(bs.WrongSchema, match="iamp.MotionGrid v2 on k: expected iamp.TrackFrame"):
        bs.TrackFrame.decode(data, where="k")


def test_register_refuses_a_limit_above_the_ceiling():
    class Huge(bs.Message):
        SCHEMA = "iamp.test.Huge"
        VERSION = 1
        MAX_BYTES = bs.MAX_PAYLOAD_BYTES + 1

    with pytest.raises(TypeError, match="MAX_BYTES"):
        bs.register(Huge)
    assert "iamp.test.Huge" not in bs.REGISTRY


def test_an_envelope_in_another_key_order_still_decodes_within_the_default_limit():
    """Every encoder writes schema, v, body; another order is valid msgpack and decodes, held to DEFAULT_MAX_BYTES."""
    data = dict(golden_payloads())["iamp.TrackFrame.v2.msgpack"]
    env = msgpack.unpackb(data, raw=False)
    reordered = msgpack.packb({"body": env["body"], "v": env["v"], "schema": env["schema"]}, use_bin_type=True)
    assert bs.decode(reordered).encode() == data
    assert bs.TrackFrame.decode(reordered).encode() == data
    padded = msgpack.packb({"body": env["body"], "v": env["v"], "schema": env["schema"], "pad": b"\0" * _wire.DEFAULT_MAX_BYTES}, use_bin_type=True)
    with pytest.raises(bs.PayloadTooLarge, match="DEFAULT_MAX_BYTES"):
        bs.decode(padded)


def _same(a, b) -> bool:
    """Equal, NaN equal to NaN (headers of fuzzed payloads hold NaNs)."""
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    return a == b or (a != a and b != b)


def test_peek_header_reads_what_unpack_envelope_reads_without_building_the_body(monkeypatch):
    """The recorder's and the sinks' header read: the same schema, version and header as the full unpack for every
    golden payload and every fuzzed one the full unpack accepts; where that raises, the same error, but for the
    documented leniency of the walk (what it skips is not decoded: bad UTF-8, lengths), which decoding still refuses."""
    for name, data in golden_payloads():
        schema, version, body = _wire.unpack_envelope(data)
        assert _same(_wire.peek_header(data), (schema, version, body.get("header"))), name
    lenient = checked = 0
    for how, data in mutated_payloads(FUZZ_N // 4, seed=FUZZ_SEED + 1):
        try:
            schema, version, body = _wire.unpack_envelope(data)
        except bs.SchemaError as exc:
            try:
                _wire.peek_header(data)
            except bs.SchemaError as again:
                assert (type(again), str(again)) == (type(exc), str(exc)), how
            else:
                lenient += 1
                assert "not valid msgpack" in str(exc), how  # only what msgpack itself refused in the skipped parts
                with pytest.raises(bs.SchemaError):
                    bs.decode(data)
            continue
        header = body.get("header")
        assert _same(_wire.peek_header(data), (schema, version, header if isinstance(header, dict) else None)), how
        checked += 1
    assert checked > FUZZ_N // 40 and lenient < FUZZ_N // 4 // 20  # the fuzz reaches both; the leniency stays rare
    # an envelope in the encoders' layout is walked, not unpacked
    data = dict(golden_payloads())["iamp.MotionGrid.v2.msgpack"]
    monkeypatch.setattr(_wire.msgpack, "unpackb", lambda *a, **k: (_ for _ in ()).throw(AssertionError("unpacked")))
    assert _wire.peek_header(data)[:2] == ("iamp.MotionGrid", 2)


def test_peek_header_falls_back_for_other_layouts_and_refuses_what_unpack_envelope_refuses():
    data = dict(golden_payloads())["iamp.TrackFrame.v2.msgpack"]
    env = msgpack.unpackb(data, raw=False)
    reordered = msgpack.packb({"body": env["body"], "v": env["v"], "schema": env["schema"]}, use_bin_type=True)
    assert _same(_wire.peek_header(reordered), ("iamp.TrackFrame", 2, env["body"]["header"]))
    for bad, error in ((data + b"\0", bs.MalformedPayload), (data[:-1], bs.MalformedPayload), (b"", bs.MalformedPayload),
                       (msgpack.packb({"schema": "iamp.TrackFrame", "v": 2, "body": []}, use_bin_type=True), bs.MalformedPayload),
                       (data + b"\0" * bs.TrackFrame.MAX_BYTES, bs.PayloadTooLarge)):
        with pytest.raises(error):
            _wire.peek_header(bad)
    no_header = msgpack.packb({"schema": "iamp.TrackFrame", "v": 2, "body": {"x": 1}}, use_bin_type=True)
    assert _wire.peek_header(no_header) == ("iamp.TrackFrame", 2, None)
