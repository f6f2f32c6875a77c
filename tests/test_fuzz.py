"""Property-based fuzzing of every decoder: bad input is rejected with the decoder's own error, never a crash.

Decoders: calibration files (``Calibration.from_json``), wire messages (``CloudMsg``, ``CalibMsg``,
``StatusMsg``), the OpenROV serial telemetry parser, CSV IMU logs, image files of a recorded dive and the
image check of ``Sensor.process``. Each gets arbitrary bytes, structured-but-wrong values and mutations of a
valid input (truncation, byte flips, insertions). ``benchmarks/fuzz_decoders.py`` runs the same generators at
volume and reports the rejection reasons.
"""

from __future__ import annotations

import itertools
import json
import math
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from lrsensor.calibration import Calibration
from lrsensor.errors import CalibrationFileError, ExtractionError
from lrsensor.frames import Pose
from services.errors import ImuError, WireError
from services.imu import CsvImu, OpenRovParser
from services.wire import CalibMsg, CloudMsg, StatusMsg

FAST = settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.too_slow])


# ---------------------------------------------------------------------------------------------------------
# Generators shared with benchmarks/fuzz_decoders.py
# ---------------------------------------------------------------------------------------------------------


def valid_cloud(n: int = 20, seed: int = 0) -> CloudMsg:
    rng = np.random.default_rng(seed)
    return CloudMsg(
        robot="rov1",
        seq=int(rng.integers(0, 1000)),
        t_ns=1_700_000_000_000_000_000,
        pose=Pose(1.0, -2.0, 3.0, 0.1, -0.05, 1.2),
        points_body=rng.normal(size=(n, 3)).astype(np.float32),
        laser=rng.integers(0, 2, size=n).astype(np.uint8),
        quality=rng.random(n).astype(np.float32),
        uv=rng.random((n, 2)).astype(np.float32) * 1000,
        sent_ns=1_700_000_000_000_000_100,
    )


def valid_payloads() -> dict[str, bytes]:
    return {
        "cloud": valid_cloud().to_bytes(),
        "calib": CalibMsg("rov1", Calibration.paper(0.1)).to_bytes(),
        "status": StatusMsg("rov1", 1_700_000_000_000_000_000, "running", 10, 9, 1, 0, 8).to_bytes(),
    }


DECODERS: dict[str, Any] = {"cloud": CloudMsg, "calib": CalibMsg, "status": StatusMsg}

msgpack_values = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(-(2**63), 2**64 - 1)
    | st.floats(allow_nan=True, allow_infinity=True)
    | st.text(max_size=12)
    | st.binary(max_size=64),
    lambda inner: st.lists(inner, max_size=5) | st.dictionaries(st.text(max_size=8), inner, max_size=5),
    max_leaves=25,
)
json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=10),
    lambda inner: st.lists(inner, max_size=6) | st.dictionaries(st.text(max_size=10), inner, max_size=6),
    max_leaves=30,
)


@st.composite
def mutated(draw: st.DrawFn, data: bytes) -> bytes:
    """A valid payload after 1-4 random edits: truncation, byte flip, insertion, deletion, duplication."""
    out = bytearray(data)
    for _ in range(draw(st.integers(1, 4))):
        op = draw(st.sampled_from(["truncate", "flip", "insert", "delete", "dup"]))
        i = draw(st.integers(0, max(0, len(out) - 1)))
        if op == "truncate":
            del out[i:]
        elif op == "flip" and out:
            out[i] ^= draw(st.integers(1, 255))
        elif op == "insert":
            out[i:i] = draw(st.binary(min_size=1, max_size=8))
        elif op == "delete":
            del out[i : i + draw(st.integers(1, 8))]
        elif op == "dup":
            out[i:i] = out[i : i + draw(st.integers(1, 16))]
    return bytes(out)


