"""Benchmark of the laser-plane calibration on simulated tilted lasers (issue 4).

For a few tilt cases: render wall images at 0.4, 0.5 and 0.6 m with the TRUE (tilted) lasers, calibrate from
the NOMINAL calibration, and compare: tilt truth vs estimate, normal error (deg), plane offset error at the
laser (mm), and the median relative range error of walls at 0.8 and 1.0 m processed with the nominal and the
calibrated planes (and, for reference, with the true planes: the extractor's own floor).

Run: ``python benchmarks/bench_calib.py`` (prints markdown tables; about a minute on one core).
"""

from __future__ import annotations

import time

import numpy as np

from lrsensor import Sensor
from lrsensor.calib import BoardSpec, LaserCalibrationConfig, WallImage, calibrate_lasers
from lrsensor.calib.planefit import normal_angle_deg
from lrsensor.calibration import Calibration
from lrsensor.sim import Checkerboard, checkerboard_wall_scene, paper_calibration, tilted_calibration, wall_scene

#: name -> per laser (tilt about body y, tilt about body x) in degrees.
CASES: dict[str, tuple[tuple[float, float], ...]] = {
    "pitch +-1": ((1.0, 0.0), (-1.0, 0.0)),
    "pitch/roll 1.5": ((1.5, 0.6), (-1.2, -0.9)),
    "mixed 2": ((2.0, -0.5), (0.5, 1.5)),
    "converging 2": ((-2.0, 0.0), (2.0, 0.0)),
}
CAL_DISTANCES_M = (0.4, 0.5, 0.6)
TEST_DISTANCES_M = (0.8, 1.0)


def median_range_error(cal: Calibration, image: np.ndarray, dist: float) -> float:
    """Median relative range error (fraction) of a wall square to body x at ``dist``."""
    scan = Sensor(cal).process(image)
    return float(np.median(np.abs(scan.points[:, 0] / dist - 1.0)))


def run_case(name: str, tilts: tuple[tuple[float, float], ...], mode: str) -> list[str]:
    """Rows of the table for one case; ``mode`` is ``distance``, ``board`` or ``one wall + mounting``."""
    true = tilted_calibration(tilts_deg=tilts)
    nominal = paper_calibration()
    walls: list[WallImage] = []
    config = LaserCalibrationConfig()
    if mode == "board":
        board = Checkerboard(9, 6, 0.03, offset_u_m=-0.25, offset_v_m=0.0)
        normals = ((1.0, 0.0, 0.0), (1.0, 0.1, 0.0), (1.0, -0.1, 0.05))
        for i, (d, n) in enumerate(zip(CAL_DISTANCES_M, normals, strict=True)):
            img = checkerboard_wall_scene(d, n, board, calibration=true).render(seed=i).image
            walls.append(WallImage(img, None, name=f"board {d}"))
        config = LaserCalibrationConfig(board=BoardSpec(9, 6, 0.03))
    elif mode == "one wall + mounting":
        img = wall_scene(0.5, calibration=true).render(seed=0).image
        walls.append(WallImage(img, 0.5, name="wall 0.5"))
        config = LaserCalibrationConfig(mounting={l.name: l.point for l in true.lasers})
    else:
        for i, d in enumerate(CAL_DISTANCES_M):
            walls.append(WallImage(wall_scene(d, calibration=true).render(seed=i).image, d, name=f"wall {d}"))
    t0 = time.perf_counter()
    result = calibrate_lasers(walls, nominal, config)
    dt = time.perf_counter() - t0
    tests = {d: wall_scene(d, calibration=true).render(seed=100 + i).image for i, d in enumerate(TEST_DISTANCES_M)}
    rows = []
    for li, (est, tru, nom) in enumerate(zip(result.calibration.lasers, true.lasers, nominal.lasers, strict=True)):
        rep = result.report.lasers[li]
        errs = []
        for d, img in tests.items():
            for cal in (nominal, result.calibration, true):
                scan = Sensor(cal).process(img)
                sel = scan.laser == li
                errs.append(float(np.median(np.abs(scan.points[sel, 0] / d - 1.0))) * 100)
        offset_mm = abs(float((est.point_body - tru.point_body) @ tru.normal_body)) * 1000
        rows.append(
            f"| {name} | {mode} | {est.name} | {normal_angle_deg(tru.normal_body, nom.normal_body):.3f} | "
            f"{rep.tilt_deg:.3f} | {normal_angle_deg(est.normal_body, tru.normal_body):.4f} | {offset_mm:.3f} | "
            f"{rep.rms_mm:.3f} | " + " | ".join(f"{e:.3f}" for e in errs) + f" | {dt:.2f} |"
        )
    return rows


def main() -> None:
    head = ["case", "walls", "laser", "tilt truth deg", "tilt est. deg", "normal err deg", "offset err mm", "RMS mm"]
    for d in TEST_DISTANCES_M:
        head += [f"{d} m nominal %", f"{d} m calibrated %", f"{d} m true planes %"]
    head.append("fit s")
    print("Laser calibration from simulated walls (1920x1080, f = 554 px, b = 0.1 m, default water).")
    print("Range errors are medians of |x / x_true - 1| in percent; 'true planes' is the extractor's floor.\n")
    print("| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    for name, tilts in CASES.items():
        for row in run_case(name, tilts, "distance"):
            print(row, flush=True)
    for row in run_case("pitch/roll 1.5", CASES["pitch/roll 1.5"], "board"):
        print(row, flush=True)
    for row in run_case("pitch/roll 1.5", CASES["pitch/roll 1.5"], "one wall + mounting"):
        print(row, flush=True)


if __name__ == "__main__":
    main()
