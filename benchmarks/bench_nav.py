"""Benchmark of laser-aided navigation (issue 27): the map trusting the poses vs the map with corrected poses.

    python benchmarks/bench_nav.py [--seconds 90] [--seed 1] [--acceptance 24] [--out benchmarks/results/nav.md]
    python -m benchmarks.bench_nav --modes '' --realtime drift      # the map thread's hold, fed in real time
    python -m benchmarks.bench_nav --modes '' --replay-acceptance 24  # a recorded acceptance run per variant

A simulated 3-robot dive in the tank (``mapping.synth``: ``three_rov_plans``, both laser fans ray-traced at
10 Hz, 400 rays per laser, 2 mm range noise) with each navigation of ``lrsensor.sim.navigation``:

- ``good``: today's navigation solution (1.5 cm position noise + 2 mm/sqrt(s) walk, 0.2 deg attitude);
- ``drift``: DVL + compass dead reckoning (1 % scale, 1.5 deg compass bias wandering by 0.5 deg, a slow
  velocity bias, white noise; the position error grows past 0.5 m);
- ``depth-only``: attitude with the compass bias and depth, a horizontal fix at launch only;
- ``mixed``: one robot of each (rov1 good, rov2 drift, rov3 depth-only).

Each dive is replayed into ``mapping.MapBuilder`` three times, as the base station does it
(``mapping.synth.replay_dive``): trusting the poses (``lrsensor base --nav off``: clouds without a fix are left
out), correcting them first with the filter (``mapping.navigation``, ``--nav filter``), and with the smoother
(``--nav on``, the base's default; ``mapping.smoother``: past poses re-estimated and their clouds re-placed in the
map, a last smoothing at the end of the dive; fixes weighted by ``SMOOTHED_NAV``); where a robot has no fix after
its launch (``depth-only``, ``mixed``), a fourth time as the third with its pose graph (``graph``:
``NavConfig.graph_without_fix``; ``mapping.posegraph``), and with ``--graph-track`` a fifth time as the fourth with
the graphs' gates (``tracked``: ``mapping.graph_config.TRACKED``, ``NavConfig.frame_graph_launches``: what
``lrsensor base --no-fix graph``, the default, runs). The served map is
scored against the tank's faces (``mapping.synth.score_map``: a face is *seen* with 3000 true hits and 30 frames
where both lasers hit it; *recovered* with a plane within 2 deg and 5 cm). Per mode and way: faces seen / recovered,
the worst angle and offset over the seen faces that have a plane (a seen face without one is counted in "missing"),
duplicates, spurious planes, the clouds left unplaced, the robots' horizontal position error (of the poses the
clouds are in the map with at the end, served in NED: largest, and the robots' last estimates), the share of scans
whose registration constrained both horizontal axes, the navigation's wall time per scan on this machine, and the
smoother's (all its runs, including the map's rebuilds, divided by the scans; and its longest run)."""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from mapping.navigation import NavConfig
from mapping.planes import open3d
from mapping.smoother import SMOOTHED_NAV, SmootherConfig
from mapping.synth import (
    DiveMap,
    hit_faces,
    replay_dive,
    score_map,
    simulate_dive,
    tank,
    three_rov_plans,
    wall_yaw_deg,
)
from mapping.types import MapConfig

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


#: ``NavConfig`` fields every navigated replay of :func:`run_mode` takes (``--nav-bias`` sets the velocity bias)
NAV_OVERRIDES: dict[str, Any] = {}
#: ``GraphConfig`` fields the ``graph`` replays of :func:`run_mode` take (``--graph-second-hypothesis``)
GRAPH_OVERRIDES: dict[str, Any] = {}
#: whether depth-only and mixed dives get a fifth replay, ``tracked`` (``--graph-track``)
TRACKED_ROWS: list[bool] = []
#: GraphConfig fields the ``tracked`` replays take on top of TRACKED (``--no-hold``, ``--heading-check``)
TRACKED_OVERRIDES: dict[str, Any] = {}
#: NavConfig fields the ``tracked`` replays take on top of the others' (``--fleet-compass``)
TRACKED_NAV_OVERRIDES: dict[str, Any] = {}
#: per tracked replay and robot, what its hold did (a markdown row; mapping.graph_hold)
HOLDS: list[str] = []
#: --fleet-unbiased: the compasses' mean bias over the fleet and the dive removed from every reading (a what-if)
FLEET_UNBIASED: list[bool] = []


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


