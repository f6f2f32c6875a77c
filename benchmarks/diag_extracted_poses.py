"""Where a map from extracted clouds loses faces (issue 27): the same clouds mapped with each kind of pose.

    python -m benchmarks.diag_extracted_poses --mode good --seed 1 [--max-range-m 3] [--dives DIR]
        [--ways true,trusted,filter,smoothed] [--set KEY=VALUE ...] [--times 1,2,3,5,10] [--trace-refilter ROBOT]

One of ``bench_nav``'s 90 s 3-robot dives, its clouds extracted from its rendered 640x360 frames
(``benchmarks.fleet_dives``: found in ``DIR`` when rendered before; rendering takes about 30 ms of CPU per frame),
cut at ``--max-range-m`` along the optical axis, mapped in-process (``mapping.synth.replay_dive``) each way, each
robot's clouds given its calibration's range error (its folder's ``calib.json`` through
:func:`lrsensor.range_theory.range_error_per_px`, as the base station gives a schema-2 cloud's; the range noise it
makes is on by default; ``--set map.stripe_sigma_px=0`` turns it off, :mod:`mapping.range_noise`):

- ``true``: placed at the true poses, no navigation (what the map's fitting makes of these points);
- ``trusted``: placed at the navigation's poses as they are (``good`` only: the others lack fixes or drift);
- ``filter``: the base's navigation without the smoother (``NavConfig`` of ``lrsensor base --nav on``);
- ``smoothed``: the base's navigation, its smoother's runs taken over at once (``bench_nav_procs``'s in-process).

Per way: faces recovered (2 deg, 5 cm) of seen, duplicates, spurious planes, the faces off the bar (deg / cm),
per robot the horizontal error of the served poses against the truth (mean / max, cm: as each cloud was placed,
and as the clouds are in the map at the end, after the smoother's last run) and the mean heading error of the
poses the clouds are in the map with (deg, served); with ``--trace``, each robot's worst 3 s bins.
``--set nav.KEY=VALUE`` / ``smoother.KEY=VALUE`` / ``graph.KEY=VALUE`` (the pose graphs' ``GraphConfig``,
depth-only robots) change the base's tuning, ``map.KEY=VALUE`` the map's ``MapConfig`` (every way; a what-if).
``--trace-refilter ROBOT``: per smoothing run, where its re-filter of ``ROBOT`` first parts from the live filter
(``benchmarks.trace_refilter``). ``--times``: first the served planes at the true poses at those seconds of the
dive and at its end.
Prints markdown; a diagnostic, not a figure of merit."""

from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from lrsensor.calibration import Calibration
from lrsensor.frames import body_to_ned
from lrsensor.range_theory import range_error_per_px
from mapping.range_noise import cloud_noise_per_m
from mapping.synth import DiveFrame, DiveMap, hit_faces, replay_dive, score_map, tank
from mapping.types import MapConfig

from .bench_nav_procs import base_nav
from .fleet_dives import dive_frames, extracted_frames, write_fleet
from .trace_refilter import RefilterTrace, describe

WAYS = ("true", "trusted", "filter", "smoothed")


def _tuning(sets: list[str]) -> dict[str, Any]:
    """``base_nav()`` with ``nav.KEY=VALUE`` / ``smoother.KEY=VALUE`` / ``graph.KEY=VALUE`` / ``map.KEY=VALUE``
    (the map's ``MapConfig``, as ``cfg``) applied (VALUE a Python literal, or ``inf``)."""
    import ast

    kw = base_nav()
    for s in sets:
        key, value = s.split("=", 1)
        part, name = key.split(".", 1)
        field = {"nav": "nav_cfg", "smoother": "smoother", "graph": "graph_cfg", "map": "cfg"}[part]
        base = kw.get(field) or MapConfig()
        kw[field] = replace(base, **{name: float(value) if value == "inf" else ast.literal_eval(value)})
    return kw


def run_way(way: str, frames: list[DiveFrame], kw: dict[str, Any]) -> tuple[list[dict[str, Any]], DiveMap | None]:
    """The served planes of ``frames`` mapped ``way`` (:data:`WAYS`), and the replay with navigation (else None)."""
    if way in ("true", "trusted"):
        fr = [replace(f, pose_est=f.pose_true) if way == "true" else f for f in frames]
        fr = [replace(f, points_ned_est=body_to_ned(f.points_body, f.pose_est)) for f in fr]
        run = replay_dive(fr, navigate=False, cfg=kw.get("cfg"), range_error_per_px=kw.get("range_error_per_px"))
        return run.planes(), None
    smoother = kw["smoother"] if way == "smoothed" else None
    run = replay_dive(frames, navigate=True, background="wait", **{**kw, "smoother": smoother})
    return run.planes(), run


def final_yaw_deg(run: DiveMap, frames: list[DiveFrame]) -> dict[str, float]:
    """Per robot the mean heading error (deg) of the poses its clouds are in the map with at the end, served (turned
    by the fleet frame) against the truth."""
    truth = {(f.robot, f.t_ns): f.pose_true for f in frames}
    out = {}
    for robot, poses in run.placed.items():
        err = [math.remainder((run.frame.pose(p) if run.frame is not None else p).yaw_rad
                              - truth[(robot, t)].yaw_rad, 2 * math.pi) for t, p in poses.items()]  # fmt: skip
        out[robot] = math.degrees(float(np.mean(err))) if err else math.nan
    return out


