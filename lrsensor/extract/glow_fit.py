"""Turbid water: the joint stripe-and-glow fit of one column's profile (:func:`fit_one`) and its rounds
(:func:`fit_rounds`), for the glow stage (:mod:`lrsensor.extract.glow`, which documents the model, the choices and
their measurements).

A fit (:func:`fit_into`) solves the model's linear parameters at a start, then takes Gauss-Newton steps in all of
them; the rounds fit the points beside another laser's stripe again with the other stripe where the previous round
put it, only where it moved enough to matter: by more than :data:`ROUND_TOL_PX` times how much of it reaches the
fit's window (:func:`reach_weight`).
"""

from __future__ import annotations

import math

import numpy as np

from ._jit import callee, empty, full, inline, njit, zeros

#: Gauss-Newton steps after the linear start, and the largest step of the centre and of sigma per iteration, px.
ITERATIONS = 4
MAX_STEP_PX = 1.0
#: ... the steps stop where the centre's and sigma's both fall to this, px.
STOP_PX = 1e-3
#: Rounds of the fits: the first with the common fit's neighbours, each next one with the previous round's.
ROUNDS = 4
#: ... a point is refitted in the next round only where the other stripe (its centre or sigma) moved by more than
#: this, px.
ROUND_TOL_PX = 0.01
#: The joint fit is kept within this distance of the common fit's centre, px.
MAX_MOVE_PX = 4.0
#: Linear parameters of the joint fit: background level and slope, stripe, glow step, glow ramp, neighbour.
N_LIN = 8
#: Phi(x) = 1 - phi(x) t P(t), t = 1 / (1 + p x), x >= 0 (Abramowitz-Stegun 26.2.17, |error| < 7.5e-8).
_AS_P = 0.2316419
_INV_SQRT_2PI = 0.3989422804014327
#: A fit with the glow is kept where the glow two sigmas outward of its edge exceeds this share of the stripe's
#: peak (the glow test's share, :data:`lrsensor.extract.glow.TRIGGER_FRAC`).
GLOW_MIN_FRAC = 0.05


@inline
def upper_tail(a, gauss):  # type: ignore[no-untyped-def]
    """``1 - Phi(a)`` for ``a >= 0`` given ``gauss = exp(-a^2 / 2)`` (Abramowitz-Stegun 26.2.17)."""
    t = 1.0 / (1.0 + _AS_P * a)
    poly = t * (0.319381530 + t * (-0.356563782 + t * (1.781477937 + t * (-1.821255978 + t * 1.330274429))))
    return gauss * _INV_SQRT_2PI * poly


