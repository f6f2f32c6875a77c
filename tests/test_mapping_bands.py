"""Bands of one vertical face scanned at depths farther apart than ``merge_gap_down_m`` are one plane when the
band rule is on (``PlaneMap.bands``); copies a pose error set off the face and distinct faces stay apart."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from mapping import MapConfig
from mapping.plane_map import PlaneMap, PlaneRecord

Q = 1e-4
S = 1_000_000_000  # ns per s
#: the rule on (it is off by default: docs/mapping.md, "Bands of one face")
ON = MapConfig(merge_band_gap_down_m=3.0)


def _band(
    rng: np.random.Generator, north: float, east: tuple[float, float], down: tuple[float, float], t_s: float
) -> PlaneRecord:
    """One window's observation of the face north = const facing south: 1500 points over ``east`` x ``down``,
    3 mm noise."""
    n = 1500
    p = np.stack([north + rng.normal(0, 0.003, n), rng.uniform(*east, n), rng.uniform(*down, n)], 1)
    t = int(t_s * S)
    q = np.rint(p / Q).astype(np.int64)
    return PlaneRecord.from_points(q, np.array([-1.0, 0, 0]), "rov1", t - S, t, MapConfig())


def _two_bands(cfg: MapConfig, far_north: float, far_east: tuple[float, float] = (0.0, 0.5)) -> PlaneMap:
    # a pillar's face 0.5 m wide crossed at 0.7-1.2 m down, later at 2.4-2.7 m: a gap of 1.2 m along down
    rng = np.random.default_rng(7)
    pm = PlaneMap(cfg)
    for t in range(3):
        pm.add(_band(rng, 3.0, (0.0, 0.5), (0.7, 1.2), t + 1))
    for t in range(3):
        pm.add(_band(rng, far_north, far_east, (2.4, 2.7), t + 10))
    return pm


def test_the_rule_is_off_by_default_and_bands_then_stay_two_planes() -> None:
    assert MapConfig().merge_band_gap_down_m == 0.0
    assert len(_two_bands(MapConfig(), 3.03)) == 2


def test_two_bands_of_one_face_fuse_into_one_plane() -> None:
    pm = _two_bands(ON, 3.03)
    assert len(pm) == 1
    (plane,) = pm.planes.values()
    assert plane.record.n_obs == 6
    assert abs(-plane.fit.d / plane.fit.normal[0] - 3.015) < 0.01


def test_a_copy_a_decimetre_off_the_face_stays_apart() -> None:
    # a robot whose pose is 10 cm off puts its band beside the face: navigation registers to it, it must show
    assert len(_two_bands(ON, 3.10)) == 2


def test_a_coplanar_face_beside_it_stays_apart() -> None:
    # the same plane 1 m along the wall: another pillar's face, not the same stretch of face
    assert len(_two_bands(ON, 3.0, far_east=(1.5, 2.0))) == 2


def test_bands_beyond_merge_band_gap_down_m_stay_apart() -> None:
    assert len(_two_bands(replace(ON, merge_band_gap_down_m=1.1), 3.0)) == 2


def test_a_single_window_band_waits_until_it_is_confirmed() -> None:
    rng = np.random.default_rng(8)
    pm = PlaneMap(ON)
    for t in range(3):
        pm.add(_band(rng, 3.0, (0.0, 0.5), (0.7, 1.2), t + 1))
    pm.add(_band(rng, 3.0, (0.0, 0.5), (2.4, 2.7), 10))
    assert len(pm) == 2  # one odd window must not stretch the face over the tank's depth
    pm.add(_band(rng, 3.0, (0.0, 0.5), (2.4, 2.7), 11))
    assert len(pm) == 1
