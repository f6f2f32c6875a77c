"""Benchmark of laser-aided navigation (issue 27): the map trusting the poses vs the map with corrected poses.

    python benchmarks/bench_nav.py [--seconds 90] [--seed 1] [--out benchmarks/results/nav.md]

A simulated 3-robot dive in the tank (``mapping.synth``: ``three_rov_plans``, both laser fans ray-traced at
10 Hz, 400 rays per laser, 2 mm range noise) with each navigation of ``lrsensor.sim.navigation``:

- ``good``: today's navigation solution (1.5 cm position noise + 2 mm/sqrt(s) walk, 0.2 deg attitude);
- ``drift``: DVL + compass dead reckoning (1 % scale, 1.5 deg compass bias wandering by 0.5 deg, a slow
  velocity bias, white noise; the position error grows past 0.5 m);
- ``depth-only``: attitude with the compass bias and depth, a horizontal fix at launch only;
- ``mixed``: one robot of each (rov1 good, rov2 drift, rov3 depth-only).

Each dive is replayed into ``mapping.MapBuilder`` three times, as the base station does it
(``mapping.synth.replay_dive``): trusting the poses (``lrsensor base --nav off``: clouds without a fix are left
out), correcting them first with the filter (``mapping.navigation``, the base's default), and with the smoother
(``mapping.smoother``: past poses re-estimated and their clouds re-placed in the map, a last smoothing at the end of
the dive; fixes weighted by ``SMOOTHED_NAV``). The served map is scored against the tank's faces
(``mapping.synth.score_map``: a face is *seen* with 3000 true hits and 30 frames where both lasers hit it;
*recovered* with a plane within 2 deg and 5 cm). Per mode and way: faces seen / recovered, the worst angle and
offset over the seen faces that have a plane (a seen face without one is counted in "missing"), duplicates,
spurious planes, the clouds left unplaced, the robots' horizontal position error (of the poses the clouds are in
the map with at the end, served in NED: largest, and the robots' last estimates), the share of scans whose
registration constrained both horizontal axes, the navigation's wall time per scan on this machine, and the
smoother's (all its runs, including the map's rebuilds, divided by the scans; and its longest run).
"""

from __future__ import annotations

import argparse
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from mapping.planes import open3d
from mapping.smoother import SMOOTHED_NAV, SmootherConfig
from mapping.synth import DiveMap, hit_faces, replay_dive, score_map, simulate_dive, tank, three_rov_plans

MODES: dict[str, str | dict[str, str]] = {
    "good": "good",
    "drift": "drift",
    "depth-only": "depth-only",
    "mixed": {"rov1": "good", "rov2": "drift", "rov3": "depth-only"},
}


@dataclass
class Row:
    """One replay's figures."""

    mode: str
    way: str
    seen: int
    recovered: int
    missing: int
    worst_angle_deg: float
    worst_offset_cm: float
    duplicates: int
    spurious: int
    unplaced: int
    clouds: int
    max_error_m: float
    final_error_m: float
    constrained: float
    cost_ms_mean: float
    cost_ms_p99: float
    wall_s: float
    smooth_ms: float = math.nan
    smooth_max_s: float = math.nan


def _final_error(frames: list[Any], run: DiveMap, navigate: bool) -> float:
    """Largest over the robots of the horizontal error of the last pose known for each robot."""
    worst = 0.0
    last = {f.robot: f for f in frames}
    for robot, f in last.items():
        if navigate:
            est = run.estimates.get(robot)
            pose = est.pose if est is not None else None
            if pose is not None and run.frame is not None:
                pose = run.frame.pose(pose)
        else:
            pose = f.pose_est if math.isfinite(f.pose_est.north_m + f.pose_est.east_m) else None
        if pose is None:
            return math.inf
        worst = max(worst, math.hypot(pose.north_m - f.pose_true.north_m, pose.east_m - f.pose_true.east_m))
    return worst


