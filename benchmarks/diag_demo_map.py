"""Record the clouds ``lrsensor demo`` feeds its map, replay them through the map offline (issue 27's duplicates).

    python -m benchmarks.diag_demo_map record --out /tmp/demo.npz [--duration-s 45]
    python -m benchmarks.diag_demo_map replay /tmp/demo.npz [--set merge_max_rms_m=0.03 ...] [--planes]

The demo runs in real time (how many frames each robot renders depends on the machine's load) and without
navigation, so its map is a function of the clouds the base received, in the order it received them. ``record``
runs the demo once with the map's entry points logged (every ``add_cloud`` with its points and pose, every
``advance_time`` and ``flush``) and the true pose of every cloud (the simulator's trajectory); ``replay`` feeds that
log to a fresh :class:`mapping.MapBuilder` (optionally with other :class:`mapping.MapConfig` values) and scores the
served map as the demo does (:func:`services.demo.score_map`). Each robot's clouds get the range error of the
calibration its simulated ROV serves (:func:`demo_range_error_per_px`), as the demo's base gives its schema-2
clouds (their range noise: on by default, off with ``--set stripe_sigma_px=0``, :mod:`mapping.range_noise`).
Replays of one log are deterministic, so variants of the map compare on the same clouds. ``--planes`` prints, for
every face with more than one plane, each plane's robots, capture spans, tilt from vertical, offset from the true
face, depth band, and for the clouds on each plane their trusted poses' errors (roll, pitch, position along the
face's normal). A diagnostic, not a figure of merit.
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path
from typing import Any

import numpy as np

from lrsensor.frames import Pose


def record(out: Path, duration_s: float, seed: int) -> int:
    """Run the demo with the map's inputs logged; write them (and the true poses) to ``out`` (npz)."""
    from mapping.builder import MapBuilder
    from services import demo

    calls: list[tuple[str, str, int]] = []
    clouds: list[np.ndarray] = []
    poses: list[tuple[float, ...]] = []
    dives: dict[str, Any] = {}
    add, adv, flush = MapBuilder.add_cloud, MapBuilder.advance_time, MapBuilder.flush
    sim = demo.simulated_robot

    def add_logged(self: MapBuilder, robot: str, t_ns: int, points_ned: Any, pose: Pose) -> Any:
        calls.append(("add", robot, int(t_ns)))
        clouds.append(np.asarray(points_ned, dtype=np.float32))
        poses.append((pose.north_m, pose.east_m, pose.down_m, pose.roll_rad, pose.pitch_rad, pose.yaw_rad))
        return add(self, robot, t_ns, points_ned, pose)

    def adv_logged(self: MapBuilder, robot: str, t_ns: int) -> Any:
        calls.append(("time", robot, int(t_ns)))
        return adv(self, robot, t_ns)

    def flush_logged(self: MapBuilder) -> Any:
        calls.append(("flush", "", 0))
        return flush(self)

    def sim_logged(robot: str, cfg: Any, n_frames: int) -> Any:
        out = sim(robot, cfg, n_frames)
        dives[robot] = out[0]
        return out

    MapBuilder.add_cloud = add_logged  # type: ignore[method-assign]
    MapBuilder.advance_time = adv_logged  # type: ignore[method-assign]
    MapBuilder.flush = flush_logged  # type: ignore[method-assign]
    demo.simulated_robot = sim_logged  # type: ignore[assignment]
    t0 = time.monotonic()
    res = demo.run_demo(demo.DemoConfig(duration_s=duration_s, seed=seed, progress=False, out_dir=out.parent / "demo"))
    print(demo.format_summary(res, demo.DemoConfig(duration_s=duration_s)))
    truth = []
    for _kind, robot, t in (c for c in calls if c[0] == "add"):
        tp = dives[robot].true_pose(t)
        truth.append((tp.north_m, tp.east_m, tp.down_m, tp.roll_rad, tp.pitch_rad, tp.yaw_rad))
    lens = np.array([c.shape[0] for c in clouds], np.int64)
    np.savez_compressed(
        out,
        kind=np.array([c[0] for c in calls]),
        robot=np.array([c[1] for c in calls]),
        t_ns=np.array([c[2] for c in calls], np.int64),
        lens=lens,
        points=np.concatenate(clouds) if clouds else np.zeros((0, 3), np.float32),
        pose=np.array(poses, np.float64).reshape(-1, 6),
        truth=np.array(truth, np.float64).reshape(-1, 6),
    )
    print(f"recorded {len(clouds)} clouds ({int(lens.sum())} points) in {time.monotonic() - t0:.0f} s -> {out}")
    return 0


