"""The one msgpack user: envelope, strict field codec and ndarray codec.

Wire form of every message: the msgpack map ``{"schema": str, "v": int,
"body": {field: value}}``. Packing uses ``use_bin_type=True``; unpacking uses
``raw=False``, string map keys only and buffer limits. A numpy array travels as
the list ``[dtype_str, shape_list, raw_bytes]`` (little-endian, C order). Enums
travel as their integer values.

Field types are read from the dataclass annotations, so the codec is written
once: ``int``, ``float``, ``str``, ``bool``, ``bytes``, IntEnum subclasses,
nested message parts (dataclasses), ``tuple[T, ...]``, ``dict[str, T]``,
``T | None`` and ``Annotated[np.ndarray, Array(dtype, dims)]``. Decoding checks
the schema name, the version, that every field is present and no field is
unknown, every type, array dtypes and shapes (named dims must agree across the
fields of one object), and the payload size. Anything wrong raises a
``SchemaError`` subclass with a message that names the schema and the field.

Versions. A format change bumps the class's ``VERSION`` and adds a golden
payload (``tests/bus_schemas/make_golden.py``); a payload of another version
raises ``WrongVersion``, unless the class lists that version in ``UPGRADES``:
a function that makes an old body a body of today's version, for changes
that lose nothing (``Header.source_wall_ns``: old payloads read with 0,
"unknown"), so that old recordings still replay. The upgraded body is then
decoded as strictly as any other.

Hostile payloads. Decoding never raises anything but a ``SchemaError`` and
never allocates more than the payload's size allows:

- every message class states ``MAX_BYTES`` (default ``DEFAULT_MAX_BYTES``,
  1 MiB), checked before msgpack unpacking; no class may state more than
  ``MAX_PAYLOAD_BYTES``. The schema is read from the envelope's first bytes
  (every encoder writes ``schema`` and ``v`` first), so ``decode_any`` and
  ``unpack_envelope`` hold a payload to its own schema's limit, and one whose
  schema cannot be read there to ``DEFAULT_MAX_BYTES``. Worst case, a payload
  of nothing but empty containers costs about 70 bytes of memory per payload
  byte while it is unpacked, which is why the limits are sized to the message;
- msgpack's ``max_*_len`` options bound every string, bin, array and map;
- an array's dtype, shape and byte length are checked before numpy sees them:
  a known dtype string, one non-negative int per schema dim, each at most
  ``MAX_ARRAY_DIM``, the extent (zero dims counted as 1) times the itemsize
  at most ``MAX_PAYLOAD_BYTES``, and the product of the shape times the
  itemsize equal to the byte length;
- any other error while building a field (numpy, a dataclass) becomes a
  ``MalformedPayload`` naming the schema and the field.

Values. A field (scalar or array) annotated with a ``Range`` is checked after
decoding: finite and within ``[lo, hi]``; NaN only where the range allows it
(``nan=True``: "unknown"), infinities never. What happens to a value outside
its range depends on where it is:

- ``clear=True`` (reported evidence a stage derives otherwise, e.g. a
  tracker's velocity or size): the value becomes NaN, "unknown";
- in an array over the rows of a column-wise message (the class states
  ``ROWS``, the dim name of its objects: ``TrackFrame.ROWS = "n"``): that
  object's row is dropped from every array of that dim;
- inside an element of a tuple field the message names in ``DROP_ELEMENTS``
  (``CorridorSet.vehicles``): that element is dropped;
- anywhere else (headers, stamps, grid geometry): the whole message is
  rejected with ``OutOfRange``.

Each drop or clear is recorded, when the caller passes ``report=[...]`` to
``decode``, as an ``OutOfRangeRecord`` (action, field path with indices
removed, how many values); the runtime turns them into issues
(``out_of_range_dropped`` / ``out_of_range_cleared``), so none is silent.

Speed. ``decode`` and ``encode`` first try the codec generated once per
message class (``_fastcodec``: every field's checks written out, the arrays
of a message range-checked together and handed out as writable slices of one
buffer per dtype and range). It accepts only what passes every check here
with nothing out of range and gives up on anything else; the reference codec
below then decides, so results, errors and records are this module's
(``FAST = False``: the reference codec only; the tests compare the two).
"""

from __future__ import annotations

import contextvars
import dataclasses
import enum
import re
import math
import types
import typing
from dataclasses import dataclass
from typing import Any, Annotated, ClassVar

