"""The generated per-class codec (``bus_schemas._fastcodec``) against the reference codec of ``_wire``.

For every payload, decoding with the fast path (``_wire.FAST`` True) must
give what the reference codec alone gives: the same message (every value,
dtype and shape, NaN bits included) and the same out-of-range records, or
the same error class and message; encoding must give the same bytes or the
same error. Checked on the samples and goldens, on real messages of the
chain at 18 vehicles (embedded data, dense data builder), on the hostile
corpus (``testkit.mutations``), on real payloads edited out of range and on
messages that cannot be encoded.
"""

from __future__ import annotations

import contextlib
import dataclasses
import enum
import random
import struct

import msgpack
import numpy as np
import pytest

import bus_schemas as bs
from bus_schemas import _fastcodec, _wire
from testkit.chain_messages import dense_messages
from testkit.mutations import golden_payloads, mutated_payloads, targeted_payloads
from testkit.samples import SAMPLES

HOSTILE_N = 3000
HOSTILE_SEED = 16

pytestmark = pytest.mark.skipif(not _fastcodec.ENABLED, reason="the fast path runs on little-endian hosts only")


@contextlib.contextmanager
def _codec(fast: bool):
    old = _wire.FAST
    _wire.FAST = fast
    try:
        yield
    finally:
        _wire.FAST = old


def _canon(value):
    """A comparable form of a decoded value: types, dtypes, shapes and float bits included."""
    if isinstance(value, np.ndarray):
        return ("ndarray", value.dtype.str, value.shape, value.tobytes())
    if dataclasses.is_dataclass(value):
        return (type(value).__name__, tuple((f.name, _canon(getattr(value, f.name))) for f in dataclasses.fields(value)))
    if isinstance(value, enum.Enum):
        return (type(value).__name__, value.value)
    if isinstance(value, float):
        return ("float", struct.pack("<d", value))
    if isinstance(value, (tuple, list)):
        return (type(value).__name__, tuple(_canon(v) for v in value))
    if isinstance(value, dict):
        return ("dict", tuple((k, _canon(v)) for k, v in value.items()))
    return (type(value).__name__, value)


def _decoded(data: bytes, fast: bool, cls: type | None = None):
    """("decoded", message, records) or ("raised", error class, message)."""
    report: list = []
    with _codec(fast):
        try:
            if cls is None:
                msg = bs.decode(data, where="iamp/t/x/y", report=report)
            else:
                msg = cls.decode(data, where="iamp/t/x/y", report=report)
        except Exception as exc:  # noqa: BLE001 - compared below
            return ("raised", type(exc), str(exc))
    return ("decoded", _canon(msg), report)


def _encoded(msg, fast: bool):
    with _codec(fast):
        try:
            return ("encoded", msg.encode())
        except Exception as exc:  # noqa: BLE001 - compared below
            return ("raised", type(exc), str(exc))


def _assert_same_decoding(data: bytes, what: str) -> tuple:
    fast, ref = _decoded(data, True), _decoded(data, False)
    assert fast == ref, what
    return ref


@pytest.fixture(scope="module")
def real_messages(tmp_path_factory):
    """The chain's messages at about 18 vehicles per frame (embedded K729, dense data builder)."""
    msgs = dense_messages(18, 12, tmp_path_factory.mktemp("dense"))
    assert sum(len(m.relations) for m in msgs if isinstance(m, bs.RelationSet)) > 50  # real many-pair messages
    return msgs


def test_every_schema_has_a_fast_codec_and_it_is_taken():
    for schema, make in SAMPLES.items():
        msg = make()
        cls = type(msg)
        body = _fastcodec.encode_body(msg)
        assert body is not None, f"{schema}: no fast encoder (a field type _fastcodec does not handle?)"
        assert _fastcodec.decode(cls, msgpack.unpackb(msg.encode(), raw=False)["body"]) is not None, f"{schema}: no fast decoder"


@pytest.mark.parametrize("name, data", golden_payloads() + [(s, m().encode()) for s, m in sorted(SAMPLES.items())], ids=lambda v: v if isinstance(v, str) else "")
def test_samples_and_goldens_decode_and_encode_the_same_both_ways(name, data):
    outcome = _assert_same_decoding(data, name)
    if outcome[0] == "raised":  # a golden of a version this build no longer reads
        assert outcome[1] is bs.WrongVersion, name
        return
    assert outcome[2] == []
    with _codec(False):
        msg = bs.decode(data)
    assert _encoded(msg, True) == _encoded(msg, False)


def test_real_messages_decode_and_encode_the_same_both_ways(real_messages):
    schemas = set()
    for msg in real_messages:
        fast_bytes, ref_bytes = _encoded(msg, True), _encoded(msg, False)
        assert fast_bytes == ref_bytes and fast_bytes[0] == "encoded", msg.SCHEMA
        data = ref_bytes[1]
        body = msgpack.unpackb(data, raw=False)["body"]
        assert _fastcodec.decode(type(msg), body) is not None, f"{msg.SCHEMA}: the fast path gave up on a real message"
        outcome = _assert_same_decoding(data, msg.SCHEMA)
        assert outcome[0] == "decoded" and outcome[1] == _canon(msg)
        with _codec(True):
            assert bs.decode(data).encode() == data
        schemas.add(msg.SCHEMA)
    assert {"iamp.TrackFrame", "iamp.CorridorSet", "iamp.RelationSet", "iamp.IntentionBelief"} <= schemas


def test_hostile_payloads_fail_or_pass_the_same_both_ways():
    raised = 0
    for how, data in list(mutated_payloads(HOSTILE_N, seed=HOSTILE_SEED)) + list(targeted_payloads(big=False)):
        outcome = _assert_same_decoding(data, how)
        raised += outcome[0] == "raised"
        for cls in (bs.TrackFrame, bs.AccelerationProfiles, bs.MotionGrid):  # the class entry point too
            assert _decoded(data, True, cls) == _decoded(data, False, cls), (how, cls.__name__)
    assert raised > HOSTILE_N // 2  # the corpus does reach the checks


