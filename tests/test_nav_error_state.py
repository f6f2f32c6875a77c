"""The dead reckoning's error as a state of the filter (``NavConfig.dr_error_state``; issue 27, extracted clouds):
each raw position measures the position plus that error at the fix's white noise, and the error moves only as a
dead reckoning's can. Scans registered to a wrong plane then cannot walk a robot off good fixes (the error would
have to jump), while a drifting dead reckoning's error grows slowly and the scans follow it."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
from test_nav_bias import _dive
from test_nav_jump import SHIFT_M, _corner, _walls

from lrsensor.frames import Pose
from mapping.landmarks import PlaneLandmarks
from mapping.navigation import NavConfig, RobotNav
from mapping.smoother import SMOOTHED_NAV

S = 1_000_000_000
#: the smoother's tuning with the error state
ERROR_NAV = replace(SMOOTHED_NAV, dr_error_state=True)


def _off_fixes(nav: RobotNav) -> float:
    """How far (m) a robot holding station with good fixes goes from them at most: 10 s against the right walls,
    then 3 s against walls 20 cm off (a wrong plane the scans register to)."""
    right, wrong = _walls(), _walls(SHIFT_M)
    off = 0.0
    for k in range(130):
        true, pts = _corner(k)
        nav.update(k * S // 10, true, pts, right if k < 100 else wrong)
        off = max(off, math.hypot(float(nav.x[0]) - 3.0, float(nav.x[1]) - 1.0))
    return off


def test_good_fixes_hold_against_scans_of_a_wrong_map() -> None:
    # after 10 s of scans that agree with the fixes the error and its rate are known to be small: moving the
    # estimate 20 cm within a second would take the dead reckoning's error 20 cm/s
    assert _off_fixes(RobotNav("rov1", ERROR_NAV)) < 0.04


def test_a_drift_pinned_by_the_scans_is_followed() -> None:
    # the dead reckoning drifts 2 cm/s north while the corner pins both axes for 40 s, then the west wall alone
    # leaves north free: the error's rate, learnt from the scans, carries the estimate along
    nav = RobotNav("rov1", ERROR_NAV)
    track = _dive(ERROR_NAV, nav=nav, corner_s=40.0)
    assert abs(float(nav.x[2]) - 0.02) < 0.005  # the error's rate is the drift's
    assert max(abs(e) for _, e, _ in track) < 0.03
    assert all(abs(e) < 3 * sd for _, e, sd in track)


def test_snapshot_restores_the_error_state() -> None:
    nav = RobotNav("rov1", ERROR_NAV)
    right = _walls()
    for k in range(20):
        true, pts = _corner(k)
        nav.update(k * S // 10, true, pts, right)
    snap = nav.snapshot()
    x = nav.x.copy()
    true, pts = _corner(20)
    nav.update(20 * S // 10, true, pts, right)
    nav.restore(snap)
    assert nav.x.shape == (7,)
    assert np.array_equal(nav.x, x)


def _unpinned(cfg: NavConfig, seconds: float = 30.0) -> tuple[float, float, float]:
    """A robot cruising east at 0.2 m/s with no map to register to, its dead reckoning drifting 2 cm/s north, for
    ``seconds`` at 10 Hz. Returns (its north standard deviation, its north error, the physical bound on the dead
    reckoning's error: the fix's noise, 2 % of the distance and 2 cm/s of current over the time; all m)."""
    nav = RobotNav("rov1", cfg)
    empty = PlaneLandmarks.empty()
    n = round(seconds * 10)
    est = None
    for k in range(n + 1):
        t = k * 0.1
        true = Pose(3.0, 0.2 * t, 1.0, 0.0, 0.0, math.pi / 2)
        raw = Pose(true.north_m + 0.02 * t, true.east_m, 1.0, 0.0, 0.0, true.yaw_rad)
        est = nav.update(k * S // 10, raw, np.zeros((0, 3)), empty)
    assert est is not None
    assert est.pose is not None
    bound = math.sqrt(cfg.dr_error_fix_sigma_m**2 + (0.02 * 0.2 * seconds) ** 2 + (0.02 * seconds) ** 2)
    return est.std["north_m"], est.pose.north_m - 3.0, bound


def test_an_unpinned_robot_stays_within_its_physical_bound() -> None:
    bounded = replace(ERROR_NAV, dr_error_bound_fraction=0.02, dr_error_bound_current_m_s=0.02)
    std, err, bound = _unpinned(bounded)
    # the position's uncertainty is the dead reckoning error's: within what 2 % of the distance and a 2 cm/s
    # current make in 30 s (plus the increment's own noise), and it covers the drift
    assert std <= bound * 1.05
    assert abs(err) <= 3.0 * std
    # without the bound the error's rate walks and its covariance outgrows the physics
    std_free, _, _ = _unpinned(ERROR_NAV)
    assert std_free > bound * 1.2


def test_the_bound_restarts_where_the_scans_pin_unless_counted_from_the_launch() -> None:
    # 3 s looking into the corner pins both axes every scan: the bound's distance and time restart there, unless
    # the bound is counted from the launch (then a registration to a wrong wall cannot move its centre)
    right = _walls()
    times = []
    for pins in (True, False):
        nav = RobotNav("rov1", replace(ERROR_NAV, dr_error_bound_fraction=0.02, dr_error_bound_pins=pins))
        for k in range(30):
            true, pts = _corner(k)
            nav.update(k * S // 10, true, pts, right)
        times.append(float(nav.pin_time.max()))
    assert times[0] < 0.15
    assert times[1] > 2.8
