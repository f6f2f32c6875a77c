"""Named scenes of the test bench: ``named_scene(name) -> SimSetup``; the list is :data:`SCENES`.

Body-frame scenes put the camera at the body origin looking along +x (the paper's default mounting); the
lasers are the planes z_b = -0.05 (top) and +0.05 (bottom) unless the scene changes them (``tilted_lasers``).
The ``tank`` is given in NED and rendered from a vehicle pose.

Any scene can be seen through a flat port: ``named_scene("wall_1.0").with_port(acrylic_port(2.0))`` (the
camera of the calibration is then the in-air camera behind the port; :func:`acrylic_port` is the issue's acrylic
window). Ported scenes are not in :data:`SCENES`, whose renders are the references of the extractor's checks.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..calibration import Calibration, LaserPlane
from ..camera import Camera
from ..errors import SimulationError
from ..frames import Pose, rot_x, rot_y
from ..port import FlatPort
from .render import LaserModel, Render, render
from .scene import Checkerboard, Cylinder, Rectangle, Scene, Surface, box, stained
from .water import WaterModel

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class SimSetup:
    """Everything needed to render a scene: geometry, the TRUE calibration, pose, water and laser models.

    Attributes:
        name: scene name.
        scene: the surfaces (body frame, or NED with ``pose``).
        calibration: the true calibration the image is rendered with.
        pose: vehicle pose in NED (NED scenes only).
        water, laser: water/sensor and laser models.
        description: one line for humans.
        wall_distance_m, wall_normal: for single-wall scenes, the wall plane ``n . p = distance`` in the body
            frame (``n`` unit, pointing from the camera to the wall).
    """

    name: str
    scene: Scene
    calibration: Calibration
    pose: Pose | None = None
    water: WaterModel = field(default_factory=WaterModel.default)
    laser: LaserModel = field(default_factory=LaserModel)
    description: str = ""
    wall_distance_m: float | None = None
    wall_normal: tuple[float, float, float] | None = None

    def render(self, seed: int | np.random.Generator | None = 0, *, keep_layers: bool = False) -> Render:
        """Render this setup (see :func:`lrsensor.sim.render`)."""
        return render(
            self.scene,
            self.calibration,
            pose=self.pose,
            water=self.water,
            laser_model=self.laser,
            seed=seed,
            keep_layers=keep_layers,
        )

    def scaled(self, width: int, height: int) -> SimSetup:
        """The same setup at another image size (intrinsics scaled, same field of view)."""
        return replace(self, calibration=scale_calibration(self.calibration, width, height))

    def with_(self, **changes: Any) -> SimSetup:
        """A copy with some fields changed (``water=...``, ``calibration=...``, ``pose=...``)."""
        return replace(self, **changes)

    def with_port(self, port: FlatPort | None) -> SimSetup:
        """The same scene seen through a flat port (None: none): the calibration's camera becomes the in-air camera
        behind ``port``, so the render and its truth are exact through the port (named ``<name>+port``)."""
        name = self.name.removesuffix("+port") + ("+port" if port is not None else "")
        return replace(self, name=name, calibration=replace(self.calibration, port=port))


def scale_calibration(calib: Calibration, width: int, height: int) -> Calibration:
    """``calib`` with its camera resampled to ``width x height`` (pixel-centre convention kept)."""
    cam = calib.camera
    sx, sy = width / cam.width, height / cam.height
    new = Camera(
        width,
        height,
        cam.fx * sx,
        cam.fy * sy,
        (cam.cx + 0.5) * sx - 0.5,
        (cam.cy + 0.5) * sy - 0.5,
        cam.distortion,
    )
    return replace(calib, camera=new)


def acrylic_port(tilt_deg: float = 0.0) -> FlatPort:
    """The flat port of issue 26: acrylic (n 1.49) 8 mm thick, its inner surface 20 mm in front of the lens, sea
    water (n 1.34); its normal tilted ``tilt_deg`` degrees from the optical axis, about the camera's x axis."""
    t = math.radians(tilt_deg)
    return FlatPort((0.0, math.sin(t), math.cos(t)), 0.02, 0.008, 1.0, 1.49, 1.34)


def paper_calibration(width: int = 1920, height: int = 1080, baseline_m: float = 0.1) -> Calibration:
    """The nominal calibration of the paper's simulation (section 5.1)."""
    return Calibration.paper(baseline_m, width, height)