def _array_triples(obj, out):
    if isinstance(obj, dict):
        for k, v in obj.items():
            if isinstance(v, list) and len(v) == 3 and isinstance(v[0], str) and isinstance(v[2], bytes):
                out.append((obj, k))
            else:
                _array_triples(v, out)
    elif isinstance(obj, list):
        for v in obj:
            _array_triples(v, out)


def _scalars(obj, out):
    if isinstance(obj, dict):
        for k, v in obj.items():
            if type(v) in (int, float):
                out.append((obj, k))
            else:
                _scalars(v, out)
    elif isinstance(obj, list) and not (len(obj) == 3 and isinstance(obj[0], str)):
        for v in obj:
            _scalars(v, out)


BAD_FLOATS = [float("nan"), float("inf"), -float("inf"), 1e300, -1e300, 2e6, -2.0, 1.5, 0.0]
BAD_INTS = [-1, -2, 2, 2**62, 2**63 - 1, -(2**63), 0, 7]


def test_real_payloads_edited_out_of_range_drop_clear_or_refuse_the_same_both_ways(real_messages):
    """Array values and scalars set to NaN, infinities, huge, negative: the drops, clears and refusals of the reference."""
    rng = random.Random(16)
    payloads = [m.encode() for m in real_messages if isinstance(m, (bs.TrackFrame, bs.CorridorSet, bs.RelationSet, bs.IntentionBelief))]
    kinds = {"decoded": 0, "raised": 0, "records": 0}
    for k in range(600):
        env = msgpack.unpackb(rng.choice(payloads), raw=False)
        for _ in range(rng.randint(1, 3)):
            if rng.random() < 0.7:
                triples: list = []
                _array_triples(env["body"], triples)
                if not triples:
                    continue
                parent, key = rng.choice(triples)
                dtype, shape, buf = parent[key]
                values = np.frombuffer(buf, dtype=dtype).copy()
                if values.size:
                    bad = BAD_FLOATS if values.dtype.kind == "f" else BAD_INTS
                    with np.errstate(all="ignore"):
                        values[rng.randrange(values.size)] = rng.choice(bad) if values.dtype.kind == "f" else np.array(rng.choice(bad)).astype(values.dtype)
                    parent[key] = [dtype, shape, values.tobytes()]
            else:
                scalars: list = []
                _scalars(env["body"], scalars)
                parent, key = rng.choice(scalars)
                parent[key] = rng.choice(BAD_FLOATS) if type(parent[key]) is float else rng.choice(BAD_INTS)
        outcome = _assert_same_decoding(msgpack.packb(env, use_bin_type=True), f"edit {k}")
        kinds[outcome[0]] += 1
        kinds["records"] += outcome[0] == "decoded" and bool(outcome[2])
    assert min(kinds.values()) > 10, kinds  # accepted, refused and repaired (dropped or cleared) payloads all occur


def test_decoded_arrays_are_writable_aligned_native_and_independent(real_messages):
    data = max((m for m in real_messages if isinstance(m, bs.RelationSet)), key=lambda m: len(m.relations)).encode()
    with _codec(False):
        ref = bs.decode(data)
    with _codec(True):
        fast = bs.decode(data)
    arrays = [getattr(r, f.name) for r in fast.relations for f in dataclasses.fields(r) if isinstance(getattr(r, f.name), np.ndarray)]
    assert len(arrays) > 100
    for a in arrays:
        assert a.flags.writeable and a.flags.c_contiguous and a.flags.aligned and a.dtype.isnative
    for a in arrays[: len(arrays) // 2]:  # a consumer writing into its arrays touches no other array
        a[...] = 1
    assert _canon(fast.relations[-1]) == _canon(ref.relations[-1])


def test_messages_that_cannot_be_encoded_fail_the_same_both_ways():
    tf = SAMPLES["iamp.TrackFrame"]()
    rs = SAMPLES["iamp.RelationSet"]()
    r0 = rs.relations[0]
    cases = {
        "float32 where float64": dataclasses.replace(tf, x_m=tf.x_m.astype(np.float32)),
        "dims disagree": dataclasses.replace(tf, y_m=tf.y_m[:-1]),
        "2-D where 1-D": dataclasses.replace(tf, x_m=tf.x_m.reshape(1, -1)),
        "list for an array": dataclasses.replace(tf, x_m=list(tf.x_m)),
        "non-contiguous array": dataclasses.replace(tf, x_m=np.repeat(tf.x_m, 2)[::2]),
        "np.int64 for an int": dataclasses.replace(r0, track_id=np.int64(5)),
        "bool for an int": dataclasses.replace(r0, track_id=True),
        "str for an int": dataclasses.replace(r0, track_id="5"),
        "np.float32 for a float": dataclasses.replace(r0, leader_gap_m=np.float32(1.5)),
        "int for an enum": dataclasses.replace(r0, signal_phase=1),
        "not an enum value": dataclasses.replace(r0, signal_phase=99),
        "bytes for a str": dataclasses.replace(r0, influencing_rule=b"x"),
        "a list for a tuple": dataclasses.replace(rs, relations=list(rs.relations)),
        "a wrong element": dataclasses.replace(rs, relations=(r0, tf)),
        "a header of another class": dataclasses.replace(rs, header=tf),
    }
    for name, part in cases.items():
        msg = part if isinstance(part, bs.Message) else dataclasses.replace(rs, relations=(part,))
        assert _encoded(msg, True) == _encoded(msg, False), name
