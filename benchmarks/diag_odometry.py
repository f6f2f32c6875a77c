"""How far a depth-only pose graph walks on its scan odometry alone, against what its standard deviation says
(issue 27; docs/navigation-design.md, "Depth-only robots on extracted clouds").

    python -m benchmarks.diag_odometry [--seed 1] [--traced] [--max-range-m 3] [--window-s 7] [--every-s 10]
        [--dives DIR] [--set graph.KEY=VALUE ...]

``bench_nav``'s 90 s depth-only dive, its clouds extracted from the rendered 640x360 frames (the cache of
``benchmarks.diag_extracted_poses``; ``--traced``: the ray-traced clouds), cut at ``--max-range-m`` along the
optical axis. Each robot's dive is cut into windows of ``--window-s`` starting every ``--every-s``; each window is
a fresh :class:`mapping.posegraph.GraphNav` (``base_nav()``'s tuning, ``--set`` applied) launched at the true pose
and fed the raw poses and clouds with an empty map: what a broken track has, its odometry, velocity walk and
compass. Prints markdown: per window the horizontal error against the truth at its end and the largest, the
standard deviation (the larger axis) at the end, the scans whose error lay beyond 3 standard deviations, and the
scans placed (standard deviation under ``place_std_m``) with an error over 10 cm; then the sums. A diagnostic."""

from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from mapping.landmarks import PlaneLandmarks
from mapping.posegraph import GraphNav

from .diag_extracted_poses import _tuning
from .fleet_dives import depth_only_frames


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--traced", action="store_true")
    ap.add_argument("--max-range-m", type=float, default=3.0)
    ap.add_argument("--window-s", type=float, default=7.0)
    ap.add_argument("--every-s", type=float, default=10.0)
    ap.add_argument("--dives", type=Path, default=Path("/tmp/nav23/dives"))
    ap.add_argument("--set", action="append", default=[], help="graph.KEY=VALUE (nav. too)")
    a = ap.parse_args(argv)
    frames = depth_only_frames(a.seed, traced=a.traced, max_range_m=a.max_range_m, dives=a.dives)
    kw = _tuning(a.set)
    empty = PlaneLandmarks.empty()
    t0 = frames[0].t_ns
    kind = "traced" if a.traced else "extracted 640x360"
    print(f"depth-only seed {a.seed}, {kind} clouds cut at {a.max_range_m:g} m, odometry alone over "
          f"{a.window_s:g} s windows {' '.join(a.set)}\n")  # fmt: skip
    print("| robot | from s | error end / max (cm) | std end (cm) | scans beyond 3 std | placed > 10 cm |")
    print("|---|---|---|---|---|---|")
    ends, stds, beyond, wrong, n_scans = [], [], 0, 0, 0
    c0 = time.process_time()
    for robot in sorted({f.robot for f in frames}):
        rows = [f for f in frames if f.robot == robot]
        start = 0.0
        while start + a.window_s <= (rows[-1].t_ns - t0) * 1e-9:
            win = [f for f in rows if start <= (f.t_ns - t0) * 1e-9 < start + a.window_s]
            nav = GraphNav(robot, kw["nav_cfg"], kw["graph_cfg"])
            err, sd, placed = [], [], []
            for i, f in enumerate(win):
                raw = f.pose_est
                if i == 0:
                    raw = replace(raw, north_m=f.pose_true.north_m, east_m=f.pose_true.east_m)
                est = nav.update(f.t_ns, raw, f.points_body, empty)
                if i == 0 or est.pose is None:
                    continue
                err.append(math.hypot(est.pose.north_m - f.pose_true.north_m, est.pose.east_m - f.pose_true.east_m))
                sd.append(max(est.std["north_m"], est.std["east_m"]))
                placed.append(sd[-1] <= nav.gcfg.place_std_m)
            e, s, p = np.array(err), np.array(sd), np.array(placed)
            out = int(np.sum(e > 3 * s))
            bad = int(np.sum(p & (e > 0.1)))
            print(f"| {robot} | {start:g} | {100 * e[-1]:.0f} / {100 * e.max():.0f} | {100 * s[-1]:.0f} | "
                  f"{out} of {e.size} | {bad} |")  # fmt: skip
            ends.append(e[-1])
            stds.append(s[-1])
            beyond += out
            wrong += bad
            n_scans += e.size
            start += a.every_s
    e_end, s_end = np.array(ends), np.array(stds)
    print(f"\nwindows {e_end.size}: error at the end median {100 * np.median(e_end):.0f} cm, largest "
          f"{100 * e_end.max():.0f} cm; std at the end median {100 * np.median(s_end):.0f} cm; windows ending beyond "
          f"3 std {int(np.sum(e_end > 3 * s_end))}; scans beyond 3 std {beyond} of {n_scans}; placed with an error "
          f"over 10 cm {wrong}; CPU {time.process_time() - c0:.0f} s")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
