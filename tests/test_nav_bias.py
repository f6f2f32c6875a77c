"""The dead reckoning's velocity bias (issue 27, rounds 7 and 9): a current drifts a robot's dead reckoning by a steady
velocity, so its error grows with time along an axis no scan pins, not with the square root of time. The filter
estimates the bias while the scans pin both axes and follows the drift once they pin only one; its covariance
covers the error."""

from __future__ import annotations

import math

import numpy as np

from lrsensor.frames import Pose, ned_to_body
from mapping.navigation import NavConfig, PlaneLandmarks, RobotNav
from mapping.smoother import SMOOTHED_NAV, RobotSmoother, SmootherConfig
from mapping.synth import Scene, tank, trace

S = 1_000_000_000
DRIFT_M_S = 0.02  # the current's drag on the dead reckoning, north
#: the bias state on (an option, off in NavConfig(): docs/navigation-design.md)
BIAS = NavConfig(dr_bias_sigma_m_s=0.003)


def _walls(scene: Scene) -> PlaneLandmarks:
    planes = []
    for i, f in enumerate(scene.faces):
        n, c, u = np.array(f.normal), np.array(f.center), np.array(f.u)
        extent = {"centroid": c.tolist(), "u": u.tolist(), "v": np.cross(n, u).tolist(),
                  "u_range_m": [-f.half_u, f.half_u], "v_range_m": [-f.half_v, f.half_v]}  # fmt: skip
        planes.append({"id": i + 1, "normal": n.tolist(), "d": f.d, "n_points": 10_000, "extent": extent})
    return PlaneLandmarks.from_planes(planes)


def _dive(
    cfg: NavConfig, drift_m_s: float = DRIFT_M_S, nav: RobotNav | None = None, corner_s: float = 20.0
) -> list[tuple[float, float, float]]:
    """A robot holding station 3 m from the south wall and 1 m from the west wall while its dead reckoning drifts
    north at 2 cm/s: ``corner_s`` looking into the corner (both axes pinned), then 8 s at the west wall only (north
    free).
    Returns, per scan of the second part, (time s, north error m, north std m)."""
    scene = tank(pillars=False)
    lm = _walls(scene)
    west = Scene(tuple(f for f in scene.faces if f.name == "wall.west"))
    nav = nav if nav is not None else RobotNav("rov1", cfg)
    out = []
    for k in range(round((corner_s + 8.0) * 10)):
        t = k * 0.1
        corner = t < corner_s
        true = Pose(3.0, 1.0, 1.0, 0.0, 0.0, math.radians(225.0 if corner else 270.0))
        hits = trace(scene if corner else west, true, n_rays=200, fan_deg=120.0 if corner else 60.0)
        raw = Pose(true.north_m + drift_m_s * t, true.east_m, true.down_m, 0.0, 0.0, true.yaw_rad)
        est = nav.update(round(t * S), raw, ned_to_body(hits.points_ned, true), lm)
        assert est.pose is not None
        if not corner:
            assert not est.constrained["north"]
            out.append((t, est.pose.north_m - true.north_m, est.std["north_m"]))
    return out


def test_a_current_s_drift_is_followed_along_an_axis_no_scan_pins() -> None:
    track = _dive(BIAS)
    errors = np.array([abs(e) for _, e, _ in track])
    assert errors.max() < 0.03  # 16 cm of drift in the 8 s: the estimated bias carries the prediction
    assert all(abs(e) <= 3.0 * s for _, e, s in track)  # and the covariance covers what is left


def test_without_the_bias_state_the_filter_is_overconfident_along_the_free_axis() -> None:
    # the default, without the bias state (white velocity noise only): the error outgrows 3 sigma
    track = _dive(NavConfig(dr_bias_sigma_m_s=0.0))
    _, err, std = track[-1]
    assert abs(err) > 0.1
    assert abs(err) > 3.0 * std