def demo_range_error_per_px(robot: str) -> float:
    """The range error per pixel (1/(m px)) of the calibration ``robot`` serves in ``lrsensor demo`` (its default
    camera), what the demo's base gives that robot's clouds (:func:`lrsensor.range_theory.range_error_per_px`)."""
    from lrsensor.range_theory import range_error_per_px
    from services.demo import DemoConfig
    from services.simsource import open_sim

    cfg = DemoConfig()
    return range_error_per_px(open_sim(1, cfg.width, cfg.height, robot=robot)[2])


def replay(path: Path, sets: dict[str, float], planes: bool) -> dict[str, Any]:
    """Replay a recording through a fresh map; the demo's score of the served map (and the builder)."""
    from dataclasses import replace

    from mapping import MapConfig
    from mapping.builder import MapBuilder
    from services.demo import score_map

    with np.load(path) as z:
        a = {k: z[k] for k in z.files}  # an NpzFile decompresses an array on every access
    cfg = replace(MapConfig(), **sets)
    b = MapBuilder(cfg)
    offs = np.concatenate([[0], np.cumsum(a["lens"])])
    k = 0
    told: set[str] = set()
    for kind, robot, t in zip(a["kind"], a["robot"], a["t_ns"], strict=True):
        if kind == "add":
            if str(robot) not in told:
                told.add(str(robot))
                b.set_range_error(str(robot), demo_range_error_per_px(str(robot)))
            p = a["pose"][k]
            b.add_cloud(str(robot), int(t), a["points"][offs[k] : offs[k + 1]].astype(np.float64), Pose(*p))
            k += 1
        elif kind == "time":
            b.advance_time(str(robot), int(t))
        else:
            b.flush()
    served = b.map_json()["planes"]
    score = score_map(served)
    if planes:
        _print_planes(a, b, served, score)
    return {"score": score, "builder": b, "served": served}


