"""The compact cloud (schema 2): round trips, strict refusal, the base's triangulation and calibration checks."""

from __future__ import annotations

import contextlib
from pathlib import Path

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lrsensor.calibration import Calibration
from lrsensor.frames import Pose
from lrsensor.scan import Scan
from lrsensor.triangulation import triangulate
from services.base import BaseStation
from services.calibbook import CalibrationBook
from services.errors import WireError
from services.keys import FleetKeys
from services.wire import (
    ROW_SCALE,
    STRIPE_SCHEMA_VERSION,
    CloudMsg,
    StripeMsg,
    calibration_fingerprint,
    decode_cloud,
)

CAL = Calibration.paper(0.1, 640, 360)
FP = calibration_fingerprint(CAL)


def stripe_scan(seed: int = 0, gaps: bool = True) -> Scan:
    """Two lasers' stripes across a 640-column image, rows near the two lasers' rows on a wall 1-2 m ahead."""
    rng = np.random.default_rng(seed)
    cols = np.arange(0, 640)
    if gaps:
        cols = cols[(cols < 100) | (cols > 130)]
    uv_parts, laser_parts = [], []
    for li, row in enumerate((150.0, 210.0)):
        v = row + 5 * np.sin(cols / 80.0) + rng.normal(0, 0.2, cols.size)
        uv_parts.append(np.c_[cols, v])
        laser_parts.append(np.full(cols.size, li))
    uv = np.concatenate(uv_parts)
    laser = np.concatenate(laser_parts)
    points = triangulate(CAL, uv, laser)
    keep = np.all(np.isfinite(points), axis=1)
    return Scan(points[keep], laser[keep], uv[keep], rng.random(int(keep.sum())))


def make_stripe(seed: int = 0) -> StripeMsg:
    return StripeMsg.from_scan(
        "rov1",
        42,
        1_700_000_000_123_456_789,
        Pose(1.5, -2.25, 3.0, 0.01, -0.02, 2.5),
        stripe_scan(seed),
        FP,
        sent_ns=1_700_000_000_200_000_000,
    )


def raw(msg: StripeMsg) -> dict:
    return msgpack.unpackb(msg.to_bytes(), raw=False)


def repack(d: dict) -> bytes:
    return msgpack.packb(d, use_bin_type=True)


def assert_same(a: StripeMsg, b: StripeMsg) -> None:
    assert (a.robot, a.seq, a.t_ns, a.sent_ns, a.pose, a.calib_id) == (
        b.robot,
        b.seq,
        b.t_ns,
        b.sent_ns,
        b.pose,
        b.calib_id,
    )
    for name in ("laser", "column", "row_fx", "quality_u8"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))


def test_round_trip_and_decode_cloud_dispatch() -> None:
    m = make_stripe()
    back = StripeMsg.from_bytes(m.to_bytes())
    assert_same(back, m)
    any_msg = decode_cloud(m.to_bytes())
    assert isinstance(any_msg, StripeMsg)
    assert_same(any_msg, m)
    old = CloudMsg.from_scan("rov1", 1, 2, Pose.identity(), stripe_scan())
    assert isinstance(decode_cloud(old.to_bytes()), CloudMsg)  # schema 1 still decodes


def test_empty_and_single_point_clouds_round_trip() -> None:
    for keep in (0, 1):
        scan = stripe_scan()
        m = StripeMsg.from_scan("rov1", 0, 1, Pose.identity(), scan.select(np.arange(len(scan)) < keep), FP)
        assert len(StripeMsg.from_bytes(m.to_bytes())) == keep


def test_any_point_order_round_trips() -> None:
    m = make_stripe()
    perm = np.random.default_rng(3).permutation(len(m))
    shuffled = StripeMsg(m.robot, 1, 2, m.pose, FP, m.laser[perm], m.column[perm], m.row_fx[perm], m.quality_u8[perm])
    assert_same(StripeMsg.from_bytes(shuffled.to_bytes()), shuffled)


