"""The pose graph's scan odometry and its guards for a broken track (mapping/graph_odometry.py; issue 27,
docs/navigation-design.md, "Depth-only robots on extracted clouds"): along one wall with noisy stripe normals the
increment's along-wall move and its claimed standard deviation stay consistent, and a barely observed move is
widened."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from mapping.errors import MapInputError
from mapping.graph_config import TRACKED, GraphConfig
from mapping.graph_odometry import odometry_factor, speed_bound, spread_bound
from mapping.odometry import OdometryConfig, increment

DT_S = 0.1
BASE = GraphConfig()
#: the registration's prior on one 0.1 s move as the graph sets it (velocity walk, white 5 cm/s, velocity's)
PRIOR_COV = np.eye(2) * (
    BASE.velocity_walk_m_s**2 * DT_S**3 + (0.05 * DT_S) ** 2 + BASE.velocity_walk_m_s**2 * 0.1 * DT_S**2
)
SPEED_VAR = (BASE.max_speed_m_s * DT_S) ** 2
HONEST = replace(BASE, odometry_speed_bound="prediction", odometry_spread_m=0.03, odometry_residual_scale=True)
MOVE = np.array([0.02, 0.03])  # the true move: 2 cm toward the wall (north), 3 cm along it (east)


def _wall_scan(rng: np.random.Generator, at: np.ndarray, noise_m: float, n: int = 150) -> np.ndarray:
    """One stripe (n, 3) on a wall 1 m north of the origin (facing south), seen from ``at`` (north, east), in stripe
    order, its range (north) noisy by ``noise_m``."""
    east = np.sort(rng.uniform(-0.6, 0.6, n))
    pts = np.stack([np.full(n, 1.0) + rng.normal(0.0, noise_m, n), east, np.zeros(n)], axis=1)
    return pts - np.array([at[0], at[1], 0.0])


def _along_wall(gcfg: GraphConfig, noise_m: float, draws: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per draw the between-factor's error along the wall (east, m), its claimed standard deviation there (the
    factor's covariance), and its error across (north): a prediction off by 1 cm per axis, the scan pair noisy."""
    ocfg = OdometryConfig(residual_scale=gcfg.odometry_residual_scale)
    err, sd, across = [], [], []
    for seed in range(draws):
        rng = np.random.default_rng(seed)
        prev, new = _wall_scan(rng, np.zeros(2), noise_m), _wall_scan(rng, MOVE, noise_m)
        pred = MOVE + rng.normal(0.0, 0.01, 2)
        z, info, pairs = odometry_factor(prev, new, pred, PRIOR_COV, SPEED_VAR, gcfg, ocfg)
        assert pairs > 0
        cov = np.linalg.inv(info)
        err.append(z[1] - MOVE[1])
        sd.append(math.sqrt(cov[1, 1]))
        across.append(z[0] - MOVE[0])
    return np.array(err), np.array(sd), np.array(across)


def test_along_one_wall_with_noisy_normals_the_move_stays_within_its_claimed_deviation() -> None:
    # 8 mm of range noise at 1 cm spacing: the stripe normals lean by degrees, and the noise itself gives the scan
    # an information along the wall, which grows with the noise
    err, sd, across = _along_wall(BASE, 0.008, 60)
    assert np.max(np.abs(err) / sd) > 3.0  # the first graph's odometry: claimed below what it moved wrong
    err, sd, across = _along_wall(HONEST, 0.008, 60)
    assert np.all(np.abs(err) <= 3.0 * sd)
    assert np.median(sd) > 0.015  # along the wall: the prediction's centimetre, not the noise's millimetres
    assert np.sqrt(np.mean(across**2)) < 0.004  # across the wall the scan still pins the move to millimetres


def test_noisier_stripes_claim_no_more_along_the_wall() -> None:
    _, sd_clean, _ = _along_wall(HONEST, 0.002, 20)
    _, sd_noisy, _ = _along_wall(HONEST, 0.008, 20)
    assert np.median(sd_noisy) >= 0.8 * np.median(sd_clean)
    _, sd_clean, _ = _along_wall(BASE, 0.002, 20)
    _, sd_noisy, _ = _along_wall(BASE, 0.008, 20)
    assert np.median(sd_noisy) < 0.6 * np.median(sd_clean)  # without the guards the noise reads as information


