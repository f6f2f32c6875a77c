"""``benchmarks.bench_nav`` keeps every name it had after its split (other benchmarks, tests and scratch wrappers
import them from there): the same objects as in its parts, so that a knob patched in place or a row collected by
the replays is the one the replays and the tables read."""

from __future__ import annotations

import benchmarks.bench_nav as bench_nav
import benchmarks.nav_acceptance as nav_acceptance
import benchmarks.nav_dives as nav_dives
import benchmarks.nav_tables as nav_tables

#: What bench_nav itself defines: the replays, the command line and the knobs they read.
OWN = {
    "FLEET_UNBIASED",
    "GRAPH_OVERRIDES",
    "MAP_OVERRIDES",
    "MERGE_BANDS_GAP_M",
    "NAV_OVERRIDES",
    "TRACKED_NAV_OVERRIDES",
    "TRACKED_OVERRIDES",
    "TRACKED_ROWS",
    "main",
    "run_mode",
}


def test_bench_nav_exports_the_same_objects_as_its_parts() -> None:
    parts = (nav_dives, nav_acceptance, nav_tables)
    moved = {name: getattr(part, name) for part in parts for name in vars(part) if name in bench_nav.__all__}
    assert not OWN & set(moved)
    assert {*moved, *OWN} == set(bench_nav.__all__)
    for name, obj in moved.items():
        assert getattr(bench_nav, name) is obj, name


def test_a_held_row_collected_through_bench_nav_is_in_the_table() -> None:
    row = "| test | tracked | rov9 | 1 | 0 | 0 | 0.00 | 0.0 |"
    bench_nav.HOLDS.append(row)
    try:
        assert row in nav_tables.hold_lines()
    finally:
        bench_nav.HOLDS.remove(row)
