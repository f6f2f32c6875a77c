"""Base-station ingest benchmark: N simulated robots at 30 Hz, ~3800 points per cloud, against one base station.

Each step of the sweep starts a fresh ``lrsensor base`` process (router in-process, map off unless ``--map``) on a
free loopback port, then this process plays N robots: one Zenoh client session, one BLOCK/reliable publisher per
robot, clouds synthesized (no rendering) and stamped with their capture time just before encoding. After
``--duration-s`` the base station is given time to drain, and its status is read:

* clouds/s sustained: distinct clouds the base station accepted over the publishing window;
* latency p50/p99: base-station processing time minus capture time (both on this machine's clock), in ms;
* loss: clouds published but never accepted (counted by sequence number);
* base CPU: the base process's user+system CPU time over the run, in % of one core.

Run: ``python benchmarks/bench_ingest.py [--robots 1,5,10,20,30,40] [--duration-s 8] [--map]``. Prints a
Markdown table and writes it to ``benchmarks/results/ingest.md``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
RATE_HZ = 30.0
POINTS = 3800
TARGET_ROBOTS = 20
TARGET_P99_MS = 50.0
#: Encoded size of one synthetic cloud (with uv), bytes: 3800 x (12 + 1 + 4 + 8) + header.
CLOUD_BYTES = POINTS * 25 + 200


def synth_clouds(n_variants: int = 8, seed: int = 0) -> list[dict[str, np.ndarray]]:
    """A few body-frame clouds like a 1920-column two-laser frame of a wall 1-3 m ahead."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n_variants):
        u = np.tile(np.linspace(0, 1919, POINTS // 2), 2)
        laser = np.repeat(np.arange(2), POINTS // 2).astype(np.uint8)
        x = rng.uniform(1.0, 3.0) + 0.01 * rng.standard_normal(POINTS)
        y = (u - 959.5) / 554.3 * x
        z = np.where(laser == 0, -0.05, 0.05)
        pts = np.stack([x, y, z], axis=1).astype(np.float32)
        uv = np.stack([u, 540 + 554.3 * z / x], axis=1).astype(np.float32)
        out.append({"points": pts, "laser": laser, "quality": rng.uniform(0.5, 1, POINTS).astype(np.float32), "uv": uv})
    return out


def cpu_seconds(pid: int) -> float:
    """User + system CPU time of a process, seconds (Linux /proc)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def get_status(session: Any, fleet: str) -> dict[str, Any] | None:
    for reply in session.get(f"lrs/{fleet}/base/status", timeout=5.0):
        if reply.ok is not None:
            data: dict[str, Any] = json.loads(reply.ok.payload.to_bytes())
            return data
    return None


def _generate_worker(
    ep: str, fleet: str, robots: list[str], duration_s: float, barrier: Any, start: Any, results: Any
) -> None:
    results.put(generate(ep, fleet, robots, duration_s, 0.0, barrier=barrier, start=start))


def generate(
    ep: str,
    fleet: str,
    robots: list[str],
    duration_s: float,
    start_wall: float,
    barrier: Any = None,
    start: Any = None,
) -> tuple[int, float]:
    """Publish 30 Hz clouds for ``robots`` from ``start_wall`` (Unix time) for ``duration_s``.

    Returns (clouds sent, worst lag behind the schedule in s). Runs in this process or in a worker process.
    """
    import zenoh

    from lrsensor.frames import Pose
    from services.wire import ENCODING, CloudMsg
    from services.zconfig import NetworkOptions, open_session

    clouds = synth_clouds()
    n = len(robots)
    with open_session(NetworkOptions(mode="client", connect=(ep,)), "client") as session:
        pubs = [
            session.declare_publisher(
                f"lrs/{fleet}/{r}/cloud",
                encoding=zenoh.Encoding(ENCODING),
                congestion_control=zenoh.CongestionControl.BLOCK,
                reliability=zenoh.Reliability.RELIABLE,
            )
            for r in robots
        ]
        for p in pubs:
            while not p.matching_status.matching:
                time.sleep(0.01)
        if barrier is not None:  # several generator processes: start together
            barrier.wait(timeout=120)
            barrier.wait(timeout=10)
            start_wall = float(start.value)
        period = 1.0 / (RATE_HZ * n)
        n_total = int(duration_s * RATE_HZ) * n
        seqs = [0] * n
        lag_max = 0.0
        for i in range(n_total):
            due = start_wall + i * period
            now = time.time()
            if due > now:
                time.sleep(due - now)
            else:
                lag_max = max(lag_max, now - due)
            k = i % n
            c = clouds[(i // n + k) % len(clouds)]
            msg = CloudMsg(
                robots[k],
                seqs[k],
                time.time_ns(),
                Pose(1.0 + 0.01 * k, 2.0, 1.5, 0.0, 0.0, 0.3),
                c["points"],
                c["laser"],
                c["quality"],
                c["uv"],
                time.time_ns(),
            )
            pubs[k].put(msg.to_bytes())
            seqs[k] += 1
        # keep the session open until the base station holds every cloud: closing a session drops what is
        # still queued for transmission
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            st = get_status(session, fleet)
            if st and sum(st["robots"].get(r, {}).get("received", 0) for r in robots) >= sum(seqs):
                break
            time.sleep(0.1)
        for p in pubs:
            p.undeclare()
    return sum(seqs), lag_max


def run_step(n_robots: int, duration_s: float, with_map: bool, generators: int = 1) -> dict[str, Any]:
    """One step of the sweep: a fresh base station, ``n_robots`` robots for ``duration_s``, its figures."""
    from services.testnet import free_port
    from services.zconfig import NetworkOptions, open_session

    fleet = "bench"
    port = free_port()
    ep = f"tcp/127.0.0.1:{port}"
    base = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "lrsensor",
            "base",
            "--fleet",
            fleet,
            "--listen",
            ep,
            "--map",
            "on" if with_map else "off",
            "--status-every-s",
            "0",
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        session = None
        deadline = time.monotonic() + 30
        while session is None:
            try:
                session = open_session(NetworkOptions(mode="client", connect=(ep,)), "client")
            except Exception:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.1)
        with session:
            while get_status(session, fleet) is None:
                time.sleep(0.1)
            robots = [f"r{k:02d}" for k in range(n_robots)]
            groups = [robots[g::generators] for g in range(generators) if robots[g::generators]]
            cpu0 = cpu_seconds(base.pid)  # includes the generators' start-up: a slight over-estimate of CPU %
            if len(groups) == 1:
                start_wall = time.time() + 0.5
                sent, lag_max = generate(ep, fleet, groups[0], duration_s, start_wall)
            else:
                import multiprocessing as mp

                ctx = mp.get_context("spawn")
                barrier = ctx.Barrier(len(groups) + 1)
                start = ctx.Value("d", 0.0)
                results = ctx.Queue()
                procs = [
                    ctx.Process(target=_generate_worker, args=(ep, fleet, g, duration_s, barrier, start, results))
                    for g in groups
                ]
                for pr in procs:
                    pr.start()
                start.value = 0.0
                barrier.wait(timeout=120)  # every generator is connected and matched
                start.value = time.time() + 0.5
                barrier.wait(timeout=10)  # ... and reads the common start time
                start_wall = float(start.value)
                outs = [results.get(timeout=duration_s + 300) for _ in procs]
                for pr in procs:
                    pr.join(30)
                sent = sum(o[0] for o in outs)
                lag_max = max(o[1] for o in outs)
            t_sent = time.time()
            send_s = t_sent - start_wall
            # drain: wait until every published cloud is accepted or nothing moves for 5 s
            last, still = -1, time.monotonic()
            while True:
                st = get_status(session, fleet)
                got = sum(v["received"] for v in st["robots"].values()) if st else 0
                if got >= sent:
                    break
                if got != last:
                    last, still = got, time.monotonic()
                elif time.monotonic() - still > 5.0:
                    break
                time.sleep(0.1)
            drain_s = time.time() - t_sent
            cpu = cpu_seconds(base.pid) - cpu0
            assert st is not None
            received = sum(v["received"] for v in st["robots"].values())
            lat = st["ingest"]["latency_ms"]
        return {
            "robots": n_robots,
            "offered_hz": n_robots * RATE_HZ,
            "sent": sent,
            "received": received,
            "loss": sent - received,
            "missed": sum(v["missed"] for v in st["robots"].values()),
            "clouds_s": received / max(send_s, 1e-9),
            "send_rate": sent / max(send_s, 1e-9),
            "p50_ms": lat["p50"],
            "p99_ms": lat["p99"],
            "drain_s": drain_s,
            "lag_max_ms": 1000 * lag_max,
            "cpu_pct": 100 * cpu / (send_s + drain_s),
            "mb_s": received * CLOUD_BYTES / max(send_s, 1e-9) / 1e6,
            "map_planes": st["map"]["planes"],
        }
    finally:
        base.send_signal(signal.SIGTERM)
        try:
            base.wait(30)
        except subprocess.TimeoutExpired:
            base.kill()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robots", default="1,5,10,20,30,40,60", help="comma-separated robot counts")
    ap.add_argument("--duration-s", type=float, default=8.0, help="publishing time per step")
    ap.add_argument(
        "--generators", type=int, default=1, help="load-generator processes (robots split among them; default 1)"
    )
    ap.add_argument("--map", action="store_true", help="also build the map (Open3D) in the base station")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "ingest.md"))
    args = ap.parse_args()
    load_before = os.getloadavg()[0]
    rows = []
    for n in (int(x) for x in args.robots.split(",")):
        r = run_step(n, args.duration_s, args.map, args.generators)
        rows.append(r)
        ok = r["loss"] == 0 and r["p99_ms"] is not None and r["p99_ms"] < TARGET_P99_MS
        print(
            f"N={n:3d}: {r['clouds_s']:7.1f} clouds/s of {r['offered_hz']:.0f} offered, p50 {r['p50_ms']} ms, "
            f"p99 {r['p99_ms']} ms, loss {r['loss']}, base CPU {r['cpu_pct']:.0f}%  {'ok' if ok else 'OVER TARGET'}",
            file=sys.stderr,
            flush=True,
        )
    header = (
        f"Base-station ingest ({'map on' if args.map else 'map off'}): N robots x {RATE_HZ:.0f} Hz, {POINTS} points "
        f"per cloud ({rows[0]['mb_s'] / max(rows[0]['clouds_s'], 1e-9) * 1e6 / 1e3:.0f} kB), {args.duration_s:.0f} s "
        f"per step, base station and {args.generators} load-generator process(es) on the same "
        f"{os.cpu_count()}-core machine "
        f"({platform.python_version()}, Zenoh loopback TCP, BLOCK congestion control). "
        f"Latency = base processing time - capture time. 1-min load average before the sweep: {load_before:.1f} "
        f"(other work on the machine inflates the tail)."
    )
    lines = [
        header,
        "",
        "| robots | offered clouds/s | sustained clouds/s | MB/s | p50 ms | p99 ms | loss | missed | base CPU % | "
        "max send lag ms | verdict |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|",
    ]
    saturated = None
    for r in rows:
        ok = (
            r["loss"] == 0
            and r["p99_ms"] is not None
            and r["p99_ms"] < TARGET_P99_MS
            and (r["clouds_s"] >= 0.95 * r["offered_hz"])
        )
        if not ok and saturated is None:
            saturated = r["robots"]
        lines.append(
            f"| {r['robots']} | {r['offered_hz']:.0f} | {r['clouds_s']:.1f} | {r['mb_s']:.1f} | {r['p50_ms']} | "
            f"{r['p99_ms']} | {r['loss']} | {r['missed']} | {r['cpu_pct']:.0f} | {r['lag_max_ms']:.0f} | "
            f"{'ok' if ok else 'over target'} |"
        )
    target = next((r for r in rows if r["robots"] == TARGET_ROBOTS), None)
    lines.append("")
    if target is not None:
        met = target["loss"] == 0 and target["p99_ms"] is not None and target["p99_ms"] < TARGET_P99_MS
        lines.append(
            f"Target {TARGET_ROBOTS} robots x 30 Hz with no loss and p99 < {TARGET_P99_MS:.0f} ms: "
            f"{'met' if met else 'NOT met'} (p99 {target['p99_ms']} ms, loss {target['loss']})."
        )
    lines.append(
        f"Saturation: first step over target at N = {saturated}."
        if saturated
        else "No step of this sweep saturated (every step: no loss, p99 under target, sustained >= 95 % of offered)."
    )
    first_over = next((r for r in rows if r["robots"] == saturated), None)
    if first_over is not None:
        who = (
            "the load generator (Python, on the same cores) fell behind its schedule first "
            f"(max send lag {first_over['lag_max_ms']:.0f} ms) while the base station used "
            f"{first_over['cpu_pct']:.0f} % of one core"
            if first_over["lag_max_ms"] > 100
            else f"the base station used {first_over['cpu_pct']:.0f} % of one core"
        )
        lost = sum(r["loss"] for r in rows)
        tail = (
            "No step lost a cloud (BLOCK congestion control pushes back)."
            if lost == 0
            else f"{lost} clouds in total were not accepted within the drain time."
        )
        lines.append(f"At N = {saturated}: {who}. {tail}")
    text = "\n".join(lines)
    print(text)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
