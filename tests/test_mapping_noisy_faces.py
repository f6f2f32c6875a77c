"""Noisy far faces (``MapConfig.tilt_prior_deg``, :mod:`mapping.noisy_faces`): a tilt prior weighed against the
points' expected errors, and RMS gates that test the thickness beyond those errors."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from mapping import MapConfig
from mapping.builder_state import decode_state, encode_state
from mapping.noisy_faces import error_at_r2, horizontal_spread, noise_quanta2, prior_fit, prior_within
from mapping.plane_map import PlaneMap, PlaneRecord, record_from_wire, record_to_wire
from mapping.planes import plane_quality

ON = MapConfig()  # the default: a tilt prior of 10 deg (docs/mapping.md, "Noisy far faces")
OFF = MapConfig(tilt_prior_deg=0.0)


def _stripes(range_m: float, tilt_deg: float, offsets_m: tuple[float, float], n: int = 300) -> np.ndarray:
    """Two horizontal stripes (down -0.05 and +0.05 m) 2 m long on a face ``range_m`` north of the origin whose
    top leans ``tilt_deg`` toward the vehicle, each stripe moved along north by its entry of ``offsets_m`` (a range
    error shared by the whole stripe, as the extractor's along-stripe smoothing makes it): (2 n, 3) NED metres."""
    east = np.linspace(-1.0, 1.0, n)
    parts = []
    for z, off in zip((-0.05, 0.05), offsets_m, strict=True):
        north = range_m + z * math.tan(math.radians(tilt_deg)) + off
        parts.append(np.stack([np.full_like(east, north), east, np.full_like(east, z)], 1))
    return np.concatenate(parts)


def _tilt_deg(normal: np.ndarray) -> float:
    return math.degrees(math.asin(abs(float(normal[2]))))


def test_a_far_stripe_pair_s_tilt_goes_toward_vertical_only_as_far_as_its_noise_leaves_it_open() -> None:
    # 4.5 m: the pair's ranges differ by 3 cm of their noise; the plain fit leans 17 deg, the prior's under 3
    pts = _stripes(4.5, 0.0, (0.015, -0.015))
    sigma = error_at_r2(0.002, np.full(pts.shape[0], 4.5**2))
    assert float(sigma[0]) > 0.03
    _c, _w, plain, _sag = plane_quality(pts)
    _c, _w, axes, noise_m = prior_fit(pts, sigma, ON)
    assert _tilt_deg(plain[:, 0]) > 15.0
    assert _tilt_deg(axes[:, 0]) < 3.0
    assert noise_m == pytest.approx(float(sigma[0]))
    assert horizontal_spread(pts - pts.mean(axis=0), axes[:, 0]) == pytest.approx(0.578, abs=0.01)
    # a wide prior leaves the data's tilt
    _c, _w, wide, _noise = prior_fit(pts, sigma, MapConfig(tilt_prior_deg=85.0))
    assert _tilt_deg(wide[:, 0]) > 15.0


def test_a_near_sloping_face_keeps_its_slope() -> None:
    # real structures slope: 1.2 m away, millimetres of noise, the pair's 10 cm of height measure 12 deg; the
    # prior takes var / (var + sigma^2 / tan^2(10 deg)) of it (0.9 here: the pair's 5 cm sd against 3 mm of noise)
    pts = _stripes(1.2, 12.0, (0.0, 0.0))
    sigma = error_at_r2(0.002, np.full(pts.shape[0], 1.2**2))
    _c, _w, axes, _noise = prior_fit(pts, sigma, ON)
    assert 10.5 < _tilt_deg(axes[:, 0]) < 12.0
    _c, _w, axes, _noise = prior_fit(pts, sigma, MapConfig(tilt_prior_deg=30.0))
    assert _tilt_deg(axes[:, 0]) == pytest.approx(12.0, abs=0.2)


def test_floors_and_single_stripe_ribbons_are_judged_without_the_prior() -> None:
    rng = np.random.default_rng(1)
    floor = np.stack([rng.uniform(2, 4, 500), rng.uniform(-1, 1, 500), 3.0 + 0.002 * rng.standard_normal(500)], 1)
    sigma = np.full(500, 0.05)
    _c, w, axes, noise_m = prior_fit(floor, sigma, ON)
    assert _tilt_deg(axes[:, 0]) > 89.0
    assert noise_m == 0.0
    assert math.sqrt(w[0]) < 0.003
    assert prior_within(10**6, np.array([0.0, 0.0, 1.0]), ON) == 0


def test_the_expected_error_grows_faster_than_r2_beyond_the_band_it_was_measured_in() -> None:
    r2 = np.array([1.0, 2.25**2, 4.5**2])
    err = error_at_r2(0.002, r2)
    assert err[0] == pytest.approx(0.002)
    assert err[1] == pytest.approx(0.002 * 2.25**2)
    assert err[2] == pytest.approx(0.002 * 4.5**2 * 4.0)


def _record(pts_m: np.ndarray, sigma_m: float, cfg: MapConfig, robot: str = "rov1") -> PlaneRecord:
    q = cfg.quantum_m
    noise = noise_quanta2(np.full(pts_m.shape[0], sigma_m), q) if cfg.tilt_prior_deg > 0 else 0
    pq = np.rint(pts_m / q).astype(np.int64)
    return PlaneRecord.from_points(pq, np.array([-1.0, 0.0, 0.0]), robot, 0, 10**9, cfg, noise)


def test_two_noisy_views_of_a_far_wall_fuse_and_stay_vertical_by_default() -> None:
    rng = np.random.default_rng(2)

    def view(shift: float) -> np.ndarray:
        pts = _stripes(4.5, 0.0, (shift, -shift), n=400)
        pts[:, 0] += 0.04 * rng.standard_normal(pts.shape[0])
        return pts

    a, b = view(0.02), view(-0.02)
    for cfg, fused in ((ON, True), (OFF, False)):
        m = PlaneMap(cfg)
        m.add(_record(a, 0.045, cfg))
        m.add(_record(b, 0.045, cfg, "rov2"))
        assert (len(m.planes) == 1) is fused
    m = PlaneMap(ON)
    m.add(_record(a, 0.045, ON))
    m.add(_record(b, 0.045, ON, "rov2"))
    (plane,) = m.planes.values()
    assert _tilt_deg(plane.fit.normal) < 2.0  # each view leans 10-20 deg, the other way
    assert abs(plane.fit.d + 4.5 * plane.fit.normal[0]) < 0.01


def test_a_record_s_noise_survives_fusion_and_the_wire() -> None:
    pts = _stripes(4.5, 0.0, (0.0, 0.0))
    a, b = _record(pts, 0.045, ON), _record(pts + 0.001, 0.04, ON)
    assert a.noise > 0
    assert (a + b).noise == a.noise + b.noise
    back = record_from_wire(record_to_wire(a))
    assert back == a
    assert back.noise == a.noise
    plain = _record(pts, 0.045, OFF)
    assert plain.noise == 0
    assert plain.within[5] < a.within[5]


def test_a_plane_s_noise_survives_the_saved_state(tmp_path: Path) -> None:
    m = PlaneMap(ON)
    m.add(_record(_stripes(4.5, 0.0, (0.01, -0.01)), 0.045, ON))
    header, arrays = encode_state(ON, m, {}, {}, {})
    back, _tracks, _windows, _taken = decode_state(ON, json.loads(json.dumps(header)), arrays, tmp_path / "state")
    (rec,) = (p.record for p in back.planes.values())
    (orig,) = (p.record for p in m.planes.values())
    assert rec.noise == orig.noise > 0
    assert rec.within == orig.within
