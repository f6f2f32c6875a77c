"""The acceptance check of issue 27 through processes: a whole fleet of one navigation, 90 s in real time.

    python benchmarks/bench_nav_procs.py --mode depth-only --seeds 1,2 --runs 2 [--seconds 90] [--inprocess]
        [--map-workers N] [--dives DIR] [--out benchmarks/results/nav_procs.md]

``bench_nav``'s 3-robot dive of one navigation (``good``, ``drift`` or ``depth-only`` for every robot; the same
plans, seed and navigation noise) is rendered into one recorded dive folder per robot (:mod:`benchmarks.fleet_dives`:
640x360 frames at the dive's 10 Hz, ``imu.csv`` with the dive's estimated poses). Then, as processes on loopback
(multicast scouting off): ``lrsensor base --nav on`` (its defaults: the smoother, ``--no-fix graph``) and one
``lrsensor rov --source DIR --imu csv:DIR/imu.csv --rate 10`` per robot, each replaying its dive at the dive's
rate. Once every cloud is acknowledged, the map served on ``lrs/<fleet>/map`` is scored against the tank as
``bench_nav`` scores it (:func:`mapping.synth.score_map`: a face is *seen* with 3000 true hits and 30 frames where
both lasers hit it; *recovered* with a plane within 2 deg and 5 cm; duplicates; spurious planes), with what the
base's status says of each robot (placed clouds, position, heading source) and every process's CPU time.

``--inprocess`` adds the same dive replayed in this process as the base maps it (:func:`mapping.synth.replay_dive`
with the base's navigation: the smoother, the gated graphs of ``--no-fix graph``; the smoother's runs handed over
at once, ``background="wait"``, so it is reproducible): once with ``bench_nav``'s traced clouds (``traced``), once
with the clouds extracted from the rendered images (``extracted``: what the ROVs send), and, with
``--realtime``, the extracted clouds fed at their capture times with the smoother truly on a thread of its own
(``extracted, real time``). A gap between ``traced`` and ``extracted`` is the clouds'; between ``extracted`` and the
processes, the road's (ordering, timing, the smoother's hand-over, dropped clouds).
"""

from __future__ import annotations

import argparse
import math
import os
import resource
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from mapping.synth import hit_faces, score_map, tank

try:  # python -m benchmarks.bench_nav_procs
    from benchmarks.bench_nav import client_session, get_json, wait_for_base
    from benchmarks.fleet_dives import dive_frames, extracted_frames, write_fleet
except ImportError:  # python benchmarks/bench_nav_procs.py: this file's folder is on the path
    from bench_nav import client_session, get_json, wait_for_base  # type: ignore[no-redef]
    from fleet_dives import dive_frames, extracted_frames, write_fleet  # type: ignore[no-redef]


@dataclass
class Row:
    """One run's figures."""

    mode: str
    seed: int
    way: str
    seen: int
    recovered: int
    missing: int
    worst_angle_deg: float
    worst_offset_cm: float
    duplicates: int
    spurious: int
    placed: dict[str, int]
    clouds: int
    wall_s: float
    heading: str = "-"
    positions: str = "-"
    cpu_s: dict[str, float] = field(default_factory=dict)
    rov_wall_s: dict[str, float] = field(default_factory=dict)
    load: tuple[float, float] = (math.nan, math.nan)
    faces_off: str = ""
    size: str = "traced"
    #: processes: clouds the base's capture order released before their turn (a robot more than 1 s behind)
    forced: int = -1
    #: processes: recovered, duplicates, spurious of the map served as the last cloud is acknowledged
    at_end: str = "-"


def _score(mode: str, seed: int, way: str, planes: list[dict[str, Any]], frames: list[Any]) -> Row:
    scene = tank()
    score = score_map(planes, scene, hit_faces(scene, frames))
    seen = [f for f in score.faces if f.hit]
    with_plane = [f for f in seen if f.plane_ids]
    off = [f"{f.face.name} {f.angle_deg:.1f}/{100 * f.offset_m:.1f}" for f in with_plane
           if not (f.angle_deg <= 2.0 and f.offset_m <= 0.05)]  # fmt: skip
    return Row(
        mode=mode,
        seed=seed,
        way=way,
        seen=len(seen),
        recovered=len(seen) - len(score.missing()),
        missing=len(seen) - len(with_plane),
        worst_angle_deg=max((f.angle_deg for f in with_plane), default=math.nan),
        worst_offset_cm=100 * max((f.offset_m for f in with_plane), default=math.nan),
        duplicates=len(score.duplicates()),
        spurious=len(score.spurious),
        placed={},
        clouds=len(frames),
        wall_s=math.nan,
        faces_off=", ".join(off),
    )


