"""IMU sources and pose interpolation: CSV logs, OpenROV telemetry over pyserial (loop:// and a pty)."""

from __future__ import annotations

import math
import os
import pty
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import serial
from waiting import wait_until

from lrsensor.frames import Pose, R_ned_from_body
from services.errors import ImuError
from services.imu import CsvImu, OpenRovParser, SerialImu, open_imu, parse_serial_spec, write_csv
from services.posetrack import PoseTrack, has_fix

WAIT_S = 5.0  # how long a test waits for the reader thread to parse what it wrote

# ----------------------------------------------------------------------------- pose track


def test_interpolation_is_linear_in_position_and_slerp_in_attitude() -> None:
    track = PoseTrack.from_arrays([1_000, 2_000], [Pose(0, 0, 1, 0, 0, 0), Pose(2, -4, 3, 0, 0, math.radians(90))])
    p = track.pose_at(1_250)
    assert p is not None
    assert (p.north_m, p.east_m, p.down_m) == pytest.approx((0.5, -1.0, 1.5))
    assert p.yaw_rad == pytest.approx(math.radians(22.5))  # slerp about one axis: angle linear in t
    assert p.roll_rad == pytest.approx(0.0, abs=1e-12)
    assert p.pitch_rad == pytest.approx(0.0, abs=1e-12)


def test_slerp_takes_the_short_way_across_plus_minus_pi() -> None:
    track = PoseTrack.from_arrays(
        [0, 10], [Pose(0, 0, 0, 0, 0, math.radians(170)), Pose(0, 0, 0, 0, 0, math.radians(-170))]
    )
    p = track.pose_at(5)
    assert p is not None
    assert abs(abs(p.yaw_rad) - math.pi) < 1e-9


def test_interpolated_attitude_is_a_geodesic() -> None:
    a = Pose(0, 0, 0, 0.3, -0.2, 1.0)
    b = Pose(0, 0, 0, -0.1, 0.4, -0.5)
    track = PoseTrack.from_arrays([0, 100], [a, b])
    R0, R1 = a.R_ned_from_body, b.R_ned_from_body
    total = math.acos((np.trace(R0.T @ R1) - 1) / 2)
    for t in (25, 50, 75):
        p = track.pose_at(t)
        assert p is not None
        Rt = R_ned_from_body(p.roll_rad, p.pitch_rad, p.yaw_rad)
        ang = math.acos(np.clip((np.trace(R0.T @ Rt) - 1) / 2, -1, 1))
        assert ang == pytest.approx(total * t / 100, abs=1e-9)


def test_no_extrapolation_outside_the_span() -> None:
    track = PoseTrack.from_arrays([100, 200, 300], [Pose.identity()] * 3)
    assert track.pose_at(99) is None
    assert track.pose_at(301) is None
    assert track.pose_at(100) is not None
    assert track.pose_at(300) is not None
    assert PoseTrack().pose_at(0) is None


def test_out_of_order_and_non_finite_samples_are_rejected() -> None:
    track = PoseTrack()
    assert track.append(10, Pose.identity())
    assert not track.append(10, Pose.identity())
    assert not track.append(5, Pose.identity())
    assert not track.append(20, Pose(math.nan, 0, 0, 0, 0, 0))
    assert len(track) == 1
    assert track.rejected == 3


def test_live_track_is_bounded_and_can_be_waited_on() -> None:
    track = PoseTrack(max_samples=5)
    for i in range(10):
        track.append(i, Pose.identity())
    assert len(track) == 10  # trimmed in batches: at most twice the bound
    track.append(10, Pose.identity())
    assert len(track) == 5
    assert track.span == (6, 10)
    assert track.pose_at(5) is None
    assert not track.wait_covering(20, timeout_s=0.01)
    threading.Timer(0.05, lambda: track.append(25, Pose.identity())).start()
    assert track.wait_covering(20, timeout_s=5.0)


NAN = math.nan


def test_attitude_and_depth_come_from_every_sample_position_only_from_fixes() -> None:
    # fixes at 0 and 1 s, attitude and depth only at 0.5 and 1.5 s
    track = PoseTrack.from_arrays(
        [0, 500_000_000, 1_000_000_000, 1_500_000_000],
        [Pose(0, 0, 1, 0, 0, 0), Pose(NAN, NAN, 2, 0, 0, 0.2), Pose(2, -2, 3, 0, 0, 0.4), Pose(NAN, NAN, 4, 0, 0, 0.6)],
    )
    assert track.n_fixes == 2
    p = track.pose_at(250_000_000)  # between two fixes 1 s apart: interpolated
    assert p is not None
    assert (p.north_m, p.east_m, p.down_m, p.yaw_rad) == pytest.approx((0.5, -0.5, 1.5, 0.1))
    p = track.pose_at(1_250_000_000)  # after the last fix: attitude and depth, no position
    assert p is not None
    assert (p.down_m, p.yaw_rad) == pytest.approx((3.5, 0.5))
    assert not has_fix(p)
    assert math.isnan(p.north_m)
    assert math.isnan(p.east_m)
    fixed = track.pose_at(1_000_000_000)
    assert fixed is not None
    assert has_fix(fixed)


