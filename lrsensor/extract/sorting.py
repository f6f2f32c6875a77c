"""Order statistics for the kernels: the median of an array and its ``k``-th smallest value.

numpy's sort and median compile into several libraries of their own (quicksort, partition, selection), seconds
of the one-time compile for a few dozen to a few thousand values a frame. Neither needs a whole sort: a selection
(Hoare's, on a copy) finds the ``k``-th smallest value in linear time, and it is the sorted order's, so the medians
are numba's ``np.median`` to the bit and :func:`kth` is ``np.sort(a)[k]``.
"""

from __future__ import annotations

import numpy as np

from ._jit import empty, inline


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
def kth(a, k):  # type: ignore[no-untyped-def]
    """The ``k``-th smallest value of a 1-D array ``a`` without NaN (``np.sort(a)[k]``; :func:`select` on a copy)."""
    x = a.copy()
    return select(x, x.size, k)


@inline
def median(a):  # type: ignore[no-untyped-def]
    """``np.median`` of a non-empty 1-D array ``a`` as numba computes it (NaN ordered last): the middle value, or
    the mean of the two middle values, of its sorted order (:func:`select` on a copy of its values)."""
    n = a.size
    x = empty(n, np.float64)
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