@inline
def sheet_edge(t, u, f, ph, sg, d, kap):  # type: ignore[no-untyped-def]
    """The sheet's glow at ``t`` px outward of its edge, blurred by a Gaussian of ``sg`` px, and its derivatives in
    ``t`` and ``sg``: ``(B, dB/dt, dB/dsg)``; 1 at the edge before the blur (scalars or arrays alike: the reference
    calls it on arrays). ``u = t / sg``, ``f = Phi(u)``, ``ph = phi(u)`` (the fit has them); ``d``: the edge's rows
    from the sheet's vanishing row (> 0); ``kap``: the attenuation's growth (:func:`.glow.glow_refit`).

    Seen ``t`` rows outward of the stripe, the sheet lies at range ``x_w d / (d + t)`` (``x_w`` the wall's), and its
    single-scatter radiance grows only by the shorter path in and out (the sheet's area a pixel sees, the fan's
    ``1 / r`` and the light's ``1 / R^2`` cancel): ``h(t) = exp(kap t / (d + t))``, ``kap = 2 alpha s x_w`` (``alpha``
    the water's attenuation, ``s`` the path's obliqueness). Blurred: ``h`` expanded to second order about
    ``max(t, 0)`` under the Gaussian over ``t' >= 0`` (within 1.4 % of the edge's value at 3 m with 4 px of blur,
    0.1 % with 1.5 px). ``kap = 0``: the blurred step ``Phi(u)`` of the step model."""
    te = np.maximum(t, 0.0)
    pos = np.sign(te)  # 1 outward of the edge (h follows t), 0 inward (h expanded at the edge)
    dt = t - te
    e = 1.0 / (d + te)
    g1 = kap * d * e * e
    g2 = -2.0 * g1 * e
    g3 = -3.0 * g2 * e
    h = np.exp(kap * te * e)
    h1 = h * g1
    h2 = h * (g1 * g1 + g2)
    h3 = h * (g1 * g1 * g1 + 3.0 * g1 * g2 + g3)
    m1 = sg * ph
    m2 = sg * sg * (f - u * ph)
    mm1 = m1 + dt * f
    mm2 = m2 + dt * (2.0 * m1 + dt * f)
    b = h * f + h1 * mm1 + 0.5 * h2 * mm2
    # in t: the moments' own change, and outward h's
    m0_t = ph / sg
    m1_t = -u * ph
    m2_t = sg * u * u * ph
    inw = 1.0 - pos
    mm1_t = m1_t + inw * f + dt * m0_t
    mm2_t = m2_t + 2.0 * inw * (m1 + dt * f) + dt * (2.0 * m1_t + dt * m0_t)
    b_t = h * m0_t + h1 * mm1_t + 0.5 * h2 * mm2_t + pos * (h1 * f + h2 * mm1 + 0.5 * h3 * mm2)
    # in sg
    m0_s = -u * ph / sg
    m1_s = ph * (1.0 + u * u)
    m2_s = 2.0 * sg * (f - u * ph) - sg * u * u * u * ph
    b_s = h * m0_s + h1 * (m1_s + dt * m0_s) + 0.5 * h2 * (m2_s + dt * (2.0 * m1_s + dt * m0_s))
    return b, b_t, b_s


@inline
def _dot(x, y, n):  # type: ignore[no-untyped-def]
    """``sum(x[:n] * y[:n])`` in four sums (a single one would wait on every add)."""
    s0 = 0.0
    s1 = 0.0
    s2 = 0.0
    s3 = 0.0
    i = 0
    while i + 4 <= n:
        s0 += x[i] * y[i]
        s1 += x[i + 1] * y[i + 1]
        s2 += x[i + 2] * y[i + 2]
        s3 += x[i + 3] * y[i + 3]
        i += 4
    while i < n:
        s0 += x[i] * y[i]
        i += 1
    return (s0 + s1) + (s2 + s3)


@inline
def _gauss_rows(out, q0, k_rows, c, inv_s):  # type: ignore[no-untyped-def]
    """``out[i] = exp(-((q0 + i - c) inv_s)^2 / 2)`` for ``i < k_rows``: from the row nearest ``c`` outward, each row
    the last times the ratio of neighbouring rows, which changes by ``exp(-inv_s^2)`` a row (three exponentials
    instead of one a row, which were half a fit's time; relative error ~1e-14; rows far out may underflow to 0)."""
    m = min(max(int(math.floor(c - q0 + 0.5)), 0), k_rows - 1)  # noqa: RUF046 (numba: floor of a float is a float)
    z = (q0 + m - c) * inv_s
    g0 = math.exp(-0.5 * z * z)
    out[m] = g0
    h2 = 0.5 * inv_s * inv_s
    k2 = math.exp(-2.0 * h2)
    g = g0
    r = math.exp(-z * inv_s - h2)
    for i in range(m + 1, k_rows):
        g *= r
        out[i] = g
        r *= k2
    g = g0
    r = math.exp(z * inv_s - h2)
    for i in range(m - 1, -1, -1):
        g *= r
        out[i] = g
        r *= k2


