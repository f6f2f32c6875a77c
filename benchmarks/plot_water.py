"""The pictures of docs/water.md: a turbid column's profile, and range error against range through a flat port.

    python -m benchmarks.plot_water [--out docs/img]

1. ``turbid_profile.png``: one column of the independent turbidity model (``benchmarks/turbid_model.py``; the
   bottom laser, walls at 2 m and 3 m, glow step 0.5 of the stripe peak, 4 px of forward-scatter blur): the noisy
   green samples, the model's noise-free layers (stripe, sheet glow, veil) and their sum, the true stripe centre,
   the default extractor's centre (``Sensor.process``) and the same extractor with the glow fit off
   (``glow_fit=False``: one Gaussian on a line, the clear-water fit).
2. ``port_error.png``: the signed median range error of the bottom laser's stripe on a wall at 0.3-3 m, seen
   through the acrylic port of ``benchmarks/bench_port.py`` (8 mm at 20 mm from the lens, sea water), triangulated
   with the in-air intrinsics, with the focal length scaled by the water's index, with a pinhole fitted to a
   checkerboard-like grid in water at 1 m, with the pinhole best for the stripes at 1 m, and with the exact port
   model (:mod:`lrsensor.port` road of the calibration's ``port``).
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

import numpy as np

from benchmarks.bench_port import pinhole_best_at, pinhole_grid_fit, stripe_on_wall
from benchmarks.turbid_model import Turbid, render
from lrsensor import Calibration, Sensor
from lrsensor.sim.scenes import acrylic_port
from lrsensor.triangulation import triangulate

LASER = 1  # the bottom laser
COLUMN = 700  # a column left of the centre: the glow is well developed there, the stripe bright enough
HALF_ROWS = 28  # rows shown either side of the true centre
RANGES_M = np.geomspace(0.3, 3.0, 13)


def _centre_at(sensor: Sensor, image: np.ndarray, column: int, **options: object) -> float:
    """The extractor's row of the bottom laser's stripe in ``column`` (NaN where it returned none)."""
    scan = sensor.process(image, **options)  # type: ignore[arg-type]
    at = (scan.laser == LASER) & (np.round(scan.uv[:, 0]).astype(int) == column)
    return float(scan.uv[at, 1][0]) if at.any() else float("nan")


def turbid_profile(out: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(12, 5.4), sharey=False)
    for ax, distance in zip(axes, (2.0, 3.0), strict=True):
        frame = render(Turbid(distance_m=distance, glow_step=0.5, blur_px=4.0, seed=0))
        sensor = Sensor(frame.calibration)
        row_true = float(frame.rows[LASER, COLUMN])
        r0 = round(row_true)
        rows = np.arange(r0 - HALF_ROWS, r0 + HALF_ROWS + 1)
        green = frame.image[rows, COLUMN, 1].astype(float)
        layers = {k: np.asarray(frame.layers[k][rows, COLUMN], float) for k in ("stripe", "glow", "veil")}
        model = layers["stripe"] + layers["glow"] + layers["veil"]
        ax.plot(rows, green, ".", color="0.45", ms=4, label="image (green)")
        ax.plot(rows, model, "-", color="k", lw=1.5, label="model, noise-free")
        ax.plot(rows, layers["stripe"] + layers["veil"], "--", color="tab:green", lw=1, label="stripe + veil")
        ax.plot(rows, layers["glow"] + layers["veil"], ":", color="tab:orange", lw=1.5, label="sheet glow + veil")
        marks = (
            (row_true, "k", "-", "true centre"),
            (_centre_at(sensor, frame.image, COLUMN), "tab:blue", "--", "lrsensor (stripe + glow edge)"),
            (_centre_at(sensor, frame.image, COLUMN, glow_fit=False), "tab:red", ":", "one Gaussian on a line"),
        )
        for row, colour, style, label in marks:
            if np.isfinite(row):
                ax.axvline(row, color=colour, ls=style, lw=1.2, label=f"{label}: {row - row_true:+.2f} px")
        px_pct = 100.0 * distance / (frame.calibration.camera.fy * 0.1) * 1.0  # 1 px of row, % of range (approx.)
        ax.set_title(f"wall {distance:g} m, glow 0.5, blur 4 px, column {COLUMN} (1 px: {px_pct:.0f} % of range)",
                     fontsize=9)  # fmt: skip
        ax.set_xlabel("image row v (px; the glow lies outward, towards the bottom edge)", fontsize=9)
        ax.set_ylabel("green (DN)")
        ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=2)
    fig.tight_layout()
    path = out / "turbid_profile.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def port_error(out: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    port = acrylic_port()
    true_cal = replace(Calibration.paper(0.1), port=port)
    air = replace(true_cal, port=None)
    cam = air.camera
    scaled = replace(air, camera=replace(cam, fx=cam.fx * port.n_water, fy=cam.fy * port.n_water))
    models = (
        ("in-air intrinsics", air),
        ("focal length x n_water", scaled),
        ("pinhole calibrated in water at 1 m (grid)", replace(air, camera=pinhole_grid_fit(true_cal, 1.0))),
        ("best pinhole for the stripes at 1 m", replace(air, camera=pinhole_best_at(true_cal, 1.0, scaled.camera))),
        ("flat-port model (lrsensor)", true_cal),
    )
    errors: dict[str, list[float]] = {name: [] for name, _ in models}
    for d in RANGES_M:
        uv, p = stripe_on_wall(true_cal, LASER, float(d))
        r_true = np.linalg.norm(p - true_cal.camera_center_body, axis=1)
        for name, model in models:
            got = triangulate(model, uv, np.full(uv.shape[0], LASER))
            rel = (np.linalg.norm(got - model.camera_center_body, axis=1) - r_true) / r_true
            errors[name].append(100.0 * float(np.nanmedian(rel)))
    fig, (ax, zoom) = plt.subplots(1, 2, figsize=(12, 5.2))
    colours = ("tab:red", "tab:orange", "tab:green", "tab:purple", "tab:blue")
    for (name, _), colour in zip(models, colours, strict=True):
        ax.plot(RANGES_M, errors[name], "o-", ms=3, color=colour, label=name)
        if name != "in-air intrinsics":
            zoom.plot(RANGES_M, errors[name], "o-", ms=3, color=colour, label=name)
    for a, title in ((ax, "signed median range error"), (zoom, "the same without the in-air intrinsics")):
        a.axhline(0.0, color="0.6", lw=0.8)
        a.set_xscale("log")
        a.set_xticks([0.3, 0.5, 1.0, 2.0, 3.0], ["0.3", "0.5", "1", "2", "3"])
        a.minorticks_off()
        a.set_xlabel("wall distance (m)")
        a.set_ylabel("range error (% of range)")
        a.set_title(title)
    fig.legend(*ax.get_legend_handles_labels(), fontsize=8, loc="lower center", ncol=3)
    fig.suptitle("Bottom laser's stripe through an 8 mm acrylic port 20 mm from the lens, sea water", fontsize=10)
    fig.tight_layout(rect=(0, 0.12, 1, 1))
    path = out / "port_error.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("docs/img"), help="folder for the pictures")
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    for make in (turbid_profile, port_error):
        print(f"wrote {make(args.out)}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
