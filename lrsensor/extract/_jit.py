"""The compiler switch of the extractor's kernels: numba when it is installed, plain Python otherwise.

Every kernel of :mod:`lrsensor.extract` is decorated with :data:`njit` (compiled once, cached on disk in
``__pycache__``, no GIL held, numpy's error model: a division by zero gives inf or NaN, never an exception),
:data:`inline` (small helpers inlined into their callers). Multiplies and adds may be fused
(``fastmath={"contract"}``: one rounding instead of two, nothing else of fast-math), so floating-point results
agree with the numpy reference (:mod:`lrsensor.extract.reference`) to rounding, not bit for bit; the detection is
integer arithmetic and stays bit for bit.

Without numba (:data:`HAVE_NUMBA` False) the decorators return the function unchanged: the kernels are then
importable (the reference reads their constants) but never called, since the extractor runs its reference.
"""

from __future__ import annotations

from typing import Any

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
    trailing_zeros: Any = _ctz  # the number of trailing zero bits of an unsigned integer (one instruction)
except ImportError:  # pragma: no cover
    HAVE_NUMBA = False

    def njit(f: Any) -> Any:
        return f

    inline = njit

    def _trailing_zeros_py(x: Any) -> int:
        """The number of trailing zero bits of a positive integer."""
        return (int(x) & -int(x)).bit_length() - 1

    trailing_zeros = _trailing_zeros_py