@inline
def reach_weight(nb_c, nb_s, hw):  # type: ignore[no-untyped-def]
    """How much of another stripe (centre ``nb_c`` rows from the window's middle row, sigma ``nb_s``) reaches a fit's
    window of ``hw`` rows either side: its Gaussian at the window's row nearest its centre (1 inside the window).
    A later round refits a point where its other stripe moved by more than :data:`ROUND_TOL_PX` times this: a stripe
    whose tail alone reaches the window moves the fit by a fraction of its own move (at 2 m with 4 px of blur the
    stripes are 28 px apart, the other stripe's centre 2-3 sigmas beyond the window)."""
    e = max(abs(nb_c) - hw, 0.0) / nb_s
    return math.exp(-0.5 * e * e)


@callee
def _solve(M, b, k):  # type: ignore[no-untyped-def]
    """Solve ``M[:k, :k] x = b[:k]`` in place for a symmetric positive definite ``M`` (normal equations; Cholesky,
    half the work of an elimination with pivots: the solves were a third of a fit's time); False when singular (a
    pivot at or below 1e-12, or below 1e-13 of its diagonal entry: a column the others nearly span)."""
    for j in range(k):
        d = M[j, j]
        for p in range(j):
            d -= M[j, p] * M[j, p]
        if not (d > 1e-12 and d > 1e-13 * M[j, j]):
            return False
        d = math.sqrt(d)
        M[j, j] = d
        inv = 1.0 / d
        for i in range(j + 1, k):
            acc = M[i, j]
            for p in range(j):
                acc -= M[i, p] * M[j, p]
            M[i, j] = acc * inv
    for i in range(k):  # L y = b
        acc = b[i]
        for p in range(i):
            acc -= M[i, p] * b[p]
        b[i] = acc / M[i, i]
    for i in range(k - 1, -1, -1):  # L^T x = y
        acc = b[i]
        for p in range(i + 1, k):
            acc -= M[p, i] * b[p]
        b[i] = acc / M[i, i]
    return True


@njit
def fit_one(  # type: ignore[no-untyped-def]
    y, q, side, c, sg, nb_c, nb_s, nb_side, glow_on, ramp, min_sig, max_sig, sat_dn, d_rc=1.0, kap_k=0.0, nb_d=1.0,
    nb_kk=0.0, rho=0.0,
):
    """The joint fit of one profile ``y`` (K,) at rows ``q`` (K,) (relative to the window's middle row) from the
    centre ``c`` and width ``sg``; ``nb_c``, ``nb_s``: another stripe's centre and sigma (NaN: none), ``nb_side``
    the side of its glow (0: none shows); ``glow_on``: this stripe's glow in the model (False: a stripe beside
    another one, no glow); ``ramp``: the glow's linear and quadratic growth outward in the model. Returns ``(c,
    sigma, A, g, ok, rss, dof)``: the fit, its residual sum of squares (at the last Gauss-Newton step's start) and
    degrees of freedom. Samples at or above ``sat_dn`` (clipped) are left out. ``d_rc``, ``kap_k``: the window's
    middle row's distance from the sheet's vanishing row (px, towards the glow) and the attenuation's growth times
    the edge's distance (:func:`sheet_edge`'s ``kap d``, px; 0: the glow a plain blurred step); ``nb_d``, ``nb_kk``:
    the same for the other stripe's glow (its edge's distance from its sheet's vanishing row, px, and its ``kap d``);
    ``rho``: where positive, the glow's step held at that share of the stripe's amplitude (no parameter of its own,
    no glow test: ``g = rho A``), where negative, free and untested (the caller pools the steps); 0: free, tested."""
    kk = N_LIN + 2
    return fit_into(
        y,
        q,
        side,
        c,
        sg,
        nb_c,
        nb_s,
        nb_side,
        glow_on,
        ramp,
        min_sig,
        max_sig,
        sat_dn,
        empty((kk, kk), np.float64),
        empty(kk, np.float64),
        empty(kk, np.float64),
        empty(N_LIN, np.float64),
        empty(kk, np.int64),
        empty((N_LIN + 5, y.size), np.float64),
        False,
        d_rc,
        kap_k,
        nb_d,
        nb_kk,
        rho,
    )


