"""ROS 2 over Zenoh without a bridge (issue 28, item 2): samples exactly as rmw_zenoh_cpp (Jazzy) carries them.

The expected key, hash, attachment layout and token shape are written here from ../CONVENTIONS (read from
rmw_zenoh's source), not taken from the code under test; the payloads are decoded with mcap-ros2-support's
CDR reader (an independent decoder) from the message definitions.
"""

from __future__ import annotations

import struct
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from waiting import wait_until

from lrsensor.calibration import Calibration
from lrsensor.frames import Pose
from services.fleet_tap import FleetTap
from services.imu import CsvImu
from services.ros2 import Ros2Error, Ros2Node, attachment, check_topic, dds_type_name, mangle
from services.ros2_views import Ros2FleetSink, Ros2ScanPublisher, body_to_base_link, ned_to_map, pose_stamped
from services.simsource import record_sim_dive
from services.sources import FolderSource
from services.testnet import TestNetwork

pytest.importorskip("rosbags")
dynamic = pytest.importorskip("mcap_ros2._dynamic")

JAZZY_POINTCLOUD2 = "RIHS01_9198cabf7da3796ae6fe19c4cb3bdd3525492988c70522628af5daa124bae2b5"
POINTCLOUD2_MSG = """std_msgs/Header header
uint32 height
uint32 width
sensor_msgs/PointField[] fields
bool is_bigendian
uint32 point_step
uint32 row_step
uint8[] data
bool is_dense
================================================================================
MSG: std_msgs/Header
builtin_interfaces/Time stamp
string frame_id
================================================================================
MSG: builtin_interfaces/Time
int32 sec
uint32 nanosec
================================================================================
MSG: sensor_msgs/PointField
string name
uint32 offset
uint8 datatype
uint32 count
"""


def decode(schema: str, text: str, payload: bytes) -> Any:
    return dynamic.generate_dynamic(schema, text)[schema](payload)


class Sniffer:
    """Everything on ``0/**`` (with attachments) and the ROS liveliness tokens, seen by a plain Zenoh session."""

    def __init__(self, session: Any) -> None:
        self.session = session
        self.samples: list[tuple[str, bytes, bytes | None]] = []
        self.sub = session.declare_subscriber("0/**", self._on)

    def _on(self, s: Any) -> None:
        att = s.attachment.to_bytes() if s.attachment is not None else None
        self.samples.append((str(s.key_expr), s.payload.to_bytes(), att))

    def tokens(self) -> list[str]:
        return [str(r.ok.key_expr) for r in self.session.liveliness().get("@ros2_lv/0/**", timeout=2.0) if r.ok]


def test_names_and_attachment_layout() -> None:
    assert dds_type_name("sensor_msgs/msg/PointCloud2") == "sensor_msgs::msg::dds_::PointCloud2_"
    assert mangle("/lrs/tank/rov1/points") == "%lrs%tank%rov1%points"
    att = attachment(7, 1_700_000_000_123_456_789, bytes(range(16)))
    assert len(att) == 33
    assert struct.unpack_from("<qqB", att) == (7, 1_700_000_000_123_456_789, 16)
    assert att[17:] == bytes(range(16))
    for bad in ("points", "/a//b", "/a/1b", "/a/b-c", "/a/"):
        with pytest.raises(Ros2Error, match="invalid ROS 2 topic"):
            check_topic(bad)
    with pytest.raises(Ros2Error, match="package/msg/Name"):
        dds_type_name("PointCloud2")


def test_frames_follow_rep_103_and_105() -> None:
    # a point 1 m ahead, 2 m to the right, 3 m below the body is (1, -2, -3) in base_link
    np.testing.assert_allclose(body_to_base_link(np.array([[1.0, 2.0, 3.0]])), [[1.0, -2.0, -3.0]])
    # 1 m north, 2 m east, 3 m deep is (2, 1, -3) in the ENU map
    np.testing.assert_allclose(ned_to_map(np.array([[1.0, 2.0, 3.0]])), [[2.0, 1.0, -3.0]])


