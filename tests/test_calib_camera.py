"""Camera intrinsics from simulated checkerboard views (distorted wide lens), the board pose, and refusals."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from lrsensor.calib import BoardSpec, estimate_board_pose
from lrsensor.calib.planefit import normal_angle_deg
from lrsensor.calibration import Calibration
from lrsensor.cli import main
from lrsensor.errors import CalibrationFitError
from lrsensor.sim import (
    Checkerboard,
    checkerboard_wall_scene,
    distorted_calibration,
    scale_calibration,
    tilted_calibration,
    wall_scene,
)

W, H = 960, 540
#: (wall normal, distance m, board centre offset on the wall (u, v) m)
VIEWS = [
    ((1, 0, 0), 0.5, (0.0, 0.0)),
    ((1, 0.35, 0), 0.6, (0.25, -0.1)),
    ((1, -0.35, 0), 0.6, (-0.25, 0.1)),
    ((1, 0, 0.35), 0.55, (0.2, 0.1)),
    ((1, 0, -0.35), 0.55, (-0.2, -0.1)),
    ((1, 0.25, 0.25), 0.5, (0.3, 0.1)),
    ((1, -0.25, 0.2), 0.5, (-0.3, -0.1)),
]


@pytest.fixture(scope="module")
def boards(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    d = tmp_path_factory.mktemp("boards")
    true = scale_calibration(distorted_calibration(tilted_calibration()), W, H)
    paths = []
    for i, (n, dist, (ou, ov)) in enumerate(VIEWS):
        board = Checkerboard(9, 6, 0.04, offset_u_m=ou, offset_v_m=ov)
        img = checkerboard_wall_scene(dist, n, board, calibration=true, width=W, height=H).render(seed=i).image
        p = d / f"board_{i}.png"
        cv2.imwrite(str(p), img)
        paths.append(p)
    plain = d / "no_board.png"
    cv2.imwrite(str(plain), wall_scene(0.5, calibration=true, width=W, height=H).render(seed=9).image)
    true.save(d / "true.json")
    return {"dir": d, "true": true, "paths": paths, "plain": plain}


def test_calibrate_camera_cli_recovers_intrinsics(boards: dict[str, Any], tmp_path: Path, capsys: Any) -> None:
    out = tmp_path / "cam.json"
    args = ["calibrate", "camera", *map(str, boards["paths"]), str(boards["plain"])]
    code = main([*args, "--board", "9x6", "--square-m", "0.04", "--out", str(out)])
    text = capsys.readouterr().out
    assert code == 0
    assert "RMS reprojection error" in text
    assert "board not found in" in text
    assert "no_board.png" in text
    cam, truth = Calibration.load(out).camera, boards["true"].camera
    assert cam.fx == pytest.approx(truth.fx, rel=0.01)
    assert cam.fy == pytest.approx(truth.fy, rel=0.01)
    assert cam.cx == pytest.approx(truth.cx, abs=2.0)
    assert cam.cy == pytest.approx(truth.cy, abs=2.0)
    assert cam.distortion[0] == pytest.approx(truth.distortion[0], abs=0.01)
    # Reprojecting through the estimated model matches the true one within a fraction of a pixel.
    pts = np.array([[x, y, 1.0] for x in np.linspace(-1.2, 1.2, 7) for y in np.linspace(-0.6, 0.6, 5)])
    assert np.abs(cam.project(pts) - truth.project(pts)).max() < 1.0
    cal = Calibration.load(out)
    assert cal.metadata["camera_calibration"]["images_without_board"] == [str(boards["plain"])]
    assert len(cal.lasers) == 2


def test_calibrate_camera_keeps_lasers_of_calib(boards: dict[str, Any], tmp_path: Path) -> None:
    out = tmp_path / "cam.json"
    args = ["calibrate", "camera", *map(str, boards["paths"]), "--board", "9x6", "--square-m", "0.04"]
    assert main([*args, "--calib", str(boards["dir"] / "true.json"), "--out", str(out)]) == 0
    assert Calibration.load(out).lasers == boards["true"].lasers


def test_too_few_boards_is_refused(boards: dict[str, Any], tmp_path: Path, capsys: Any) -> None:
    out = tmp_path / "cam.json"
    args = ["calibrate", "camera", *map(str, boards["paths"][:2]), str(boards["plain"])]
    code = main([*args, "--board", "9x6", "--square-m", "0.04", "--out", str(out)])
    err = capsys.readouterr()
    assert code == 2
    assert not out.exists()
    assert "found in only 2 of 3 images, need >= 3" in err.err
    assert "no_board.png" in err.err


def test_camera_rms_above_threshold_is_refused(boards: dict[str, Any], tmp_path: Path, capsys: Any) -> None:
    out = tmp_path / "cam.json"
    args = ["calibrate", "camera", *map(str, boards["paths"]), "--board", "9x6", "--square-m", "0.04"]
    assert main([*args, "--max-rms-px", "0.001", "--out", str(out)]) == 2
    assert "RMS reprojection error" in capsys.readouterr().err
    assert not out.exists()


def test_board_pose_gives_the_wall_plane(boards: dict[str, Any]) -> None:
    true = boards["true"]
    for i in (0, 1, 5):
        n, dist, _ = VIEWS[i]
        img = cv2.imread(str(boards["paths"][i]))
        pose = estimate_board_pose(img, true.camera, BoardSpec(9, 6, 0.04))
        plane = pose.plane_body(true)
        n_true = np.asarray(n, float) / np.linalg.norm(n)
        assert normal_angle_deg(plane.normal, n_true) < 0.2
        assert plane.offset == pytest.approx(dist, abs=0.001)
        assert pose.reprojection_rms_px < 0.3


def test_board_spec_parsing_and_missing_board(boards: dict[str, Any]) -> None:
    spec = BoardSpec.parse("9x6", 0.04)
    assert spec.pattern_size == (9, 6)
    assert spec.object_points().shape == (54, 3)
    with pytest.raises(CalibrationFitError, match="COLSxROWS"):
        BoardSpec.parse("nine by six", 0.04)
    with pytest.raises(CalibrationFitError, match="square size"):
        BoardSpec(9, 6, 0.0)
    img = cv2.imread(str(boards["plain"]))
    with pytest.raises(CalibrationFitError, match="not found"):
        estimate_board_pose(img, boards["true"].camera, spec, name="no_board.png")
