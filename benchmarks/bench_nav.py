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

# Layout: this module is the in-process replays (run_mode, with the knobs below that the options set and scratch
# wrappers patch in place) and the command line; every name it had stays importable from here (__all__). Its parts:
# benchmarks.nav_dives (the dives' navigation modes, a replay's figures, the real-time feed),
# benchmarks.nav_acceptance (the acceptance through processes and its in-process replays) and
# benchmarks.nav_tables (the markdown tables).

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from mapping.navigation import NavConfig
from mapping.planes import open3d
from mapping.smoother import SMOOTHED_NAV, SmootherConfig
from mapping.synth import hit_faces, replay_dive, score_map, simulate_dive, tank, three_rov_plans, wall_yaw_deg
from mapping.types import MapConfig

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # run as a script: python benchmarks/bench_nav.py
    sys.path.insert(0, str(ROOT))

from benchmarks.nav_acceptance import (  # noqa: E402
    ACCEPTANCE,
    BIAS_SIGMA_M_S,
    REPLAY_VARIANTS,
    Acceptance,
    client_session,
    get_json,
    replay_acceptance,
    run_acceptance,
    run_replays,
    wait_for_base,
)
from benchmarks.nav_dives import MODES, Row, _final_error, _heading_rows, run_realtime, unbias_fleet  # noqa: E402
from benchmarks.nav_tables import HEADINGS, HOLDS, acceptance_table, heading_lines, hold_lines, table  # noqa: E402

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
#: --fleet-unbiased: the compasses' mean bias over the fleet and the dive removed from every reading (a what-if)
FLEET_UNBIASED: list[bool] = []
#: MapConfig fields every replay's map takes (--merge-bands)
MAP_OVERRIDES: dict[str, Any] = {}
#: --merge-bands: how far apart along down two bands of one vertical face may be (m)
MERGE_BANDS_GAP_M = 3.0


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


__all__ = [
    "ACCEPTANCE",
    "BIAS_SIGMA_M_S",
    "FLEET_UNBIASED",
    "GRAPH_OVERRIDES",
    "HEADINGS",
    "HOLDS",
    "MAP_OVERRIDES",
    "MERGE_BANDS_GAP_M",
    "MODES",
    "NAV_OVERRIDES",
    "REPLAY_VARIANTS",
    "TRACKED_NAV_OVERRIDES",
    "TRACKED_OVERRIDES",
    "TRACKED_ROWS",
    "Acceptance",
    "Row",
    "acceptance_table",
    "client_session",
    "get_json",
    "heading_lines",
    "hold_lines",
    "main",
    "replay_acceptance",
    "run_acceptance",
    "run_mode",
    "run_realtime",
    "run_replays",
    "table",
    "unbias_fleet",
    "wait_for_base",
]


if __name__ == "__main__":
    raise SystemExit(main())
