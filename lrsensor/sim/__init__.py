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

    wall_scene(0.5, normal=(1, 0, 0), calibration=true_calib)   # wall n.p = 0.5 m (n: camera -> wall)
    checkerboard_wall_scene(1.0, board=Checkerboard(9, 6, 0.05, offset_u_m=.., offset_v_m=..))
    render(scene, calibration, pose=None, water=WaterModel.turbid(), laser_model=LaserModel(), seed=0)

Scenes: :mod:`lrsensor.sim.scene` has :class:`Plane`, :class:`Rectangle` (optionally carrying a
:class:`Checkerboard`), :class:`Cylinder`, :func:`box` (6 rectangles), and :class:`Scene` (surfaces in the
body frame or in NED; ``Scene.raycast(origins, dirs) -> (t, surface_id, normal)``,
``Scene.distance_to_surface(points)``, ``Scene.in_body(pose)``).

Named scenes (:data:`SCENES`): ``paper_box``, ``wall_0.3`` .. ``wall_3.0``, ``tilted_wall``, ``corner``,
``pipe``, ``occluder``, ``turbid``, ``cluttered``, ``tilted_lasers``, ``distorted``, ``checkerboard_wall``,
``tank`` (NED).

Water (:class:`WaterModel`, SI units, image levels in DN): ``clean()`` (no noise, flat background: exact
tests), ``default()``, ``turbid()``, ``cluttered()``; fields for attenuation, backscatter glow, haze, ambient
light, read/shot noise, distractor blobs, marine snow and speckle. Every random effect is seeded.

Dives (:mod:`lrsensor.sim.dive`): ``Trajectory``, ``tank_trajectories(n, ...)``, ``simulate_imu``,
``record_dive(out_dir, ...)`` and ``trace_dive_clouds(...)``.
"""

from __future__ import annotations

from .render import LaserModel, LaserTruth, Render, Truth, draw_stripe, render, trace_fan, trace_truth
from .scene import Checkerboard, Cylinder, Plane, Rectangle, Scene, Surface, box
from .scenes import (
    SCENES,
    WALL_DISTANCES_M,
    SimSetup,
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
    "box",
    "checkerboard_wall_scene",
    "distorted_calibration",
    "draw_stripe",
    "named_scene",
    "paper_box_surfaces",
    "paper_calibration",
    "render",
    "scale_calibration",
    "tank_scene",
    "tilted_calibration",
    "trace_fan",
    "trace_truth",
    "wall_rectangle",
    "wall_scene",
]
