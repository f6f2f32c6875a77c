"""Benchmark of the plane workers: a fleet replayed through a real base station with 0, 1, 2, 4 worker processes.

    python benchmarks/bench_workers.py [--robots 20] [--seconds 4] [--workers 0,1,2,4] [--out ...]

A synthetic tank dive (``mapping.synth``, ~3300 points per cloud, robot k replays base robot k % 2 shifted in
time, as in bench_mapping) is published by a separate process over Zenoh (TCP loopback) to a base station (a
router session in this process) whose map runs in its own thread (0 workers) or in N ``lrsensor map-worker``
processes. Two runs per configuration, navigation on and off:

* **flood**: every cloud published as fast as the BLOCK publisher lets it; clouds/s = clouds / (first received to
  all committed, the final flush included): the throughput the base and its workers sustain.
* **real time**: the fleet at its real rate (robots x 30 Hz, capture time = publication time); the map-update
  latency p50/p99 (capture to commit, ``map.latency_ms``) and whether every cloud reached the map.

Navigation runs as ``lrsensor base`` runs it by default (``--nav filter``): in the base's map thread with 0
workers (every scan registered), in the workers otherwise (``services.map_worker_nav``: every sixth scan at 30 Hz
registered, against the workers' mirror of the merged planes). CPU: the base process's, and the worker processes'
(from /proc) during the flood.

The same map: the planes of the flood run (map frame) against one ``MapBuilder`` fed the same clouds in capture
order (the merge is order-sensitive), largest angle and offset difference over the large faces; with navigation,
the reference also navigates in that one process by the workers' rule (``WorkerNav``: the stride, the filter; a
registered scan against the builder's ``snapshot(T)``, ``MapBuilder.snapshot_landmarks``, the lag the base's
workers use). The snapshot columns: scans that waited for their snapshot in the workers, the longest wait, and
scans registered against another snapshot (late past the cap) with observations merged late or past the hold cap.
"""

from __future__ import annotations

import argparse
import math
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:  # run as a script: python benchmarks/bench_workers.py
    sys.path.insert(0, str(ROOT))


def fleet_frames(robots: int, seconds: float) -> list[tuple[str, int, Any, Any]]:
    """(robot, capture t_ns, points_body float32, pose) in capture-time order, robots interleaved."""
    from mapping.synth import simulate_dive, tank, two_rov_plans

    frames = simulate_dive(tank(), two_rov_plans(), duration_s=seconds, rate_hz=30.0, n_rays=1900, seed=3)
    base = {r: [f for f in frames if f.robot == r] for r in ("rov1", "rov2")}
    n = len(base["rov1"])
    out = []
    for i in range(n):
        for k in range(robots):
            src = base["rov1" if k % 2 == 0 else "rov2"][(i + 7 * k) % n]
            out.append((f"r{k:02d}", base["rov1"][i].t_ns, src.points_body.astype(np.float32), src.pose_est))
    return out


def publish(endpoint: str, fleet: str, robots: int, seconds: float, paced: bool) -> int:
    """The publisher process: every robot's clouds, flooded or at 30 Hz (capture time = publication time)."""
    import zenoh

    from services.keys import FleetKeys
    from services.wire import CloudMsg
    from services.zconfig import NetworkOptions, open_session

    keys = FleetKeys(fleet)
    stream = fleet_frames(robots, seconds)
    seqs: dict[str, int] = {}
    with open_session(NetworkOptions(mode="client", connect=(endpoint,)), "client") as s:
        names = sorted({r for r, *_ in stream})
        pubs = {r: s.declare_publisher(keys.cloud(r), congestion_control=zenoh.CongestionControl.BLOCK) for r in names}
        t0_cap = stream[0][1]
        t0 = time.time_ns()
        print("ready", flush=True)
        sys.stdin.readline()
        t0 = time.time_ns()
        for robot, t_ns, pts, pose in stream:
            if paced:
                due = t0 + (t_ns - t0_cap)
                wait = (due - time.time_ns()) / 1e9
                if wait > 0:
                    time.sleep(wait)
                t_ns = time.time_ns()
            seq = seqs.get(robot, 0)
            seqs[robot] = seq + 1
            n = len(pts)
            msg = CloudMsg(robot, seq, t_ns, pose, pts, np.zeros(n, np.uint8), np.ones(n, np.float32))
            pubs[robot].put(msg.to_bytes())
        time.sleep(2.0)  # let the last samples leave before the session closes (closing drops what is queued)
        for p in pubs.values():
            p.undeclare()
    return 0


