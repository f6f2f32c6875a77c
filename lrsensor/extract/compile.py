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
from .chains import expand_half, select_candidates
from .detect import detect_band, green_rows, local_maxima, noise_dn, noise_dn_rows
from .finish import finish_points
from .fit import fit_columns
from .fit_clipped import core_peaks, fit_columns_clipped
from .fit_common import fit_columns_common
from .frame import extract_frame, frame_profile_stats, process_candidates
from .geometry import max_fwhm_at, triangulate_points
from .refit import point_table, refit_columns, refit_full, refit_targets
from .smooth import smooth_runs

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
        i64 = np.zeros(4, np.int64)
        f64 = np.zeros(4)
        nan = np.full(4, np.nan)
        b = np.zeros(4, np.bool_)
        img = np.zeros((8, 8, 3), np.uint8)
        select_candidates(np.arange(4, dtype=np.int64), i64 + 2, f64 + 1.0, 8, 2, 3.0, 4, 3, 2)
        expand_half(i64, f64, i64, i64, 4, 8)
        fit_columns(img, i64, i64 + 4, 2, 1, 1.0, 250.0, 0.5, 5.0, 1, 2, nan, nan, nan, f64 + 20.0, 4.7)
        refit_targets(
            i64,
            i64,
            f64,
            f64,
            f64,
            b,
            b,
            point_table(i64, i64, 2, 8),
            10.0,
            (6.0, 8.0, 2.0),
            i64,
            np.full((3, 4), np.nan),
        )
        finish_points(
            i64,
            i64,
            f64,
            f64,
            f64,
            b,
            b,
            f64,
            i64,
            i64,
            np.ones(2),
            8,
            16,
            5.0,
            2.5,
            8,
            5.0,
            np.array([4, 1]),
            np.zeros((3, 4)),
            1.2,
            4,
            0.75,
            3.0,
            2.0,
        )
        smooth_runs(np.full(16, np.nan), np.full(16, -1, np.int64), np.array([4, 1]))
        eye = np.eye(3)
        g = green_rows(img.reshape(-1), 8, 0, 8)
        noise_dn(g, 2)
        noise_dn_rows(img.reshape(-1), 8, np.arange(8), 2)
        local_maxima(g, 1.0, 0, 2, i64, i64 + 8, 8, 0)
        detect_band(img, 2, 6, 2, 4.0, 0.3, 3.5, np.zeros(8, np.int64), np.full(8, 7, np.int64), 0)
        frame_profile_stats(img, i64, i64 + 4, 2, 250.0, 5.0, f64)
        core_peaks(img, i64, i64 + 4, 1, 250.0)
        fit_columns_common(img, i64, i64 + 4, 2, 1.0, 250.0, 0.5, 5.0, 1, 2, 4.7)
        fit_columns_clipped(img, i64, i64 + 4, 2, 1.0, 250.0, 1, 2, 0.5, 5.0, 4.7)
        triangulate_points(f64, f64, i64, np.ones(4), np.zeros(5), eye, np.zeros(3), eye[:2], eye[:2])
        process_candidates(
            img,
            np.zeros(0, np.int64),
            np.zeros(0, np.int64),
            np.zeros(0),
            np.ones(2),
            np.array([2, 4, 8, 4, 20, 2, 2], np.int64),
            np.array([3.0, 250.0, 0.8, 5.0, 5.0, 2.5, 1.2, 20.0, 0.75]),
            np.array([4, 1], np.int64),
            np.ones(4),
            np.zeros(5),
            eye,
            np.zeros(3),
            eye[:2],
            eye[:2],
            np.array([0.0, 0.0, 1.0]),
            4.7,
            True,
        )
        extract_frame(
            img,
            np.array([[2, 6]], np.int64),
            np.zeros((1, 8), np.int64),
            np.full((1, 8), 7, np.int64),
            np.array([2.0, 4.0, 0.3, 3.5]),
            np.array([2, 4, 8, 4, 20, 1, 2], np.int64),
            np.array([3.0, 250.0, 0.8, 5.0, 5.0, 2.5, 1.2, 20.0, 0.75]),
            np.array([4, 1], np.int64),
            np.ones(4),
            np.zeros(5),
            eye,
            np.zeros(3),
            eye[:1],
            eye[:1],
            np.array([0.0, 0.0, 1.0]),
            4.7,
            np.array([0.0, 0.0, 1.0, 0.0, 0.2, 5.0]),
        )
        _READY.set()


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


#: The kernels that must be compiled before :func:`ready` says so.
_KERNELS = (
    select_candidates,
    expand_half,
    fit_columns,
    point_table,
    refit_targets,
    finish_points,
    smooth_runs,
    triangulate_points,
    green_rows,
    noise_dn,
    noise_dn_rows,
    local_maxima,
    frame_profile_stats,
    fit_columns_common,
    fit_columns_clipped,
    core_peaks,
    max_fwhm_at,
    process_candidates,
    detect_band,
    refit_columns,
    refit_full,
    extract_frame,
)


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