import msgpack
import numpy as np

from . import _fastcodec
from ._plans import (  # noqa: F401  (re-exported: the schemas and tests import them from here)
    MAX_ARRAY_DIM, MAX_PAYLOAD_BYTES, MiB, _ALLOWED_DTYPES, _ARRAY, _BOOL, _BYTES, _DICT, _ENUM, _FLOAT, _INT, _OBJ, _PLAIN, _RANGE,
    _STR, _TUPLE, _UNION, Array, Range, _hints, _optional, _plan,
)
from .errors import MalformedPayload, OutOfRange, PayloadTooLarge, SchemaError, UnknownSchema, WrongSchema, WrongVersion

DEFAULT_MAX_BYTES = 1 * MiB  # Message.MAX_BYTES unless a class states its own
MAX_STR_BYTES = 1 * MiB  # longest msgpack string (ids, modes, paths, projections)
MAX_ARRAY_LEN = 1_000_000  # longest msgpack array (tuples of objects; ndarrays travel as bin)
MAX_MAP_LEN = 100_000  # largest msgpack map (objects, dict fields)
_HEAD_BYTES = 256  # where schema and version must be found to be read before unpacking


@dataclass(frozen=True, slots=True)
class OutOfRangeRecord:
    """One drop or clear made while decoding: ``action`` ``dropped`` or ``cleared``; ``count`` values (rows, elements)."""

    action: str
    field: str
    count: int
    detail: str


_REPORT: contextvars.ContextVar[list | None] = contextvars.ContextVar("iamp_out_of_range_report", default=None)
_INDEX = re.compile(r"\[[^\]]*\]")


def _record(action: str, path: str, count: int, detail: str) -> None:
    report = _REPORT.get()
    if report is not None:
        report.append(OutOfRangeRecord(action, _INDEX.sub("[]", path), int(count), detail))


class _DropElement(Exception):
    """An out-of-range value inside an element of a ``DROP_ELEMENTS`` tuple: that element goes."""

    def __init__(self, path: str, detail: str) -> None:
        super().__init__(detail)
        self.path = path
        self.detail = detail


REGISTRY: dict[str, type["Message"]] = {}

# Decode and encode first by the generated per-class codec (``_fastcodec``), which gives up on anything it does not
# accept as is; the reference codec below then decides. False: the reference codec only (tests compare the two).
FAST = True


class Message:
    """Base of all bus messages: ``encode()`` and ``decode()`` written once."""

    __slots__ = ()
    SCHEMA: ClassVar[str]
    VERSION: ClassVar[int]
    # Largest payload of this schema, bytes, checked before unpacking (see the module
    # docstring). Default 1 MiB; a class sized otherwise states its own with the sizes it
    # was sized from.
    MAX_BYTES: ClassVar[int] = DEFAULT_MAX_BYTES
    # tuple fields whose elements (objects) are dropped, not the message, when a value inside is out of range
    DROP_ELEMENTS: ClassVar[tuple[str, ...]] = ()
    # older versions this build still reads: version -> function making an old body a body of VERSION
    # (only for changes that lose nothing, e.g. a new header field whose default means "unknown")
    UPGRADES: ClassVar[dict[int, Any]] = {}

    def encode(self) -> bytes:
        body = _fastcodec.encode_body(self) if FAST else None  # None: the reference codec (below) decides
        if body is None:
            body = _encode_obj(self, type(self).SCHEMA)
        return msgpack.packb({"schema": self.SCHEMA, "v": self.VERSION, "body": body}, use_bin_type=True)

    @classmethod
    def decode(cls, data: bytes, *, where: str = "", report: list | None = None) -> "Message":
        """Decode ``data`` as exactly this class; ``where`` (a key) goes into errors.

        ``report``: a list that gets one ``OutOfRangeRecord`` per object
        dropped or value cleared for being out of range.
        """
        schema, version, body = unpack_envelope(data, where=where, expect=cls)
        if schema != cls.SCHEMA:
            raise WrongSchema(f"{_short(schema)} v{version}{_at(where)}: expected {cls.SCHEMA}")
        return cls._from_body(version, body, where, report)

    @classmethod
    def _from_body(cls, version: int, body: Any, where: str, report: list | None = None) -> "Message":
        if version != cls.VERSION:
            upgrade = cls.UPGRADES.get(version) if type(version) is int else None
            if upgrade is None:
                raise WrongVersion(f"{cls.SCHEMA} v{version}{_at(where)}: this build reads v{cls.VERSION}{_also(cls)}")
            body = upgrade(body)
        if FAST:
            msg = _fastcodec.decode(cls, body)  # None unless every check passed and nothing is out of range
            if msg is not None:
                return msg
        records: list = []
        token = _REPORT.set(records)
        try:
            msg = _decode_obj(cls, body, f"{cls.SCHEMA}", where)
        except SchemaError:
            raise
        except _DropElement as exc:  # a drop outside any droppable element: the message goes
            raise OutOfRange(f"{exc.path}{_at(where)}: {exc.detail}") from None
        except Exception as exc:  # a last net: field decoding converts its own errors already
            raise MalformedPayload(f"{cls.SCHEMA}{_at(where)}: {type(exc).__name__}: {_short(exc)}") from None
        finally:
            _REPORT.reset(token)
        if report is not None:
            report.extend(records)
        return msg


