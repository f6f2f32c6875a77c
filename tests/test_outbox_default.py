"""A ROV without ``--outbox`` keeps its outbox in the user's state directory, so a plain restart continues its
numbering (issue 30, found by the chaos soak); one process per outbox folder, by an ``flock`` the kernel
releases when its holder dies.

The autouse fixture of ``conftest.py`` points ``XDG_STATE_HOME`` at a folder of each test.
"""

from __future__ import annotations

import json
import logging
import os
import signal
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import pytest
from procs import Proc, client_session, lrsensor_cmd
from waiting import wait_until

from services.outbox import LOCK_FILE, Outbox, OutboxError, OutboxInUseError, default_outbox_dir
from services.testnet import free_port

FLEET = "obd"
WAIT_S = 30.0

# ----------------------------------------------------------------------------------------- the default folder


def test_the_default_folder_follows_the_xdg_state_home(tmp_path: Path) -> None:
    assert default_outbox_dir("f1", "rov1") == Path(os.environ["XDG_STATE_HOME"]) / "lrsensor/outbox/f1/rov1"
    assert default_outbox_dir("f1", "rov1", {"XDG_STATE_HOME": "/s", "HOME": "/h"}) == Path(
        "/s/lrsensor/outbox/f1/rov1"
    )
    # unset, empty or relative (the XDG rules): ~/.local/state
    for env in ({"HOME": "/h"}, {"XDG_STATE_HOME": "", "HOME": "/h"}, {"XDG_STATE_HOME": "rel", "HOME": "/h"}):
        assert default_outbox_dir("f1", "rov1", env) == Path("/h/.local/state/lrsensor/outbox/f1/rov1")
    # no HOME either: the password database's home
    import pwd

    home = Path(pwd.getpwuid(os.getuid()).pw_dir)
    assert default_outbox_dir("f", "r", {}) == home / ".local/state/lrsensor/outbox/f/r"


def _rov_args(*extra: str) -> Any:
    from lrsensor.cli import build_parser

    return build_parser().parse_args(["rov", "--fleet", FLEET, "--robot", "rov1", "--source", "sim", *extra])


def test_the_rov_opens_its_default_folder_and_continues_from_it() -> None:
    from services.cli_rov import _open_outbox

    folder = Path(os.environ["XDG_STATE_HOME"]) / "lrsensor" / "outbox" / FLEET / "rov1"
    with _open_outbox(_rov_args(), FLEET, "rov1") as (box, temporary):
        assert not temporary
        assert box.directory == folder
        box.append(0, b"a")
        box.append(1, b"b")
        box.take_acked([0])
    with _open_outbox(_rov_args(), FLEET, "rov1") as (box, temporary):  # a restart
        assert box.next_seq == 2
        assert box.pending() == [1]  # forwarded by the next run
    assert folder.is_dir()  # kept, also when empty
    with _open_outbox(_rov_args("--no-outbox"), FLEET, "rov1") as (box, temporary):
        assert box is None