def tilted_calibration(
    base: Calibration | None = None,
    tilts_deg: tuple[tuple[float, float], ...] = ((1.5, 0.6), (-1.2, -0.9)),
    offsets_m: tuple[tuple[float, float, float], ...] = ((0.002, -0.001, 0.0), (-0.001, 0.002, 0.0)),
) -> Calibration:
    """True lasers tilted against nominal: per laser (about body y, about body x) in degrees, plus a point offset.

    A tilt about body y pitches the sheet (the stripe moves up/down with range); about body x it rolls the
    sheet (the stripe slants across the image).
    """
    base = base or paper_calibration()
    lasers = []
    for i, lp in enumerate(base.lasers):
        ty, tx = tilts_deg[i % len(tilts_deg)]
        R = rot_y(math.radians(ty)) @ rot_x(math.radians(tx))
        n = R @ lp.normal_body
        off = np.asarray(offsets_m[i % len(offsets_m)])
        lasers.append(LaserPlane.make(lp.name, (lp.point_body + off).tolist(), n.tolist()))
    return base.with_lasers(lasers, {"simulated": "tilted lasers (true calibration)"})


def distorted_calibration(
    base: Calibration | None = None,
    distortion: tuple[float, float, float, float, float] = (-0.12, 0.035, 0.0006, -0.0004, -0.004),
) -> Calibration:
    """``base`` with Brown-Conrady lens distortion ``[k1, k2, p1, p2, k3]`` (mild barrel by default)."""
    base = base or paper_calibration()
    return replace(base, camera=replace(base.camera, distortion=distortion))


def _wall_axes(normal: ArrayLike) -> tuple[FloatArray, FloatArray, FloatArray]:
    n = np.asarray(normal, dtype=float)
    n = n / np.linalg.norm(n)
    z = np.array([0.0, 0.0, 1.0])
    v = z - (z @ n) * n
    if np.linalg.norm(v) < 1e-6:
        v = np.array([1.0, 0.0, 0.0]) - n[0] * n
    v /= np.linalg.norm(v)
    u = np.cross(v, n)
    return n, u, v


def wall_rectangle(
    distance_m: float,
    normal: ArrayLike = (1.0, 0.0, 0.0),
    size_m: float = 40.0,
    board: Checkerboard | None = None,
    name: str = "wall",
    albedo: float = 0.6,
) -> Rectangle:
    """A (large) wall: the plane ``n . p = distance_m`` (body frame, ``n`` from the camera to the wall).

    Its u axis is horizontal (body +y for a perpendicular wall), its v axis points down (body +z).
    """
    n, u, v = _wall_axes(normal)
    if not distance_m > 0:
        msg = f"wall distance must be positive (in front of the camera), got {distance_m} m"
        raise SimulationError(msg)
    return Rectangle.make(n * distance_m, u, v, size_m, size_m, name, albedo, board)


def wall_scene(
    distance_m: float,
    normal: ArrayLike = (1.0, 0.0, 0.0),
    *,
    calibration: Calibration | None = None,
    water: WaterModel | None = None,
    board: Checkerboard | None = None,
    width: int = 1920,
    height: int = 1080,
    name: str | None = None,
) -> SimSetup:
    """One flat wall ``n . p = distance_m`` in front of the camera (perpendicular to body x by default)."""
    calib = calibration or paper_calibration(width, height)
    if (calib.camera.width, calib.camera.height) != (width, height) and calibration is None:
        calib = scale_calibration(calib, width, height)
    n = np.asarray(normal, dtype=float)
    n = n / np.linalg.norm(n)
    wall = wall_rectangle(distance_m, n, board=board)
    return SimSetup(
        name=name or f"wall_{distance_m:g}",
        scene=Scene((wall,)),
        calibration=calib,
        water=water if water is not None else WaterModel.default(),
        description=f"flat wall at {distance_m:g} m, normal {np.round(n, 4).tolist()}",
        wall_distance_m=float(distance_m),
        wall_normal=(float(n[0]), float(n[1]), float(n[2])),
    )


def checkerboard_wall_scene(
    distance_m: float = 1.0,
    normal: ArrayLike = (1.0, 0.0, 0.0),
    board: Checkerboard | None = None,
    *,
    calibration: Calibration | None = None,
    water: WaterModel | None = None,
    width: int = 1920,
    height: int = 1080,
) -> SimSetup:
    """A wall carrying a checkerboard (9x6 inner corners, 5 cm squares, above the top stripe by default)."""
    board = board or Checkerboard(cols=9, rows=6, square_m=0.05, offset_u_m=0.1, offset_v_m=-0.36)
    water = water if water is not None else WaterModel.default().with_(ambient_dn=120.0)
    s = wall_scene(distance_m, normal, calibration=calibration, water=water, board=board, width=width, height=height)
    return replace(s, name="checkerboard_wall", description=f"wall at {distance_m:g} m with a checkerboard")


