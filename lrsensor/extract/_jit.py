"""The compiler switch of the extractor's kernels: numba when it is installed, plain Python otherwise.

Every kernel of :mod:`lrsensor.extract` is decorated with :data:`njit` (compiled once, cached on disk in
``__pycache__``, no GIL held, numpy's error model: a division by zero gives inf or NaN, never an exception),
:data:`inline` (small helpers inlined into their callers). Multiplies and adds may be fused
(``fastmath={"contract"}``: one rounding instead of two, nothing else of fast-math), so floating-point results
agree with the numpy reference (:mod:`lrsensor.extract.reference`) to rounding, not bit for bit; the detection is
integer arithmetic and stays bit for bit.

The kernels make their arrays with :func:`empty`, :func:`zeros`, :func:`full` and :func:`arange` (numpy's, with the
dtype always given): numba compiles its own ``np.empty``, ``np.zeros``, ``np.full`` and ``np.arange`` as a library
per spelling of shape and dtype (``np.zeros(n)``, ``np.zeros(n, np.float64)`` and ``np.zeros(n, float)`` three times
over), in each process that compiles, while these four are built in place in the calling kernel, like its arithmetic
(:mod:`lrsensor.extract.compile`).

Without numba (:data:`HAVE_NUMBA` False) the decorators return the function unchanged: the kernels are then
importable (the reference reads their constants) but never called, since the extractor runs its reference.
"""

from __future__ import annotations

from typing import Any

import numpy as np


def empty(shape: Any, dtype: Any) -> Any:
    """``np.empty(shape, dtype)``: a C-ordered array of an int or tuple ``shape``, uninitialised."""
    return np.empty(shape, dtype)


def zeros(shape: Any, dtype: Any) -> Any:
    """``np.zeros(shape, dtype)``."""
    return np.zeros(shape, dtype)


def full(shape: Any, value: Any, dtype: Any) -> Any:
    """``np.full(shape, value, dtype)``: ``value`` converted to ``dtype`` as numpy converts it."""
    return np.full(shape, value, dtype)


def arange(n: Any, dtype: Any) -> Any:
    """``np.arange(n, dtype=dtype)``: 0, 1, ..., n - 1."""
    return np.arange(n, dtype=dtype)


try:  # pragma: no cover - depends on the platform
    import numba
    from numba.cpython.unsafe.numbers import trailing_zeros as _ctz

    HAVE_NUMBA = True
    #: Compile a kernel (cached on disk, no GIL, numpy's error model, multiplies and adds may be fused).
    njit: Any = numba.njit(cache=True, nogil=True, error_model="numpy", fastmath={"contract"})
    #: Compile a small helper, or a thin stage that mostly calls kernels, into its callers (numba inlines it before
    #: typing, and it takes its callers' options): one library less, whose call tree LLVM would otherwise optimise
    #: and compile once more (:mod:`lrsensor.extract.compile`).
    inline: Any = numba.njit(inline="always", error_model="numpy")
    #: Compile a kernel that only other kernels call (as :data:`njit`), without the wrappers through which Python
    #: and C would call it: numba builds both into every kernel's library, where LLVM optimises and compiles them,
    #: and no caller links them (:mod:`lrsensor.extract.compile`).
    _no_wrappers: dict[str, Any] = {"no_cpython_wrapper": True, "no_cfunc_wrapper": True}
    callee: Any = numba.njit(cache=True, nogil=True, error_model="numpy", fastmath={"contract"}, **_no_wrappers)
    trailing_zeros: Any = _ctz  # the number of trailing zero bits of an unsigned integer (one instruction)
except ImportError:  # pragma: no cover
    HAVE_NUMBA = False

    def njit(f: Any) -> Any:
        return f

    inline = njit
    callee = njit

    def _trailing_zeros_py(x: Any) -> int:
        """The number of trailing zero bits of a positive integer."""
        return (int(x) & -int(x)).bit_length() - 1

    trailing_zeros = _trailing_zeros_py