def register(cls: type[Message]) -> type[Message]:
    """Class decorator: add a message class to ``REGISTRY`` (after ``@dataclass``)."""
    if not (isinstance(getattr(cls, "SCHEMA", None), str) and isinstance(getattr(cls, "VERSION", None), int)):
        raise TypeError(f"{cls.__name__} needs SCHEMA: str and VERSION: int class constants")
    if not (type(cls.MAX_BYTES) is int and 0 < cls.MAX_BYTES <= MAX_PAYLOAD_BYTES):
        raise TypeError(f"{cls.__name__}.MAX_BYTES must be an int in 1..{MAX_PAYLOAD_BYTES}")
    if len(msgpack.packb({"schema": cls.SCHEMA, "v": cls.VERSION})) > _HEAD_BYTES:
        raise TypeError(f"{cls.__name__}.SCHEMA is too long to be read before unpacking")
    if cls.SCHEMA in REGISTRY and REGISTRY[cls.SCHEMA] is not cls:
        raise TypeError(f"schema {cls.SCHEMA} registered twice")
    REGISTRY[cls.SCHEMA] = cls
    return cls


def _also(cls: type["Message"]) -> str:
    return "".join(f" (and v{v})" for v in sorted(cls.UPGRADES))


def _at(where: str) -> str:
    return f" on {where}" if where else ""


def _short(value: Any, limit: int = 120) -> str:
    """``str(value)`` cut to ``limit`` characters: hostile values stay out of log lines whole."""
    text = str(value)
    return text if len(text) <= limit else f"{text[:limit]}... ({len(text)} chars)"


def _read_head(data: bytes | bytearray | memoryview) -> tuple[str, int] | None:
    """(schema, version) from the first ``_HEAD_BYTES`` of an envelope, without unpacking the body.

    None unless the payload starts as every encoder writes it: a 3-entry map
    whose first keys are ``schema`` (a str) and ``v`` (an int).
    """
    head = bytes(data[:_HEAD_BYTES])
    up = msgpack.Unpacker(
        raw=False, max_buffer_size=_HEAD_BYTES, max_str_len=_HEAD_BYTES, max_bin_len=0, max_array_len=0, max_map_len=0, max_ext_len=0
    )
    try:
        up.feed(head)
        return _schema_and_version(up)
    except Exception:  # out of data, wrong types, limits: just not readable here
        return None


def _schema_and_version(up: msgpack.Unpacker) -> tuple[str, int] | None:
    """(schema, version) read from an unpacker at an envelope's start, as every encoder writes it (a 3-entry map,
    ``schema`` a str then ``v`` an int); None where it starts otherwise (msgpack's errors propagate)."""
    if up.read_map_header() != 3 or up.unpack() != "schema":
        return None
    schema = up.unpack()
    if up.unpack() != "v":
        return None
    version = up.unpack()
    return (schema, version) if isinstance(schema, str) and type(version) is int else None


