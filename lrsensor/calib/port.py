"""Calibrating the camera's flat port from checkerboard images taken in water.

The camera's intrinsics and distortion are calibrated in air (``lrsensor calibrate camera``); the glass's
thickness and the refractive indices are known from the housing. What is left to measure is where the window
is: ``distance_m`` (lens centre to the inner surface) and, optionally, a small tilt of its normal.

Method: a checkerboard is photographed in the water in several poses (different distances and angles). Its
corners are found as for the camera calibration; each image's pose starts from ``solvePnP`` on a pinhole in
the water (the in-air rays scaled down by ``n_water / n_air``), then Levenberg-Marquardt adjusts all the board
poses, ``distance_m`` and the normal's two tilt components together, minimising the pixel distance between the
detected corners and their exact projections through the port (:func:`lrsensor.port.project_pixels_through_port`;
numerical Jacobian: a few dozen parameters). The standard deviation of ``distance_m`` follows from the Jacobian
and the residuals. Why not a pinhole in water: it cannot tell the port's distance at all, and it is biased
across the image (docs/water.md, "What ignoring the port costs").

Refusals (:class:`PortCalibrationError`): no ``port`` in the input (thickness and indices are needed), fewer
boards than ``min_images``, an RMS reprojection error above ``max_rms_px``, a ``distance_m`` whose standard
deviation exceeds ``max_distance_sigma_m`` (views too alike: add nearer and more oblique ones), a fit that
leaves the port's valid range (distance <= 0, tilt above 30 deg).
"""

from __future__ import annotations

import datetime as _dt
import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..calibration import Calibration
from ..errors import GeometryError
from ..port import FlatPort, project_pixels_through_port
from .board import BoardCalibrationError, BoardSpec, corners_clear_of_stripes, find_board_corners, image_table_lines
from .camera import ImageLike, _load

FloatArray = NDArray[np.float64]

#: Levenberg-Marquardt iterations at most.
MAX_ITERATIONS = 60
#: Pixel residual given to a corner whose projection does not exist for a trial port (outside the view).
MISSING_RESIDUAL_PX = 1e3


class PortCalibrationError(BoardCalibrationError):
    """The port calibration was refused; ``not_found`` lists the images without a board."""


@dataclass(frozen=True)
class PortCalibrationResult:
    """The port measured from boards in water.

    Attributes:
        port: the fitted port (thickness and indices from the input).
        calibration: the input calibration with this port and a ``port_calibration`` metadata block.
        rms_px: RMS corner reprojection error over all images, pixels.
        per_image_rms_px: per used image name, RMS reprojection error, pixels.
        distance_sigma_m: standard deviation of ``distance_m``, metres.
        tilt_deg: angle between the fitted normal and the optical axis, degrees.
        used, not_found: names of the images whose board was (not) found.
    """

    port: FlatPort
    calibration: Calibration
    rms_px: float
    per_image_rms_px: dict[str, float]
    distance_sigma_m: float
    tilt_deg: float
    used: list[str]
    not_found: list[str]
    metadata: dict[str, Any] = field(default_factory=dict)

    def format_table(self) -> str:
        """Plain-text report."""
        p = self.port
        lines = [
            f"port distance_m {p.distance_m:.5f} m (sigma {1e3 * self.distance_sigma_m:.3f} mm), thickness_m "
            f"{p.thickness_m:.4f} m, n_glass {p.n_glass}, n_water {p.n_water}",
            f"normal_cam [{p.normal_cam[0]:.5f}, {p.normal_cam[1]:.5f}, {p.normal_cam[2]:.5f}] "
            f"(tilt {self.tilt_deg:.3f} deg)",
            f"RMS reprojection error: {self.rms_px:.4f} px over {len(self.used)} images",
            "",
        ]
        lines += image_table_lines(self.per_image_rms_px, self.not_found)
        return "\n".join(lines)


def _rotation(rvec: FloatArray) -> FloatArray:
    """Rodrigues' formula: the rotation (3, 3) of the rotation vector ``rvec`` (3,), radians."""
    theta = float(np.linalg.norm(rvec))
    if theta < 1e-12:
        return np.eye(3)
    k = rvec / theta
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(theta) * kx + (1.0 - math.cos(theta)) * (kx @ kx)


