"""The reference's continuity (numpy): step 2 of :func:`lrsensor.extract.reference.extract_frame`, what
:func:`lrsensor.extract.chains.select_candidates` computes.

:func:`_pick` runs the steps in order: :func:`_merge_plateaus` (maxima of one column closer than 3 rows merged),
:func:`_top_k` (the ``k`` strongest candidates per column), :func:`_chains` (candidates of nearby columns linked
into chains, never across two lasers' blocks of columns), then per column the candidate on the strongest chain
long enough. Columns are the virtual detection columns ``laser * width_d + column_d``; rows are full-resolution.
The names keep the underscore they had in :mod:`lrsensor.extract.reference`.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .settings import Settings

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


def _merge_plateaus(u: IntArray, v: IntArray, a: FloatArray) -> tuple[IntArray, FloatArray, FloatArray]:
    """Sort by column then row and merge maxima of one column closer than 3 rows (plateaus) into their mean."""
    order = np.argsort(u, kind="stable")  # rows stay ascending within a column (findNonZero is row-major)
    u, v, a = u[order], v[order], a[order]
    new = np.ones(u.size, bool)
    new[1:] = (u[1:] != u[:-1]) | (v[1:] - v[:-1] > 3)
    if bool(new.all()):
        return u, v.astype(np.float64), a
    gid = np.cumsum(new) - 1
    cnt = np.bincount(gid)
    vm = np.bincount(gid, weights=v.astype(np.float64)) / cnt
    am = np.zeros(cnt.size)
    np.maximum.at(am, gid, a)
    return u[new], vm, am


def _top_k(u: IntArray, v: FloatArray, a: FloatArray, n_cols: int, k: int) -> tuple[FloatArray, FloatArray]:
    """(n_cols, k) rows and strengths of the k strongest candidates per column (NaN / 0 where fewer)."""
    if k > 1:
        order = np.lexsort((-a, u))
        u, v, a = u[order], v[order], a[order]
    first = np.searchsorted(u, u, side="left")
    rank = np.arange(u.size) - first
    keep = rank < k
    V = np.full((n_cols, k), np.nan)
    A = np.zeros((n_cols, k))
    V[u[keep], rank[keep]] = v[keep]
    A[u[keep], rank[keep]] = a[keep]
    return V, A


def _chains(
    V: FloatArray, A: FloatArray, max_jump: float, block: int, max_gap: int = 3
) -> tuple[NDArray[Any], NDArray[Any], NDArray[Any]]:
    """Link candidates of nearby columns into chains (stripe pieces).

    A node (column c, candidate i) is linked to the mutually nearest candidate of column c + 1 when their rows
    differ by at most ``max_jump``; nodes left without a partner are then tried across gaps of up to
    ``max_gap - 1`` empty columns (dim or occluded columns do not cut a stripe). Columns in different blocks
    of ``block`` columns (one block per laser) are never linked.

    Returns per node (n_cols * k,): chain id, chain length (nodes) and chain strength (sum of strengths).
    """
    n_cols, k = V.shape
    n = n_cols * k
    if k == 1:
        cols = np.flatnonzero(np.isfinite(V[:, 0]))
        if cols.size == 0:
            return np.arange(n), np.ones(n, np.int64), A.ravel().copy()
        v = V[cols, 0]
        link = (np.diff(cols) <= max_gap) & (np.abs(np.diff(v)) <= max_jump) & (cols[1:] // block == cols[:-1] // block)
        rid = np.cumsum(np.concatenate([[True], ~link])) - 1
        root = np.arange(n)
        root[cols] = cols[np.flatnonzero(np.concatenate([[True], ~link]))][rid]
        length = np.bincount(root, minlength=n)[root]
        strength = np.bincount(root, weights=A.ravel(), minlength=n)[root]
        return root, length, strength
    prev = np.arange(n)
    has_next = np.zeros((n_cols, k), bool)
    has_prev = np.zeros((n_cols, k), bool)
    ii = np.arange(k)[None, :]
    for lag in range(1, max_gap + 1):
        if n_cols <= lag:
            break
        a_ok = ~has_next[:-lag] & np.isfinite(V[:-lag])
        b_ok = ~has_prev[lag:] & np.isfinite(V[lag:])
        D = np.abs(V[:-lag, :, None] - V[lag:, None, :])
        D = np.where(a_ok[:, :, None] & b_ok[:, None, :], D, np.inf)
        j_best = np.argmin(D, axis=2)  # for node (c, i) the nearest in c + lag
        i_best = np.argmin(D, axis=1)  # for node (c + lag, j) the nearest in c
        dmin = np.take_along_axis(D, j_best[:, :, None], axis=2)[:, :, 0]
        mutual = np.take_along_axis(i_best, j_best, axis=1) == ii
        c = np.arange(n_cols - lag)
        same_block = (c // block) == ((c + lag) // block)
        link = mutual & (dmin <= max_jump) & same_block[:, None]
        if not np.any(link):
            continue
        cc = c[:, None]
        src = (cc * k + ii)[link]
        dst = ((cc + lag) * k + j_best)[link]
        prev[dst] = src
        has_next.reshape(-1)[src] = True
        has_prev.reshape(-1)[dst] = True
    root = prev
    for _ in range(math.ceil(math.log2(max(n_cols, 2))) + 1):
        nxt = root[root]
        if np.array_equal(nxt, root):
            break
        root = nxt
    length = np.bincount(root, minlength=n)[root]
    strength = np.bincount(root, weights=A.ravel(), minlength=n)[root]
    return root, length, strength


def _pick(
    U: IntArray,
    Vr: IntArray,
    Ar: FloatArray,
    n_cols: int,
    s: Settings,
    block: int,
    jump: float,
    min_run: int,
) -> tuple[IntArray, FloatArray, IntArray, IntArray]:
    """Candidate selection: plateaus, k strongest, chains, pick (as ``chains.select_candidates``)."""
    U, Vf, Ar = _merge_plateaus(U, Vr, Ar)
    k = int(min(s.max_candidates, np.bincount(U).max()))
    V, A = _top_k(U, Vf, Ar, n_cols, k)
    root, length, strength = _chains(V, A, jump, block)
    score = np.where(np.isfinite(V.ravel()) & (length >= min_run), strength, -np.inf).reshape(n_cols, k)
    pick = np.argmax(score, axis=1) if k > 1 else np.zeros(n_cols, np.int64)
    col_v = np.flatnonzero(np.isfinite(score[np.arange(n_cols), pick]))
    node = col_v * k + pick[col_v]
    return col_v, V.ravel()[node], root[node], length[node]