#: per tracked replay and robot, its heading against the truth (a markdown row; heading_lines)
HEADINGS: list[str] = []
#: MapConfig fields every replay's map takes (--merge-bands)
MAP_OVERRIDES: dict[str, Any] = {}
#: --merge-bands: how far apart along down two bands of one vertical face may be (m)
MERGE_BANDS_GAP_M = 3.0


def _bias_setup(feed: Any) -> None:
    """A replay variant: ``--nav on`` with the dead reckoning's velocity bias always open (not adaptive)."""
    from mapping.navigation import Navigator
    from mapping.smoother import FleetPlacements

    cfg = replace(SMOOTHED_NAV, dr_bias_sigma_m_s=BIAS_SIGMA_M_S, dr_bias_adaptive=False)
    feed.navigator = Navigator(cfg, SmootherConfig())
    feed.fleet = FleetPlacements(feed.navigator, feed.builder, background=True)


#: the velocity bias's launch sigma (m/s) of the option measured (``NavConfig.dr_bias_sigma_m_s``)
BIAS_SIGMA_M_S = 0.003


def run_mode(mode: str, seconds: float, seed: int) -> list[Row]:
    """Simulate one dive and replay it both ways."""
    scene = tank()
    frames = simulate_dive(
        scene, three_rov_plans(), duration_s=seconds, rate_hz=10.0, n_rays=400, seed=seed, navigation=MODES[mode]
    )
    if FLEET_UNBIASED:
        frames = unbias_fleet(frames)
    hits = hit_faces(scene, frames)
    rows = []
    ways = ["trusted", "corrected", "smoothed"] + (["graph"] if mode in ("depth-only", "mixed") else [])
    if TRACKED_ROWS and mode in ("depth-only", "mixed"):
        ways.append("tracked")
    for way in ways:
        navigate = way != "trusted"
        kw: dict[str, Any] = {"nav_cfg": replace(NavConfig(), **NAV_OVERRIDES)} if navigate else {}
        if way == "graph":  # as smoothed, the robots without a fix on their pose graphs (opt-in)
            from mapping.graph_config import GraphConfig

            kw = {"nav_cfg": replace(SMOOTHED_NAV, graph_without_fix=True, **NAV_OVERRIDES),
                  "smoother": SmootherConfig(), "background": "wait",
                  "graph_cfg": GraphConfig(**GRAPH_OVERRIDES)}  # fmt: skip
        if way == "tracked":  # as graph, the gated graph (mapping.graph_config.TRACKED, opt-in)
            from mapping.graph_config import TRACKED

            kw = {"nav_cfg": replace(SMOOTHED_NAV, graph_without_fix=True, frame_graph_launches=True,
                                     **NAV_OVERRIDES, **TRACKED_NAV_OVERRIDES),
                  "smoother": SmootherConfig(), "background": "wait",
                  "graph_cfg": replace(TRACKED, **TRACKED_OVERRIDES)}  # fmt: skip
        if way == "smoothed":
            # the runs split as lrsensor base --nav on splits them (a thread of their own), each waited for, so the
            # figures are reproducible and the map thread's hold is measured apart
            kw = {"nav_cfg": replace(SMOOTHED_NAV, **NAV_OVERRIDES), "smoother": SmootherConfig(),
                  "background": "wait"}  # fmt: skip
        if MAP_OVERRIDES:
            kw["cfg"] = replace(MapConfig(), **MAP_OVERRIDES)
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
                smooth_hold_s=max(run.smooth_hold_s, default=math.nan),
            )
        )
        print(rows[-1], flush=True)
        if way == "tracked":
            HEADINGS.extend(_heading_rows(mode, seed, frames, run, wall_yaw_deg(run.planes(), score)))
        for robot, h in sorted(run.hold.items()):
            HOLDS.append(f"| {mode} | {way} | {robot} | {h['committed']:.0f} | {h['replaced']:.0f} | "
                         f"{h['dropped']:.0f} | {h['lag_mean_s']:.2f} | {h['lag_max_s']:.1f} |")  # fmt: skip
    return rows


#: The acceptance run's robots and their navigation (independent dives, one of each).
ACCEPTANCE = {"rov1": "good", "rov2": "drift", "rov3": "depth-only"}


