"""Arenas: the state of a whole core in a few flat buffers, named tuples rebuilt inside kernels.

Kernels read named tuples of arrays (``st.soc[p, i]``), which keeps every rule readable. But
every array handed from Python to a compiled function costs about 0.1 µs to check and unbox,
and a named tuple takes numba's slow path (about 0.4 µs per field): a supervised BMS has
hundreds of arrays, so calling it with its named tuples would cost far more than running it.

An :class:`Arena` therefore holds every array of a set of named tuples ("bundles") in five
flat buffers, one per dtype, and describes each field by a row of an int64 layout table
(offset, size, shape). Python keeps named tuples of *views* into the buffers; a kernel receives
the buffers and the layout (six arrays) and calls :func:`unpack` to rebuild the same named
tuples as views, at no cost. Compiled, :func:`unpack` is generated per named-tuple class from
its field specs; as plain Python (``NUMBA_DISABLE_JIT=1``) it does the same with NumPy.

Field kinds: an array of float64 / int64 / int32 / int8 / bool; a float, int or bool scalar
(immutable parameters); a nested named tuple.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
from numba.core import cgutils, types
from numba.core.imputils import impl_ret_borrowed
from numba.extending import intrinsic, overload
from numba.np.arrayobj import make_array, populate_array
from numpy.typing import NDArray

I64 = NDArray[np.int64]

KINDS: dict[str, Any] = {
    "f": np.float64,
    "i": np.int64,
    "h": np.int32,
    "c": np.int8,
    "b": np.bool_,
}
"""Arena code -> dtype; the arenas are passed in this order."""
_CODE = {np.dtype(v): k for k, v in KINDS.items()}
MAX_DIM = 4
LAYOUT_COLS = 2 + MAX_DIM


@dataclass(frozen=True)
class FieldSpec:
    name: str
    kind: str
    """Arena code, or ``"t"`` for a nested named tuple."""
    ndim: int
    """0 for a scalar."""
    nested: Any = None
    rows: int = 1
    """Layout rows the field takes (a nested tuple: all of its own)."""


SPECS: dict[type, tuple[FieldSpec, ...]] = {}
"""Named-tuple class -> its field specs (recorded from the first instance an arena holds)."""


def _spec_of(value: Any, name: str) -> FieldSpec:
    if isinstance(value, tuple) and hasattr(value, "_fields"):
        specs = spec(value)
        return FieldSpec(name, "t", 0, type(value), 1 + sum(s.rows for s in specs))
    if isinstance(value, np.ndarray):
        code = _CODE.get(value.dtype)
        if code is None or value.ndim > MAX_DIM:
            raise TypeError(f"field {name}: unsupported array {value.dtype} ndim {value.ndim}")
        return FieldSpec(name, code, value.ndim)
    if isinstance(value, bool | np.bool_):
        return FieldSpec(name, "b", 0)
    if isinstance(value, int | np.integer):
        return FieldSpec(name, "i", 0)
    if isinstance(value, float | np.floating):
        return FieldSpec(name, "f", 0)
    raise TypeError(f"field {name}: an arena holds arrays, numbers, named tuples, not {value!r}")


def spec(nt: Any) -> tuple[FieldSpec, ...]:
    """Field specs of ``nt``'s class (recorded once; every instance must agree)."""
    cls = type(nt)
    got = tuple(_spec_of(getattr(nt, f), f) for f in nt._fields)
    known = SPECS.setdefault(cls, got)
    if known != got:
        raise TypeError(f"{cls.__name__}: fields differ from an earlier instance: {got}")
    return known


class Arenas(NamedTuple):
    """The five buffers and the layout: what a kernel receives."""

    f: NDArray[np.float64]
    i: NDArray[np.int64]
    h: NDArray[np.int32]
    c: NDArray[np.int8]
    b: NDArray[np.bool_]
    lay: I64


class Arena:
    """Collects named tuples, then moves them into flat buffers (:meth:`seal`)."""

    def __init__(self) -> None:
        self._items: list[Any] = []

    def add(self, nt: Any) -> int:
        """Register ``nt``; returns its handle (its layout row after :meth:`seal`)."""
        spec(nt)
        self._items.append(nt)
        return len(self._items) - 1

    def seal(self) -> tuple[Arenas, list[Any], list[int]]:
        """Allocate the buffers; returns them, the named tuples as views, and the layout row
        of each (in the order added)."""
        rows: list[tuple[str, int, tuple[int, ...], Any]] = []
        starts: list[int] = []
        for nt in self._items:
            starts.append(len(rows))
            _flatten(nt, rows)
        sizes = dict.fromkeys(KINDS, 0)
        offsets = []
        for kind, n, _, _ in rows:
            if kind == "t":
                offsets.append(0)
                continue
            offsets.append(sizes[kind])
            sizes[kind] += n
        bufs = {k: np.zeros(max(sizes[k], 1), KINDS[k]) for k in KINDS}
        lay = np.zeros((max(len(rows), 1), LAYOUT_COLS), np.int64)
        for r, ((kind, n, shape, value), off) in enumerate(zip(rows, offsets, strict=True)):
            lay[r, 0], lay[r, 1] = off, n
            lay[r, 2 : 2 + len(shape)] = shape
            if kind != "t" and n:
                bufs[kind][off : off + n] = np.asarray(value).reshape(-1)
        arenas = Arenas(bufs["f"], bufs["i"], bufs["h"], bufs["c"], bufs["b"], lay)
        views = [unpack(type(nt), *arenas, k) for nt, k in zip(self._items, starts, strict=True)]
        return arenas, views, starts