def test_fixes_too_far_apart_are_not_interpolated() -> None:
    times = [0, 1_000_000_000, 2_000_000_000, 3_000_000_000]
    poses = [Pose(0, 0, 1, 0, 0, 0), Pose(NAN, NAN, 1, 0, 0, 0), Pose(NAN, NAN, 1, 0, 0, 0), Pose(3, 0, 1, 0, 0, 0)]
    track = PoseTrack.from_arrays(times, poses)  # default: fixes more than 2 s apart are not interpolated
    p = track.pose_at(1_500_000_000)
    assert p is not None
    assert not has_fix(p)
    wide = PoseTrack(max_fix_gap_s=5.0)
    wide.extend(np.array(times), np.array([[q.north_m, q.east_m, q.down_m, 0, 0, 0] for q in poses]))
    p = wide.pose_at(1_500_000_000)
    assert p is not None
    assert p.north_m == pytest.approx(1.5)


def test_a_sample_with_only_one_horizontal_coordinate_is_refused() -> None:
    track = PoseTrack()
    assert not track.append(1, Pose(NAN, 0, 0, 0, 0, 0))
    assert not track.append(2, Pose(math.inf, 0, 0, 0, 0, 0))
    assert not track.append(3, Pose(NAN, NAN, NAN, 0, 0, 0))
    assert track.append(4, Pose(NAN, NAN, 1, 0, 0, 0))
    assert track.rejected == 3


def test_separate_series_and_a_silent_gap_give_no_pose() -> None:
    track = PoseTrack(keep_s=60.0, max_gap_s=0.5)
    for k in range(11):  # attitude at 10 Hz, depth at 5 Hz, over 1 s
        track.add_attitude(k * 100_000_000, 0.0, 0.0, 0.01 * k)
        if k % 2 == 0:
            track.add_depth(k * 100_000_000, 1.0 + 0.1 * k)
    p = track.pose_at(150_000_000)
    assert p is not None
    assert (p.yaw_rad, p.down_m) == pytest.approx((0.015, 1.15))
    assert not has_fix(p)
    # the link falls silent for 2 s, then resumes: the frames in the gap get no pose, not an old one
    track.add_attitude(3_000_000_000, 0.0, 0.0, 0.3)
    track.add_depth(3_000_000_000, 4.0)
    assert track.pose_at(2_000_000_000) is None
    assert "more than" in track.why_no_pose(2_000_000_000)
    assert track.pose_at(3_000_000_000) is not None
    # a frame after a silence longer than the gap is not waited for
    assert not track.wait_covering(4_000_000_000, timeout_s=30.0)


def test_live_track_keeps_at_least_its_time_window() -> None:
    track = PoseTrack(keep_s=1.0)
    for k in range(1000):  # 10 s at 100 Hz
        track.append(k * 10_000_000, Pose(NAN, NAN, 1, 0, 0, 0))
    span = track.span
    assert span is not None
    assert span[1] - span[0] >= 1_000_000_000
    assert span[1] - span[0] <= 2_000_000_000


# ----------------------------------------------------------------------------- CSV


def test_csv_round_trip(tmp_path: Path) -> None:
    times = [1_000_000_000 + i * 20_000_000 for i in range(5)]
    poses = [Pose(0.1 * i, -0.2 * i, 1.0 + i, 0.01 * i, -0.02 * i, 0.5 + 0.1 * i) for i in range(5)]
    write_csv(tmp_path / "imu.csv", times, poses)
    imu = open_imu(f"csv:{tmp_path / 'imu.csv'}")
    assert imu.rejected == 0
    assert imu.track.span == (times[0], times[-1])
    p = imu.track.pose_at(times[2])
    assert p is not None
    assert (p.north_m, p.down_m, p.yaw_rad, p.pitch_rad) == pytest.approx((0.2, 3.0, 0.7, -0.04))