def test_layout_is_runs_of_columns_with_row_steps() -> None:
    m = make_stripe()
    d = raw(m)
    assert (d["v"], d["type"], d["n"]) == (STRIPE_SCHEMA_VERSION, "cloud", len(m))
    assert d["runs"] == 4  # two lasers, one gap each
    np.testing.assert_array_equal(np.frombuffer(d["run_laser"], "u1"), [0, 0, 1, 1])
    np.testing.assert_array_equal(np.frombuffer(d["run_u0"], "<u2"), [0, 131, 0, 131])
    np.testing.assert_array_equal(np.frombuffer(d["run_len"], "<u2"), [100, 509, 100, 509])
    assert len(d["dv"]) == 2 * (len(m) - 4)
    assert len(d["quality"]) == len(m)
    assert d["calib"] == FP
    # about 3 bytes a point against 25 for schema 1
    old = CloudMsg.from_scan("rov1", 42, 1, Pose.identity(), stripe_scan())
    assert len(old.to_bytes()) > 7 * len(m.to_bytes())


def test_rows_keep_a_4096th_of_a_pixel_and_big_jumps_start_runs() -> None:
    scan = stripe_scan()
    uv = scan.uv.copy()
    uv[300, 1] += 20.0  # a depth step: beyond an int16 step
    jumped = Scan(scan.points, scan.laser, uv, scan.quality)
    m = StripeMsg.from_scan("rov1", 0, 1, Pose.identity(), jumped, FP)
    back = StripeMsg.from_bytes(m.to_bytes())
    order = np.lexsort((uv[:, 0], scan.laser))
    assert np.abs(back.uv - uv[order]).max() <= 0.5 / ROW_SCALE + 1e-12
    assert back.runs()[0].size == 6
    assert np.abs(back.quality - scan.quality[order]).max() <= 0.5 / 255 + 1e-6


def test_base_triangulation_matches_the_sensor_within_a_millionth_of_range() -> None:
    scan = stripe_scan()
    m = StripeMsg.from_bytes(make_stripe().to_bytes())
    cloud = m.to_cloud(CAL)
    order = np.lexsort((scan.uv[:, 0], scan.laser))
    ref = scan.points[order]
    rel = np.linalg.norm(cloud.points_body - ref, axis=1) / np.linalg.norm(ref, axis=1)
    assert rel.max() < 1e-4  # the bar: 0.01 % of range
    assert np.median(rel) < 1e-5
    assert (cloud.robot, cloud.seq, cloud.t_ns, cloud.sent_ns) == (m.robot, m.seq, m.t_ns, m.sent_ns)
    np.testing.assert_array_equal(cloud.laser, m.laser)


def test_scans_schema_2_cannot_carry_are_refused_at_encoding() -> None:
    scan = stripe_scan()
    uv = scan.uv.copy()
    uv[5, 0] += 0.5
    with pytest.raises(WireError, match="whole-pixel columns"):
        StripeMsg.from_scan("rov1", 0, 1, Pose.identity(), Scan(scan.points, scan.laser, uv, scan.quality), FP)
    uv = scan.uv.copy()
    uv[5, 1] = np.nan
    with pytest.raises(WireError, match="finite"):
        StripeMsg.from_scan("rov1", 0, 1, Pose.identity(), Scan(scan.points, scan.laser, uv, scan.quality), FP)
    with pytest.raises(WireError, match="calib_id"):
        StripeMsg.from_scan("rov1", 0, 1, Pose.identity(), scan, b"short")


def test_fingerprint_survives_the_file_and_names_the_geometry(tmp_path: Path) -> None:
    path = tmp_path / "c.json"
    CAL.save(path)
    assert calibration_fingerprint(Calibration.load(path)) == FP
    assert calibration_fingerprint(CAL.with_lasers(CAL.lasers, {"note": "metadata only"})) == FP
    assert calibration_fingerprint(Calibration.paper(0.1001, 640, 360)) != FP
    assert len(FP) == 8


