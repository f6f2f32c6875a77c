"""Camera intrinsics from checkerboard images (``cv2.calibrateCamera``) with a reprojection report.

Boards that are not found are listed and skipped; the calibration is refused when fewer than ``min_images``
boards were found or the RMS reprojection error exceeds ``max_rms_px``.
"""

from __future__ import annotations

import datetime as _dt
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..calibration import Calibration
from ..camera import Camera
from .board import BoardCalibrationError, BoardSpec, corners_clear_of_stripes, find_board_corners, image_table_lines

ImageLike = str | os.PathLike[str] | NDArray[np.uint8]


class CameraCalibrationError(BoardCalibrationError):
    """The camera calibration was refused; ``not_found`` lists the images without a board."""


@dataclass(frozen=True)
class CameraCalibrationResult:
    """Intrinsics estimated from boards.

    Attributes:
        camera: the new intrinsics and distortion.
        rms_px: OpenCV's overall RMS reprojection error, pixels.
        per_image_rms_px: per used image name, RMS reprojection error, pixels.
        used: names of the images whose board was found.
        not_found: names of the images whose board was not found.
        calibration: the full calibration (new camera, lasers and mounting kept from the base calibration).
    """

    camera: Camera
    rms_px: float
    per_image_rms_px: dict[str, float]
    used: list[str]
    not_found: list[str]
    calibration: Calibration
    metadata: dict[str, Any] = field(default_factory=dict)

    def format_table(self) -> str:
        """Plain-text report."""
        c = self.camera
        lines = [
            f"camera {c.width}x{c.height}: fx {c.fx:.3f} fy {c.fy:.3f} cx {c.cx:.3f} cy {c.cy:.3f} px",
            "distortion [k1 k2 p1 p2 k3]: " + " ".join(f"{d:.6f}" for d in c.distortion),
            f"RMS reprojection error: {self.rms_px:.4f} px over {len(self.used)} images",
            "",
        ]
        lines += image_table_lines(self.per_image_rms_px, self.not_found)
        return "\n".join(lines)


def _load(image: ImageLike) -> NDArray[np.uint8] | None:
    if isinstance(image, np.ndarray):
        return image
    import cv2

    img = cv2.imread(str(image), cv2.IMREAD_COLOR)
    return None if img is None else np.asarray(img, dtype=np.uint8)


def calibrate_camera(
    images: Sequence[tuple[str, ImageLike]],
    board: BoardSpec,
    *,
    base: Calibration | None = None,
    min_images: int = 3,
    max_rms_px: float = 1.0,
    fix_k3: bool = False,
    progress: bool = False,
) -> CameraCalibrationResult:
    """Estimate the camera intrinsics from images of a checkerboard.

    Args:
        images: ``(name, path or BGR image)`` pairs, all of one size.
        board: the checkerboard (inner corners, square size in metres).
        base: calibration whose mounting and lasers are kept (default: ``Calibration.paper()`` lasers).
        min_images: refuse with fewer boards found.
        max_rms_px: refuse when the RMS reprojection error exceeds this, pixels.
        fix_k3: keep k3 = 0 (for narrow lenses and few boards; wide lenses such as the paper's need k3).
        progress: tqdm progress bar over the images.

    Raises:
        CameraCalibrationError: too few boards found, images of different sizes, or RMS above the threshold.
    """
    import cv2

    items: Any = images
    if progress:
        from tqdm import tqdm

        items = tqdm(images, desc="board images", unit="img", disable=None)
    obj = board.object_points()
    obj_pts: list[NDArray[np.float32]] = []
    img_pts: list[NDArray[np.float32]] = []
    used: list[str] = []
    not_found: list[str] = []
    size: tuple[int, int] | None = None
    for name, src in items:
        img = _load(src)
        if img is None:
            not_found.append(name)
            continue
        h, w = img.shape[:2]
        if size is None:
            size = (w, h)
        elif size != (w, h):
            msg = f"{name}: image is {w}x{h} but the first image is {size[0]}x{size[1]}; use one camera mode"
            raise CameraCalibrationError(msg, not_found)
        corners = find_board_corners(img, board)
        if corners is None:
            not_found.append(name)
            continue
        clear = corners_clear_of_stripes(img, corners, board)
        obj_pts.append(obj[clear])
        img_pts.append(corners[clear].astype(np.float32).reshape(-1, 1, 2))
        used.append(name)
    if len(used) < min_images or size is None:
        msg = (
            f"checkerboard ({board.cols}x{board.rows} inner corners) found in only {len(used)} of "
            f"{len(images)} images, need >= {min_images}"
        )
        if not_found:
            msg += "; not found in: " + ", ".join(not_found)
        raise CameraCalibrationError(msg, not_found)
    flags = cv2.CALIB_FIX_K3 if fix_k3 else 0
    rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(obj_pts, img_pts, size, None, None, flags=flags)
    per_image: dict[str, float] = {}
    for name, o, ip, rv, tv in zip(used, obj_pts, img_pts, rvecs, tvecs, strict=True):
        proj, _ = cv2.projectPoints(o, rv, tv, K, dist)
        e = np.linalg.norm(proj.reshape(-1, 2) - ip.reshape(-1, 2), axis=1)
        per_image[name] = float(np.sqrt(np.mean(e * e)))
    d = np.zeros(5)
    flat = np.asarray(dist, dtype=float).ravel()
    d[: min(5, flat.size)] = flat[:5]
    camera = Camera(
        size[0],
        size[1],
        float(K[0, 0]),
        float(K[1, 1]),
        float(K[0, 2]),
        float(K[1, 2]),
        (float(d[0]), float(d[1]), float(d[2]), float(d[3]), float(d[4])),
    )
    if not float(rms) <= max_rms_px:
        msg = (
            f"calibration refused, no output written: RMS reprojection error {float(rms):.4f} px exceeds "
            f"{max_rms_px:.4f} px (--max-rms-px); worst images: "
            + ", ".join(f"{n} {e:.3f} px" for n, e in sorted(per_image.items(), key=lambda kv: -kv[1])[:3])
        )
        raise CameraCalibrationError(msg, not_found)
    src = base or Calibration.paper(width=size[0], height=size[1])
    metadata = dict(src.metadata)
    metadata["camera_calibration"] = {
        "date": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "tool": "lrsensor calibrate camera",
        "board": {"cols": board.cols, "rows": board.rows, "square_m": board.square_m},
        "rms_px": round(float(rms), 5),
        "per_image_rms_px": {n: round(e, 5) for n, e in per_image.items()},
        "images_used": used,
        "images_without_board": not_found,
        "thresholds": {"max_rms_px": max_rms_px, "min_images": min_images},
        "fix_k3": fix_k3,
    }
    from dataclasses import replace

    calibration = replace(src, camera=camera, metadata=metadata)
    return CameraCalibrationResult(camera, float(rms), per_image, used, not_found, calibration, metadata)


def image_names(paths: Sequence[str | os.PathLike[str]]) -> list[tuple[str, ImageLike]]:
    """``(name, path)`` pairs for :func:`calibrate_camera` from paths."""
    return [(str(Path(p)), p) for p in paths]
