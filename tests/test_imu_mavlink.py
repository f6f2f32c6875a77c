"""The MAVLink pose source against an ArduSub-like pymavlink sender on loopback UDP (tests/mavsender.py):
poses against the truth sent, with and without LOCAL_POSITION_NED, a silent link, and a ROV process run with
``--imu mavlink:...`` whose published clouds are checked against the truth."""

from __future__ import annotations

import math
import threading
import time
from pathlib import Path
from typing import Any

import pytest

pytest.importorskip("pymavlink")

from mavsender import ArduSubSender, free_udp_port
from procs import Proc, lrsensor_cmd
from waiting import wait_until

from services.errors import ImuError
from services.imu import open_imu
from services.imu_mavlink import MavlinkImu
from services.posetrack import has_fix
from services.testnet import free_port
from services.wire import decode_cloud
from services.zconfig import NetworkOptions, open_session

WAIT_S = 10.0
ANGLE_TOL_RAD = 1e-6
DEPTH_TOL_M = 1e-3
TIME_TOL_NS = 1_000_000


def angle_diff(a: float, b: float) -> float:
    return abs((a - b + math.pi) % (2 * math.pi) - math.pi)


def run_sender(imu: MavlinkImu, sender: ArduSubSender, seconds: float) -> None:
    """Let the sender play ``seconds`` of the dive after the receiver's clock is mapped."""
    sender.start()
    assert wait_until(lambda: imu.assembler.offset_ns is not None, WAIT_S), imu.counters
    threading.Event().wait(seconds)  # the dive plays for a fixed time: nothing to wait for


@pytest.mark.parametrize("local_position", [False, True], ids=["no-dvl", "with-local-position"])
def test_poses_match_the_truth_sent(local_position: bool) -> None:
    port = free_udp_port()
    with MavlinkImu(f"udpin:127.0.0.1:{port}") as imu:
        sender = ArduSubSender(port, local_position=local_position)
        try:
            run_sender(imu, sender, 2.5)
        finally:
            sender.stop()
        offset = imu.assembler.offset_ns
        assert offset is not None
        c = imu.counters
        assert (c.rejected, c.ignored) == (0, 0)
        assert c.held > 0  # sent before the first SYSTEM_TIME (0.5 s in): held, then placed
        assert c.dropped_held == 0
        attitudes = sender.of("ATTITUDE")
        assert c.attitude == len(attitudes)
        assert c.depth == len(sender.of("GLOBAL_POSITION_INT"))
        assert c.fixes == (len(sender.of("LOCAL_POSITION_NED")) if local_position else 0)
        truth = sender.truth
        # the i-th attitude sample of the track is the i-th ATTITUDE sent (the offset may have been refined by
        # microseconds since: the samples are checked at the times they were placed at)
        times, _ = imu.track.series()["attitude"]
        assert len(times) == len(attitudes)
        posed = fixed = 0
        for t_ns, m in zip(times.tolist(), attitudes, strict=True):
            assert abs(t_ns - m.unix_ns) < TIME_TOL_NS  # the autopilot's clock mapped within 1 ms
            p = imu.track.pose_at(t_ns)
            if p is None:  # before the first or after the last depth sample
                continue
            posed += 1
            for got, sent in zip((p.roll_rad, p.pitch_rad, p.yaw_rad), truth.attitude(m.unix_ns), strict=True):
                assert angle_diff(got, sent) < ANGLE_TOL_RAD
            assert abs(p.down_m - truth.depth_m(m.unix_ns)) < DEPTH_TOL_M
            if has_fix(p):
                assert local_position
                fixed += 1
                n, e = truth.north_east_m(m.unix_ns)
                assert (abs(p.north_m - n), abs(p.east_m - e)) < (1e-3, 1e-3)
            else:
                assert math.isnan(p.north_m)
                assert math.isnan(p.east_m)
        assert posed >= len(attitudes) - 10  # all but the ends (depth comes at 5 Hz, attitude at 25 Hz)
        assert fixed >= (posed - 10 if local_position else 0)


