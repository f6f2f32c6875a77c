"""The navigation benchmark's acceptance through processes (``--acceptance``, ``--replay-acceptance``).

:func:`run_acceptance` runs ``lrsensor base`` and one ``lrsensor rov --imu csv:FILE`` per robot of
:data:`ACCEPTANCE` as processes on loopback, each replaying its own recorded dive, and scores the map the base
serves (:class:`Acceptance`); with ``record`` the run is recorded, and :func:`replay_acceptance` maps the
recording again in this process, once per variant of :data:`REPLAY_VARIANTS` (:func:`run_replays`).
:func:`client_session`, :func:`get_json` and :func:`wait_for_base` talk to the base over loopback
(``benchmarks.bench_nav_procs`` uses them too). The tables: :mod:`benchmarks.nav_tables`.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from mapping.smoother import SMOOTHED_NAV, SmootherConfig

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


def _bias_setup(feed: Any) -> None:
    """A replay variant: ``--nav on`` with the dead reckoning's velocity bias always open (not adaptive)."""
    from mapping.navigation import Navigator
    from mapping.smoother import FleetPlacements

    cfg = replace(SMOOTHED_NAV, dr_bias_sigma_m_s=BIAS_SIGMA_M_S, dr_bias_adaptive=False)
    feed.navigator = Navigator(cfg, SmootherConfig())
    feed.fleet = FleetPlacements(feed.navigator, feed.builder, background=True)


#: the velocity bias's launch sigma (m/s) of the option measured (``NavConfig.dr_bias_sigma_m_s``)
BIAS_SIGMA_M_S = 0.003


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