def unpack_envelope(data: bytes, *, where: str = "", expect: type["Message"] | None = None) -> tuple[str, int, dict]:
    """Return (schema, version, body) of a payload, checking only the envelope.

    The payload is held to ``expect.MAX_BYTES`` when given (a payload whose
    head names another schema raises ``WrongSchema`` before unpacking), else
    to the ``MAX_BYTES`` of the registered schema its head names, else to
    ``DEFAULT_MAX_BYTES``; all before msgpack unpacks anything.
    """
    what = f"{expect.SCHEMA} payload" if expect is not None else "payload"
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise MalformedPayload(f"{what}{_at(where)} is {type(data).__name__}, not bytes")
    if len(data) > MAX_PAYLOAD_BYTES:
        raise PayloadTooLarge(f"{what}{_at(where)} has {len(data)} bytes, limit {MAX_PAYLOAD_BYTES} (MAX_PAYLOAD_BYTES)")
    head = _read_head(data)
    if expect is not None:
        if head is not None and head[0] != expect.SCHEMA:
            raise WrongSchema(f"{_short(head[0])} v{head[1]}{_at(where)}: expected {expect.SCHEMA}")
        limit, limit_name = expect.MAX_BYTES, f"{expect.__name__}.MAX_BYTES"
    elif head is not None and head[0] in REGISTRY:
        cls = REGISTRY[head[0]]
        what = f"{cls.SCHEMA} payload"
        limit, limit_name = cls.MAX_BYTES, f"{cls.__name__}.MAX_BYTES"
    else:
        limit, limit_name = DEFAULT_MAX_BYTES, "DEFAULT_MAX_BYTES, schema not readable or not registered"
    if len(data) > limit:
        raise PayloadTooLarge(f"{what}{_at(where)} has {len(data)} bytes, limit {limit} ({limit_name})")
    try:
        env = msgpack.unpackb(
            bytes(data),
            raw=False,
            strict_map_key=True,
            max_bin_len=limit,
            max_str_len=min(limit, MAX_STR_BYTES),
            max_array_len=min(limit, MAX_ARRAY_LEN),
            max_map_len=min(limit, MAX_MAP_LEN),
            max_ext_len=0,
        )
    except Exception as exc:  # msgpack raises several unrelated types
        raise MalformedPayload(f"{what}{_at(where)} is not valid msgpack: {type(exc).__name__}: {_short(exc)}") from None
    if not isinstance(env, dict) or set(env) != {"schema", "v", "body"}:
        raise MalformedPayload(f"{what}{_at(where)} is not an envelope {{schema, v, body}}")
    schema, version, body = env["schema"], env["v"], env["body"]
    if not isinstance(schema, str) or type(version) is not int or not isinstance(body, dict):
        raise MalformedPayload(f"{what}{_at(where)} has an envelope with wrong types")
    return schema, version, body


def peek_schema(data: bytes) -> tuple[str, int]:
    """(schema, version) of a payload without decoding the body; raises SchemaError."""
    schema, version, _ = peek_header(data)
    return schema, version


def peek_header(data: bytes, *, where: str = "") -> tuple[str, int, dict | None]:
    """(schema, version, the body's ``header`` map or None) of a payload, without building the rest of its body.

    For the readers that need only the envelope and the header (the recorder, a sink's stamps, the replay's
    pacing): the body is walked with msgpack's ``skip`` (its structure checked to the last byte, nothing
    allocated) instead of unpacked, ~8x less CPU on the dense frames' larger messages. A payload laid out
    otherwise than every encoder writes it (``schema``, ``v``, ``body``, in that order, the body a map), or
    one the walk cannot read, goes through ``unpack_envelope``: the same result, or the same ``SchemaError``.
    What the walk does not check: the key types and the lengths of what it skips (a string of more than
    ``MAX_STR_BYTES`` inside the body, a map keyed by numbers): those payloads pass here and fail where they are
    decoded. The size limits are ``unpack_envelope``'s: a payload over its class's limit goes there and gets its error."""
    if isinstance(data, (bytes, bytearray, memoryview)) and len(data) <= MAX_PAYLOAD_BYTES:
        walked = _walk_header(data)
        if walked is not None:
            cls = REGISTRY.get(walked[0])
            if len(data) <= (cls.MAX_BYTES if cls is not None else DEFAULT_MAX_BYTES):  # (unpack_envelope's limit)
                return walked
    schema, version, body = unpack_envelope(data, where=where)
    header = body.get("header")
    return schema, version, header if isinstance(header, dict) else None


