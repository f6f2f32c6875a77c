"""Simulator: ray casting against hand-worked values, exact truth, exact stripe rendering, occlusion, water."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from lrsensor.calibration import Calibration, LaserPlane
from lrsensor.errors import SimulationError
from lrsensor.frames import Pose, body_to_ned
from lrsensor.sim import (
    SCENES,
    Checkerboard,
    Cylinder,
    Plane,
    Rectangle,
    Scene,
    WaterModel,
    acrylic_port,
    box,
    checkerboard_wall_scene,
    named_scene,
    render,
    wall_rectangle,
    wall_scene,
)

SMALL = (480, 270)


# --------------------------------------------------------------------------- ray casting
def test_plane_raycast_hand_worked() -> None:
    scene = Scene((Plane.make((2, 0, 0), (1, 0, 0)),))
    t, sid, n = scene.raycast((0, 0, 0), [[1, 1, 0], [-1, 0, 0], [0, 1, 0], [2, 0, 0]])
    # t is in units of |dir|: (1,1,0) reaches x = 2 at t = 2; (2,0,0) at t = 1
    np.testing.assert_allclose(t, [2.0, np.inf, np.inf, 1.0])
    np.testing.assert_array_equal(sid, [0, -1, -1, 0])
    np.testing.assert_allclose(n[0], [1, 0, 0])
    np.testing.assert_allclose(n[1], [0, 0, 0])


def test_rectangle_raycast_and_distance() -> None:
    rect = Rectangle.make((2, 0, 0), (0, 1, 0), (0, 0, 1), 1.0, 1.0, "r")
    scene = Scene((rect,))
    t, sid, _ = scene.raycast(np.zeros(3), [[1, 0.2, 0], [1, 0.3, 0], [1, 0, 0.24], [1, 0, -0.26]])
    np.testing.assert_allclose(t, [2.0, np.inf, 2.0, np.inf])
    np.testing.assert_array_equal(sid, [0, -1, 0, -1])
    d = scene.distance_to_surface([[0, 0, 0], [2, 1.5, 0], [3, 0, 0.5]])
    np.testing.assert_allclose(d, [2.0, 1.0, 1.0])


def test_cylinder_raycast_hand_worked() -> None:
    cyl = Cylinder.make((3, 0, 0), (0, 0, 1), 1.0, 2.0, "pipe")
    scene = Scene((cyl,))
    t, _sid, n = scene.raycast(np.zeros(3), [[1, 0, 0], [1, 1.5 / 3, 0], [1, 0, 0.5], [1, 0, 0.6]])
    # front at x = 2; y = 1.5 at x = 3 misses; z = 1 at x = 2 is on the rim; z = 1.2 misses, far side z = 2.4 too
    np.testing.assert_allclose(t, [2.0, np.inf, 2.0, np.inf])
    np.testing.assert_allclose(n[0], [-1, 0, 0], atol=1e-12)
    # oblique ray y = x / 4: (x - 3)^2 + x^2 / 16 = 1  ->  (17/16) x^2 - 6 x + 8 = 0, nearer root
    t2, _, n2 = scene.raycast(np.zeros(3), [[1, 0.25, 0]])
    x = (6 - math.sqrt(36 - 4 * (17 / 16) * 8)) / (2 * 17 / 16)
    np.testing.assert_allclose(t2, [x])
    p = np.array([x, x / 4, 0])
    np.testing.assert_allclose(n2[0], (p - [3, 0, 0]) / np.linalg.norm(p - [3, 0, 0]), atol=1e-12)
    # from inside the pipe the far wall is hit
    t3, _, _ = scene.raycast((3, 0, 0), [[1, 0, 0]])
    np.testing.assert_allclose(t3, [1.0])
    # on the axis 2 m past the end: the nearest point is the rim (radial 1, axial 2)
    np.testing.assert_allclose(scene.distance_to_surface([[0, 0, 0], [3, 0, 3]]), [2.0, math.sqrt(5.0)])


def test_box_faces_face_outward_and_nearest_wins() -> None:
    faces = box((3, 0, 0), (1, 1, 1), name="b")
    scene = Scene((Plane.make((10, 0, 0), (1, 0, 0), "far"), *faces))
    t, sid, n = scene.raycast(np.zeros(3), [[1, 0, 0]])
    assert t[0] == pytest.approx(2.5)
    assert scene.surfaces[sid[0]].name == "b-x"
    np.testing.assert_allclose(n[0], [-1, 0, 0])
    for f in faces:
        centre_dir = np.asarray(f.center) - np.array([3, 0, 0])
        assert float(f.normal @ centre_dir) > 0


def test_ned_scene_in_body_frame() -> None:
    wall_ned = Scene((Plane.make((5, 0, 0), (1, 0, 0)),), "ned")
    with pytest.raises(SimulationError, match="pose"):
        wall_ned.in_body(None)
    body = wall_ned.in_body(Pose(2.0, 0.0, 1.0, 0.0, 0.0, 0.0))
    t, _, _ = body.raycast(np.zeros(3), [[1, 0, 0]])
    assert t[0] == pytest.approx(3.0)
    east_wall = Scene((Rectangle.make((0, 4, 0), (1, 0, 0), (0, 0, 1), 10, 10),), "ned")
    body = east_wall.in_body(Pose(0.0, 1.0, 0.0, 0.0, 0.0, math.pi / 2))
    t, _, _ = body.raycast(np.zeros(3), [[1, 0, 0]])
    assert t[0] == pytest.approx(3.0)


def test_raycast_rejects_bad_shapes() -> None:
    scene = Scene((Plane.make((1, 0, 0), (1, 0, 0)),))
    with pytest.raises(Exception, match="shape"):
        scene.raycast(np.zeros((2, 3)), np.ones((3, 3)))
    with pytest.raises(SimulationError):
        Plane.make((0, 0, 0), (0, 0, 0))


# --------------------------------------------------------------------------- truth
def _project_cv(calib: Calibration, pts: np.ndarray) -> np.ndarray:
    rvec, _ = cv2.Rodrigues(calib.R_cam_body)
    uv, _ = cv2.projectPoints(pts.reshape(-1, 1, 3), rvec, calib.t_cam_body, calib.camera.K, calib.camera.dist)
    return uv.reshape(-1, 2)


@pytest.mark.parametrize("name", ["paper_box", "distorted", "tilted_lasers", "pipe", "tank"])
def test_truth_matches_cv2_projectpoints(name: str) -> None:
    r = named_scene(name, *SMALL).with_(water=WaterModel.clean()).render(seed=0)
    for lt in r.truth.lasers:
        assert len(lt) > 100
        uv_cv = _project_cv(r.calibration, lt.points_body)
        assert np.abs(uv_cv - lt.uv).max() < 0.01
        # every truth point is on its laser plane and on the surface it names
        lp = r.calibration.lasers[lt.index]
        assert np.abs(lp.signed_distance(lt.points_body)).max() < 1e-9
        for sid in np.unique(lt.surface_id):
            sel = lt.surface_id == sid
            d = r.truth.scene_body.surfaces[sid].distance(lt.points_body[sel])
            assert d.max() < 1e-8


def test_truth_in_ned_lies_on_the_tank() -> None:
    setup = named_scene("tank", *SMALL)
    truth = setup.with_(water=WaterModel.clean()).render(seed=0).truth
    pts_ned = truth.points_ned()
    assert pts_ned.shape[0] > 100
    assert setup.scene.distance_to_surface(pts_ned).max() < 1e-8
    np.testing.assert_allclose(
        body_to_ned(truth.lasers[0].points_body, setup.pose), truth.points_ned()[: len(truth.lasers[0])]
    )


def test_wall_truth_is_the_paper_geometry() -> None:
    # perpendicular wall at D: v = cy -/+ fy c / D for the top/bottom laser, every column visible
    setup = wall_scene(1.25, width=1920, height=1080)
    r = setup.with_(water=WaterModel.clean()).render(seed=0)
    cam = r.calibration.camera
    for lt, sign in zip(r.truth.lasers, (-1, 1), strict=True):
        cols = r.truth.visible_columns(lt.index)
        assert cols.size == cam.width
        v = r.truth.v_at_columns(lt.index, cols)
        np.testing.assert_allclose(v, cam.cy + sign * cam.fy * 0.05 / 1.25, atol=1e-9)
        pts = r.truth.points_at_columns(lt.index, cols)
        np.testing.assert_allclose(pts[:, 0], 1.25, atol=1e-12)
    assert np.isnan(r.truth.v_at_columns(0, [-5.0, 5000.0])).all()


def test_scaled_scene_keeps_the_field_of_view() -> None:
    full = named_scene("tilted_wall").with_(water=WaterModel.clean()).render(seed=0).truth
    half = named_scene("tilted_wall", 960, 540).with_(water=WaterModel.clean()).render(seed=0).truth
    u = np.arange(100, 900, 50, dtype=float)
    v_half = half.v_at_columns(0, u)
    v_full = full.v_at_columns(0, (u + 0.5) * 2 - 0.5)
    np.testing.assert_allclose(v_half, (v_full + 0.5) / 2 - 0.5, atol=1e-6)


# --------------------------------------------------------------------------- exact stripe rendering
def _column_centroids(img_g: np.ndarray, truth_v: np.ndarray, cols: np.ndarray, half: int) -> np.ndarray:
    out = np.full(cols.size, np.nan)
    for i, (c, v) in enumerate(zip(cols, truth_v, strict=True)):
        lo, hi = max(round(v) - half, 0), min(round(v) + half + 1, img_g.shape[0])
        w = img_g[lo:hi, c]
        if w.sum() > 0:
            out[i] = (w * np.arange(lo, hi)).sum() / w.sum()
    return out


@pytest.mark.parametrize("name", ["wall_1.0", "wall_0.3", "tilted_lasers", "distorted", "corner"])
def test_stripe_centroid_is_the_true_centre(name: str) -> None:
    # clean water, 8-bit image: the intensity centroid of each column is the projected truth (<= 0.05 px)
    setup = named_scene(name).with_(water=WaterModel.clean())
    r = setup.render(seed=0, keep_layers=True)
    g = r.image[:, :, 1].astype(float) - 8.0  # clean background level
    g[g < 0.5] = 0.0
    for lt in r.truth.lasers:
        other = r.truth.v_at_columns(1 - lt.index)
        cols = r.truth.visible_columns(lt.index, min_peak_dn=20.0)
        v = r.truth.v_at_columns(lt.index, cols)
        slope = np.abs(np.gradient(v))
        keep = (np.abs(v - other[cols]) > 30) & (slope < 0.5)
        keep[:4] = keep[-4:] = False
        cols, v = cols[keep], v[keep]
        assert cols.size > 500
        err = np.abs(_column_centroids(g, v, cols, 12) - v)
        assert np.nanmedian(err) < 0.02, name
        assert np.nanpercentile(err, 95) < 0.05, name
        # the float layer (before 8-bit rounding) is exact
        errf = np.abs(_column_centroids(r.layers["laser"].astype(float), v, cols, 12) - v)
        assert np.nanmax(errf) < 0.01, name


def test_saturated_stripe_is_flat_topped_and_centred() -> None:
    r = named_scene("wall_0.3").with_(water=WaterModel.clean()).render(seed=0)
    g = r.image[:, :, 1]
    v = r.truth.v_at_columns(0, [960.0])[0]
    col = g[int(v) - 6 : int(v) + 7, 960]
    assert (col == 255).sum() >= 3  # flat top
    assert r.image[round(v), 960, 0] < 255  # the blue bleed is not saturated


def test_stripe_is_green() -> None:
    r = named_scene("wall_1.0", *SMALL).with_(water=WaterModel.clean()).render(seed=0)
    v = round(r.truth.v_at_columns(0, [240.0])[0])
    b, gr, rd = r.image[v, 240].astype(int)
    assert gr > 2 * b > 0
    assert gr > 5 * rd


# --------------------------------------------------------------------------- occlusion and shadows
def test_box_in_front_hides_the_wall() -> None:
    setup = named_scene("occluder")
    r = setup.with_(water=WaterModel.clean()).render(seed=0)
    names = r.truth.scene_body.names()
    for lt in r.truth.lasers:
        on_wall = np.array([names[s] == "wall" for s in lt.surface_id])
        on_box = np.array([names[s].startswith("box") for s in lt.surface_id])
        assert on_wall.any()
        assert on_box.any()
        # the box (|y| <= 0.2 at x = 0.85) shadows the wall for |y/x| < 0.2 / 0.85
        p = lt.points_body[on_wall]
        assert np.abs(p[:, 1] / p[:, 0]).min() >= 0.2 / 0.85 - 1e-6
        # the stripe columns over the box show the box, not the wall
        cols = r.truth.visible_columns(lt.index)
        centre = r.truth.points_at_columns(lt.index, [959.5])
        assert centre[0, 0] == pytest.approx(0.85, abs=1e-9)
        assert cols.size > 1800


def test_camera_shadow_hides_lit_points() -> None:
    # a block below the top laser's sheet (the sheet passes over it) but between the camera and the wall
    wall = wall_rectangle(2.0, name="wall")
    block = box((0.6, 0.0, 0.135), (0.2, 0.4, 0.33), name="block")  # z from -0.03 to 0.3
    scene = Scene((wall, *block))
    calib = named_scene("wall_1.0").calibration
    r = render(scene, calib, water=WaterModel.clean(), seed=0)
    top = r.truth.lasers[0]
    # the top laser itself reaches the wall straight ahead...
    _t, sid, _ = scene.raycast(calib.lasers[0].point_body, [[1, 0, 0]])
    assert scene.surfaces[sid[0]].name == "wall"
    # ...but the camera cannot see that part of the stripe
    names = r.truth.scene_body.names()
    ys = top.points_body[[names[s] == "wall" for s in top.surface_id], 1]
    assert np.abs(ys).min() > 0.3
    assert np.isnan(r.truth.v_at_columns(0, [959.5])[0])


# --------------------------------------------------------------------------- water, seeds, boards
def test_render_is_deterministic_for_a_seed() -> None:
    setup = named_scene("cluttered", *SMALL)
    a = setup.render(seed=7).image
    b = setup.render(seed=7).image
    c = setup.render(seed=8).image
    np.testing.assert_array_equal(a, b)
    assert np.abs(a.astype(int) - c.astype(int)).mean() > 0.5


def test_background_is_murky_not_flat() -> None:
    r = named_scene("wall_2.0", *SMALL).render(seed=1)
    b = r.image[:100, :, 0].astype(float)
    assert b.std() > 2.0
    assert r.image[:100].mean(axis=(0, 1))[0] > r.image[:100].mean(axis=(0, 1))[2]  # bluish, not red


def test_turbid_glow_and_attenuation() -> None:
    setup = named_scene("turbid", *SMALL)
    quiet = setup.water.with_(read_noise_dn=0.0, shot_noise_gain=0.0, snow=0, texture=0.0, vignetting=0.0)
    glow = setup.with_(water=quiet).render(seed=0)
    flat = setup.with_(water=quiet.with_(backscatter=0.0)).render(seed=0)
    v_top = glow.truth.v_at_columns(0, [240.0])[0]
    v_bot = glow.truth.v_at_columns(1, [240.0])[0]
    g, f = glow.image[:, 240, 1].astype(float), flat.image[:, 240, 1].astype(float)
    above = slice(0, int(v_top) - 8)
    between = slice(int(v_top) + 4, int(v_bot) - 4)
    assert (g[above] - f[above]).mean() > 3.0  # glow on the sheet's side of the stripe
    assert abs((g[between] - f[between]).mean()) < 1.0  # nothing between the sheets
    # brighter nearer the camera (toward the image border)
    assert g[5] - f[5] > g[int(v_top) - 12] - f[int(v_top) - 12]
    clear = named_scene("wall_1.5").with_(water=WaterModel.clean())
    assert glow.truth.lasers[0].peak_dn.max() < 0.5 * clear.render(seed=0).truth.lasers[0].peak_dn.max()


def test_physical_glow_ends_at_the_stripe_centre() -> None:
    from lrsensor.sim.fan import LaserModel
    from lrsensor.sim.lighting import _rays_of, _Sheet, laser_glow

    setup = named_scene("turbid", *SMALL)
    r = setup.with_(water=setup.water.with_(snow=0)).render(seed=0)
    cal, body = r.calibration, r.truth.scene_body
    h, w = cal.camera.height, cal.camera.width
    gain = 0.2 * setup.water.backscatter * LaserModel().peak_dn_at_1m / 190.0
    for laser, outward in ((0, -1), (1, +1)):  # the top sheet glows above its stripe, the bottom one below
        g = laser_glow(body, cal, laser, LaserModel(), setup.water, (h, w)).astype(float)
        sheet = _Sheet(body, cal, laser, LaserModel(), setup.water)
        for c in (60, 240, 400):
            v = r.truth.v_at_columns(laser, [float(c)])[0]
            rows = np.arange(round(v) - 2.4995, round(v) + 2.5, 0.001)  # 1000 samples per pixel, 5 pixels
            fine = sheet.radiance(*_rays_of(cal, np.stack([np.full(rows.shape, float(c)), rows], axis=1)))
            lit = rows[fine > 0]
            end = lit.max() if outward < 0 else lit.min()
            assert abs(end - v) < 0.002, (laser, c, end, v)  # the sheet ends where it meets the wall
            pixels = fine.reshape(5, 1000).mean(axis=1) * gain  # each pixel's glow, integrated finely
            np.testing.assert_allclose(g[round(v) - 2 : round(v) + 3, c], pixels, rtol=0.03, atol=0.02)
    with pytest.raises(SimulationError, match="glow_model"):
        laser_glow(body, cal, 0, LaserModel(), setup.water.with_(glow_model="x"), (h, w))


def test_checkerboard_is_found_at_the_true_corners() -> None:
    setup = checkerboard_wall_scene(0.9)
    r = setup.render(seed=2)
    gray = cv2.cvtColor(r.image, cv2.COLOR_BGR2GRAY)
    ok, corners = cv2.findChessboardCorners(gray, (9, 6))
    assert ok
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-4)
    corners = cv2.cornerSubPix(gray, corners, (5, 5), (-1, -1), crit).reshape(-1, 2)
    board = r.truth.boards()[0]
    truth_uv = r.calibration.project_body(board["corners_body"])
    if np.linalg.norm(corners[0] - truth_uv[0]) > np.linalg.norm(corners[-1] - truth_uv[0]):
        corners = corners[::-1]
    err = np.linalg.norm(corners - truth_uv, axis=1)
    assert np.median(err) < 0.1
    assert err.max() < 0.3
    # the wall plane in truth: n . p + d = 0 for every corner
    n, d = board["plane_normal_body"], board["plane_d_body"]
    assert np.abs(board["corners_body"] @ n + d).max() < 1e-12


def test_tilted_board_on_a_tilted_wall_is_found() -> None:
    a = math.radians(25)
    b = Checkerboard(cols=7, rows=5, square_m=0.04, offset_u_m=0.0, offset_v_m=-0.25, rotation_rad=0.4)
    setup = checkerboard_wall_scene(0.7, (math.cos(a), math.sin(a), 0.0), b, width=960, height=540)
    gray = cv2.cvtColor(setup.render(seed=0).image, cv2.COLOR_BGR2GRAY)
    ok, _ = cv2.findChessboardCorners(gray, (7, 5))
    assert ok


def test_every_named_scene_renders() -> None:
    for name in SCENES:
        r = named_scene(name, 240, 135).render(seed=0)
        assert r.image.shape == (135, 240, 3)
        assert r.image.dtype == np.uint8
        assert sum(len(lt) for lt in r.truth.lasers) > 0, name
    with pytest.raises(SimulationError, match="unknown scene"):
        named_scene("no_such_scene")


def test_laser_plane_perpendicular_to_x_is_refused() -> None:
    calib = named_scene("wall_1.0").calibration.with_lasers([LaserPlane.make("bad", (0, 0, 0), (1, 0, 0))])
    with pytest.raises(SimulationError, match="perpendicular"):
        render(Scene((wall_rectangle(1.0),)), calib)


def test_true_points_on_rays_scores_any_measurement() -> None:
    r = named_scene("occluder", *SMALL).with_(water=WaterModel.clean()).render(seed=0)
    C = r.calibration.camera_center_body
    truth_pts = r.truth.lasers[0].points_body[::50]
    np.testing.assert_allclose(r.truth.true_points_on_rays(truth_pts, C), truth_pts, atol=1e-9)
    # a measurement 1 % too far along its ray has a +1 % range error
    far = C + 1.01 * (truth_pts - C)
    back = r.truth.true_points_on_rays(far, C)
    rel = (np.linalg.norm(far - C, axis=1) - np.linalg.norm(back - C, axis=1)) / np.linalg.norm(back - C, axis=1)
    np.testing.assert_allclose(rel, 0.01, atol=1e-9)


def test_steep_stripe_rows_are_centred() -> None:
    # a laser rolled by 70 degrees draws a steep stripe: it is drawn per row, each row centred on the truth
    from lrsensor.frames import rot_x

    calib = named_scene("wall_1.0").calibration
    n = rot_x(math.radians(70)) @ np.array([0.0, 0.0, 1.0])
    calib = calib.with_lasers([LaserPlane.make("steep", (0, 0, -0.05), n)])
    r = render(Scene((wall_rectangle(1.0),)), calib, water=WaterModel.clean(), keep_layers=True)
    lt = r.truth.lasers[0]
    order = np.argsort(lt.uv[:, 1])
    layer = r.layers["laser"].astype(float)
    errs = []
    for row in range(100, 1000, 37):
        u_t = np.interp(row, lt.uv[order, 1], lt.uv[order, 0])
        lo = round(u_t) - 15
        w = layer[row, lo : lo + 31]
        errs.append((w * np.arange(lo, lo + 31)).sum() / w.sum() - u_t)
    assert np.abs(errs).max() < 1e-3


def test_halo_is_symmetric_and_camera_artifacts_render() -> None:
    from lrsensor.sim import LaserModel

    setup = named_scene("wall_1.0").with_(water=WaterModel.clean(), laser=LaserModel(halo_fraction=0.3))
    r = setup.render(seed=0, keep_layers=True)
    layer = r.layers["laser"].astype(float)
    v = r.truth.v_at_columns(0, [960.0])[0]
    lo = round(v) - 20
    w = layer[lo : lo + 41, 960]
    assert (w * np.arange(lo, lo + 41)).sum() / w.sum() == pytest.approx(v, abs=0.01)
    assert w[10] > 0.5  # the halo reaches 10 px out
    art = named_scene("camera_artifacts", *SMALL)
    a = art.render(seed=1).image
    b = art.with_(water=art.water.with_(jpeg_quality=0)).render(seed=1).image
    c = art.with_(water=art.water.with_(jpeg_quality=0, bayer=False)).render(seed=1).image
    assert a.shape == b.shape == c.shape == (270, 480, 3)
    assert a.dtype == np.uint8
    assert np.abs(a.astype(int) - b.astype(int)).max() > 0  # JPEG changed it
    assert np.abs(b.astype(int) - c.astype(int)).max() > 0  # so did the Bayer mosaic


# --------------------------------------------------------------------------- through a flat port
@pytest.mark.parametrize("tilt_deg", [0.0, 2.0])
def test_ported_truth_is_exact_through_the_port(tilt_deg: float) -> None:
    from lrsensor.port import pixel_rays_in_water

    setup = named_scene("paper_box", *SMALL).with_(water=WaterModel.clean()).with_port(acrylic_port(tilt_deg))
    assert setup.name == "paper_box+port"
    assert setup.calibration.port == acrylic_port(tilt_deg)
    r = setup.render(seed=0)
    cal = r.calibration
    assert cal.port is not None
    for lt in r.truth.lasers:
        assert len(lt) > 100
        # each truth pixel's ray in the water passes through its truth point
        o_cam, d_cam = pixel_rays_in_water(cal.camera, cal.port, lt.uv)
        p_cam = cal.body_to_cam(lt.points_body)
        along = np.einsum("ij,ij->i", p_cam - o_cam, d_cam)
        miss = np.linalg.norm(o_cam + along[:, None] * d_cam - p_cam, axis=1)
        assert miss.max() < 1e-8
        # and the pinhole projection of the in-air camera is far from it (the port is drawn)
        assert np.median(np.linalg.norm(cal.project_body(lt.points_body) - lt.uv, axis=1)) > 5.0


def test_ported_stripe_centroid_is_the_true_centre() -> None:
    setup = named_scene("wall_1.0").with_(water=WaterModel.clean()).with_port(acrylic_port(2.0))
    r = setup.render(seed=0, keep_layers=True)
    for lt in r.truth.lasers:
        cols = r.truth.visible_columns(lt.index, min_peak_dn=20.0)[4:-4]
        assert cols.size > 1500
        v = r.truth.v_at_columns(lt.index, cols)
        errf = np.abs(_column_centroids(r.layers["laser"].astype(float), v, cols, 12) - v)
        assert np.nanmax(errf) < 0.01


def test_ported_scene_is_processed_within_a_tenth_of_a_percent() -> None:
    from lrsensor import Sensor
    from lrsensor.sim.score import score_scan

    setup = named_scene("wall_1.0", 960, 540).with_port(acrylic_port(2.0))
    r = setup.render(seed=0)
    score = score_scan(r, Sensor(setup.calibration).process(r.image))
    assert score["median"] < 0.1, score
    assert score["p95"] < 0.5, score
    assert score["coverage"] > 95.0, score
    # the same image with the port ignored reads every range about a quarter short
    ignored = score_scan(r, Sensor(setup.with_port(None).calibration).process(r.image))
    assert ignored["median"] > 20.0, ignored


def test_ported_checkerboard_and_glow_render() -> None:
    setup = checkerboard_wall_scene(0.9).with_(water=WaterModel.turbid()).with_port(acrylic_port())
    r = setup.render(seed=1)
    gray = cv2.cvtColor(r.image, cv2.COLOR_BGR2GRAY)
    ok, corners = cv2.findChessboardCorners(gray, (9, 6))
    assert ok
    board = r.truth.boards()[0]
    truth_uv = r.calibration.project_water_body(board["corners_body"])
    corners = corners.reshape(-1, 2)
    if np.linalg.norm(corners[0] - truth_uv[0]) > np.linalg.norm(corners[-1] - truth_uv[0]):
        corners = corners[::-1]
    assert np.median(np.linalg.norm(corners - truth_uv, axis=1)) < 0.5
