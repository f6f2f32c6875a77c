"""The merger's own ceiling: plane observations per second one base station can fuse into the shared map.

    python benchmarks/bench_merger.py [--cases 20x1,20x20,100x100] [--seconds 6]

With plane workers (``lrsensor base --map-workers N``, docs/scaling.md) the base station keeps one serial job
for the map: decode each worker's :class:`~services.map_worker_wire.PlaneObservations`, turn its records back
into :class:`~mapping.PlaneRecord` values, and fuse them (``MapBuilder.merge``: association and exact addition of
statistics). Everything per robot runs in the workers and scales with their number; this serial part does not,
so it sets how many robots one base can serve however many workers it has.

The observations here are the real ones: a synthetic dive (``mapping.synth``, as in bench_workers: robot k
replays one of two tank robots shifted in time, ~3300 points a cloud at 30 Hz) goes through a worker-side
``MapBuilder.observe_cloud`` and out as wire payloads, exactly as :class:`services.map_worker.MapWorker` sends
them. Then the merge alone is timed on a fresh map, in capture order, on one thread:

* **R robots x 1 site**: every robot in the one tank (a dozen large planes, every observation associates with
  one);
* **R robots x R sites**: robot k's dive moved 40 m east per k (its own tank): a map R times larger to search,
  as a fleet spread over a harbour would make.

Reported: payloads and observations per second, what that is in clouds per second (each payload commits the
clouds of one extraction window) and in robots at 30 Hz, the share of the time in decoding. Writes
``benchmarks/results/merger.md``.
"""

from __future__ import annotations

import argparse
import os
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

try:
    from benchmarks.bench_workers import fleet_frames
except ImportError:  # run as a script: python benchmarks/bench_merger.py
    from bench_workers import fleet_frames  # type: ignore[no-redef]


def observations(robots: int, seconds: float, site_spacing_m: float) -> tuple[list[bytes], int]:
    """The wire payloads a worker serving every robot sends for the dive, in capture order; and the clouds."""
    from mapping import MapBuilder, MapConfig
    from mapping.ned import cloud_to_ned
    from mapping.plane_map import record_to_wire
    from services.map_worker_wire import PlaneObservations

    worker = MapBuilder(MapConfig())
    pending: dict[str, list[int]] = {}
    payloads: list[bytes] = []
    frames = fleet_frames(robots, seconds)
    for robot, t_ns, pts, pose in frames:
        k = int(robot[1:])
        pose = replace(pose, east_m=pose.east_m + k * site_spacing_m)
        seqs = pending.setdefault(robot, [])
        seqs.append(len(seqs))
        records = worker.observe_cloud(robot, t_ns, cloud_to_ned(pts.astype(np.float64), pose), pose)
        if records is not None:
            wire = tuple(record_to_wire(r) for r in records)
            payloads.append(PlaneObservations("w0", robot, 1, tuple(seqs), wire, t_ns).to_bytes())
            pending[robot] = []
    return payloads, len(frames)


def merge_all(payloads: list[bytes]) -> dict[str, Any]:
    """Decode and merge every payload into a fresh map on this thread; the times (s) and counts."""
    from mapping import MapBuilder, MapConfig
    from mapping.plane_map import record_from_wire
    from services.map_worker_wire import PlaneObservations

    merger = MapBuilder(MapConfig())
    decode_s = merge_s = 0.0
    n_obs = n_clouds = 0
    for payload in payloads:
        t0 = time.perf_counter()
        obs = PlaneObservations.from_bytes(payload)
        records = [record_from_wire(r) for r in obs.records]
        t1 = time.perf_counter()
        merger.merge(records)
        t2 = time.perf_counter()
        decode_s += t1 - t0
        merge_s += t2 - t1
        n_obs += len(records)
        n_clouds += len(obs.seqs)
    return {
        "payloads": len(payloads),
        "observations": n_obs,
        "clouds": n_clouds,
        "decode_s": decode_s,
        "merge_s": merge_s,
        "planes": merger.n_planes,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", default="20x1,20x20,100x100", help="ROBOTSxSITES, comma-separated (sites 1 or ROBOTS)")
    ap.add_argument("--seconds", type=float, default=6.0, help="simulated dive length per robot")
    ap.add_argument("--repeats", type=int, default=3, help="merge runs per case (the best is reported)")
    ap.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "merger.md")
    args = ap.parse_args(argv)
    load0 = os.getloadavg()[0]
    rows = []
    for case in args.cases.split(","):
        robots, sites = (int(v) for v in case.split("x"))
        if sites not in (1, robots):
            ap.error(f"--cases {case}: sites must be 1 or the number of robots")
        payloads, clouds = observations(robots, args.seconds, 40.0 if sites > 1 else 0.0)
        runs = [merge_all(payloads) for _ in range(args.repeats)]
        best = min(runs, key=lambda r: r["decode_s"] + r["merge_s"])
        if best["clouds"] != clouds:
            msg = f"the payloads commit {best['clouds']} clouds, the dive has {clouds}"
            raise RuntimeError(msg)
        total = best["decode_s"] + best["merge_s"]
        rows.append((robots, sites, best, total))
        print(f"{case}: {best['observations'] / total:.0f} observations/s, {best['clouds'] / total:.0f} clouds/s")
    load1 = os.getloadavg()[0]
    lines = [
        f"## The merger's ceiling ({args.seconds:g} s of dive per robot at 30 Hz; one thread; best of "
        f"{args.repeats}; load average {load0:.1f} -> {load1:.1f} on {os.cpu_count()} cores)",
        "",
        "`python benchmarks/bench_merger.py`",
        "",
        "| robots | sites | planes in the map | payloads | observations | payloads/s | observations/s | clouds/s "
        "| robots at 30 Hz | decoding share |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for robots, sites, r, total in rows:
        lines.append(
            f"| {robots} | {sites} | {r['planes']} | {r['payloads']} | {r['observations']} | "
            f"{r['payloads'] / total:.0f} | {r['observations'] / total:.0f} | {r['clouds'] / total:.0f} | "
            f"{r['clouds'] / total / 30:.0f} | {100 * r['decode_s'] / total:.0f} % |"
        )
    lines += [
        "",
        "A payload is one extraction of one robot's window (it commits the clouds since the last one); clouds/s is "
        "what the merge alone sustains, the ceiling of one base station whatever the number of workers.",
        "",
    ]
    text = "\n".join(lines)
    print(text)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