def _walk_header(data: bytes | bytearray | memoryview) -> tuple[str, int, dict | None] | None:
    """``peek_header``'s walk of a payload in the encoders' layout; None where it is not that or not readable."""
    up = msgpack.Unpacker(raw=False, strict_map_key=True, max_buffer_size=max(len(data), 1), max_str_len=MAX_STR_BYTES,
                          max_bin_len=len(data), max_array_len=MAX_ARRAY_LEN, max_map_len=MAX_MAP_LEN, max_ext_len=0)
    try:
        up.feed(data)
        head = _schema_and_version(up)
        if head is None or up.unpack() != "body":
            return None
        schema, version = head
        header = None
        for _ in range(up.read_map_header()):
            key = up.unpack()
            if not isinstance(key, str):
                return None
            if key == "header":  # (a key twice: the last, as a dict keeps it)
                header = up.unpack()
            else:
                up.skip()
        if up.tell() != len(data):  # (trailing bytes: unpack_envelope's error)
            return None
    except Exception:  # noqa: BLE001 - msgpack raises several unrelated types: unpack_envelope says what is wrong
        return None
    return schema, version, header if isinstance(header, dict) else None


def restamp_source_wall(data: bytes, wall_for: "typing.Callable[[int], int]", *, where: str = "") -> bytes:
    """``data`` with its header's known (not 0) ``source_wall_ns`` replaced by ``wall_for(recorded value)``.

    For a replay, whose recorded wall stamps are those of the recorded run:
    republished with the replay's own publish time, end-to-end latency
    measures the replayed run. A payload without a header or with an unknown
    (0) or missing wall stamp (an older version) comes back unchanged; the
    body is repacked as it is, not decoded (arrays stay bytes). Raises a
    ``SchemaError`` for a payload that is not an envelope.
    """
    schema, version, body = unpack_envelope(data, where=where)
    header = body.get("header") if isinstance(body, dict) else None
    if not (isinstance(header, dict) and type(header.get("source_wall_ns")) is int and header["source_wall_ns"] > 0):
        return data
    header["source_wall_ns"] = int(wall_for(header["source_wall_ns"]))
    return msgpack.packb({"schema": schema, "v": version, "body": body}, use_bin_type=True)


def decode_any(data: bytes, *, where: str = "", report: list | None = None) -> Message:
    """Decode a payload of any registered schema (``report`` as for ``Message.decode``)."""
    schema, version, body = unpack_envelope(data, where=where)
    cls = REGISTRY.get(schema)
    if cls is None:
        raise UnknownSchema(f"{_short(schema)} v{version}{_at(where)}: unknown schema")
    return cls._from_body(version, body, where, report)


# --------------------------------------------------------------------------- field codec

def _encode_obj(obj: Any, path: str) -> dict:
    out = {}
    dims: dict[str, int] = {}
    for name, tp in _hints(type(obj)).items():
        out[name] = _encode_value(getattr(obj, name), tp, f"{path}.{name}", dims)
    return out


def _encode_value(value: Any, tp: Any, path: str, dims: dict[str, int]) -> Any:
    kind, a, b, c = _plan(tp)
    if kind == _RANGE:  # ranges are checked on decode; encode what the annotation's type says
        return _encode_value(value, c, path, dims)
    if kind == _PLAIN:
        return _encode_value(value, a, path, dims)
    if kind == _ARRAY:
        arr = np.asarray(value)
        if arr.dtype != c:
            raise TypeError(f"{path}: array dtype {arr.dtype}, schema wants {a.dtype}")
        _check_dims(arr.shape, a, path, dims, TypeError)
        arr = np.ascontiguousarray(arr, dtype=b)
        return [a.dtype, list(arr.shape), arr.tobytes()]
    if kind == _UNION:
        if value is None:
            return None
        return _encode_value(value, b, path, dims)
    if kind == _TUPLE:
        return [_encode_value(v, a, f"{path}[{i}]", {}) for i, v in enumerate(value)]
    if kind == _DICT:
        return {str(k): _encode_value(v, a, f"{path}[{k}]", {}) for k, v in value.items()}
    if kind == _ENUM:
        return int(a(value).value)
    if kind == _OBJ:
        if not isinstance(value, a):
            raise TypeError(f"{path}: expected {a.__name__}, got {type(value).__name__}")
        return _encode_obj(value, path)
    if kind == _FLOAT:
        return float(value)
    if kind == _INT:
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
            raise TypeError(f"{path}: expected int, got {type(value).__name__}")
        return int(value)
    if kind == _BOOL:
        return bool(value)
    if kind == _STR:
        if not isinstance(value, str):
            raise TypeError(f"{path}: expected str, got {type(value).__name__}")
        return value
    if kind == _BYTES:
        return bytes(value)
    raise TypeError(f"{path}: unsupported field type {tp!r}")


