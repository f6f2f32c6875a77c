"""Benchmark of the shared map: cost per incoming cloud and full re-extraction cost.

    python benchmarks/bench_mapping.py [--robots 20] [--seconds 6] [--out benchmarks/results/mapping.md]

A synthetic tank dive (``mapping.synth``: two ROVs, 1900 rays per laser, ~3300 points per cloud at 30 Hz) is
replayed as N robots interleaved in capture-time order (robot k replays base robot k % 2 shifted in time), the way
the base station's single map thread receives them. Measured per ``MapBuilder.add_cloud`` call: wall and CPU time
(mean, p50, p99, max); the sustainable rate on the map thread is 1 / mean CPU time per cloud. Then one window of
about 100k points is extracted from scratch (``extract_planes`` + claims), the full re-extraction cost.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np

from mapping import MapBuilder, MapConfig
from mapping.planes import claim_points, extract_planes, open3d
from mapping.synth import simulate_dive, tank, two_rov_plans


def _stream(robots: int, seconds: float) -> list[tuple[str, int, np.ndarray, object]]:
    frames = simulate_dive(tank(), two_rov_plans(), duration_s=seconds, rate_hz=30.0, n_rays=1900, seed=3)
    base = {"rov1": [f for f in frames if f.robot == "rov1"], "rov2": [f for f in frames if f.robot == "rov2"]}
    n = len(base["rov1"])
    out = []
    for i in range(n):
        for k in range(robots):
            src = base["rov1" if k % 2 == 0 else "rov2"][(i + 7 * k) % n]
            t_ns = base["rov1"][i].t_ns
            out.append((f"r{k:02d}", t_ns, src.points_ned_est, src.pose_est))
    return out


def _percentiles(x: np.ndarray) -> tuple[float, float, float, float]:
    return float(x.mean()), float(np.percentile(x, 50)), float(np.percentile(x, 99)), float(x.max())


def bench_stream(cfg: MapConfig, stream: list) -> dict[str, float]:
    b = MapBuilder(cfg)
    wall, cpu = [], []
    for robot, t_ns, pts, pose in stream:
        w0, c0 = time.perf_counter(), time.process_time()
        b.add_cloud(robot, t_ns, pts, pose)
        cpu.append(time.process_time() - c0)
        wall.append(time.perf_counter() - w0)
    w0, c0 = time.perf_counter(), time.process_time()
    b.flush()
    st = b.stats()
    w = np.array(wall) * 1e3
    c = np.array(cpu) * 1e3
    mean_c = float(c.mean())
    return {
        "clouds": len(stream),
        "points_per_cloud": float(np.mean([s[2].shape[0] for s in stream])),
        "wall": _percentiles(w),
        "cpu": _percentiles(c),
        "rate": 1e3 / mean_c if mean_c > 0 else float("inf"),
        "extractions": st["extractions"],
        "planes": st["planes"],
    }


def bench_full(cfg: MapConfig, stream: list, target_points: int = 100_000) -> dict[str, float]:
    pts, veh, n = [], [], 0
    for _robot, _t, p, pose in stream:
        if _robot != "r00":
            continue
        pts.append(p)
        veh.append(np.repeat(pose.p_ned[None, :], p.shape[0], axis=0))
        n += p.shape[0]
        if n >= target_points:
            break
    p = np.concatenate(pts)
    v = np.concatenate(veh)
    times = []
    for rep in range(3):
        c0, w0 = time.process_time(), time.perf_counter()
        ex = extract_planes(p, v, cfg, seed=rep)
        claim_points(p, ex.grid, ex.candidates, ex.cell_keys, cfg, np.ones(p.shape[0], dtype=bool))
        times.append((time.process_time() - c0, time.perf_counter() - w0))
    t = np.array(times) * 1e3
    return {
        "points": p.shape[0],
        "cpu_ms": float(t[:, 0].min()),
        "wall_ms": float(t[:, 1].min()),
        "planes": len(ex.candidates),
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--robots", type=int, default=20)
    ap.add_argument("--seconds", type=float, default=6.0, help="simulated dive length per robot")
    ap.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "mapping.md")
    args = ap.parse_args()
    open3d()  # import once, outside the timings
    stream = _stream(args.robots, args.seconds)
    configs = {
        "default: every cloud, 1 cm thinning, extract every 10 clouds or 1 s": MapConfig(),
        "every cloud, extract every 30 clouds (1 s)": MapConfig(
            window_clouds=30, extract_every_clouds=30, extract_every_points=120_000
        ),
        "operator cap: 10 clouds/s per robot (max_cloud_rate_hz=10), extract every 1 s": MapConfig(
            max_cloud_rate_hz=10.0
        ),
    }
    load0 = os.getloadavg()[0]
    rows = []
    for name, cfg in configs.items():
        r = bench_stream(cfg, stream)
        rows.append((name, r))
        print(name, r, flush=True)
    full = bench_full(MapConfig(extract_every_points=200_000), stream)
    load1 = os.getloadavg()[0]
    need = args.robots * 30
    lines = [
        f"## Map update cost ({args.robots} robots interleaved, {rows[0][1]['points_per_cloud']:.0f} points per "
        f"cloud, {rows[0][1]['clouds']} clouds; load average {load0:.1f} -> {load1:.1f} on {os.cpu_count()} cores)",
        "",
        "| configuration | CPU ms/cloud mean | p50 | p99 | max | wall ms/cloud mean | wall p99 | sustainable "
        f"clouds/s (1 thread) | needed for {args.robots} x 30 Hz | planes |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, r in rows:
        c, w = r["cpu"], r["wall"]
        lines.append(
            f"| {name} | {c[0]:.2f} | {c[1]:.2f} | {c[2]:.1f} | {c[3]:.1f} | {w[0]:.2f} | {w[2]:.1f} | "
            f"{r['rate']:.0f} | {need} | {r['planes']} |"
        )
    lines += [
        "",
        "## Full re-extraction of one window",
        "",
        "| points | CPU ms | wall ms | planes found |",
        "|---|---|---|---|",
        f"| {full['points']} | {full['cpu_ms']:.1f} | {full['wall_ms']:.1f} | {full['planes']} |",
        "",
    ]
    text = "\n".join(lines)
    print(text)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