def test_the_bias_state_survives_a_snapshot() -> None:
    nav = RobotNav("rov1", BIAS)
    lm = PlaneLandmarks.empty()
    for k in range(5):
        nav.update(k * S // 10, Pose(0.01 * k, 0.0, 1.0, 0.0, 0.0, 0.0), np.zeros((0, 3)), lm)
    snap = nav.snapshot()
    other = RobotNav("rov1", BIAS)
    other.restore(snap)
    assert np.allclose(other.x, nav.x)
    assert np.allclose(other.P, nav.P)
    assert np.allclose(other.fix_mean, nav.fix_mean)


def test_the_smoother_carries_the_bias_back_over_the_window() -> None:
    # the same station keeping under the smoother: every revised pose of the dive stays on the truth (the backward
    # pass runs over all five states; its poses use the bias the later scans saw)
    _, worst = _smoothed_dive(BIAS, corner_s=20.0, n_scans=280)
    assert worst < 0.03


def _smoothed_dive(cfg: NavConfig, corner_s: float, n_scans: int) -> tuple[RobotSmoother, float]:
    """Station keeping in the tank's south-west corner for ``corner_s``, then facing the west wall alone, at 10 Hz
    with a north drift of DRIFT_M_S in the raw poses, through the smoother: the smoother and the worst north error
    (m) of its revised poses."""
    scene = tank(pillars=False)
    lm = _walls(scene)
    west = Scene(tuple(f for f in scene.faces if f.name == "wall.west"))
    sm = RobotSmoother("rov1", cfg, SmootherConfig())
    truth = {}
    for k in range(n_scans):
        t = k * 0.1
        corner = t < corner_s
        true = Pose(3.0, 1.0, 1.0, 0.0, 0.0, math.radians(225.0 if corner else 270.0))
        hits = trace(scene if corner else west, true, n_rays=200, fan_deg=120.0 if corner else 60.0)
        raw = Pose(true.north_m + DRIFT_M_S * t, true.east_m, true.down_m, 0.0, 0.0, true.yaw_rad)
        sm.update(round(t * S), raw, ned_to_body(hits.points_ned, true), lm)
        truth[round(t * S)] = true
    revised = sm.smooth(lm)
    assert len(revised) == n_scans
    return sm, max(abs(p.north_m - truth[t].north_m) for t, p in revised.items())


#: the smoother's default: each robot's bias held at zero until its fixes' disagreement persists (a drift shows)
ADAPTIVE = SMOOTHED_NAV


def test_the_default_opens_the_bias_only_once_a_drift_shows() -> None:
    assert ADAPTIVE.dr_bias_sigma_m_s > 0
    assert ADAPTIVE.dr_bias_adaptive
    steady = RobotNav("rov1", ADAPTIVE)
    track = _dive(ADAPTIVE, drift_m_s=0.0, nav=steady)
    assert not steady.bias_open  # good dead reckoning: the bias stays held at zero
    assert abs(float(steady.x[2])) < 1e-4
    assert math.sqrt(float(steady.P[2, 2])) < 1e-4
    assert max(abs(e) for _, e, _ in track) < 0.02
    drifting = RobotNav("rov1", ADAPTIVE)
    # a drift shows once its disagreement persists over about fix_quality_s (20 s): by then the corner has pinned
    # both axes long enough to estimate the bias that carries the prediction along the west wall
    track = _dive(ADAPTIVE, nav=drifting, corner_s=40.0)
    assert drifting.bias_open  # 2 cm/s: the fixes' disagreement persisted past fix_persist_min_m
    assert max(abs(e) for _, e, _ in track) < 0.03  # and the drift is followed where no scan pins north
    assert all(abs(e) <= 3.0 * s for _, e, s in track)


def test_an_open_bias_survives_a_snapshot() -> None:
    nav = RobotNav("rov1", ADAPTIVE)
    _dive(ADAPTIVE, nav=nav, corner_s=40.0)
    assert nav.bias_open
    twin = RobotNav("rov1", ADAPTIVE)
    assert not twin.bias_open
    twin.restore(nav.snapshot())
    assert twin.bias_open
    fresh = RobotNav("rov1", ADAPTIVE)
    nav.restore(fresh.snapshot())  # and back: a restart closes it again
    assert not nav.bias_open


def test_the_smoother_re_runs_the_filter_s_choice() -> None:
    # the smoother restarts the filter from a scan's snapshot: its re-runs open the bias at the same fix, and the
    # revised poses of the whole drifting dive stay on the truth
    sm, worst = _smoothed_dive(ADAPTIVE, corner_s=40.0, n_scans=480)
    assert sm.nav.bias_open
    assert worst < 0.03