def _check_dims(shape: tuple[int, ...], spec: Array, path: str, dims: dict[str, int], exc: type[Exception]) -> None:
    if len(shape) != len(spec.dims):
        raise exc(f"{path}: array has {len(shape)} dims, schema wants {len(spec.dims)}")
    for size, want in zip(shape, spec.dims):
        if isinstance(want, int) and size != want:
            raise exc(f"{path}: array shape {tuple(shape)}, schema wants {spec.dims}")
        if isinstance(want, str):
            have = dims.setdefault(want, size)
            if have != size:
                raise exc(f"{path}: dim '{want}' is {size} here but {have} in another field")


def _decode_obj(cls: type, body: Any, path: str, where: str) -> Any:
    if not isinstance(body, dict):
        raise MalformedPayload(f"{path}{_at(where)}: expected a map, got {type(body).__name__}")
    hints = _hints(cls)
    if body.keys() == hints.keys():  # the usual case, one set comparison
        missing = unknown = ()
    else:
        left_out = [n for n in hints if n not in body]
        optional = _optional(cls)
        missing = [n for n in left_out if n not in optional]
        unknown = [n for n in body if n not in hints]
        if left_out and not missing and not unknown:  # only fields with a default left out: they read as their default
            hints = {n: tp for n, tp in hints.items() if n in body}
    if missing:
        raise MalformedPayload(f"{path}{_at(where)}: missing field(s) {', '.join(missing)}")
    if unknown:
        names = ", ".join(_short(n, 40) for n in unknown[:5]) + (f" and {len(unknown) - 5} more" if len(unknown) > 5 else "")
        raise MalformedPayload(f"{path}{_at(where)}: unknown field(s) {names}")
    dims: dict[str, int] = {}
    kwargs = {}
    rows = getattr(cls, "ROWS", None)
    drop_fields = getattr(cls, "DROP_ELEMENTS", ())
    bad_rows: list[np.ndarray] = []
    for n, tp in hints.items():
        try:
            kwargs[n] = _decode_value(body[n], tp, f"{path}.{n}", where, dims, rows=(rows, bad_rows) if rows else None, drop=n in drop_fields)
        except (SchemaError, _DropElement):
            raise
        except Exception as exc:  # numpy, enum, int/float conversions: never anything but a SchemaError
            raise _bad(f"{path}.{n}", where, f"{type(exc).__name__}: {_short(exc)}") from None
    if bad_rows:
        mask = np.logical_or.reduce(bad_rows)
        keep = ~mask
        for n, tp in hints.items():
            spec = _array_spec(tp)
            if spec is not None and spec.dims and spec.dims[0] == rows:
                kwargs[n] = kwargs[n][keep]
        _record("dropped", path, int(mask.sum()), f"{int(mask.sum())} of {mask.size} objects with a value out of range")
    try:
        return cls(**kwargs)
    except Exception as exc:
        raise MalformedPayload(f"{path}{_at(where)}: {type(exc).__name__}: {_short(exc)}") from None


def _array_spec(tp: Any) -> "Array | None":
    if typing.get_origin(tp) is Annotated:
        return next((m for m in typing.get_args(tp)[1:] if isinstance(m, Array)), None)
    return None


def _check_range(value: Any, rng: Range, path: str, rows: tuple | None, spec: "Array | None") -> Any:
    """``value`` checked against ``rng``; cleared, marked for a row drop, or raised (see the module docstring)."""
    if isinstance(value, np.ndarray):
        if not rng.any_bad(value):
            return value
        bad = rng.bad(value)
        n_bad = int(bad.sum())
        first = value[bad].flat[0]
        what = f"{n_bad} value(s) outside {rng.describe()} (first: {_short(first, 40)})"
        if rng.clear and value.dtype.kind == "f":
            value = value.copy()
            value[bad] = np.nan
            _record("cleared", path, n_bad, what)
            return value
        if rows is not None and spec is not None and spec.dims and spec.dims[0] == rows[0] and value.ndim >= 1:
            rows[1].append(bad.reshape(bad.shape[0], -1).any(axis=1) if value.ndim > 1 else bad)
            return value
        raise _DropElement(path, what)
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return value
    if not rng.bad_scalar(value):
        return value
    what = f"{_short(value, 40)} is outside {rng.describe()}"
    if rng.clear and isinstance(value, float):
        _record("cleared", path, 1, what)
        return math.nan
    raise _DropElement(path, what)