def planes_over_time(
    frames: list[DiveFrame], cfg: MapConfig | None, marks_s: list[float], per_px: dict[str, float] | None = None
) -> list[int]:
    """The served planes of ``frames`` mapped at their true poses (no navigation) just before the first frame at
    each of ``marks_s`` (s of capture time from the first frame), then at the end (after ``flush``); ``per_px``:
    robot -> its calibration's range error per pixel."""
    from mapping.builder import MapBuilder

    b = MapBuilder(cfg or MapConfig())
    for robot, g in (per_px or {}).items():
        b.set_range_error(robot, g)
    t0 = frames[0].t_ns
    out: list[int] = []
    for f in frames:
        while len(out) < len(marks_s) and (f.t_ns - t0) * 1e-9 >= marks_s[len(out)]:
            out.append(len(b.map_json()["planes"]))
        b.add_cloud(f.robot, f.t_ns, body_to_ned(f.points_body, f.pose_true), f.pose_true)
    b.flush()
    out += [len(b.map_json()["planes"])] * (len(marks_s) - len(out))
    return [*out, len(b.map_json()["planes"])]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--mode", default="good")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--seconds", type=float, default=90.0)
    ap.add_argument("--max-range-m", type=float, default=3.0)
    ap.add_argument("--dives", type=Path, default=Path("/tmp/nav23/dives"))
    ap.add_argument("--ways", default=",".join(WAYS))
    ap.add_argument("--set", action="append", default=[], help="nav./smoother./graph./map.KEY=VALUE")
    ap.add_argument("--trace", action="store_true")
    ap.add_argument("--trace-refilter", default="", metavar="ROBOT", help="where each run's re-filter parts")
    ap.add_argument("--times", default="", help="e.g. 1,2,3,5,10: served planes at the true poses then, and at the end")
    a = ap.parse_args(argv)
    frames = dive_frames(a.mode, a.seed, a.seconds)
    folders = write_fleet(a.dives, a.mode, a.seed, a.seconds, "640x360")
    frames = extracted_frames(frames, folders)
    frames = [replace(f, points_body=f.points_body[f.points_body[:, 0] <= a.max_range_m]) for f in frames]
    scene = tank()
    truth = hit_faces(scene, frames)
    kw = _tuning(a.set)
    kw["range_error_per_px"] = {r: range_error_per_px(Calibration.load(d / "calib.json")) for r, d in folders.items()}
    noise = {r: cloud_noise_per_m(kw.get("cfg") or MapConfig(), g) for r, g in kw["range_error_per_px"].items()}
    print(f"{a.mode} seed {a.seed}, extracted 640x360 clouds cut at {a.max_range_m:g} m {' '.join(a.set)}; range "
          f"noise k (1/m): {', '.join(f'{r} {k:.5f}' for r, k in sorted(noise.items()))}\n")  # fmt: skip
    if a.times:
        marks = [float(x) for x in a.times.split(",")]
        counts = planes_over_time(frames, kw.get("cfg"), marks, kw["range_error_per_px"])
        print(f"served planes at the true poses at {a.times} s and at the end: {' / '.join(map(str, counts))}\n")
    print("| way | recovered / seen | dup | spurious | faces off (deg / cm) | pose error, mean / max (cm) "
          "| at the end (cm) | heading (deg) | CPU s |")  # fmt: skip
    print("|---|---|---|---|---|---|---|---|---|")
    traces: list[str] = []
    parts: list[str] = []
    for way in a.ways.split(","):
        c0 = time.process_time()
        with RefilterTrace(a.trace_refilter) as rt:
            planes, run = run_way(way, frames, kw)
        if a.trace_refilter and rt.runs:
            parts += [f"{way} {a.trace_refilter} {line}" for line in describe(rt, frames[0].t_ns)]
        errors = run.position_error_m if run is not None else {}
        final = run.final_error_m if run is not None else {}
        yaw = final_yaw_deg(run, frames) if run is not None else {}
        score = score_map(planes, scene, truth)
        seen = [f for f in score.faces if f.hit]
        off = [f"{f.face.name} " + (f"{f.angle_deg:.1f}/{100 * f.offset_m:.1f}" if f.plane_ids else "none")
               for f in seen if not (f.angle_deg <= 2.0 and f.offset_m <= 0.05)]  # fmt: skip
        err = ", ".join(f"{r} {100 * np.mean(e):.1f} / {100 * np.max(e):.1f}" for r, e in sorted(errors.items()))
        end = ", ".join(f"{100 * np.mean(e):.1f} / {100 * np.max(e):.1f}" for _, e in sorted(final.items()) if e)
        head = ", ".join(f"{v:+.2f}" for _, v in sorted(yaw.items()))
        print(f"| {way} | {len(seen) - len(score.missing())} / {len(seen)} | {len(score.duplicates())} | "
              f"{len(score.spurious)} | {', '.join(off) or '-'} | {err or '-'} | {end or '-'} | {head or '-'} | "
              f"{time.process_time() - c0:.0f} |", flush=True)  # fmt: skip
        for r, e in sorted(errors.items()):
            bins = [100 * float(np.max(c)) for c in np.array_split(np.asarray(e), max(1, int(a.seconds / 3)))]
            traces.append(f"{way} {r}: " + " ".join(f"{b:.0f}" for b in bins))
    if a.trace:
        print("\nmax horizontal error (cm) per 3 s of the dive:\n\n" + "\n".join(f"    {t}" for t in traces))
    if parts:
        print("\nwhere each smoothing run's re-filter first parts from the live filter (10 cm):\n\n"
              + "\n".join(f"    {t}" for t in parts))  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
