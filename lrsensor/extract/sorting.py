"""Sorting for the kernels' medians: a sorted copy and the median of an array (numba-compiled when inlined).

numpy's sort and median compile into several libraries of their own (quicksort, partition, selection), seconds
of the one-time compile for a few dozen to a few thousand values a frame; a shell sort compiles in a fraction of
that and orders values as ``np.sort`` does (NaN last), so the medians are numba's ``np.median`` to the bit.
"""

from __future__ import annotations

from ._jit import inline

#: Gaps of the shell sort (Ciura's), largest first.
GAPS = (701, 301, 132, 57, 23, 10, 4, 1)


@inline
def sorted_copy(a):  # type: ignore[no-untyped-def]
    """A sorted copy of the 1-D array ``a``, NaN last (as ``np.sort``)."""
    out = a.copy()
    n = out.size
    for gap in GAPS:
        for i in range(gap, n):
            x = out[i]
            j = i
            while j >= gap and (out[j - gap] > x or (out[j - gap] != out[j - gap] and x == x)):
                out[j] = out[j - gap]
                j -= gap
            out[j] = x
    return out


@inline
def median(a):  # type: ignore[no-untyped-def]
    """``np.median`` of a non-empty 1-D array ``a`` as numba computes it (NaN ordered last)."""
    srt = sorted_copy(a)
    h = srt.size // 2
    return srt[h] if srt.size % 2 else (srt[h - 1] + srt[h]) / 2