def _flatten(nt: Any, rows: list[tuple[str, int, tuple[int, ...], Any]]) -> None:
    for s in SPECS[type(nt)]:
        value = getattr(nt, s.name)
        if s.kind == "t":
            rows.append(("t", 0, (), None))
            _flatten(value, rows)
        elif s.ndim == 0:
            rows.append((s.kind, 1, (), value))
        else:
            rows.append((s.kind, int(value.size), tuple(int(x) for x in value.shape), value))


def unpack(
    cls: Any, f: Any, i: Any, h: Any, c: Any, b: Any, lay: I64, k: int
) -> Any:  # pragma: no cover - replaced by the compiled overload in kernels
    """``cls`` rebuilt from the arenas, its first field at layout row ``k`` (views, no copy)."""
    bufs = {"f": f, "i": i, "h": h, "c": c, "b": b}
    out = []
    r = k
    for s in SPECS[cls]:
        if s.kind == "t":
            out.append(unpack(s.nested, f, i, h, c, b, lay, r + 1))
        elif s.ndim == 0:
            value = bufs[s.kind][lay[r, 0]]
            out.append(value.item() if hasattr(value, "item") else value)
        else:
            off, n = int(lay[r, 0]), int(lay[r, 1])
            shape = tuple(int(x) for x in lay[r, 2 : 2 + s.ndim])
            out.append(bufs[s.kind][off : off + n].reshape(shape))
        r += s.rows
    return cls(*out)


@intrinsic
def _view(typingctx, buf, off, shape):  # type: ignore[no-untyped-def]
    """C-contiguous view of ``buf[off:off + prod(shape)]`` shaped ``shape``, sharing ``buf``'s
    memory. Unchecked: the layout comes from :meth:`Arena.seal`.

    The view has no memory-info (no reference count): the arena is owned by Python for the
    whole call, and a view never leaves the kernel. That is the point: a named tuple of
    counted arrays costs two atomic operations per array at every non-inlined call it is
    passed to (about 10 µs per step for one method); views cost nothing. A view made this
    way costs a few ns; ``buf[a:b].reshape(shape)`` about 100 ns."""
    if not isinstance(buf, types.Array) or not isinstance(shape, types.UniTuple):
        return None
    ndim = shape.count
    ret = types.Array(buf.dtype, ndim, "C")

    def codegen(context, builder, signature, args):  # type: ignore[no-untyped-def]
        buf_v, off_v, shape_v = args
        src = make_array(buf)(context, builder, buf_v)
        dst = make_array(ret)(context, builder)
        intp = context.get_value_type(types.intp)
        size = context.get_abi_sizeof(context.get_data_type(buf.dtype))
        itemsize = context.get_constant(types.intp, size)
        start = context.cast(builder, off_v, signature.args[1], types.intp)
        data = builder.gep(src.data, [start])
        dims = [
            context.cast(builder, d, shape.dtype, types.intp)
            for d in cgutils.unpack_tuple(builder, shape_v, ndim)
        ]
        strides = []
        acc = itemsize
        for d in reversed(dims):
            strides.append(acc)
            acc = builder.mul(acc, d)
        strides.reverse()
        populate_array(
            dst,
            data=data,
            shape=cgutils.pack_array(builder, dims, intp),
            strides=cgutils.pack_array(builder, strides, intp),
            itemsize=itemsize,
            meminfo=None,
            parent=None,
        )
        return impl_ret_borrowed(context, builder, ret, dst._getvalue())

    return ret(buf, off, shape), codegen


def _source(cls: Any, k: str) -> str:
    """Python source of an expression that rebuilds ``cls`` from row ``k``."""
    parts = []
    r = 0
    for s in SPECS[cls]:
        row = f"{k} + {r}"
        if s.kind == "t":
            parts.append(_source(s.nested, f"{k} + {r + 1}"))
        elif s.ndim == 0:
            parts.append(f"{s.kind}[lay[{row}, 0]]")
        else:
            shape = ", ".join(f"lay[{row}, {2 + d}]" for d in range(s.ndim))
            parts.append(f"_view({s.kind}, lay[{row}, 0], ({shape},))")
        r += s.rows
    name = f"_cls_{id(cls)}"
    _CLASSES[name] = cls
    return f"{name}({', '.join(parts)})"


_CLASSES: dict[str, Any] = {}


@overload(unpack)
def _unpack_compiled(cls, f, i, h, c, b, lay, k):  # type: ignore[no-untyped-def]
    # no annotations: numba compares this signature with the generated one, names and all
    target = cls.instance_class
    if target not in SPECS:
        raise TypeError(f"{target.__name__} was never added to an arena")
    body = _source(target, "k")
    src = f"def impl(cls, f, i, h, c, b, lay, k):\n    return {body}\n"
    ns: dict[str, Any] = {**_CLASSES, "_view": _view}
    exec(compile(src, f"<arena unpack {target.__name__}>", "exec"), ns)
    return ns["impl"]


__all__ = ["SPECS", "Arena", "Arenas", "FieldSpec", "spec", "unpack"]
