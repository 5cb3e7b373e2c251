"""Field annotations and field plans, shared by the reference codec (``_wire``) and the generated one (``_fastcodec``).

``Array`` and ``Range`` annotate message fields (see ``_wire``'s docstring
for what they mean on the wire and at decoding); ``_plan(tp)`` is what a
codec needs to know about one field type, worked out once per type;
``_hints(cls)`` a dataclass's field types in field order. The array limits
both codecs check live here too.
"""

from __future__ import annotations

import dataclasses
import enum
import math
import types
import typing
from dataclasses import dataclass
from typing import Any, Annotated

import numpy as np

MiB = 1024 * 1024
MAX_PAYLOAD_BYTES = 64 * MiB  # ceiling: checked first, and no class may state a larger MAX_BYTES
MAX_ARRAY_DIM = 2**31 - 1  # largest size of one array dim
_ALLOWED_DTYPES = frozenset(
    ["bool", "uint8", "int8", "uint16", "int16", "uint32", "int32", "uint64", "int64", "float16", "float32", "float64"]
)


@dataclass(frozen=True, slots=True)
class Array:
    """Annotation for an ndarray field: exact dtype and named or fixed dims.

    ``dims`` entries are ``int`` (fixed size), ``str`` (a named size that must
    agree with every other use of that name in the same object) or ``None``
    (free).
    """

    dtype: str
    dims: tuple[int | str | None, ...]


@dataclass(frozen=True, slots=True)
class Range:
    """Annotation: the values a scalar or array field may take (see the module docstring).

    Finite and within ``[lo, hi]`` (``None``: unbounded on that side, still
    finite); ``nan``: NaN allowed (unknown); ``clear``: a value out of range
    becomes NaN (recorded) instead of dropping its object or rejecting the
    message. ``unit`` is documentation only.
    """

    lo: float | None = None
    hi: float | None = None
    nan: bool = False
    clear: bool = False
    unit: str = ""

    def bad(self, values: np.ndarray) -> np.ndarray:
        """Mask of the values outside this range."""
        v = np.asarray(values)
        if v.dtype.kind in "iub":
            bad = np.zeros(v.shape, dtype=bool)
        else:
            finite = np.isfinite(v)
            bad = ~finite if not self.nan else np.isinf(v)
        if self.lo is not None:
            bad |= v < self.lo
        if self.hi is not None:
            bad |= v > self.hi
        return bad

    def any_bad(self, values: np.ndarray) -> bool:
        """Whether any value lies outside this range (``bad(values).any()``, by two reductions)."""
        v = values
        if v.size == 0:
            return False
        kind = v.dtype.kind
        if kind not in "iubf":
            return bool(self.bad(v).any())
        lo, hi = v.min(), v.max()
        if kind == "f" and not (math.isfinite(lo) and math.isfinite(hi)):
            # NaN (it propagates through min/max) or an infinity: bad unless NaN is allowed, then value by value
            return bool(self.bad(v).any()) if self.nan else True
        return bool((self.lo is not None and lo < self.lo) or (self.hi is not None and hi > self.hi))

    def bad_scalar(self, value: int | float) -> bool:
        """Whether one int or float lies outside this range (Python comparisons: any int size)."""
        if isinstance(value, float) and not math.isfinite(value):
            return not (self.nan and math.isnan(value))
        return (self.lo is not None and value < self.lo) or (self.hi is not None and value > self.hi)

    def describe(self) -> str:
        lo = "-inf" if self.lo is None else f"{self.lo:g}"
        hi = "inf" if self.hi is None else f"{self.hi:g}"
        return f"[{lo}, {hi}]" + (" or NaN" if self.nan else "") + (f" {self.unit}" if self.unit else "")


_HINTS: dict[type, dict[str, Any]] = {}


_OPTIONAL: dict[type, frozenset[str]] = {}


def _optional(cls: type) -> frozenset[str]:
    """The fields of ``cls`` that have a default (each one's "unknown": ``Header.source_wall_ns`` 0, ``SceneInfo.clock``
    "unknown", NaN for the estimated state, ...): a payload may leave them out and reads with the default."""
    found = _OPTIONAL.get(cls)
    if found is None:
        found = _OPTIONAL[cls] = frozenset(f.name for f in dataclasses.fields(cls)
                                           if f.default is not dataclasses.MISSING or f.default_factory is not dataclasses.MISSING)
    return found


def _hints(cls: type) -> dict[str, Any]:
    h = _HINTS.get(cls)
    if h is None:
        allh = typing.get_type_hints(cls, include_extras=True)
        h = {f.name: allh[f.name] for f in dataclasses.fields(cls)}
        _HINTS[cls] = h
    return h


# What ``_encode_value`` and ``_decode_value`` need to know about a field type, worked out once per type (the typing
# introspection and the ``Annotated[...]`` construction cost more than decoding a small value).
_RANGE, _PLAIN, _ARRAY, _UNION, _TUPLE, _DICT, _ENUM, _OBJ, _FLOAT, _INT, _BOOL, _STR, _BYTES, _UNSUPPORTED = range(14)
_PLANS: dict[int, tuple[Any, tuple]] = {}


def _make_plan(tp: Any) -> tuple:
    origin = typing.get_origin(tp)
    if origin is Annotated:
        base, *meta = typing.get_args(tp)
        rng = next((m for m in meta if isinstance(m, Range)), None)
        spec = next((m for m in meta if isinstance(m, Array)), None)
        if rng is not None:
            return (_RANGE, rng, spec, Annotated[(base, spec)] if spec is not None else base)
        if spec is None:
            return (_PLAIN, base, None, None)
        return (_ARRAY, spec, np.dtype(spec.dtype).newbyteorder("<"), np.dtype(spec.dtype))
    if origin in (typing.Union, types.UnionType):
        args = typing.get_args(tp)
        return (_UNION, type(None) in args, [a for a in args if a is not type(None)][0], None)
    if origin is tuple:
        (elem, _ellipsis) = typing.get_args(tp)
        return (_TUPLE, elem, None, None)
    if origin is dict:
        _k, vt = typing.get_args(tp)
        return (_DICT, vt, None, None)
    if isinstance(tp, type) and issubclass(tp, enum.Enum):
        return (_ENUM, tp, None, None)
    if dataclasses.is_dataclass(tp):
        return (_OBJ, tp, None, None)
    simple = {float: _FLOAT, int: _INT, bool: _BOOL, str: _STR, bytes: _BYTES}
    return (simple.get(tp, _UNSUPPORTED) if isinstance(tp, type) else _UNSUPPORTED, None, None, None)


def _plan(tp: Any) -> tuple:
    # keyed by id (hashing a typing.Annotated is slow); the entry keeps ``tp`` alive and is checked by identity
    entry = _PLANS.get(id(tp))
    if entry is None or entry[0] is not tp:
        entry = _PLANS[id(tp)] = (tp, _make_plan(tp))
    return entry[1]
