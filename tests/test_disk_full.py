"""The base station's disk fills up (issue 30, item 4): nothing is acknowledged that is not stored, the base keeps
serving, and once space returns everything received is stored and acknowledged, nothing lost.

The state folder lies on a real 8 MiB tmpfs that the test fills with a file until the kernel says ENOSPC, so the
base's own writes (the map's state, then fleet.json) fail as they would on a full card. Needs root (mount).
"""

from __future__ import annotations

import errno
import json
import os
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from waiting import wait_until

from lrsensor.calibration import Calibration
from services.imu import CsvImu
from services.simsource import record_sim_dive
from services.sources import FolderSource
from services.testnet import TestNetwork

N_FRAMES = 10
FULL_S = 8.0  # several checkpoint periods (2 s) with the disk full; the long version holds it a minute


@pytest.fixture
def small_disk(tmp_path: Path) -> Iterator[Path]:
    if os.geteuid() != 0:
        pytest.skip("mounting a tmpfs needs root")
    mnt = tmp_path / "disk"
    mnt.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=8m", "tmpfs", str(mnt)], capture_output=True).returncode:
        pytest.skip("cannot mount a tmpfs here")
    try:
        yield mnt
    finally:
        subprocess.run(["umount", "-l", str(mnt)], capture_output=True)


def fill(disk: Path) -> Path:
    """Write a file until the kernel refuses with ENOSPC; returns it."""
    filler = disk / "filler"
    chunk = b"\0" * 65536
    with filler.open("wb", buffering=0) as f:  # unbuffered: nothing left to flush at close
        while True:
            try:
                f.write(chunk)
            except OSError as err:
                if err.errno != errno.ENOSPC:
                    raise
                return filler


def acked(net: TestNetwork, robot: str) -> list[list[int]]:
    for reply in net.session().get(net.keys.base_acks(robot), timeout=2.0):
        if reply.ok is not None:
            ranges: list[list[int]] = json.loads(reply.ok.payload.to_bytes())["ranges"]
            return ranges
    return []


@pytest.mark.parametrize(
    "full_s", [pytest.param(FULL_S, id="8s"), pytest.param(60.0, id="1min", marks=pytest.mark.long)]
)
def test_a_full_disk_acknowledges_nothing_unstored_and_loses_nothing(
    small_disk: Path, tmp_path: Path, full_s: float
) -> None:
    dive = record_sim_dive(tmp_path / "rov1", "rov1", n_frames=N_FRAMES, seed=7, clean_water=True)
    state = small_disk / "state"
    with TestNetwork("full") as net:
        base = net.start_base(state, map_mode="on")
        filler = fill(small_disk)
        h = net.start_rov(
            "rov1", FolderSource(dive), CsvImu(dive / "imu.csv"), Calibration.load(dive / "calib.json"),
            ack_timeout_s=60.0,
        )  # fmt: skip
        assert wait_until(lambda: base.status()["robots"].get("rov1", {}).get("received") == N_FRAMES, 30.0)
        t_full = time.monotonic()
        seen: list[Any] = []
        while time.monotonic() - t_full < full_s:  # the base serves, and acknowledges nothing it could not store
            seen.append(acked(net, "rov1"))
            assert base.status()["robots"]["rov1"]["received"] == N_FRAMES
            time.sleep(0.5)
        assert all(r == [] for r in seen), seen
        filler.unlink()  # space returns
        assert wait_until(lambda: acked(net, "rov1") == [[0, N_FRAMES - 1]], 30.0)
        assert h.join(60)
        assert h.result is not None
        assert h.result.delivered
        status = base.status()
    robot = status["robots"]["rov1"]
    assert (robot["received"], robot["missed"], robot["rejected"]) == (N_FRAMES, 0, 0)
    saved = json.loads((state / "fleet.json").read_text())["robots"]["rov1"]
    assert saved["acked"] == [[0, N_FRAMES - 1]]
    assert saved["ranges"] == [[0, N_FRAMES - 1]]
