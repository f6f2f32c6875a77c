"""Laser-stripe extractors: image in, stripe pixels (u, v) per laser out.

Every extractor is a function ``extract(image_bgr, calibration, **options) -> Detections``. They are looked up
by name in :data:`METHODS` (imported lazily so that importing the package stays cheap).

The default extractor (:mod:`.subpixel`) is a package of stage modules on one compiled road:

- :mod:`.subpixel`: the entry points (``extract``, ``extract_points``); :mod:`.config`: its options;
  :mod:`.settings`: the typed records the road reads, built once per (calibration, configuration);
  :mod:`.bands`: where each laser's stripe can be;
- the road (numba kernels): :mod:`.frame` (the seven calls per frame; the first two in :mod:`.frame_locate`),
  :mod:`.detect`, :mod:`.chains`, the fit (:mod:`.fit`: one column-parallel fit for every kind of profile, its
  pieces in :mod:`.columns`), :mod:`.refit`, :mod:`.glow` (turbid water: the stripe fitted jointly with the laser
  sheet's glow), :mod:`.finish`, :mod:`.smooth`, :mod:`.geometry`; :mod:`._jit` (the decorators) and
  :mod:`.compile` (loading or compiling the kernels);
- the readable numpy reference of the whole frame: :mod:`.reference` (the frame), :mod:`.reference_detect`,
  :mod:`.reference_chains`, :mod:`.reference_fit` with :mod:`.centre` (the vectorized profile fit),
  :mod:`.reference_glow`, :mod:`.reference_finish` and :mod:`.reference_pooled`; tests compare the road with it on
  whole frames.

:mod:`.paper` is the paper's Algorithm 1, the baseline.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass, fields, replace
from typing import Any, TypeVar

import numpy as np
from numpy.typing import NDArray

from ..calibration import Calibration
from ..errors import ExtractionError

FloatArray = NDArray[np.float64]
C = TypeVar("C")


@dataclass(frozen=True)
class Detections:
    """Stripe measurements of one image.

    Attributes:
        uv: (N, 2) sub-pixel image coordinates of stripe centres.
        laser: (N,) index of the laser (into ``Calibration.lasers``) each measurement belongs to.
        quality: (N,) confidence in [0, 1].
    """

    uv: FloatArray
    laser: NDArray[np.int_]
    quality: FloatArray

    @classmethod
    def empty(cls) -> Detections:
        """No measurements."""
        return cls(np.zeros((0, 2)), np.zeros(0, dtype=int), np.zeros(0))


Extractor = Callable[..., Detections]

#: Extractor name -> "module:function" (relative to this package).
METHODS: dict[str, str] = {
    "subpixel": ".subpixel:extract",
    "paper": ".paper:extract",
}
DEFAULT_METHOD = "subpixel"
#: What the sub-pixel extractor's ``channel`` option may name (``SubpixelConfig.channel``).
CHANNELS = ("green", "luma")


def channel_option(method: str | None, channel: str | None) -> dict[str, str]:
    """The extractor options of a command line's ``--channel`` flag: ``{"channel": channel}``, or none when the
    flag is not given; an :class:`ExtractionError` when it is given with a ``method`` other than the sub-pixel
    extractor (None = the default), the only one that has it."""
    if channel is None:
        return {}
    if (method or DEFAULT_METHOD) != "subpixel":
        msg = f"--channel is an option of the subpixel extractor, not of --method {method}"
        raise ExtractionError(msg)
    return {"channel": channel}


def command_line_options(
    method: str | None, channel: str | None, min_range_m: float | None, max_range_m: float | None
) -> dict[str, Any]:
    """The extractor options of a command line's ``--channel``, ``--min-range-m`` and ``--max-range-m`` flags, for
    ``Sensor.process(image, method=method, **options)``: the flags given (None = not given, the extractor's
    default); ``--channel`` as :func:`channel_option` (refused with another method)."""
    options: dict[str, Any] = dict(channel_option(method, channel))
    if min_range_m is not None:
        options["min_range_m"] = min_range_m
    if max_range_m is not None:
        options["max_range_m"] = max_range_m
    return options


def get_extractor(method: str) -> Extractor:
    """The extractor function registered under ``method``; raises :class:`ExtractionError` if unknown."""
    try:
        target = METHODS[method]
    except KeyError:
        msg = f"unknown extraction method {method!r}; choose one of {sorted(METHODS)}"
        raise ExtractionError(msg) from None
    module_name, func = target.split(":")
    module = importlib.import_module(module_name, __name__)
    fn: Extractor = getattr(module, func)
    return fn


def config_with_options(cls: type[C], config: C | None, label: str, options: dict[str, Any]) -> C:
    """``config`` (or ``cls()``'s defaults) with keyword overrides; unknown names raise :class:`ExtractionError`."""
    base = config or cls()
    names = {f.name for f in fields(cls)}  # type: ignore[arg-type]
    unknown = sorted(set(options) - names)
    if unknown:
        msg = f"unknown {label} extractor option(s) {unknown}; known: {sorted(names)}"
        raise ExtractionError(msg)
    return replace(base, **options) if options else base  # type: ignore[type-var]


def check_image(image: Any, calibration: Calibration) -> NDArray[np.uint8]:
    """Validate an image for processing: (H, W, 3) uint8 BGR of the calibration's size."""
    if not isinstance(image, np.ndarray):
        msg = f"image must be a numpy array (H, W, 3) uint8 BGR, got {type(image).__name__}"
        raise ExtractionError(msg)
    if image.ndim != 3 or image.shape[2] != 3:
        msg = f"image must have shape (H, W, 3) BGR, got {image.shape}"
        raise ExtractionError(msg)
    if image.dtype != np.uint8:
        msg = f"image must be uint8, got {image.dtype}"
        raise ExtractionError(msg)
    h, w = image.shape[:2]
    cam = calibration.camera
    if (w, h) != (cam.width, cam.height):
        msg = f"image is {w}x{h} but the calibration's camera is {cam.width}x{cam.height}"
        raise ExtractionError(msg)
    return image