def reference_planes(
    robots: int,
    seconds: float,
    nav: bool = False,
    lag_s: float = 0.0,
    every_s: float | None = None,
    snapshot_lag_s: float | None = None,
) -> list[dict[str, Any]]:
    """The map of one ``MapBuilder`` fed the publisher's clouds in capture order, then flushed: with the raw poses,
    or with ``nav`` the poses one process's ``WorkerNav`` (stride ``every_s``, default the workers') corrects
    against the builder's planes of the moment, or with ``lag_s`` those of ``lag_s`` of capture time before, or
    with ``snapshot_lag_s`` by the workers' rule: ``snapshot(T)`` of that lag."""
    from collections import deque

    from mapping import MapBuilder, MapConfig
    from mapping.navigation import NavConfig
    from services.map_worker_nav import REGISTER_EVERY_S, WorkerNav

    b = MapBuilder(MapConfig())
    wn = WorkerNav(register_every_s=REGISTER_EVERY_S if every_s is None else every_s)
    min_points = NavConfig().min_landmark_points
    seen: deque[tuple[int, Any]] = deque()  # (capture time the planes became these, planes)
    mirror = b.landmarks(min_points)
    for robot, t_ns, pts, raw in fleet_frames(robots, seconds):
        pose = raw
        if nav:
            lm = b.landmarks(min_points)
            if not seen or seen[-1][1] is not lm:
                seen.append((t_ns, lm))
            while seen and seen[0][0] <= t_ns - lag_s * 1e9:
                mirror = seen.popleft()[1]
            if snapshot_lag_s is not None:
                lm = b.snapshot_landmarks(t_ns, round(snapshot_lag_s * 1e9), min_points)
            step = wn.step(robot, t_ns, raw, pts, mirror if lag_s > 0 else lm)
            if step.pose is None or not step.placed:
                b.advance_time(robot, t_ns)  # as a worker does: the robot's pending clouds due by time
                continue
            pose = step.pose
        b.add_cloud_body(robot, t_ns, pts.astype(np.float64), pose)
    b.flush()
    planes: list[dict[str, Any]] = b.map_json()["planes"]
    return planes


def _proc_cpu_s(pids: list[int]) -> float:
    """User + system CPU seconds of these processes so far (Linux /proc; 0 for a process gone)."""
    tick = os.sysconf("SC_CLK_TCK")
    total = 0.0
    for pid in pids:
        try:
            fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        total += (int(fields[11]) + int(fields[12])) / tick
    return total


def run_one(
    n_workers: int, nav: bool, paced: bool, robots: int, seconds: float, lag_s: float | None = None
) -> dict[str, Any]:
    """One configuration through a real base station; returns the figures."""
    from services.base import BaseStation
    from services.testnet import TestNetwork

    with TestNetwork("bench") as net:
        base = net.base = BaseStation(
            net.router,
            net.keys,
            None,
            map_mode="on",
            navigation=nav,
            map_workers=n_workers,
            worker_endpoint=net.endpoint if n_workers else None,
            save_period_s=60.0,
        )
        base.feed.set_smoothing(False)  # lrsensor base's default, --nav filter
        base.start()
        if n_workers:
            assert base.feed.pool is not None
            if not base.feed.pool.wait_for_workers(n_workers, 120):
                msg = "the worker processes did not come up"
                raise RuntimeError(msg)
            if lag_s is not None:  # before the first cloud: every job carries it
                base.feed.pool.snapshot_lag_ns = round(lag_s * 1e9)
        cmd = [sys.executable, __file__, "--publish", net.endpoint, "--fleet", "bench", "--robots", str(robots)]
        cmd += ["--seconds", str(seconds)] + (["--paced"] if paced else [])
        pub = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, cwd=ROOT)
        assert pub.stdin is not None
        assert pub.stdout is not None
        pub.stdout.readline()  # ready: the frames are simulated
        pids = [p.pid for p in getattr(base, "_worker_procs", [])]
        cpu0 = os.times()
        wcpu0 = _proc_cpu_s(pids)
        pub.stdin.write(b"go\n")
        pub.stdin.flush()
        t_first = None
        deadline = time.monotonic() + 600
        pub_cpu0 = _proc_cpu_s([pub.pid])
        pub_cpu = 0.0
        while time.monotonic() < deadline and pub.poll() is None:
            if t_first is None and base.processed > 0:
                t_first = time.perf_counter()
            pub_cpu = max(pub_cpu, _proc_cpu_s([pub.pid]) - pub_cpu0)  # read while it lives
            time.sleep(0.02)
        pub.wait(60)
        base.drain(600)
        total = base.processed
        base.flush_map(600)
        t_end = time.perf_counter()
        cpu1 = os.times()
        wcpu1 = _proc_cpu_s(pids)
        st = base.status()
        mapped = sum(v.get("mapped", 0) for v in st["robots"].values())
        assert base.map is not None
        planes = base.map.map_json()["planes"]  # the map frame (the reference's), not turned by the fleet frame
        unplaced = st["map"]["unplaced"]
        snaps = st["map"].get("worker_pool", {}).get("snapshots")
    wall = t_end - (t_first or t_end)
    return {
        "workers": n_workers,
        "nav": nav,
        "paced": paced,
        "clouds": total,
        "mapped": mapped,
        "unplaced": unplaced,
        "rate": total / wall if wall > 0 else float("nan"),
        "p50": st["map"]["latency_ms"]["p50"],
        "p99": st["map"]["latency_ms"]["p99"],
        "base_cpu_s": (cpu1.user + cpu1.system) - (cpu0.user + cpu0.system),
        "worker_cpu_s": wcpu1 - wcpu0,
        "pub_cpu_s": pub_cpu,
        "wall_s": wall,
        "planes": planes,
        "snapshots": snaps,
    }


