"""Diagnose the depth-only fleet's duplicates (issue 27): who made each copy of a face, when, and how sure it was.

    python -m benchmarks.diag_copies --seed 1 [--seconds 90] [--fleet-unbiased] [--out FILE]

Replays one simulated dive (``bench_nav``'s ``depth-only`` mode) once, the ``tracked`` way only (the gated pose
graph, ``mapping.graph_config.TRACKED``), logging every scan's estimate and how each cloud reached the map:
``direct`` (placed at once: before the robot's first passed check), ``committed`` (held, then a passed check) or
``replaced`` (held, then checked alone after a slide, a break or at the end). For each face the scorer gives more
than one plane: each plane's robots (points, capture span), its signed offset from the true face (cm, along the
face's normal into the water), its depth band; then for the copy (every plane but the face's best), per cloud
whose points lie on it (within 2 cm of the copy and nearer it than the face's best plane, inside its box): the
robot, the capture time, how the cloud was placed, the placed pose's error along the face's normal (cm, final
pose minus truth), the estimate's horizontal std (cm) at that scan. Each spurious plane (matched to no face)
gets its nearest face by normal and the same table of the clouds on it (pose error along its own normal). Prints
markdown; a diagnostic, not a figure of merit."""

from __future__ import annotations

import argparse
import copy
import math
import sys
from collections import defaultdict
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from lrsensor.frames import body_to_ned
from mapping import graph_hold
from mapping.graph_config import TRACKED
from mapping.navigator import Navigator
from mapping.served import served_planes
from mapping.smoother import SMOOTHED_NAV, SmootherConfig
from mapping.synth import hit_faces, replay_dive, score_map, simulate_dive, tank, three_rov_plans

from .bench_nav import MODES, unbias_fleet

#: (robot, t_ns) -> the estimate at that scan
EST: dict[tuple[str, int], Any] = {}
#: (robot, t_ns) -> how the held cloud was released: ("committed" | "replaced", release time ns)
WAY: dict[tuple[str, int], tuple[str, int]] = {}
_CUR: list[str] = []


def _patch() -> None:
    """Log each estimate and each release (the robot of the current update)."""
    update = Navigator.update
    settle = Navigator.settle

    def logged_update(self: Navigator, robot: str, t_ns: int, raw: Any, pts: Any, lm: Any) -> Any:
        _CUR[:] = [robot]
        est = update(self, robot, t_ns, raw, pts, lm)
        EST[(robot, int(t_ns))] = est
        return est

    def logged_settle(self: Navigator, robot: str, lm: Any) -> Any:
        _CUR[:] = [robot]
        return settle(self, robot, lm)

    release = graph_hold._release

    def logged_release(hold: Any, c: Any, pose: Any, t: int) -> None:
        caller = sys._getframe(1).f_code.co_name
        way = "committed" if caller == "commit_held" else ("replaced1" if c.pinned == 1 else "replaced")
        WAY[(_CUR[0], int(c.t_ns))] = (way, int(t))
        release(hold, c, pose, t)

    Navigator.update = logged_update  # type: ignore[method-assign]
    Navigator.settle = logged_settle  # type: ignore[method-assign]
    graph_hold._release = logged_release


def _signed_offset(p: dict[str, Any], face: Any) -> float:
    """The plane's centroid's distance (m) from the true face, along its normal into the water."""
    cen = np.array(p["extent"]["centroid"], dtype=float)
    return float(cen @ np.array(face.normal) + face.d)


def _why_apart(builder: Any, a: int, b: int) -> str:
    """Why the map keeps planes ``a`` and ``b`` apart: the gates of :meth:`PlaneMap.matches` on their records."""
    from mapping.plane_map import PlaneMap, _angle_deg, fit_parts, rms_distance

    recs = builder.planes_records()
    ra, rb = recs[a], recs[b]
    pm = PlaneMap(builder.cfg)
    cfg = pm.cfg
    fa, fb = ra.fit(cfg.quantum_m, cfg.between_window_weight), rb.fit(cfg.quantum_m, cfg.between_window_weight)
    merged = fit_parts(
        ra.stats + rb.stats,
        tuple(x + y for x, y in zip(ra.within, rb.within, strict=True)),
        tuple(x + y for x, y in zip(ra.orient, rb.orient, strict=True)),
        cfg.quantum_m,
        cfg.between_window_weight,
    )
    return (
        f"touch {pm._touch(ra, rb)}, angle {_angle_deg(fa.normal, fb.normal):.2f} deg, rms a->b "
        f"{100 * rms_distance(fa, fb):.1f} b->a {100 * rms_distance(fb, fa):.1f} cm, own rms "
        f"{100 * fa.rms_m:.1f}/{100 * fb.rms_m:.1f}, fused rms {100 * merged.rms_m:.1f} cm, matches "
        f"{pm.matches(ra, fa, rb, fb)}, centroids off the other plane "
        f"{100 * abs(float(fb.normal @ fa.centroid + fb.d)):.1f}/"
        f"{100 * abs(float(fa.normal @ fb.centroid + fa.d)):.1f} cm"
    )


