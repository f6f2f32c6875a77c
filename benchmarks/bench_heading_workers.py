"""The map of a depth-only (or mixed) fleet with plane workers against the base's map thread (issue 27).

    python benchmarks/bench_heading_workers.py [--modes depth-only,mixed] [--seeds 1] [--seconds 90]
        [--workers 2] [--runs 1] [--out benchmarks/results/heading_workers.md]

``bench_nav``'s 3-robot dive of one navigation (ray-traced clouds, 10 Hz, the same plans, seed and navigation noise)
is published over Zenoh, in capture order and as fast as the base takes it (a map that falls behind holds the
publishers back: no cloud is left out), to a base station as ``lrsensor base
--nav on`` runs it (``--no-fix graph``; the smoother's runs handed over at once, ``--smoother wait``), three ways:

* ``map thread``: no plane worker (what a 2-core machine runs by default);
* ``N workers, no fleet heading``: N plane workers in this process (``services.map_worker.MapWorker`` on their own
  sessions, as ``lrsensor base --map-workers N`` runs them in processes), the fleet heading left out of the
  workers (:class:`services.map_worker_heading.HeadingRelay` says nothing: what the workers did before it);
* ``N workers``: the same, with the fleet heading (the views in the workers, the estimate at the base).

The map the base serves (``lrs/<fleet>/map``, turned by its frame) is scored as ``bench_nav`` scores it
(:func:`mapping.synth.score_map`: seen faces, recovered within 2 deg and 5 cm, duplicates, spurious planes), with
what the status says of each robot's heading and the CPU time of this process (the base and its workers; the
machine's other load inflates wall times, not CPU).
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:  # run as a script: python benchmarks/bench_heading_workers.py
    sys.path.insert(0, str(ROOT))

from benchmarks.bench_nav import MODES  # noqa: E402
from benchmarks.bench_nav_procs import _score  # noqa: E402


def run(
    frames: list[Any], mode: str, seed: int, workers: int, heading: bool, lag_s: float | None = None
) -> tuple[Any, dict[str, Any]]:
    """One replay through a base with ``workers`` in-process plane workers (0: its map thread); ``heading`` False
    leaves the fleet heading out of the workers; ``lag_s``: the workers' snapshot lag (None: the base's). The scored
    row and the base's status."""
    import zenoh

    import services.map_worker_heading as relay_module
    from services.base import BaseStation
    from services.map_worker import MapWorker
    from services.testnet import TestNetwork
    from services.wire import CloudMsg

    phase = relay_module.HeadingRelay.phase
    if not heading:
        relay_module.HeadingRelay.phase = lambda self, *a: ""  # type: ignore[method-assign]
    c0, t0 = time.process_time(), time.perf_counter()
    try:
        with TestNetwork(f"hw{workers}") as net:
            # not a rate test: a map that falls behind holds the publishers back (BLOCK) instead of leaving clouds out
            base = BaseStation(net.router, net.keys, None, map_mode="on", navigation=True, remote_workers=workers > 0,
                               no_fix="graph", map_wait_s=3600.0)  # fmt: skip
            base.feed.set_smoothing(True, wait=True)  # --smoother wait (a no-op with workers: no smoother there)
            net.base = base
            base.start()
            pool = [MapWorker(net.session(), net.keys, f"w{i}") for i in range(workers)]
            for w in pool:
                w.start()
            try:
                if base.feed.pool is not None:
                    assert base.feed.pool.wait_for_workers(workers, 30)
                    if lag_s is not None:
                        base.feed.pool.snapshot_lag_ns = round(lag_s * 1e9)
                s = net.session()
                robots = sorted({f.robot for f in frames})
                pubs = {r: s.declare_publisher(net.keys.cloud(r), congestion_control=zenoh.CongestionControl.BLOCK)
                        for r in robots}  # fmt: skip
                seqs: dict[str, int] = {}
                for f in frames:
                    seq = seqs[f.robot] = seqs.get(f.robot, -1) + 1
                    pts = f.points_body.astype(np.float32)
                    n = len(pts)
                    msg = CloudMsg(f.robot, seq, f.t_ns, f.pose_est, pts, np.zeros(n, np.uint8), np.ones(n, np.float32))
                    pubs[f.robot].put(msg.to_bytes())
                deadline = time.monotonic() + 600
                while base.processed < len(frames) and time.monotonic() < deadline:
                    time.sleep(0.1)
                base.drain(600)
                while base.feed.pool is not None and base.feed.pool.in_flight and time.monotonic() < deadline:
                    time.sleep(0.2)  # the workers' queues (a flush waits 60 s at most)
                base.flush_map(600)
                status = base.status()
                planes = base.feed.map_json()["planes"]
            finally:
                for w in pool:
                    w.close()
    finally:
        relay_module.HeadingRelay.phase = phase  # type: ignore[method-assign]
    way = "map thread" if workers == 0 else f"{workers} workers" + ("" if heading else ", no fleet heading")
    way += "" if lag_s is None or not workers else f", snapshot lag {lag_s:g} s"
    row = _score(mode, seed, way, planes, frames)
    row.cpu_s = {"this process": time.process_time() - c0}
    row.wall_s = time.perf_counter() - t0
    robots_st = status.get("robots", {})
    row.placed = {r: int(v.get("nav", {}).get("placed", 0)) for r, v in sorted(robots_st.items())}
    row.heading = ", ".join(f"{r} {v.get('nav', {}).get('heading')}" for r, v in sorted(robots_st.items()))
    return row, status