def _print_planes(a: Any, b: Any, served: list[dict[str, Any]], score: dict[str, Any]) -> None:
    """Print the planes of each duplicated face and the trusted poses' errors of the clouds on them."""
    from services.demo import truth_faces

    faces = {f["name"]: f for f in truth_faces()}
    add = a["kind"] == "add"
    robots, ts = a["robot"][add], a["t_ns"][add]
    t0 = int(ts.min())
    offs = np.concatenate([[0], np.cumsum(a["lens"])])
    for name in score["duplicates"]:
        f = faces[name]
        fn, fc = f["normal"], f["center"]
        print(f"\n## {name}")
        mine = []
        for p in served:
            n = np.asarray(p["normal"], float)
            if abs(float(n @ fn)) < math.cos(math.radians(5)):
                continue
            c = np.asarray(p["extent"]["centroid"], float)
            off = float((c - fc) @ fn)
            if abs(off) > 0.15 or abs((c - fc) @ f["u"]) > f["half_u"] + 0.3:
                continue
            mine.append(p)
            tilt = math.degrees(math.asin(min(1.0, abs(float(n[2])))))
            contrib = ", ".join(
                f"{r} {c_['n_points']} {(c_['first_ns'] - t0) * 1e-9:.1f}-{(c_['last_ns'] - t0) * 1e-9:.1f}"
                for r, c_ in sorted(p["contributions"].items())
            )
            lo, hi = p["extent"]["aabb_min"], p["extent"]["aabb_max"]
            print(
                f"plane {p['id']}: n_obs {p['n_obs']}, {p['n_points']} pts, normal {np.round(n, 4)}, "
                f"tilt {tilt:.2f} deg, "
                f"angle to face {math.degrees(math.acos(min(1.0, abs(float(n @ fn))))):.2f} deg, centroid off "
                f"{100 * off:+.1f} cm, rms {100 * p['rms_m']:.2f} cm, down {lo[2]:.2f}-{hi[2]:.2f}, "
                f"u {(np.array(p['extent']['corners']) @ f['u']).min():.2f}.."
                f"{(np.array(p['extent']['corners']) @ f['u']).max():.2f}; {contrib}"
            )
        for p in mine:
            n, d = np.asarray(p["normal"], float), float(p["d"])
            lo = np.array(p["extent"]["aabb_min"]) - 0.02
            hi = np.array(p["extent"]["aabb_max"]) + 0.02
            others = [(np.asarray(q["normal"], float), float(q["d"])) for q in mine if q is not p]
            rows = []
            for k in range(len(robots)):
                pts = a["points"][offs[k] : offs[k + 1]].astype(np.float64)
                if pts.shape[0] == 0:
                    continue
                dist = np.abs(pts @ n + d)
                on = np.all((pts >= lo) & (pts <= hi), axis=1) & (dist < 0.02)
                for no, do in others:
                    on &= dist < np.abs(pts @ no + do)
                if int(on.sum()) < 20:
                    continue
                pe, tr = a["pose"][k], a["truth"][k]
                err = pe[:3] - tr[:3]
                rows.append(
                    (
                        str(robots[k]),
                        (int(ts[k]) - t0) * 1e-9,
                        int(on.sum()),
                        math.degrees(pe[3] - tr[3]),
                        math.degrees(pe[4] - tr[4]),
                        100 * float(err @ fn),
                        100 * float(err[2]),
                        float(np.median(pts[on, 2])),
                        100 * float(np.median(pts[on] @ fn) - float(fc @ fn)),
                    )
                )
            print(
                f"\nclouds on plane {p['id']} (robot, t s, points, droll deg, dpitch deg, pos err along face "
                "normal cm, down err cm, median down m, median offset of its points from the face cm):"
            )
            for r in rows:
                print("  " + " ".join(f"{x:+.2f}" if isinstance(x, float) else str(x) for x in r))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    rec = sub.add_parser("record")
    rec.add_argument("--out", type=Path, required=True)
    rec.add_argument("--duration-s", type=float, default=45.0)
    rec.add_argument("--seed", type=int, default=0)
    rep = sub.add_parser("replay")
    rep.add_argument("path", type=Path, nargs="+")
    rep.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="a MapConfig field (number)")
    rep.add_argument("--planes", action="store_true")
    args = ap.parse_args()
    if args.cmd == "record":
        return record(args.out, args.duration_s, args.seed)
    sets: dict[str, float] = {}
    for kv in args.set:
        key, _, value = kv.partition("=")
        sets[key] = int(value) if value.isdigit() else float(value)
    for path in args.path:
        res = replay(path, sets, args.planes)
        s = res["score"]
        errs = list(s["matched"].values())
        worst = (max(e["angle_deg"] for e in errs), 100 * max(e["offset_m"] for e in errs)) if errs else (0.0, 0.0)
        print(
            f"{path.name}: {len(res['served'])} planes, {len(s['matched'])}/{s['faces']} faces, "
            f"worst {worst[0]:.2f} deg {worst[1]:.1f} cm, duplicates {s['duplicates'] or 'none'}, "
            f"spurious {s['spurious']}"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