def test_the_speed_bound_widens_a_barely_observed_move_instead_of_claiming_it() -> None:
    # east barely observed (a 20 cm standard deviation) and moved 30 cm, farther than 0.6 m/s allows in 0.1 s
    h = np.diag([1 / 0.002**2, 1 / 0.2**2])
    pred = np.array([0.02, 0.03])
    z = np.array([0.021, 0.33])
    z_added, info = speed_bound(z, h, pred, SPEED_VAR, "added")
    assert z_added[1] == pytest.approx(0.33)  # claimed within sqrt(1 / info) = 5.8 cm: five deviations off
    assert (z_added[1] - pred[1]) * math.sqrt(info[1, 1]) > 5.0
    z_pred, info_pred = speed_bound(z, h, pred, SPEED_VAR, "prediction")
    assert np.allclose(info_pred, info)
    assert abs(z_pred[1] - pred[1]) * math.sqrt(info_pred[1, 1]) < 1.0  # within its deviation of the prediction
    assert z_pred[0] == pytest.approx(z[0], abs=1e-4)  # the pinned direction is the scan's
    z_rest, _ = speed_bound(np.array([0.02, 0.03]), np.zeros((2, 2)), pred, SPEED_VAR, "rest")
    assert np.allclose(z_rest, 0.0)  # nothing observed: no move, not the graph's own velocity again
    with pytest.raises(MapInputError, match="odometry_speed_bound"):
        speed_bound(z, h, pred, SPEED_VAR, "centre")


def test_the_spread_of_restarted_registrations_bounds_the_information() -> None:
    h = np.diag([1 / 0.002**2, 1 / 0.005**2])
    z = np.array([0.02, 0.03])
    # the restarts agree: the information stays
    assert np.allclose(spread_bound(z, h, [z, z + 1e-5, z - 1e-5]), h, rtol=0.01)
    # the restarts along east stayed near their starts (3 cm either side): east's variance is at least 3 cm's
    out = spread_bound(z, h, [z, z + np.array([0.0, 0.028]), z - np.array([0.0, 0.029])])
    assert 1 / out[1, 1] >= 0.028**2
    assert out[0, 0] == pytest.approx(h[0, 0], rel=1e-6)


def test_the_residual_scatter_scales_the_scan_information() -> None:
    def info(noise_m: float, scaled: bool) -> float:
        """The scan's information across a wall (1/m^2): the posterior's less the prior's."""
        rng = np.random.default_rng(3)
        # 2 cm apart: on a denser stripe the nearest neighbour picks a point of the same range error
        prev, new = _wall_scan(rng, np.zeros(2), noise_m, 60), _wall_scan(rng, np.zeros(2), noise_m, 60)
        _, cov, pairs = increment(prev, new, PRIOR_COV, OdometryConfig(residual_scale=scaled))
        assert pairs > 0
        return float((np.linalg.inv(cov) - np.linalg.inv(PRIOR_COV))[0, 0])

    # residuals within the 1 cm the information assumes: unchanged; of a few centimetres: divided by their scatter
    assert info(0.003, True) == pytest.approx(info(0.003, False), rel=1e-6)
    assert info(0.02, True) < 0.5 * info(0.02, False)


def test_the_guards_are_off_by_default_and_in_the_tracked_setting() -> None:
    for cfg in (GraphConfig(), TRACKED):
        assert cfg.odometry_spread_m == 0.0
        assert cfg.odometry_speed_bound == "added"
        assert not cfg.odometry_residual_scale


def _along_one_wall(cfg: GraphConfig, seed: int) -> tuple[np.ndarray, np.ndarray, bool]:
    """A graph launched at a corner (a wall 1 m north and one 1.5 m east, 8 mm of range noise) moving east 3 cm per
    0.1 s scan, after 2 s along the north wall alone for 3 s, no map: per scan the east error and east standard
    deviation (m), and whether the last scan's cloud would be placed."""
    from lrsensor.frames import Pose
    from mapping.landmarks import PlaneLandmarks
    from mapping.posegraph import GraphNav

    rng = np.random.default_rng(seed)
    g = GraphNav("rov1", graph=cfg)
    err, sd = [], []
    placed = False
    for k in range(50):
        east = 0.03 * k
        wall = _wall_scan(rng, np.zeros(2), 0.008)
        if k < 20:
            north = np.sort(rng.uniform(-0.6, 0.9, 100))
            side = np.stack([north, 1.5 - east + rng.normal(0.0, 0.008, 100), np.zeros(100)], axis=1)
            wall = np.concatenate([wall, side])
        fix = (0.0, 0.0) if k == 0 else (math.nan, math.nan)
        est = g.update(k * 100_000_000, Pose(fix[0], fix[1], 1.0, 0.0, 0.0, 0.0), wall, PlaneLandmarks.empty())
        assert est.pose is not None
        if k:
            err.append(abs(est.pose.east_m - east))
            sd.append(est.std["east_m"])
            placed = est.placed
    return np.array(err), np.array(sd), placed


def test_a_graph_along_one_wall_says_it_does_not_know_where_it_is_along_it() -> None:
    pytest.importorskip("gtsam")
    for seed in (1, 3):
        err, sd, placed = _along_one_wall(BASE, seed)
        assert err[-1] > 3.0 * sd[-1]  # the first graph: decimetres off, claimed within centimetres
        assert placed
        assert sd[-1] < BASE.place_std_m
        err, sd, placed = _along_one_wall(HONEST, seed)
        assert np.all(err <= 3.0 * sd)
        assert sd[-1] > HONEST.place_std_m  # the status says so: nothing placed
        assert not placed