def test_a_scan_is_published_exactly_as_rmw_zenoh_carries_it() -> None:
    with TestNetwork("t") as net:
        sniffer = Sniffer(net.session())
        node = Ros2Node(net.session(), name="lrsensor_rov1")
        pub = Ros2ScanPublisher(node, net.keys.root, "rov1")
        pts = np.array([[1.0, 0.2, -0.1], [1.5, -0.3, 0.25]], dtype=np.float32)
        for i in range(3):
            pub.publish(1_700_000_000_000_000_000 + i, pts)
        assert wait_until(lambda: len(sniffer.samples) == 3, 10.0)
        tokens = sniffer.tokens()
        node.close()
    key, payload, _ = sniffer.samples[0]
    assert key == f"0/lrs/t/rov1/points/sensor_msgs::msg::dds_::PointCloud2_/{JAZZY_POINTCLOUD2}"
    assert payload[:4] == b"\x00\x01\x00\x00"
    msg = decode("sensor_msgs/PointCloud2", POINTCLOUD2_MSG, payload)
    assert (msg.header.frame_id, msg.header.stamp.sec, msg.header.stamp.nanosec) == ("rov1/base_link", 1_700_000_000, 0)
    assert [(f.name, f.offset, f.datatype) for f in msg.fields] == [("x", 0, 7), ("y", 4, 7), ("z", 8, 7)]
    got = np.frombuffer(bytes(msg.data), dtype="<f4").reshape(-1, 3)
    np.testing.assert_allclose(got, pts * np.array([1, -1, -1], dtype=np.float32))
    seqs = []
    for _, _, a in sniffer.samples:
        assert a is not None
        assert len(a) == 33
        seq, t_pub, n = struct.unpack_from("<qqB", a)
        assert n == 16
        assert abs(t_pub - time.time_ns()) < 60e9  # the publish wall clock
        seqs.append(seq)
    assert seqs == [1, 2, 3]
    assert len({a[17:] for _, _, a in sniffer.samples if a}) == 1  # one GID per publisher
    mp = [t.split("/") for t in tokens if "/MP/" in t]
    assert len(mp) == 1
    chunks = mp[0]
    assert len(chunks) == 13
    assert all(chunks)
    assert chunks[5] == "MP"
    assert chunks[9:12] == ["%lrs%t%rov1%points", "sensor_msgs::msg::dds_::PointCloud2_", JAZZY_POINTCLOUD2]
    assert len(chunks[12].split(":")) == 6
    assert any("/NN/" in t and t.endswith("/lrsensor_rov1") for t in tokens)


@pytest.fixture(scope="module")
def dive(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return record_sim_dive(tmp_path_factory.mktemp("ros2") / "rov1", "rov1", n_frames=16, seed=4, clean_water=True)


def test_the_base_view_publishes_map_clouds_poses_and_planes(dive: Path) -> None:
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_JAZZY)
    marker_text = ts.generate_msgdef("visualization_msgs/msg/MarkerArray", ros_version=2)[0]
    pose_text = ts.generate_msgdef("geometry_msgs/msg/PoseStamped", ros_version=2)[0]
    with TestNetwork("b") as net:
        base = net.start_base(None, map_mode="on")
        sniffer = Sniffer(net.session())
        node = Ros2Node(net.session(), name="lrsensor_base")
        tap = FleetTap(net.session(), net.keys, [Ros2FleetSink(node, net.keys.root)])
        h = net.start_rov("rov1", FolderSource(dive), CsvImu(dive / "imu.csv"), Calibration.load(dive / "calib.json"))
        assert h.join(60)
        assert wait_until(lambda: base.status()["robots"].get("rov1", {}).get("received") == 16, 20.0)
        base.flush_map()

        def planes_shown() -> bool:  # the first MarkerArray may be the empty map of the start
            arrays = [decode("visualization_msgs/MarkerArray", marker_text, p) for k, p, _ in list(sniffer.samples)
                      if "MarkerArray" in k]  # fmt: skip
            return any(m.action == 0 for arr in arrays for m in arr.markers)

        assert wait_until(planes_shown, 20.0)
        assert wait_until(tap.idle, 10.0)
        tap.close()
        node.close()
    by_topic: dict[str, list[bytes]] = {}
    for key, payload, att in sniffer.samples:
        assert att is not None
        assert len(att) == 33
        by_topic.setdefault(key.split("/")[4], []).append(payload)  # 0/lrs/b/<rov1|map>/<topic>/<type>/<hash>
    assert len(by_topic["points_map"]) == 16
    assert len(by_topic["pose"]) == 16
    cloud = decode("sensor_msgs/PointCloud2", POINTCLOUD2_MSG, by_topic["points_map"][0])
    assert cloud.header.frame_id == "map"
    assert cloud.width > 0
    pose = decode("geometry_msgs/PoseStamped", pose_text, by_topic["pose"][0])
    assert pose.header.frame_id == "map"
    markers = [decode("visualization_msgs/MarkerArray", marker_text, p) for p in by_topic["planes"]]
    shown = {m.id for arr in markers for m in arr.markers if m.action == 0}
    assert shown  # the dive's walls as TRIANGLE_LIST markers
    assert all(m.type == 11 and len(m.points) == 6 for arr in markers for m in arr.markers if m.action == 0)


def test_pose_conversion_keeps_heading() -> None:
    from rosbags.typesys import Stores, get_typestore

    class FakeNode:
        _ts = get_typestore(Stores.ROS2_JAZZY)

    # heading east (yaw 90 deg in NED) is yaw 0 in ENU: the base_link x axis points along map x
    msg = pose_stamped(FakeNode(), Pose(1.0, 2.0, 3.0, 0.0, 0.0, np.pi / 2), 0)  # type: ignore[arg-type]
    q = msg.pose.orientation
    assert (msg.pose.position.x, msg.pose.position.y, msg.pose.position.z) == (2.0, 1.0, -3.0)
    assert abs(abs(q.w) - 1.0) < 1e-9
    assert pose_stamped(FakeNode(), Pose(float("nan"), float("nan"), 3.0, 0, 0, 0), 0) is None  # type: ignore[arg-type]