def _bad(path: str, where: str, what: str) -> MalformedPayload:
    return MalformedPayload(f"{path}{_at(where)}: {what}")


def _decode_array(raw: Any, spec: "Array", dt: np.dtype, out_dt: np.dtype, path: str, where: str, dims: dict[str, int]) -> np.ndarray:
    """An ``[dtype, shape, bytes]`` field as a writable array of ``spec`` (little-endian ``dt`` on the wire)."""
    if not (isinstance(raw, list) and len(raw) == 3):
        raise _bad(path, where, "expected an array [dtype, shape, bytes]")
    dtype, shape, buf = raw
    if type(dtype) is not str or dtype != spec.dtype or dtype not in _ALLOWED_DTYPES:
        raise _bad(path, where, f"array dtype {_short(repr(dtype), 40)}, schema wants {spec.dtype}")
    if not isinstance(shape, list):
        raise _bad(path, where, "array shape is not a list of non-negative ints")
    if len(shape) != len(spec.dims):
        raise _bad(path, where, f"array has {len(shape)} dims, schema wants {len(spec.dims)}")
    if len(shape) == 1:  # most fields: the same checks, in the same order, without the generic loops
        n = shape[0]
        if type(n) is not int or not 0 <= n <= MAX_ARRAY_DIM:
            raise _bad(path, where, f"array shape {_short(shape, 60)} is not a list of ints in 0..{MAX_ARRAY_DIM}")
        if not isinstance(buf, bytes):
            raise _bad(path, where, "array data is not bytes")
        if max(n, 1) * dt.itemsize > MAX_PAYLOAD_BYTES:
            raise _bad(path, where, f"array shape {shape} {dtype} is larger than any payload ({MAX_PAYLOAD_BYTES} bytes)")
        if n * dt.itemsize != len(buf):
            raise _bad(path, where, f"array of shape {shape} {dtype} needs {n * dt.itemsize} bytes, got {len(buf)}")
        want = spec.dims[0]
        if want is not None and (dims.setdefault(want, n) != n if isinstance(want, str) else n != want):
            _check_dims((n,), spec, path + _at(where), dims, MalformedPayload)  # raises with the message
        return np.frombuffer(buf, dtype=dt).astype(out_dt, copy=True)
    if not all(type(d) is int and 0 <= d <= MAX_ARRAY_DIM for d in shape):
        raise _bad(path, where, f"array shape {_short(shape, 60)} is not a list of ints in 0..{MAX_ARRAY_DIM}")
    if not isinstance(buf, bytes):
        raise _bad(path, where, "array data is not bytes")
    if math.prod(max(d, 1) for d in shape) * dt.itemsize > MAX_PAYLOAD_BYTES:
        raise _bad(path, where, f"array shape {shape} {dtype} is larger than any payload ({MAX_PAYLOAD_BYTES} bytes)")
    if math.prod(shape) * dt.itemsize != len(buf):
        raise _bad(path, where, f"array of shape {shape} {dtype} needs {math.prod(shape) * dt.itemsize} bytes, got {len(buf)}")
    _check_dims(tuple(shape), spec, path + _at(where), dims, MalformedPayload)
    try:
        return np.frombuffer(buf, dtype=dt).reshape(shape).astype(out_dt, copy=True)
    except Exception as exc:  # unreachable after the checks above; kept so numpy can never escape
        raise _bad(path, where, f"array {dtype} {shape}: {type(exc).__name__}: {_short(exc)}") from None