def test_to_cloud_refuses_another_calibration_and_impossible_pixels() -> None:
    m = make_stripe()
    with pytest.raises(WireError, match="calibration mismatch"):
        m.to_cloud(Calibration.paper(0.12, 640, 360))
    small = Calibration.paper(0.1, 320, 180)
    on_small = StripeMsg(
        m.robot, 0, 1, m.pose, calibration_fingerprint(small), m.laser, m.column, m.row_fx, m.quality_u8
    )
    with pytest.raises(WireError, match="outside the 320x180 image"):
        on_small.to_cloud(small)
    bad_laser = m.laser.copy()
    bad_laser[0] = 5
    with pytest.raises(WireError, match="laser index 5"):
        StripeMsg(m.robot, 0, 1, m.pose, FP, bad_laser, m.column, m.row_fx, m.quality_u8).to_cloud(CAL)


def test_every_truncation_is_refused() -> None:
    data = make_stripe().to_bytes()
    for cut in range(0, len(data), 7):
        with pytest.raises(WireError):
            StripeMsg.from_bytes(data[:cut])
        with pytest.raises(WireError):
            decode_cloud(data[:cut])


@pytest.mark.parametrize(
    ("change", "reason"),
    [
        ({"v": 3}, "schema version 3"),
        ({"type": "status"}, "type"),
        ({"n": 5}, "bytes, expected"),
        ({"runs": 0}, "'runs'"),
        ({"runs": 5}, "for the declared runs"),
        ({"calib": b"\x00" * 4}, "calibration fingerprint"),
        ({"calib": "abcdefgh"}, "'calib' must be binary"),
        ({"run_len": np.array([100, 509, 100, 508], "<u2").tobytes()}, "the runs hold"),
        ({"run_len": np.array([0, 609, 100, 509], "<u2").tobytes()}, "empty"),
        ({"run_u0": np.array([0, 65500, 0, 131], "<u2").tobytes()}, "beyond 65535"),
        ({"dv": b"\x00"}, "'dv' has 1 bytes"),
        ({"quality": b"\x00"}, "'quality'"),
        ({"seq": -1}, "'seq'"),
        ({"robot": "a/b"}, "not a valid name"),
        ({"pose": None}, "'pose' must be a map"),
    ],
)
def test_inconsistent_fields_are_refused(change: dict, reason: str) -> None:
    d = raw(make_stripe())
    d.update(change)
    with pytest.raises(WireError, match=reason):
        decode_cloud(repack(d))


@pytest.mark.parametrize("missing", ["robot", "seq", "t_ns", "pose", "calib", "n", "runs", "run_v0", "dv", "quality"])
def test_missing_field_is_named(missing: str) -> None:
    d = raw(make_stripe())
    del d[missing]
    with pytest.raises(WireError, match=missing):
        StripeMsg.from_bytes(repack(d))


def test_schema_1_decoder_names_the_version() -> None:
    with pytest.raises(WireError, match="schema version 2"):
        CloudMsg.from_bytes(make_stripe().to_bytes())


@settings(max_examples=200, deadline=None)
@given(st.integers(0, 4000), st.integers(0, 255))
def test_byte_flips_never_raise_anything_but_wire_error(pos: int, value: int) -> None:
    data = bytearray(make_stripe().to_bytes())
    data[pos % len(data)] = value
    with contextlib.suppress(WireError):
        decode_cloud(bytes(data))


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=400))
def test_random_bytes_never_raise_anything_but_wire_error(data: bytes) -> None:
    with contextlib.suppress(WireError):
        decode_cloud(data)


# ----------------------------------------------------------------------------- the base's side


