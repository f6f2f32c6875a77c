"""Wire messages: round trips, and strict refusal of truncated, garbage, wrong-version and inconsistent input."""

from __future__ import annotations

import contextlib
import math

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lrsensor.calibration import Calibration
from lrsensor.frames import Pose
from lrsensor.scan import Scan
from services.errors import WireError
from services.wire import MAX_PAYLOAD_BYTES, SCHEMA_VERSION, CalibMsg, CloudMsg, StatusMsg


def make_cloud(n: int = 50, seed: int = 0, uv: bool = True) -> CloudMsg:
    rng = np.random.default_rng(seed)
    return CloudMsg(
        robot="rov1",
        seq=42,
        t_ns=1_700_000_000_123_456_789,
        pose=Pose(1.5, -2.25, 3.0, 0.01, -0.02, 2.5),
        points_body=rng.normal(0, 2, (n, 3)).astype(np.float32),
        laser=rng.integers(0, 2, n).astype(np.uint8),
        quality=rng.random(n).astype(np.float32),
        uv=rng.random((n, 2)).astype(np.float32) * 640 if uv else None,
        sent_ns=1_700_000_000_200_000_000,
    )


def raw(msg: CloudMsg | CalibMsg | StatusMsg) -> dict:
    return msgpack.unpackb(msg.to_bytes(), raw=False)


def repack(d: dict) -> bytes:
    return msgpack.packb(d, use_bin_type=True)


@pytest.mark.parametrize("n", [0, 1, 3800])
@pytest.mark.parametrize("uv", [True, False])
def test_cloud_round_trip(n: int, uv: bool) -> None:
    m = make_cloud(n, uv=uv)
    back = CloudMsg.from_bytes(m.to_bytes())
    assert (back.robot, back.seq, back.t_ns, back.sent_ns, back.pose) == (m.robot, m.seq, m.t_ns, m.sent_ns, m.pose)
    np.testing.assert_array_equal(back.points_body, m.points_body)
    np.testing.assert_array_equal(back.laser, m.laser)
    np.testing.assert_array_equal(back.quality, m.quality)
    if uv:
        assert back.uv is not None
        np.testing.assert_array_equal(back.uv, m.uv)
    else:
        assert back.uv is None


def test_cloud_arrays_travel_as_little_endian_bytes() -> None:
    m = make_cloud(4)
    d = raw(m)
    assert d["v"] == SCHEMA_VERSION
    assert d["type"] == "cloud"
    assert d["n"] == 4
    assert isinstance(d["points"], bytes)
    assert len(d["points"]) == 4 * 12
    np.testing.assert_array_equal(np.frombuffer(d["points"], "<f4").reshape(4, 3), m.points_body)
    assert set(d["pose"]) == {"north_m", "east_m", "down_m", "roll_rad", "pitch_rad", "yaw_rad"}


def test_cloud_from_scan_narrows_to_float32() -> None:
    scan = Scan(np.array([[1.0, 0.1, -0.05]]), np.array([0]), np.array([[320.0, 100.5]]), np.array([0.9]))
    m = CloudMsg.from_scan("rov2", 0, 5, Pose.identity(), scan)
    assert m.points_body.dtype == np.float32
    assert m.laser.dtype == np.uint8
    back = CloudMsg.from_bytes(m.to_bytes())
    np.testing.assert_allclose(back.points_body, scan.points, rtol=1e-6)


def test_calib_round_trip() -> None:
    cal = Calibration.paper(0.1, 640, 360)
    back = CalibMsg.from_bytes(CalibMsg("rov3", cal).to_bytes())
    assert back.robot == "rov3"
    assert back.calibration == cal


def test_calib_payload_is_the_calibration_file_mapping() -> None:
    cal = Calibration.paper(0.1, 640, 360)
    d = raw(CalibMsg("rov3", cal))
    assert d["camera"]["fx"] == cal.camera.fx
    assert len(d["lasers"]) == 2
    assert Calibration.from_dict(d) == cal  # any msgpack reader gets the file format of CONVENTIONS


@pytest.mark.parametrize("state", ["starting", "running", "done", "stopped", "failed"])
def test_status_round_trip(state: str) -> None:
    m = StatusMsg("rov1", 123, state, frames=10, published=8, skipped=1, failed=1, last_seq=7)
    assert StatusMsg.from_bytes(m.to_bytes()) == m


def test_every_truncation_is_refused() -> None:
    data = make_cloud(3).to_bytes()
    for cut in range(len(data)):
        with pytest.raises(WireError):
            CloudMsg.from_bytes(data[:cut])


def test_trailing_bytes_are_refused() -> None:
    with pytest.raises(WireError, match="trailing"):
        CloudMsg.from_bytes(make_cloud(3).to_bytes() + b"\x00")


