"""The calibration file: CONVENTIONS format, round trip, validation errors that name the key."""

from __future__ import annotations

import copy
import json
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from lrsensor.calibration import Calibration, LaserPlane
from lrsensor.errors import CalibrationFileError, LrsensorError

CONVENTIONS_EXAMPLE: dict[str, Any] = {
    "camera": {
        "width": 1920,
        "height": 1080,
        "fx": 554.28,
        "fy": 554.28,
        "cx": 959.5,
        "cy": 539.5,
        "distortion": [0.0, 0.0, 0.0, 0.0, 0.0],
    },
    "R_cam_from_body": [[0, 1, 0], [0, 0, 1], [1, 0, 0]],
    "t_cam_from_body": [0, 0, 0],
    "lasers": [
        {"name": "top", "point": [0, 0, -0.05], "normal": [0, 0, 1]},
        {"name": "bottom", "point": [0, 0, 0.05], "normal": [0, 0, 1]},
    ],
}


def test_reads_conventions_example(tmp_path: Path) -> None:
    path = tmp_path / "calib.json"
    path.write_text(json.dumps(CONVENTIONS_EXAMPLE))
    cal = Calibration.load(path)
    assert cal.camera.fx == 554.28
    assert [l.name for l in cal.lasers] == ["top", "bottom"]
    assert cal.lasers[0].point == (0.0, 0.0, -0.05)
    np.testing.assert_allclose(cal.camera_center_body, [0, 0, 0])
    assert cal.lasers == Calibration.paper(0.1).lasers
    assert cal.camera.fx == pytest.approx(Calibration.paper(0.1).camera.fx, abs=0.01)


def test_save_load_round_trip(tmp_path: Path) -> None:
    cal = Calibration.paper(0.1).with_lasers(
        [
            LaserPlane.make("top", (0.01, 0, -0.05), (0.02, 0.0, 1.0)),
            LaserPlane.make("bottom", (0, 0, 0.05), (0, 0.03, 1)),
        ],
        metadata={"residuals": {"top": 0.1}},
    )
    path = tmp_path / "sub" / "calib.json"
    cal.save(path)
    again = Calibration.load(path)
    assert again == cal
    assert again.metadata["residuals"] == {"top": 0.1}
    data = json.loads(path.read_text())
    assert data["format"] == "lrsensor-calibration"
    assert set(data) >= {"camera", "R_cam_from_body", "t_cam_from_body", "lasers"}


def test_unknown_keys_are_accepted() -> None:
    data = copy.deepcopy(CONVENTIONS_EXAMPLE)
    data["format"] = "other"
    data["whatever"] = {"x": 1}
    data["lasers"][0]["colour"] = "green"
    Calibration.from_dict(data)


def test_normal_is_normalised() -> None:
    data = copy.deepcopy(CONVENTIONS_EXAMPLE)
    data["lasers"][1]["normal"] = [0, 0.0174524, 0.9998477]
    cal = Calibration.from_dict(data)
    assert np.linalg.norm(cal.lasers[1].normal_body) == pytest.approx(1.0, abs=1e-12)


def _drop(d: dict[str, Any], path: list[Any]) -> None:
    for k in path[:-1]:
        d = d[k]
    del d[path[-1]]


def _set(d: dict[str, Any], path: list[Any], value: Any) -> None:
    for k in path[:-1]:
        d = d[k]
    d[path[-1]] = value


@pytest.mark.parametrize(
    ("path", "expect"),
    [
        (["camera"], "camera"),
        (["camera", "fx"], "camera.fx"),
        (["camera", "width"], "camera.width"),
        (["R_cam_from_body"], "R_cam_from_body"),
        (["t_cam_from_body"], "t_cam_from_body"),
        (["lasers"], "lasers"),
        (["lasers", 1, "normal"], r"lasers\[1\].normal"),
        (["lasers", 0, "point"], r"lasers\[0\].point"),
    ],
)
def test_missing_key_is_named(path: list[Any], expect: str) -> None:
    data = copy.deepcopy(CONVENTIONS_EXAMPLE)
    _drop(data, path)
    with pytest.raises(CalibrationFileError, match=expect):
        Calibration.from_dict(data)


@pytest.mark.parametrize(
    ("path", "value", "expect"),
    [
        (["camera", "fx"], float("nan"), "camera.fx"),
        (["camera", "fx"], -5.0, "camera.fx"),
        (["camera", "cy"], "539", "camera.cy"),
        (["camera", "distortion"], [0, 0, 0], "camera.distortion"),
        (["lasers", 0, "normal"], [0, 0, 0], r"lasers\[0\].normal"),
        (["lasers", 1, "point"], [0, float("inf"), 0], r"lasers\[1\].point\[1\]"),
        (["R_cam_from_body"], [[1, 0, 0], [0, 1, 0], [0, 0, 2]], "R_cam_from_body"),
        (["camera", "width"], 10.5, "camera.width"),
    ],
)
def test_bad_value_is_named(path: list[Any], value: Any, expect: str) -> None:
    data = copy.deepcopy(CONVENTIONS_EXAMPLE)
    _set(data, path, value)
    with pytest.raises(CalibrationFileError, match=expect):
        Calibration.from_dict(data)


def test_non_finite_json_literal_rejected() -> None:
    text = json.dumps(CONVENTIONS_EXAMPLE).replace('"fx": 554.28', '"fx": NaN')
    with pytest.raises(CalibrationFileError, match="NaN"):
        Calibration.from_json(text)


def test_unreadable_and_garbage(tmp_path: Path) -> None:
    with pytest.raises(CalibrationFileError, match="cannot read"):
        Calibration.load(tmp_path / "missing.json")
    bad = tmp_path / "bad.json"
    bad.write_bytes(b"\x00\xff{not json")
    with pytest.raises(CalibrationFileError, match="not valid JSON"):
        Calibration.load(bad)
    with pytest.raises(CalibrationFileError, match="top level"):
        Calibration.from_json("[1, 2]")
    assert issubclass(CalibrationFileError, LrsensorError)


def test_port_round_trip_and_absence(tmp_path: Path) -> None:
    from lrsensor.port import FlatPort

    port = FlatPort((0.0349, -0.01, 0.9993), distance_m=0.021, thickness_m=0.0085, n_glass=1.5, n_water=1.339)
    cal = replace(Calibration.paper(0.1), port=port)
    path = tmp_path / "calib.json"
    cal.save(path)
    again = Calibration.load(path)
    assert again == cal
    assert again.port == port
    assert json.loads(path.read_text())["port"]["type"] == "flat"
    assert "port" not in Calibration.paper(0.1).to_dict()  # no port: the file is written as before
    assert Calibration.from_dict(CONVENTIONS_EXAMPLE).port is None
    data = copy.deepcopy(CONVENTIONS_EXAMPLE)
    data["port"] = {"type": "none"}
    assert Calibration.from_dict(data).port is None
    data["port"] = {**port.to_dict(), "thickness_m": -0.001}
    with pytest.raises(CalibrationFileError, match=r"port\.thickness_m"):
        Calibration.from_dict(data)
