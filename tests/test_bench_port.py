"""The flat-port benchmark's measurements (benchmarks/bench_port.py) on a small scale."""

from __future__ import annotations

import numpy as np

from benchmarks import bench_port as bp
from lrsensor.calibration import Calibration
from lrsensor.sim import acrylic_port


def test_exact_pixels_of_random_ports_are_within_a_thousandth_of_a_percent() -> None:
    rows = bp.exact_pixels(2)
    cells = [c.strip() for c in rows[2].strip("|").split("|")]
    assert cells[0] == "2"
    assert int(cells[1]) > 20_000
    assert cells[5] == "100.000 %"


def test_folded_pixels_of_a_distorted_camera_are_left_out() -> None:
    cam = bp.distorted_calibration().camera
    dirs = np.array([[0.1, 0.05, 1.0], [3.0, 0.2, 1.0]])  # in view; far outside it (folded by the polynomial)
    uv = cam.project(dirs)
    assert cam.in_image(uv[1:2]).all()  # the polynomial folds it into the image
    assert bp.one_to_one(cam, uv, dirs).tolist() == [True, False]


def test_cost_of_ignoring_the_port() -> None:
    rows, best, grid = bp.cost_table(acrylic_port())
    first = [c.strip().rstrip(" %") for c in rows[2].strip("|").split("|")]
    assert first[0] == "0.3"
    in_air, edge = float(first[1]), float(first[2])
    assert -26.0 < in_air < -22.0  # a quarter short
    assert -26.0 < edge < -22.0
    assert float(first[-1]) < 1e-10  # the port model is exact
    assert best.fx > Calibration.paper().camera.fx  # the water narrows the view: a longer focal length
    assert grid.fx > best.fx
