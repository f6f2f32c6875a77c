"""benchmarks.diag_extracted_poses: its tuning what-ifs and its ways of placing a dive's clouds."""

from __future__ import annotations

import pytest

from benchmarks.diag_extracted_poses import _tuning, final_yaw_deg, run_way
from benchmarks.fleet_dives import dive_frames


def test_tuning_sets_nav_and_smoother_fields() -> None:
    kw = _tuning(["nav.fix_quality_factor=3.0", "smoother.every_s=5.0"])
    assert kw["nav_cfg"].fix_quality_factor == 3.0
    assert kw["smoother"].every_s == 5.0
    assert _tuning(["map.range_noise_per_m=0.002"])["cfg"].range_noise_per_m == 0.002
    with pytest.raises(KeyError):
        _tuning(["sensor.max_range_m=3"])


def test_true_and_trusted_ways_map_without_navigation() -> None:
    frames = dive_frames("good", 1, 4.0)
    for way in ("true", "trusted"):
        planes, run = run_way(way, frames, _tuning([]))
        assert planes
        assert run is None
    planes, run = run_way("filter", frames, _tuning([]))
    assert run is not None
    robots = sorted({f.robot for f in frames})
    assert sorted(run.position_error_m) == robots
    # the good dive's compasses are unbiased: the poses the clouds are in the map with keep the heading
    yaw = final_yaw_deg(run, frames)
    assert sorted(yaw) == robots
    assert all(abs(v) < 1.0 for v in yaw.values())


def test_the_stripe_error_diagnostics_truth_lies_on_the_tank() -> None:
    """``benchmarks.diag_stripe_error``'s truth: the line of each point's sheet and column meets the wall ahead
    (north wall at 8 m, seen from 6 m north facing north) at the depth the geometry gives."""
    import numpy as np

    from benchmarks.diag_stripe_error import true_depth_m
    from lrsensor.frames import Pose

    pose = Pose(6.0, 1.0, 1.5, 0.0, 0.0, 0.0)
    pts = np.array([[1.0, 0.0, -0.05], [1.0, 0.5, 0.05], [1.0, 0.0, 0.05]])
    depth = true_depth_m(pts, pose, pts[:, 2])
    assert depth == pytest.approx([2.0, 2.0, 2.0])  # the wall 2 m ahead, at any column of either sheet
    south = true_depth_m(pts[:1], Pose(6.0, 1.0, 1.5, 0.0, 0.0, np.pi), pts[:1, 2])
    assert south == pytest.approx([6.0])  # turned round: the south wall
