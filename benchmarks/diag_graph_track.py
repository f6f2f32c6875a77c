"""Where a depth-only fleet's pose graphs lose their track (issue 27): per robot and 3 s of the dive, what was placed,
held or lost, and why the re-localizations failed.

    python -m benchmarks.diag_graph_track [--seed 1] [--traced] [--max-range-m 3] [--dives DIR] [--set graph.KEY=V]

``bench_nav``'s 90 s depth-only dive, its clouds extracted from the rendered 640x360 frames (the cache of
``benchmarks.diag_extracted_poses``; ``--traced``: the ray-traced clouds), cut at ``--max-range-m`` along the
optical axis (``--max-range-m 0``: uncut), mapped in-process as the base maps them (``base_nav()``, ``--set`` as
``diag_extracted_poses``). Prints markdown: the map's score; per robot and 3 s bin the scans placed, held and on
a broken track, the mean and largest horizontal error of the graph's estimate against the truth (cm), its mean
standard deviation (the larger axis, cm), the mean inliers and directions pinned by the registration, and the
map's planes then; then per robot the tries of a check or re-localization (:func:`mapping.relocalize.unique_place`)
and why each failed: ``share`` (the best place explains less than ``min_share`` of the points: faces the map does
not have) or ``ridge`` (places scoring near the best lie farther apart than ``unique_m``: one wall, parallel
walls). A diagnostic: it wraps the graph's functions, nothing is changed."""

from __future__ import annotations

import argparse
import math
import sys
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

import mapping.graph_gate as graph_gate
import mapping.posegraph as posegraph
import mapping.relocalize as reloc
from mapping.synth import hit_faces, replay_dive, score_map, tank

from .diag_extracted_poses import _tuning
from .fleet_dives import depth_only_frames


