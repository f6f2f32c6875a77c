"""The served map joins bands of one vertical face (``MapConfig.serve_band_gap_down_m``) while the planes
navigation registers against stay as built; copies and distinct faces stay apart in both."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from test_mapping_bands import _band, _two_bands

from lrsensor.frames import Pose
from mapping import MapBuilder, MapConfig
from mapping.plane_map import PlaneMap
from mapping.served import served_planes


def test_two_bands_of_one_face_are_served_as_one_plane_but_stay_two_landmarks() -> None:
    pm = _two_bands(MapConfig(), 3.03)
    assert len(pm) == 2  # the map (what navigation registers against) keeps both
    served = served_planes(pm)
    assert len(served) == 1
    (plane,) = served
    assert plane["id"] == min(pm.planes)
    assert plane["n_points"] == sum(p.record.stats.n for p in pm.planes.values())
    assert abs(plane["d"] + 3.015 * plane["normal"][0]) < 0.01


def test_a_copy_a_decimetre_off_and_a_coplanar_face_beside_it_are_served_apart() -> None:
    assert len(served_planes(_two_bands(MapConfig(), 3.10))) == 2
    assert len(served_planes(_two_bands(MapConfig(), 3.0, far_east=(1.5, 2.0)))) == 2


def test_two_planes_that_overlap_in_depth_yet_stayed_apart_are_copies_not_bands() -> None:
    # 3 cm apart over the same depths: the map did not fuse them (offset), so they are no bands of one face
    rng = np.random.default_rng(3)
    pm = PlaneMap(replace(MapConfig(), merge_offset_m=0.02))
    for t in range(3):
        pm.add(_band(rng, 3.0, (0.0, 0.5), (0.7, 1.2), t + 1))
    for t in range(3):
        pm.add(_band(rng, 3.03, (0.0, 0.5), (0.8, 1.3), t + 10))
    assert len(pm) == 2
    assert len(served_planes(pm)) == 2


def test_off_serves_the_planes_as_built() -> None:
    pm = _two_bands(replace(MapConfig(), serve_band_gap_down_m=0.0), 3.03)
    assert len(served_planes(pm)) == 2


def test_the_builder_serves_joined_bands_and_registers_to_the_planes_as_built() -> None:
    rng = np.random.default_rng(5)
    b = MapBuilder(MapConfig(extract_every_clouds=1, window_clouds=1, min_obs_frames=1, min_frame_points=10))
    for k, (down, t0) in enumerate(((0.95, 0.0), (2.55, 20.0))):
        for i in range(8):
            n = 1500
            pts = np.stack([3.0 + rng.normal(0, 0.003, n), rng.uniform(0, 0.5, n), rng.uniform(-0.25, 0.25, n)], 1)
            pts[:, 2] += down
            t = int((t0 + i) * 1e9)
            b.add_cloud("rov1", t, pts, Pose(2.0, 0.25, down, 0.0, 0.0, 0.0))
        assert len(b.landmarks()) == k + 1
    b.flush()
    assert len(b.landmarks()) == 2
    assert len(b.map_json()["planes"]) == 1


def test_copies_a_few_centimetres_apart_over_the_same_depths_are_served_as_one_when_asked() -> None:
    # the map kept them apart (offset gate 2 cm here); serve_copy_offset_m joins them in the served view only,
    # while a copy a decimetre off stays apart
    def built(gap: float, **served: float) -> tuple[PlaneMap, list[dict[str, object]]]:
        rng = np.random.default_rng(3)
        pm = PlaneMap(replace(MapConfig(), merge_offset_m=0.02, **served))
        for t in range(3):
            pm.add(_band(rng, 3.0, (0.0, 0.5), (0.7, 1.2), t + 1))
        for t in range(3):
            pm.add(_band(rng, 3.0 + gap, (0.0, 0.5), (0.8, 1.3), t + 10))
        return pm, served_planes(pm)

    pm, served = built(0.03, serve_copy_offset_m=0.04)
    assert len(pm) == 2
    assert len(served) == 1
    assert served[0]["n_points"] == sum(p.record.stats.n for p in pm.planes.values())
    assert len(built(0.03)[1]) == 2  # off (the default)
    assert len(built(0.10, serve_copy_offset_m=0.04)[1]) == 2