def plane_diff(a: list[dict[str, Any]], b: list[dict[str, Any]], min_points: int = 10_000) -> tuple[float, float]:
    """Largest angle (deg) and offset (m) between each large plane of ``a`` and its nearest in ``b``."""
    worst_a, worst_d = 0.0, 0.0
    for p in (p for p in a if p["n_points"] >= min_points):
        best = min(b, key=lambda q: abs(q["d"] - p["d"]) + 1 - float(np.dot(q["normal"], p["normal"])))
        worst_a = max(worst_a, math.degrees(math.acos(min(1.0, float(np.dot(best["normal"], p["normal"]))))))
        worst_d = max(worst_d, abs(best["d"] - p["d"]))
    return worst_a, worst_d


def tank_score(planes: list[dict[str, Any]], seconds: float) -> tuple[float, float, int, int]:
    """Against the simulated tank: worst angle (deg) and offset (m) over the faces hit, faces missing (2 deg,
    5 cm), duplicated faces."""
    from mapping.synth import hit_faces, score_map, simulate_dive, tank, two_rov_plans

    frames = simulate_dive(tank(), two_rov_plans(), duration_s=seconds, rate_hz=30.0, n_rays=1900, seed=3)
    sc = score_map(planes, tank(), hit_faces(tank(), frames))
    hit = [f for f in sc.faces if f.hit]
    worst_a = max((f.angle_deg for f in hit), default=float("nan"))
    worst_d = max((f.offset_m for f in hit), default=float("nan"))
    return worst_a, worst_d, len(sc.missing()), len(sc.duplicates())


