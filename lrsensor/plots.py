"""PNG plots of the sensor core (matplotlib, imported lazily; the Agg backend, no screen needed)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from .errors import LrsensorError
from .range_theory import RangeCamera, pixel_change, pixel_from_range


def pyplot() -> Any:
    """matplotlib.pyplot with the Agg backend, or a clear error when matplotlib is missing."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as err:  # pragma: no cover - depends on the install
        msg = "plots need matplotlib: pip install 'lrsensor[plot]'"
        raise LrsensorError(msg) from err
    return plt


def plot_range_theory(
    path: Path,
    baselines_m: Sequence[float],
    cam: RangeCamera,
    step_m: float = 0.1,
    max_distance_m: float = 8.0,
) -> None:
    """The paper's Fig. 9 and Fig. 10: pixel value and pixel change per step against distance."""
    plt = pyplot()
    x = np.linspace(0.1, max_distance_m, 600)
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(8, 8), sharex=True)
    for b in baselines_m:
        ax1.plot(x, pixel_from_range(x, b, cam), label=f"b = {b:g} m")
        ax2.plot(x, pixel_change(x, b, step_m, cam), label=f"b = {b:g} m")
    ax1.set_ylabel("pixel value v [px]")
    ax1.set_ylim(0, 300)
    ax1.set_title("Pixel value against distance (paper Fig. 9 top / Fig. 10)")
    ax1.grid(True, alpha=0.3)
    ax1.legend()
    ax2.axhline(1.0, color="green", lw=2, label="1 px")
    ax2.set_yscale("log")
    ax2.set_ylabel(f"pixel change per {step_m * 100:g} cm [px]")
    ax2.set_xlabel("distance x_b [m]")
    ax2.set_title("Pixel difference against distance (paper Fig. 9 bottom)")
    ax2.grid(True, which="both", alpha=0.3)
    ax2.legend()
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)
