"""Measure the depth-only fleet's compass biases from the launch fixes and the walls seen near them (issue 27).

    python -m benchmarks.diag_fleet_heading [--seeds 1,2,3,5] [--seconds 0,1,2] [--out FILE]

Simulates ``bench_nav``'s ``depth-only`` dives (``mapping.synth``: 3 robots, 10 Hz, 400 rays; a fix at launch only)
and estimates every robot's compass bias with :func:`mapping.fleet_heading.estimate`: from each robot's launch scan
alone (``--seconds 0``), and from its scans over the first S seconds, each placed relative to its fix by the true
move turned into its compass frame (what a perfect scan odometry gives; ``offset_sigma`` 1 cm per second since the
launch: a what-if for the extra walls, not what a graph gives). Prints per seed and robot the true bias at the launch
(reported minus true heading, mean over its first second; the simulator's is a constant of random sign plus a
wander) and over the dive, the estimate and its predicted standard deviation, and the common heading's (the mean
over the robots): estimated minus true. Markdown; a diagnostic."""

from __future__ import annotations

import argparse
import ast
import math
from pathlib import Path
from typing import Any

import numpy as np

from lrsensor.frames import R_ned_from_body
from mapping.fleet_heading import View, estimate
from mapping.synth import simulate_dive, tank, three_rov_plans


def views(frames: list[Any], seconds: float) -> list[View]:
    """Each robot's scans of the first ``seconds`` after its first frame (its launch fix) as :class:`View`\\ s."""
    first: dict[str, Any] = {}
    out = []
    for f in frames:
        f0 = first.setdefault(f.robot, f)
        dt = (f.t_ns - f0.t_ns) * 1e-9
        if dt > seconds + 1e-6:
            continue
        est = f.pose_est
        pts = f.points_body @ R_ned_from_body(est.roll_rad, est.pitch_rad, est.yaw_rad).T
        # the true move turned into the robot's compass frame (its bias at this scan)
        b = math.remainder(est.yaw_rad - f.pose_true.yaw_rad, 2 * math.pi)
        d = np.array([f.pose_true.north_m - f0.pose_true.north_m, f.pose_true.east_m - f0.pose_true.east_m])
        c, s = math.cos(b), math.sin(b)
        u = np.array([c * d[0] - s * d[1], s * d[0] + c * d[1]])
        fix = (f0.pose_est.north_m, f0.pose_est.east_m)
        out.append(View(f.robot, fix, pts[:, 0:2], (float(u[0]), float(u[1])), 0.01 * dt))
    return out


def true_bias(frames: list[Any], robot: str, upto_s: float | None) -> float:
    """Mean of reported minus true heading (rad) over ``robot``'s frames within ``upto_s`` of its first (all)."""
    fs = [f for f in frames if f.robot == robot]
    t0 = fs[0].t_ns
    b = [
        math.remainder(f.pose_est.yaw_rad - f.pose_true.yaw_rad, 2 * math.pi)
        for f in fs
        if upto_s is None or (f.t_ns - t0) * 1e-9 <= upto_s
    ]
    return float(np.mean(b))