@pytest.mark.parametrize(
    ("change", "reason"),
    [
        ({"v": 2}, "schema version 2"),
        ({"v": True}, "schema version"),
        ({"type": "calib"}, "type"),
        ({"n": 4}, "bytes, expected"),
        ({"laser": b"\x00\x01"}, "'laser' has 2 bytes"),
        ({"quality": b"\x00" * 4}, "'quality'"),
        ({"uv": b"\x00" * 8}, "'uv'"),
        ({"seq": -1}, "'seq'"),
        ({"seq": "7"}, "'seq' must be an integer"),
        ({"t_ns": -1}, "'t_ns'"),
        ({"robot": "a/b"}, "not a valid name"),
        ({"robot": "base"}, "reserved"),
        ({"robot": 3}, "'robot' must be a string"),
        ({"pose": [1, 2, 3]}, "'pose' must be a map"),
        ({"points": [1.0, 2.0]}, "'points' must be binary"),
    ],
)
def test_inconsistent_fields_are_refused(change: dict, reason: str) -> None:
    d = raw(make_cloud(3))
    d.update(change)
    with pytest.raises(WireError, match=reason):
        CloudMsg.from_bytes(repack(d))


@pytest.mark.parametrize("missing", ["robot", "seq", "t_ns", "pose", "n", "points", "laser", "quality"])
def test_missing_field_is_named(missing: str) -> None:
    d = raw(make_cloud(3))
    del d[missing]
    with pytest.raises(WireError, match=missing):
        CloudMsg.from_bytes(repack(d))


def test_non_finite_values_are_refused() -> None:
    d = raw(make_cloud(3))
    pts = np.frombuffer(d["points"], "<f4").copy()
    pts[4] = np.nan
    d["points"] = pts.tobytes()
    with pytest.raises(WireError, match="not finite"):
        CloudMsg.from_bytes(repack(d))
    d = raw(make_cloud(3))
    d["pose"]["yaw_rad"] = math.inf
    with pytest.raises(WireError, match="yaw_rad"):
        CloudMsg.from_bytes(repack(d))
    d = raw(make_cloud(3))
    d["quality"] = np.array([0.1, np.inf, 0.2], "<f4").tobytes()
    with pytest.raises(WireError, match="quality"):
        CloudMsg.from_bytes(repack(d))


def test_encoding_refuses_non_finite_and_bad_shapes() -> None:
    m = make_cloud(3)
    bad = m.points_body.copy()
    bad[0, 0] = np.nan
    with pytest.raises(WireError, match="non-finite"):
        CloudMsg(m.robot, 0, 1, m.pose, bad, m.laser, m.quality).to_bytes()
    with pytest.raises(WireError, match="inconsistent"):
        CloudMsg(m.robot, 0, 1, m.pose, m.points_body, m.laser[:2], m.quality)


def test_oversized_payload_is_refused_before_decoding() -> None:
    with pytest.raises(WireError, match="larger than"):
        CloudMsg.from_bytes(b"\x80" * (MAX_PAYLOAD_BYTES + 1))


def test_unknown_extra_fields_are_ignored() -> None:
    d = raw(make_cloud(3))
    d["future_field"] = {"x": 1}
    assert CloudMsg.from_bytes(repack(d)).seq == 42


@pytest.mark.parametrize("payload", [b"", b"\xc1", b"{}", b"[1,2]", b"\x93\x01\x02\x03", b"hello world"])
def test_garbage_is_refused(payload: bytes) -> None:
    for cls in (CloudMsg, CalibMsg, StatusMsg):
        with pytest.raises(WireError):
            cls.from_bytes(payload)


def test_invalid_calibration_is_refused_with_the_key() -> None:
    d = raw(CalibMsg("rov1", Calibration.paper()))
    d["camera"]["fx"] = -5.0
    with pytest.raises(WireError, match=r"camera\.fx"):
        CalibMsg.from_bytes(repack(d))


def test_status_refuses_unknown_state() -> None:
    d = raw(StatusMsg("rov1", 1, "running"))
    d["state"] = "sleeping"
    with pytest.raises(WireError, match="unknown state"):
        StatusMsg.from_bytes(repack(d))


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=400))
def test_random_bytes_never_raise_anything_but_wire_error(data: bytes) -> None:
    for cls in (CloudMsg, CalibMsg, StatusMsg):
        with contextlib.suppress(WireError):
            cls.from_bytes(data)


@settings(max_examples=200, deadline=None)
@given(st.integers(0, 300), st.integers(0, 255))
def test_byte_flips_never_raise_anything_but_wire_error(pos: int, value: int) -> None:
    data = bytearray(make_cloud(5).to_bytes())
    data[pos % len(data)] = value
    with contextlib.suppress(WireError):
        CloudMsg.from_bytes(bytes(data))
