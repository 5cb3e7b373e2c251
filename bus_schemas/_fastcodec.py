"""The codec's fast path: one generated decoder and encoder per message class.

``_wire``'s reference codec walks a message field by field, dispatching on
each field's plan and checking each array on its own (two numpy reductions
per small array). Here the same plans are turned once per message class into
Python source (``exec``), one function per dataclass with every field's
checks written out (no per-value dispatch), and the arrays of one message are
handled together:

- decoding checks the structure of every array field (``[dtype, shape,
  bytes]``, dtype, dims, byte length, named dims agreeing within the object)
  while walking, but only collects its bytes, per (dtype, range) group of the
  message; at the end each group is joined into one writable buffer, its
  range checked by one ``Range.any_bad`` (the same test as per array, since
  it is a test of every value), and every array field becomes a slice (a
  writable view) of its group's array;
- objects are built as their dataclass ``__init__`` builds them (each field
  set once through its slot), without the keyword handling;
- encoding writes each field as the reference does (the same Python values,
  so the same bytes after ``msgpack.packb``).

The bodies it decodes are those ``_wire.unpack_envelope`` unpacked (msgpack's
builtin types, every bin within the payload limit).

The fast path is optimistic: it accepts only what it can check to be fine
and gives up (``None``) on anything else: a type, dtype or shape it does not
expect, a value out of range (to be dropped, cleared or refused), a subclass.
The caller then runs the reference codec on the same input, which accepts,
repairs or refuses it with its own messages and records. So for every
payload the result (message, error class and message, out-of-range records)
is the reference codec's; ``tests/bus_schemas/test_fast_codec.py`` checks
that on real, golden and hostile payloads.

A class whose field types this module does not handle (arrays inside a
union, tuple or dict, a ``Range`` on anything but an int, float or array,
...) gets no fast codec and always uses the reference one. Only
little-endian hosts use the fast path (the wire is little-endian; the views
must be native arrays).
"""

from __future__ import annotations

import dataclasses
import math
import sys
import types
from typing import Any, Callable

import numpy as np

from . import _plans as W

ENABLED = sys.byteorder == "little"


class _GiveUp(Exception):
    """Raised inside the generated code: this input is for the reference codec."""


class _Unsupported(Exception):
    """A field type the generator does not handle: the class keeps the reference codec only."""


_DECODERS: dict[type, Callable[[Any], Any] | None] = {}
_ENCODERS: dict[type, Callable[[Any], dict] | None] = {}


def decode(cls: type, body: Any) -> Any:
    """``cls`` decoded from ``body`` (the envelope's body, already upgraded), or None: use the reference codec."""
    fn = _DECODERS.get(cls, False)
    if fn is False:
        fn = _DECODERS[cls] = _build(cls, _DecodeGen) if ENABLED else None
    if fn is None:
        return None
    try:
        return fn(body)
    except Exception:  # _GiveUp, or anything else unexpected: the reference codec decides
        return None


def encode_body(msg: Any) -> dict | None:
    """The body dict of ``msg`` as the reference ``_encode_obj`` makes it, or None: use the reference codec."""
    cls = type(msg)
    fn = _ENCODERS.get(cls, False)
    if fn is False:
        fn = _ENCODERS[cls] = _build(cls, _EncodeGen) if ENABLED else None
    if fn is None:
        return None
    try:
        return fn(msg)
    except Exception:  # _GiveUp, or an error the reference codec reports with its own message
        return None


def _build(cls: type, gen_type: type) -> Callable | None:
    try:
        return gen_type(cls).build()
    except _Unsupported:
        return None


# --------------------------------------------------------------------------- shared by both generators


