"""The extractor's stripe row error (pixels) on a simulated dive's extracted clouds, by depth: where
``MapConfig.stripe_sigma_px`` comes from (docs/mapping.md, "Range noise").

    python -m benchmarks.diag_stripe_error --mode good --seed 1 [--dives DIR] [--every 7]

The clouds are those of ``benchmarks.diag_extracted_poses`` (``benchmarks.fleet_dives``: rendered frames of one of
``bench_nav``'s dives at 640x360 through :class:`lrsensor.Sensor`, cached; read only, never rendered here when the
folder exists). Each point lies in its laser's sheet (``z`` = -/+ the laser offset ``c`` in the body frame of
:func:`lrsensor.sim.scenes.paper_calibration`) on the ray of its image column; the truth is where that line of the
sheet meets the tank's faces at the frame's true pose. With the stripe ``v = f_px c / x`` rows off the horizon at
depth ``x``, the row error is ``f_px c (1 / x_est - 1 / x_true)``. Per depth band: the median and robust standard
deviation (1.4826 MAD) of the row error, and the depth error it makes (mm). Points that meet no face (a pipe) or
are off by more than half a metre are left out. Prints markdown; a diagnostic.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from lrsensor.calibration import Calibration
from lrsensor.frames import Pose
from mapping.synth import tank

from .fleet_dives import dive_frames, extracted_frames, write_fleet

BANDS_M = ((0.5, 1.0), (1.0, 1.5), (1.5, 2.0), (2.0, 2.5), (2.5, 3.0), (2.0, 3.0), (3.0, 4.0), (4.0, 6.0))


def true_depth_m(points_body: np.ndarray, pose: Pose, laser_z_m: np.ndarray) -> np.ndarray:
    """Depth (m, along body x) at which the sheet line of each point's column meets the tank's faces, (N,); NaN
    where it meets none. ``laser_z_m``: (N,) the point's sheet height (body z)."""
    faces = tank().faces
    normal = np.array([f.normal for f in faces])
    offset = np.array([f.d for f in faces])
    centre = np.array([f.center for f in faces])
    u = np.array([f.u for f in faces])
    v = np.array([f.v for f in faces])
    half = np.array([(f.half_u, f.half_v) for f in faces])
    slope = points_body[:, 1] / points_body[:, 0]
    rot = pose.R_ned_from_body
    origin = np.stack([np.zeros_like(slope), np.zeros_like(slope), laser_z_m], 1) @ rot.T + pose.p_ned
    direction = np.stack([np.ones_like(slope), slope, np.zeros_like(slope)], 1) @ rot.T  # per metre of depth
    with np.errstate(divide="ignore", invalid="ignore"):  # a face parallel to the line: inf or NaN, never inside
        s = -(origin @ normal.T + offset) / (direction @ normal.T)  # (N, F)
        rel = origin[:, None, :] + s[:, :, None] * direction[:, None, :] - centre[None]
        inside = (np.abs(np.einsum("nfk,fk->nf", rel, u)) <= half[:, 0]) & (
            np.abs(np.einsum("nfk,fk->nf", rel, v)) <= half[:, 1]
        )
    depth = np.where(inside & (s > 0.05), s, np.inf).min(axis=1)
    return np.where(np.isfinite(depth), depth, np.nan)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--mode", default="good")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--seconds", type=float, default=90.0)
    ap.add_argument("--dives", type=Path, default=Path("/tmp/nav23/dives"))
    ap.add_argument("--every", type=int, default=7, help="every n-th frame")
    a = ap.parse_args(argv)
    folders = write_fleet(a.dives, a.mode, a.seed, a.seconds, "640x360")
    frames = extracted_frames(dive_frames(a.mode, a.seed, a.seconds), folders)
    calib = Calibration.load(next(iter(folders.values())) / "calib.json")
    f_px = calib.camera.fy
    c_m = abs(float(calib.lasers[0].point[2]))
    x_est, x_true = [], []
    for fr in frames[:: a.every]:
        p = fr.points_body
        if p.shape[0]:
            x_est.append(p[:, 0])
            x_true.append(true_depth_m(p, fr.pose_true, np.sign(p[:, 2]) * c_m))
    xe, xt = np.concatenate(x_est), np.concatenate(x_true)
    ok = np.isfinite(xt) & (np.abs(xe - xt) < 0.5)
    xe, xt = xe[ok], xt[ok]
    row = f_px * c_m * (1.0 / xe - 1.0 / xt)
    print(f"{a.mode} seed {a.seed}, 640x360 (f_px {f_px:g}, laser offset {c_m:g} m), every {a.every}th frame, "
          f"{xt.size} points\n")  # fmt: skip
    print("| depth (m) | points | row error median (px) | robust sd (px) | depth error p50 / p90 (mm) |")
    print("|---|---|---|---|---|")
    for lo, hi in BANDS_M:
        m = (xt >= lo) & (xt < hi)
        if np.count_nonzero(m) < 50:
            continue
        e = row[m]
        sd = 1.4826 * float(np.median(np.abs(e - np.median(e))))
        dx = np.abs(xe[m] - xt[m]) * 1e3
        print(f"| {lo:g}-{hi:g} | {int(m.sum())} | {float(np.median(e)):+.4f} | {sd:.4f} | "
              f"{float(np.median(dx)):.1f} / {float(np.percentile(dx, 90)):.1f} |")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
