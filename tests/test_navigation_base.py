"""The base station's navigation over Zenoh (issue 27): a depth-only robot's clouds are placed with the
estimated pose once its launch fix started the estimator; the corrected pose is published and served on
``<root>/<robot>/nav``; the status says per robot what the scans constrain; ``navigation=False`` trusts the
raw poses as before."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
from waiting import wait_until

from lrsensor.calibration import Calibration
from lrsensor.sim.dive import record_dive
from services.imu import CsvImu
from services.sources import FolderSource
from services.testnet import TestNetwork

N_FRAMES = 6
WAIT_S = 10.0


@pytest.fixture(scope="module")
def depth_only_dive(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("nav") / "rov1"
    record_dive(
        out,
        robot="rov1",
        duration_s=N_FRAMES / 5.0,
        rate_hz=5.0,
        width=320,
        height=180,
        seed=3,
        navigation="depth-only",
    )
    return out


def _run(folder: Path, navigation: bool) -> tuple[dict[str, Any], list[dict[str, Any]], list[Any]]:
    got: list[dict[str, Any]] = []
    with TestNetwork("navnet") as net:
        base = net.start_base(None, map_mode="on", navigation=navigation)
        session = net.session()
        sub = session.declare_subscriber(net.keys.nav("rov1"), lambda s: got.append(json.loads(s.payload.to_bytes())))
        imu = CsvImu(folder / "imu.csv")
        h = net.start_rov("rov1", FolderSource(folder), imu, Calibration.load(folder / "calib.json"))
        assert h.join(60)
        assert h.result is not None
        assert h.result.published == N_FRAMES
        assert wait_until(lambda: base.status()["robots"].get("rov1", {}).get("received") == N_FRAMES, WAIT_S)
        base.flush_map()
        if navigation:
            assert wait_until(lambda: len(got) >= 1, WAIT_S)
        replies = list(session.get(net.keys.all_nav, timeout=2.0))
        status = base.status()
        sub.undeclare()
    return status, got, replies


def test_navigation_places_a_depth_only_robot_and_publishes_its_pose(depth_only_dive: Path) -> None:
    status, got, replies = _run(depth_only_dive, navigation=True)
    msg = got[-1]
    for key in (
        "t_ns",
        "north_m",
        "east_m",
        "down_m",
        "roll_deg",
        "pitch_deg",
        "yaw_deg",
        "north_m_std",
        "east_m_std",
        "yaw_deg_std",
        "constrained",
    ):
        assert key in msg, key
    assert msg["robot"] == "rov1"
    assert msg["north_m"] is not None  # the launch fix started it
    truth = json.loads((depth_only_dive / "truth.json").read_text())
    # the base's two ingest threads may map a later cloud first: compare the first placed one with its frame
    placed = next(m for m in got if m["north_m"] is not None)
    frame = next(f for f in truth["frames"] if f["t_ns"] == placed["t_ns"])
    assert abs(placed["north_m"] - frame["pose"]["north_m"]) < 0.1
    answers = [json.loads(r.ok.payload.to_bytes()) for r in replies if r.ok is not None]
    assert [a["robot"] for a in answers] == ["rov1"]
    robot = status["robots"]["rov1"]
    nav = robot["nav"]
    assert nav["placed"] >= 1  # clouds without a fix, placed with the estimated position
    assert nav["placed"] + nav["unplaced"] == N_FRAMES
    assert robot["unplaced"] == nav["unplaced"]
    assert nav["position"] in {"constrained", "partly", "unconstrained", "lost"}
    # one pinned direction: the free one's bearing is said, else nothing
    assert (nav["degenerate"] is not None) == (nav["position"] == "partly")
    assert "degenerate" in answers[0]
    assert status["map"]["navigation"] is True
    assert status["map"]["clouds"] == nav["placed"]


def test_without_navigation_clouds_without_a_fix_stay_unplaced(depth_only_dive: Path) -> None:
    status, got, replies = _run(depth_only_dive, navigation=False)
    assert got == []
    assert all(r.ok is None for r in replies)
    robot = status["robots"]["rov1"]
    assert "nav" not in robot
    assert status["map"]["navigation"] is False
    assert robot["unplaced"] >= N_FRAMES - 1  # only the launch frame has a fix
    assert status["map"]["clouds"] == N_FRAMES - robot["unplaced"]