def run_mode(mode: str, seconds: float, seed: int) -> list[Row]:
    """Simulate one dive and replay it both ways."""
    scene = tank()
    frames = simulate_dive(
        scene, three_rov_plans(), duration_s=seconds, rate_hz=10.0, n_rays=400, seed=seed, navigation=MODES[mode]
    )
    hits = hit_faces(scene, frames)
    rows = []
    for way in ("trusted", "corrected", "smoothed"):
        navigate = way != "trusted"
        kw: dict[str, Any] = {}
        if way == "smoothed":
            kw = {"nav_cfg": SMOOTHED_NAV, "smoother": SmootherConfig()}
        t0 = time.perf_counter()
        run = replay_dive(frames, navigate=navigate, **kw)
        wall = time.perf_counter() - t0
        score = score_map(run.planes(), scene, hits)
        seen = [f for f in score.faces if f.hit]
        with_plane = [f for f in seen if f.plane_ids]
        # the poses the clouds are in the map with at the end (smoothing revises them), served in NED
        errs = [e for v in run.final_error_m.values() for e in v]
        cost = np.array(run.nav_cost_s) * 1e3 if run.nav_cost_s else np.zeros(1)
        rows.append(
            Row(
                mode=mode,
                way=way,
                seen=len(seen),
                recovered=len(seen) - len(score.missing()),
                missing=len(seen) - len(with_plane),
                worst_angle_deg=max((f.angle_deg for f in with_plane), default=math.nan),
                worst_offset_cm=100 * max((f.offset_m for f in with_plane), default=math.nan),
                duplicates=len(score.duplicates()),
                spurious=len(score.spurious),
                unplaced=sum(run.unplaced.values()),
                clouds=len(frames),
                max_error_m=max(errs) if errs else math.nan,
                final_error_m=_final_error(frames, run, navigate),
                constrained=run.constrained_scans / len(frames) if navigate else math.nan,
                cost_ms_mean=float(cost.mean()) if navigate else math.nan,
                cost_ms_p99=float(np.percentile(cost, 99)) if navigate else math.nan,
                wall_s=wall,
                smooth_ms=1e3 * sum(run.smooth_cost_s) / len(frames) if run.smooth_cost_s else math.nan,
                smooth_max_s=max(run.smooth_cost_s, default=math.nan),
            )
        )
        print(rows[-1], flush=True)
    return rows


def _f(x: float, fmt: str) -> str:
    return "-" if not math.isfinite(x) else format(x, fmt)


def table(rows: list[Row]) -> str:
    """The markdown table of the rows."""
    lines = [
        "| navigation | poses | faces seen / recovered (2 deg, 5 cm) | seen without a plane | worst angle (deg) | "
        "worst offset (cm) | duplicates | spurious planes | unplaced clouds | position error max / final (m) | "
        "scans constraining N and E | nav wall ms/scan mean / p99 | smoother ms/scan / longest run (s) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r.mode} | {r.way} | {r.seen} / {r.recovered} | {r.missing} | {_f(r.worst_angle_deg, '.2f')} | "
            f"{_f(r.worst_offset_cm, '.1f')} | {r.duplicates} | {r.spurious} | {r.unplaced} of {r.clouds} | "
            f"{_f(r.max_error_m, '.2f')} / {_f(r.final_error_m, '.2f')} | "
            f"{'-' if not math.isfinite(r.constrained) else f'{100 * r.constrained:.0f} %'} | "
            f"{_f(r.cost_ms_mean, '.2f')} / {_f(r.cost_ms_p99, '.1f')} | "
            f"{_f(r.smooth_ms, '.2f')} / {_f(r.smooth_max_s, '.2f')} |"
        )
    return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=90.0, help="simulated dive length")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--modes", default=",".join(MODES), help="comma-separated navigation modes")
    ap.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "nav.md")
    args = ap.parse_args()
    open3d()  # import once, outside the timings
    load0 = os.getloadavg()[0]
    rows: list[Row] = []
    for mode in [m.strip() for m in args.modes.split(",") if m.strip()]:
        rows += run_mode(mode, args.seconds, args.seed)
    load1 = os.getloadavg()[0]
    corrected = [r for r in rows if r.way != "trusted" and math.isfinite(r.cost_ms_mean)]
    cost = max((r.cost_ms_mean for r in corrected), default=math.nan)
    text = "\n".join(
        [
            f"## Trusted vs corrected poses (3 robots, {args.seconds:g} s at 10 Hz, seed {args.seed}; "
            f"load average {load0:.1f} -> {load1:.1f} on {os.cpu_count()} cores)",
            "",
            f"`python benchmarks/bench_nav.py --seconds {args.seconds:g} --seed {args.seed}`",
            "",
            table(rows),
            "",
            "Worst angle and offset are over the seen faces that have a plane; a face with a plane outside 2 deg or "
            "5 cm is seen but not recovered. Position errors are of the poses the clouds are in the map with at the "
            "end (with navigation: served in NED, turned by the fleet frame); final: each robot's last estimate, the "
            "worst robot (- where a robot's position is unknown). Smoother: its wall time over the dive (re-filter, "
            "smoothing, re-placing and rebuilding the map) per scan, and its longest single run (all robots).",
            "",
            f"Navigation cost: at most {cost:.2f} ms (wall, mean) per scan (one thread, this machine), i.e. one map "
            f"thread corrects about {1e3 / cost:.0f} scans/s"
            if math.isfinite(cost)
            else "",
            "",
        ]
    )
    print(text)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