def _spurious_rows(ids: list[int], by_id: dict[int, Any], scene: Any, t0: int) -> list[str]:
    """Markdown rows for the planes the scorer matched to no face: the nearest face by normal (within 15 deg; else
    none), the plane's largest corner distance from it (cm) and angle (deg), its robots (points, capture span)."""
    if not ids:
        return []
    lines = [
        "## spurious planes",
        "",
        "| plane | points | nearest face | corners off (cm, max) | angle (deg) | robots: points, span (s) |",
        "|---|---|---|---|---|---|",
    ]
    for pid in ids:
        p = by_id[pid]
        n = np.array(p["normal"], dtype=float)
        corners = np.array(p["extent"]["corners"], dtype=float)
        near: tuple[float, str, float] | None = None  # (corners off, cm; face; angle, deg)
        for face in scene.faces:
            fn = np.array(face.normal)
            ang = math.degrees(math.acos(max(-1.0, min(1.0, float(n @ fn)))))
            off = 100 * float(np.max(np.abs(corners @ fn + face.d)))
            if ang <= 15.0 and (near is None or off < near[0]):
                near = (off, face.name, ang)
        contrib = ", ".join(
            f"{r} {c['n_points']} {(c['first_ns'] - t0) * 1e-9:.1f}-{(c['last_ns'] - t0) * 1e-9:.1f}"
            for r, c in sorted(p["contributions"].items())
        )
        where = f"{near[1]} | {near[0]:.1f} | {near[2]:.2f}" if near else "none | - | -"
        lines.append(f"| {pid} | {p['n_points']} | {where} | {contrib} |")
    return [*lines, ""]


