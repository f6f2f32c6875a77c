"""The map's box index (``mapping.plane_map._Boxes``): the same association as a test of every plane."""

from __future__ import annotations

import numpy as np

from mapping import MapConfig
from mapping.plane_map import MapPlane, PlaneMap, PlaneRecord


def _patch(rng: np.random.Generator, centre: np.ndarray, normal: np.ndarray, robot: str, t_ns: int) -> PlaneRecord:
    """A 0.6 x 0.4 m patch of 400 points around ``centre`` (NED, m) facing ``normal``, quantized as the map does."""
    cfg = MapConfig()
    u = np.cross(normal, [0.0, 0.0, 1.0] if abs(normal[2]) < 0.9 else [1.0, 0.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(normal, u)
    a = rng.uniform(-0.3, 0.3, 400)[:, None]
    b = rng.uniform(-0.2, 0.2, 400)[:, None]
    p = centre + a * u + b * v + rng.normal(0.0, 0.002, (400, 1)) * normal
    q = np.rint(p / cfg.quantum_m).astype(np.int64)
    return PlaneRecord.from_points(q, normal, robot, t_ns, t_ns + 10, cfg)


def _brute(pm: PlaneMap, rec: PlaneRecord) -> list[int]:
    return [pid for pid in sorted(pm.planes) if pm._touch(rec, pm.planes[pid].record)]


def test_the_index_finds_exactly_the_planes_a_test_of_each_finds() -> None:
    rng = np.random.default_rng(5)
    pm = PlaneMap(MapConfig())
    normals = np.array([[1.0, 0, 0], [0, 1.0, 0], [0, 0, -1.0], [0.7071, 0.7071, 0]])
    for i in range(400):  # patches scattered over a 6 m cube: fusions, removals and new planes all happen
        rec = _patch(rng, rng.uniform(0.0, 6.0, 3), normals[i % 4], f"r{i % 3}", i)
        assert pm._touching(rec) == _brute(pm, rec)
        pm.add(rec)
    assert len(pm._boxes.row) == len(pm.planes)
    assert len(pm.planes) > 50
    for _ in range(50):
        probe = _patch(rng, rng.uniform(-1.0, 7.0, 3), normals[0], "probe", 0)
        assert pm._touching(probe) == _brute(pm, probe)


def test_planes_filled_directly_are_indexed_on_the_next_add() -> None:
    """A saved map is loaded by filling ``planes``; the next association must see those planes."""
    rng = np.random.default_rng(6)
    cfg = MapConfig()
    wall = _patch(rng, np.array([3.0, 1.0, 1.0]), np.array([-1.0, 0.0, 0.0]), "rov1", 1)
    pm = PlaneMap(cfg)
    pm.planes[7] = MapPlane(7, wall, cfg)
    pm.next_id = 8
    pm.add(_patch(rng, np.array([3.0, 1.1, 1.05]), np.array([-1.0, 0.0, 0.0]), "rov2", 2))
    assert list(pm.planes) == [7]
    assert pm.planes[7].record.n_obs == 2