class _Gen:
    def __init__(self, root: type) -> None:
        self.root = root
        self.ns: dict[str, Any] = {"_GiveUp": _GiveUp, "np": np, "math": math, "_ndarray": np.ndarray}
        self.lines: list[str] = []
        self.fn_names: dict[type, str] = {}
        self.todo: list[type] = []

    def const(self, value: Any, hint: str = "c") -> str:
        """A name in the generated code's globals bound to ``value``."""
        name = f"_{hint}{len(self.ns)}"
        self.ns[name] = value
        return name

    def fn_for(self, cls: type) -> str:
        name = self.fn_names.get(cls)
        if name is None:
            name = self.fn_names[cls] = f"_{self.prefix}_{cls.__name__}_{len(self.fn_names)}"
            self.todo.append(cls)
        return name

    def generate_all(self) -> str:
        root_fn = self.fn_for(self.root)
        while self.todo:
            self.gen_class(self.todo.pop())
        return root_fn

    def compile(self) -> None:
        src = "\n".join(self.lines)
        exec(compile(src, f"<bus_schemas fast {self.prefix} {self.root.__name__}>", "exec"), self.ns)

    @staticmethod
    def field_kind(tp: Any) -> tuple[Any, Any]:
        """(plan without a Range, the Range or None)."""
        plan = W._plan(tp)
        if plan[0] == W._RANGE:
            rng = plan[1]
            plan = W._plan(plan[3])
            if plan[0] not in (W._INT, W._FLOAT, W._ARRAY):
                raise _Unsupported(f"Range on {plan!r}")
            return plan, rng
        while plan[0] == W._PLAIN:
            plan = W._plan(plan[1])
            if plan[0] == W._RANGE:
                raise _Unsupported("nested Range")
        return plan, None

    @staticmethod
    def array_spec_ok(spec: Any) -> None:
        if spec.dtype not in W._ALLOWED_DTYPES or not spec.dims:
            raise _Unsupported(f"array {spec!r}")


# --------------------------------------------------------------------------- decoding


