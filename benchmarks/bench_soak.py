"""Load and soak: N simulated robots at 30 Hz against one base station, for minutes.

    python benchmarks/bench_soak.py [--robots 5] [--rate 30] [--duration 60] [--points 3800] [--map off]

Real processes on loopback: the base station is ``lrsensor base`` (in-process router, ``--state`` on disk);
the robots run in a second process, each with its own Zenoh session and the ROV's real delivery path
(:class:`services.delivery.OutboxSink`: disk outbox, BLOCK publisher, acks, re-sends). Each robot sends a
synthetic cloud of ``--points`` points (two wall stripes 1-3 m ahead, a slowly moving pose) every 1/rate s,
stamped with its capture time just before it is encoded.

Measured (the base station's own status queryable and ``/proc/<pid>/status``):

- throughput: clouds/s and points/s the base station processed, over the whole run and per interval;
- latency capture -> processed by the base (decode, de-duplication, counters, NED transform, map), p50/p99;
- loss: clouds sent minus distinct clouds the base holds, and its ``missed`` count (both must be 0);
- memory: the base station's resident set size sampled every second (must stay bounded: the growth over
  the second half of the run is reported).

Prints a markdown table and writes it to ``benchmarks/results/soak.md``.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

FLEET = "soak"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _client_conf(port: int) -> Any:
    import zenoh

    conf = {
        "mode": "client",
        "connect": {"endpoints": [f"tcp/127.0.0.1:{port}"], "timeout_ms": 10000},
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
    }
    return zenoh.Config.from_json5(json.dumps(conf))


def rss_mb(pid: int) -> float:
    """Resident set size of ``pid`` in MiB (Linux ``/proc``), NaN if unavailable."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return float("nan")


# ---------------------------------------------------------------------------------------------------------
# Load generator (runs in its own process: python bench_soak.py --load ...)
# ---------------------------------------------------------------------------------------------------------