#: the smoother's runs in the real-time in-process replay: True (on a thread of their own, as the base) or "wait"
BACKGROUND: dict[str, bool | str] = {}


def base_nav() -> dict[str, Any]:
    """``replay_dive``'s keywords for what ``lrsensor base --nav on`` (``--no-fix graph``) runs."""
    from mapping.smoother import SMOOTHED_NAV, SmootherConfig
    from services.map_worker_nav import no_fix_config

    nav_cfg, graph_cfg = no_fix_config(SMOOTHED_NAV, "graph")
    return {"nav_cfg": nav_cfg, "graph_cfg": graph_cfg, "smoother": SmootherConfig()}


def run_inprocess(mode: str, seed: int, seconds: float, frames: list[Any], way: str, realtime: bool) -> Row:
    """``frames`` replayed in this process as the base maps them (see the module docstring)."""
    from mapping.synth import replay_dive

    t0 = time.perf_counter()
    c0 = time.process_time()
    background = BACKGROUND.get("rt", True) if realtime else "wait"
    run = replay_dive(frames, navigate=True, background=background, realtime=realtime, **base_nav())
    row = _score(mode, seed, way, run.planes(), frames)
    row.wall_s = time.perf_counter() - t0
    row.cpu_s = {"this process": time.process_time() - c0}
    per = {f.robot for f in frames}
    row.placed = {r: len(run.placed.get(r, {})) for r in sorted(per)}
    return row


def _reap(p: subprocess.Popen[bytes], timeout_s: float) -> tuple[int, float]:
    """Wait for ``p`` (at most ``timeout_s``); its exit code and CPU time (user + system, s)."""
    deadline = time.monotonic() + timeout_s
    while True:
        pid, status, ru = os.wait4(p.pid, os.WNOHANG)
        if pid == p.pid:
            p.returncode = os.waitstatus_to_exitcode(status)
            return p.returncode, ru.ru_utime + ru.ru_stime
        if time.monotonic() > deadline:
            msg = f"process {p.args!r} still running after {timeout_s:.0f} s"
            raise TimeoutError(msg)
        time.sleep(0.05)


