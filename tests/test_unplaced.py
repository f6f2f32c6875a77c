"""A robot whose pose source has attitude and depth only (issue 27): its clouds travel with north/east null,
the ROV counts them, and the base station counts them as unplaced instead of mapping them at 0, 0."""

from __future__ import annotations

import csv
from pathlib import Path

import pytest
from waiting import wait_until

from lrsensor.calibration import Calibration
from services.imu import CsvImu
from services.posetrack import has_fix
from services.simsource import record_sim_dive
from services.sources import FolderSource
from services.testnet import TestNetwork
from services.wire import CloudMsg, StripeMsg, decode_cloud

N_FRAMES = 6
WAIT_S = 10.0


@pytest.fixture(scope="module")
def depth_only_dive(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A recorded dive whose IMU log keeps the launch fix (first row) and drops every other position."""
    folder = record_sim_dive(
        tmp_path_factory.mktemp("depth-only") / "rov1", "rov1", n_frames=N_FRAMES, clean_water=True
    )
    path = folder / "imu.csv"
    rows = list(csv.reader(path.open(newline="")))
    header = rows[0]
    i_n, i_e = header.index("north_m"), header.index("east_m")
    for row in rows[2:]:
        row[i_n] = row[i_e] = ""
    with path.open("w", newline="") as fh:
        csv.writer(fh).writerows(rows)
    return folder


def test_clouds_without_a_fix_are_published_null_and_counted_unplaced(depth_only_dive: Path) -> None:
    folder = depth_only_dive
    imu = CsvImu(folder / "imu.csv")
    assert imu.rejected == 0  # rows without a position are samples, not malformed rows
    got: list[CloudMsg | StripeMsg] = []
    with TestNetwork("nofix") as net:
        # lost: the map's side of "unplaced" (the default, graph, may place the robot's clouds by its pose graph)
        base = net.start_base(None, map_mode="on", no_fix="lost")
        sub = net.session().declare_subscriber(
            net.keys.cloud("rov1"), lambda smp: got.append(decode_cloud(smp.payload.to_bytes()))
        )
        h = net.start_rov("rov1", FolderSource(folder), imu, Calibration.load(folder / "calib.json"))
        assert h.join(60)
        assert h.result is not None
        assert (h.result.frames, h.result.published, h.result.skipped) == (N_FRAMES, N_FRAMES, 0)
        assert h.result.unplaced == N_FRAMES
        assert "no horizontal fix 6" in h.result.summary("rov1")
        assert wait_until(lambda: base.status()["robots"].get("rov1", {}).get("unplaced") == N_FRAMES, WAIT_S)
        # the ROV's own last status message reaches the base a moment after its last cloud
        assert wait_until(
            lambda: base.status()["robots"]["rov1"].get("reported", {}).get("unplaced") == N_FRAMES, WAIT_S
        )
        base.flush_map()
        status = base.status()
        sub.undeclare()
    assert len(got) == N_FRAMES
    assert all(not has_fix(m.pose) for m in got)
    robot = status["robots"]["rov1"]
    assert (robot["received"], robot["unplaced"]) == (N_FRAMES, N_FRAMES)
    assert robot["reported"]["unplaced"] == N_FRAMES  # the ROV's own status says it too
    assert (status["map"]["unplaced"], status["map"]["clouds"], status["map"]["planes"]) == (N_FRAMES, 0, 0)
