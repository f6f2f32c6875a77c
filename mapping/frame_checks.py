"""The checks of one extracted plane across the frames of its window: how many frames see it, and how its stripes
bulge within single frames (pipes). Used by :func:`mapping.builder_window.extract_window` on the candidates of
:func:`mapping.planes.extract_planes`; NED metres (shifted by the window's origin).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from .planes import PlaneCandidate, VoxelGrid

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


def frame_sagitta(
    points: FloatArray, frame: IntArray, normal: FloatArray, min_points: int = 15, min_length_m: float = 0.05
) -> float:
    """Median over frames of the bulge of each frame's stripes across a plane (metres; 0 when unknown).

    Within one frame there is no pose noise between the points (they share the frame's pose), so the bend of a
    stripe is the surface's own: per frame, the residuals ``r`` to the plane are fitted with
    ``r = a + b u + c u^2 + e v`` (``u`` along the stripes, i.e. the horizontal in-plane axis, ``v`` across them),
    and the bulge of that frame is ``|c| (L / 2)^2`` over its stripe length ``L``. A pipe's arcs bulge by
    ``L^2 / (8 r)``; a wall's stripes do not bulge, whatever the frame-to-frame pose noise.

    Args:
        points: (K, 3) points of one plane, metres.
        frame: (K,) frame (cloud) index of each point.
        normal: (3,) unit normal of the plane.
        min_points, min_length_m: frames with fewer points or shorter stripes are ignored.
    """
    if points.shape[0] < min_points:
        return 0.0
    c = points.mean(axis=0)
    x = points - c
    down = np.array([0.0, 0.0, 1.0])
    u_axis = np.cross(down, normal)
    if np.linalg.norm(u_axis) < 0.2:
        return 0.0  # a near-horizontal plane: the stripes do not run along a fixed in-plane axis
    u_axis /= np.linalg.norm(u_axis)
    v_axis = np.cross(normal, u_axis)
    u, v, r = x @ u_axis, x @ v_axis, x @ normal
    _, g = np.unique(frame, return_inverse=True)
    g = g.reshape(-1)
    ng = int(g.max()) + 1
    cols = (np.ones_like(u), u, u * u, v)
    gram = np.empty((ng, 4, 4))
    rhs = np.empty((ng, 4))
    for i in range(4):
        rhs[:, i] = np.bincount(g, weights=cols[i] * r, minlength=ng)
        for j in range(i, 4):
            gram[:, i, j] = gram[:, j, i] = np.bincount(g, weights=cols[i] * cols[j], minlength=ng)
    umin = np.full(ng, np.inf)
    umax = np.full(ng, -np.inf)
    np.minimum.at(umin, g, u)
    np.maximum.at(umax, g, u)
    length = umax - umin
    ok = (gram[:, 0, 0] >= min_points) & (length >= min_length_m)
    if not np.any(ok):
        return 0.0
    reg = 1e-9 * np.eye(4)[None, :, :]
    coef = np.linalg.solve(gram[ok] + reg, rhs[ok][:, :, None])[:, :, 0]
    bulge = np.abs(coef[:, 2]) * (length[ok] / 2.0) ** 2
    return float(np.median(bulge))


def frame_support(
    points: FloatArray,
    grid: VoxelGrid,
    cand: PlaneCandidate,
    frame: IntArray,
    distance_m: float,
    min_points: int,
) -> int:
    """How many frames of the window see ``cand``: frames with at least ``min_points`` full-resolution points
    within ``distance_m`` of its plane in the voxels of its inliers.

    Every frame of a window (committed context included) counts. One frame alone is two laser stripes a few
    centimetres apart that share one pose and one image: an error of that single image (a stripe triangulated
    with the wrong laser, a reflection, a mis-detected stripe near a corner where the range is longest) moves
    both stripes together and they still fit a plane perfectly, only a plane that is not there. Real surfaces
    are seen by consecutive frames of the window; a candidate supported by a single frame is dropped.

    Args:
        points: (N, 3) full-resolution window points (same frame as the extraction), metres.
        grid: the window's voxel grid (``grid.inverse`` maps points to voxels).
        cand: the candidate plane.
        frame: (N,) frame (cloud) index of every point.
        distance_m: inlier distance to the candidate's plane.
        min_points: points a frame needs to count.
    """
    in_vox = np.zeros(grid.keys.shape[0], dtype=bool)
    in_vox[cand.voxel_index] = True
    sel = in_vox[grid.inverse]
    sel[sel] = np.abs(points[sel] @ cand.normal + cand.d) <= distance_m
    if not np.any(sel):
        return 0
    _, counts = np.unique(frame[sel], return_counts=True)
    return int(np.count_nonzero(counts >= min_points))