def run_processes(
    mode: str,
    seed: int,
    seconds: float,
    folders: dict[str, Path],
    work: Path,
    base_args: tuple[str, ...] = (),
    rov_args: tuple[str, ...] = (),
) -> tuple[Row, dict[str, Any]]:
    """``lrsensor base`` and one ``lrsensor rov`` per robot on loopback (see the module docstring); the served map
    scored, with the status. Returns the row and the served map."""

    from services.testnet import free_port

    fleet, port = "navprocs", free_port()
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    lrs = [sys.executable, "-m", "lrsensor"]
    logs = {name: (work / f"{name}.log").open("wb") for name in ("base", *folders)}
    load0 = os.getloadavg()[0]
    t0 = time.perf_counter()
    base = subprocess.Popen(
        [*lrs, "base", "--fleet", fleet, "--listen", f"tcp/127.0.0.1:{port}", "--state", str(work / "state"),
         "--map", "on", "--nav", "on", "--status-every-s", "10", *base_args],
        stdout=logs["base"], stderr=subprocess.STDOUT, env=env,
    )  # fmt: skip
    rovs: dict[str, subprocess.Popen[bytes]] = {}
    cpu: dict[str, float] = {}
    rov_wall: dict[str, float] = {}
    served: dict[str, Any] = {}
    status: dict[str, Any] = {}
    try:
        with client_session(port) as session:

            def get(key: str) -> dict[str, Any] | None:
                return get_json(session, key, 10.0)

            wait_for_base(session, fleet, base, work / "base.log", 90.0)
            started: dict[str, float] = {}
            for robot, d in folders.items():
                started[robot] = time.perf_counter()
                rovs[robot] = subprocess.Popen(
                    [*lrs, "rov", "--fleet", fleet, "--robot", robot, "--connect", f"tcp/127.0.0.1:{port}",
                     "--source", str(d), "--imu", f"csv:{d / 'imu.csv'}", "--calib", str(d / "calib.json"),
                     "--rate", "10", "--ack-timeout-s", "120", "--outbox", str(work / f"outbox-{robot}"), *rov_args],
                    stdout=logs[robot], stderr=subprocess.STDOUT, env=env,
                )  # fmt: skip
            for robot, p in rovs.items():
                code, cpu[robot] = _reap(p, 3 * seconds + 300)
                rov_wall[robot] = time.perf_counter() - started[robot]
                if code != 0:
                    msg = f"{robot} exited {code}: " + (work / f"{robot}.log").read_text(errors="replace")[-3000:]
                    raise RuntimeError(msg)
            # every cloud acknowledged (checkpointed): wait for the map thread to have taken them all
            deadline = time.monotonic() + 60
            while time.monotonic() < deadline:
                status = get(f"lrs/{fleet}/base/status") or {}
                if not status.get("map", {}).get("backlog"):
                    break
                time.sleep(0.5)
            early = get(f"lrs/{fleet}/map") or {}
            early_flushed = int((get(f"lrs/{fleet}/base/status") or {}).get("map", {}).get("quiet_flushes", 0))
            # then the map once the base has seen the fleet go quiet (services.capture_order.QuietFlush)
            deadline = time.monotonic() + 30
            while time.monotonic() < deadline:
                status = get(f"lrs/{fleet}/base/status") or {}
                if "quiet_flushes" not in status.get("map", {}) or status["map"]["quiet_flushes"] > 0:
                    break
                time.sleep(0.5)
            time.sleep(1.0)
            status = get(f"lrs/{fleet}/base/status") or {}
            served = get(f"lrs/{fleet}/map") or {}
    finally:
        for p in (*rovs.values(), base):
            if p.returncode is None and p.poll() is None:
                p.send_signal(signal.SIGTERM)
        for name, p in (*rovs.items(), ("base", base)):
            if p.returncode is None:
                try:
                    _, cpu[name] = _reap(p, 60)
                except TimeoutError:
                    p.kill()
        for fh in logs.values():
            fh.close()
    wall = time.perf_counter() - t0
    frames = dive_frames(mode, seed, seconds)
    row = _score(mode, seed, "processes", served.get("planes", []), frames)
    first = _score(mode, seed, "", early.get("planes", []), frames)
    row.at_end = f"{first.recovered}, {first.duplicates}, {first.spurious}" + (" (flushed)" if early_flushed else "")
    robots = status.get("robots", {})
    row.wall_s = wall
    row.cpu_s = cpu
    row.rov_wall_s = rov_wall
    row.load = (load0, os.getloadavg()[0])
    row.placed = {r: int(v.get("nav", {}).get("placed", 0)) for r, v in sorted(robots.items())}
    row.clouds = sum(int(v.get("received", 0)) for v in robots.values())
    row.positions = ", ".join(f"{r} {v.get('nav', {}).get('position', '-')}" for r, v in sorted(robots.items()))
    row.heading = ", ".join(sorted({str(v.get("nav", {}).get("heading")) for v in robots.values()}))
    row.forced = int(status.get("map", {}).get("order_forced", -1))
    ks = ", ".join(f"{r} {v.get('range_noise_per_m', '-')}" for r, v in sorted(robots.items()))
    print(f"the base's range noise k (1/m) per robot: {ks}", flush=True)  # schema 2: its calibration's
    return row, served