def _port_of(base: FlatPort, theta: FloatArray, fit_tilt: bool) -> FlatPort:
    """The port of the parameters ``theta`` (distance, then the normal's x and y over z when fitted)."""
    normal = (float(theta[1]), float(theta[2]), 1.0) if fit_tilt else base.normal_cam
    return replace(base, normal_cam=normal, distance_m=float(theta[0]))


def calibrate_port(
    images: Sequence[tuple[str, ImageLike]],
    board: BoardSpec,
    calibration: Calibration,
    *,
    fit_tilt: bool = True,
    min_images: int = 3,
    max_rms_px: float = 1.0,
    max_distance_sigma_m: float = 0.0005,
) -> PortCalibrationResult:
    """Measure the calibration's flat port (``distance_m``, and the normal's tilt with ``fit_tilt``) from
    checkerboard images taken in water (see the module documentation).

    Args:
        images: ``(name, path or BGR image)`` pairs of the calibration's image size.
        board: the checkerboard (inner corners, square size in metres).
        calibration: in-air camera, and a ``port`` whose thickness and indices are known; its ``distance_m``
            and normal are the first guess.
        fit_tilt: also fit the normal's tilt (else keep the input's normal).
        min_images, max_rms_px, max_distance_sigma_m: refusal thresholds.

    Raises:
        PortCalibrationError: see the module documentation; the message says what to change.
    """
    import cv2

    base = calibration.port
    if base is None:
        msg = (
            "the calibration has no `port`: add one with the glass's thickness_m and the indices n_air, n_glass, "
            "n_water (its distance_m and normal_cam are the first guess)"
        )
        raise PortCalibrationError(msg)
    cam = calibration.camera
    obj = board.object_points().astype(np.float64)
    views: list[tuple[str, FloatArray, FloatArray]] = []  # name, board points (M, 3), corners (M, 2)
    not_found: list[str] = []
    for name, src in images:
        img = _load(src)
        if img is None:
            not_found.append(name)
            continue
        if (img.shape[1], img.shape[0]) != (cam.width, cam.height):
            msg = f"{name}: image is {img.shape[1]}x{img.shape[0]} but the camera is {cam.width}x{cam.height}"
            raise PortCalibrationError(msg, not_found)
        corners = find_board_corners(img, board)
        if corners is None:
            not_found.append(name)
            continue
        clear = corners_clear_of_stripes(img, corners, board)
        views.append((name, obj[clear], corners[clear]))
    if len(views) < min_images:
        msg = (
            f"checkerboard ({board.cols}x{board.rows} inner corners) found in only {len(views)} of {len(images)} "
            f"images, need >= {min_images}"
        )
        raise PortCalibrationError(msg, not_found)
    # first poses: solvePnP on a pinhole in the water (in-air normalized coordinates over the index ratio)
    ratio = base.n_water / base.n_air
    poses = []
    for name, o, c in views:
        xy = cam.normalized(c) / ratio
        ok, rvec, tvec = cv2.solvePnP(o, xy.astype(np.float64), np.eye(3), np.zeros(5))
        if not ok:
            msg = f"{name}: solvePnP failed for the checkerboard"
            raise PortCalibrationError(msg, not_found)
        poses += [np.asarray(rvec, float).ravel(), np.asarray(tvec, float).ravel()]
    n0 = base.normal
    head = [base.distance_m] + ([n0[0] / n0[2], n0[1] / n0[2]] if fit_tilt else [])
    n_head = len(head)
    theta = np.concatenate([np.array(head), *poses])

    def residuals(t: FloatArray) -> FloatArray:
        try:
            port = _port_of(base, t, fit_tilt)
        except GeometryError:
            return np.full(sum(2 * o.shape[0] for _, o, _ in views), MISSING_RESIDUAL_PX)
        out = []
        for i, (_, o, c) in enumerate(views):
            k = n_head + 6 * i
            p_cam = o @ _rotation(t[k : k + 3]).T + t[k + 3 : k + 6]
            r = (project_pixels_through_port(cam, port, p_cam) - c).ravel()
            out.append(np.where(np.isfinite(r), r, MISSING_RESIDUAL_PX))
        return np.concatenate(out)

    lam = 1e-3
    r = residuals(theta)
    cost = float(r @ r)
    jac = np.zeros((r.size, theta.size))
    for _ in range(MAX_ITERATIONS):
        for j in range(theta.size):
            h = 1e-7 * max(1.0, abs(theta[j]))
            step = np.zeros(theta.size)
            step[j] = h
            jac[:, j] = (residuals(theta + step) - r) / h
        a = jac.T @ jac
        g = jac.T @ r
        improved = False
        for _ in range(10):
            delta = np.linalg.solve(a + lam * np.diag(np.diag(a) + 1e-12), -g)
            r_new = residuals(theta + delta)
            cost_new = float(r_new @ r_new)
            if cost_new < cost:
                theta, r, cost = theta + delta, r_new, cost_new
                lam = max(lam * 0.3, 1e-9)
                improved = True
                break
            lam *= 10.0
        if not improved or np.abs(delta).max() < 1e-12:
            break
    try:
        port = _port_of(base, theta, fit_tilt)
    except GeometryError as err:
        msg = f"the fit left the port's valid range ({err}): check the board, the input port and the images"
        raise PortCalibrationError(msg, not_found) from err
    dof = max(r.size - theta.size, 1)
    with np.errstate(all="ignore"):
        cov = np.linalg.pinv(jac.T @ jac) * (cost / dof)
    sigma_d = float(math.sqrt(max(cov[0, 0], 0.0)))
    per_image: dict[str, float] = {}
    k = 0
    for name, o, _ in views:
        e = r[k : k + 2 * o.shape[0]].reshape(-1, 2)
        per_image[name] = float(np.sqrt(np.mean(np.sum(e * e, axis=1))))
        k += 2 * o.shape[0]
    rms = float(np.sqrt(cost / (r.size / 2)))
    tilt_deg = math.degrees(math.acos(min(1.0, port.normal_cam[2])))
    if not rms <= max_rms_px:
        worst = sorted(per_image.items(), key=lambda kv: -kv[1])[:3]
        msg = (
            f"calibration refused, no output written: RMS reprojection error {rms:.4f} px exceeds {max_rms_px:.4f} "
            "px (--max-rms-px); check the port's thickness and indices and the in-air intrinsics; worst images: "
            + ", ".join(f"{n} {e:.3f} px" for n, e in worst)
        )
        raise PortCalibrationError(msg, not_found)
    if not (port.distance_m > 0 and sigma_d <= max_distance_sigma_m):
        msg = (
            f"calibration refused, no output written: distance_m {port.distance_m:.5f} m is not fixed by these "
            f"views (standard deviation {1e3 * sigma_d:.3f} mm > {1e3 * max_distance_sigma_m:.3f} mm): add board "
            "views nearer the camera, more oblique and towards the image's edges"
        )
        raise PortCalibrationError(msg, not_found)
    metadata = dict(calibration.metadata)
    metadata["port_calibration"] = {
        "date": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "tool": "lrsensor calibrate port",
        "board": {"cols": board.cols, "rows": board.rows, "square_m": board.square_m},
        "rms_px": round(rms, 5),
        "per_image_rms_px": {n: round(e, 5) for n, e in per_image.items()},
        "distance_sigma_m": sigma_d,
        "tilt_deg": round(tilt_deg, 5),
        "fit_tilt": fit_tilt,
        "images_used": list(per_image),
        "images_without_board": not_found,
        "thresholds": {
            "max_rms_px": max_rms_px,
            "min_images": min_images,
            "max_distance_sigma_m": max_distance_sigma_m,
        },
    }
    out = replace(calibration, port=port, metadata=metadata)
    return PortCalibrationResult(port, out, rms, per_image, sigma_d, tilt_deg, list(per_image), not_found, metadata)