def paper_box_surfaces(front_m: float = 3.0, half_width_m: float = 1.0, back_m: float = -1.0) -> list[Rectangle]:
    """The paper's 2 m x 2 m box (section 5.1): front wall at ``front_m``, side walls, floor and ceiling."""
    length = front_m - back_m
    xc = (front_m + back_m) / 2.0
    hw = half_width_m
    return [
        Rectangle.make((front_m, 0, 0), (0, 1, 0), (0, 0, 1), 2 * hw, 2 * hw, "front"),
        Rectangle.make((xc, -hw, 0), (1, 0, 0), (0, 0, 1), length, 2 * hw, "left"),
        Rectangle.make((xc, hw, 0), (1, 0, 0), (0, 0, 1), length, 2 * hw, "right"),
        Rectangle.make((xc, 0, hw), (1, 0, 0), (0, 1, 0), length, 2 * hw, "floor"),
        Rectangle.make((xc, 0, -hw), (1, 0, 0), (0, 1, 0), length, 2 * hw, "ceiling"),
    ]


# --------------------------------------------------------------------------- the tank (NED)
#: The simulated tank: north 0..12 m, east 0..8 m, floor at 4 m depth.
TANK_SIZE_M = (12.0, 8.0, 4.0)
#: Square pillars: (north, east) centre and side, metres.
TANK_PILLARS = (((4.0, 3.0), 0.6), ((8.0, 5.5), 0.6))
#: A vertical pipe: (north, east) centre, radius, metres.
TANK_PIPE = ((6.0, 4.3), 0.2)


def tank_scene() -> Scene:
    """The simulated tank in NED: 4 walls, a floor, 2 square pillars and a vertical pipe.

    North 0..12 m, east 0..8 m, floor at 4 m depth; pillars 0.6 m square at (4, 3) and (8, 5.5), the pipe
    (r = 0.2 m) at (6, 4.3). Every planar face's normal (``axis_u x axis_v``) points into the water, so its
    plane ``normal . p + d = 0`` (``Scene.to_dicts``) is the truth a map of the tank is scored against.
    """
    ln, le, depth = TANK_SIZE_M
    dz = depth / 2.0
    # every face's normal (axis_u x axis_v) points into the water
    surfaces: list[Surface] = [
        Rectangle.make((ln, le / 2, dz), (0, -1, 0), (0, 0, 1), le, depth, "wall_north"),
        Rectangle.make((0.0, le / 2, dz), (0, 1, 0), (0, 0, 1), le, depth, "wall_south"),
        Rectangle.make((ln / 2, le, dz), (1, 0, 0), (0, 0, 1), ln, depth, "wall_east"),
        Rectangle.make((ln / 2, 0.0, dz), (-1, 0, 0), (0, 0, 1), ln, depth, "wall_west"),
        Rectangle.make((ln / 2, le / 2, depth), (1, 0, 0), (0, -1, 0), ln, le, "floor"),
    ]
    for k, ((n, e), side) in enumerate(TANK_PILLARS):
        # floor-to-surface pillars: their top and bottom faces would coincide with the surface and the floor
        faces = box((n, e, dz), (side, side, depth), name=f"pillar{k + 1}")
        surfaces.extend(f for f in faces if not f.name.endswith("z"))
    surfaces = stained(surfaces, 0.25)
    (pn, pe), pr = TANK_PIPE
    surfaces.append(Cylinder.make((pn, pe, dz), (0, 0, 1), pr, depth, "pipe"))
    return Scene(tuple(surfaces), "ned")


# --------------------------------------------------------------------------- named scenes
def _paper_box(w: int, h: int) -> SimSetup:
    return SimSetup(
        "paper_box",
        Scene(tuple(paper_box_surfaces())),
        paper_calibration(w, h),
        description="the paper's 2 m x 2 m box, front wall at 3 m, camera centred (section 5.1)",
    )


def _tilted_wall(w: int, h: int) -> SimSetup:
    a = math.radians(35.0)
    s = wall_scene(1.0, (math.cos(a), math.sin(a), 0.0), width=w, height=h)
    return replace(s, name="tilted_wall", description="wall at 1 m along its normal, turned 35 deg about body z")


def _corner(w: int, h: int) -> SimSetup:
    corner = np.array([1.6, 0.25, 0.0])
    length = 4.0
    surfaces = []
    for name, d in (("corner_left", (-1.0, -1.0, 0.0)), ("corner_right", (-1.0, 1.0, 0.0))):
        dv = np.asarray(d) / np.linalg.norm(d)
        surfaces.append(Rectangle.make(corner + dv * length / 2, dv, (0, 0, 1), length, 4.0, name))
    return SimSetup(
        "corner",
        Scene(tuple(surfaces)),
        paper_calibration(w, h),
        description="two walls meeting in a concave vertical edge 1.6 m ahead",
    )


