"""``lrsensor demo``: a fleet of simulated ROVs diving the simulated tank, a base station building the map, all
in one process on the in-process test network (:mod:`services.testnet`).

Each ROV renders its camera with :mod:`lrsensor.sim` (reduced resolution, 640x360 by default, the paper's
camera scaled), runs the real sensor (:meth:`lrsensor.Sensor.process`) on every frame, and publishes its clouds
over Zenoh; the base station counts them and feeds the map. The run lasts ``duration_s`` of wall-clock time,
then every ROV ends its dive, waits until the base station has acknowledged every cloud, and the demo prints a
summary table and writes the map (JSON) and a PNG top view with the robots' tracks.
"""

from __future__ import annotations

import json
import logging
import math
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .simsource import SimDive, open_sim
from .sources import Frame
from .testnet import RovHandle, TestNetwork

log = logging.getLogger(__name__)


#: Closest a stripe may come to the principal row and still be used, pixels (see :func:`useful_range_m`).
MIN_STRIPE_OFFSET_PX = 4.0


def useful_range_m(calibration: Any, max_range_m: float = 5.0) -> float:
    """Farthest range worth measuring with this camera, metres along the optical axis.

    A stripe at range x sits ``f c / x`` pixels from the principal row (paper eq. 33, c = each laser's offset);
    closer than :data:`MIN_STRIPE_OFFSET_PX` the two lasers' stripes merge and 0.1 px of error is more than
    2.5 % of range. At the demo's 640x360 (f = 185 px) that is about 2.3 m; at 1920x1080 the extractor's 5 m.
    """
    c = min(abs(float(l.point_body[2])) for l in calibration.lasers) or 0.05
    return float(min(max_range_m, calibration.camera.fy * c / MIN_STRIPE_OFFSET_PX))


@dataclass(frozen=True)
class DemoConfig:
    """Settings of the demo.

    Attributes:
        n_robots: simulated ROVs.
        duration_s: wall-clock time the ROVs dive before they end their dives.
        width, height: simulated camera size (the paper's camera scaled; 640x360 keeps the demo fast).
        rate_hz: simulated frame rate (capture times are spaced by 1 / rate_hz of simulated time).
        speed_m_s: speed of the vehicles along their loops.
        out_dir: where map.json, status.json and map.png go.
        state_dir: the base station's state (a temporary folder if None).
        seed: seed of rendering and IMU noise.
        progress: show a live progress display.
        navigation: the base station corrects the poses from the scans (``lrsensor base --nav``).
    """

    n_robots: int = 3
    duration_s: float = 60.0
    width: int = 640
    height: int = 360
    rate_hz: float = 2.0
    speed_m_s: float = 0.4
    out_dir: Path = Path("lrsensor-demo")
    state_dir: Path | None = None
    seed: int = 0
    progress: bool = True
    navigation: bool = False


class DeadlineSource:
    """A simulated dive that ends at a wall-clock deadline (or when its frames run out)."""

    finite = True
    live = False

    def __init__(self, dive: SimDive, deadline: float, stop: threading.Event | None = None) -> None:
        self.dive = dive
        self.deadline = deadline
        self.stop = stop or threading.Event()
        self.name = dive.name

    def __enter__(self) -> DeadlineSource:
        return self

    def __exit__(self, *exc: object) -> None:
        return None

    def __iter__(self) -> Iterator[Frame]:
        for frame in self.dive:
            if time.monotonic() >= self.deadline or self.stop.is_set():
                return
            yield frame


@dataclass
class DemoResult:
    """What the demo measured."""

    rows: list[dict[str, Any]]
    status: dict[str, Any]
    map: dict[str, Any]
    truth: dict[str, Any] | None
    png: Path | None
    elapsed_s: float

    @property
    def ok(self) -> bool:
        """True when every published cloud was received (none missed, none rejected)."""
        return all(r["received"] == r["published"] and r["missed"] == 0 and r["rejected"] == 0 for r in self.rows)


def truth_faces() -> list[dict[str, Any]]:
    """The tank's vertical faces (walls, pillar sides) as planes in NED: name, normal, point, half extents."""
    from lrsensor.sim.scene import Rectangle
    from lrsensor.sim.scenes import tank_scene

    faces = []
    for s in tank_scene().surfaces:
        if not isinstance(s, Rectangle):
            continue
        u, v = np.asarray(s.axis_u, float), np.asarray(s.axis_v, float)
        n = np.cross(u, v)
        n /= np.linalg.norm(n)
        if abs(n[2]) > 0.5:  # floor and tops: the horizontal laser fans do not map them
            continue
        faces.append(
            {
                "name": s.name,
                "normal": n,
                "center": np.asarray(s.center, float),
                "u": u,
                "v": v,
                "half_u": s.half_u,
                "half_v": s.half_v,
            }
        )
    return faces