def table(rows: list[Any], status: list[dict[str, Any]]) -> str:
    """The markdown table of the rows."""
    lines = [
        "| navigation | seed | road | faces seen / recovered (2 deg, 5 cm) | worst angle (deg) / offset (cm) | "
        "duplicates | spurious | faces off | clouds placed (unplaced) per robot, of received | heading (status) | "
        "fleet heading's wait (s) | left out (map behind) | CPU s | wall s |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r, st in zip(rows, status, strict=True):
        fh = st.get("map", {}).get("worker_pool", {}).get("fleet_heading")
        wait = "-" if not fh else f"{fh['wait_s']:.2f}"
        robots = st.get("robots", {})
        unplaced = {k: robots.get(k, {}).get("nav", {}).get("unplaced", "-") for k in r.placed}
        placed = " / ".join(f"{v} ({unplaced[k]})" for k, v in r.placed.items())
        lines.append(
            f"| {r.mode} | {r.seed} | {r.way} | {r.seen} / {r.recovered} | {r.worst_angle_deg:.2f} / "
            f"{r.worst_offset_cm:.1f} | {r.duplicates} | {r.spurious} | {r.faces_off or '-'} | {placed} (of "
            f"{r.clouds}) | {r.heading} | {wait} | {st.get('map', {}).get('skipped', '-')} | "
            f"{r.cpu_s['this process']:.0f} | {r.wall_s:.0f} |"
        )
    return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--modes", default="depth-only,mixed")
    ap.add_argument("--seeds", default="1")
    ap.add_argument("--seconds", type=float, default=90.0)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--runs", type=int, default=1, help="draws of each road with workers")
    ap.add_argument("--ways", default="thread,before,after", help="of: thread, before (no fleet heading), after")
    ap.add_argument("--lag-s", type=float, default=None, help="the workers' snapshot lag (default: the base's)")
    ap.add_argument("--out", type=Path, default=None, help="append the table to this markdown file")
    args = ap.parse_args()
    from mapping.synth import simulate_dive, tank, three_rov_plans

    rows: list[Any] = []
    stats: list[dict[str, Any]] = []
    ways = args.ways.split(",")
    for mode in args.modes.split(","):
        for seed in (int(s) for s in args.seeds.split(",")):
            frames = simulate_dive(tank(), three_rov_plans(), duration_s=args.seconds, rate_hz=10.0, n_rays=400,
                                   seed=seed, navigation=MODES[mode])  # fmt: skip
            todo = [(0, True)] if "thread" in ways else []
            todo += [(args.workers, False)] * args.runs if "before" in ways else []
            todo += [(args.workers, True)] * args.runs if "after" in ways else []
            for workers, heading in todo:
                row, st = run(frames, mode, seed, workers, heading, args.lag_s)
                rows.append(row)
                stats.append(st)
                print(table(rows[-1:], stats[-1:]), flush=True)
    text = table(rows, stats)
    print(text)
    if args.out is not None:
        with args.out.open("a") as fh:
            fh.write(text + "\n")
    return 0 if all(math.isfinite(r.worst_angle_deg) for r in rows) else 1


if __name__ == "__main__":
    raise SystemExit(main())