@callee
def fit_into(  # type: ignore[no-untyped-def]
    y, q, side, c, sg, nb_c, nb_s, nb_side, glow_on, ramp, min_sig, max_sig, sat_dn, M, b, xr, lin, par, work, warm,
    d_rc, kap_k, nb_d, nb_kk, rho,
):
    """:func:`fit_one` with its work arrays given (``M`` (N_LIN + 2, N_LIN + 2), ``b``, ``xr`` (N_LIN + 2,), ``lin``
    (N_LIN,), ``par`` (N_LIN + 2,) int64, ``work`` (N_LIN + 5, >= K): the Jacobian's columns, the residual and the two
    Gaussians along the rows): the fits of a frame allocate nothing per point. The rows ``q`` are one apart.
    ``warm``: ``lin`` holds the linear parameters of a fit of this model at ``c``, ``sg`` (a round's earlier fit, its
    other stripe moved a little): one Gauss-Newton step from there, no linear start.

    First the linear parameters alone at the start, then at most :data:`ITERATIONS` Gauss-Newton steps in all of
    them, fewer where the centre's and sigma's step falls to :data:`STOP_PX`; each pass builds the normal equations
    row by row, in the parameters the profile's model has, and sums the squared residuals at its start (the last
    pass's sum is the fit's: a converged step changes it by its square, and a pass of its own would cost as much as
    a step). With ``kap_k > 0`` the glow's column is the sheet's shape (:func:`sheet_edge`) at the edge's distance
    from the vanishing row at each step (its change with the centre left out of the Jacobian); with ``nb_kk > 0`` the
    other stripe's glow too (its edge ``nb_d`` px from its vanishing row: at 3 m its glow, outward of it, grows within
    this window as fast as this stripe's)."""
    k_rows = y.size
    held = glow_on and rho > 0.0  # the glow's step held at rho times the stripe's amplitude: no parameter of its own
    has_nb = math.isfinite(nb_c)
    nb_glow = has_nb and nb_side != 0.0
    # the active parameters, linear first, then the centre and sigma: the normal equations in them alone (the
    # reference's identity rows for the others decouple exactly)
    n_lin = 0
    for a in range(N_LIN):
        keep = (a != 3 or (glow_on and not held)) and (a not in (4, 5) or (glow_on and ramp)) and (a != 6 or has_nb)
        if not keep or (a == 7 and not nb_glow):
            continue
        par[n_lin] = a
        n_lin += 1
    # (a held width, min_sig == max_sig, is no parameter: the centre's step is then the one with the width fixed)
    free_s = min_sig < max_sig
    par[n_lin] = N_LIN
    par[n_lin + 1] = N_LIN + 1
    kk = n_lin + 2 if free_s else n_lin + 1
    for a in range(N_LIN + 2):
        xr[a] = 0.0
    if not warm:
        for a in range(N_LIN):
            lin[a] = 0.0
    if held:
        lin[3] = 0.0  # (the step is rho lin[2], carried in the stripe's column)
    jac = work[: N_LIN + 2]
    res = work[N_LIN + 2]
    g_own = work[N_LIN + 3]
    g_nb = work[N_LIN + 4]
    if has_nb:  # the other stripe's Gaussian: held in the fit
        _gauss_rows(g_nb, q[0], k_rows, nb_c, 1.0 / nb_s)
    nb_de = max(nb_d, 1.0)
    nb_kap = nb_kk / nb_de
    rss = np.nan
    dof = -kk
    for i in range(k_rows):
        dof += y[i] < sat_dn
    for it in range(1 if warm else 0, 2 if warm else ITERATIONS + 1):
        full = it > 0
        m_ = kk if full else n_lin
        r2 = 0.0
        inv_sg = 1.0 / sg
        n_s = 0  # the samples taken (unclipped)
        _gauss_rows(g_own, q[0], k_rows, c, inv_sg)
        d_e = max(d_rc + side * c, 1.0)
        kap = kap_k / d_e
        b_t = 0.0
        b_s = 0.0
        for i in range(k_rows):
            if y[i] >= sat_dn:
                continue
            z = (q[i] - c) * inv_sg
            gz = g_own[i]
            xr[0] = 1.0
            xr[1] = q[i]
            xr[2] = gz
            f = 0.0
            ph = 0.0
            rmp = 0.0
            if glow_on:
                u = side * z
                tail = upper_tail(abs(u), gz)
                f = 1.0 - tail if u >= 0.0 else tail
                ph = gz * _INV_SQRT_2PI
                xr[3] = f
                if kap_k > 0.0:
                    xr[3], b_t, b_s = sheet_edge(u * sg, u, f, ph, sg, d_e, kap)
                if ramp:
                    rmp = sg * (u * f + ph)
                    xr[4] = rmp
                    xr[5] = sg * sg * ((u * u + 1.0) * f + u * ph)
                if held:
                    xr[2] = gz + rho * xr[3]
            if has_nb:
                gd = g_nb[i]
                xr[6] = gd
                if nb_glow:
                    ud = nb_side * (q[i] - nb_c) / nb_s
                    td = upper_tail(abs(ud), gd)
                    fd = 1.0 - td if ud >= 0.0 else td
                    if nb_kk > 0.0:  # (the other stripe is held: its shape's derivatives are not needed)
                        fd = sheet_edge(ud * nb_s, ud, fd, gd * _INV_SQRT_2PI, nb_s, nb_de, nb_kap)[0]
                    xr[7] = fd
            r = y[i]
            if full:
                for j in range(N_LIN):
                    r -= xr[j] * lin[j]
                r2 += r * r
                g3 = rho * lin[2] if held else lin[3]
                if kap_k > 0.0 and glow_on:  # the sheet's shape (sheet_edge) in t = side (q - c)
                    xr[N_LIN] = lin[2] * gz * z * inv_sg - side * (g3 * b_t + lin[4] * f + 2.0 * lin[5] * rmp)
                    xr[N_LIN + 1] = lin[2] * gz * z * z * inv_sg + g3 * b_s + lin[4] * ph + 2.0 * lin[5] * sg * f
                else:
                    xr[N_LIN] = (lin[2] * gz * z - g3 * ph * side) * inv_sg - side * (lin[4] * f + 2.0 * lin[5] * rmp)
                    xr[N_LIN + 1] = (
                        (lin[2] * gz * z * z - g3 * ph * side * z) * inv_sg + lin[4] * ph + 2.0 * lin[5] * sg * f
                    )
            for a in range(m_):
                jac[a, n_s] = xr[par[a]]
            res[n_s] = r
            n_s += 1
        # the normal equations from the Jacobian's columns (row by row into the sums would chain every sum through
        # memory: several times slower)
        for a in range(m_):
            ja = jac[a]
            b[a] = _dot(ja, res, n_s)
            for j in range(a, m_):
                M[a, j] = M[j, a] = _dot(ja, jac[j], n_s)
        if not _solve(M, b, m_):
            return c, sg, lin[2], lin[3], False, np.nan, np.nan
        if not full:
            for a in range(n_lin):
                lin[par[a]] = b[a]
            continue
        rss = r2
        for a in range(n_lin):
            lin[par[a]] += b[a]
        dc = min(max(b[n_lin], -MAX_STEP_PX), MAX_STEP_PX)
        ds = min(max(sg + min(max(b[n_lin + 1], -MAX_STEP_PX), MAX_STEP_PX), min_sig), max_sig) - sg if free_s else 0.0
        c += dc
        sg += ds
        if abs(dc) <= STOP_PX and abs(ds) <= STOP_PX:
            break
    x2 = 2.0 * sg  # the glow two sigmas outward of the edge (where its step is complete) is a glow
    g_out = lin[3] + lin[4] * x2 + lin[5] * x2 * x2
    # (a held step is the stripe's glow by construction: no test of its own)
    # (rho < 0: the test left to the caller, which pools the stripe's steps)
    ok = math.isfinite(c) and lin[2] > 0.0 and (not glow_on or rho != 0.0 or g_out > GLOW_MIN_FRAC * lin[2])
    g_fit = rho * lin[2] if held else lin[3]
    return c, sg, lin[2], g_fit, ok, rss, float(dof)