def _decode_value(
    raw: Any, tp: Any, path: str, where: str, dims: dict[str, int], rows: tuple | None = None, drop: bool = False
) -> Any:
    kind, a, b, c = _plan(tp)
    if kind == _RANGE:
        inner = _plan(c)
        if inner[0] == _ARRAY:
            return _check_range(_decode_array(raw, inner[1], inner[2], inner[3], path, where, dims), a, path, rows, b)
        return _check_range(_decode_value(raw, c, path, where, dims, rows, drop), a, path, rows, b)
    if kind == _PLAIN:
        return _decode_value(raw, a, path, where, dims)
    if kind == _ARRAY:
        return _decode_array(raw, a, b, c, path, where, dims)
    if kind == _UNION:
        if raw is None:
            if a:
                return None
            raise _bad(path, where, "is nil")
        return _decode_value(raw, b, path, where, dims)
    if kind == _TUPLE:
        if not isinstance(raw, list):
            raise _bad(path, where, f"expected a list, got {type(raw).__name__}")
        if not drop:
            return tuple([_decode_value(v, a, f"{path}[{i}]", where, {}) for i, v in enumerate(raw)])
        out = []
        for i, v in enumerate(raw):
            try:
                out.append(_decode_value(v, a, f"{path}[{i}]", where, {}))
            except _DropElement as exc:
                _record("dropped", path, 1, f"{path}[{i}]: {_INDEX.sub('[]', exc.path)}: {exc.detail}")
        return tuple(out)
    if kind == _DICT:
        if not isinstance(raw, dict):
            raise _bad(path, where, f"expected a map, got {type(raw).__name__}")
        if not all(type(k) is str for k in raw):
            raise _bad(path, where, "map keys are not all str")
        return {k: _decode_value(v, a, f"{path}[{_short(k, 40)}]", where, {}) for k, v in raw.items()}
    if kind == _ENUM:
        if type(raw) is not int:
            raise _bad(path, where, f"expected an enum value (int), got {type(raw).__name__}")
        try:
            return a(raw)
        except ValueError:
            raise _bad(path, where, f"{raw} is not a {a.__name__}") from None
    if kind == _OBJ:
        return _decode_obj(a, raw, path, where)
    if kind == _FLOAT:
        if isinstance(raw, bool) or not isinstance(raw, (int, float)):
            raise _bad(path, where, f"expected float, got {type(raw).__name__}")
        return float(raw)
    if kind == _INT:
        if type(raw) is not int:
            raise _bad(path, where, f"expected int, got {type(raw).__name__}")
        return raw
    if kind == _BOOL:
        if type(raw) is not bool:
            raise _bad(path, where, f"expected bool, got {type(raw).__name__}")
        return raw
    if kind == _STR:
        if not isinstance(raw, str):
            raise _bad(path, where, f"expected str, got {type(raw).__name__}")
        return raw
    if kind == _BYTES:
        if not isinstance(raw, bytes):
            raise _bad(path, where, f"expected bytes, got {type(raw).__name__}")
        return raw
    raise _bad(path, where, f"unsupported field type {tp!r}")


def json_schema(cls: type) -> dict:
    """A JSON-Schema-like description of a message body (for MCAP schema records)."""

    def describe(tp: Any) -> dict:
        origin = typing.get_origin(tp)
        if origin is Annotated:
            base, *meta = typing.get_args(tp)
            spec = next((m for m in meta if isinstance(m, Array)), None)
            rng = next((m for m in meta if isinstance(m, Range)), None)
            if spec is None:
                out = describe(base)
                if rng is not None:
                    out.update({k: v for k, v in (("minimum", rng.lo), ("maximum", rng.hi)) if v is not None})
                    out["description"] = f"range {rng.describe()}" + (", out of range: cleared to NaN" if rng.clear else "")
                return out
            return {
                "type": "array",
                "description": f"ndarray as [dtype, shape, bytes]; dtype {spec.dtype}, dims {list(spec.dims)}"
                + (f"; values {rng.describe()}" + (", out of range: cleared to NaN" if rng.clear else "") if rng is not None else ""),
            }
        if origin in (typing.Union, types.UnionType):
            args = [a for a in typing.get_args(tp) if a is not type(None)]
            return {"anyOf": [describe(args[0]), {"type": "null"}]}
        if origin is tuple:
            return {"type": "array", "items": describe(typing.get_args(tp)[0])}
        if origin is dict:
            return {"type": "object", "additionalProperties": describe(typing.get_args(tp)[1])}
        if isinstance(tp, type) and issubclass(tp, enum.Enum):
            return {"type": "integer", "enum": [int(m.value) for m in tp], "description": ", ".join(f"{m.value}={m.name}" for m in tp)}
        if dataclasses.is_dataclass(tp):
            hints = _hints(tp)
            return {
                "type": "object",
                "title": tp.__name__,
                "properties": {n: describe(t) for n, t in hints.items()},
                "required": list(hints),
                "additionalProperties": False,
            }
        return {"type": {int: "integer", float: "number", str: "string", bool: "boolean", bytes: "string"}.get(tp, "string")}

    body = describe(cls)
    return {
        **body,
        "$comment": "msgpack envelope {schema, v, body}; this describes body",
        "title": cls.SCHEMA,
        "version": cls.VERSION,
    }
