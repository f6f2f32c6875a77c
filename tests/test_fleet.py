"""Multi-process fleet on loopback: ``lrsensor base`` and two ``lrsensor rov`` processes replaying recorded
dives, watched from an independent Zenoh session and from zenoh-cli; clean exits on SIGTERM/SIGINT.
"""

from __future__ import annotations

import json
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import pytest
import zenoh
from procs import Proc, client_session, lrsensor_cmd
from waiting import wait_until

from lrsensor.calibration import Calibration
from services.simsource import record_sim_dive
from services.testnet import free_port
from services.wire import CalibMsg

pytestmark = pytest.mark.slow

N_FRAMES = 12
FLEET = "fp"
WAIT_S = 20.0  # how long a test waits for a service or a message unless it says otherwise


@pytest.fixture(scope="module")
def dives(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("fleet-dives")
    return {r: record_sim_dive(root / r, r, n_frames=N_FRAMES, seed=5) for r in ("rov1", "rov2")}


def get_status(session: Any) -> dict[str, Any] | None:
    for reply in session.get(f"lrs/{FLEET}/base/status", timeout=2.0):
        if reply.ok is not None:
            data: dict[str, Any] = json.loads(reply.ok.payload.to_bytes())
            return data
    return None


class Membership:
    """Liveliness events of the fleet, seen from the test's own session."""

    def __init__(self, session: Any) -> None:
        self.events: list[tuple[str, str]] = []
        self.lock = threading.Lock()
        self.sub = session.liveliness().declare_subscriber(f"lrs/{FLEET}/*/alive", self._on, history=True)

    def _on(self, sample: Any) -> None:
        robot = str(sample.key_expr).split("/")[2]
        kind = "joined" if sample.kind == zenoh.SampleKind.PUT else "left"
        with self.lock:
            self.events.append((robot, kind))

    def has(self, robot: str, kind: str) -> bool:
        with self.lock:
            return (robot, kind) in self.events


def test_base_and_two_rov_processes(dives: dict[str, Path], tmp_path: Path, procs: list[Proc]) -> None:
    port = free_port()
    state = tmp_path / "state"
    (state / "calib").mkdir(parents=True)
    shutil.copy(dives["rov2"] / "calib.json", state / "calib" / "rov2.json")  # rov2 fetches it from the base
    base = Proc(
        lrsensor_cmd(
            "base", "--fleet", FLEET, "--listen", f"tcp/127.0.0.1:{port}", "--state", str(state), "--map", "off"
        ),
        tmp_path / "base.log",
    )
    procs.append(base)
    with client_session(port) as session:
        assert wait_until(lambda: get_status(session) is not None, WAIT_S), base.output()
        members = Membership(session)
        rovs = {}
        for robot, folder in dives.items():
            args = ["rov", "--fleet", FLEET, "--robot", robot, "--connect", f"tcp/127.0.0.1:{port}"]
            args += ["--source", str(folder), "--imu", f"csv:{folder / 'imu.csv'}", "--rate", "3"]
            if robot == "rov1":
                args += ["--calib", str(folder / "calib.json")]
            rovs[robot] = Proc(lrsensor_cmd(*args), tmp_path / f"{robot}.log")
            procs.append(rovs[robot])

        # liveliness shows both robots, and each answers its calibration queryable while it runs
        for robot, folder in dives.items():
            assert wait_until(lambda r=robot: members.has(r, "joined"), WAIT_S), rovs[robot].output()
            replies = [r.ok for r in session.get(f"lrs/{FLEET}/{robot}/calib", timeout=5.0) if r.ok is not None]
            assert len(replies) == 1, f"{robot}: calibration queryable did not answer"
            msg = CalibMsg.from_bytes(replies[0].payload.to_bytes())
            assert msg.robot == robot
            assert msg.calibration == Calibration.load(folder / "calib.json")

        # a finite source ends the run with exit code 0 once every cloud is delivered
        for robot, p in rovs.items():
            assert p.p.wait(90) == 0, p.output()
            out = p.output()
            assert f"rov {robot}: frames {N_FRAMES}, published {N_FRAMES}" in out, out
            assert "delivery confirmed" in out, out
        assert "calibration of rov2 fetched" in rovs["rov2"].output()

        # ... and liveliness shows their departure
        for robot in dives:
            assert wait_until(lambda r=robot: members.has(r, "left"), WAIT_S)

        # every cloud published arrived, counted by sequence number
        status = get_status(session)
        assert status is not None
        for robot in dives:
            st = status["robots"][robot]
            assert (st["received"], st["missed"], st["rejected"], st["last_seq"]) == (N_FRAMES, 0, 0, N_FRAMES - 1)
            assert st["alive"] is False

        # an independent client (zenoh-cli) reads the status
        zenoh_cli = shutil.which("zenoh", path=str(Path(sys.executable).parent)) or shutil.which("zenoh")
        assert zenoh_cli, "zenoh-cli is not installed"
        cli = subprocess.run(
            [
                zenoh_cli,
                "--mode",
                "client",
                "--connect",
                f"tcp/127.0.0.1:{port}",
                "get",
                "-s",
                f"lrs/{FLEET}/base/status",
                "--decoder",
                "json",
            ],
            capture_output=True,
            text=True,
            timeout=60,
            check=False,
        )
        assert cli.returncode == 0, cli.stderr
        line = next(ln for ln in cli.stdout.splitlines() if ln.strip().startswith("{"))
        cli_status = json.loads(line)
        assert {r: cli_status["robots"][r]["received"] for r in dives} == {"rov1": N_FRAMES, "rov2": N_FRAMES}
        members.sub.undeclare()

    # SIGTERM: the base closes its session and exits 0 within a few seconds, counters persisted
    t0 = time.monotonic()
    assert base.stop(signal.SIGTERM, timeout_s=10) == 0, base.output()
    assert time.monotonic() - t0 < 10
    saved = json.loads((state / "fleet.json").read_text())
    assert saved["robots"]["rov1"]["ranges"] == [[0, N_FRAMES - 1]]


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_entry_points_close_on_signals(tmp_path: Path, procs: list[Proc], sig: int) -> None:
    port = free_port()
    base = Proc(
        lrsensor_cmd("base", "--fleet", FLEET, "--listen", f"tcp/127.0.0.1:{port}", "--map", "off"),
        tmp_path / "base.log",
    )
    procs.append(base)
    with client_session(port) as session:
        assert wait_until(lambda: get_status(session) is not None, WAIT_S), base.output()
        rov = Proc(
            lrsensor_cmd(
                "rov",
                "--fleet",
                FLEET,
                "--robot",
                "rov3",
                "--connect",
                f"tcp/127.0.0.1:{port}",
                "--source",
                "sim",
                "--sim-frames",
                "3000",
                "--sim-size",
                "320x180",
                "--rate",
                "5",
            ),
            tmp_path / "rov.log",
        )
        procs.append(rov)
        assert wait_until(
            lambda: (get_status(session) or {}).get("robots", {}).get("rov3", {}).get("received", 0) >= 2, 60
        ), rov.output()
        t0 = time.monotonic()
        assert rov.stop(sig, timeout_s=10) == 0, rov.output()
        assert time.monotonic() - t0 < 8  # "within a few seconds", with margin for a loaded machine
        assert "rov rov3: frames" in rov.output()
        assert wait_until(lambda: (get_status(session) or {})["robots"]["rov3"]["alive"] is False, 10)
    t0 = time.monotonic()
    assert base.stop(sig, timeout_s=10) == 0, base.output()
    assert time.monotonic() - t0 < 8
    assert "base station stopped" in base.output()