@callee
def neighbour(t, at, cols, laser, nb_ok, v_nb, s_nb, reach):  # type: ignore[no-untyped-def]
    """The nearest point of another laser (``nb_ok``: an unclipped fit) in the column of point ``t`` whose stripe
    (centre ``v_nb``, sigma ``s_nb``) reaches within ``reach`` rows of the point's centre ``v_nb[t]`` by 3 sigma;
    -1: none."""
    col = cols[t]
    nb = -1
    best = np.inf
    for li in range(at.shape[0]):
        j = at[li, col]
        if li == laser[t] or j < 0 or not nb_ok[j]:
            continue
        dj = abs(v_nb[j] - v_nb[t])
        if dj < reach + 3.0 * s_nb[j] and dj < best:
            best = dj
            nb = j
    return nb


@callee
def fit_rounds(  # type: ignore[no-untyped-def]
    image,
    cols,
    laser,
    at,
    vv,
    sig,
    v_init,
    s_init,
    nb_ok,
    nb0,
    fit_me,
    glowing,
    side,
    rc,
    hw,
    reach,
    sg0,
    lo_sig,
    max_sig,
    sat_dn,
    ramp,
    n_rounds,
    d_rc,
    kap_k,
    rho,
):
    """The joint fits of the points ``fit_me`` (:func:`.glow.glow_refit`'s arrays; ``reach`` (N,): the rows within
    which another stripe is looked for), with the glow's ramp or without: ``n_rounds`` rounds (at most
    :data:`ROUNDS`), the first with the other stripes at ``v_init``, ``s_init`` (N,), each next one with the previous
    round's, at the points whose other stripe (its centre or sigma) moved by more than :data:`ROUND_TOL_PX` times
    how much of it reaches the window (:func:`reach_weight`; a stripe out of the window in both rounds leaves the same
    fit: at 2 m, 9 of 10 refits were). A later round refits a point without a glow (a stripe beside another one) by
    one Gauss-Newton step from its last fit where its model stays (the other stripe moved by hundredths of a px: the
    step lands within the rounds' tolerance of a whole refit, a third of its cost); a glowing point is refitted whole
    from the common fit (where the glow's model is poor, far walls with much blur, its fits do not converge in
    :data:`ITERATIONS` steps, and continuing them moved the single columns' median by 0.05-0.1 px there).
    ``d_rc``, ``kap_k`` (N,): each point's window's distance from its sheet's vanishing row and its glow's growth
    (:func:`fit_one`).
    Returns ``(centre_row, sigma, fitted, rss, dof, steps)``: (N,) each and the fitted stripe amplitudes, glow
    steps and the log-determinants of the fits' last normal matrices (3, N; :func:`.water.retell` scores with them)."""
    n = cols.size
    v_out = v_init.copy()
    s_out = s_init.copy()
    fitted = zeros(n, np.bool_)
    last_c = full(n, np.nan, np.float64)  # the other stripe (centre, sigma, its glow's side) in each point's last fit
    last_s = full(n, np.nan, np.float64)
    last_side = zeros(n, np.float64)
    lin_t = zeros((n, N_LIN), np.float64)  # each point's last fit's linear parameters
    rss = full(n, np.nan, np.float64)
    dof = full(n, np.nan, np.float64)
    steps = zeros((3, n), np.float64)
    k_max = 1  # the longest window's rows
    for t in range(n):
        k_max = max(k_max, 2 * hw[t] + 1)
    y = empty(k_max, np.float64)
    q = empty(k_max, np.float64)
    kk = N_LIN + 2
    M = empty((kk, kk), np.float64)
    b = empty(kk, np.float64)
    xr = empty(kk, np.float64)
    lin = empty(N_LIN, np.float64)
    par = empty(kk, np.int64)
    work = empty((N_LIN + 5, k_max), np.float64)
    for rnd in range(n_rounds):
        v1 = v_out.copy()
        s1 = s_out.copy()
        taken = False
        for t in range(n):
            if not fit_me[t] or (rnd > 0 and not (nb0[t] >= 0 and fitted[t])):
                continue
            nb = nb0[t] if rnd == 0 else neighbour(t, at, cols, laser, nb_ok, v1, s1, reach[t])
            nb_s = 1.0 if nb < 0 else max(s1[nb], lo_sig)
            nb_c = np.nan if nb < 0 else v1[nb] - rc[t]
            if not abs(nb_c) < hw[t] + 3.0 * nb_s:  # (also NaN) its stripe does not reach the fit's window
                nb_c = np.nan
            if rnd > 0:  # refitted only where the other stripe moved (out of the window in both: the same fit)
                out_both = math.isnan(nb_c) and math.isnan(last_c[t])
                moved = max(abs(nb_c - last_c[t]), abs(nb_s - last_s[t])) * reach_weight(nb_c, nb_s, hw[t])
                if out_both or moved <= ROUND_TOL_PX:  # (NaN: it came into the window or left it)
                    continue
            # the other stripe's glow, where its edge lies in the window
            nb_side = side[nb] if nb >= 0 and glowing[nb] and abs(nb_c) <= hw[t] else 0.0
            # one step from the last fit where its model stays (the other stripe moved by hundredths of a px)
            # (a glowing point whose other stripe only reaches the window with its tail, now and in its last fit: one
            # step too, the tail's move changes the fit by a fraction of it)
            tail = abs(nb_c) > hw[t] and abs(last_c[t]) > hw[t]
            cold = rnd == 0 or (glowing[t] and not tail)
            warm = not cold and math.isnan(nb_c) == math.isnan(last_c[t]) and nb_side == last_side[t]
            last_c[t] = nb_c
            last_s[t] = nb_s
            last_side[t] = nb_side
            for a in range(N_LIN):
                lin[a] = lin_t[t, a]
            k_rows = 2 * hw[t] + 1
            for i in range(k_rows):
                y[i] = float(image[rc[t] - hw[t] + i, cols[t], 1])
                q[i] = float(i - hw[t])
            # the first round from the common fit, the next ones from the point's last fit
            c, sg, a_fit, g_fit, good, rs, df = fit_into(
                y[:k_rows],
                q[:k_rows],
                side[t],
                (vv[t] if cold else v_out[t]) - rc[t],
                sg0[t] if cold else s_out[t],
                nb_c,
                nb_s,
                nb_side,
                glowing[t],
                ramp,
                lo_sig,
                max_sig,
                sat_dn,
                M,
                b,
                xr,
                lin,
                par,
                work,
                warm,
                d_rc[t],
                kap_k[t],
                d_rc[nb] + side[nb] * (v1[nb] - rc[nb]) if nb >= 0 else 1.0,
                kap_k[nb] if nb >= 0 else 0.0,
                rho[t],
            )
            if good and abs(rc[t] + c - vv[t]) <= MAX_MOVE_PX:
                v_out[t] = rc[t] + c
                s_out[t] = sg
                rss[t] = rs
                dof[t] = df
                steps[0, t] = a_fit
                steps[1, t] = g_fit
                # (M holds the last step's Cholesky factor in its first n - dof rows: n the unclipped samples)
                n_m = -int(df)
                for i in range(k_rows):
                    n_m += y[i] < sat_dn
                ld = 0.0
                for j in range(n_m):
                    ld += 2.0 * math.log(M[j, j])
                steps[2, t] = ld
                fitted[t] = True
                taken = True
                for a in range(N_LIN):
                    lin_t[t, a] = lin[a]
        if not taken:  # the next round would see the same other stripes as this one: nothing to refit
            break
    return v_out, s_out, fitted, rss, dof, steps
