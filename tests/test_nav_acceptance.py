"""Acceptance of navigation through processes (issue 27): ``lrsensor base`` and one ``lrsensor rov --imu csv:FILE``
per robot, each replaying its own recorded dive (rendered images; good, drifting and depth-only navigation in
``imu.csv``); the map served on ``lrs/<fleet>/map`` is scored against the tank's faces and the status must say
where the scans did not constrain a robot. The figures of a longer run are in benchmarks/results/nav.md
(``python -m benchmarks.bench_nav --acceptance``)."""

from __future__ import annotations

from pathlib import Path

import pytest

pytest.importorskip("zenoh")

from benchmarks.bench_nav import ACCEPTANCE, run_acceptance

pytestmark = pytest.mark.slow


def test_a_fleet_of_processes_maps_the_tank_and_says_where_it_is_lost(tmp_path: Path) -> None:
    a = run_acceptance(tmp_path, seconds=20.0, rate_hz=5.0, seed=1, nav="on")
    n = int(20.0 * 5.0)
    assert a.clouds == n * len(ACCEPTANCE), a.status
    robots = a.status["robots"]
    for robot, mode in ACCEPTANCE.items():
        nav = robots[robot]["nav"]
        assert nav["placed"] + nav["unplaced"] == n, (robot, nav)
        if mode == "depth-only":
            # no map of anyone else around its launch and no fix after it: its pose graph follows it on scan
            # odometry and places its first clouds while within 10 cm, then the status says it is lost
            assert nav["position"] in {"lost", "unconstrained"}, nav
            assert nav["placed"] <= 10, nav
            assert robots[robot]["unplaced"] == nav["unplaced"]
        else:
            assert nav["placed"] == n, (robot, nav)
            assert nav["position"] in {"constrained", "partly", "unconstrained"}, nav
    assert a.map_json.get("nav_frame") is not None
    # the faces the two placed robots saw are in the served map (the demo's tolerance: 5 deg, 15 cm)
    assert a.matched_loose >= 2, a
    # the base smoothed the robots' past poses and re-placed their clouds while they dived
    smoothing = a.status["map"]["smoothing"]
    assert smoothing["runs"] >= 1, smoothing
    assert smoothing["replaced"] >= 1, smoothing
