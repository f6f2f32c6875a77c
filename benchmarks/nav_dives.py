"""The navigation benchmark's dives and the figures one replay of them gives (:mod:`benchmarks.bench_nav`).

:data:`MODES` names each robot's navigation in a dive (``lrsensor.sim.navigation``); :class:`Row` holds one
replay's figures, with :func:`_final_error` (the robots' last horizontal error) and :func:`_heading_rows` (a
tracked replay's headings against the truth); :func:`unbias_fleet` is the ``--fleet-unbiased`` what-if on a
dive; :func:`run_realtime` feeds a dive to ``--nav on`` in real time (``--realtime``). The replays themselves,
:func:`benchmarks.bench_nav.run_mode`, stay in bench_nav with the knobs they read.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

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
    smooth_hold_s: float = math.nan


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


def unbias_fleet(frames: list[Any]) -> list[Any]:
    """The dive as if its compasses' biases averaged to zero over the robots and the dive: their mean (reported
    minus true heading over every frame) taken off every frame's reported heading (``--fleet-unbiased``). Each
    robot keeps its own bias about that mean, and its wander."""
    from lrsensor.frames import body_to_ned

    mean = float(np.mean([math.remainder(f.pose_est.yaw_rad - f.pose_true.yaw_rad, 2 * math.pi) for f in frames]))
    out = []
    for f in frames:
        est = replace(f.pose_est, yaw_rad=f.pose_est.yaw_rad - mean)
        out.append(replace(f, pose_est=est, points_ned_est=body_to_ned(f.points_body, est)))
    return out


def _heading_rows(mode: str, seed: int, frames: list[Any], run: DiveMap, yaws: list[float]) -> list[str]:
    """Per robot of a tracked replay: its compass bias (reported minus true heading, mean over the dive), the heading
    error of the poses its clouds were placed with (served, mean and largest magnitude), and the map's heading
    error (the median yaw error of its wall planes), degrees."""
    rows = []
    map_yaw = f"{float(np.median(yaws)):+.2f}" if yaws else "-"
    for robot in sorted({f.robot for f in frames}):
        bias = [
            math.remainder(f.pose_est.yaw_rad - f.pose_true.yaw_rad, 2 * math.pi) for f in frames if f.robot == robot
        ]
        err = np.array(run.yaw_error_deg.get(robot, []))
        placed = f"{err.mean():+.2f} / {np.abs(err).max():.2f}" if err.size else "-"
        rows.append(
            f"| {mode} (seed {seed}) | {robot} | {math.degrees(float(np.mean(bias))):+.2f} | {placed} | {map_yaw} |"
        )
    return rows


def run_realtime(mode: str, seconds: float, seed: int) -> str:
    """The simulated dive of ``mode`` fed to ``--nav on``'s filter and smoother in real time (each frame at its
    capture time), the smoother's runs truly on a thread of their own as the base station runs them: the map
    thread's longest hold by a run (start and hand-over), its longest step per frame, and the served map's score.
    Returns a markdown table."""
    scene = tank()
    frames = simulate_dive(
        scene, three_rov_plans(), duration_s=seconds, rate_hz=10.0, n_rays=400, seed=seed, navigation=MODES[mode]
    )
    hits = hit_faces(scene, frames)
    run = replay_dive(
        frames, navigate=True, nav_cfg=SMOOTHED_NAV, smoother=SmootherConfig(), background=True, realtime=True
    )
    score = score_map(run.planes(), scene, hits)
    seen = [f for f in score.faces if f.hit]
    return "\n".join(
        [
            "| dive | faces seen / recovered (2 deg, 5 cm) | duplicates | spurious | smoother runs | longest "
            "map-thread hold by a run during the dive (ms) | longest map-thread step per frame (ms) |",
            "|---|---|---|---|---|---|---|",
            f"| {mode}, {seconds:g} s, seed {seed} | {len(seen)} / {len(seen) - len(score.missing())} | "
            f"{len(score.duplicates())} | {len(score.spurious)} | {len(run.smooth_cost_s)} | "
            f"{1e3 * max(run.smooth_hold_s, default=math.nan):.0f} | {1e3 * max(run.step_s, default=math.nan):.0f} |",
        ]
    )
