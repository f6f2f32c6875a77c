"""``lrsensor.sim``: the ground-truth simulator (the project's test bench).

It renders what the camera of the paper's section 5.1 sees (1920x1080, fx = fy = 554.28 px, lasers at
z_b = -0.05 m (top) and +0.05 m (bottom), 120 degree fans), with exact ground truth.

Public API (stable; other parts of the project build on it)::

    from lrsensor.sim import named_scene, SCENES, wall_scene, render, WaterModel, LaserModel

    setup = named_scene("wall_1.0")                 # SimSetup; also width=, height= (intrinsics scaled)
    r = setup.render(seed=0)                        # Render
    r.image                                         # (H, W, 3) uint8 BGR
    r.calibration                                   # the TRUE Calibration (tilted lasers, distortion...)
    lt = r.truth.lasers[0]                          # LaserTruth of laser 0 ("top"), dense visible samples:
    lt.points_body, lt.uv, lt.surface_id            #   (N,3) m body frame, (N,2) distorted px, (N,) ids
    r.truth.v_at_columns(0, u)                      # true stripe centre row at columns u (NaN = unseen)
    r.truth.points_at_columns(0, u)                 # true body points (M,3) at columns u
    r.truth.visible_columns(0)                      # integer columns where laser 0 is visible
    r.truth.scene_body.distance_to_surface(points)  # error metric for triangulated points (body frame)
    r.truth.boards()                                # checkerboards: corners_body (rows*cols,3), plane
    r.truth.true_points_on_rays(points, C)          # true point on each measurement's camera ray (scoring)
    named_scene("wall_1.0").with_port(acrylic_port(2.0))  # the same scene through a flat port (exact)

    wall_scene(0.5, normal=(1, 0, 0), calibration=true_calib)   # wall n.p = 0.5 m (n: camera -> wall)
    checkerboard_wall_scene(1.0, board=Checkerboard(9, 6, 0.05, offset_u_m=.., offset_v_m=..))
    render(scene, calibration, pose=None, water=WaterModel.turbid(), laser_model=LaserModel(), seed=0)

Scenes: :mod:`lrsensor.sim.scene` has :class:`Plane`, :class:`Rectangle` (optionally carrying a
:class:`Checkerboard`: inner corners, square size, offset and rotation on the wall), :class:`Cylinder`,
:func:`box` (6 rectangles), ``stained(surfaces, amount)`` (albedo pattern), and :class:`Scene` (surfaces in
the body frame or in NED; ``Scene.raycast(origins, dirs) -> (t, surface_id, normal)``,
``Scene.distance_to_surface(points)``, ``Scene.in_body(pose)``, ``Scene.to_dicts()``).

Rendering: every laser fan (from the TRUE calibration's plane and point, 120 deg centred on body +x) is traced
densely into the scene (first hit, then the camera's view of it: occlusion and shadows), projected with
``Camera.project`` (OpenCV distortion; through the calibration's flat port exactly when it has one, and every
ray cast from the camera then starts on the port and is refracted, so ported renders have exact truth), and
drawn per column (per row where steeper than 45 deg) as a Gaussian profile at the exact sub-pixel centre
(sigma from blur and sheet thickness; peak from range, incidence, albedo and water attenuation; clipped at 255:
flat-topped close up), green with a little blue/red bleed.

Named scenes (:data:`SCENES`): ``paper_box``, ``wall_0.3`` .. ``wall_3.0``, ``tilted_wall``, ``corner``,
``pipe``, ``occluder``, ``turbid``, ``cluttered``, ``tilted_lasers``, ``distorted``, ``checkerboard_wall``,
``camera_artifacts``
(Bayer demosaicing, JPEG, stripe halo), ``tank`` (NED).

Water (:class:`WaterModel`, SI units, image levels in DN): ``clean()`` (no noise, flat background: exact
tests), ``default()``, ``turbid()``, ``cluttered()``; fields for attenuation, backscatter glow, haze, ambient
light, read/shot noise, distractor blobs, marine snow, speckle, Bayer mosaic and JPEG. Every random effect
is seeded.

Dives (:mod:`lrsensor.sim.dive`, NED tank of :func:`tank_scene`)::

    from lrsensor.sim.dive import tank_trajectories, simulate_imu, record_dive, trace_dive_clouds, frame_times_ns
    trajs = tank_trajectories(3)                    # Trajectory per robot k (independent of n): pose_at(t_ns)
    imu = simulate_imu(trajs[0], t_start_ns, t_end_ns, rate_hz=100, seed=0)   # ImuLog, write_csv / read_csv
    record_dive("out/rov1", robot="rov1", robot_index=0, duration_s=10, rate_hz=5, width=960, height=540)
    for cloud in trace_dive_clouds(trajs[0], frame_times_ns(10, 5, trajs[0].t0_ns)):
        cloud.t_ns, cloud.pose, cloud.points_body, cloud.laser       # TRUE points, no rendering

Performance (one thread, 1920x1080, wall scene): about 100 ms a render, 20-60 ms a truth-only trace
(``trace_truth``); ``benchmarks/bench_sim.py`` prints the table for every scene.

Conventions: body frame x forward, y starboard, z down; pixels (u, v) with the OpenCV origin; the laser ``k``
is ``calibration.lasers[k]`` (0 = top at z_b = -0.05 m, 1 = bottom at +0.05 m for the paper's sensor).
The fan of a laser is centred on body +x projected into its plane; fan angle theta > 0 toward body +y.
"""

from __future__ import annotations

from .render import (
    LaserModel,
    LaserTruth,
    Render,
    Truth,
    draw_stripe,
    render,
    stripe_splats,
    trace_fan,
    trace_truth,
)
from .scene import Checkerboard, Cylinder, Plane, Rectangle, Scene, Surface, box
from .scenes import (
    SCENES,
    WALL_DISTANCES_M,
    SimSetup,
    acrylic_port,
    checkerboard_wall_scene,
    distorted_calibration,
    named_scene,
    paper_box_surfaces,
    paper_calibration,
    scale_calibration,
    tank_scene,
    tilted_calibration,
    wall_rectangle,
    wall_scene,
)
from .water import WaterModel

__all__ = [
    "SCENES",
    "WALL_DISTANCES_M",
    "Checkerboard",
    "Cylinder",
    "LaserModel",
    "LaserTruth",
    "Plane",
    "Rectangle",
    "Render",
    "Scene",
    "SimSetup",
    "Surface",
    "Truth",
    "WaterModel",
    "acrylic_port",
    "box",
    "checkerboard_wall_scene",
    "distorted_calibration",
    "draw_stripe",
    "named_scene",
    "paper_box_surfaces",
    "paper_calibration",
    "render",
    "scale_calibration",
    "stripe_splats",
    "tank_scene",
    "tilted_calibration",
    "trace_fan",
    "trace_truth",
    "wall_rectangle",
    "wall_scene",
]
