"""A registration's correction kept out of the dead reckoning error's rate (``NavConfig.dr_error_rate_weight``,
``dr_error_rate_young_s``; issue 27, :mod:`mapping.nav_error`): a scan registered to a young plane off its face
moves the position but writes no confident wrong rate, while a drift the scans pin against old planes is still
learnt."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
from test_nav_bias import _dive

from lrsensor.frames import Pose, ned_to_body
from mapping.landmarks import PlaneLandmarks
from mapping.nav_error import consider_update, rate_gain, rate_weight, young_planes
from mapping.navigation import NavConfig, RobotNav
from mapping.smoother import SMOOTHED_NAV
from mapping.synth import Scene, tank, trace

S = 1_000_000_000
#: the smoother's tuning with the error state
ERROR_NAV = replace(SMOOTHED_NAV, dr_error_state=True)
#: the rate kept out of registrations that use a plane younger than 3 s
YOUNG_OUT = replace(ERROR_NAV, dr_error_rate_weight=0.0, dr_error_rate_young_s=3.0)
#: how far the young plane lies off its face (m): nav32's rov3 plane
OFF_M = 0.14


def _planes(shift_m: dict[str, float], first: dict[str, tuple[str, int]]) -> PlaneLandmarks:
    """The tank's walls as map planes: face name -> its shift along its normal (m, default 0) and -> (the robot
    that began it, when, ns; default another robot at 0)."""
    planes = []
    for i, f in enumerate(tank(pillars=False).faces):
        n, c, u = np.array(f.normal), np.array(f.center), np.array(f.u)
        sh = shift_m.get(f.name, 0.0)
        extent = {"centroid": (c + sh * n).tolist(), "u": u.tolist(), "v": np.cross(n, u).tolist(),
                  "u_range_m": [-f.half_u, f.half_u], "v_range_m": [-f.half_v, f.half_v]}  # fmt: skip
        who, t_ns = first.get(f.name, ("rov2", 0))
        contrib = {who: {"n_points": 10_000, "first_ns": t_ns}}
        planes.append({"id": i + 1, "normal": n.tolist(), "d": f.d - sh, "n_points": 10_000, "extent": extent,
                       "contributions": contrib})  # fmt: skip
    return PlaneLandmarks.from_planes(planes)


#: the young plane's map: the south wall begun by another robot 0.7 s before the corner scans (``WEST_S``)
WEST_S = 10.0


def _young_map() -> PlaneLandmarks:
    return _planes({"wall.south": OFF_M}, {"wall.south": ("rov3", round((WEST_S - 0.7) * S))})


def _young_plane(cfg: NavConfig, wrong_s: float = 1.0) -> RobotNav:
    """A robot with good fixes holding station 3 m from the south wall and 1 m from the west wall: ``WEST_S`` facing
    the west wall alone (north free), then ``wrong_s`` looking into the corner, where the south wall is a plane
    another robot began 0.7 s before, ``OFF_M`` off its face (nav32's runaway, in small)."""
    scene = tank(pillars=False)
    west = Scene(tuple(f for f in scene.faces if f.name == "wall.west"))
    old, young = _planes({}, {}), _young_map()
    nav = RobotNav("rov1", cfg)
    for k in range(round((WEST_S + wrong_s) * 10)):
        t = k * 0.1
        corner = t >= WEST_S
        true = Pose(3.0, 1.0, 1.0, 0.0, 0.0, math.radians(225.0 if corner else 270.0))
        hits = trace(scene if corner else west, true, n_rays=200, fan_deg=120.0 if corner else 60.0)
        pts = ned_to_body(hits.points_ned, true)
        nav.update(round(t * S), true, pts, young if corner else old)
    return nav


def test_a_young_plane_off_its_face_moves_the_position_but_writes_no_rate() -> None:
    kept_out = _young_plane(YOUNG_OUT)
    full = _young_plane(ERROR_NAV)
    for nav in (kept_out, full):
        assert float(nav.x[0]) - 3.0 > 0.1  # the registration still moves the position (north free till then)
    # with the full gain the jump writes a confident north rate the drift never had (then carried along a free
    # axis at minus the rate); kept out, the rate stays the launch's
    assert abs(float(full.x[2])) > 0.008
    assert math.sqrt(float(full.P[2, 2])) < 0.012
    assert abs(float(kept_out.x[2])) < 0.001
    assert math.sqrt(float(kept_out.P[2, 2])) > 0.02


def test_a_drift_pinned_against_old_planes_is_still_learnt() -> None:
    # the dead reckoning drifts 2 cm/s north while the corner (old planes) pins both axes for 40 s, then the west
    # wall alone leaves north free: the rate is learnt from those registrations and carries the estimate
    for cfg in (YOUNG_OUT, replace(ERROR_NAV, dr_error_rate_weight=0.3)):
        nav = RobotNav("rov1", cfg)
        track = _dive(cfg, nav=nav, corner_s=40.0)
        assert abs(float(nav.x[2]) - 0.02) < 0.005
        assert max(abs(e) for _, e, _ in track) < 0.03
        assert all(abs(e) < 3 * sd for _, e, sd in track)
    # kept out of every registration, the rate is learnt only through the covariance, slowly
    nav = RobotNav("rov1", replace(ERROR_NAV, dr_error_rate_weight=0.0))
    track = _dive(nav.cfg, nav=nav, corner_s=40.0)
    assert abs(float(nav.x[2]) - 0.02) > 0.005


def test_the_consider_update_is_the_kalman_update_with_the_gain_rows_scaled() -> None:
    rng = np.random.default_rng(3)
    n = 7
    a = rng.normal(size=(n, n))
    p = a @ a.T + np.eye(n) * 0.1
    x = rng.normal(size=n)
    h = np.zeros((3, n))
    h[[0, 1, 2], [0, 1, 4]] = 1.0
    r = np.diag([0.02, 0.05, 0.01])
    z = rng.normal(size=3)
    k = p @ h.T @ np.linalg.inv(h @ p @ h.T + r)
    hf = h.T @ np.linalg.inv(r) @ h
    x_opt = x + k @ (z - h @ x)
    p_opt = np.linalg.inv(np.linalg.inv(p) + hf)
    for w in (1.0, 0.3, 0.0):
        g = rate_gain(n, w)
        ks = g[:, None] * k
        i_kh = np.eye(n) - ks @ h
        want = i_kh @ p @ i_kh.T + ks @ r @ ks.T  # Joseph form, any gain
        got_x, got_p = consider_update(x, p, x_opt, p_opt, hf, g)
        np.testing.assert_allclose(got_x, x + ks @ (z - h @ x), atol=1e-9)
        np.testing.assert_allclose(got_p, want, atol=1e-9)
        assert np.all(np.linalg.eigvalsh(got_p) > 0)
    # at 0 the rate keeps its mean and variance; at 1 it is the optimal update
    got_x, got_p = consider_update(x, p, x_opt, p_opt, hf, rate_gain(n, 0.0))
    np.testing.assert_allclose(got_x[2:4], x[2:4])
    np.testing.assert_allclose(got_p[2:4, 2:4], p[2:4, 2:4], atol=1e-12)
    np.testing.assert_allclose(consider_update(x, p, x_opt, p_opt, hf, rate_gain(n, 1.0))[1], p_opt, atol=1e-9)


def test_young_planes_by_their_first_contribution() -> None:
    lm = _planes({}, {"wall.south": ("rov3", 9 * S), "wall.west": ("rov1", 5 * S)})
    young = young_planes(lm, 10 * S, 3.0)
    names = [f.name for f in tank(pillars=False).faces]
    assert [names[i] for i in np.flatnonzero(young)] == ["wall.south"]
    assert not young_planes(lm, 10 * S, 0.0).any()
    assert [names[i] for i in np.flatnonzero(young_planes(lm, 10 * S, 6.0))] == ["wall.south", "wall.west"]
    assert not young_planes(replace(lm, contrib=()), 10 * S, 3.0).any()  # without contributions: old


def test_the_rate_weight_applies_to_young_planes() -> None:
    cfg = replace(ERROR_NAV, dr_error_rate_weight=0.2)
    assert rate_weight(cfg, False) == 0.2  # no condition: every registration
    assert rate_weight(replace(cfg, dr_error_rate_weight=1.0), True) == 1.0
    assert rate_weight(replace(ERROR_NAV, dr_error_state=False, dr_error_rate_weight=0.2), True) == 1.0
    young = replace(cfg, dr_error_rate_young_s=3.0)
    assert rate_weight(young, True) == 0.2
    assert rate_weight(young, False) == 1.0