def table(rows: list[Row]) -> str:
    """The markdown table of the rows."""
    lines = [
        "| navigation, images | seed | road | faces seen / recovered (2 deg, 5 cm) | worst angle (deg) / offset (cm) | "
        "duplicates | spurious | at the last ack: recovered, dup, spurious | clouds placed per robot (of received) | "
        "faces off | status: position; heading | out of order | "
        "CPU s (base, rovs) | wall s (rovs) | load |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        cpu = ", ".join(f"{v:.0f}" for v in r.cpu_s.values())
        rw = ", ".join(f"{v:.0f}" for v in r.rov_wall_s.values()) or "-"
        load = "-" if not math.isfinite(r.load[0]) else f"{r.load[0]:.1f} -> {r.load[1]:.1f}"
        placed = " / ".join(str(v) for v in r.placed.values())
        forced = str(r.forced) if r.forced >= 0 else "-"
        lines.append(
            f"| {r.mode}, {r.size} | {r.seed} | {r.way} | {r.seen} / {r.recovered} | {r.worst_angle_deg:.2f} / "
            f"{r.worst_offset_cm:.1f} | {r.duplicates} | {r.spurious} | {r.at_end} | {placed} (of {r.clouds}) | "
            f"{r.faces_off or '-'} | {r.positions}; {r.heading} | {forced} | {cpu} | {r.wall_s:.0f} ({rw}) | {load} |"
        )
    return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--mode", default="depth-only", choices=("good", "drift", "depth-only"))
    ap.add_argument("--seeds", default="1")
    ap.add_argument("--runs", type=int, default=1, help="runs through processes per seed")
    ap.add_argument("--seconds", type=float, default=90.0)
    ap.add_argument("--inprocess", action="store_true", help="also the in-process replays (traced, extracted)")
    ap.add_argument("--realtime", action="store_true", help="with --inprocess: also the extracted clouds in real time")
    ap.add_argument("--smoother", default=None, choices=("thread", "wait"), help="lrsensor base --smoother")
    ap.add_argument("--map-workers", type=int, default=None, metavar="N", help="lrsensor base --map-workers N")
    ap.add_argument("--size", default="640x360", help="rendered image size (WxH; the paper's camera is 1920x1080)")
    ap.add_argument(
        "--max-range-m",
        type=float,
        default=None,
        metavar="M",
        help="lrsensor rov --max-range-m M (and the in-process extracted clouds cut at M along the optical axis)",
    )
    ap.add_argument("--dives", type=Path, default=Path(tempfile.gettempdir()) / "lrs-nav-procs")
    ap.add_argument("--out", type=Path, default=None, help="append the table to this markdown file")
    args = ap.parse_args()
    base_args: tuple[str, ...] = () if args.map_workers is None else ("--map-workers", str(args.map_workers))
    if args.smoother is not None:
        base_args += ("--smoother", args.smoother)
    rov_args: tuple[str, ...] = () if args.max_range_m is None else ("--max-range-m", str(args.max_range_m))
    rows: list[Row] = []
    for seed in (int(s) for s in args.seeds.split(",")):
        folders = write_fleet(args.dives, args.mode, seed, args.seconds, args.size)
        cut = "" if args.max_range_m is None else f", cut at {args.max_range_m:g} m"
        if args.inprocess:
            frames = dive_frames(args.mode, seed, args.seconds)
            rows.append(run_inprocess(args.mode, seed, args.seconds, frames, "in-process, traced", False))
            print(table(rows[-1:]), flush=True)
            ext = extracted_frames(frames, folders)
            if args.max_range_m is not None:  # the default mounting: the optical axis is the body's x
                ext = [replace(f, points_body=f.points_body[f.points_body[:, 0] <= args.max_range_m]) for f in ext]
            for way, rt in (("in-process, extracted", False), ("in-process, extracted, real time", True)):
                if rt and not args.realtime:
                    continue
                rows.append(replace(run_inprocess(args.mode, seed, args.seconds, ext, way + cut, rt), size=args.size))
                print(table(rows[-1:]), flush=True)
        for _ in range(args.runs):
            with tempfile.TemporaryDirectory(prefix="nav-procs-") as tmp:
                row, _ = run_processes(args.mode, seed, args.seconds, folders, Path(tmp), base_args, rov_args)
            way = row.way + ("" if args.map_workers is None else f", --map-workers {args.map_workers}")
            way += "" if args.smoother is None else f", --smoother {args.smoother}"
            way += "" if args.max_range_m is None else f", --max-range-m {args.max_range_m:g}"
            rows.append(replace(row, way=way, size=args.size))
            print(table(rows[-1:]), flush=True)
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    text = table(rows)
    print(text)
    print(f"children CPU {children.ru_utime + children.ru_stime:.0f} s")
    if args.out is not None:
        with args.out.open("a") as fh:
            fh.write(text + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
