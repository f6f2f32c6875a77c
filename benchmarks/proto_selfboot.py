"""PROTOTYPE (not for the product): a noisy parametric bootstrap of the whole extractor on its own model.

For each frame: extract; render the extractor's own model of the frame (both stripes at the returned rows, the
told width, the glow stage's amplitudes, the told glow share, attenuation and the sheet's shape convolved with the
blur numerically, a background from the frame) with read and shot noise; extract that render; the per-column row
error on the render, smoothed along the stripe and averaged over R renders, is subtracted from the frame's rows.
"""

from __future__ import annotations

import sys
from unittest import mock

import numpy as np


def uniform_filter1d(x, n):
    return nanmean_window(x, n // 2)


def median_filter(x, n, mode="nearest"):
    h = n // 2
    xp = np.pad(x, h, mode="edge")
    win = np.lib.stride_tricks.sliding_window_view(xp, n)
    return np.median(win, axis=1)

sys.path.insert(0, "benchmarks")
from bench_turbid import OUTLIER_REL, WITHIN_REL, FrameScore, parse_cells, summarise, table_row  # noqa: E402
from turbid_model import render  # noqa: E402

from lrsensor import Sensor  # noqa: E402
from lrsensor.extract import frame as fr  # noqa: E402
from lrsensor.triangulation import triangulate  # noqa: E402

READ_DN = 1.5  # ORACLE: the model's sensor noise
E_PER_DN = 8.0
_ = OUTLIER_REL


def exact_edge(t, s, kap, d_e, n=48):
    """The sheet's shape h (t' >= 0) convolved with a Gaussian of s px at t (arrays), Simpson."""
    x_hi = np.minimum(t / s, 6.0)
    span = x_hi + 6.0
    ok = span > 0
    hstep = np.where(ok, span, 0.0) / n
    acc = np.zeros_like(t)
    for k in range(n + 1):
        x = -6.0 + k * hstep
        tp = np.maximum(t - s * x, 0.0)
        f = np.exp(kap * tp / (d_e + tp) - 0.5 * x * x)
        wgt = 1.0 if k in (0, n) else (4.0 if k % 2 else 2.0)
        acc += wgt * f
    return np.where(ok, acc * hstep / 3.0 / np.sqrt(2 * np.pi), 0.0)


BOX = 41


def box2d(x, n):
    h = n // 2
    out = x
    for ax in (0, 1):
        c = np.cumsum(np.pad(out, [(h + 1, h) if a == ax else (0, 0) for a in (0, 1)], mode="edge"), axis=ax)
        if ax == 0:
            out = (c[n:] - c[:-n]) / n
        else:
            out = (c[:, n:] - c[:, :-n]) / n
    return out


def fill(x):
    good = np.isfinite(x)
    if good.sum() < 2:
        return x
    idx = np.arange(x.size)
    lo, hi = idx[good].min(), idx[good].max()
    out = np.full_like(x, np.nan)
    out[lo : hi + 1] = np.interp(idx[lo : hi + 1], idx[good], x[good])
    return out


def self_render(img, scan, rec, rng, width_scale=1.0):
    H, W, _ = img.shape
    p = rec["p"]
    v_g, s_g, own, a_g, n_g, retry = rec["out"]
    geo = rec["geo"]
    water = rec["water"]
    side_tab = rec["side"]
    alpha, s_w = water[0], water[1]
    g = img[:, :, 1].astype(float)
    level = np.zeros((H, W))
    rows = np.arange(H, dtype=float)[:, None]
    truth = np.full((2, W), np.nan)
    for li in (0, 1):
        m = scan.laser == li
        u = np.round(scan.uv[m, 0]).astype(int)
        c_u = np.full(W, np.nan)
        c_u[u] = scan.uv[m, 1]
        c_u = fill(c_u)
        mm = (p.laser == li) & np.isfinite(a_g) & own
        A = np.full(W, np.nan)
        A[p.cols[mm]] = a_g[mm]
        A = fill(A)
        fin = np.isfinite(A)
        A[fin] = median_filter(A[fin], 31, mode="nearest")
        share = max(water[3 + li], 0.0)
        s = (s_w if s_w > 0 else float(np.median(s_g[own & (p.laser == li)]))) * width_scale
        if width_scale < 0:
            s = -width_scale
        cols = np.flatnonzero(np.isfinite(c_u) & np.isfinite(A))
        c = c_u[cols][None, :]
        a = A[cols][None, :]
        z = (rows - c) / s
        prof = a * np.exp(-0.5 * z * z)
        side = side_tab[li, cols][None, :].astype(float)
        if share > 0:
            t = side * (rows - c)
            d_e = np.maximum(side * (c - geo.glow_vanish[li, cols][None, :]), 1.0)
            kap = alpha * geo.glow_path[li, cols][None, :] / d_e
            prof += share * a * exact_edge(t, s, kap, d_e)
        level[:, cols] += prof
        truth[li, cols] = c_u[cols]
    level += box2d(g - level, BOX)
    noisy = level + rng.normal(size=level.shape) * np.sqrt(READ_DN**2 + np.maximum(level, 0) / E_PER_DN)
    im2 = img.copy()
    im2[:, :, 1] = np.clip(np.floor(noisy + 0.5), 0, 255).astype(np.uint8)
    return im2, truth


def process(sensor, img):
    rec: dict = {}
    orig = fr.refine_points

    def spy(image, p, glow_side, s, geo, water):
        out = orig(image, p, glow_side, s, geo, water)
        rec.update(p=p, out=out, side=glow_side, geo=geo, water=water.copy())
        return out

    with mock.patch.object(fr, "refine_points", spy):
        scan = sensor.process(img)
    return scan, rec


def score(frame, uv, laser, points):
    W = frame.rows.shape[1]
    errors, outward, columns = [], [], []
    for li, side in ((0, -1.0), (1, 1.0)):
        m = laser == li
        u = np.round(uv[m, 0]).astype(int)
        ok = (u >= 0) & (u < W)
        u = u[ok]
        x_true = frame.range_m[li, u]
        with np.errstate(invalid="ignore"):
            rel = (points[m][ok, 0] - x_true) / x_true
        errors.append(rel)
        outward.append(side * (uv[m][ok, 1] - frame.rows[li, u]))
        vis = frame.visible[li]
        if vis.any():
            seen = np.zeros(W, bool)
            seen[u] = True
            good = np.zeros(W, bool)
            with np.errstate(invalid="ignore"):
                good[u[np.abs(rel) <= WITHIN_REL]] = True
            n = int(vis.sum())
            columns.append((float((seen & vis).sum()) / n, float((good & vis).sum()) / n))
    return FrameScore(np.concatenate(errors), np.concatenate(outward), tuple(columns))


def nanmean_window(x, half):
    good = np.isfinite(x)
    s = np.concatenate([[0.0], np.cumsum(np.where(good, x, 0.0))])
    c = np.concatenate([[0.0], np.cumsum(good.astype(float))])
    i = np.arange(x.size)
    lo = np.maximum(i - half, 0)
    hi = np.minimum(i + half + 1, x.size)
    cnt = c[hi] - c[lo]
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(cnt > 0, (s[hi] - s[lo]) / cnt, np.nan)


def main():
    spec = sys.argv[1]
    reps = int(sys.argv[2]) if len(sys.argv) > 2 else 2
    half = int(sys.argv[3]) if len(sys.argv) > 3 else 64
    width_scale = float(sys.argv[4]) if len(sys.argv) > 4 else 1.0
    noise_free = len(sys.argv) > 5 and sys.argv[5] == "nf"
    for cell in parse_cells(spec, noise_free=noise_free):
        before, after = [], []
        for seed in (0, 1, 2):
            frame = render(cell.turbid(seed))
            sensor = Sensor(frame.calibration)
            scan, rec = process(sensor, frame.image)
            before.append(score(frame, scan.uv, scan.laser, scan.points))
            uv = scan.uv.copy()
            W = frame.rows.shape[1]
            if rec and rec["water"][1] > 0:
                rng = np.random.default_rng(1000 + seed)
                acc = np.zeros((2, W))
                cnt = np.zeros((2, W))
                for _r in range(reps):
                    im2, truth = self_render(frame.image, scan, rec, rng, width_scale)
                    scan2, rec2 = process(Sensor(frame.calibration), im2)
                    for li in (0, 1):
                        m = scan2.laser == li
                        u2 = np.round(scan2.uv[m, 0]).astype(int)
                        d = np.full(W, np.nan)
                        d[u2] = scan2.uv[m, 1] - truth[li, u2]
                        sm = nanmean_window(d, half)
                        ok = np.isfinite(sm)
                        acc[li, ok] += sm[ok]
                        cnt[li, ok] += 1
                    print(f"  seed {seed} rep {_r}: told {rec['water'][:2]} render told {rec2['water'][:2]}",
                          f"render bias px {np.nanmedian(acc / np.where(cnt > 0, cnt, np.nan), axis=1)}", flush=True)
                corr = np.where(cnt > 0, acc / np.maximum(cnt, 1), 0.0)
                for li in (0, 1):
                    m = scan.laser == li
                    u = np.round(scan.uv[m, 0]).astype(int)
                    uv[m, 1] -= corr[li, u]
            pts = triangulate(frame.calibration, uv, scan.laser)
            after.append(score(frame, uv, scan.laser, pts))
        print("before", table_row(cell, summarise(before)), flush=True)
        print("after ", table_row(cell, summarise(after)), flush=True)


if __name__ == "__main__":
    main()