def _cloud_rows(
    run: Any, by_key: dict[Any, Any], t0: int, p: dict[str, Any], q: dict[str, Any] | None, fn: Any
) -> list[str]:
    """Per robot, a markdown row on the placed clouds whose points lie on plane ``p`` (at least 20 points within 2 cm
    of it, inside its box, and nearer it than plane ``q`` when given): clouds, capture span, points, how placed,
    release lag, the placed pose's error along ``fn`` (3,) (cm), yaw error (deg), the estimate's std (cm), motions."""
    frame = run.frame
    n_c, d_c = np.array(p["normal"]), float(p["d"])
    n_b, d_b = (np.array(q["normal"]), float(q["d"])) if q is not None else (n_c, math.inf)
    lo, hi = np.array(p["extent"]["aabb_min"]) - 0.02, np.array(p["extent"]["aabb_max"]) + 0.02
    rows = defaultdict(list)
    for robot, poses in run.placed.items():
        for t, pose in poses.items():
            f = by_key[(robot, t)]
            served = frame.pose(pose)
            pts = body_to_ned(f.points_body, served)
            pts = pts[np.all(np.isfinite(pts), axis=1)]
            inbox = np.all((pts >= lo) & (pts <= hi), axis=1)
            dc = np.abs(pts @ n_c + d_c)
            db = np.abs(pts @ n_b + d_b)  # inf without q
            on = inbox & (dc < 0.02) & (dc < db)
            if int(on.sum()) < 20:
                continue
            est = EST.get((robot, t))
            std = math.hypot(est.std.get("north_m", math.nan), est.std.get("east_m", math.nan)) if est else math.nan
            way = WAY.get((robot, t), ("direct", t))
            err = np.array([served.north_m - f.pose_true.north_m, served.east_m - f.pose_true.east_m, 0.0])
            dyaw = math.degrees(math.remainder(served.yaw_rad - f.pose_true.yaw_rad, 2 * math.pi))
            rows[robot].append((t, int(on.sum()), way, float(err @ fn), dyaw, std, est.motion if est else "-"))
    lines = []
    for robot, rs in sorted(rows.items()):
        ts = [(r[0] - t0) * 1e-9 for r in rs]
        ways = [r[2][0] for r in rs]
        lags = [(r[2][1] - r[0]) * 1e-9 for r in rs if r[2][0] != "direct"]
        e = [100 * r[3] for r in rs]
        stds = [100 * r[5] for r in rs]
        mot = " ".join(sorted({r[6] for r in rs}))
        n_way = "/".join(str(ways.count(w)) for w in ("direct", "committed", "replaced", "replaced1"))
        lines.append(
            f"| {robot} | {len(rs)} | {min(ts):.1f}-{max(ts):.1f} | {sum(r[1] for r in rs)} | {n_way} | "
            f"{np.mean(lags) if lags else 0:.1f} | {np.mean(e):+.1f}, {min(e):+.1f}..{max(e):+.1f} | "
            f"{np.mean([r[4] for r in rs]):+.2f} | {np.nanmean(stds):.1f}, {np.nanmax(stds):.1f} | {mot} |"
        )
    return lines


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=90.0)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--fleet-unbiased", action="store_true")
    ap.add_argument("--copy-offsets", default="", help="also score the served map with these serve_copy_offset_m (m)")
    ap.add_argument("--mode", default="depth-only", choices=["depth-only", "mixed"])
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="a GraphConfig field of the tracked replay (float), e.g. verify_tol_m=0.04",
    )
    args = ap.parse_args()
    _patch()
    sets = {k: float(v) for k, v in (kv.split("=", 1) for kv in args.set)}
    scene = tank()
    frames = simulate_dive(
        scene,
        three_rov_plans(),
        duration_s=args.seconds,
        rate_hz=10.0,
        n_rays=400,
        seed=args.seed,
        navigation=MODES[args.mode],
    )
    if args.fleet_unbiased:
        frames = unbias_fleet(frames)
    hits = hit_faces(scene, frames)
    run = replay_dive(
        frames,
        navigate=True,
        nav_cfg=replace(SMOOTHED_NAV, graph_without_fix=True, frame_graph_launches=True),
        smoother=SmootherConfig(),
        background="wait",
        graph_cfg=replace(TRACKED, **sets),
    )
    planes = run.planes()  # NED
    by_id = {int(p["id"]): p for p in planes}
    score = score_map(planes, scene, hits)
    frame = run.frame
    t0 = min(f.t_ns for f in frames)
    by_key = {(f.robot, f.t_ns): f for f in frames}
    recovered = sum(1 for f in score.faces if f.hit) - len(score.missing())
    lines = [
        f"# {args.mode} seed {args.seed}{' unbiased' if args.fleet_unbiased else ''}: {recovered} faces in the bar, "
        f"duplicates {score.duplicates()}, spurious {score.spurious}",
        "",
    ]
    for x in (float(v) for v in args.copy_offsets.split(",") if v):
        pm = copy.copy(run.builder._map)
        pm.cfg = replace(pm.cfg, serve_copy_offset_m=x)
        sc = score_map([frame.plane_json(p) for p in served_planes(pm)], scene, hits)
        n = sum(1 for f in sc.faces if f.hit) - len(sc.missing())
        lines.append(
            f"served copies joined within {x:.3f} m: {n} faces in the bar, duplicates {sc.duplicates()}, "
            f"spurious {sc.spurious}"
        )
    lines.append("")
    lines += _spurious_rows(score.spurious, by_id, scene, t0)
    for pid in score.spurious:
        p = by_id[pid]
        lines += [
            f"spurious {pid}: clouds on it (pose error along its own normal)",
            "",
            "| robot | clouds | span (s) | points | ways (direct/committed/replaced/one wall) | release lag (s) | "
            "pose error along normal (cm) mean, range | yaw err (deg) | std (cm) mean, max | motions |",
            "|---|---|---|---|---|---|---|---|---|---|",
            *_cloud_rows(run, by_key, t0, p, None, np.array(p["normal"])),
            "",
        ]
    for fs in score.faces:
        if len(fs.plane_ids) < 2:
            continue
        face = fs.face
        fn = np.array(face.normal)
        lines += [
            f"## {face.name} (normal {tuple(round(x, 2) for x in face.normal)})",
            "",
            "| plane | points | robots: points, span (s) | offset (cm) | angle (deg) | depth band (m) | along u (m) |",
            "|---|---|---|---|---|---|---|",
        ]
        offs = {}
        for pid in fs.plane_ids:
            p = by_id[pid]
            offs[pid] = _signed_offset(p, face)
            ang = math.degrees(math.acos(min(1.0, abs(float(np.array(p["normal"]) @ fn)))))
            lo, hi = p["extent"]["aabb_min"], p["extent"]["aabb_max"]
            cu = np.array(p["extent"]["corners"]) @ np.array(face.u)
            contrib = ", ".join(
                f"{r} {c['n_points']} {(c['first_ns'] - t0) * 1e-9:.1f}-{(c['last_ns'] - t0) * 1e-9:.1f}"
                for r, c in sorted(p["contributions"].items())
            )
            lines.append(
                f"| {pid} | {p['n_points']} | {contrib} | {100 * offs[pid]:+.1f} | {ang:.2f} | "
                f"{lo[2]:.2f}-{hi[2]:.2f} | {cu.min():.2f}-{cu.max():.2f} |"
            )
        best = max(fs.plane_ids, key=lambda i: by_id[i]["n_points"])
        lines.append("")
        for pid in fs.plane_ids:
            if pid == best:
                continue
            p, q = by_id[pid], by_id[best]
            lines += [
                f"copy {pid} ({100 * (offs[pid] - offs[best]):+.1f} cm from plane {best}; "
                f"{_why_apart(run.builder, pid, best)}): clouds on it",
                "",
                "| robot | clouds | span (s) | points | ways (direct/committed/replaced/one wall) | release lag (s) | "
                "pose error along normal (cm) mean, range | yaw err (deg) | std (cm) mean, max | motions |",
                "|---|---|---|---|---|---|---|---|---|---|",
            ]
            lines += _cloud_rows(run, by_key, t0, p, q, fn)
            lines.append("")
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out is not None:
        args.out.write_text(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