def why_not(rel: Any, down: float, center: Any, radius: float, lm: Any) -> str:
    """Why :func:`mapping.relocalize.unique_place` (default tuning) found no place: ``walls`` (fewer than 2 wall
    planes), ``share``, ``ridge``, ``fine`` (the refinement's), or ``ok``."""
    cfg = reloc.RelocConfig()
    walls = reloc._walls(lm)
    if len(walls) < 2 or rel.shape[0] < cfg.min_points:
        return "walls"
    if rel.shape[0] > cfg.max_points:
        rel = rel[np.linspace(0, rel.shape[0] - 1, cfg.max_points).astype(np.int64)]
    cand = reloc._grid(np.asarray(center, dtype=np.float64), max(radius, cfg.step_m), cfg.step_m)
    s = reloc._scores(rel, down, cand, walls, cfg.tol_m, cfg)
    best = int(np.argmax(s))
    if s[best] < max(cfg.min_points, cfg.min_share * rel.shape[0]):
        return "share"
    rivals = cand[s >= cfg.near_best * s[best]]
    if float(np.max(np.hypot(*(rivals - cand[best]).T))) > cfg.unique_m:
        return "ridge"
    return "fine"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--traced", action="store_true")
    ap.add_argument("--max-range-m", type=float, default=3.0)
    ap.add_argument("--dives", type=Path, default=Path("/tmp/nav23/dives"))
    ap.add_argument("--set", action="append", default=[], help="nav.KEY=VALUE, smoother.KEY=VALUE or graph.KEY=VALUE")
    a = ap.parse_args(argv)
    frames = depth_only_frames(a.seed, traced=a.traced, max_range_m=a.max_range_m, dives=a.dives)
    truth = {(f.robot, f.t_ns): f.pose_true for f in frames}
    t0 = frames[0].t_ns
    scans: list[tuple[str, float, float, float, bool, bool, bool, int, int, int]] = []
    tries: list[tuple[str, float, str, bool, float]] = []
    why_last: list[str] = []
    found = reloc.unique_place

    def traced_place(rel: Any, down: float, center: Any, radius: float, lm: Any, cfg: Any = None) -> Any:
        place = found(rel, down, center, radius, lm, cfg)
        why_last.append("ok" if place is not None else why_not(rel, down, center, radius, lm))
        return place

    def wrap(fn: Any, kind: str) -> Any:
        def run(g: Any, key: int, t: int, raw: Any, pts: Any, lm: Any) -> Any:
            n, tried = len(why_last), g.track.tried_ns
            out = fn(g, key, t, raw, pts, lm)
            if g.track.tried_ns != tried or kind == "check":
                tp = truth[(g.robot, t)]
                err = float(np.hypot(g._est[key, 0] - tp.north_m, g._est[key, 1] - tp.east_m))
                why = why_last[-1] if len(why_last) > n else "-"
                tries.append((g.robot, (t - t0) * 1e-9, f"{kind}: {why}", g.track.verified_ns == t, err))
            return out

        return run

    update = posegraph.GraphNav.update

    def traced_update(g: Any, t_ns: int, raw: Any, pts: Any, lm: Any) -> Any:
        est = update(g, t_ns, raw, pts, lm)
        tp = truth[(g.robot, t_ns)]
        err = math.hypot(est.pose.north_m - tp.north_m, est.pose.east_m - tp.east_m) if est.pose else math.nan
        std = max(est.std["north_m"], est.std["east_m"])
        scans.append((g.robot, (t_ns - t0) * 1e-9, err, std, est.placed, est.held, g.track.broken, est.inliers,
                      est.pinned, len(lm)))  # fmt: skip
        return est

    setattr(graph_gate, "unique_place", traced_place)  # noqa: B010
    setattr(posegraph, "verify", wrap(graph_gate.verify, "check"))  # noqa: B010 (the graph calls these names)
    setattr(posegraph, "relocalize", wrap(graph_gate.relocalize, "reloc"))  # noqa: B010
    setattr(posegraph.GraphNav, "update", traced_update)  # noqa: B010
    try:
        run = replay_dive(frames, navigate=True, background="wait", **_tuning(a.set))
    finally:
        setattr(graph_gate, "unique_place", found)  # noqa: B010
        setattr(posegraph, "verify", graph_gate.verify)  # noqa: B010
        setattr(posegraph, "relocalize", graph_gate.relocalize)  # noqa: B010
        setattr(posegraph.GraphNav, "update", update)  # noqa: B010
    scene = tank()
    score = score_map(run.planes(), scene, hit_faces(scene, frames))
    seen = [f for f in score.faces if f.hit]
    kind = "traced" if a.traced else "extracted 640x360"
    print(f"depth-only seed {a.seed}, {kind} clouds, cut at {a.max_range_m:g} m {' '.join(a.set)}: "
          f"{len(seen) - len(score.missing())} of {len(seen)} faces, {len(score.duplicates())} duplicates, "
          f"{len(score.spurious)} spurious; unplaced {dict(sorted(run.unplaced.items()))}\n")  # fmt: skip
    print("| robot | s | scans placed / held / broken | error mean / max (cm) | std (cm) | inliers | pinned | planes |")
    print("|---|---|---|---|---|---|---|---|")
    for robot in sorted({s[0] for s in scans}):
        rows = [s for s in scans if s[0] == robot]
        for b in range(0, 90, 3):
            rs = [s for s in rows if b <= s[1] < b + 3]
            if not rs:
                continue
            err, std = np.array([s[2] for s in rs]), np.array([s[3] for s in rs])
            print(f"| {robot} | {b} | {sum(s[4] for s in rs)} / {sum(s[5] for s in rs)} / {sum(s[6] for s in rs)} | "
                  f"{100 * np.nanmean(err):.0f} / {100 * np.nanmax(err):.0f} | {100 * np.mean(std):.0f} | "
                  f"{np.mean([s[7] for s in rs]):.0f} | {np.mean([s[8] for s in rs]):.1f} | {rs[-1][9]} |")  # fmt: skip
    print("\nerror against the standard deviation (robot: scans whose error lay beyond 3 std, of all / of those on a "
          "broken track; scans placed with an error over 10 cm; the largest error on a broken track and the std "
          "then, cm):\n")  # fmt: skip
    for robot in sorted({s[0] for s in scans}):
        rows = [s for s in scans if s[0] == robot and math.isfinite(s[2])]
        out = [s for s in rows if s[2] > 3 * s[3]]
        broken = [s for s in rows if s[6]]
        worst = max(broken, key=lambda s: s[2]) if broken else None
        far = f"{100 * worst[2]:.0f} / {100 * worst[3]:.0f}" if worst else "-"
        print(
            f"- {robot}: {len(out)} of {len(rows)} / {sum(s[6] for s in out)} of {len(broken)}; "
            f"placed over 10 cm {sum(1 for s in rows if s[4] and s[2] > 0.1)}; worst broken {far}"
        )
    print("\nchecks and re-localizations (robot: tries, passed; why the others failed; the estimate's error when "
          "one passed, cm):\n")  # fmt: skip
    for robot in sorted({s[0] for s in scans}):
        ts = [t for t in tries if t[0] == robot]
        ok = [t for t in ts if t[3]]
        why = Counter(t[2] for t in ts if not t[3])
        first = ", ".join(f"{t[1]:.1f} s {100 * t[4]:.0f}" for t in ok[:8])
        print(f"- {robot}: {len(ts)} tries, {len(ok)} passed ({first}); failed: {dict(why.most_common())}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
