"""A face as thick as the robots' pose errors make it still takes the views that lie on it (the demo's duplicate,
issue 27); distinct faces near it stay apart (``merge_max_rms_m``: what a fusion adds, :func:`added_rms_m`)."""

from __future__ import annotations

import math

import numpy as np

from mapping import MapConfig
from mapping.plane_map import MapPlane, PlaneMap, PlaneRecord, added_rms_m, fit_parts

Q = 1e-4
S = 1_000_000_000  # ns per s


def _view(rng: np.random.Generator, robot: str, north: float, t_s: float, n: int = 2000) -> PlaneRecord:
    """One robot's view of the face north = const facing south (normal -north), 3 mm noise, east 0-3 m,
    down 1-2 m: one observation as a window gives it."""
    p = np.stack([north + rng.normal(0, 0.003, n), rng.uniform(0, 3, n), rng.uniform(1, 2, n)], 1)
    t = int(t_s * S)
    return PlaneRecord.from_points(
        np.rint(p / Q).astype(np.int64), np.array([-1.0, 0, 0]), robot, t - S, t, MapConfig()
    )


def _thick_face(rng: np.random.Generator, half_m: float, cfg: MapConfig) -> PlaneMap:
    """A map holding one plane of the wall north = 3 made of two robots' views ``2 * half_m`` apart (their poses
    disagree): its RMS is about ``half_m``, the plane at 3.0. Put in directly, as a loaded map is."""
    rec = _view(rng, "rov1", 3.0 - half_m, 1)
    for k in range(1, 12):
        rec = rec + _view(rng, "rov3" if k % 2 else "rov1", 3.0 + (half_m if k % 2 else -half_m), k + 1)
    pm = PlaneMap(cfg)
    pm.planes[1] = MapPlane(1, rec, cfg)
    pm.next_id = 2
    return pm


def _norths(pm: PlaneMap) -> list[float]:
    return sorted(round(-float(p.fit.d) / float(p.fit.normal[0]), 2) for p in pm.planes.values())


def test_a_view_lying_on_a_face_as_thick_as_the_bound_joins_it() -> None:
    # Robots 6.4 cm apart make a face plane 3.2 cm RMS thick, above merge_max_rms_m (3 cm): a view 1 cm from it
    # (within its thickness) made a second plane of the face when the test took the fused plane's whole RMS.
    rng = np.random.default_rng(1)
    cfg = MapConfig()
    pm = _thick_face(rng, 0.032, cfg)
    (face,) = pm.planes.values()
    assert face.fit.rms_m > cfg.merge_max_rms_m
    view = _view(rng, "rov3", 3.01, 30)
    merged = fit_parts(
        face.record.stats + view.stats,
        tuple(a + b for a, b in zip(face.record.within, view.within, strict=True)),
        tuple(a + b for a, b in zip(face.record.orient, view.orient, strict=True)),  # type: ignore[arg-type]
        Q,
    )
    assert merged.rms_m > cfg.merge_max_rms_m  # the whole-RMS test refused it
    pm.add(view)
    assert len(pm) == 1
    assert pm.planes[1].record.n_obs == 13


def test_distinct_faces_near_a_thick_face_stay_apart() -> None:
    rng = np.random.default_rng(2)
    pm = _thick_face(rng, 0.032, MapConfig())
    for t in range(3):
        pm.add(_view(rng, "rov2", 2.88, 40 + t))  # a face 12 cm in front of the wall (a pillar, a plate)
        pm.add(_view(rng, "rov2", 3.1, 50 + t))  # and one 10 cm behind it (a recess seen through an opening)
    assert _norths(pm) == [2.88, 3.0, 3.1]


def test_a_plane_thickened_past_the_cap_takes_no_view_a_thin_face_would_refuse() -> None:
    # A plane 4.5 cm RMS thick (views bridged into it) excuses only merge_max_rms_m of its thickness: a view 5.5 cm
    # off it (inside merge_offset_m) stays apart, as it would from a thin plane (it adds 3.3 cm of thickness).
    rng = np.random.default_rng(3)
    cfg = MapConfig()
    pm = _thick_face(rng, 0.045, cfg)
    view = _view(rng, "rov2", 3.055, 60)
    pm.add(view)
    assert len(pm) == 2


def test_added_thickness_of_parallel_planes_is_their_distance_times_the_root_of_the_shares() -> None:
    rng = np.random.default_rng(4)
    a, b = _view(rng, "a", 3.0, 1, n=3000), _view(rng, "b", 3.06, 2, n=1000)
    fa, fb = a.fit(Q), b.fit(Q)
    merged = fit_parts(
        a.stats + b.stats,
        tuple(x + y for x, y in zip(a.within, b.within, strict=True)),
        tuple(x + y for x, y in zip(a.orient, b.orient, strict=True)),  # type: ignore[arg-type]
        Q,
    )
    got = added_rms_m(fa, a.stats.n, fb, b.stats.n, merged, 0.03)
    assert got == abs(got)
    assert math.isclose(got, 0.06 * math.sqrt(0.75 * 0.25), rel_tol=0.03)
    # a part's own RMS is excused only up to own_max_m
    assert added_rms_m(fa, a.stats.n, fb, b.stats.n, merged, 0.001) > got
