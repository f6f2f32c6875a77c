"""A robot whose clock is minutes off the base station's (issue 30, item 4).

Two ROV processes on loopback, one 5 minutes ahead of the base station, one 5 minutes behind
(``LRS_CLOCK_OFFSET_S``, :data:`services.delivery.CLOCK_OFFSET_ENV`: their publication and status stamps),
each replaying a dive whose capture times are on its own clock. Nothing the delivery does is keyed on the
clocks agreeing: every cloud is delivered, acknowledged (with the map on: taken in by the map) and counted
once; the base station reports each robot's offset, measured from the arrival of its status messages, and its
latency and transit figures are on its own clock (positive, seconds, not minus five minutes).
"""

from __future__ import annotations

import json
import os
import signal
import time
from pathlib import Path
from typing import Any

import pytest

zenoh = pytest.importorskip("zenoh")

from procs import Proc, lrsensor_cmd  # noqa: E402
from waiting import wait_until  # noqa: E402

from services.delivery import CLOCK_OFFSET_ENV  # noqa: E402
from services.ledger import CLOCK_OFFSET_MIN_S, RobotRecord  # noqa: E402
from services.testnet import free_port  # noqa: E402

N_FRAMES = 30
OFFSETS = {"rov1": 300.0, "rov2": -300.0}


def _status(port: int, fleet: str) -> dict[str, Any] | None:
    conf = {
        "mode": "client",
        "connect": {"endpoints": [f"tcp/127.0.0.1:{port}"], "timeout_ms": 10000},
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
    }
    with zenoh.open(zenoh.Config.from_json5(json.dumps(conf))) as s:
        for reply in s.get(f"lrs/{fleet}/base/status", timeout=3.0):
            if reply.ok is not None:
                data: dict[str, Any] = json.loads(reply.ok.payload.to_bytes())
                return data
    return None


def test_the_offset_is_the_smallest_arrival_lag_and_corrected_only_beyond_the_threshold() -> None:
    rec = RobotRecord()
    assert rec.clock_offset_ns() is None
    assert rec.clock_correction_ns() == 0
    for lag_s in (-299.9, -299.5, -290.0):  # a robot 300 s ahead; transits 0.1 s, 0.5 s, a late one 10 s
        rec.clock_lags.append(int(lag_s * 1e9))
    assert rec.clock_offset_ns() == pytest.approx(299.9e9)
    assert rec.clock_correction_ns() == rec.clock_offset_ns()
    assert rec.to_json()["clock_offset_s"] == pytest.approx(299.9)
    assert rec.to_json()["clock_corrected"] is True
    rec.cloud_lags.append(int(-299.95e9))  # a cloud that crossed faster than any status message
    assert rec.clock_offset_ns() == pytest.approx(299.95e9)
    synced = RobotRecord()
    synced.clock_lags.append(int(0.2e9))  # in step: the lag is the transit; nothing is shifted
    assert abs(synced.clock_offset_ns() or 0) < CLOCK_OFFSET_MIN_S * 1e9
    assert synced.clock_correction_ns() == 0
    assert synced.to_json()["clock_corrected"] is False


def test_the_rov_stamps_on_its_own_clock() -> None:
    """The environment variable shifts what the ROV stamps (checked in a child process: it is read at import)."""
    import subprocess
    import sys

    code = (
        "import time; from services.delivery import wall_clock_ns; "
        "print(round((wall_clock_ns() - time.time_ns()) / 1e9))"
    )
    env = dict(os.environ, **{CLOCK_OFFSET_ENV: "-300"})
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "-300"


@pytest.mark.slow
def test_robots_minutes_off_the_base_clock_deliver_everything_once(tmp_path: Path, procs: list[Proc]) -> None:
    from lrsensor.sim.dive import record_dive

    fleet, port = "ck", free_port()
    base = Proc(
        lrsensor_cmd("base", "--fleet", fleet, "--listen", f"tcp/127.0.0.1:{port}", "--state", str(tmp_path / "state"),
                     "--map", "auto", "--status-every-s", "0"),
        tmp_path / "base.log",
    )  # fmt: skip
    procs.append(base)
    for i, (robot, offset) in enumerate(OFFSETS.items()):
        # recorded on the robot's own clock: the capture times are minutes off the base station's too
        record_dive(
            tmp_path / f"dive-{robot}", robot=robot, robot_index=i, n_robots=2, duration_s=N_FRAMES / 10.0,
            rate_hz=10.0, width=640, height=360, seed=3 + i, t0_ns=time.time_ns() + int(offset * 1e9),
        )  # fmt: skip
    assert wait_until(lambda: _status(port, fleet) is not None, 30), base.output()
    rovs = {}
    for robot, offset in OFFSETS.items():
        dive = tmp_path / f"dive-{robot}"
        args = lrsensor_cmd(
            "rov", "--fleet", fleet, "--robot", robot, "--connect", f"tcp/127.0.0.1:{port}", "--source", str(dive),
            "--imu", f"csv:{dive / 'imu.csv'}", "--calib", str(dive / "calib.json"), "--rate", "10",
            "--ack-timeout-s", "60", "--outbox", str(tmp_path / f"outbox-{robot}"),
        )  # fmt: skip
        os.environ[CLOCK_OFFSET_ENV] = f"{offset:g}"
        try:
            rovs[robot] = Proc(args, tmp_path / f"{robot}.log")
        finally:
            del os.environ[CLOCK_OFFSET_ENV]
        procs.append(rovs[robot])
    for robot, rov in rovs.items():
        assert rov.wait(180) == 0, rov.output()
        assert f"rov {robot}: frames {N_FRAMES}, published {N_FRAMES}" in rov.output(), rov.output()
        assert "delivery confirmed" in rov.output(), rov.output()
    st = _status(port, fleet)
    assert st is not None
    for robot, offset in OFFSETS.items():
        r = st["robots"][robot]
        # delivered, acknowledged (with the map: taken in by it) and counted once
        assert (r["received"], r["acked"], r["missed"], r["duplicates"]) == (N_FRAMES, N_FRAMES, 0, 0), r
        assert r["clock_offset_s"] == pytest.approx(offset, abs=3.0), r  # measured and reported
        assert r["clock_corrected"] is True, r
    ingest = st["ingest"]
    for figure in ("transit_ms", "latency_ms"):
        p50, p99 = ingest[figure]["p50"], ingest[figure]["p99"]
        assert p50 is not None, ingest
        assert 0.0 <= p50 <= p99 < 120_000.0, ingest  # on the base's clock: not minus (or plus) five minutes
    assert ingest["clock_suspect"] <= 2, ingest  # at most a cloud or two before a robot's first status
    assert base.stop(signal.SIGTERM) == 0, base.output()