class _DecodeGen(_Gen):
    prefix = "dec"

    def __init__(self, root: type) -> None:
        super().__init__(root)
        self.groups: dict[tuple[str, int], int] = {}  # (dtype, id(range) or 0) -> group index
        self.group_dtypes: list[np.dtype] = []
        self.group_ranges: list[Any] = []
        self.ns["_set"] = object.__setattr__
        self.ns["_new"] = object.__new__

    def group(self, spec: Any, rng: Any) -> int:
        key = (spec.dtype, id(rng) if rng is not None else 0)
        g = self.groups.get(key)
        if g is None:
            g = self.groups[key] = len(self.group_dtypes)
            self.group_dtypes.append(np.dtype(spec.dtype))
            self.group_ranges.append(rng)
            self.ns.setdefault("_keep_ranges", []).append(rng)  # keeps id(rng) meaningful
        return g

    def build(self) -> Callable[[Any], Any]:
        root_fn = self.generate_all()
        self.compile()
        walk = self.ns[root_fn]
        dtypes = tuple(self.group_dtypes)
        ranges = tuple(self.group_ranges)
        n_groups = len(dtypes)

        def decode_fast(body: Any) -> Any:
            bufs = tuple([] for _ in range(n_groups))
            pending: list = []
            msg = walk(body, bufs, pending)
            arrays = []
            for g in range(n_groups):
                arr = np.frombuffer(bytearray().join(bufs[g]), dtypes[g])  # one writable buffer per group
                rng = ranges[g]
                if rng is not None and rng.any_bad(arr):
                    raise _GiveUp  # drop, clear or refuse: the reference codec's business
                arrays.append(arr)
            offsets = [0] * n_groups
            for fill, args in pending:
                fill(arrays, offsets, *args)
            return msg

        return decode_fast

    def gen_class(self, cls: type) -> None:
        fn = self.fn_names[cls]
        hints = W._hints(cls)
        setters = self.slot_setters(cls, hints)
        keys = self.const(dict.fromkeys(hints).keys(), "keys")
        L = [f"def {fn}(body, B, P):", f"    if type(body) is not dict or body.keys() != {keys}: raise _GiveUp"]
        values: list[tuple[str, str]] = []  # (field, variable) of the fields set now
        arrays: list[tuple[str, int, str, int]] = []  # (field, group, count or shape variable, ndim): set by the fill
        dims_seen: set[str] = set()
        for i, (name, tp) in enumerate(hints.items()):
            plan, rng = self.field_kind(tp)
            v = f"v{i}"
            L.append(f"    {v} = body[{name!r}]")
            kind = plan[0]
            if kind == W._ARRAY:
                spec = plan[1]
                self.array_spec_ok(spec)
                g = self.group(spec, rng)
                L.extend(self.array_lines(v, spec, g, i, dims_seen))
                arrays.append((name, g, f"n{i}", len(spec.dims)))
                continue
            L.extend("    " + line for line in self.value_lines(v, plan, rng))
            values.append((name, v))
        if arrays:
            groups = sorted({a[1] for a in arrays})
            L.insert(2, "    " + "; ".join(f"ap{g} = B[{g}].append" for g in groups))
        if setters is not None:
            # what the dataclass __init__ does (each field set once, in order), without its keyword handling
            L.append(f"    obj = _new({self.const(cls, 'cls')})")
            L.extend(f"    {setters[name]}(obj, {v})" for name, v in values)
        else:
            if arrays and hasattr(cls, "__post_init__"):
                raise _Unsupported("arrays are set after __init__; a __post_init__ would see None")
            kwargs = [f"{name}={v}" for name, v in values] + [f"{a[0]}=None" for a in arrays]
            L.append(f"    obj = {self.const(cls, 'cls')}({', '.join(kwargs)})")
        if arrays:
            fill = self.gen_fill(cls, arrays, setters)
            L.append(f"    P.append(({fill}, (obj, {', '.join(a[2] for a in arrays)})))")
        L.append("    return obj")
        self.lines.extend(L)
        self.lines.append("")

    def slot_setters(self, cls: type, hints: dict) -> dict[str, str] | None:
        """Field -> the name of its slot's setter, when an object can be built as its dataclass ``__init__`` builds it:
        a slots dataclass with the generated ``__init__``, no ``__post_init__`` and no ``__new__`` of its own; else None."""
        init = getattr(cls, "__init__", None)
        if (
            "__slots__" not in cls.__dict__
            or hasattr(cls, "__post_init__")
            or cls.__new__ is not object.__new__
            or getattr(init, "__qualname__", "") != f"{cls.__qualname__}.__init__"
            or getattr(getattr(init, "__code__", None), "co_filename", "") != "<string>"  # made by dataclasses, not written in the class
            or list(hints) != [f.name for f in dataclasses.fields(cls) if f.init]
        ):
            return None
        out = {}
        for name in hints:
            slot = cls.__dict__.get(name)
            if not isinstance(slot, types.MemberDescriptorType):
                return None
            out[name] = self.const(slot.__set__, "set")
        return out

    def array_lines(self, v: str, spec: Any, g: int, i: int, dims_seen: set[str]) -> list[str]:
        """Check ``[dtype, shape, bytes]`` in ``v`` as ``_decode_array`` does; leave the count (1-D) or shape in ``n{i}``."""
        item = np.dtype(spec.dtype).itemsize
        nd = len(spec.dims)
        # the same acceptance as ``_decode_array``, fewer operations: an unpacking of the wrong length raises (give up);
        # n * itemsize == len(buf) implies n >= 0; a named dim seen before was checked to be an int in range there
        L = [
            f"    if type({v}) is not list: raise _GiveUp",
            f"    d, sh, buf = {v}",
            f"    if type(d) is not str or d != {spec.dtype!r} or type(sh) is not list or type(buf) is not bytes: raise _GiveUp",
        ]
        n = f"n{i}"
        if nd == 1:
            want = spec.dims[0]
            L.append(f"    {n}, = sh")
            if isinstance(want, str) and want in dims_seen:
                L.append(f"    if {n} != dim_{want} or type({n}) is not int or {n} * {item} != len(buf): raise _GiveUp")
            else:
                L.append(f"    if type({n}) is not int or {n} > {W.MAX_ARRAY_DIM} or {n} * {item} != len(buf): raise _GiveUp")
                if isinstance(want, int):
                    L.append(f"    if {n} != {want}: raise _GiveUp")
                elif isinstance(want, str):
                    dims_seen.add(want)
                    L.append(f"    dim_{want} = {n}")
        else:
            L += [
                f"    {n} = tuple(sh)",
                f"    if len({n}) != {nd}: raise _GiveUp",
                f"    for x in {n}:",
                f"        if type(x) is not int or not 0 <= x <= {W.MAX_ARRAY_DIM}: raise _GiveUp",
                f"    if math.prod([x or 1 for x in {n}]) * {item} > {W.MAX_PAYLOAD_BYTES} or math.prod({n}) * {item} != len(buf): raise _GiveUp",
            ]
            for k, want in enumerate(spec.dims):
                size = f"{n}[{k}]"
                if isinstance(want, int):
                    L.append(f"    if {size} != {want}: raise _GiveUp")
                elif isinstance(want, str):
                    if want in dims_seen:
                        L.append(f"    if {size} != dim_{want}: raise _GiveUp")
                    else:
                        dims_seen.add(want)
                        L.append(f"    dim_{want} = {size}")
        L.append(f"    ap{g}(buf)")
        return L

    def gen_fill(self, cls: type, arrays: list[tuple[str, int, str, int]], setters: dict[str, str] | None) -> str:
        """A function setting every array field of ``obj`` to its slice of its group's array."""
        fn = f"_fill_{cls.__name__}_{len(self.ns)}"
        params = ", ".join(f"a{k}" for k in range(len(arrays)))
        L = [f"def {fn}(A, O, obj, {params}):"]
        for k, (name, g, _var, nd) in enumerate(arrays):
            if nd == 1:
                L.append(f"    o = O[{g}]; e = o + a{k}; O[{g}] = e")
                value = f"A[{g}][o:e]"
            else:
                L.append(f"    o = O[{g}]; e = o + math.prod(a{k}); O[{g}] = e")
                value = f"A[{g}][o:e].reshape(a{k})"
            L.append(f"    {setters[name]}(obj, {value})" if setters is not None else f"    _set(obj, {name!r}, {value})")
        self.lines.extend(L)
        self.lines.append("")
        return fn

    def value_lines(self, v: str, plan: tuple, rng: Any) -> list[str]:
        """Lines (no indent) that check and convert the scalar or container in ``v`` as ``_decode_value`` does."""
        kind = plan[0]
        if kind == W._INT:
            L = [f"if type({v}) is not int: raise _GiveUp"]
            return L + self.range_lines(v, rng, is_float=False)
        if kind == W._FLOAT:
            L = [f"if type({v}) is not float:", f"    if type({v}) is not int: raise _GiveUp", f"    {v} = float({v})"]
            return L + self.range_lines(v, rng, is_float=True)
        if kind == W._BOOL:
            return [f"if type({v}) is not bool: raise _GiveUp"]
        if kind == W._STR:
            return [f"if type({v}) is not str: raise _GiveUp"]
        if kind == W._BYTES:
            return [f"if type({v}) is not bytes: raise _GiveUp"]
        if kind == W._ENUM:
            members = self.const({m.value: m for m in plan[1]}, "enum")
            return [f"if type({v}) is not int: raise _GiveUp", f"{v} = {members}[{v}]"]  # KeyError: not a member, give up
        if kind == W._OBJ:
            return [f"{v} = {self.fn_for(plan[1])}({v}, B, P)"]
        if kind == W._UNION:
            inner, inner_rng = self.field_kind(plan[2])
            if inner[0] == W._ARRAY:
                raise _Unsupported("array in a union")
            lines = self.value_lines(v, inner, inner_rng)
            if not plan[1]:
                return [f"if {v} is None: raise _GiveUp", *lines]
            return [f"if {v} is not None:", *("    " + line for line in lines)]
        if kind in (W._TUPLE, W._DICT):
            elem, elem_rng = self.field_kind(plan[1])
            if elem[0] == W._ARRAY:
                raise _Unsupported("array in a container")
            if kind == W._TUPLE:
                if elem[0] == W._OBJ:
                    return [f"if type({v}) is not list: raise _GiveUp", f"{v} = tuple([{self.fn_for(elem[1])}(x, B, P) for x in {v}])"]
                conv = self.elem_fn(elem, elem_rng)
                return [f"if type({v}) is not list: raise _GiveUp", f"{v} = tuple([{conv}(x, B, P) for x in {v}])"]
            conv = self.elem_fn(elem, elem_rng)
            return [
                f"if type({v}) is not dict: raise _GiveUp",
                f"for k in {v}:",
                "    if type(k) is not str: raise _GiveUp",
                f"{v} = {{k: {conv}(x, B, P) for k, x in {v}.items()}}",
            ]
        raise _Unsupported(f"plan {plan!r}")

    def elem_fn(self, plan: tuple, rng: Any) -> str:
        """A function converting one container element."""
        if plan[0] == W._OBJ:
            return self.fn_for(plan[1])
        fn = f"_elem_{len(self.ns)}"
        self.ns[fn] = None  # reserve the name
        body = self.value_lines("x", plan, rng)
        self.lines.extend([f"def {fn}(x, B, P):", *("    " + line for line in body), "    return x", ""])
        return fn

    def range_lines(self, v: str, rng: Any, *, is_float: bool) -> list[str]:
        """Give up unless ``v`` is surely inside ``rng`` (``Range.bad_scalar`` false): finite and within the bounds, or an allowed NaN."""
        if rng is None:
            return []
        lo = self.const(rng.lo if rng.lo is not None else -sys.float_info.max, "lo")
        hi = self.const(rng.hi if rng.hi is not None else sys.float_info.max, "hi")
        # an int outside +-float max with an open bound is fine for the reference; giving up there is merely slow
        if is_float and rng.nan:
            return [f"if not {lo} <= {v} <= {hi} and {v} == {v}: raise _GiveUp"]
        return [f"if not {lo} <= {v} <= {hi}: raise _GiveUp"]