def score_map(planes: list[dict[str, Any]], angle_deg: float = 5.0, dist_m: float = 0.15) -> dict[str, Any]:
    """Match map planes to the tank's true faces: normals within ``angle_deg``, offset within ``dist_m``, and
    the plane's centroid over the face (0.3 m margin). Returns matched faces (the best plane's errors), the
    count of spurious planes, and ``duplicates``: face name -> planes matched to it, where more than one."""
    faces = truth_faces()
    matched: dict[str, dict[str, float]] = {}
    per_face: dict[str, int] = {}
    spurious = 0
    cos_tol = math.cos(math.radians(angle_deg))
    for p in planes:
        n = np.asarray(p["normal"], float)
        c = np.asarray(p.get("extent", {}).get("centroid", [math.nan] * 3), float)
        best = None
        for f in faces:
            cosang = abs(float(n @ f["normal"]))
            off = abs(float(n @ f["center"]) + float(p["d"]))
            rel = c - f["center"]
            over = abs(rel @ f["u"]) <= f["half_u"] + 0.3 and abs(rel @ f["v"]) <= f["half_v"] + 0.3
            if cosang >= cos_tol and off <= dist_m and over:
                err = {"angle_deg": math.degrees(math.acos(min(1.0, cosang))), "offset_m": off}
                if best is None or off < best[1]["offset_m"]:
                    best = (f["name"], err)
        if best is None:
            spurious += 1
            continue
        per_face[best[0]] = per_face.get(best[0], 0) + 1
        if best[0] not in matched or best[1]["offset_m"] < matched[best[0]]["offset_m"]:
            matched[best[0]] = best[1]
    duplicates = {name: n for name, n in sorted(per_face.items()) if n > 1}
    return {"faces": len(faces), "matched": matched, "spurious": spurious, "duplicates": duplicates}


def _progress_line(handles: dict[str, RovHandle], status: dict[str, Any], left_s: float) -> str:
    parts = []
    for robot, h in handles.items():
        c = h.service.counters
        rx = status["robots"].get(robot, {}).get("received", 0)
        parts.append(f"{robot}: {c.frames} frames, {rx} clouds rx")
    return " | ".join(parts) + f" | map {status['map']['planes']} planes | {max(0.0, left_s):4.0f} s left"


def run_demo(cfg: DemoConfig, stop: threading.Event | None = None) -> DemoResult:
    """Run the demo fleet; returns the summary (also printed by the CLI).

    ``stop`` (set on SIGINT/SIGTERM by the CLI) ends the dives early; the summary is still produced.
    """
    stop = stop or threading.Event()
    t_start = time.monotonic()
    cfg.out_dir.mkdir(parents=True, exist_ok=True)
    state = cfg.state_dir or Path(tempfile.mkdtemp(prefix="lrsensor-demo-state-"))
    robots = [f"rov{k + 1}" for k in range(cfg.n_robots)]
    max_frames = int(cfg.duration_s * 20) + 10  # more than the renderer can draw in duration_s
    with TestNetwork("demo") as net:
        base = net.start_base(state, map_mode="auto", navigation=cfg.navigation)
        sims = {}
        for robot in robots:
            sims[robot] = simulated_robot(robot, cfg, max_frames)
        _warm_up(sims[robots[0]][0])
        deadline = time.monotonic() + cfg.duration_s
        handles: dict[str, RovHandle] = {}
        for robot, (dive, imu, calib) in sims.items():
            handles[robot] = net.start_rov(
                robot,
                DeadlineSource(dive, deadline, stop),
                imu,
                calib,
                ack_timeout_s=60,
                process_options={"max_range_m": useful_range_m(calib)},
            )
        _watch(handles, base, deadline, cfg.progress)
        for h in handles.values():
            h.join(120)
        base.flush_map()
        status = base.status()
        map_json = base.map_json()
        tracks = base.tracks()
    rows = []
    for robot, h in handles.items():
        c = h.service.counters
        st = status["robots"].get(robot, {})
        rows.append(
            {
                "robot": robot,
                "frames": c.frames,
                "published": c.published,
                "skipped": c.skipped,
                "failed": c.failed,
                "received": st.get("received", 0),
                "missed": st.get("missed", 0),
                "rejected": st.get("rejected", 0),
                "points": c.points,
                "delivered": c.delivered,
            }
        )
    truth = score_map(map_json.get("planes", [])) if map_json.get("planes") is not None else None
    (cfg.out_dir / "map.json").write_text(json.dumps(map_json, indent=1))
    (cfg.out_dir / "status.json").write_text(json.dumps(status, indent=1))
    png = _plot(cfg.out_dir / "map.png", map_json, tracks)
    return DemoResult(rows, status, map_json, truth, png, time.monotonic() - t_start)