@dataclass
class Acceptance:
    """What the acceptance run through processes gives: the served map scored against the tank's faces."""

    faces: int
    matched: int
    matched_loose: int
    worst_angle_deg: float
    worst_offset_cm: float
    duplicates: int
    spurious: int
    clouds: int
    placed: int
    positions: dict[str, str]
    wall_s: float
    hold_ms: float
    map_json: dict[str, Any]
    status: dict[str, Any]


def client_session(port: int) -> Any:
    """A Zenoh client session to the base listening on 127.0.0.1:``port`` (scouting off: loopback only)."""
    import zenoh

    conf = {
        "mode": "client",
        "connect": {"endpoints": [f"tcp/127.0.0.1:{port}"], "timeout_ms": 30000},
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
    }
    return zenoh.open(zenoh.Config.from_json5(json.dumps(conf)))


def get_json(session: Any, key: str, timeout_s: float) -> dict[str, Any] | None:
    """The first reply to a query of ``key`` as JSON, or None where none came within ``timeout_s``."""
    for reply in session.get(key, timeout=timeout_s):
        if reply.ok is not None:
            out: dict[str, Any] = json.loads(reply.ok.payload.to_bytes())
            return out
    return None


def wait_for_base(session: Any, fleet: str, base: subprocess.Popen[bytes], log: Path, timeout_s: float) -> None:
    """Wait until ``base`` answers on ``lrs/<fleet>/base/status``; RuntimeError with its ``log`` where it ended or
    did not answer within ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while get_json(session, f"lrs/{fleet}/base/status", 5.0) is None:
        if time.monotonic() > deadline or base.poll() is not None:
            raise RuntimeError("the base station did not come up: " + log.read_text(errors="replace"))
        time.sleep(0.2)


def run_acceptance(
    work: Path,
    seconds: float = 12.0,
    rate_hz: float = 5.0,
    seed: int = 1,
    nav: str = "on",
    size: str = "640x360",
    record: Path | None = None,
) -> Acceptance:
    """``lrsensor base --nav NAV`` (``nav`` may carry more of the base's flags: ``"on --no-fix graph"``) and one
    ``lrsensor rov --imu csv:FILE`` per robot of :data:`ACCEPTANCE` as processes on
    loopback, each replaying its own recorded dive (``lrsensor.sim.dive.record_dive``: rendered images, the
    navigation's ``imu.csv``); the map served on ``lrs/<fleet>/map`` once every cloud is acknowledged, scored
    against the tank's true faces (``services.demo.score_map``: matched within 2 deg and 5 cm, and within the
    demo's 5 deg and 15 cm). With ``record``, ``lrsensor record`` writes the fleet's clouds there (MCAP) for
    :func:`replay_acceptance`."""
    import signal
    import sys

    from lrsensor.sim.dive import record_dive
    from services.demo import score_map as score_served
    from services.testnet import free_port

    width, height = (int(x) for x in size.split("x"))
    dives = {}
    for i, (robot, mode) in enumerate(ACCEPTANCE.items()):
        dives[robot] = work / "dives" / robot
        record_dive(
            dives[robot],
            robot=robot,
            robot_index=i,
            n_robots=len(ACCEPTANCE),
            duration_s=seconds,
            rate_hz=rate_hz,
            width=width,
            height=height,
            seed=seed * 100 + i,
            navigation=mode,
        )
    fleet, port = "acc", free_port()
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    lrs = [sys.executable, "-m", "lrsensor"]
    t0 = time.perf_counter()
    logs = {name: (work / f"{name}.log").open("wb") for name in ("base", *ACCEPTANCE)}
    base = subprocess.Popen(
        [*lrs, "base", "--fleet", fleet, "--listen", f"tcp/127.0.0.1:{port}", "--state", str(work / "state"),
         "--map", "on", "--nav", *nav.split(), "--status-every-s", "0"],
        stdout=logs["base"], stderr=subprocess.STDOUT, env=env,
    )  # fmt: skip
    rovs: dict[str, subprocess.Popen[bytes]] = {}
    try:
        with client_session(port) as session:

            def get(key: str) -> dict[str, Any] | None:
                return get_json(session, key, 5.0)

            wait_for_base(session, fleet, base, work / "base.log", 60.0)
            if record is not None:
                logs["record"] = (work / "record.log").open("wb")
                rovs["record"] = subprocess.Popen(
                    [*lrs, "record", "--fleet", fleet, "--connect", f"tcp/127.0.0.1:{port}", "--out", str(record),
                     "--overwrite"],
                    stdout=logs["record"], stderr=subprocess.STDOUT, env=env,
                )  # fmt: skip
                time.sleep(1.0)  # its subscription declared before the first cloud
            for robot, d in dives.items():
                rovs[robot] = subprocess.Popen(
                    [*lrs, "rov", "--fleet", fleet, "--robot", robot, "--connect", f"tcp/127.0.0.1:{port}",
                     "--source", str(d), "--imu", f"csv:{d / 'imu.csv'}", "--calib", str(d / "calib.json"),
                     "--rate", str(rate_hz), "--ack-timeout-s", "60", "--outbox", str(work / f"outbox-{robot}")],
                    stdout=logs[robot], stderr=subprocess.STDOUT, env=env,
                )  # fmt: skip
            for robot, p in rovs.items():
                if robot == "record":
                    continue
                if p.wait(timeout=240) != 0:
                    msg = f"{robot} failed: " + (work / f"{robot}.log").read_text(errors="replace")
                    raise RuntimeError(msg)
            # every cloud acknowledged: the map thread has taken them all; let its queue drain
            time.sleep(2.0)
            status = get(f"lrs/{fleet}/base/status") or {}
            served = get(f"lrs/{fleet}/map") or {}
    finally:
        for p in (*rovs.values(), base):
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
        for p in (*rovs.values(), base):
            try:
                p.wait(30)
            except subprocess.TimeoutExpired:
                p.kill()
        for fh in logs.values():
            fh.close()
    wall = time.perf_counter() - t0
    planes = served.get("planes", [])
    strict = score_served(planes, angle_deg=2.0, dist_m=0.05)
    loose = score_served(planes)
    errs = list(strict["matched"].values())
    robots = status.get("robots", {})
    return Acceptance(
        faces=int(strict["faces"]),
        matched=len(strict["matched"]),
        matched_loose=len(loose["matched"]),
        worst_angle_deg=max((e["angle_deg"] for e in errs), default=math.nan),
        worst_offset_cm=100 * max((e["offset_m"] for e in errs), default=math.nan),
        duplicates=sum(n - 1 for n in strict["duplicates"].values()),
        spurious=int(strict["spurious"]),
        clouds=sum(int(r.get("received", 0)) for r in robots.values()),
        placed=sum(int(r.get("nav", {}).get("placed", 0)) for r in robots.values()),
        positions={name: str(r.get("nav", {}).get("position", "-")) for name, r in sorted(robots.items())},
        wall_s=wall,
        hold_ms=float((status.get("map", {}).get("smoothing") or {}).get("max_hold_ms") or math.nan),
        map_json=served,
        status=status,
    )


def replay_acceptance(recording: Path, nav: str = "filter", setup: Any = None) -> dict[str, Any]:
    """Replay a recorded acceptance run (:func:`run_acceptance` with ``record``) in this process through
    ``services.mapfeed.MapFeed`` as ``lrsensor base --nav NAV`` maps it (clouds in their recorded order, compact
    ones triangulated with the recorded calibration); ``setup(feed)`` may change the feed's navigation before it
    starts. Returns the served map's score (``services.demo.score_map``: ``matched``, ``loose``, ``spurious``,
    ``duplicates``), the feed, and the map thread's longest hold of one cloud (``max_hold_s``)."""
    import tempfile

    from services.demo import score_map as score_served
    from services.mapfeed import MapFeed, load_map_builder
    from services.replay import read_recording
    from services.wire import CloudMsg, StripeMsg, calibration_fingerprint, decode_cloud

    rec = read_recording(recording)
    with tempfile.TemporaryDirectory(prefix="nav-replay-") as tmp:
        builder = load_map_builder(Path(tmp), "on")
        feed = MapFeed(builder, lambda robot, seq: None, navigation=nav != "off", queue_size=1 << 16)
        if nav == "filter":
            feed.set_smoothing(False)
        if setup is not None:
            setup(feed)
        seen: set[tuple[str, int]] = set()
        msgs: list[CloudMsg] = []
        for _, robot, payload in rec.clouds:
            m = decode_cloud(payload)
            if (m.robot, m.seq) in seen:
                continue
            seen.add((m.robot, m.seq))
            if isinstance(m, StripeMsg):
                calib = next(c for c in rec.calibrations[robot] if calibration_fingerprint(c) == m.calib_id)
                m = m.to_cloud(calib)
            msgs.append(m)
        holds: list[float] = []
        orig = feed._map_one

        def timed(msg: CloudMsg) -> bool:
            t0 = time.perf_counter()
            try:
                return orig(msg)
            finally:
                holds.append(time.perf_counter() - t0)

        feed._map_one = timed  # type: ignore[method-assign]
        feed.start(None)
        t0 = time.perf_counter()
        for m in msgs:
            feed.take(m, time.time_ns())
        feed.flush()
        wall = time.perf_counter() - t0
        served = feed.map_json()
        feed.close(save=False)
    planes = served.get("planes", [])
    strict = score_served(planes, angle_deg=2.0, dist_m=0.05)
    loose = score_served(planes)
    return {
        "matched": len(strict["matched"]),
        "loose": len(loose["matched"]),
        "spurious": int(strict["spurious"]),
        "duplicates": sum(n - 1 for n in strict["duplicates"].values()),
        "errors": strict["matched"],
        "feed": feed,
        "max_hold_s": max(holds, default=0.0),
        "wall_s": wall,
        "clouds": len(msgs),
    }


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


#: The variants :func:`run_replays` replays a recorded acceptance run with (name -> (``--nav``, setup)).
REPLAY_VARIANTS: dict[str, tuple[str, Any]] = {"`--nav off`": ("off", None), "`--nav filter`": ("filter", None)}
REPLAY_VARIANTS["`--nav on`"] = ("on", None)
REPLAY_VARIANTS["`--nav on`, velocity bias"] = ("on", _bias_setup)


def run_replays(seconds: float, seed: int) -> str:
    """One acceptance run through processes (``--nav on``) recorded with ``lrsensor record``, then replayed
    in-process per variant of :data:`REPLAY_VARIANTS` (:func:`replay_acceptance`). Returns a markdown table."""
    import tempfile

    lines = [
        f"| variant | {seconds:g} s seed {seed}: faces 2 deg, 5 cm / 5 deg, 15 cm, spurious | duplicates |",
        "|---|---|---|",
    ]
    with tempfile.TemporaryDirectory(prefix="nav-replays-") as tmp:
        rec = Path(tmp) / "acceptance.mcap"
        run_acceptance(Path(tmp), seconds=seconds, seed=seed, nav="on", record=rec)
        for name, (nav, setup) in REPLAY_VARIANTS.items():
            r = replay_acceptance(rec, nav=nav, setup=setup)
            lines.append(f"| {name} | {r['matched']} / {r['loose']}, {r['spurious']} | {r['duplicates']} |")
            print(lines[-1], flush=True)
    return "\n".join(lines)


def acceptance_table(rows: list[tuple[str, Acceptance]]) -> str:
    """The markdown table of acceptance runs."""
    lines = [
        "| base | faces matched 2 deg, 5 cm / 5 deg, 15 cm (of the tank's) | worst angle (deg) | worst offset (cm) | "
        "duplicates | spurious (2 deg, 5 cm) | clouds received / placed | position at the end | wall (s) | "
        "smoother's longest map-thread hold (ms) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for nav, a in rows:
        pos = ", ".join(f"{r} {p}" for r, p in a.positions.items())
        lines.append(
            f"| `--nav {nav}` | {a.matched} / {a.matched_loose} (of {a.faces}) | {_f(a.worst_angle_deg, '.2f')} | "
            f"{_f(a.worst_offset_cm, '.1f')} | {a.duplicates} | {a.spurious} | {a.clouds} / {a.placed} | {pos} | "
            f"{a.wall_s:.0f} | {_f(a.hold_ms, '.0f')} |"
        )
    return "\n".join(lines)


def _f(x: float, fmt: str) -> str:
    return "-" if not math.isfinite(x) else format(x, fmt)


def table(rows: list[Row]) -> str:
    """The markdown table of the rows."""
    lines = [
        "| navigation | poses | faces seen / recovered (2 deg, 5 cm) | seen without a plane | worst angle (deg) | "
        "worst offset (cm) | duplicates | spurious planes | unplaced clouds | position error max / final (m) | "
        "scans constraining N and E | nav wall ms/scan mean / p99 | smoother ms/scan / longest run (s) | "
        "longest map-thread hold (s) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r.mode} | {r.way} | {r.seen} / {r.recovered} | {r.missing} | {_f(r.worst_angle_deg, '.2f')} | "
            f"{_f(r.worst_offset_cm, '.1f')} | {r.duplicates} | {r.spurious} | {r.unplaced} of {r.clouds} | "
            f"{_f(r.max_error_m, '.2f')} / {_f(r.final_error_m, '.2f')} | "
            f"{'-' if not math.isfinite(r.constrained) else f'{100 * r.constrained:.0f} %'} | "
            f"{_f(r.cost_ms_mean, '.2f')} / {_f(r.cost_ms_p99, '.1f')} | "
            f"{_f(r.smooth_ms, '.2f')} / {_f(r.smooth_max_s, '.2f')} | {_f(r.smooth_hold_s, '.3f')} |"
        )
    return "\n".join(lines)


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


def heading_lines() -> list[str]:
    """The headings' table of the tracked rows (empty without one)."""
    if not HEADINGS:
        return []
    return [
        "Headings of the tracked rows against the truth (deg): each robot's compass bias (reported minus true "
        "heading, mean over the dive), the heading error of the poses its clouds were placed with (served; mean, "
        "largest magnitude), and the map's (the median yaw error of its wall planes; positive turns north towards "
        "east).",
        "",
        "| mode | robot | compass bias mean | placed heading error mean / max | map heading error |",
        "|---|---|---|---|---|",
        *HEADINGS,
        "",
    ]


def hold_lines() -> list[str]:
    """The held clouds' table of the tracked rows (empty without one)."""
    if not HOLDS:
        return []
    return [
        "Held clouds of the tracked rows (placed only once their track's next check passed; mapping.graph_hold): "
        "committed at a passed check, re-placed after a slide or a break (checked alone), dropped; how long a "
        "placed cloud waited (capture time of the scan that released it minus its own).",
        "",
        "| mode | way | robot | committed | re-placed | dropped | wait mean (s) | wait max (s) |",
        "|---|---|---|---|---|---|---|---|",
        *HOLDS,
        "",
    ]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=90.0, help="simulated dive length")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--modes", default=",".join(MODES), help="comma-separated navigation modes")
    ap.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "nav.md")
    ap.add_argument(
        "--acceptance",
        type=float,
        default=0.0,
        metavar="S",
        help="also run the acceptance check through processes (S-second dives; lrsensor base --nav off/filter/on)",
    )
    ap.add_argument(
        "--realtime",
        default="",
        metavar="MODE",
        help="also feed MODE's dive to --nav on in real time (smoother truly in the background): map-thread hold",
    )
    ap.add_argument(
        "--replay-acceptance",
        type=float,
        default=0.0,
        metavar="S",
        help="also record one S-second acceptance run and replay it in-process per variant (off, filter, on)",
    )
    ap.add_argument(
        "--nav-bias",
        action="store_true",
        help="navigated replays with the dead reckoning's velocity bias always open in the filter and smoother "
        f"(NavConfig.dr_bias_sigma_m_s {BIAS_SIGMA_M_S}, not adaptive)",
    )
    ap.add_argument(
        "--nav-bias-adaptive",
        action="store_true",
        help="as --nav-bias, but each robot's bias held at zero until its fixes' disagreement persists "
        "(NavConfig.dr_bias_adaptive; the smoothed rows' default, this sets it for the filter's rows too)",
    )
    ap.add_argument(
        "--no-nav-bias",
        action="store_true",
        help="navigated replays without the velocity bias (NavConfig.dr_bias_sigma_m_s 0; the default before it)",
    )
    ap.add_argument(
        "--graph-second-hypothesis",
        action="store_true",
        help="the graph rows with GraphConfig.second_hypothesis (an option: ambiguous plane factors left out)",
    )
    ap.add_argument(
        "--graph-track",
        action="store_true",
        help="depth-only and mixed dives also replayed with the gated graph ('tracked': mapping.graph_config.TRACKED, "
        "NavConfig.frame_graph_launches; an option)",
    )
    ap.add_argument(
        "--heading-check",
        type=float,
        default=None,
        metavar="SHARE",
        help="the tracked rows with GraphConfig.heading_check: each check also takes the heading from the walls "
        "the robot contributed at most SHARE of the points to (0: the others' walls only; 0.99: all but its own)",
    )
    ap.add_argument(
        "--verify-anchor",
        type=float,
        default=None,
        metavar="M",
        help="the tracked rows with GraphConfig.verify_anchor_m: a passed check whose place lies more than M from "
        "the estimate also anchors the pose there before the held clouds are committed",
    )
    ap.add_argument(
        "--fleet-compass",
        action="store_true",
        help="the tracked rows with NavConfig.frame_fleet_compass: the served map turned to the fleet's mean compass",
    )
    ap.add_argument(
        "--fleet-unbiased",
        action="store_true",
        help="a what-if: the dives' compasses with their mean bias over the fleet and the dive removed",
    )
    ap.add_argument(
        "--no-hold",
        action="store_true",
        help="the tracked rows without GraphConfig.hold_until_verified (clouds placed before their track's next "
        "check, as before the hold)",
    )
    ap.add_argument(
        "--merge-bands",
        action="store_true",
        help="every replay's map joins bands of one vertical face across depth gaps (MapConfig."
        "merge_band_gap_down_m 3.0; an option)",
    )
    ap.add_argument(
        "--no-fix-graph",
        action="store_true",
        help="with --acceptance, also a run of lrsensor base --nav on --no-fix graph (rov3's gated pose graph)",
    )
    args = ap.parse_args()
    if args.graph_track:
        TRACKED_ROWS.append(True)
    if args.merge_bands:
        MAP_OVERRIDES["merge_band_gap_down_m"] = MERGE_BANDS_GAP_M
    if args.no_hold:
        TRACKED_OVERRIDES["hold_until_verified"] = False
    if args.fleet_unbiased:
        FLEET_UNBIASED.append(True)
    if args.fleet_compass:
        TRACKED_NAV_OVERRIDES["frame_fleet_compass"] = True
    if args.verify_anchor is not None:
        TRACKED_OVERRIDES["verify_anchor_m"] = args.verify_anchor
    if args.heading_check is not None:
        TRACKED_OVERRIDES.update(heading_check=True, heading_own_share=args.heading_check)
    if args.nav_bias:
        NAV_OVERRIDES.update(dr_bias_sigma_m_s=BIAS_SIGMA_M_S, dr_bias_adaptive=False)
    if args.nav_bias_adaptive:
        NAV_OVERRIDES.update(dr_bias_sigma_m_s=BIAS_SIGMA_M_S, dr_bias_adaptive=True)
    if args.no_nav_bias:
        NAV_OVERRIDES["dr_bias_sigma_m_s"] = 0.0
    if args.graph_second_hypothesis:
        GRAPH_OVERRIDES["second_hypothesis"] = True
    open3d()  # import once, outside the timings
    load0 = os.getloadavg()[0]
    rows: list[Row] = []
    for mode in [m.strip() for m in args.modes.split(",") if m.strip()]:
        rows += run_mode(mode, args.seconds, args.seed)
    accepted: list[tuple[str, Acceptance]] = []
    if args.acceptance > 0:
        import tempfile

        for nav in ("off", "filter", "on", *(("on --no-fix graph",) if args.no_fix_graph else ())):
            with tempfile.TemporaryDirectory(prefix="nav-acceptance-") as tmp:
                accepted.append((nav, run_acceptance(Path(tmp), seconds=args.acceptance, seed=args.seed, nav=nav)))
            print(acceptance_table(accepted[-1:]), flush=True)
    extra: list[str] = []
    if args.realtime:
        extra += ["### Fed in real time", "", f"`python -m benchmarks.bench_nav --modes '' --seconds {args.seconds:g} "
                  f"--seed {args.seed} --realtime {args.realtime}`", "", run_realtime(args.realtime, args.seconds,
                  args.seed), ""]  # fmt: skip
        print("\n".join(extra), flush=True)
    if args.replay_acceptance > 0:
        table_r = run_replays(args.replay_acceptance, args.seed)
        cmd = f"--modes '' --seed {args.seed} --replay-acceptance {args.replay_acceptance:g}"
        extra += ["### A recorded acceptance run replayed per variant", "", f"`python -m benchmarks.bench_nav {cmd}`",
                  "", table_r, ""]  # fmt: skip
        print(table_r, flush=True)
    load1 = os.getloadavg()[0]
    corrected = [r for r in rows if r.way != "trusted" and math.isfinite(r.cost_ms_mean)]
    cost = max((r.cost_ms_mean for r in corrected), default=math.nan)
    acc_cmd = f"--modes '' --seed {args.seed} --acceptance {args.acceptance:g}" + (
        " --no-fix-graph" if args.no_fix_graph else ""
    )
    acc_section = (
        [
            f"### Acceptance through processes ({args.acceptance:g} s dives at 5 Hz, 640x360 rendered images)",
            "",
            *([f"`python -m benchmarks.bench_nav {acc_cmd}`", ""] if not rows else []),
            "`lrsensor base` and one "
            "`lrsensor rov --imu csv:FILE` per robot (rov1 good, rov2 drift, rov3 depth-only), each replaying "
            "its own recorded dive; the map served on `lrs/<fleet>/map` once every cloud is acknowledged, "
            "scored against all 12 faces of the tank (a short dive sees a few).",
            "",
            acceptance_table(accepted),
            "",
        ]
        if accepted
        else []
    )
    rows_lines = [
        f"## Trusted vs corrected poses (3 robots, {args.seconds:g} s at 10 Hz, seed {args.seed}; "
        f"load average {load0:.1f} -> {load1:.1f} on {os.cpu_count()} cores)",
        "",
        f"`python benchmarks/bench_nav.py --seconds {args.seconds:g} --seed {args.seed}"
        + (f" --acceptance {args.acceptance:g}" if args.acceptance > 0 else "")
        + (" --nav-bias" if args.nav_bias else "")
        + (" --nav-bias-adaptive" if args.nav_bias_adaptive else "")
        + (" --no-nav-bias" if args.no_nav_bias else "")
        + (" --graph-second-hypothesis" if args.graph_second_hypothesis else "")
        + (" --modes " + args.modes if args.modes != ap.get_default("modes") else "")
        + (" --graph-track" if args.graph_track else "")
        + (" --merge-bands" if args.merge_bands else "")
        + (" --no-hold" if args.no_hold else "")
        + (f" --heading-check {args.heading_check:g}" if args.heading_check is not None else "")
        + (" --fleet-compass" if args.fleet_compass else "")
        + (" --fleet-unbiased" if args.fleet_unbiased else "")
        + (" --no-fix-graph" if args.no_fix_graph else "")
        + "`",
        "",
        table(rows),
        "",
        *hold_lines(),
        *heading_lines(),
        "Worst angle and offset are over the seen faces that have a plane; a face with a plane outside 2 deg or "
        "5 cm is seen but not recovered. Position errors are of the poses the clouds are in the map with at the "
        "end (with navigation: served in NED, turned by the fleet frame); final: each robot's last estimate, the "
        "worst robot (- where a robot's position is unknown). Smoother: its wall time over the dive (re-filter, "
        "smoothing, re-placing and rebuilding the map) per scan, and its longest single run (all robots; the end "
        "of the dive's last run included); the runs during the dive go on a thread of their own, and the longest "
        "map-thread hold is what one of them kept the map thread for (starting it and handing it over).",
        "",
        f"Navigation cost: at most {cost:.2f} ms (wall, mean) per scan (one thread, this machine), i.e. one map "
        f"thread corrects about {1e3 / cost:.0f} scans/s"
        if math.isfinite(cost)
        else "",
        "",
    ]
    text = "\n".join([*rows_lines, *acc_section, *extra])
    print(text)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    if not rows and args.out.exists():
        # only the extra sections ran: they replace their own sections of the results, the rest stays
        old = args.out.read_text()
        for section in "\n".join(acc_section + extra).split("### ")[1:]:
            head = section.split("\n", 1)[0]
            start = old.find("### " + head)
            if start >= 0:
                end = old.find("\n### ", start + 4)
                old = old[:start] + "### " + section.rstrip() + "\n" + (old[end:] if end >= 0 else "")
            else:
                old = old.rstrip() + "\n\n### " + section.rstrip() + "\n"
        text = old
    args.out.write_text(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