def test_csv_rows_without_a_fix_have_attitude_and_depth(tmp_path: Path) -> None:
    f = tmp_path / "imu.csv"
    f.write_text(
        "t_ns,roll_deg,pitch_deg,yaw_deg,north_m,east_m,down_m\n"
        "1000000000,0,0,0,1.0,2.0,1\n"  # the launch fix
        "1100000000,0,0,10,,,1.5\n"
        "1200000000,0,0,20, , ,2\n"
        "1300000000,0,0,20,,3.0,2\n"  # one coordinate only: refused
        "1400000000,0,0,20,nan,nan,2\n"  # an explicit nan is not 'no fix': refused
    )
    imu = CsvImu(f)
    assert imu.rejected == 2
    assert len(imu.track) == 3
    p = imu.track.pose_at(1_150_000_000)
    assert p is not None
    assert (p.down_m, p.yaw_rad) == pytest.approx((1.75, math.radians(15)))
    assert not has_fix(p)
    launch = imu.track.pose_at(1_000_000_000)
    assert launch is not None
    assert (launch.north_m, launch.east_m) == (1.0, 2.0)
    # written back, a pose without a fix leaves both cells empty
    times, poses = imu.track.samples()
    write_csv(tmp_path / "back.csv", times, poses)
    rows = (tmp_path / "back.csv").read_text().splitlines()
    assert rows[2].split(",")[4:6] == ["", ""]
    assert len(CsvImu(tmp_path / "back.csv").track) == 3


def test_csv_bad_rows_are_skipped_and_counted(tmp_path: Path) -> None:
    f = tmp_path / "imu.csv"
    f.write_text(
        "t_ns,roll_deg,pitch_deg,yaw_deg,north_m,east_m,down_m\n"
        "1000,0,0,0,0,0,1\n"
        "garbage\n"
        "2000,0,0,nan,0,0,1\n"
        "1500,0,0,0,0,0,1\n"
        "1200,0,x,0,0,0,1\n"
        "1100,0,0,0,0,0,1\n"  # ok? 1100 > 1000 but after 1500 was accepted -> not after previous
        "3000,0,0,90,0,0,2\n"
        "4000.0,0,0,90,0,0,2\n"  # an integral decimal is accepted
        "4000.5,0,0,90,0,0,2\n"  # a fractional nanosecond is not
    )
    imu = CsvImu(f)
    assert len(imu.track) == 4
    assert imu.rejected == 5


@pytest.mark.parametrize(
    ("text", "reason"),
    [
        ("", "empty"),
        ("t_ns,roll_deg\n1,2\n", "lacks"),
        ("t_ns,roll_deg,pitch_deg,yaw_deg,north_m,east_m,down_m\nbad,row\n", "no valid sample"),
    ],
)
def test_unusable_csv_is_refused(tmp_path: Path, text: str, reason: str) -> None:
    f = tmp_path / "imu.csv"
    f.write_text(text)
    with pytest.raises(ImuError, match=reason):
        CsvImu(f)


def test_missing_csv_and_unknown_spec_are_refused(tmp_path: Path) -> None:
    with pytest.raises(ImuError, match="cannot open"):
        open_imu(f"csv:{tmp_path / 'nope.csv'}")
    with pytest.raises(ImuError, match="unknown IMU"):
        open_imu("gps:1")


# ----------------------------------------------------------------------------- OpenROV telemetry


def test_parse_serial_spec() -> None:
    assert parse_serial_spec("/dev/ttyUSB0@57600") == ("/dev/ttyUSB0", 57600)
    assert parse_serial_spec("loop://") == ("loop://", 115200)
    with pytest.raises(ImuError, match="baud"):
        parse_serial_spec("/dev/ttyS0@fast")
    with pytest.raises(ImuError, match="no port"):
        parse_serial_spec("@9600")


def test_parser_reads_full_and_partial_lines() -> None:
    p = OpenRovParser()
    assert p.feed(b"hdgd:90.0;deep:1.5;pitc:2.0;ro") == []
    out = p.feed(b"ll:-1.0;vout:11.9;\r\nhdgd:180;deep:1.6;pitc:0;roll:0;\n")
    assert len(out) == 2
    r = out[0]
    assert (r.yaw_rad, r.down_m, r.pitch_rad, r.roll_rad) == pytest.approx(
        (math.radians(90), 1.5, math.radians(2), math.radians(-1))
    )
    assert out[1].yaw_rad == pytest.approx(-math.pi)  # 180 deg heading wraps to -pi
    assert p.rejected == 0


def test_parser_needs_all_four_fields_then_updates_incrementally() -> None:
    p = OpenRovParser()
    assert p.feed(b"hdgd:10;deep:2\n") == []
    assert p.feed(b"vout:12.1;iout:0.5\n") == []
    out = p.feed(b"pitc:1;roll:2\ndeep:2.5\n")
    assert [r.down_m for r in out] == [2.0, 2.5]


@pytest.mark.parametrize(
    "garbage",
    [
        b"\xff\xfe\x00garbage\n",
        b"hdgd90;deep:1\n",
        b"hdgd:abc;deep:1\n",
        b"hdgd:nan;deep:1\n",
        b"hdgd:10;deep:1;pitc:400;roll:0\n",
        b"9x:1\n",
        b"h\xe9gd:1\n",
    ],
)
def test_parser_rejects_garbage_lines_and_keeps_going(garbage: bytes) -> None:
    p = OpenRovParser()
    out = p.feed(b"hdgd:1;deep:1;pitc:1;roll:1\n" + garbage + b"hdgd:2;deep:2;pitc:2;roll:2\n")
    assert p.rejected == 1
    assert [r.down_m for r in out] == [1.0, 2.0]