# --------------------------------------------------------------------------- encoding


class _EncodeGen(_Gen):
    prefix = "enc"

    def __init__(self, root: type) -> None:
        super().__init__(root)
        self.ns["_ints"] = (int, np.integer)
        self.ns["_asarray"] = np.asarray

    def build(self) -> Callable[[Any], dict]:
        root_fn = self.generate_all()
        self.compile()
        return self.ns[root_fn]

    def gen_class(self, cls: type) -> None:
        fn = self.fn_names[cls]
        hints = W._hints(cls)
        L = [f"def {fn}(obj):", f"    if type(obj) is not {self.const(cls, 'cls')}: raise _GiveUp"]
        out: list[str] = []
        dims_seen: set[str] = set()
        for i, (name, tp) in enumerate(hints.items()):
            plan, _rng = self.field_kind(tp)  # ranges are checked on decode only
            v = f"v{i}"
            L.append(f"    {v} = obj.{name}")
            if plan[0] == W._ARRAY:
                L.extend("    " + line for line in self.array_lines(v, plan, dims_seen))
            else:
                L.extend("    " + line for line in self.value_lines(v, plan))
            out.append(f"{name!r}: {v}")
        L.append(f"    return {{{', '.join(out)}}}")
        self.lines.extend(L)
        self.lines.append("")

    def array_lines(self, v: str, plan: tuple, dims_seen: set[str]) -> list[str]:
        """As ``_encode_value`` for an array: dtype and dims checked, then ``[dtype, shape, C-order bytes]``."""
        spec, _wire_dt, dt = plan[1], plan[2], plan[3]
        self.array_spec_ok(spec)
        nd = len(spec.dims)
        dt_name = self.const(dt, "dt")
        L = [
            f"if type({v}) is not _ndarray: {v} = _asarray({v})",
            f"dt = {v}.dtype",
            f"if dt is not {dt_name} and dt != {dt_name}: raise _GiveUp",  # the same test, the identity first (the usual case)
        ]
        if nd == 1:  # an unpacking of a shape of another length raises: give up
            sizes, shape = ["n"], "[n]"
            L.append(f"n, = {v}.shape")
        else:
            sizes, shape = [f"sh[{k}]" for k in range(nd)], "list(sh)"
            L += [f"sh = {v}.shape", f"if len(sh) != {nd}: raise _GiveUp"]
        for size, want in zip(sizes, spec.dims):
            if isinstance(want, int):
                L.append(f"if {size} != {want}: raise _GiveUp")
            elif isinstance(want, str):
                var = f"dim_{want}"
                if want in dims_seen:
                    L.append(f"if {size} != {var}: raise _GiveUp")
                else:
                    dims_seen.add(want)
                    L.append(f"{var} = {size}")
        # tobytes() writes C order whatever the layout; the dtype is native and little-endian (ENABLED)
        L.append(f"{v} = [{spec.dtype!r}, {shape}, {v}.tobytes()]")
        return L

    def value_lines(self, v: str, plan: tuple) -> list[str]:
        kind = plan[0]
        if kind == W._INT:
            return [
                f"if type({v}) is not int:",
                f"    if isinstance({v}, bool) or not isinstance({v}, _ints): raise _GiveUp",
                f"    {v} = int({v})",
            ]
        if kind == W._FLOAT:
            return [f"if type({v}) is not float: {v} = float({v})"]
        if kind == W._BOOL:
            return [f"if type({v}) is not bool: {v} = bool({v})"]
        if kind == W._STR:
            return [f"if not isinstance({v}, str): raise _GiveUp"]
        if kind == W._BYTES:
            return [f"{v} = bytes({v})"]
        if kind == W._ENUM:
            enum_cls = self.const(plan[1], "enum")
            return [f"{v} = {v}._value_ if type({v}) is {enum_cls} else int({enum_cls}({v}).value)"]
        if kind == W._OBJ:
            return [f"{v} = {self.fn_for(plan[1])}({v})"]  # gives up unless exactly that class
        if kind == W._UNION:
            inner, _rng = self.field_kind(plan[2])
            if inner[0] == W._ARRAY:
                raise _Unsupported("array in a union")
            return [f"if {v} is not None:", *("    " + line for line in self.value_lines(v, inner))]
        if kind in (W._TUPLE, W._DICT):
            elem, _rng = self.field_kind(plan[1])
            if elem[0] == W._ARRAY:
                raise _Unsupported("array in a container")
            conv = self.fn_for(elem[1]) if elem[0] == W._OBJ else self.elem_fn(elem)
            if kind == W._TUPLE:  # a tuple or list only: a one-shot iterable must reach the reference codec unread
                return [f"if type({v}) is not tuple and type({v}) is not list: raise _GiveUp", f"{v} = [{conv}(x) for x in {v}]"]
            return [f"if type({v}) is not dict: raise _GiveUp", f"{v} = {{str(k): {conv}(x) for k, x in {v}.items()}}"]
        raise _Unsupported(f"plan {plan!r}")

    def elem_fn(self, plan: tuple) -> str:
        fn = f"_elem_{len(self.ns)}"
        self.ns[fn] = None
        body = self.value_lines("x", plan)
        self.lines.extend([f"def {fn}(x):", *("    " + line for line in body), "    return x", ""])
        return fn
