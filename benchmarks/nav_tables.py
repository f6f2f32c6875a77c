"""The navigation benchmark's markdown tables (:mod:`benchmarks.bench_nav`).

:func:`table`: one row per replay (:class:`~benchmarks.nav_dives.Row`); :func:`acceptance_table`: one row per
acceptance run (:class:`~benchmarks.nav_acceptance.Acceptance`); :func:`hold_lines` and :func:`heading_lines`:
the tracked replays' held clouds and headings, from the rows :func:`benchmarks.bench_nav.run_mode` collects in
:data:`HOLDS` and :data:`HEADINGS` (empty without a tracked replay).
"""

from __future__ import annotations

import math

from .nav_acceptance import Acceptance
from .nav_dives import Row

#: per tracked replay and robot, what its hold did (a markdown row; mapping.graph_hold)
HOLDS: list[str] = []
#: per tracked replay and robot, its heading against the truth (a markdown row; heading_lines)
HEADINGS: list[str] = []


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