def replay(
    seed: int, seconds: float, nav: dict[str, Any], graph: dict[str, Any], unbiased: bool, mode: str = "depth-only"
) -> str:
    """``bench_nav``'s ``tracked`` replay of the depth-only dive (``--graph-track``) with these ``NavConfig`` and
    ``GraphConfig`` fields: a markdown row (faces within 2 deg and 5 cm, duplicates, spurious, the map's heading
    error as ``bench_nav`` gives it, the worst face, unplaced clouds, the served frame's turn, each robot's placed
    poses' heading error)."""
    from dataclasses import replace

    from benchmarks.bench_nav import MODES, unbias_fleet
    from mapping.graph_config import TRACKED
    from mapping.smoother import SMOOTHED_NAV, SmootherConfig
    from mapping.synth import hit_faces, replay_dive, score_map, wall_yaw_deg

    scene = tank()
    frames = simulate_dive(scene, three_rov_plans(), duration_s=seconds, rate_hz=10.0, n_rays=400, seed=seed,
                           navigation=MODES[mode])  # fmt: skip
    if unbiased:
        frames = unbias_fleet(frames)
    hits = hit_faces(scene, frames)
    run = replay_dive(
        frames,
        navigate=True,
        nav_cfg=replace(SMOOTHED_NAV, graph_without_fix=True, frame_graph_launches=True, **nav),
        smoother=SmootherConfig(),
        background="wait",
        graph_cfg=replace(TRACKED, **graph),
    )
    score = score_map(run.planes(), scene, hits)
    seen = [f for f in score.faces if f.hit]
    with_plane = [f for f in seen if f.plane_ids]
    yaws = wall_yaw_deg(run.planes(), score)
    worst_a = max((f.angle_deg for f in with_plane), default=math.nan)
    worst_o = 100 * max((f.offset_m for f in with_plane), default=math.nan)
    placed = ", ".join(f"{float(np.mean(v)):+.2f}" for _, v in sorted(run.yaw_error_deg.items()) if v)
    return (
        f"| {seed} | {len(seen) - len(score.missing())} of {len(seen)} | {len(score.duplicates())} | "
        f"{len(score.spurious)} | {float(np.median(yaws)) if yaws else math.nan:+.2f} | "
        f"{worst_a:.2f} / {worst_o:.1f} | "
        f"{sum(run.unplaced.values())} | {math.degrees(run.frame.yaw_rad):+.2f} | {placed} |"
    )


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", default="1,2,3,5")
    ap.add_argument("--seconds", default="0,1,2", help="comma-separated: scans within S s of each launch")
    ap.add_argument("--dive-s", type=float, default=90.0)
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument(
        "--replay",
        action="store_true",
        help="instead: bench_nav's tracked replay per seed (faces, duplicates, spurious, map heading error)",
    )
    ap.add_argument("--fleet-unbiased", action="store_true", help="with --replay: bench_nav's what-if")
    ap.add_argument("--mode", default="depth-only", choices=["depth-only", "mixed"], help="with --replay")
    ap.add_argument(
        "--set", action="append", default=[], metavar="KEY=VALUE",
        help="with --replay: a NavConfig (nav.KEY) or GraphConfig (graph.KEY) field, e.g. nav.fleet_heading=1",
    )  # fmt: skip
    args = ap.parse_args()
    if args.replay:
        nav: dict[str, Any] = {}
        graph: dict[str, Any] = {}
        for kv in args.set:
            key, val = kv.split("=", 1)
            where, name = key.split(".", 1)
            value = float(val) if val in ("inf", "-inf") else ast.literal_eval(val)  # numbers, True, 'text'
            (nav if where == "nav" else graph)[name] = bool(int(val)) if name == "fleet_heading" else value
        rows = ["| seed | faces in the bar | duplicates | spurious | map heading (deg) | worst deg / cm | unplaced | "
                "frame turn (deg) | placed heading error per robot (deg, mean) |",
                "|---|---|---|---|---|---|---|---|---|"]  # fmt: skip
        for seed in (int(s) for s in args.seeds.split(",")):
            rows.append(replay(seed, args.dive_s, nav, graph, args.fleet_unbiased, args.mode))
            print(rows[-1], flush=True)
        text = f"{args.mode}, settings: {' '.join(args.set) or 'TRACKED'}\n\n" + "\n".join(rows) + "\n"
        print(text)
        if args.out is not None:
            args.out.write_text(text)
        return 0
    lines = [
        "| seed | scans within (s) | walls shared / observations | robot | true bias at launch / dive mean | "
        "estimate +- sd | error |",
        "|---|---|---|---|---|---|---|",
    ]
    for seed in (int(s) for s in args.seeds.split(",")):
        frames = simulate_dive(
            tank(), three_rov_plans(), duration_s=args.dive_s, rate_hz=10.0, n_rays=400, seed=seed,
            navigation="depth-only",
        )  # fmt: skip
        robots = sorted({f.robot for f in frames})
        launch = {r: true_bias(frames, r, 1.0) for r in robots}
        dive = {r: true_bias(frames, r, None) for r in robots}
        for secs in (float(s) for s in args.seconds.split(",")):
            got = estimate(views(frames, secs))
            for r in robots:
                err = got.bias_rad[r] - launch[r]
                lines.append(
                    f"| {seed} | {secs:g} | {got.walls} / {got.observations} | {r} | "
                    f"{math.degrees(launch[r]):+.2f} / {math.degrees(dive[r]):+.2f} | "
                    f"{math.degrees(got.bias_rad[r]):+.2f} +- {math.degrees(got.sd_rad[r]):.2f} | "
                    f"{math.degrees(err):+.2f} |"
                )
            common = float(np.mean([launch[r] for r in robots]))
            lines.append(
                f"| {seed} | {secs:g} | | common | {math.degrees(common):+.2f} / "
                f"{math.degrees(float(np.mean(list(dive.values())))):+.2f} | "
                f"{math.degrees(got.common_rad):+.2f} +- {math.degrees(got.common_sd_rad):.2f} | "
                f"**{math.degrees(got.common_rad - common):+.2f}** |"
            )
            print(lines[-1], flush=True)
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out is not None:
        args.out.write_text(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
