"""Neighbour refits: the stripes of two lasers close together, each fitted with the other subtracted.

At long range (walls beyond about 4 m) the two lasers' stripes come within a fit window of each other, and each
pulls the other's centre. The points whose column holds another laser's good point within ``max_dist`` rows are
refitted with that point's Gaussian subtracted, a few rounds (:data:`NEIGHBOUR_REFITS`), each round only where the
neighbour moved by more than :data:`NEIGHBOUR_TOL` since the point's last refit (:func:`refit_targets`), and only
where the neighbour's tail reaches :data:`NEIGHBOUR_TAIL` of the point's amplitude in the rows its centroid reads
or :data:`NEIGHBOUR_FLANK_TAIL` in its background flanks (:func:`read_reach`). The refits are the frame's fit
(:func:`.fit.fit_columns`) of those points with the neighbour's Gaussian subtracted (:func:`refit_columns`).

The constants here are the one definition that the compiled road and the reference
(:mod:`lrsensor.extract.reference`) both read.
"""

from __future__ import annotations

import math

import numpy as np

from ._jit import empty, full, inline, njit
from .columns import put_fit, take
from .fit import fit_columns


@inline
def rows_overlap(laser, v, good, n_lasers, max_dist):  # type: ignore[no-untyped-def]
    """Whether the row ranges of two lasers' ``good`` points come within ``max_dist`` of each other (else no point
    has an other-laser neighbour for :func:`refit_targets`: a cheap test that spares its dense arrays)."""
    lo = full(n_lasers, np.inf, np.float64)
    hi = full(n_lasers, -np.inf, np.float64)
    n = v.size
    t = 0
    while t < n:  # runs of one laser (the points are sorted by laser): each run's bounds kept in registers
        li = laser[t]
        a = np.inf
        b = -np.inf
        while t < n and laser[t] == li:
            x = v[t] if good[t] else np.nan
            a = min(a, x) if x == x else a
            b = max(b, x) if x == x else b
            t += 1
        lo[li] = min(lo[li], a)
        hi[li] = max(hi[li], b)
    for a in range(n_lasers):
        for b in range(n_lasers):
            if a != b and lo[a] <= hi[b] + max_dist and lo[b] <= hi[a] + max_dist:
                return True
    return False


#: A neighbour stripe is subtracted only where its Gaussian exceeds this fraction of the point's own amplitude
#: (at least 1 DN) somewhere in the rows the point's centroid reads (:func:`read_reach`, :func:`refit_targets`).
#: Below it, the refit moves centres by hundredths of a pixel at most, and not toward the truth (walls at 4.5-6 m
#: and the tank against no gate: at most 0.048 px, on few points, the gated output as close to the truth or
#: closer): a thin stripe (sigma 0.8 px) 11 rows away, as two lasers' stripes are on a wall at 5 m, adds less than
#: 1e-3 of its peak 7 rows away.
NEIGHBOUR_TAIL = 1e-2


#: The same threshold for the rows of the background flanks only (beyond the centroid's reach). There the tail
#: tilts the background line instead of adding to the peak: a contamination ``eps`` (fraction of the amplitude)
#: of one flank's mean moves a centroid of weight sigma ``s`` by about ``sqrt(2) eps s^2 / D`` pixels, ``D`` the
#: rows between the flanks' centres (10 or more). A tail of 5 % at the outer flank row averages less than 2.5 % over
#: the flank's 3 rows, so a centre moves by at most about 0.01 px (``s`` up to 2 px) and typically 0.003 px (``s``
#: 1.1 px): a tenth to a thirtieth of the centre's noise where the stripes meet (about 0.09 px on a wall at 5 m).
#: There the two stripes' tails reach 1-5 % of the other's peak at the outer flank rows, depending on each frame's
#: window (``refit_targets``).
NEIGHBOUR_FLANK_TAIL = 5e-2


#: ``log(NEIGHBOUR_TAIL / NEIGHBOUR_FLANK_TAIL)``: the flank rows' tail scaled to :data:`NEIGHBOUR_TAIL`'s test.
LOG_FLANK_TAIL = math.log(NEIGHBOUR_TAIL / NEIGHBOUR_FLANK_TAIL)


#: Rounds of refits of the points with another laser's stripe close by (:func:`.frame.fit_points`).
NEIGHBOUR_REFITS = 4


#: A point is refitted again only if its neighbour moved by more than this since its last refit: row and sigma
#: in pixels, amplitude relative (:func:`refit_targets`). A point's fit depends on nothing else that changes
#: between the rounds, and it moves by less than its neighbour does.
NEIGHBOUR_TOL = 1e-2


@inline
def read_reach(sig, sat, near, far, wide_sigma):  # type: ignore[no-untyped-def]
    """How many rows from its centre a point's fit reads, one row of re-centring included: ``(core, flanks)``, the
    Gaussian-weighted centroid out to 3 of its weight's sigma (``max(sig, 1.1)``; the weights beyond are below
    1.1 % of the peak's) and the log-parabola and background flanks out to ``near`` rows from the peak (a
    neighbour's Gaussian matters only there, and less in the flanks: :data:`NEIGHBOUR_FLANK_TAIL`); the whole
    window (``far``) for both for a saturated or wide profile (``sig`` above ``wide_sigma`` or not finite: their
    flanks move out with the plateau). The reference's is :func:`lrsensor.extract.reference_finish.read_reach`."""
    if sat or not sig <= wide_sigma:  # (True for a NaN sigma)
        return far, far
    return min(far, 1.0 + math.ceil(3.0 * max(sig, 1.1))), min(far, 1.0 + near)