def _warm_up(dive: SimDive) -> None:
    """Process one frame before the clock starts (the extractor compiles its kernels on first use)."""
    from lrsensor.sensor import Sensor

    t0 = time.monotonic()
    frame = next(iter(dive))
    Sensor(dive.calibration).process(frame.image)
    log.info("sensor warmed up in %.1f s", time.monotonic() - t0)


def simulated_robot(robot: str, cfg: DemoConfig, n_frames: int) -> tuple[SimDive, Any, Any]:
    """One demo ROV: its frame source flying at ``cfg.speed_m_s``, the IMU of that same flight, its calibration."""
    dive, _, calib = open_sim(n_frames, cfg.width, cfg.height, cfg.seed, robot, cfg.rate_hz)
    dive.trajectory = _with_speed(dive, cfg.speed_m_s)
    return dive, dive.imu(), calib  # the IMU must follow the trajectory actually flown


def _with_speed(dive: SimDive, speed_m_s: float) -> Any:
    """The dive's trajectory flown at ``speed_m_s`` (keeping its direction)."""
    from dataclasses import replace

    traj = dive.trajectory
    sign = 1.0 if traj.speed_m_s >= 0 else -1.0
    return replace(traj, speed_m_s=sign * abs(speed_m_s) * (abs(traj.speed_m_s) / 0.2))


def _watch(handles: dict[str, RovHandle], base: Any, deadline: float, progress: bool) -> None:
    """Show progress until every ROV has ended its dive."""
    tty = progress and sys.stderr.isatty()
    bar = None
    if tty:
        from tqdm import tqdm

        total = max(1, round(deadline - time.monotonic()))
        bar = tqdm(total=total, desc="demo dive", unit="s", bar_format="{desc}: {bar:20} {n:.0f}/{total} s {postfix}")
    last_print = 0.0
    while not all(h.done.is_set() for h in handles.values()):
        time.sleep(0.5)
        status = base.status()
        left = deadline - time.monotonic()
        line = _progress_line(handles, status, left)
        if bar is not None:
            bar.n = min(bar.total, bar.total - max(0, round(left)))
            bar.set_postfix_str(line, refresh=True)
        elif progress and time.monotonic() - last_print >= 5.0:
            last_print = time.monotonic()
            print(f"[demo] {line}", file=sys.stderr, flush=True)
    if bar is not None:
        bar.close()


def _plot(path: Path, map_json: dict[str, Any], tracks: dict[str, np.ndarray]) -> Path | None:
    try:
        from mapping.view import plot_top_view
    except ImportError as err:
        log.warning("no map plot: %s", err)
        return None
    plot_top_view(
        path,
        map_json.get("planes", []),
        {r: t.tolist() for r, t in tracks.items()},
        title="lrsensor demo: shared map of the tank (top view, NED)",
    )
    return path


def format_summary(res: DemoResult, cfg: DemoConfig) -> str:
    """The summary table as Markdown-like text."""
    lines = [
        f"lrsensor demo: {cfg.n_robots} simulated ROVs in the tank, {cfg.width}x{cfg.height} camera "
        f"(the paper's camera scaled), {res.elapsed_s:.0f} s",
        "",
        "| robot | frames | published | skipped (no pose) | failed | received | missed | rejected | points |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in res.rows:
        lines.append(
            f"| {r['robot']} | {r['frames']} | {r['published']} | {r['skipped']} | {r['failed']} | {r['received']} "
            f"| {r['missed']} | {r['rejected']} | {r['points']} |"
        )
    planes = res.map.get("planes", [])
    lines.append("")
    if res.status["map"]["enabled"]:
        lines.append(f"map: {len(planes)} planes")
        if res.truth is not None:
            t = res.truth
            errs = list(t["matched"].values())
            worst = (
                f"; worst {max(e['angle_deg'] for e in errs):.2f} deg, {100 * max(e['offset_m'] for e in errs):.1f} cm"
                if errs
                else ""
            )
            dups = t.get("duplicates", {})
            dup_text = (
                f"{sum(n - 1 for n in dups.values())} duplicate planes ("
                + ", ".join(f"{name} x{n}" for name, n in dups.items())
                + ")"
                if dups
                else "no duplicate planes"
            )
            lines.append(
                f"vs truth: {len(t['matched'])} of the tank's {t['faces']} vertical faces mapped "
                f"(within 5 deg and 15 cm){worst}; {dup_text}; {t['spurious']} spurious planes (match no face)"
            )
    else:
        lines.append("map: disabled (the mapping package or Open3D is missing)")
    if res.png is not None:
        lines.append(f"plot: {res.png}")
    lines.append(f"files: {cfg.out_dir / 'map.json'}, {cfg.out_dir / 'status.json'}")
    lines.append("every cloud delivered: " + ("yes" if res.ok else "NO"))
    return "\n".join(lines)
