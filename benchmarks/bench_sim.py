"""Simulator speed and truth accuracy: ms per render per named scene, ms per truth-only trace.

Run: ``python benchmarks/bench_sim.py [--repeat N] [--width W --height H]``. Prints markdown tables.
One thread (BLAS and OpenCV), as the stripe-extraction benchmarks measure.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse
import time

import cv2
import numpy as np

from lrsensor.sim import SCENES, WaterModel, named_scene, trace_truth
from lrsensor.sim.dive import frame_times_ns, tank_trajectories, trace_dive_clouds


def _best_ms(fn: object, repeat: int) -> float:
    """Median CPU time of this thread (ms): robust against other processes sharing the machine."""
    times = []
    for _ in range(repeat):
        t = time.thread_time()
        fn()  # type: ignore[operator]
        times.append(time.thread_time() - t)
    return 1000.0 * float(np.median(times))


def _centroid_error(name: str, width: int, height: int) -> tuple[float, float]:
    r = named_scene(name, width, height).with_(water=WaterModel.clean()).render(seed=0)
    g = r.image[:, :, 1].astype(float) - 8.0
    g[g < 0.5] = 0.0
    errs = []
    for lt in r.truth.lasers:
        other = r.truth.v_at_columns(1 - lt.index)
        cols = r.truth.visible_columns(lt.index, min_peak_dn=20.0)
        v = r.truth.v_at_columns(lt.index, cols)
        keep = (np.abs(v - other[cols]) > 14) & (np.abs(np.gradient(v)) < 0.5)
        for c, vc in zip(cols[keep], v[keep], strict=True):
            lo, hi = max(round(vc) - 6, 0), min(round(vc) + 7, g.shape[0])
            w = g[lo:hi, c]
            if w.sum() > 0:
                errs.append(abs((w * np.arange(lo, hi)).sum() / w.sum() - vc))
    e = np.asarray(errs)
    return float(np.median(e)), float(np.percentile(e, 95))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--width", type=int, default=1920)
    ap.add_argument("--height", type=int, default=1080)
    args = ap.parse_args()
    cv2.setNumThreads(1)
    print(f"## Simulator speed ({args.width}x{args.height}, one thread, CPU ms, median of {args.repeat})\n")
    print("| scene | render ms | truth-only trace ms | truth samples | visible columns (top/bottom) |")
    print("|---|---:|---:|---:|---:|")
    for name in SCENES:
        setup = named_scene(name, args.width, args.height)
        setup.render(seed=0)  # warm-up (noise bank)
        ms = _best_ms(lambda s=setup: s.render(seed=1), args.repeat)
        tr = _best_ms(lambda s=setup: trace_truth(s.scene, s.calibration, s.pose, s.laser), args.repeat)
        r = setup.render(seed=1)
        n = sum(len(lt) for lt in r.truth.lasers)
        cols = "/".join(str(r.truth.visible_columns(i).size) for i in range(len(r.truth.lasers)))
        print(f"| {name} | {ms:.0f} | {tr:.0f} | {n} | {cols} |")
    trajs = tank_trajectories(3)
    times = frame_times_ns(2.0, 10.0, trajs[0].t0_ns)
    t = time.thread_time()
    n_pts = sum(c.points_body.shape[0] for c in trace_dive_clouds(trajs[0], times))
    dt = (time.thread_time() - t) / len(times) * 1000
    print(f"\ntrace_dive_clouds (tank, 1920x1080 camera): {dt:.0f} CPU ms per frame, {n_pts / len(times):.0f} points")
    print("\n## Stripe centroid vs truth (clean water, 8-bit image, per column)\n")
    print("| scene | median px | p95 px |")
    print("|---|---:|---:|")
    for name in ("wall_0.3", "wall_1.0", "wall_3.0", "tilted_wall", "distorted", "tilted_lasers", "pipe"):
        med, p95 = _centroid_error(name, args.width, args.height)
        print(f"| {name} | {med:.4f} | {p95:.4f} |")


if __name__ == "__main__":
    main()