def test_parser_drops_overlong_runs_without_newline() -> None:
    p = OpenRovParser(max_line_bytes=64)
    assert p.feed(b"x" * 100) == []
    assert p.rejected == 1
    assert len(p.feed(b"\nhdgd:2;deep:2;pitc:2;roll:2\n")) == 1


def test_parser_random_bytes_never_raise() -> None:
    rng = np.random.default_rng(0)
    p = OpenRovParser()
    for _ in range(200):
        p.feed(rng.integers(0, 256, int(rng.integers(1, 200)), dtype=np.uint8).tobytes())
    out = p.feed(b"\nhdgd:5;deep:5;pitc:5;roll:5\n")
    assert out
    assert out[-1].down_m == 5.0


def test_serial_imu_over_pyserial_loop() -> None:
    port = serial.serial_for_url("loop://", timeout=0.05)
    with SerialImu("loop://", serial_port=port) as imu:
        port.write(b"hdgd:45;deep:3.25;pit")
        port.write(b"c:1;roll:-2\n\xde\xad\xbe\xef\nhdgd:46;deep:3.3;pitc:1;roll:-2\n")
        assert wait_until(lambda: len(imu.track) == 2, WAIT_S)
        assert imu.rejected == 1
        t0, _ = imu.track.span  # type: ignore[misc]
        p = imu.track.pose_at(t0)
        assert p is not None
        assert (p.down_m, p.yaw_rad) == pytest.approx((3.25, math.radians(45)))
        assert not has_fix(p)  # OpenROV has no position: none is invented
        assert math.isnan(p.north_m)
        assert math.isnan(p.east_m)
    port.close()


def test_serial_imu_over_a_pty() -> None:
    master, slave = pty.openpty()
    name = os.ttyname(slave)
    try:
        with open_imu(f"serial:{name}@57600") as imu:
            os.write(master, b"garbage\x00\x01\nhdgd:10;deep:1;pitc:0;roll:0\n")
            assert wait_until(lambda: len(imu.track) == 1, WAIT_S)
            os.write(master, b"hdgd:12;deep:1.1;")
            os.write(master, b"pitc:0;roll:0\n")
            assert wait_until(lambda: len(imu.track) == 2, WAIT_S)
            assert imu.rejected == 1
    finally:
        os.close(master)
        os.close(slave)


def test_serial_imu_unopenable_port_is_refused() -> None:
    with pytest.raises(ImuError, match="cannot open"), open_imu("serial:/dev/does-not-exist@9600"):
        pass


# ----------------------------------------------------------------------------- MAVLink without pymavlink


def test_mavlink_without_pymavlink_says_what_to_install(monkeypatch: pytest.MonkeyPatch) -> None:
    import sys

    monkeypatch.setitem(sys.modules, "pymavlink", None)  # as if it were not installed
    imu = open_imu("mavlink:udpin:127.0.0.1:14551")  # the import waits until the source opens
    with pytest.raises(ImuError, match=r"pip install 'lrsensor\[mavlink\]'"), imu:
        pass


def test_a_live_pose_waits_for_the_fix_that_follows_the_depth() -> None:
    # a DVL autopilot sends depth and position together; the depth after a frame may arrive before the fix
    track = PoseTrack(max_fix_gap_s=1.0)
    for t in (0, 200_000_000):
        track.add_attitude(t, 0.0, 0.0, 0.5)
        track.add_depth(t, 2.0)
    track.add_fix(0, 1.0, -1.0)
    frame = 100_000_000
    p = track.pose_at(frame)
    assert p is not None
    assert not has_fix(p)
    threading.Timer(0.05, lambda: track.add_fix(200_000_000, 3.0, -3.0)).start()
    p = track.pose_waiting(frame, timeout_s=5.0)
    assert p is not None
    assert has_fix(p)
    assert (p.north_m, p.east_m) == pytest.approx((2.0, -2.0))
    # a source that sends no fixes is not waited for
    no_fix = PoseTrack()
    no_fix.add_attitude(0, 0.0, 0.0, 0.0)
    no_fix.add_depth(0, 1.0)
    no_fix.add_attitude(200_000_000, 0.0, 0.0, 0.0)
    no_fix.add_depth(200_000_000, 1.0)
    t0 = time.monotonic()
    p = no_fix.pose_waiting(frame, timeout_s=5.0)
    assert p is not None
    assert not has_fix(p)
    assert time.monotonic() - t0 < 1.0