def same_map_nav(
    robots: int, seconds: float, flood: list[dict[str, Any]], ref: list[dict[str, Any]], lag: float
) -> str:
    """With navigation: the worker runs' maps and one process's variants against one process by the workers' rule
    (``ref``: the stride, ``snapshot(T)`` of ``lag``), and each against the tank."""
    variants: list[tuple[str, list[dict[str, Any]]]] = [
        (f"one process, every 6th scan, snapshot(T) of {lag:g} s before (the reference)", ref),
        ("one process, every 6th scan, the planes of the moment", reference_planes(robots, seconds, True)),
        ("one process, every scan, the planes of the moment", reference_planes(robots, seconds, True, every_s=0.0)),
    ]
    for old in (0.3, 0.6):
        name = f"one process, every 6th scan, the planes of {old:g} s before"
        variants.append((name, reference_planes(robots, seconds, True, old)))
    variants.append(("one process, no navigation (raw poses)", reference_planes(robots, seconds, False)))
    variants += [(f"flood through {f['workers']} worker processes", f["planes"]) for f in flood]
    lines = [
        "| map (navigation on, seeded replay) | vs the reference: max deg | max mm | vs the tank: worst deg | worst mm "
        "| faces missing | duplicated |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, planes in variants:
        da, dd = plane_diff(ref, planes)
        ta, td, miss, dup = tank_score(planes, seconds)
        lines.append(f"| {name} | {da:.2f} | {dd * 1e3:.1f} | {ta:.2f} | {td * 1e3:.1f} | {miss} | {dup} |")
    return "\n".join(lines)


def _ms(v: float | None) -> str:
    return "-" if v is None else f"{v:.0f}"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--robots", type=int, default=20)
    ap.add_argument("--seconds", type=float, default=4.0, help="simulated dive length per robot")
    ap.add_argument("--workers", default="0,1,2,4", help="worker process counts (0: the map in the base process)")
    ap.add_argument("--nav", default="off,on", help="navigation settings to run: off, on or both")
    ap.add_argument("--no-same-map", action="store_true", help="leave out the same-map check with navigation")
    ap.add_argument("--lag-s", type=float, default=None, help="the workers' snapshot lag (default: the base's)")
    ap.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "workers.md")
    ap.add_argument("--publish", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--fleet", default="bench", help=argparse.SUPPRESS)
    ap.add_argument("--paced", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.publish:
        return publish(args.publish, args.fleet, args.robots, args.seconds, args.paced)
    counts = [int(x) for x in args.workers.split(",")]
    load0 = os.getloadavg()[0]
    rows = []
    for nav in [x == "on" for x in args.nav.split(",")]:
        for n in counts:
            flood = run_one(n, nav, False, args.robots, args.seconds, args.lag_s)
            real = run_one(n, nav, True, args.robots, args.seconds, args.lag_s)
            rows.append((flood, real))
            print(
                f"workers {n} nav {nav}: {flood['rate']:.0f} clouds/s, real time p50 {real['p50']} p99 {real['p99']} "
                f"ms, mapped {real['mapped']}/{real['clouds']}, snapshots flood {flood['snapshots']} real "
                f"{real['snapshots']} (load {os.getloadavg()[0]:.1f})",
                flush=True,
            )
    load1 = os.getloadavg()[0]
    need = args.robots * 30
    lines = [
        f"## Plane workers ({args.robots} robots x 30 Hz, {args.seconds:g} s of dive = {rows[0][0]['clouds']} clouds "
        f"of ~3300 points; load average {load0:.1f} -> {load1:.1f} on {os.cpu_count()} cores)",
        "",
        f"| map workers | navigation | flood: clouds/s (needed {need}) | flood CPU s: base + workers (publisher) | "
        "real time: map "
        "latency p50 ms | p99 ms | real time: mapped / sent (unplaced) | flood planes vs one process in capture order: "
        "max deg | max mm | snapshot waits: flood / real time (longest ms) | not exact: flood / real time |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    from services.map_worker_nav import SNAPSHOT_LAG_S

    lag = SNAPSHOT_LAG_S if args.lag_s is None else args.lag_s
    refs = {
        nav: reference_planes(args.robots, args.seconds, nav, snapshot_lag_s=lag if nav else None)
        for nav in {f["nav"] for f, _ in rows}
    }
    for flood, real in rows:
        da, dd = plane_diff(refs[flood["nav"]], flood["planes"])
        fs, rs = flood["snapshots"], real["snapshots"]
        if fs and rs:
            waits = f"{fs['waited']} / {rs['waited']} ({fs['max_wait_ms']} / {rs['max_wait_ms']})"
            inexact = f"{fs['not_exact'] + fs['late'] + fs['forced']} / {rs['not_exact'] + rs['late'] + rs['forced']}"
        else:
            waits = inexact = "-"
        name = "0 (map thread in the base process)" if flood["workers"] == 0 else f"{flood['workers']} processes"
        nav = "off" if not flood["nav"] else ("every scan, base" if flood["workers"] == 0 else "every 6th, workers")
        lines.append(
            f"| {name} | {nav} | {flood['rate']:.0f} | {flood['base_cpu_s']:.1f} + {flood['worker_cpu_s']:.1f} "
            f"({flood['pub_cpu_s']:.1f}) | "
            f"{_ms(real['p50'])} | {_ms(real['p99'])} | {real['mapped']} / {real['clouds']} ({real['unplaced']}) | "
            f"{da:.2f} | {dd * 1e3:.1f} | {waits} | {inexact} |"
        )
    lines.append("")
    nav_floods = [f for f, _ in rows if f["nav"] and f["workers"] > 0]
    if nav_floods and not args.no_same_map:
        table = same_map_nav(args.robots, args.seconds, nav_floods, refs[True], lag)
        lines += ["### The same map with navigation", "", table, ""]
    text = "\n".join(lines)
    print(text)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
