"""Hostile payloads for the decoder: seeded mutations of the golden payloads and targeted cases.

Used by ``tests/bus_schemas/test_hostile_payloads.py`` (which asserts that
decoding raises nothing but ``SchemaError``) and by ``bench/hostile.py
--section fuzz`` (which prints figures). Everything here is deterministic
for a given seed.
"""

from __future__ import annotations

import random
from pathlib import Path
from typing import Any, Callable, Iterator

import msgpack

GOLDEN = Path(__file__).resolve().parents[1] / "tests" / "bus_schemas" / "golden"  # of a source checkout
MiB = 1024 * 1024

# ints that break naive size arithmetic: zero, signs, the int64/uint64 edges, 2**31/2**32
EDGE_INTS = [0, 1, -1, 2, 255, 2**31 - 1, 2**31, 2**32, 2**53, 2**62, 2**63 - 1, 2**63, 2**64 - 1, -(2**31), -(2**63), 10**12]
DTYPE_STRINGS = ["float64", "float32", "int64", "int32", "uint8", "int8", "bool", "float16", "object", "O", "<f8", ">f8", "|u1", "float128", "V8", "S8", "U2", "", "x" * 300, "complex128", "datetime64[ns]"]


def golden_payloads() -> list[tuple[str, bytes]]:
    """(file name, bytes) of every golden payload, sorted by name."""
    return [(p.name, p.read_bytes()) for p in sorted(GOLDEN.glob("*.msgpack"))]


def _pack(obj: Any) -> bytes:
    return msgpack.packb(obj, use_bin_type=True)


def _unpack(data: bytes) -> Any:
    return msgpack.unpackb(data, raw=False, strict_map_key=False)


# --------------------------------------------------------------------------- random mutations


def _random_value(rng: random.Random, depth: int = 0) -> Any:
    r = rng.random()
    if r < 0.30:
        return rng.choice(EDGE_INTS)
    if r < 0.40:
        return rng.choice(DTYPE_STRINGS)
    if r < 0.50:
        return rng.randbytes(rng.choice([0, 1, 3, 8, 16]))
    if r < 0.60:
        return [rng.choice(EDGE_INTS) for _ in range(rng.randint(0, 3))]
    if r < 0.70:
        return rng.choice([None, True, False, 1.5, float("nan"), float("inf"), -0.0])
    if r < 0.80 and depth < 3:
        return [_random_value(rng, depth + 1) for _ in range(rng.randint(0, 3))]
    if r < 0.90 and depth < 3:
        return {rng.choice(["a", "header", "n", "x_m", "stamp_ns", "schema"]): _random_value(rng, depth + 1)}
    return rng.choice(EDGE_INTS)


def _nodes(obj: Any, out: list, parent: Any = None, key: Any = None) -> None:
    out.append((parent, key, obj))
    if isinstance(obj, dict):
        for k, v in obj.items():
            _nodes(v, out, obj, k)
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            _nodes(v, out, obj, i)


def _is_array_triple(obj: Any) -> bool:
    return isinstance(obj, list) and len(obj) == 3 and isinstance(obj[0], str) and isinstance(obj[1], list) and isinstance(obj[2], bytes)


def _mutate_structure(rng: random.Random, data: bytes) -> bytes:
    """Replace 1-3 values of the unpacked payload (array triples get shape/dtype/bytes mutations) and repack."""
    env = _unpack(data)
    nodes: list = []
    _nodes(env, nodes)
    for _ in range(rng.randint(1, 3)):
        parent, key, obj = rng.choice(nodes)
        if parent is None:
            continue
        if _is_array_triple(obj) and rng.random() < 0.7:
            c = rng.random()
            if c < 0.5:
                ndim = rng.choice([len(obj[1]), len(obj[1]), 0, 1, 2, 3])
                obj[1] = [rng.choice(EDGE_INTS + [0, 0, 1, 2, 3, 4]) for _ in range(ndim)]
                if rng.random() < 0.5:
                    obj[2] = b""
            elif c < 0.7:
                obj[0] = rng.choice(DTYPE_STRINGS)
            else:
                obj[2] = obj[2][: rng.randrange(len(obj[2]) + 1)] if rng.random() < 0.5 else obj[2] * 2 + b"\0"
        else:
            parent[key] = _random_value(rng)
    return _pack(env)


