"""Port calibration from checkerboard images rendered through a flat port (issue 26: distance_m within 1 mm).

The CLI runs in-process (``lrsensor.cli.main``); a refusal must exit 2 with a clear message and write nothing.
"""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path
from typing import Any

import cv2
import pytest

from lrsensor.calib import BoardSpec, PortCalibrationError, calibrate_port
from lrsensor.calibration import Calibration
from lrsensor.cli import main
from lrsensor.port import FlatPort
from lrsensor.sim import Checkerboard, acrylic_port, checkerboard_wall_scene, paper_calibration

BOARD = BoardSpec(9, 6, 0.025)
#: (wall distance m, wall yaw deg, board offset along the wall u, v m): near and far, oblique, above and below
#: the stripes, left and right.
VIEWS = (
    (0.5, 0, 0.0, -0.16),
    (0.5, 10, -0.15, 0.16),
    (0.8, -10, 0.2, 0.22),
    (0.45, 0, 0.12, 0.15),
    (0.9, 30, -0.2, -0.22),
    (0.4, -15, 0.0, 0.14),
)


@pytest.fixture(scope="module")
def bench(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """Board images through the issue's acrylic port tilted 2 deg, and an input file with a first guess."""
    d = tmp_path_factory.mktemp("port")
    true = replace(paper_calibration(), port=acrylic_port(2.0))
    paths = []
    for i, (dist, yaw, ou, ov) in enumerate(VIEWS):
        a = math.radians(yaw)
        board = Checkerboard(cols=9, rows=6, square_m=0.025, offset_u_m=ou, offset_v_m=ov)
        image = checkerboard_wall_scene(dist, (math.cos(a), math.sin(a), 0.0), board, calibration=true).render(i)
        path = d / f"board_{i}.png"
        cv2.imwrite(str(path), image.image)
        paths.append(path)
    guess = replace(paper_calibration(), port=FlatPort((0.0, 0.0, 1.0), 0.03, 0.008, 1.0, 1.49, 1.34))
    guess.save(d / "guess.json")
    return {"dir": d, "true": true, "paths": paths, "guess": guess}


def _images(bench: dict[str, Any], n: int | None = None) -> list[tuple[str, Any]]:
    return [(p.name, p) for p in bench["paths"][:n]]


def test_distance_and_tilt_are_recovered(bench: dict[str, Any]) -> None:
    result = calibrate_port(_images(bench), BOARD, bench["guess"])
    true = bench["true"].port
    assert abs(result.port.distance_m - true.distance_m) < 0.001  # the bar: 1 mm
    assert result.distance_sigma_m < 0.0005
    assert result.tilt_deg == pytest.approx(2.0, abs=0.2)
    assert result.rms_px < 0.2
    assert result.calibration.port == result.port
    assert result.port.thickness_m == true.thickness_m
    assert result.calibration.metadata["port_calibration"]["images_used"]
    # the camera and lasers are kept
    assert result.calibration.camera == bench["guess"].camera
    assert result.calibration.lasers == bench["guess"].lasers


def test_cli_writes_the_port(bench: dict[str, Any], tmp_path: Path, capsys: Any) -> None:
    out = tmp_path / "ported.json"
    args = ["calibrate", "port", *map(str, bench["paths"]), "--board", "9x6", "--square-m", "0.025"]
    code = main([*args, "--calib", str(bench["dir"] / "guess.json"), "--out", str(out)])
    assert code == 0, capsys.readouterr().err
    port = Calibration.load(out).port
    assert port is not None
    assert abs(port.distance_m - 0.02) < 0.001
    assert "distance_m" in capsys.readouterr().out


def test_without_the_tilt_the_normal_is_kept_and_the_fit_is_worse(bench: dict[str, Any]) -> None:
    tilted = calibrate_port(_images(bench), BOARD, bench["guess"])
    square = calibrate_port(_images(bench), BOARD, bench["guess"], fit_tilt=False, max_distance_sigma_m=0.01)
    assert square.port.normal_cam == (0.0, 0.0, 1.0)
    assert square.rms_px > 2.0 * tilted.rms_px  # the true port is tilted 2 deg


def test_refusals(bench: dict[str, Any], tmp_path: Path, capsys: Any) -> None:
    with pytest.raises(PortCalibrationError, match="no `port`"):
        calibrate_port(_images(bench), BOARD, paper_calibration())
    with pytest.raises(PortCalibrationError, match="found in only 2 of 2"):
        calibrate_port(_images(bench, 2), BOARD, bench["guess"])
    with pytest.raises(PortCalibrationError, match="not fixed by these views"):
        calibrate_port(_images(bench), BOARD, bench["guess"], max_distance_sigma_m=1e-7)
    out = tmp_path / "refused.json"
    args = ["calibrate", "port", *map(str, bench["paths"][:2]), "--board", "9x6", "--square-m", "0.025"]
    assert main([*args, "--calib", str(bench["dir"] / "guess.json"), "--out", str(out)]) == 2
    assert "calibration refused, no output written" in capsys.readouterr().err
    assert not out.exists()