@st.composite
def field_swapped(draw: st.DrawFn, data: bytes) -> bytes:
    """A valid message map with some fields replaced by arbitrary values, removed, or added."""
    obj = msgpack.unpackb(data, raw=False)
    for _ in range(draw(st.integers(1, 3))):
        key = draw(st.sampled_from(sorted(obj)))
        action = draw(st.sampled_from(["replace", "remove", "add"]))
        if action == "replace":
            obj[key] = draw(msgpack_values)
        elif action == "remove":
            obj.pop(key, None)
        else:
            obj[draw(st.text(max_size=6))] = draw(msgpack_values)
    try:
        return bytes(msgpack.packb(obj, use_bin_type=True))
    except (OverflowError, ValueError, TypeError):
        assume(False)
        raise AssertionError from None


def _check_cloud(msg: CloudMsg) -> None:
    n = len(msg)
    assert msg.points_body.shape == (n, 3)
    assert msg.laser.shape == (n,)
    assert msg.quality.shape == (n,)
    assert np.all(np.isfinite(msg.points_body))
    assert np.all(np.isfinite(msg.quality))
    assert all(math.isfinite(getattr(msg.pose, f)) for f in ("down_m", "roll_rad", "pitch_rad", "yaw_rad"))
    # the horizontal position is either known (finite) or unknown as a whole (null on the wire: NaN)
    ne = (msg.pose.north_m, msg.pose.east_m)
    assert all(math.isfinite(v) for v in ne) or all(math.isnan(v) for v in ne)
    assert msg.seq >= 0
    assert msg.t_ns >= 0


def decode_or_reject(kind: str, payload: bytes) -> Any:
    """Decode; None when rejected with WireError. Any other exception fails the test."""
    msg = None
    try:
        msg = DECODERS[kind].from_bytes(payload)
    except WireError as err:
        reason = str(err)
    else:
        reason = ""
    if reason or msg is None:
        assert reason, "a rejection must say why"
        return None
    if kind == "cloud":
        _check_cloud(msg)
    return msg


# ---------------------------------------------------------------------------------------------------------
# Wire messages
# ---------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("kind", sorted(DECODERS))
def test_valid_payloads_round_trip(kind: str) -> None:
    assert decode_or_reject(kind, valid_payloads()[kind]) is not None


@pytest.mark.parametrize("kind", sorted(DECODERS))
@FAST
@given(data=st.binary(max_size=512))
def test_wire_arbitrary_bytes(kind: str, data: bytes) -> None:
    decode_or_reject(kind, data)


@pytest.mark.parametrize("kind", sorted(DECODERS))
@FAST
@given(data=st.data())
def test_wire_mutated_payloads(kind: str, data: st.DataObject) -> None:
    decode_or_reject(kind, data.draw(mutated(valid_payloads()[kind])))


@pytest.mark.parametrize("kind", sorted(DECODERS))
@FAST
@given(data=st.data())
def test_wire_fields_swapped(kind: str, data: st.DataObject) -> None:
    decode_or_reject(kind, data.draw(field_swapped(valid_payloads()[kind])))


@pytest.mark.parametrize("kind", sorted(DECODERS))
@FAST
@given(obj=msgpack_values)
def test_wire_arbitrary_msgpack(kind: str, obj: Any) -> None:
    try:
        payload = msgpack.packb(obj, use_bin_type=True)
    except (OverflowError, ValueError, TypeError):
        assume(False)
    decode_or_reject(kind, payload)


@pytest.mark.parametrize(
    ("edit", "reason"),
    [
        ({"v": 2}, "version"),
        ({"v": True}, "version"),
        ({"type": "calib"}, "type"),
        ({"n": 21}, "bytes"),
        ({"n": 10**9}, "outside"),
        ({"points": b"\x00\x00\xc0\x7f" * 60}, "not finite"),  # NaN points
        ({"pose": {"north_m": float("inf")}}, "pose"),
        ({"robot": "../etc"}, "robot"),
        ({"robot": "base"}, "reserved"),
        ({"seq": -1}, "seq"),
        ({"t_ns": -1}, "t_ns"),
    ],
)
def test_cloud_rejections_name_the_reason(edit: dict[str, Any], reason: str) -> None:
    obj = msgpack.unpackb(valid_payloads()["cloud"], raw=False)
    obj.update(edit)
    with pytest.raises(WireError, match=reason):
        CloudMsg.from_bytes(msgpack.packb(obj, use_bin_type=True))