def test_book_finds_stored_then_served_calibrations(tmp_path: Path) -> None:
    asked: list[str] = []
    served = Calibration.paper(0.12, 640, 360)

    def fetch(robot: str) -> Calibration | None:
        asked.append(robot)
        return served if robot == "rov2" else None

    book = CalibrationBook(lambda r: tmp_path / f"{r}.json", fetch, retry_s=60.0)
    CAL.save(tmp_path / "rov1.json")
    assert book.lookup("rov1", FP) == (CAL, "")
    assert asked == []  # the stored calibration answered
    assert book.lookup("rov2", calibration_fingerprint(served)) == (served, "")
    calib, reason = book.lookup("rov1", calibration_fingerprint(served))
    assert calib is None
    assert reason.startswith("calibration mismatch")
    assert FP.hex() in reason
    calib, reason = book.lookup("rov3", FP)
    assert calib is None
    assert reason.startswith("no calibration")
    book.lookup("rov3", FP)
    assert asked.count("rov3") == 1  # asked again only after retry_s


def _base_without_network(tmp_path: Path, served: Calibration | None) -> BaseStation:
    base = BaseStation(None, FleetKeys("t"), tmp_path / "state", map_mode="off")
    base.calibrations = CalibrationBook(base.calibration_path, lambda robot: served)
    return base


def test_base_refuses_a_cloud_of_another_calibration_and_takes_it_once_it_holds_it(tmp_path: Path) -> None:
    base = _base_without_network(tmp_path, served=None)
    payload = make_stripe().to_bytes()
    key = base.keys.cloud("rov1")
    base.store_calibration("rov1", Calibration.paper(0.12, 640, 360))
    base._ingest(key, payload, 0)
    rec = base.records["rov1"]
    assert (len(rec.seqs), rec.rejected) == (0, 1)
    assert "calibration mismatch" in rec.rejected_reasons
    base.checkpoint()
    assert base.ledger.acks_json("rov1")["ranges"] == []  # not acknowledged: the robot keeps it
    base.store_calibration("rov1", CAL)  # the operator stores the calibration the robot measured with
    base._ingest(key, payload, 0)
    assert (len(rec.seqs), rec.rejected, rec.points) == (1, 1, len(make_stripe()))
    base.checkpoint()
    assert base.ledger.acks_json("rov1")["ranges"] == [[42, 42]]


def test_base_triangulates_with_the_calibration_the_robot_serves(tmp_path: Path) -> None:
    base = _base_without_network(tmp_path, served=CAL)
    base._ingest(base.keys.cloud("rov1"), make_stripe().to_bytes(), 0)
    base._ingest(
        base.keys.cloud("rov1"), CloudMsg.from_scan("rov1", 7, 1, Pose.identity(), stripe_scan()).to_bytes(), 0
    )
    rec = base.records["rov1"]
    assert (len(rec.seqs), rec.rejected) == (2, 0)


def test_base_triangulation_goes_through_the_robots_flat_port() -> None:
    """A robot behind a flat port: the base triangulates its stripe rows through the same port (ignoring it
    would read the wall about 25 % short)."""
    from lrsensor import Sensor
    from lrsensor.sim import named_scene
    from lrsensor.sim.scenes import acrylic_port

    setup = named_scene("wall_1.0").with_port(acrylic_port(2.0))
    scan = Sensor(setup.calibration).process(setup.render(0).image)
    assert len(scan) > 3000
    calib_id = calibration_fingerprint(setup.calibration)
    msg = StripeMsg.from_scan("rov1", 0, 1, Pose(0.0, 0.0, 0.0, 0.0, 0.0, 0.0), scan, calib_id)
    cloud = StripeMsg.from_bytes(msg.to_bytes()).to_cloud(setup.calibration)
    order = np.lexsort((scan.uv[:, 0], scan.laser))
    ref = scan.points[order]
    rel = np.linalg.norm(cloud.points_body - ref, axis=1) / np.linalg.norm(ref, axis=1)
    assert rel.max() < 1e-4  # the bar of the compact cloud: 0.01 % of range
