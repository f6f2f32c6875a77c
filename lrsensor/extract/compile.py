"""Compile management of the extractor's kernels: load or compile them without blocking a caller.

The kernels compile once (``cache=True``: tens of seconds the very first time, about a second from numba's
on-disk cache in ``lrsensor/extract/__pycache__``). :func:`ready` starts the compile in a background thread on
first use and returns False until every kernel is compiled for the argument types the extractor uses (the
extractor runs its numpy reference meanwhile); where the cache holds every kernel it loads them at once.
:func:`warm_up` compiles synchronously (benchmarks, tests). Without numba (:data:`HAVE_NUMBA` False) nothing is
compiled and :func:`ready` stays False.
"""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np

from ._jit import HAVE_NUMBA
from .frame import extract_frame
from .geometry import triangulate_points
from .settings import Bands, Geometry, Settings

__all__ = ["HAVE_NUMBA", "ready", "warm_up"]

_READY = threading.Event()
_LOCK = threading.Lock()
_STARTED = False


def warm_up() -> None:
    """Compile (or load from the cache) every kernel for the extractor's argument types; blocks until done."""
    if not HAVE_NUMBA or _READY.is_set():
        return
    with _LOCK:
        if _READY.is_set():
            return
        bands, settings, geometry = _example()
        img = np.zeros((8, 8, 3), np.uint8)
        extract_frame(img, bands, settings, geometry, True)
        f64 = np.zeros(4)
        triangulate_points(
            f64,
            f64,
            np.zeros(4, np.int64),
            geometry.camera,
            geometry.distortion,
            geometry.R_cam_body,
            geometry.origin_body,
            geometry.normals_body,
            geometry.points_body,
        )
        _READY.set()


def _example() -> tuple[Bands, Settings, Geometry]:
    """Records of the types :func:`lrsensor.extract.settings.frame_settings` builds, for an 8x8 image."""
    bands = Bands(np.array([[2, 6]], np.int64), np.zeros((1, 8), np.int64), np.full((1, 8), 7, np.int64))
    settings = Settings(
        contrast_px=2,
        snr_threshold=4.0,
        area_noise=0.3,
        min_response_dn=3.5,
        max_candidates=4,
        max_jump_px=3.0,
        min_run_cols=8,
        window_half_px=20,
        iterations=2,
        saturation_dn=250.0,
        min_fwhm_px=0.8,
        max_sigma_px=5.0,
        wide_fwhm_px=4.7,
        min_contrast_dn=5.0,
        min_snr=2.5,
        min_green_ratio=1.2,
        gate_pool_cols=4,
        snr_floor_frac=0.75,
        max_sheet_mm=20.0,
        smooth_scales=np.array([4, 1], np.int64),
        min_range_m=0.2,
        max_range_m=5.0,
    )
    eye = np.eye(3)
    geometry = Geometry(
        np.ones(4), np.zeros(5), eye, np.zeros(3), eye[:1].copy(), eye[:1].copy(), np.array([0.0, 0.0, 1.0]), 0.0
    )
    return bands, settings, geometry


def ready() -> bool:
    """True when the compiled kernels can be called without compiling; starts the background compile once."""
    global _STARTED
    if not HAVE_NUMBA:
        return False
    if _READY.is_set():
        return True
    if not _STARTED:
        _STARTED = True
        if _cached():
            warm_up()  # loading from the on-disk cache takes about a second: do it now
            return True
        threading.Thread(target=warm_up, name="lrsensor-numba-warmup", daemon=True).start()
    return False


#: The kernels that must be compiled before :func:`ready` says so: the road (which compiles every stage it calls)
#: and the triangulation, which :func:`lrsensor.triangulation.triangulate` calls on its own.
_KERNELS = (extract_frame, triangulate_points)


def _cached() -> bool:
    """Whether numba's on-disk cache holds an index for every kernel as defined now (then loading is quick)."""
    try:
        for kernel in _KERNELS:
            code = kernel.py_func.__code__
            path = Path(code.co_filename)
            name = f"{path.stem}.{kernel.py_func.__qualname__}-{code.co_firstlineno}"
            if not any((path.parent / "__pycache__").glob(f"{name}.*.nbi")):
                return False
    except (OSError, AttributeError):
        return False
    return True