def _build_in_place() -> None:  # pragma: no cover - depends on the platform
    """Teach numba :func:`empty`, :func:`zeros`, :func:`full` and :func:`arange`: typed from the shape and the
    dtype, and lowered in the calling kernel with numba's own allocation (numba's internals: where they moved, each
    is an overload that calls numpy's, compiled per signature as numba's own are)."""
    from numba.core import cgutils, types
    from numba.core.typing import npydecl
    from numba.extending import lower_builtin, overload, type_callable
    from numba.np import arrayobj

    typing: Any = npydecl
    arrays: Any = arrayobj
    cg: Any = cgutils
    if not all(hasattr(arrays, name) for name in ("_empty_nd_impl", "_parse_shape", "store_item")):
        register: Any = overload
        register(empty)(lambda shape, dtype: lambda shape, dtype: np.empty(shape, dtype))
        register(zeros)(lambda shape, dtype: lambda shape, dtype: np.zeros(shape, dtype))
        register(full)(lambda shape, value, dtype: lambda shape, value, dtype: np.full(shape, value, dtype))
        register(arange)(lambda n, dtype: lambda n, dtype: np.arange(n, dtype=dtype))
        return
    typer: Any = type_callable
    lower: Any = lower_builtin

    def array_type(shape: Any, dtype: Any) -> Any:
        ndim, nb_dtype = typing.parse_shape(shape), typing.parse_dtype(dtype)
        return None if ndim is None or nb_dtype is None else types.Array(nb_dtype, ndim, "C")

    def full_type(shape: Any, value: Any, dtype: Any) -> Any:
        return array_type(shape, dtype) if isinstance(value, (types.Number, types.Boolean)) else None

    typer(empty)(lambda context: array_type)
    typer(zeros)(lambda context: array_type)
    typer(full)(lambda context: full_type)
    typer(arange)(lambda context: lambda n, dtype: array_type(n, dtype) if isinstance(n, types.Integer) else None)

    def allocate(context: Any, builder: Any, sig: Any, shape: Any) -> Any:
        dims = arrays._parse_shape(context, builder, sig.args[0], shape)
        return arrays._empty_nd_impl(context, builder, sig.return_type, dims)

    def lower_empty(context: Any, builder: Any, sig: Any, args: Any) -> Any:
        return allocate(context, builder, sig, args[0])._getvalue()

    def lower_zeros(context: Any, builder: Any, sig: Any, args: Any) -> Any:
        array = allocate(context, builder, sig, args[0])
        cg.memset(builder, array.data, builder.mul(array.itemsize, array.nitems), 0)
        return array._getvalue()

    def lower_full(context: Any, builder: Any, sig: Any, args: Any) -> Any:
        array_type = sig.return_type
        array = allocate(context, builder, sig, args[0])
        value = context.cast(builder, args[1], sig.args[1], array_type.dtype)
        with cg.for_range(builder, array.nitems) as loop:
            arrays.store_item(context, builder, array_type, value, builder.gep(array.data, [loop.index]))
        return array._getvalue()

    def lower_arange(context: Any, builder: Any, sig: Any, args: Any) -> Any:
        array_type = sig.return_type
        array = allocate(context, builder, sig, args[0])
        with cg.for_range(builder, array.nitems) as loop:
            value = context.cast(builder, loop.index, types.intp, array_type.dtype)
            arrays.store_item(context, builder, array_type, value, builder.gep(array.data, [loop.index]))
        return array._getvalue()

    lower(empty, types.Any, types.Any)(lower_empty)
    lower(zeros, types.Any, types.Any)(lower_zeros)
    lower(full, types.Any, types.Any, types.Any)(lower_full)
    lower(arange, types.Any, types.Any)(lower_arange)


if HAVE_NUMBA:
    _build_in_place()