def _pipe(w: int, h: int) -> SimSetup:
    surfaces: list[Surface] = [
        wall_rectangle(2.0, name="wall"),
        Cylinder.make((1.2, 0.15, 0.0), (0, 0, 1), 0.15, 4.0, "pipe", albedo=0.5),
    ]
    return SimSetup(
        "pipe",
        Scene(tuple(surfaces)),
        paper_calibration(w, h),
        description="a vertical pipe (r = 0.15 m) 1.2 m ahead of a wall at 2 m",
    )


def _turbid(w: int, h: int) -> SimSetup:
    s = wall_scene(1.5, water=WaterModel.turbid(), width=w, height=h)
    return replace(s, name="turbid", description="wall at 1.5 m in turbid water (attenuation, glow, haze)")


def _cluttered(w: int, h: int) -> SimSetup:
    surfaces = stained([wall_rectangle(1.3, name="wall"), *box((0.9, -0.6, 0.3), (0.3, 0.3, 0.8), name="crate")], 0.35)
    return SimSetup(
        "cluttered",
        Scene(tuple(surfaces)),
        paper_calibration(w, h),
        water=WaterModel.cluttered(),
        description="stained wall at 1.3 m with a crate, green distractor blobs, marine snow and speckle",
    )


def _tilted_lasers(w: int, h: int) -> SimSetup:
    calib = tilted_calibration(paper_calibration(w, h))
    s = wall_scene(1.0, calibration=calib, width=w, height=h)
    return replace(s, name="tilted_lasers", description="wall at 1 m; true lasers tilted 1-2 deg against nominal")


def _distorted(w: int, h: int) -> SimSetup:
    s = _paper_box(w, h)
    return replace(
        s,
        name="distorted",
        calibration=distorted_calibration(s.calibration),
        description="the paper's box seen through a lens with barrel distortion",
    )


def _checkerboard(w: int, h: int) -> SimSetup:
    return checkerboard_wall_scene(1.0, width=w, height=h)


def _occluder(w: int, h: int) -> SimSetup:
    surfaces: list[Surface] = [wall_rectangle(2.0, name="wall"), *box((1.0, 0.0, 0.0), (0.3, 0.4, 1.0), name="box")]
    return SimSetup(
        "occluder",
        Scene(tuple(surfaces)),
        paper_calibration(w, h),
        description="a 0.4 m wide box 1 m ahead of a wall at 2 m (occlusion and camera shadow)",
    )


def _camera_artifacts(w: int, h: int) -> SimSetup:
    s = wall_scene(1.2, water=WaterModel.default().with_(bayer=True, jpeg_quality=90), width=w, height=h)
    return replace(
        s,
        name="camera_artifacts",
        laser=LaserModel(halo_fraction=0.15),
        description="wall at 1.2 m seen by a real colour camera: Bayer demosaicing, JPEG (q 90), stripe halo",
    )


def _tank(w: int, h: int) -> SimSetup:
    return SimSetup(
        "tank",
        tank_scene(),
        paper_calibration(w, h),
        pose=Pose(2.0, 2.0, 1.5, 0.0, 0.0, math.radians(10.0)),
        description="a 12 m x 8 m tank in NED with 2 square pillars and a pipe, seen from a vehicle pose",
    )


def _wall_factory(d: float) -> Callable[[int, int], SimSetup]:
    def make(w: int, h: int) -> SimSetup:
        return wall_scene(d, width=w, height=h, name=f"wall_{d:.1f}")

    return make


#: Wall distances of the ``wall_<d>`` scenes, metres.
WALL_DISTANCES_M = (0.3, 0.4, 0.5, 0.6, 0.8, 1.0, 1.5, 2.0, 2.5, 3.0)

_FACTORIES: dict[str, Callable[[int, int], SimSetup]] = {
    "paper_box": _paper_box,
    **{f"wall_{d:.1f}": _wall_factory(d) for d in WALL_DISTANCES_M},
    "tilted_wall": _tilted_wall,
    "corner": _corner,
    "pipe": _pipe,
    "occluder": _occluder,
    "turbid": _turbid,
    "cluttered": _cluttered,
    "tilted_lasers": _tilted_lasers,
    "distorted": _distorted,
    "checkerboard_wall": _checkerboard,
    "camera_artifacts": _camera_artifacts,
    "tank": _tank,
}

#: Names of the named scenes, in a stable order.
SCENES: tuple[str, ...] = tuple(_FACTORIES)


def named_scene(name: str, width: int = 1920, height: int = 1080) -> SimSetup:
    """The named scene ``name`` (one of :data:`SCENES`) at ``width x height`` (intrinsics scaled)."""
    try:
        factory = _FACTORIES[name]
    except KeyError:
        msg = f"unknown scene {name!r}; choose one of {', '.join(SCENES)}"
        raise SimulationError(msg) from None
    setup = factory(width, height)
    if (setup.calibration.camera.width, setup.calibration.camera.height) != (width, height):
        setup = setup.scaled(width, height)
    return setup
