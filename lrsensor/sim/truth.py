"""Ground truth of a render, and the render's result.

What: :class:`LaserTruth` keeps, per laser, the dense visible samples of its stripe along the fan (from
:func:`lrsensor.sim.fan.trace_fan`); :class:`Truth` gathers the lasers with the scene and the pose and answers
the questions the tests and benchmarks ask (the true stripe row and 3-D point at any image column, the
visible columns, the true point on a measured point's camera ray, checkerboard corners, JSON export);
:class:`Render` is what :func:`lrsensor.sim.render` returns: the image, the TRUE calibration and the truth.

Frames and units: points are in the body frame (x forward, y starboard, z down), metres; ``uv`` are distorted
pixel coordinates (as ``cv2.projectPoints`` gives, OpenCV origin: the centre of the top-left pixel is (0, 0));
fan angles in radians; intensities in DN of the green channel before clipping. :meth:`Truth.points_ned` maps
the points to NED with the render's pose. Queries at M columns return (M,) or (M, 3) arrays with NaN where
the laser is not seen.

Why dense samples rather than one value per column: the samples are at most ``LaserModel.max_gap_px`` apart in
the image, so linear interpolation gives the truth at any (sub-pixel) column, for any image size and on both
sides of an occlusion edge; where two stripe pieces cover a column (a step seen from the side) the brighter
one is given.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..calibration import Calibration
from ..errors import SimulationError
from ..frames import Pose, body_to_ned
from .scene import Rectangle, Scene

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
F32 = NDArray[np.float32]


@dataclass(frozen=True)
class LaserTruth:
    """Ground truth of one laser's stripe: the dense visible samples, ordered along the fan.

    The samples are those the camera sees inside the image, plus one sample beyond the image border at
    each end of a stripe piece (so that interpolation covers every column up to the border).

    Attributes:
        index, name: the laser's index in the calibration and its name.
        theta_rad: (N,) fan angle of each sample (positive toward body +y for an untilted laser).
        points_body: (N, 3) true hit points in the body frame, metres.
        uv: (N, 2) their exact projected pixels (distorted, as ``cv2.projectPoints`` gives).
        surface_id: (N,) id of the surface hit (index into the scene's surfaces).
        segment: (N,) index of the continuous stripe piece each sample belongs to (pieces end at occlusion
            edges, shadows, surface changes and the image border).
        peak_dn: (N,) peak of the stripe profile (green channel, before clipping), DN, as the camera sees it
            (after the water's forward scatter).
        sigma_px: (N,) Gaussian sigma of the stripe profile across the stripe, pixels (after forward scatter).
        range_m: (N,) distance from the camera centre to the point, metres.
    """

    index: int
    name: str
    theta_rad: FloatArray
    points_body: FloatArray
    uv: FloatArray
    surface_id: IntArray
    segment: IntArray
    peak_dn: FloatArray
    sigma_px: FloatArray
    range_m: FloatArray

    def __len__(self) -> int:
        return int(self.points_body.shape[0])

    def _pieces(self) -> list[NDArray[np.intp]]:
        """Index arrays of the u-monotonic pieces of each segment."""
        out: list[NDArray[np.intp]] = []
        for s in np.unique(self.segment):
            idx = np.flatnonzero(self.segment == s)
            if idx.size < 2:
                continue
            du = np.diff(self.uv[idx, 0])
            sign = np.sign(du)
            breaks = np.flatnonzero((sign[1:] != sign[:-1]) | (sign[1:] == 0)) + 1
            start = 0
            for b in [*breaks.tolist(), du.size]:
                piece = idx[start : b + 1]
                if piece.size >= 2 and piece.size > 1 and self.uv[piece[-1], 0] != self.uv[piece[0], 0]:
                    out.append(piece if self.uv[piece[-1], 0] > self.uv[piece[0], 0] else piece[::-1])
                start = b
        return out

    def at_columns(self, u: Sequence[float] | FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Truth at image columns ``u`` (M,): stripe centre ``v`` (M,), body points (M, 3), peak DN (M,).

        Interpolated linearly along the dense samples (spacing <= ``max_gap_px``); NaN where the laser is not
        visible in that column. Where two stripe pieces cover a column the brighter one is given.
        """
        v, pts, peak, _ = self._interp_columns(u)
        return v, pts, peak

    def theta_at_columns(self, u: Sequence[float] | FloatArray) -> FloatArray:
        """Fan angle (M,) of the laser ray seen at columns ``u``, radians; NaN where not visible."""
        return self._interp_columns(u)[3]

    def _interp_columns(self, u: Sequence[float] | FloatArray) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        uq = np.asarray(u, dtype=float).reshape(-1)
        v = np.full(uq.shape, np.nan)
        th = np.full(uq.shape, np.nan)
        pts = np.full((uq.size, 3), np.nan)
        peak = np.full(uq.shape, -np.inf)
        for piece in self._pieces():
            pu = self.uv[piece, 0]
            inside = (uq >= pu[0]) & (uq <= pu[-1])
            if not np.any(inside):
                continue
            q = uq[inside]
            pk = np.interp(q, pu, self.peak_dn[piece])
            better = pk > peak[inside]
            sel = np.flatnonzero(inside)[better]
            q = q[better]
            v[sel] = np.interp(q, pu, self.uv[piece, 1])
            th[sel] = np.interp(q, pu, self.theta_rad[piece])
            for k in range(3):
                pts[sel, k] = np.interp(q, pu, self.points_body[piece, k])
            peak[sel] = pk[better]
        peak[~np.isfinite(v)] = np.nan
        return v, pts, peak, th


@dataclass(frozen=True)
class Truth:
    """Ground truth of a render.

    Attributes:
        lasers: per-laser stripe truth (index = laser index of the calibration).
        scene: the scene as given (body or NED frame).
        scene_body: the scene in the body frame at the render's pose (surface ids are the same).
        pose: the vehicle pose in NED (None for body-frame scenes).
        width, height: image size, pixels.
    """

    lasers: tuple[LaserTruth, ...]
    scene: Scene
    scene_body: Scene
    pose: Pose | None
    width: int
    height: int

    def v_at_columns(self, laser: int, u: Sequence[float] | FloatArray | None = None) -> FloatArray:
        """True stripe centre row ``v`` (M,) of ``laser`` at columns ``u`` (default: every column); NaN = unseen."""
        cols = np.arange(self.width, dtype=float) if u is None else np.asarray(u, dtype=float)
        return self.lasers[laser].at_columns(cols)[0]

    def points_at_columns(self, laser: int, u: Sequence[float] | FloatArray | None = None) -> FloatArray:
        """True body-frame points (M, 3) of ``laser`` seen at columns ``u`` (default: every column); NaN = unseen."""
        cols = np.arange(self.width, dtype=float) if u is None else np.asarray(u, dtype=float)
        return self.lasers[laser].at_columns(cols)[1]

    def visible_columns(self, laser: int, min_peak_dn: float = 0.0) -> IntArray:
        """Integer image columns where ``laser``'s stripe is visible (peak above ``min_peak_dn``), sorted."""
        cols = np.arange(self.width, dtype=float)
        v, _, peak = self.lasers[laser].at_columns(cols)
        ok = np.isfinite(v) & (np.nan_to_num(peak, nan=-1.0) > min_peak_dn)
        return np.flatnonzero(ok).astype(np.int64)

    def true_points_on_rays(self, points_body: FloatArray, camera_center_body: FloatArray) -> FloatArray:
        """The first scene point (N, 3) on the camera ray through each measured point (N, 3), body frame.

        With it the relative range error of any measurement is ``(|p - C| - |p_true - C|) / |p_true - C|``,
        whatever column it came from. NaN rows where the ray hits nothing.
        """
        p = np.asarray(points_body, dtype=float).reshape(-1, 3)
        C = np.asarray(camera_center_body, dtype=float).reshape(3)
        d = p - C
        t, _, _ = self.scene_body.raycast(C, d)
        out = C + t[:, None] * d
        out[~np.isfinite(t)] = np.nan
        return out

    def all_points(self) -> tuple[FloatArray, IntArray]:
        """All visible dense samples: body points (N, 3) and their laser index (N,)."""
        if not self.lasers:
            return np.zeros((0, 3)), np.zeros(0, dtype=np.int64)
        pts = np.concatenate([lt.points_body for lt in self.lasers])
        idx = np.concatenate([np.full(len(lt), lt.index, dtype=np.int64) for lt in self.lasers])
        return pts, idx

    def boards(self) -> list[dict[str, Any]]:
        """Checkerboards of the scene: body-frame inner corners (rows*cols, 3), the wall plane, board size."""
        out = []
        for sid, s in enumerate(self.scene_body.surfaces):
            if isinstance(s, Rectangle) and s.board is not None:
                n = s.normal
                out.append(
                    {
                        "surface_id": sid,
                        "cols": s.board.cols,
                        "rows": s.board.rows,
                        "square_m": s.board.square_m,
                        "corners_body": s.board_corners(),
                        "plane_normal_body": n,
                        "plane_d_body": float(-n @ np.asarray(s.center)),
                    }
                )
        return out

    def to_dict(self, max_points: int | None = None) -> dict[str, Any]:
        """JSON-ready truth: surfaces (body frame, and NED when a pose is set), boards, per-laser points."""
        lasers = []
        for lt in self.lasers:
            step = 1 if max_points is None or len(lt) <= max_points else math.ceil(len(lt) / max_points)
            cols = self.visible_columns(lt.index)
            lasers.append(
                {
                    "index": lt.index,
                    "name": lt.name,
                    "n_samples": len(lt),
                    "visible_columns": int(cols.size),
                    "points_body": np.round(lt.points_body[::step], 7).tolist(),
                    "uv": np.round(lt.uv[::step], 5).tolist(),
                    "surface_id": lt.surface_id[::step].tolist(),
                }
            )
        out: dict[str, Any] = {
            "width": self.width,
            "height": self.height,
            "frame_of_points": "body",
            "surfaces_body": self.scene_body.to_dicts(),
            "boards": [
                {
                    "surface_id": b["surface_id"],
                    "cols": b["cols"],
                    "rows": b["rows"],
                    "square_m": b["square_m"],
                    "corners_body": np.asarray(b["corners_body"]).tolist(),
                    "plane_normal_body": np.asarray(b["plane_normal_body"]).tolist(),
                    "plane_d_body": b["plane_d_body"],
                }
                for b in self.boards()
            ],
            "lasers": lasers,
        }
        if self.pose is not None:
            p = self.pose
            out["pose_ned"] = {
                "north_m": p.north_m,
                "east_m": p.east_m,
                "down_m": p.down_m,
                "roll_rad": p.roll_rad,
                "pitch_rad": p.pitch_rad,
                "yaw_rad": p.yaw_rad,
            }
            out["surfaces_ned"] = self.scene.to_dicts()
        return out

    def to_json(self, max_points: int | None = 4000) -> str:
        """:meth:`to_dict` as JSON text."""
        return json.dumps(self.to_dict(max_points))

    def points_ned(self) -> FloatArray:
        """All visible truth points in NED (N, 3) (needs a pose)."""
        if self.pose is None:
            msg = "this render has no vehicle pose: its truth is in the body frame only"
            raise SimulationError(msg)
        return body_to_ned(self.all_points()[0], self.pose)


@dataclass(frozen=True)
class Render:
    """The result of :func:`render`.

    Attributes:
        image: (H, W, 3) uint8 BGR, as ``cv2.imread`` gives.
        calibration: the TRUE calibration used to render (tilted lasers, distortion and all).
        truth: the ground truth.
        layers: float32 layers when requested (``"laser"``: the stripe map in DN before noise, (H, W)).
    """

    image: NDArray[np.uint8]
    calibration: Calibration
    truth: Truth
    layers: dict[str, F32] = field(default_factory=dict)