def test_a_silent_link_gives_no_pose_never_an_old_one() -> None:
    port = free_udp_port()
    with MavlinkImu(f"udpin:127.0.0.1:{port}", stale_s=0.5) as imu:
        sender = ArduSubSender(port)
        try:
            run_sender(imu, sender, 1.0)
            sender.pause()
            paused_at = sender.last_unix_ns()
            assert wait_until(lambda: imu.counters.silences == 1, WAIT_S)  # noticed and reported
            span = imu.track.span
            assert span is not None
            last = span[1]
            assert last <= paused_at + 1_000_000
            # a frame after the staleness limit gets no pose, and nobody waits for one
            late = last + 800_000_000
            t0 = time.monotonic()
            assert not imu.track.wait_covering(late, timeout_s=5.0)
            assert time.monotonic() - t0 < 1.0
            assert imu.track.pose_at(late) is None
            threading.Event().wait(1.0)
            sender.resume()
            resumed_ns = time.time_ns()
            assert wait_until(lambda: (imu.track.span or (0, 0))[1] > resumed_ns + 500_000_000, WAIT_S)
        finally:
            sender.stop()
        # the link is back, but the frames in its gap still get no pose: the samples around them are too far apart
        assert imu.track.pose_at(late) is None
        assert "more than" in imu.track.why_no_pose(late)
        assert imu.track.pose_at(imu.track.span[1]) is not None  # type: ignore[index]


def test_other_systems_and_messages_before_the_heartbeat_are_ignored() -> None:
    from services.imu_mavlink import MavlinkPoseAssembler
    from services.posetrack import PoseTrack

    class Msg:
        def __init__(self, kind: str, sysid: int = 1, **fields: Any) -> None:
            self.kind, self.sysid = kind, sysid
            self.__dict__.update(fields)

        def get_type(self) -> str:
            return self.kind

        def get_srcSystem(self) -> int:
            return self.sysid

        def get_srcComponent(self) -> int:
            return 1

    a = MavlinkPoseAssembler(PoseTrack(keep_s=60.0, max_gap_s=1.0))
    att = {"roll": 0.0, "pitch": 0.0, "yaw": 0.5}
    a.feed(Msg("ATTITUDE", time_boot_ms=900, **att), 0.0)  # before any heartbeat
    a.feed(Msg("HEARTBEAT", sysid=255, type=6, autopilot=8), 0.0)  # a ground station
    a.feed(Msg("HEARTBEAT", type=12, autopilot=3), 0.0)
    a.feed(Msg("ATTITUDE", sysid=2, time_boot_ms=950, **att), 0.0)  # another vehicle
    assert a.counters.ignored == 2
    a.feed(Msg("SYSTEM_TIME", time_unix_usec=0, time_boot_ms=990), 0.0)  # clock not set: not used
    a.feed(Msg("ATTITUDE", time_boot_ms=1000, **att), 0.0)
    a.feed(Msg("VFR_HUD", alt=-2.5), 0.05)  # no GLOBAL_POSITION_INT yet: VFR_HUD's altitude, stamped ~1050 ms
    a.feed(Msg("ATTITUDE", time_boot_ms=1100, **att), 0.1)
    a.feed(Msg("VFR_HUD", alt=-2.7), 0.15)
    assert a.offset_ns is None
    assert a.counters.held == 4
    a.feed(Msg("SYSTEM_TIME", time_unix_usec=1_700_000_000_000_000, time_boot_ms=1000), 0.2)
    assert a.to_unix_ns(1000) == 1_700_000_000_000_000_000
    p = a.track.pose_at(1_700_000_000_100_000_000)  # boot 1100 ms, between the two depths (1050, 1150 ms)
    assert p is not None
    assert p.down_m == pytest.approx(2.6)
    assert p.yaw_rad == pytest.approx(0.5)
    # a reboot (boot time back to 0) starts the mapping over
    a.feed(Msg("ATTITUDE", time_boot_ms=50, **att), 1.0)
    assert a.offset_ns is None
    assert a.counters.reboots == 1