def _mutate_empty_object(rng: random.Random, data: bytes) -> bytes:
    """Empty every array of one object (valid: shape all zeros, no bytes), then give one array one edge-int dim.

    A zero dim next to a huge one passes a byte-length check (0 == 0) and used
    to reach numpy: the payload of issue 13.
    """
    env = _unpack(data)
    nodes: list = []
    _nodes(env, nodes)
    objects = [o for _p, _k, o in nodes if isinstance(o, dict) and any(_is_array_triple(v) for v in o.values())]
    if not objects:
        return _mutate_structure(rng, data)
    obj = rng.choice(objects)
    triples = [v for v in obj.values() if _is_array_triple(v)]
    for t in triples:
        t[1], t[2] = [0] * len(t[1]), b""
    t = rng.choice(triples)
    if t[1]:
        t[1][rng.randrange(len(t[1]))] = rng.choice(EDGE_INTS)
    return _pack(env)


def _mutate_bytes(rng: random.Random, data: bytes) -> bytes:
    """Flip, insert, delete or splice in msgpack type bytes with length fields."""
    d = bytearray(data)
    for _ in range(rng.randint(1, 4)):
        if not d:
            break
        p = rng.randrange(len(d))
        op = rng.random()
        if op < 0.5:
            d[p] = rng.randrange(256)
        elif op < 0.7:
            d[p:p] = rng.randbytes(rng.randint(1, 9))
        elif op < 0.85:
            del d[p : p + rng.randint(1, 8)]
        else:  # a 64-bit int, a 32-bit container header or a 32-bit bin length with random bytes
            d[p:p] = bytes([rng.choice([0xCF, 0xD3, 0xCE, 0xCD, 0xDC, 0xDD, 0xDE, 0xDF, 0xC5, 0xC6, 0xDB, 0xC7, 0xD4])]) + rng.randbytes(8)
    return bytes(d)


def mutated_payloads(n: int, seed: int = 0) -> Iterator[tuple[str, bytes]]:
    """``n`` mutated golden payloads: (``"<golden>:<how>"``, payload), how one of bytes, structure, empty_object."""
    rng = random.Random(seed)
    golden = golden_payloads()
    for _ in range(n):
        name, data = rng.choice(golden)
        r = rng.random()
        if r < 0.45:
            yield f"{name}:bytes", _mutate_bytes(rng, data)
        elif r < 0.85:
            yield f"{name}:structure", _mutate_structure(rng, data)
        else:
            yield f"{name}:empty_object", _mutate_empty_object(rng, data)


# --------------------------------------------------------------------------- targeted payloads


def _golden(schema: str) -> dict:
    path = next(p for p in sorted(GOLDEN.glob(f"{schema}.v*.msgpack"), reverse=True))
    return _unpack(path.read_bytes())


def _with(schema: str, edit: Callable[[dict], None]) -> bytes:
    env = _golden(schema)
    edit(env)
    return _pack(env)


def _profile_array(value: Any, *, empty_k: bool = True) -> bytes:
    """An AccelerationProfiles whose first profile's input_probs (dims k, m) is ``value``; the k arrays emptied."""

    def edit(env: dict) -> None:
        p = env["body"]["profiles"][0]
        if empty_k:
            p["chunk_mean_mps2"] = ["float32", [0], b""]
            p["chunk_sigma_mps2"] = ["float32", [0], b""]
        p["input_probs"] = value

    return _with("iamp.AccelerationProfiles", edit)


def _track_x(value: Any) -> bytes:
    def edit(env: dict) -> None:
        env["body"]["x_m"] = value

    return _with("iamp.TrackFrame", edit)


def _head(schema: str, version: int = 1) -> bytes:
    """The first bytes of a canonical envelope up to the body's value: map of 3, schema, v, "body"."""
    return b"\x83" + _pack("schema") + _pack(schema) + _pack("v") + _pack(version) + _pack("body")


def _nested(depth: int, opener: bytes, leaf: bytes = b"\xc0") -> bytes:
    return opener * depth + leaf


