"""benchmarks.diag_extracted_poses: its tuning what-ifs and its ways of placing a dive's clouds."""

from __future__ import annotations

import pytest

from benchmarks.diag_extracted_poses import _tuning, run_way
from benchmarks.fleet_dives import dive_frames


def test_tuning_sets_nav_and_smoother_fields() -> None:
    kw = _tuning(["nav.fix_quality_factor=3.0", "smoother.every_s=5.0"])
    assert kw["nav_cfg"].fix_quality_factor == 3.0
    assert kw["smoother"].every_s == 5.0
    with pytest.raises(KeyError):
        _tuning(["map.max_range_m=3"])


def test_true_and_trusted_ways_map_without_navigation() -> None:
    frames = dive_frames("good", 1, 4.0)
    for way in ("true", "trusted"):
        planes, errors = run_way(way, frames, _tuning([]))
        assert planes
        assert errors == {}
    planes, errors = run_way("filter", frames, _tuning([]))
    assert sorted(errors) == sorted({f.robot for f in frames})