def test_missing_connection_and_unopenable_ports_are_refused() -> None:
    with pytest.raises(ImuError, match="unknown IMU"):
        open_imu("mavlink:")
    with pytest.raises(ImuError, match="staleness"):
        MavlinkImu("udpin:127.0.0.1:1", stale_s=0)
    with pytest.raises(ImuError, match="cannot open"), open_imu("mavlink:udpin:203.0.113.9:9"):
        pass


# ----------------------------------------------------------------------------- a ROV process end to end


def check_clouds(clouds: list[Any], sender: ArduSubSender, local_position: bool) -> None:
    truth = sender.truth
    for m in clouds:
        p = m.pose
        # time mapping (1 ms) times the fastest rate sent (0.2 rad/s, 0.3 m/s), plus interpolation
        for got, sent in zip((p.roll_rad, p.pitch_rad, p.yaw_rad), truth.attitude(m.t_ns), strict=True):
            assert angle_diff(got, sent) < 5e-4
        assert abs(p.down_m - truth.depth_m(m.t_ns)) < DEPTH_TOL_M
        if local_position:
            assert has_fix(p)
            n, e = truth.north_east_m(m.t_ns)
            assert (abs(p.north_m - n), abs(p.east_m - e)) < (2e-3, 2e-3)
        else:
            assert not has_fix(p)


@pytest.mark.slow
def test_rov_process_with_a_mavlink_pose_source(tmp_path: Path, procs: list[Proc]) -> None:
    zport = free_port()
    cases = {"rov1": True, "rov2": False}  # rov1's autopilot sends LOCAL_POSITION_NED, rov2's does not
    got: dict[str, list[Any]] = {r: [] for r in cases}
    lock = threading.Lock()

    def on_cloud(sample: Any) -> None:
        msg = decode_cloud(sample.payload.to_bytes())
        with lock:
            got[msg.robot].append(msg)

    router = open_session(NetworkOptions(mode="router", listen=(f"tcp/127.0.0.1:{zport}",)), "router")
    senders: dict[str, ArduSubSender] = {}
    try:
        sub = router.declare_subscriber("lrs/mav/*/cloud", on_cloud)
        rovs = {}
        for robot, local_position in cases.items():
            uport = free_udp_port()
            senders[robot] = ArduSubSender(uport, local_position=local_position).start()
            args = ["rov", "--fleet", "mav", "--robot", robot, "--connect", f"tcp/127.0.0.1:{zport}"]
            args += ["--source", "sim", "--sim-frames", "60", "--sim-size", "320x180", "--rate", "10"]
            args += ["--imu", f"mavlink:udpin:127.0.0.1:{uport}", "--no-outbox", "--ack-timeout-s", "0"]
            rovs[robot] = Proc(lrsensor_cmd(*args), tmp_path / f"{robot}.log")
            procs.append(rovs[robot])
        # once clouds flow, the autopilots fall silent: later frames must get no pose, never an old one
        stopped_at: dict[str, int] = {}
        for robot, sender in senders.items():
            assert wait_until(lambda r=robot: len(got[r]) >= 5, 60), rovs[robot].output()
            sender.pause()
            stopped_at[robot] = sender.last_unix_ns()
        for p in rovs.values():
            assert p.wait(120) == 0, p.output()
        sub.undeclare()
    finally:
        for sender in senders.values():
            sender.stop()
        router.close()
    for robot, local_position in cases.items():
        out = rovs[robot].output()
        clouds = got[robot]
        assert clouds, out
        check_clouds(clouds, senders[robot], local_position)
        assert max(m.t_ns for m in clouds) <= stopped_at[robot]  # nothing posed after the link fell silent
        summary = next(line for line in out.splitlines() if f"rov {robot}: frames 60" in line)
        published = int(summary.split("published ")[1].split(",")[0])
        skipped = int(summary.split("skipped (no pose) ")[1].split(",")[0])
        unplaced = int(summary.split("no horizontal fix ")[1].split(",")[0])
        assert published == len(clouds)
        assert skipped > 0  # frames after the silence (and before the source started listening)
        assert published + skipped <= 60
        assert unplaced == (0 if local_position else published)
        assert "no pose for the frame" in out  # said at warning level, with the reason
