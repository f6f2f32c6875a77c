"""One surface seen from poses that disagree is one plane; distinct surfaces close together stay apart
(``PlaneMap.same_face``, :mod:`mapping.same_face`)."""

from __future__ import annotations

import numpy as np

from mapping import MapConfig
from mapping.plane_map import PlaneMap, PlaneRecord

Q = 1e-4
S = 1_000_000_000  # ns per s
#: the rule on (it is off by default: docs/mapping.md, "Measured")
ON = MapConfig(same_face_offset_m=0.15)


def _wall(
    rng: np.random.Generator,
    robot: str,
    north: float,
    east: tuple[float, float],
    down: tuple[float, float],
    t_s: float,
    n: int = 1500,
    hole: tuple[tuple[float, float], tuple[float, float]] | None = None,
) -> PlaneRecord:
    """An observation of the face north = const facing south (normal -north), points uniform over the box
    ``east`` x ``down`` (minus ``hole``: (east range, down range)), 3 mm noise, window ending at ``t_s``."""
    p = np.stack([north + rng.normal(0, 0.003, n), rng.uniform(*east, n), rng.uniform(*down, n)], 1)
    if hole is not None:
        (e0, e1), (d0, d1) = hole
        p = p[~((p[:, 1] > e0) & (p[:, 1] < e1) & (p[:, 2] > d0) & (p[:, 2] < d1))]
    t = int(t_s * S)
    q = np.rint(p / Q).astype(np.int64)
    return PlaneRecord.from_points(q, np.array([-1.0, 0, 0]), robot, t - S, t, MapConfig())


def _norths(pm: PlaneMap) -> list[float]:
    return sorted(round(-float(p.fit.d) / float(p.fit.normal[0]), 2) for p in pm.planes.values())


def test_a_step_in_a_wall_seen_by_one_robot_stays_two_planes() -> None:
    # one robot passes from the upper part of a wall to a recess 10 cm deeper: the covers lie side by side in
    # depth, one never over the other, so they are no copies
    rng = np.random.default_rng(3)
    pm = PlaneMap(ON)
    for t in range(3):
        pm.add(_wall(rng, "rov1", 3.0, (0, 3), (0.8, 1.5), t + 1))
    for t in range(3):
        pm.add(_wall(rng, "rov1", 3.1, (0, 3), (1.55, 2.3), t + 4))
    assert _norths(pm) == [3.0, 3.1]


def _wall_and_copy(cfg: MapConfig) -> PlaneMap:
    # rov3 never saw the wall within merge_offset_m: its copy 11 cm behind covers what rov1's plane covers
    rng = np.random.default_rng(4)
    pm = PlaneMap(cfg)
    for t in range(6):
        pm.add(_wall(rng, "rov1", 3.0, (0, 2), (1.0, 2.0), t + 1, n=3000))
    for t in range(3):
        pm.add(_wall(rng, "rov3", 3.11, (0.2, 1.8), (1.3, 1.7), 20 + t, n=3000))
    return pm


def test_a_copy_of_a_wall_made_from_other_poses_fuses_where_the_covers_overlap() -> None:
    pm = _wall_and_copy(ON)
    assert len(pm) == 1
    (plane,) = pm.planes.values()
    assert sorted(plane.record.contributions) == ["rov1", "rov3"]
    # the copy was moved onto the wall rov1 saw: the plane stays where it was, and thin
    assert _norths(pm) == [3.0]
    assert plane.fit.rms_m < 0.005


def test_same_face_offset_zero_turns_the_rule_off_and_is_the_default() -> None:
    assert MapConfig().same_face_offset_m == 0.0
    assert _norths(_wall_and_copy(MapConfig())) == [3.0, 3.11]


def test_a_face_in_front_of_a_wall_and_parallel_faces_farther_apart_stay_apart() -> None:
    rng = np.random.default_rng(5)
    cfg = ON
    pm = PlaneMap(cfg)
    box = ((0.82, 1.23), (1.32, 1.73))
    for t in range(6):  # the wall, hidden behind a 0.4 m box face standing 10 cm in front of it
        pm.add(_wall(rng, "rov1", 3.0, (0, 4), (1.0, 2.0), t + 1, n=6000, hole=box))
    for t in range(3):  # the box face, seen by another robot: its cover meets the wall's along its border only
        pm.add(_wall(rng, "rov2", 2.9, *box, 20 + t, n=3000))
    for t in range(3):  # a parallel face beyond same_face_offset_m (0.15 m), covering another part of the wall
        pm.add(_wall(rng, "rov2", 2.82, (2.5, 3.8), (1.0, 2.0), 30 + t))
    assert cfg.same_face_offset_m < 0.18
    assert _norths(pm) == [2.82, 2.9, 3.0]


def test_a_shifted_record_is_the_record_of_the_shifted_points() -> None:
    rng = np.random.default_rng(8)
    p = np.rint(np.stack([3.0 + rng.normal(0, 0.003, 800), rng.uniform(0, 1, 800), rng.uniform(1, 2, 800)], 1) / Q)
    p = p.astype(np.int64)
    cfg = MapConfig()
    t = (1234, -77, 5)
    a = PlaneRecord.from_points(p, np.array([-1.0, 0, 0]), "r", 1, 2, cfg).shifted(t, 500)
    b = PlaneRecord.from_points(p + np.array(t), np.array([-1.0, 0, 0]), "r", 1, 2, cfg)
    for key in ("stats", "aabb_min", "aabb_max", "within", "orient"):
        assert getattr(a, key) == getattr(b, key), key
    assert a.voxels.counts.sum() == b.voxels.counts.sum()
    assert np.array_equal(a.voxels.sums.sum(axis=0), b.voxels.sums.sum(axis=0))
