"""The depth-only pose graph's options for noisy clouds (issue 27, docs/navigation-design.md, "Depth-only robots on
extracted clouds"): a scan increment keeps only the directions it observes, and the others' planes of one robot's
stretch share one horizontal offset."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from mapping.graph_config import TRACKED, GraphConfig
from mapping.odometry import own_increment

#: the velocity walk's prior on one 0.1 s move (GraphConfig's defaults: 0.1 m/s per sqrt(s), 5 cm/s white)
WALK_COV = np.eye(2) * (0.1**2 * 0.1**3 + (0.05 * 0.1) ** 2)


def _posterior(h_scan: np.ndarray, delta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """What :func:`mapping.odometry.increment` returns for a scan of information ``h_scan`` (2x2) whose own
    solution is ``delta`` (2,): the posterior mean (the prior's mean is zero) and covariance."""
    p_inv = np.linalg.inv(WALK_COV)
    cov = np.linalg.inv(p_inv + h_scan)
    return cov @ h_scan @ delta, cov


def test_a_barely_observed_direction_of_a_scan_increment_is_left_to_the_prior() -> None:
    # one wall facing north: the move across it (north) pinned to 2 mm, along it (east) a few noisy stripe normals
    # leaning its way give an information of a 0.2 m standard deviation; the scan's own move (1 cm, 3 mm)
    h_scan = np.diag([1 / 0.002**2, 1 / 0.2**2])
    d, cov = _posterior(h_scan, np.array([0.01, 0.003]))
    # the prior taken out by dividing by the information: the east shift comes back amplified by the noise in d
    d_noisy = d + np.array([0.0, 1e-4])  # a tenth of a millimetre of stripe noise in the posterior
    dz_all, h_all = own_increment(d_noisy, cov, WALK_COV, 1.0, math.inf)
    assert abs(dz_all[1] - 0.003) > 0.1  # a decimetre off in one 0.1 s move
    assert h_all[1, 1] == pytest.approx(1 / 0.2**2, rel=1e-6)
    # with a 5 cm bound on the directions that count: east is the prior's alone, north the scan's own
    dz, h = own_increment(d_noisy, cov, WALK_COV, 1.0, 0.05)
    assert dz[1] == pytest.approx(0.0, abs=1e-12)
    assert h[1, 1] == pytest.approx(0.0, abs=1e-9)
    assert dz[0] == pytest.approx(0.01, abs=1e-6)
    assert h[0, 0] == pytest.approx(1 / 0.002**2, rel=1e-6)


def test_the_options_are_off_in_the_tracked_setting() -> None:
    for cfg in (GraphConfig(), TRACKED):
        assert math.isinf(cfg.stretch_s)
        assert math.isinf(cfg.odometry_observed_std_m)
        assert cfg.odometry_prior_m_s == 0.0


def test_a_shared_plane_residual_and_its_jacobians() -> None:
    gtsam = pytest.importorskip("gtsam")
    from mapping.graph_factors import make_factor

    # a wall facing north (normal +north, at north 0), its stretch's shared offset (north, east) and its own
    n, c, const = np.array([1.0, 0.0]), np.array([1.0, 0.2]), 0.0
    spec = ("plane_shared", (0,), (7, n[0], n[1], c[0], c[1], const, 0.01, 42))
    factor = make_factor(gtsam, *spec)
    values = gtsam.Values()
    x0 = gtsam.Pose2(-1.05, 0.3, math.pi + 0.01)
    values.insert(0, x0)
    values.insert(gtsam.symbol("p", 7), np.array([0.01]))
    values.insert(gtsam.symbol("s", 42), np.array([0.03, -0.5]))

    def residual(v: Any) -> float:
        pose = v.atPose2(0)
        r = pose.rotation().matrix()
        t = np.array([pose.x(), pose.y()])
        return (
            float(n @ (t + r @ c + v.atVector(gtsam.symbol("s", 42))))
            + const
            + float(v.atVector(gtsam.symbol("p", 7))[0])
        )

    # the shared offset moves the residual along the plane's normal only: its east part says nothing
    e = residual(values)
    assert e == pytest.approx(
        -1.05 + float((np.array([[math.cos(x0.theta()), -math.sin(x0.theta())]]) @ c)[0]) + 0.03 + 0.01
    )
    from mapping.graph_factors import shared_plane_error

    class _Keys:
        def keys(self) -> list[int]:
            return [0, gtsam.symbol("p", 7), gtsam.symbol("s", 42)]

    jac: list[Any] = [None, None, None]
    assert shared_plane_error(n, c, const)(_Keys(), values, jac)[0] == pytest.approx(e)
    assert factor.error(values) > 0.0  # the GTSAM factor evaluates the same residual (robust, whitened)
    step = 1e-6
    for dim in range(3):
        xi = np.zeros(3)
        xi[dim] = step
        v2 = gtsam.Values(values)
        v2.update(0, x0.retract(xi))
        assert jac[0][0, dim] == pytest.approx((residual(v2) - e) / step, abs=1e-4)
    assert jac[1][0, 0] == pytest.approx(1.0)
    assert jac[2][0] == pytest.approx(n)


def _wall(pid: int, normal: list[float], d: float, centroid: list[float], u: list[float]) -> dict[str, Any]:
    """A 10 m x 2 m wall made by another robot (``other``, first seen at t = 0)."""
    extent = {"centroid": centroid, "u": u, "v": [0.0, 0.0, 1.0], "u_range_m": [-5.0, 5.0], "v_range_m": [-1.0, 1.0]}
    return {"id": pid, "normal": normal, "d": d, "n_points": 5000, "extent": extent,
            "contributions": {"other": {"n_points": 5000, "first_ns": 0}}}  # fmt: skip


def test_the_planes_of_one_robots_stretch_share_one_offset_and_it_crosses_processes() -> None:
    pytest.importorskip("gtsam")
    from lrsensor.frames import Pose
    from mapping.landmarks import PlaneLandmarks
    from mapping.posegraph import GraphNav
    from services.map_worker_nav import decode_state, encode_state

    # a corner: a wall at north 3 m facing south and one at east 3 m facing west, both another robot's
    lm = PlaneLandmarks.from_planes([
        _wall(7, [-1.0, 0.0, 0.0], 3.0, [3.0, 0.0, 1.0], [0.0, 1.0, 0.0]),
        _wall(8, [0.0, -1.0, 0.0], 3.0, [0.0, 3.0, 1.0], [1.0, 0.0, 0.0]),
    ])  # fmt: skip
    ys = np.linspace(-0.5, 0.5, 100)
    north = np.stack([np.full_like(ys, 1.0), ys, np.zeros_like(ys)], axis=1)  # the north wall, 1 m ahead
    east = np.stack([ys, np.full_like(ys, 1.0), np.zeros_like(ys)], axis=1)  # the east wall, 1 m to the right
    body = np.concatenate([north, east])

    def run(cfg: GraphConfig) -> GraphNav:
        g = GraphNav("rov1", graph=cfg)
        g.update(0, Pose(2.0, 2.0, 1.0, 0.0, 0.0, 0.0), body, lm)
        for k in range(1, 8):
            g.update(k * 100_000_000, Pose(math.nan, math.nan, 1.0, 0.0, 0.0, 0.0), body, lm)
        return g

    shared = run(GraphConfig(stretch_s=10.0))
    assert len(shared._stretch_ids) == 1  # both walls: one robot, one stretch
    assert shared._plane_ids == {7, 8}
    assert not run(GraphConfig())._stretch_ids
    restored = GraphNav("rov1", graph=GraphConfig(stretch_s=10.0))
    restored.restore(decode_state(encode_state(shared.snapshot())))
    assert restored._stretch_ids == shared._stretch_ids
    t = 8 * 100_000_000
    a = shared.update(t, Pose(math.nan, math.nan, 1.0, 0.0, 0.0, 0.0), body, lm)
    b = restored.update(t, Pose(math.nan, math.nan, 1.0, 0.0, 0.0, 0.0), body, lm)
    assert a.pose is not None
    assert b.pose is not None
    assert math.hypot(a.pose.north_m - b.pose.north_m, a.pose.east_m - b.pose.east_m) < 0.01
