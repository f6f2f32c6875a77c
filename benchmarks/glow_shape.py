"""The glow's shape at far walls: single-column fits of the turbidity model with three glow models (issue 26).

    python benchmarks/glow_shape.py [--cells 3:0.5:4 ...] [--seed 1] [--every 24] [--noise-free]

Each visible column of a frame of :mod:`benchmarks.turbid_model` (every ``--every``-th column, both lasers) is
fitted alone, by least squares on the green rows ``c -+ (4.5 sigma + 2)`` (at most 30), as the extractor's joint
fit does: a line, the Gaussian stripe, the other laser's stripe (its centre held at its true row, its amplitude
free: an idealisation of the extractor's rounds) and both stripes' glows, with the glow in one of three shapes:

- ``step``: a step at the stripe's centre blurred like the stripe (the extractor's step model);
- ``ramp``: that step plus a blurred linear and quadratic growth outward (the extractor's ramp model, two more
  parameters);
- ``physical``: the sheet's single-scatter glow as the physics has it. Seen at the row ``delta`` px outward of the
  stripe, the sheet lies at range ``x = F / (d + delta)`` (``d`` = the stripe's distance from the laser plane's
  vanishing row, known from the centre; ``F = fy c``), and its radiance grows only by the shorter path in and out,
  ``exp(2 alpha s (x_w - x))`` (``s = sqrt(1 + xn^2)``: the oblique path in the column): the shape
  ``exp(kappa delta / (d + delta))`` with ``kappa = 2 alpha s x_w``, convolved with the stripe's blur (numerically,
  quarter-pixel steps). No parameter beyond the step's amplitude: ``alpha`` (the water's attenuation) is one number
  per frame, taken as the minimum of the residual sum of squares pooled over every 4th fitted column on a grid of
  0.05-0.6 /m and refined by a parabola. The model's own 0.3 /m is shown too.

Printed per cell: the attenuation estimated, then per shape the median row error outward (px; positive: on the
glow's side; 1 px is about 11 % of range at 3 m, 7 % at 2 m), its median absolute deviation (px) and the fitted
stripe amplitude over the true peak (the signal-to-noise gate reads it); each with the stripe's width free and held
at its true value (a width shared along the stripe: the blur is the water's). A reading aid for docs/water-design.md
("The glow's shape"), not a test: it uses scipy's least squares (a benchmark-only import).
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

try:  # python -m benchmarks.glow_shape, and the tests
    from benchmarks.turbid_model import Turbid, TurbidFrame, render
except ImportError:  # python benchmarks/glow_shape.py
    from turbid_model import Turbid, TurbidFrame, render  # type: ignore[no-redef]

FloatArray = NDArray[np.float64]
#: The attenuations (1/m) the per-frame estimate searches.
ALPHA_GRID = tuple(round(0.05 * k, 2) for k in range(1, 13))
#: The outward offsets (px) on which the physical glow is convolved with the blur.
TAU = np.arange(0.0, 90.0, 0.25) + 0.125
DEFAULT_OUT = Path(__file__).parent / "results" / "glow_shape.md"
HEADER = (
    "| range m | glow step | blur px | seed | columns | glow model | outward px | MAD px | amplitude / peak |",
    "|---:|---:|---:|---:|---:|---|---:|---:|---:|",
)


def _phi(u: FloatArray) -> FloatArray:
    return np.exp(-0.5 * u * u) / math.sqrt(2.0 * math.pi)


def _cdf(u: FloatArray) -> FloatArray:
    from scipy.special import ndtr

    return np.asarray(ndtr(u), np.float64)


def physical_glow(t: FloatArray, d: float, kappa: float, sigma: float) -> FloatArray:
    """The glow ``H(tau) exp(kappa tau / (d + tau))`` blurred by a Gaussian of ``sigma`` px, at outward offsets
    ``t`` (K,) px from its edge; 1 at the edge before the blur."""
    h = np.exp(kappa * TAU / (d + TAU))
    w = _phi((t[:, None] - TAU[None, :]) / sigma) / sigma * 0.25
    return np.asarray(w @ h, np.float64)


def fit_column(
    frame: TurbidFrame, li: int, col: int, shape: str, alpha: float, hold_sigma: bool = False
) -> tuple[float, float, float]:
    """One column's fit: (row error outward px, residual sum of squares DN^2, stripe amplitude over the true peak);
    ``hold_sigma``: the stripe's width held at its true value (what a width shared along the stripe would give)."""
    from scipy.optimize import least_squares

    cam = frame.calibration.camera
    blur = frame_blur(frame)
    F = cam.fy * 0.05
    side = -1.0 if li == 0 else 1.0
    vt = float(frame.rows[li, col])
    vn = float(frame.rows[1 - li, col])
    rc = round(vt)
    sig = math.hypot(0.0015 * cam.fy / float(frame.range_m[li, col]), blur)
    hw = min(int(4.5 * sig + 2), 30)
    q = np.arange(-hw, hw + 1, dtype=np.float64)
    y = frame.image[rc - hw : rc + hw + 1, col, 1].astype(np.float64)
    cn = vn - rc
    s = math.sqrt(1.0 + ((col - cam.cx) / cam.fx) ** 2)
    dn = abs(vn - cam.cy)

    def model(p: FloatArray) -> FloatArray:
        if hold_sigma:
            p = np.concatenate([p[:1], [sig], p[1:]])
        c, sg, a0, a1, amp, g, an, gn = p[:8]
        u = side * (q - c) / sg
        un = -side * (q - cn) / sg
        m = a0 + a1 * q + amp * np.exp(-0.5 * ((q - c) / sg) ** 2) + an * np.exp(-0.5 * ((q - cn) / sg) ** 2)
        if shape == "step":
            return m + g * _cdf(u) + gn * _cdf(un)
        if shape == "ramp":
            f, ph = _cdf(u), _phi(u)
            ramp = p[8] * sg * (u * f + ph) + p[9] * sg * sg * ((u * u + 1.0) * f + u * ph)
            return m + g * f + ramp + gn * _cdf(un)
        d = abs(rc + c - cam.cy)
        return (
            m
            + g * physical_glow(side * (q - c), d, 2.0 * alpha * s * F / d, sg)
            + gn * physical_glow(-side * (q - cn), dn, 2.0 * alpha * s * F / dn, sg)
        )

    extra = 2 if shape == "ramp" else 0
    p0 = np.array([vt - rc + 0.3 * side, sig, 20.0, 0.0, 30.0, 10.0, 30.0, 10.0] + [0.0] * extra)
    scale = np.array([1.0, 1.0, 10.0, 1.0, 10.0, 10.0, 10.0, 10.0] + [1.0] * extra)
    if hold_sigma:
        p0, scale = np.delete(p0, 1), np.delete(scale, 1)
    r = least_squares(lambda p: model(p) - y, p0, x_scale=scale)
    x = np.insert(r.x, 1, sig) if hold_sigma else r.x
    return side * (float(x[0]) - (vt - rc)), float(np.sum(r.fun**2)), float(x[4]) / float(frame.peak_dn[li, col])


