"""PNG plot of the laser calibration residuals (matplotlib with the Agg backend, imported lazily)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from .laser_records import LaserCalibrationReport


def plot_laser_residuals(report: LaserCalibrationReport, path: str | os.PathLike[str]) -> Path:
    """Residuals per laser per image: one panel per laser, residual (mm) against image column u (px).

    Inliers are dots coloured by image, outliers grey crosses (clipped to the plot); the dashed lines are the
    RMS threshold when it falls inside the plotted range (the range follows the inlier residuals).
    Writes ``path`` (PNG) and returns it.
    """
    from ..plots import pyplot

    plt = pyplot()
    names = list(report.residuals) or ["(none)"]
    fig, axes = plt.subplots(len(names), 1, figsize=(9, 3.2 * len(names)), sharex=True, squeeze=False)
    max_rms = report.thresholds.get("max_rms_mm", float("nan"))
    labels = [im.name for im in report.images]
    short = [Path(n).name for n in labels]
    if len(set(short)) == len(short):
        labels = short
    else:
        labels = [str(Path(*Path(n).parts[-2:])) if len(Path(n).parts) >= 2 else n for n in labels]
    for ax, name in zip(axes[:, 0], names, strict=True):
        per_image = report.residuals.get(name, [])
        fit = next((l for l in report.lasers if l.name == name), None)
        inl_abs = [np.abs(r[inl]) for _, r, inl in per_image if inl.any()]
        span = max(0.1, 1.5 * max(float(a.max()) for a in inl_abs) * 1000) if inl_abs else 1.0
        for gi, (u, r, inl) in enumerate(per_image):
            label = labels[gi] if gi < len(labels) else f"image {gi}"
            ax.plot(u[inl], r[inl] * 1000, ".", ms=2, label=f"{label} ({int(inl.sum())} pts)")
            if (~inl).any():
                clipped = np.clip(r[~inl] * 1000, -0.97 * span, 0.97 * span)
                ax.plot(u[~inl], clipped, "x", ms=3, color="0.6")
        if np.isfinite(max_rms) and max_rms <= span:
            for sign in (-1, 1):
                ax.axhline(sign * max_rms, ls="--", lw=1, color="red", label="RMS limit" if sign > 0 else None)
        ax.set_ylim(-span, span)
        title = f"laser {name}"
        if fit is not None:
            title += f": RMS {fit.rms_mm:.3f} mm, max {fit.max_mm:.3f} mm, tilt {fit.tilt_deg:.3f} deg"
        ax.set_title(title)
        ax.set_ylabel("residual [mm]")
        ax.grid(True, alpha=0.3)
        if per_image:
            ax.legend(fontsize=7, markerscale=4, loc="upper right")
    axes[-1, 0].set_xlabel("image column u [px]")
    fig.tight_layout()
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=100)
    plt.close(fig)
    return out