@inline
def point_table(laser, cols, n_lasers, width):  # type: ignore[no-untyped-def]
    """The index of the point of each laser and column, (L, W) int32 (-1 = none; the points of
    :func:`lrsensor.extract.frame.locate_candidates` are one per laser and column)."""
    at = full((n_lasers, width), -1, np.int32)
    for t in range(laser.size):
        at[laser[t], cols[t]] = t
    return at


@njit
def refit_targets(laser, cols, v, amp, sig, sat, good, at, max_dist, read, look, last):  # type: ignore[no-untyped-def]
    """The points to refit with another laser's stripe subtracted in one round, and that stripe (the reference's is
    :func:`lrsensor.extract.reference_finish.neighbours` and its round's selection).

    A point's neighbour is the nearest ``good`` point of another laser in its column closer than ``max_dist``
    rows, kept only where its Gaussian exceeds :data:`NEIGHBOUR_TAIL` of the point's amplitude (at least
    1 DN) in the rows the point's fit reads (:func:`read_reach` of its sigma and saturation, ``read`` = ``(near,
    far, wide_sigma)``). A point is picked when its neighbour's
    row, amplitude or sigma differ from ``last`` (3, N) (the neighbour of its previous refit, NaN = none yet) by
    more than :data:`NEIGHBOUR_TOL`; ``last`` is updated there. Only the points in the columns ``look`` (K,)
    (sorted) are looked at: a neighbour can change only in the columns of the last round's refits.

    Args:
        laser, cols, v, amp, sig, sat, good: (N,) per point: laser, column, row (NaN = no fit), amplitude (DN),
            sigma (px, NaN = 1), saturated, and whether it can be a neighbour.
        at: (L, W) the point of each laser and column (:func:`point_table`).

    Returns:
        ``(idx, nb_v, nb_a, nb_s)``: the picked points (M,), in the order of the points, and their neighbours'
        row, amplitude and sigma (M,).
    """
    near, far, wide_sigma = read
    n_lasers = at.shape[0]
    n = min(v.size, n_lasers * look.size)
    cand = empty(n, np.int64)
    nbj = empty(n, np.int64)
    arg = empty(n, np.float64)  # the log of the neighbour's Gaussian at the nearest row read, the flanks' scaled
    m = 0
    for li in range(n_lasers):  # laser by laser, columns in order: the points' order
        for c in look:
            t = at[li, c]
            if t < 0 or not math.isfinite(v[t]):
                continue
            best = max_dist
            jb = -1
            for other in range(n_lasers):
                j = at[other, c]
                if other == li or j < 0 or not good[j]:
                    continue
                dist = abs(v[j] - v[t])
                if dist < best:  # (False for a NaN row)
                    best = dist
                    jb = j
            if jb >= 0:
                cand[m] = t
                nbj[m] = jb
                core, flanks = read_reach(sig[t], sat[t], near, far, wide_sigma)
                s_j = sig[jb] if math.isfinite(sig[jb]) else 1.0
                g_c = max(best - core, 0.0) / s_j
                g_f = max(best - flanks, 0.0) / s_j
                arg[m] = max(-0.5 * g_c * g_c, -0.5 * g_f * g_f + LOG_FLANK_TAIL)
                m += 1
    # the tail's test (amp_j e^arg > NEIGHBOUR_TAIL max(amp_t, 1)) fails wherever e^arg is below NEIGHBOUR_TAIL over
    # the largest neighbour amplitude (a margin of 1e-6 for rounding): the exponential only where it can pass (at 5 m
    # the tails' logarithms are about -14: few points)
    amp_top = 0.0
    for i in range(m):
        amp_top = max(amp_top, amp[nbj[i]])
    lowest = math.log(NEIGHBOUR_TAIL / amp_top) - 1e-6 if amp_top > 0.0 else np.inf
    idx = empty(m, np.int64)
    nb_v = empty(m, np.float64)
    nb_a = empty(m, np.float64)
    nb_s = empty(m, np.float64)
    k = 0
    for i in range(m):
        t = cand[i]
        j = nbj[i]
        if not (arg[i] >= lowest and amp[j] * math.exp(arg[i]) > NEIGHBOUR_TAIL * max(amp[t], 1.0)):
            continue
        s_j = sig[j] if math.isfinite(sig[j]) else 1.0
        same = (
            abs(v[j] - last[0, t]) <= NEIGHBOUR_TOL
            and abs(amp[j] - last[1, t]) <= NEIGHBOUR_TOL * max(abs(last[1, t]), 1.0)
            and abs(s_j - last[2, t]) <= NEIGHBOUR_TOL
        )
        if same:
            continue
        last[0, t] = v[j]
        last[1, t] = amp[j]
        last[2, t] = s_j
        idx[k] = t
        nb_v[k] = v[j]
        nb_a[k] = amp[j]
        nb_s[k] = s_j
        k += 1
    return idx[:k], nb_v[:k], nb_a[:k], nb_s[:k]


@inline
def refit_columns(image, cols, rows, idx, nb_v, nb_a, nb_s, half, sigma_hint, s, max_fwhm, res):  # type: ignore[no-untyped-def]
    """Fit the points ``idx`` (M,) again with the other laser's stripe subtracted (its row, amplitude and sigma
    ``nb_v, nb_a, nb_s`` (M,)) and store the results in place into ``res``, the
    :class:`~lrsensor.extract.fit.Fits` of every point (``cols``, ``rows``, ``max_fwhm`` (N,) as for
    :func:`~lrsensor.extract.fit.fit_columns`, with its ``half``, ``sigma_hint`` and settings ``s``)."""
    c_i, r_i, mfw_i = take(cols, idx), take(rows, idx), take(max_fwhm, idx)
    new = fit_columns(image, c_i, r_i, half, sigma_hint, s, nb_v, nb_a, nb_s, mfw_i)
    for i in range(idx.size):
        put_fit(res, new, i, idx[i])