def test_without_a_writable_state_folder_the_rov_falls_back_to_a_temporary_one_and_says_so(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """A file where the state folder should be cannot be written even by root (which a chmod would not stop)."""
    from services.cli_rov import _open_outbox

    blocker = tmp_path / "not-a-folder"
    blocker.write_text("x")
    monkeypatch.setenv("XDG_STATE_HOME", str(blocker))
    with (
        caplog.at_level(logging.WARNING, logger="services.cli_rov"),
        _open_outbox(_rov_args(), FLEET, "rov1") as (box, temporary),
    ):
        assert temporary
        folder = box.directory
        assert folder.parent == Path(tempfile.gettempdir())
        assert folder.name.startswith("lrs-outbox-rov1-")
        box.append(0, b"a")
        box.take_acked([0])
    assert not folder.exists()  # removed when empty, as before
    warning = " ".join(r.getMessage() for r in caplog.records if r.levelno == logging.WARNING)
    assert "temporary folder" in warning
    assert "numbers its clouds from 0 again" in warning
    assert str(blocker) in warning


# ----------------------------------------------------------------------------------------- one process per outbox

_HOLDER = """
import sys, time
from services.outbox import Outbox
box = Outbox(sys.argv[1], fsync=False)
box.append(box.next_seq, b"held")
print("holding", flush=True)
time.sleep(120)
"""


def test_a_second_process_is_refused_and_the_lock_dies_with_its_holder(tmp_path: Path) -> None:
    folder = tmp_path / "ob"
    holder = subprocess.Popen([sys.executable, "-c", _HOLDER, str(folder)], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout is not None
        assert holder.stdout.readline().strip() == "holding"
        assert (folder / LOCK_FILE).read_text().strip() == str(holder.pid)
        with pytest.raises(OutboxInUseError, match=f"process {holder.pid}") as info:
            Outbox(folder)
        assert info.value.pid == holder.pid
        assert str(folder) in str(info.value)
        assert isinstance(info.value, OutboxError)
        holder.send_signal(signal.SIGKILL)  # no clean-up code runs: the kernel releases the flock
        holder.wait(10)
    finally:
        holder.kill()
        holder.wait(10)
    with Outbox(folder) as box:  # the stale lock file does not block a restart
        assert box.pending() == [0]
        assert (folder / LOCK_FILE).read_text().strip() == str(os.getpid())


_TRY = """
import sys
from services.outbox import Outbox, OutboxInUseError
try:
    Outbox(sys.argv[1]).close()
    print("opened")
except OutboxInUseError as err:
    print("refused", err.pid)
"""


def _other_process_opens(folder: Path) -> str:
    return subprocess.run(
        [sys.executable, "-c", _TRY, str(folder)], capture_output=True, text=True, check=True, timeout=60
    ).stdout.strip()


def test_outboxes_of_one_process_share_the_lock_until_the_last_closes(tmp_path: Path) -> None:
    first = Outbox(tmp_path)
    second = Outbox(tmp_path)  # the same process (a test playing a restart): shared, not refused
    first.close()
    first.close()  # idempotent
    with pytest.raises(OutboxError, match="closed"):
        first.append(0, b"x")
    assert _other_process_opens(tmp_path) == f"refused {os.getpid()}"
    second.close()
    assert _other_process_opens(tmp_path) == "opened"
    third = Outbox(tmp_path)
    del third  # collected without close(): released too
    assert _other_process_opens(tmp_path) == "opened"


# ----------------------------------------------------------------------------------------- lrsensor rov processes


def _status(session: Any) -> dict[str, Any] | None:
    for reply in session.get(f"lrs/{FLEET}/base/status", timeout=2.0):
        if reply.ok is not None:
            data: dict[str, Any] = json.loads(reply.ok.payload.to_bytes())
            return data
    return None


def _robot(session: Any, robot: str = "rov1") -> dict[str, Any]:
    st = _status(session)
    return dict((st or {}).get("robots", {}).get(robot, {}))


def _rov(port: int, *extra: str) -> list[str]:
    return lrsensor_cmd(
        "rov", "--fleet", FLEET, "--robot", "rov1", "--connect", f"tcp/127.0.0.1:{port}", "--source", "sim",
        "--sim-size", "320x180", *extra,
    )  # fmt: skip


def _base(port: int, tmp_path: Path) -> Proc:
    return Proc(
        lrsensor_cmd("base", "--fleet", FLEET, "--listen", f"tcp/127.0.0.1:{port}", "--map", "off"),
        tmp_path / "base.log",
    )


def _next_seq(folder: Path) -> int:
    return int(json.loads((folder / "state.json").read_text())["next_seq"])


@pytest.mark.slow
def test_a_rov_run_twice_without_outbox_continues_its_numbering(tmp_path: Path, procs: list[Proc]) -> None:
    """Before: the second run numbered from 0 again and the base dropped its clouds (duplicates or reused)."""
    n = 8
    port = free_port()
    base = _base(port, tmp_path)
    procs.append(base)
    with client_session(port) as session:
        assert wait_until(lambda: _status(session) is not None, WAIT_S), base.output()
        for run in (1, 2):
            rov = Proc(_rov(port, "--sim-frames", str(n), "--rate", "10"), tmp_path / f"rov-{run}.log")
            procs.append(rov)
            assert rov.wait(120) == 0, rov.output()
            assert wait_until(lambda r=run: _robot(session).get("received") == r * n, WAIT_S), _robot(session)
        robot = _robot(session)
    assert robot["last_seq"] == 2 * n - 1
    assert (robot["missed"], robot["reused"]) == (0, 0), robot
    folder = default_outbox_dir(FLEET, "rov1")
    assert _next_seq(folder) == 2 * n
    assert not list(folder.glob("*.msg"))  # everything acknowledged
    assert str(folder) in rov.output()  # the log names the folder


@pytest.mark.slow
def test_a_second_rov_of_the_robot_is_refused_and_a_sigkill_frees_the_outbox(tmp_path: Path, procs: list[Proc]) -> None:
    port = free_port()
    base = _base(port, tmp_path)
    procs.append(base)
    folder = default_outbox_dir(FLEET, "rov1")
    with client_session(port) as session:
        assert wait_until(lambda: _status(session) is not None, WAIT_S), base.output()
        first = Proc(_rov(port, "--sim-frames", "100000", "--rate", "5"), tmp_path / "rov-1.log")
        procs.append(first)
        assert wait_until(lambda: _robot(session).get("received", 0) >= 3, WAIT_S * 2), first.output()

        second = Proc(_rov(port, "--sim-frames", "5"), tmp_path / "rov-2.log")
        procs.append(second)
        assert second.wait(60) == 2, second.output()
        out = second.output()
        assert f"outbox {folder} is in use by process {first.p.pid}" in out, out
        assert "robot 'rov1' in fleet 'obd'" in out
        assert first.p.poll() is None  # the first one goes on
        before = _robot(session)["received"]
        assert wait_until(lambda: _robot(session)["received"] > before, WAIT_S), first.output()

        first.stop(signal.SIGKILL)
        third = Proc(_rov(port, "--sim-frames", "5", "--rate", "10"), tmp_path / "rov-3.log")
        procs.append(third)
        assert third.wait(120) == 0, third.output()
        # every number either run gave is held once: the third continued after the first's last
        produced = _next_seq(folder)
        assert wait_until(lambda: _robot(session).get("received") == produced, WAIT_S), (produced, _robot(session))
        robot = _robot(session)
    assert robot["last_seq"] == produced - 1
    assert (robot["missed"], robot["reused"]) == (0, 0), robot
    assert not list(folder.glob("*.msg"))