def synthetic_cloud_arrays(n: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Two horizontal stripes on a wall 1-3 m ahead: points (n, 3) body frame, laser (n,), quality (n,)."""
    rng = np.random.default_rng(seed)
    half = n // 2
    y = np.linspace(-1.2, 1.2, n)
    x = 2.0 + 0.3 * np.sin(y * 2.0) + rng.normal(0, 0.002, n)
    z = np.where(np.arange(n) < half, -0.05, 0.05) * x / 1.0
    points = np.stack([x, y, z], axis=1).astype(np.float32)
    laser = (np.arange(n) >= half).astype(np.uint8)
    quality = np.full(n, 0.9, np.float32)
    return points, laser, quality


def run_load(args: argparse.Namespace) -> int:
    import zenoh

    from lrsensor.frames import Pose
    from services.delivery import OutboxSink
    from services.keys import FleetKeys
    from services.outbox import Outbox
    from services.wire import CloudMsg

    keys = FleetKeys(FLEET)
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    robots = [f"r{i:02d}" for i in range(args.robots)]
    sessions = [zenoh.open(_client_conf(args.port)) for _ in robots]
    sinks = [
        OutboxSink(s, keys, r, Outbox(Path(args.outbox_dir) / r, fsync=args.fsync), ack_period_s=0.5)
        for s, r in zip(sessions, robots, strict=True)
    ]
    deadline_wait = time.monotonic() + 15
    while not all(k.base_present() for k in sinks) and time.monotonic() < deadline_wait:
        time.sleep(0.05)
    arrays = synthetic_cloud_arrays(args.points, 0)
    sent = dict.fromkeys(robots, 0)
    late = dict.fromkeys(robots, 0)
    period = 1.0 / args.rate
    t_start = time.monotonic() + 0.2

    def robot_loop(i: int, robot: str, sink: OutboxSink) -> None:
        seq = sink.outbox.next_seq
        k = 0
        t_next = t_start + i * period / max(1, len(robots))  # spread the robots over a period
        while not stop.is_set():
            now = time.monotonic()
            if now - t_start >= args.duration:
                break
            if t_next > now:
                time.sleep(t_next - now)
            elif now - t_next > period:
                late[robot] += 1
            t_next += period
            yaw = 0.2 * k * period
            pose = Pose(0.05 * k * period, 0.0, 2.0, 0.0, 0.0, yaw)
            msg = CloudMsg(robot, seq, time.time_ns(), pose, *arrays)
            sink.send(msg)
            sent[robot] += 1
            seq += 1
            k += 1

    threads = [
        threading.Thread(target=robot_loop, args=(i, r, s), daemon=True)
        for i, (r, s) in enumerate(zip(robots, sinks, strict=True))
    ]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    t_sent = time.monotonic() - t_start
    delivered = all(s.wait_empty(args.ack_wait, stop) for s in sinks)
    stats = {r: s.stats() for r, s in zip(robots, sinks, strict=True)}
    for s in sinks:
        s.close()
    for s in sessions:
        s.close()
    print(
        json.dumps(
            {"sent": sent, "late": late, "send_s": t_sent, "all_acked": delivered, "delivery": stats}, default=str
        ),
        flush=True,
    )
    return 0


# ---------------------------------------------------------------------------------------------------------
# Driver
# ---------------------------------------------------------------------------------------------------------


def _status(session: Any) -> dict[str, Any] | None:
    for reply in session.get(f"lrs/{FLEET}/base/status", timeout=3.0):
        if reply.ok is not None:
            data: dict[str, Any] = json.loads(reply.ok.payload.to_bytes())
            return data
    return None


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robots", type=int, default=5, help="simulated robots (default 5)")
    ap.add_argument("--rate", type=float, default=30.0, help="clouds per second per robot (default 30)")
    ap.add_argument("--duration", type=float, default=60.0, help="seconds of sending (default 60)")
    ap.add_argument("--points", type=int, default=3800, help="points per cloud (default 3800)")
    ap.add_argument("--map", choices=("auto", "on", "off"), default="off", help="base station map (default off)")
    ap.add_argument("--workers", type=int, default=2, help="base-station ingest workers")
    ap.add_argument("--no-fsync", dest="fsync", action="store_false", help="outbox without fsync per cloud")
    ap.add_argument("--ack-wait", type=float, default=60.0, help="seconds to wait for the last acks")
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "soak.md"))
    ap.add_argument("--load", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--port", type=int, default=0, help=argparse.SUPPRESS)
    ap.add_argument("--outbox-dir", default="", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.load:
        return run_load(args)

    import zenoh

    port = _free_port()
    work = Path(tempfile.mkdtemp(prefix="lrs-soak-"))
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    base_cmd = [
        sys.executable, "-m", "lrsensor", "base", "--fleet", FLEET, "--listen", f"tcp/127.0.0.1:{port}",
        "--state", str(work / "state"), "--map", args.map, "--workers", str(args.workers), "--status-every-s", "0",
    ]  # fmt: skip
    base_log = (work / "base.log").open("w")
    base = subprocess.Popen(base_cmd, stdout=base_log, stderr=subprocess.STDOUT, env=env)
    samples: list[dict[str, float]] = []
    try:
        with zenoh.open(_client_conf_retry(port)) as session:
            deadline = time.monotonic() + 60
            while _status(session) is None:
                if time.monotonic() > deadline or base.poll() is not None:
                    print((work / "base.log").read_text()[-3000:], file=sys.stderr)
                    raise SystemExit("the base station did not come up")
                time.sleep(0.2)
            rss0 = rss_mb(base.pid)
            load_cmd = [
                sys.executable, __file__, "--load", "--port", str(port), "--robots", str(args.robots),
                "--rate", str(args.rate), "--duration", str(args.duration), "--points", str(args.points),
                "--outbox-dir", str(work / "outbox"), "--ack-wait", str(args.ack_wait),
            ] + ([] if args.fsync else ["--no-fsync"])  # fmt: skip
            load = subprocess.Popen(load_cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
            t0 = time.monotonic()
            while load.poll() is None:
                time.sleep(1.0)
                st = _status(session)
                if st is None:
                    continue
                samples.append(
                    {
                        "t": time.monotonic() - t0,
                        "rss_mb": rss_mb(base.pid),
                        "processed": st["ingest"]["processed"],
                        "queued": st["ingest"]["queued"],
                        "p50": st["ingest"]["latency_ms"]["p50"] or float("nan"),
                        "p99": st["ingest"]["latency_ms"]["p99"] or float("nan"),
                    }
                )
                if samples and int(samples[-1]["t"]) % 10 == 0:
                    s = samples[-1]
                    print(
                        f"[soak] t={s['t']:.0f}s processed={s['processed']} queued={s['queued']} "
                        f"rss={s['rss_mb']:.0f}MiB p50={s['p50']:.1f}ms p99={s['p99']:.1f}ms",
                        file=sys.stderr,
                    )
            out, err = load.communicate()
            if load.returncode != 0:
                print(err[-3000:], file=sys.stderr)
                raise SystemExit("the load generator failed")
            result = json.loads(out.strip().splitlines()[-1])
            time.sleep(1.0)
            final = _status(session)
            assert final is not None
    finally:
        base.send_signal(signal.SIGINT)
        try:
            base.wait(timeout=30)
        except subprocess.TimeoutExpired:
            base.kill()
        base_log.close()

    report = summarize(args, result, final, samples, rss0)
    print(report)
    out_path = Path(args.out)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    out_path.write_text(report)
    print(f"written to {out_path}; work folder {work}", file=sys.stderr)
    loss = report_loss(result, final)
    return 0 if loss == 0 else 1


def _client_conf_retry(port: int) -> Any:
    import zenoh

    conf = {
        "mode": "client",
        "connect": {"endpoints": [f"tcp/127.0.0.1:{port}"], "timeout_ms": 60000},
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
    }
    return zenoh.Config.from_json5(json.dumps(conf))


def report_loss(result: dict[str, Any], final: dict[str, Any]) -> int:
    sent = sum(result["sent"].values())
    received = sum(v["received"] for r, v in final["robots"].items() if r in result["sent"])
    missed = sum(v["missed"] for r, v in final["robots"].items() if r in result["sent"])
    return (sent - received) + missed


def summarize(
    args: argparse.Namespace,
    result: dict[str, Any],
    final: dict[str, Any],
    samples: list[dict[str, float]],
    rss0: float,
) -> str:
    sent = sum(result["sent"].values())
    robots = final["robots"]
    received = sum(v["received"] for r, v in robots.items() if r in result["sent"])
    missed = sum(v["missed"] for r, v in robots.items() if r in result["sent"])
    dups = sum(v.get("duplicates", 0) for r, v in robots.items() if r in result["sent"])
    rejected = sum(v.get("rejected", 0) for v in robots.values())
    resent = sum(d["resent"] for d in result["delivery"].values())
    dropped = sum(d["dropped"] for d in result["delivery"].values())
    late = sum(result["late"].values())
    send_s = result["send_s"]
    lat = final["ingest"]["latency_ms"]
    # steady-state throughput: processed between 10 % and 90 % of the sending time
    steady = [s for s in samples if 0.1 * send_s <= s["t"] <= 0.9 * send_s]
    if len(steady) >= 2:
        thr = (steady[-1]["processed"] - steady[0]["processed"]) / (steady[-1]["t"] - steady[0]["t"])
    else:
        thr = final["ingest"]["processed"] / max(send_s, 1e-9)
    rss = [s["rss_mb"] for s in samples]
    half = [s["rss_mb"] for s in samples if s["t"] >= send_s / 2 and s["t"] <= send_s]
    growth = (max(half) - min(half)) if half else float("nan")
    offered = args.robots * args.rate
    lines = [
        f"# Soak: {args.robots} robots x {args.rate:g} Hz x {args.duration:g} s, {args.points} points per cloud, "
        f"map {args.map}, outbox fsync {'on' if args.fsync else 'off'}",
        "",
        "| measure | value |",
        "| --- | ---: |",
        f"| offered load | {offered:.0f} clouds/s ({offered * args.points / 1e6:.2f} M points/s) |",
        f"| clouds sent | {sent} (late ticks of the 30 Hz schedule: {late}) |",
        f"| sustained throughput (steady state) | {thr:.1f} clouds/s ({thr * args.points / 1e6:.2f} M points/s) |",
        f"| distinct clouds held by the base | {received} |",
        f"| **loss** (sent - held + missed) | **{(sent - received) + missed}** |",
        f"| missed (open gaps) | {missed} |",
        f"| duplicates dropped by the base / re-sends by the robots | {dups} / {resent} |",
        f"| outbox drops (full) | {dropped} |",
        f"| rejected payloads | {rejected} |",
        f"| latency capture -> base processed, p50 / p99 | {lat['p50']} ms / {lat['p99']} ms |",
        f"| all acknowledged at the end | {result['all_acked']} |",
        f"| base RSS at start / max / end | {rss0:.0f} / {max(rss, default=float('nan')):.0f} / "
        f"{(rss[-1] if rss else float('nan')):.0f} MiB |",
        f"| base RSS growth over the second half of the run | {growth:.1f} MiB |",
        "",
        "Base station over time:",
        "",
        "| t (s) | processed | clouds/s | queued | RSS (MiB) | p50 (ms) | p99 (ms) |",
        "| ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    step = max(1, len(samples) // 12)
    prev: dict[str, float] | None = None
    for s in samples[::step] + ([samples[-1]] if samples and (len(samples) - 1) % step else []):
        rate = (s["processed"] - prev["processed"]) / (s["t"] - prev["t"]) if prev and s["t"] > prev["t"] else 0.0
        lines.append(
            f"| {s['t']:.0f} | {s['processed']:.0f} | {rate:.1f} | {s['queued']:.0f} | {s['rss_mb']:.0f} "
            f"| {s['p50']:.1f} | {s['p99']:.1f} |"
        )
        prev = s
    lines += [
        "",
        "Latency percentiles are the base station's own (its status queryable, over all clouds processed);"
        " the per-interval p50/p99 columns are cumulative up to that time.",
    ]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    sys.exit(main())
