"""NED clouds: body-frame points to NED with a pose, and the integer quantization the map works in."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from lrsensor.frames import Pose, body_to_ned

from .errors import MapInputError

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

#: Quantized coordinates are stored as int32 in windows: |coordinate| must stay below this many quanta.
_INT32_LIMIT = 2**31 - 1


def cloud_to_ned(points_body: ArrayLike, pose: Pose) -> FloatArray:
    """Transform one cloud from the body frame to NED with the vehicle pose at capture time.

    Args:
        points_body: (N, 3) points in the body frame, metres.
        pose: vehicle pose in NED at the capture time.

    Returns:
        (N, 3) float64 points in NED, metres (``p_ned = R_ned_from_body p_body + p``).
    """
    return body_to_ned(points_body, pose)


def check_cloud(points_ned: ArrayLike, where: str) -> FloatArray:
    """Validate a NED cloud: (N, 3) float, non-finite rows dropped. ``where`` names the source in errors."""
    p = np.asarray(points_ned, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        msg = f"{where}: points must have shape (N, 3), got {p.shape}"
        raise MapInputError(msg)
    finite = np.all(np.isfinite(p), axis=1)
    if not finite.all():
        p = p[finite]
    return p


def quantize(points_m: ArrayLike, quantum_m: float, where: str = "points") -> NDArray[np.int32]:
    """Quantize metres to integer quanta, (N, 3) int32; raises :class:`MapInputError` beyond the int32 range."""
    p = np.asarray(points_m, dtype=np.float64)
    q = np.rint(p / quantum_m)
    if q.size and float(np.abs(q).max()) >= _INT32_LIMIT:
        msg = f"{where}: coordinates beyond {_INT32_LIMIT * quantum_m:.0f} m from the NED origin"
        raise MapInputError(msg)
    return q.astype(np.int32)
