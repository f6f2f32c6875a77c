"""Sorting for the kernels' medians: a sorted copy and the median of an array (numba-compiled when inlined).

numpy's sort and median compile into several libraries of their own (quicksort, partition, selection), seconds
of the one-time compile for a few dozen to a few thousand values a frame; a shell sort compiles in a fraction of
that and orders values as ``np.sort`` does (NaN last). The median needs no whole sort: a selection (Hoare's, on a
copy) finds its middle values in linear time (a shell sort of the smoothing's few thousand values took about as
long as the rest of the smoothing), and they are the sorted order's, so the medians are numba's ``np.median`` to
the bit.
"""

from __future__ import annotations

import numpy as np

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
def select(x, n, k):  # type: ignore[no-untyped-def]
    """The ``k``-th smallest of ``x[:n]`` (no NaN), reordering ``x[:n]`` so that the values before it are at most it
    and those after it at least it (Hoare's selection as Wirth writes it: linear time on average)."""
    lo = 0
    hi = n - 1
    while lo < hi:
        pivot = x[k]
        i = lo
        j = hi
        while i <= j:
            while x[i] < pivot:
                i += 1
            while pivot < x[j]:
                j -= 1
            if i <= j:
                x[i], x[j] = x[j], x[i]
                i += 1
                j -= 1
        if j < k:
            lo = i
        if k < i:
            hi = j
    return x[k]


@inline
def median(a):  # type: ignore[no-untyped-def]
    """``np.median`` of a non-empty 1-D array ``a`` as numba computes it (NaN ordered last): the middle value, or
    the mean of the two middle values, of its sorted order (:func:`select` on a copy of its values)."""
    n = a.size
    x = np.empty(n)
    m = 0
    for i in range(n):  # NaN last: the values first
        if a[i] == a[i]:
            x[m] = a[i]
            m += 1
    h = n // 2
    if h >= m:  # the middle of the sorted order is (or takes) a NaN
        return np.nan
    upper = select(x, m, h)
    if n % 2:
        return upper
    lower = x[0]
    for i in range(1, h):  # the largest before the h-th
        lower = max(lower, x[i])
    return (lower + upper) / 2
