"""The sensor: one image in, one body-frame scan out."""

from __future__ import annotations

import importlib
import os
from functools import lru_cache
from typing import Any

import numpy as np

from .calibration import Calibration
from .extract import DEFAULT_METHOD, check_image, get_extractor
from .extract import compile as _kernels
from .scan import Scan
from .triangulation import triangulate


class Sensor:
    """The line-laser range sensor: a calibration plus the stripe extractors.

    >>> sensor = Sensor.from_file("calib.json")          # doctest: +SKIP
    >>> scan = sensor.process(image_bgr)                 # doctest: +SKIP
    >>> scan.points                                      # (N, 3) body frame, metres
    """

    def __init__(self, calibration: Calibration, *, wait_for_kernels: bool = True, stream: bool = False) -> None:
        """A sensor with ``calibration``; readies the compiled extractor now rather than in the first frame.

        ``wait_for_kernels``: load the compiled kernels from numba's cache (about a second, once per process) or,
        on a first use, compile them once now (about 30 s, said in the log). False (a live camera that must not
        stall): compile them in the background while the numpy reference processes the frames (said in the
        log, and when the compiled road takes over). See :mod:`lrsensor.extract.compile`.

        ``stream``: the frames come in order from one camera in one water (a live camera, a video). In turbid
        water a frame tells the water's attenuation and the stripe's width that shape the glow; with ``stream``
        the next frames take them and tell them again once every
        :data:`~lrsensor.extract.glow.WATER_FRAMES` frames (a third of a glowing frame's time saved). Without
        (the default: images that may each come from other water), every frame tells its own."""
        self.calibration = calibration
        self._water = None
        if stream:
            from .extract.glow import new_water

            self._water = new_water()
        if wait_for_kernels:
            _kernels.ensure()
        else:
            _kernels.begin()

    @classmethod
    def from_file(cls, path: str | os.PathLike[str]) -> Sensor:
        """A sensor with the calibration read from ``path``."""
        return cls(Calibration.load(path))

    def process(self, image: np.ndarray, method: str = DEFAULT_METHOD, **options: Any) -> Scan:
        """Extract the laser stripes of ``image`` and triangulate them.

        Args:
            image: (H, W, 3) uint8 BGR, as ``cv2.imread`` returns, of the calibration's size.
            method: extractor name: ``"subpixel"`` (default, best) or ``"paper"`` (the paper's Algorithm 1).
            **options: extractor options (see the extractor's documentation).

        Returns:
            The scan: finite points only, body frame, metres.
        """
        img = check_image(image, self.calibration)
        if method == "subpixel":  # the compiled kernels triangulate in the same call
            det, xyz = (_POINTS or _load_points())(img, self.calibration, water=self._water, **options)
            if xyz is not None:  # triangulated and depth-gated in the compiled call
                return Scan(xyz, det.laser, det.uv, det.quality, method)
        else:
            det = get_extractor(method)(img, self.calibration, **options)
        points = triangulate(self.calibration, det.uv, det.laser)
        scan = Scan(points, det.laser.astype(int), det.uv, det.quality, method)
        lo, hi = range_limits(method, options)
        cal = self.calibration
        depth = points @ cal.R_cam_body[2] + cal.t_cam_body[2]  # camera z, metres
        with np.errstate(invalid="ignore"):
            keep = (depth >= lo) & (depth <= hi)  # NaN rows fail both: dropped too
        return scan if bool(keep.all()) else scan.select(keep)


#: ``extract.subpixel.extract_points``, imported on first use (it brings in OpenCV); kept here because an import
#: statement runs the import machinery on every call (tens of microseconds when the caches are cold).
_POINTS: Any = None


def _load_points() -> Any:
    global _POINTS
    from .extract.subpixel import extract_points

    _POINTS = extract_points
    return extract_points


#: Extractor name -> (module, configuration class) holding its default range limits.
_CONFIGS = {
    "subpixel": ("lrsensor.extract.subpixel", "SubpixelConfig"),
    "paper": ("lrsensor.extract.paper", "PaperConfig"),
}


def range_limits(method: str, options: dict[str, Any]) -> tuple[float, float]:
    """The ``(min_range_m, max_range_m)`` depth gate of an extractor call: the options, else its defaults.

    Depth is measured along the optical axis (camera z), as the extractors' laser bands are. A stripe found at the
    edge of its band can triangulate beyond the limit; :meth:`Sensor.process` drops such points so that the
    range limits hold for the output, not only for the search.
    """
    lo, hi = options.get("min_range_m"), options.get("max_range_m")
    if (lo is None or hi is None) and method in _CONFIGS:
        d_lo, d_hi = _default_limits(method)
        lo = d_lo if lo is None else lo
        hi = d_hi if hi is None else hi
    return (0.0 if lo is None else float(lo)), (np.inf if hi is None else float(hi))


@lru_cache(maxsize=8)
def _default_limits(method: str) -> tuple[float, float]:
    """The default ``(min_range_m, max_range_m)`` of a registered extractor's configuration."""
    module_name, cls_name = _CONFIGS[method]
    defaults = getattr(importlib.import_module(module_name), cls_name)()
    return float(defaults.min_range_m), float(defaults.max_range_m)