def targeted_payloads(big: bool = True) -> Iterator[tuple[str, bytes]]:
    """Named hostile payloads. ``big`` adds the 64 MB ones (a few hundred MB of test memory in all)."""
    # the payload of issue 13 and its relatives: a zero dim next to a huge one
    yield "shape [0, 2**63]", _profile_array(["float32", [0, 2**63], b""])
    yield "shape [2**63, 0]", _profile_array(["float32", [2**63, 0], b""])
    yield "shape [0, 2**64-1]", _profile_array(["float32", [0, 2**64 - 1], b""])
    yield "shape [0, 2**62]", _profile_array(["float32", [0, 2**62], b""])
    yield "shape [0, 2**31]", _profile_array(["float32", [0, 2**31], b""])
    yield "shape [0, 2**30]", _profile_array(["float32", [0, 2**30], b""])
    yield "shape [0, 2**40] k=10", _profile_array(["float32", [10, 2**40], b""], empty_k=False)
    # negative, non-int and wrongly sized shapes
    yield "shape [-1, 0]", _profile_array(["float32", [-1, 0], b""])
    yield "shape [-1, -4]", _profile_array(["float32", [-1, -4], b"\0" * 16])
    yield "shape [-(2**63)]", _track_x(["float64", [-(2**63)], b""])
    yield "shape [1.0, 2]", _profile_array(["float32", [1.0, 2], b"\0" * 8])
    yield "shape [True]", _track_x(["float64", [True], b"\0" * 8])
    yield "shape [None]", _track_x(["float64", [None], b""])
    yield "shape ['3']", _track_x(["float64", ["3"], b"\0" * 24])
    yield "shape 5", _track_x(["float64", 5, b"\0" * 40])
    yield "shape {}", _track_x(["float64", {}, b""])
    yield "shape of 3 dims", _track_x(["float64", [1, 1, 1], b"\0" * 8])
    yield "shape of 100000 dims", _track_x(["float64", [1] * 100_000, b"\0" * 8])
    # huge dims with no data
    yield "shape [2**40] empty", _track_x(["float64", [2**40], b""])
    yield "shape [2**31-1] empty", _track_x(["float64", [2**31 - 1], b""])
    yield "shape [2**63] empty", _track_x(["float64", [2**63], b""])
    # dtype strings
    for dt in ["object", "O", "<f8", ">f8", "float128", "V8", "S8", "U2", "", "complex128", "datetime64[ns]", "float32", "x" * 100_000]:
        yield f"dtype {dt[:20]!r}", _track_x([dt, [0], b""])
    for dt in [1, None, ["float64"], b"float64", 1.5, {"float64": 1}]:
        yield f"dtype {type(dt).__name__}", _track_x([dt, [0], b""])
    # byte lengths that do not match the shape
    yield "bytes short", _track_x(["float64", [4], b"\0" * 31])
    yield "bytes long", _track_x(["float64", [4], b"\0" * 33])
    yield "bytes none for [4]", _track_x(["float64", [4], b""])
    yield "bytes for [0]", _track_x(["float64", [0], b"\0" * 8])
    yield "bytes as str", _track_x(["float64", [1], "\0" * 8])
    yield "bytes as list", _track_x(["float64", [1], [0] * 8])
    yield "array of 2", _track_x(["float64", [1]])
    yield "array of 4", _track_x(["float64", [1], b"\0" * 8, 0])
    yield "array as map", _track_x({"dtype": "float64"})
    # envelope variants
    yield "empty", b""
    yield "nil", _pack(None)
    yield "reserved byte", b"\xc1"
    yield "truncated", _with("iamp.TrackFrame", lambda e: None)[:-5]
    yield "trailing data", _with("iamp.TrackFrame", lambda e: None) + b"\x00"
    yield "envelope list", _pack(["iamp.TrackFrame", 1, {}])
    yield "envelope 4 keys", _with("iamp.TrackFrame", lambda e: e.__setitem__("extra", 1))
    yield "envelope int keys", b"\x83\x01\x02\x03\x04\x05\x06"
    yield "envelope bytes keys", _pack({b"schema": "iamp.TrackFrame", b"v": 1, b"body": {}})
    yield "schema int", _with("iamp.TrackFrame", lambda e: e.__setitem__("schema", 5))
    yield "schema huge str", _with("iamp.TrackFrame", lambda e: e.__setitem__("schema", "iamp." + "x" * 500_000))
    yield "v bool", _with("iamp.TrackFrame", lambda e: e.__setitem__("v", True))
    yield "v 2**64-1", _with("iamp.TrackFrame", lambda e: e.__setitem__("v", 2**64 - 1))
    yield "v -1", _with("iamp.TrackFrame", lambda e: e.__setitem__("v", -1))
    yield "body list", _with("iamp.TrackFrame", lambda e: e.__setitem__("body", [1, 2]))
    yield "body first, over the default limit", _pack({"body": {"x": b"\0" * MiB}, "schema": "iamp.TrackFrame", "v": 1})
    yield "ext type", _with("iamp.TrackFrame", lambda e: e["body"].__setitem__("scene_id", msgpack.ExtType(5, b"\0" * 10)))
    yield "timestamp ext", _head("iamp.TrackFrame") + b"\xd6\xff\x00\x00\x00\x00"
    yield "invalid utf-8", _head("iamp.TrackFrame")[:-5] + b"\xa4\xff\xfe\xfd\xfc"
    yield "invalid utf-8 in body", _head("iamp.SceneInfo") + b"\x81\xa8scene_id\xa3\xff\xfe\xfd"
    # field values
    yield "stamp nan", _with("iamp.TrackFrame", lambda e: e["body"]["header"].__setitem__("stamp_ns", float("nan")))
    yield "float field str", _with("iamp.SceneInfo", lambda e: e["body"].__setitem__("frame_rate_hz", "10"))
    yield "enum 2**64-1", _with("iamp.CorridorSet", lambda e: e["body"]["vehicles"][0].__setitem__("status", 2**64 - 1))
    yield "enum -2**63", _with("iamp.CorridorSet", lambda e: e["body"]["vehicles"][0].__setitem__("agent_type", -(2**63)))
    yield "dict bytes keys", _with("iamp.NodeStats", lambda e: e["body"].__setitem__("counters", {b"received": 1}))
    yield "dict int values as str", _with("iamp.NodeStats", lambda e: e["body"].__setitem__("counters", {"received": "1"}))
    yield "50000 unknown fields", _with("iamp.TrackFrame", lambda e: e["body"].update({f"f{i}": i for i in range(50_000)}))
    yield "1000000 tuple entries", _with("iamp.IntentionBelief", lambda e: e["body"].__setitem__("vehicles", [{}] * 1_000_000))
    yield "tuple of nil", _with("iamp.CorridorSet", lambda e: e["body"].__setitem__("vehicles", [None] * 1000))
    # deep nesting (msgpack's own stack limit), in the body and as the whole payload
    yield "nested arrays 100000", _head("iamp.TrackFrame") + _nested(100_000, b"\x91")
    yield "nested maps 100000", _head("iamp.TrackFrame") + _nested(100_000, b"\x81\xa1a")
    yield "nested maps in a field", _head("iamp.TrackFrame") + b"\x81\xa6header" + _nested(50_000, b"\x81\xa6header")
    yield "nested maps whole", _nested(100_000, b"\x81\xa6schema")
    # size: at and above the limits
    yield "TrackFrame 1 MiB of empty maps", _head("iamp.TrackFrame") + b"\xdd" + (MiB // 2).to_bytes(4, "big") + b"\x80" * (MiB // 2)
    yield "unreadable head 2 MiB", _pack({"body": [{}] * (2 * MiB), "schema": "iamp.MotionGrid", "v": 1})
    if big:
        n = 64 * MiB - 64  # with the head, just under MAX_PAYLOAD_BYTES: held to the schema's own limit
        yield "TrackFrame 64 MiB of empty maps", _head("iamp.TrackFrame") + b"\xdd" + n.to_bytes(4, "big") + b"\x80" * n
        yield "MotionGrid 64 MiB of empty maps", _head("iamp.MotionGrid") + b"\xdd" + n.to_bytes(4, "big") + b"\x80" * n
        yield "64 MiB of zeros", b"\0" * n
        yield "64 MiB + 1 of zeros", b"\0" * (64 * MiB + 1)
        yield "64 MiB bin", _head("iamp.MotionGrid") + b"\xc6" + n.to_bytes(4, "big") + b"\0" * n