def test_oversized_and_trailing_payloads() -> None:
    from services.wire import MAX_PAYLOAD_BYTES

    with pytest.raises(WireError, match="larger"):
        CloudMsg.from_bytes(b"\x00" * (MAX_PAYLOAD_BYTES + 1))
    with pytest.raises(WireError, match="trailing"):
        CloudMsg.from_bytes(valid_payloads()["cloud"] + b"\x01")
    with pytest.raises(WireError, match="empty"):
        CloudMsg.from_bytes(b"")


# ---------------------------------------------------------------------------------------------------------
# Calibration files
# ---------------------------------------------------------------------------------------------------------


def _calib_or_reject(text: str | bytes) -> Calibration | None:
    try:
        calib = Calibration.from_json(text, "fuzz")
    except CalibrationFileError as err:
        reason = str(err)
        assert reason
        return None
    assert calib.camera.width > 0
    assert all(np.isfinite(calib.R_cam_body).ravel())
    return calib


@FAST
@given(data=st.binary(max_size=400))
def test_calibration_arbitrary_bytes(data: bytes) -> None:
    _calib_or_reject(data)


@FAST
@given(obj=json_values)
def test_calibration_arbitrary_json(obj: Any) -> None:
    _calib_or_reject(json.dumps(obj))


@FAST
@given(data=st.data())
def test_calibration_mutated_fields(data: st.DataObject) -> None:
    obj = Calibration.paper(0.1).to_dict()

    def paths(o: Any, prefix: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
        out = [prefix]
        if isinstance(o, dict):
            for k, v in o.items():
                out += paths(v, (*prefix, k))
        elif isinstance(o, list):
            for i, v in enumerate(o):
                out += paths(v, (*prefix, i))
        return out

    for _ in range(data.draw(st.integers(1, 3))):
        path = data.draw(st.sampled_from(paths(obj)[1:]))
        parent = obj
        for p in path[:-1]:
            parent = parent[p]
        if data.draw(st.booleans()) and isinstance(parent, dict):
            del parent[path[-1]]
        else:
            parent[path[-1]] = data.draw(json_values)
        if not isinstance(obj, dict):
            break
    _calib_or_reject(json.dumps(obj))


@FAST
@given(data=st.data())
def test_calibration_mutated_text(data: st.DataObject) -> None:
    _calib_or_reject(data.draw(mutated(Calibration.paper(0.1).to_json().encode())))


@pytest.mark.parametrize("bad", ["NaN", "Infinity", "-Infinity", "1e999"])
def test_calibration_non_finite_is_refused(bad: str) -> None:
    text = Calibration.paper(0.1).to_json().replace('"fx": ', f'"fx": {bad}, "_": ', 1)
    with pytest.raises(CalibrationFileError):
        Calibration.from_json(text)


# ---------------------------------------------------------------------------------------------------------
# Serial telemetry and CSV logs
# ---------------------------------------------------------------------------------------------------------

GOOD_LINE = b"hdgd:90.5;deep:1.25;pitc:-3.0;roll:2.0;temp:18.2\n"
telemetry_bytes = st.lists(
    st.one_of(
        st.binary(max_size=40),
        st.just(GOOD_LINE),
        st.sampled_from([b"\n", b"\r\n", b";", b":", b"deep:", b"nan", b"inf", b"1e400", b"\xff\xfe", b"\x00"]),
        st.builds(
            lambda k, v: f"{k}:{v};".encode(),
            st.sampled_from(["hdgd", "deep", "pitc", "roll", "x"]),
            st.floats(allow_nan=True, allow_infinity=True),
        ),
    ),
    max_size=30,
).map(b"".join)


@settings(max_examples=300, deadline=None)
@given(stream=telemetry_bytes, cuts=st.lists(st.integers(0, 2000), max_size=8))
def test_serial_parser_never_raises_and_is_chunking_invariant(stream: bytes, cuts: list[int]) -> None:
    whole = OpenRovParser()
    a = whole.feed(stream)
    chunked = OpenRovParser()
    b = []
    bounds = sorted({0, len(stream), *(c for c in cuts if c < len(stream))})
    for lo, hi in itertools.pairwise(bounds):
        b += chunked.feed(stream[lo:hi])
    assert a == b
    assert whole.rejected == chunked.rejected
    for r in a:
        assert all(math.isfinite(v) for v in (r.roll_rad, r.pitch_rad, r.yaw_rad, r.down_m))
        assert -math.pi <= r.yaw_rad < math.pi


def test_serial_parser_counts_garbage_and_recovers() -> None:
    p = OpenRovParser(max_line_bytes=64)
    out = p.feed(b"\xff\xfegarbage\n" + b"x" * 200 + b"\nroll:nan\ndeep:1e400\n" + GOOD_LINE)
    assert p.rejected == 4
    assert len(out) == 1
    assert out[0].down_m == pytest.approx(1.25)


csv_text = st.lists(
    st.lists(
        st.one_of(st.text(max_size=8), st.integers().map(str), st.floats().map(repr), st.just("nan")),
        max_size=9,
    ).map(",".join),
    max_size=12,
).map("\n".join)


@settings(max_examples=120, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(body=csv_text, with_header=st.booleans())
def test_csv_imu_rejects_with_imu_error_only(tmp_path: Path, body: str, with_header: bool) -> None:
    path = tmp_path / "imu.csv"
    header = "t_ns,roll_deg,pitch_deg,yaw_deg,north_m,east_m,down_m\n" if with_header else ""
    path.write_text(header + body, encoding="utf-8", errors="surrogatepass")
    try:
        imu = CsvImu(path)
    except ImuError as err:
        reason = str(err)
        assert reason
        return
    assert imu.rejected >= 0


def test_csv_imu_binary_garbage(tmp_path: Path) -> None:
    path = tmp_path / "imu.csv"
    path.write_bytes(b"t_ns,roll_deg,pitch_deg,yaw_deg,north_m,east_m,down_m\n\xff\xfe\x00garbage\n")
    with pytest.raises(ImuError):
        CsvImu(path)


# ---------------------------------------------------------------------------------------------------------
# Images
# ---------------------------------------------------------------------------------------------------------


def test_unreadable_image_files_are_skipped_and_counted(tmp_path: Path) -> None:
    import cv2

    from services.sources import FolderSource

    good = np.zeros((48, 64, 3), np.uint8)
    ok, png = cv2.imencode(".png", good)
    assert ok
    raw = png.tobytes()
    rng = np.random.default_rng(7)
    t0 = 1_700_000_000_000_000_000
    files = {
        t0: raw,
        t0 + 1: raw[: len(raw) // 2],  # truncated
        t0 + 2: b"",  # empty
        t0 + 3: rng.integers(0, 256, 5000, dtype=np.uint8).tobytes(),  # noise
        t0 + 4: raw[:20] + bytes(200),  # header then zeros
        t0 + 5: raw,
    }
    for t, data in files.items():
        (tmp_path / f"{t}.png").write_bytes(data)
    with FolderSource(tmp_path) as src:
        frames = list(src)
    assert [f.t_ns for f in frames] == [t0, t0 + 5]
    assert src.unreadable == 4


@pytest.mark.parametrize(
    "image",
    [
        np.zeros((1080, 1920), np.uint8),
        np.zeros((1080, 1920, 4), np.uint8),
        np.zeros((1080, 1920, 3), np.float32),
        np.zeros((100, 100, 3), np.uint8),
        np.zeros((0, 0, 3), np.uint8),
        "not an image",
        None,
    ],
)
def test_sensor_rejects_bad_images_with_extraction_error(image: Any) -> None:
    from lrsensor.sensor import Sensor

    with pytest.raises(ExtractionError):
        Sensor(Calibration.paper(0.1)).process(image)