def frame_blur(frame: TurbidFrame) -> float:
    """The frame's forward-scatter blur, px (kept with the frame by :func:`run_cell`)."""
    return float(getattr(frame, "_blur", 0.0))


def estimate_alpha(fit: Callable[[float], float]) -> float:
    """The attenuation (1/m) minimising ``fit(alpha)`` (a pooled residual sum of squares) over :data:`ALPHA_GRID`,
    refined by a parabola through the grid's minimum and its neighbours."""
    rs = [fit(a) for a in ALPHA_GRID]
    i = int(np.argmin(rs))
    if not 0 < i < len(ALPHA_GRID) - 1:
        return ALPHA_GRID[i]
    (x0, x1, x2), (y0, y1, y2) = ALPHA_GRID[i - 1 : i + 2], rs[i - 1 : i + 2]
    den = (x0 - x1) * (x0 - x2) * (x1 - x2)
    a = (x2 * (y1 - y0) + x1 * (y0 - y2) + x0 * (y2 - y1)) / den
    b = (x2 * x2 * (y0 - y1) + x1 * x1 * (y2 - y0) + x0 * x0 * (y1 - y2)) / den
    return -b / (2.0 * a) if a > 0 else x1


def run_cell(distance_m: float, glow: float, blur: float, seed: int, every: int, noise_free: bool) -> list[str]:
    """The rows of one cell (see the module's docstring)."""
    kw = {"particles_per_mpx": 0.0, "read_noise_dn": 0.0, "electrons_per_dn": 1e12} if noise_free else {}
    frame = render(Turbid(distance_m=distance_m, glow_step=glow, blur_px=blur, seed=seed, **kw))  # type: ignore[arg-type]
    object.__setattr__(frame, "_blur", blur)
    cols = [(li, c) for li in (0, 1) for c in range(10, frame.rows.shape[1] - 10, every) if frame.visible[li, c]]
    sample = cols[::4]
    alpha = estimate_alpha(lambda a: sum(fit_column(frame, li, c, "physical", a)[1] for li, c in sample))
    rows = []
    variants = [("step", 0.0), ("ramp", 0.0), ("physical", 0.3), ("physical", alpha), ("physical", 0.2)]
    for (shape, a), hold in [(v, False) for v in variants] + [(v, True) for v in variants]:
        r = np.array([fit_column(frame, li, c, shape, a, hold) for li, c in cols])
        e = r[:, 0]
        med = float(np.median(e))
        label = shape if shape != "physical" else f"physical, alpha {a:.3f}" + (" (estimated)" if a == alpha else "")
        label += ", sigma held" if hold else ""
        rows.append(
            f"| {distance_m:g} | {glow:g} | {blur:g} | {'noise-free' if noise_free else seed} | {len(cols)} "
            f"| {label} | {med:+.3f} | {float(np.median(np.abs(e - med))):.3f} | {float(np.median(r[:, 2])):.2f} |"
        )
    return rows


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--cells", nargs="*", default=["3:0.5:4"], help="range_m:glow_step:blur_px")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--every", type=int, default=24, help="fit every N-th column")
    ap.add_argument("--noise-free", action="store_true", help="no read or shot noise, no particles (8 bits kept)")
    ap.add_argument("--out", type=Path, default=None, help=f"results file (e.g. {DEFAULT_OUT})")
    args = ap.parse_args(argv)
    rows = list(HEADER)
    print("\n".join(HEADER))
    for cell in args.cells:
        d, g, b = (float(x) for x in cell.split(":"))
        for row in run_cell(d, g, b, args.seed, args.every, args.noise_free):
            rows.append(row)
            print(row, flush=True)
    if args.out is not None:
        from lrsensor.atomic import atomic_write

        stamp = time.strftime("%Y-%m-%dT%H:%MZ", time.gmtime())
        used = " ".join(sys.argv[1:] if argv is None else argv)
        text = f"<!-- python benchmarks/glow_shape.py {used}, {stamp} -->\n" + "\n".join(rows) + "\n"
        atomic_write(args.out, text, fsync=False)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
