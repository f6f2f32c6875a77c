"""The fleet as ROS 2 messages, in the frames a ROS user expects (REP 103 / REP 105).

Frames (docs/ros2.md):

* ``<robot>/base_link``: the robot's body, REP 103 (x forward, y left, z up). lrsensor's body frame is
  x forward, y right, z down, so a body point ``(x, y, z)`` is ``(x, -y, -z)`` in ``base_link``.
* ``map``: the fleet's world frame, REP 105 ENU (x east, y north, z up) with its origin at the fleet's NED
  origin, so an NED point ``(n, e, d)`` is ``(e, n, -d)`` in ``map``; an attitude ``R_ned_from_body`` becomes
  ``A R B`` with ``A`` the NED->ENU swap and ``B = diag(1, -1, -1)``.

Messages (rosbags' Jazzy type store): ``sensor_msgs/msg/PointCloud2`` (``x y z`` FLOAT32, ``header.stamp``
the capture time), ``geometry_msgs/msg/PoseStamped`` and ``visualization_msgs/msg/MarkerArray`` (each plane
a ``TRIANGLE_LIST`` marker, ``ns`` "planes", ``id`` the plane's id; removed planes ``DELETE``).

:class:`Ros2ScanPublisher` is the ROV's view (``lrsensor rov --ros2``); :class:`Ros2FleetSink` the base
station's (``lrsensor base --ros2``), fed by a :class:`~services.fleet_tap.FleetTap`.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from lrsensor.calibration import Calibration
from lrsensor.frames import Pose, body_to_ned, quat_from_R
from lrsensor.scan import Scan

from .ros2 import Ros2Node
from .wire import CloudMsg

#: The fleet's world frame in ROS (ENU).
MAP_FRAME = "map"
#: NED -> ENU (a symmetric permutation with a sign: its own inverse).
A_ENU_FROM_NED = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
#: lrsensor body (x forward, y right, z down) -> REP 103 base_link (x forward, y left, z up), and back.
B_FLU_FROM_FRD = np.diag([1.0, -1.0, -1.0])
#: PointField datatype FLOAT32.
FLOAT32 = 7
#: Marker types and actions (visualization_msgs/msg/Marker).
TRIANGLE_LIST, ADD, DELETE = 11, 0, 2
PLANE_RGBA = (1.0, 0.55, 0.1, 0.6)


def base_link(robot: str) -> str:
    """The ROS frame id of a robot's body."""
    return f"{robot}/base_link"


def build(node: Ros2Node, typename: str, **values: Any) -> Any:
    """A rosbags message of ``typename`` with ``values``; every other field its zero (nested ones too)."""
    from rosbags.interfaces import Nodetype

    ts = node._ts

    def zero(desc: Any) -> Any:
        kind, arg = desc
        if kind == Nodetype.NAME:
            return build(node, arg)
        if kind == Nodetype.BASE:
            name = arg[0]
            return "" if name == "string" else False if name == "bool" else 0.0 if name.startswith("float") else 0
        sub, length = arg
        if sub[0] == Nodetype.BASE and sub[1][0] != "string":
            dtype = {"bool": np.bool_, "byte": np.uint8, "char": np.uint8}.get(sub[1][0], sub[1][0])
            return np.zeros(length if kind == Nodetype.ARRAY else 0, dtype=dtype)
        return [zero(sub) for _ in range(length if kind == Nodetype.ARRAY else 0)]

    fields = {name: values[name] if name in values else zero(desc) for name, desc in ts.fielddefs[typename][1]}
    return ts.types[typename](**fields)


def header(node: Ros2Node, stamp_ns: int, frame_id: str) -> Any:
    """``std_msgs/msg/Header`` at ``stamp_ns`` (ns since the epoch)."""
    stamp = build(
        node, "builtin_interfaces/msg/Time", sec=int(stamp_ns // 1_000_000_000), nanosec=int(stamp_ns % 1_000_000_000)
    )
    return build(node, "std_msgs/msg/Header", stamp=stamp, frame_id=frame_id)


def pointcloud2(node: Ros2Node, points: np.ndarray, stamp_ns: int, frame_id: str) -> Any:
    """``sensor_msgs/msg/PointCloud2`` of (N, 3) points (metres) in ``frame_id``: ``x y z`` float32."""
    pts = np.ascontiguousarray(points, dtype="<f4").reshape(-1, 3)
    fields = [
        build(node, "sensor_msgs/msg/PointField", name=c, offset=4 * i, datatype=FLOAT32, count=1)
        for i, c in enumerate("xyz")
    ]
    return build(
        node,
        "sensor_msgs/msg/PointCloud2",
        header=header(node, stamp_ns, frame_id),
        height=1,
        width=pts.shape[0],
        fields=fields,
        is_bigendian=False,
        point_step=12,
        row_step=12 * pts.shape[0],
        data=pts.view(np.uint8).reshape(-1),
        is_dense=True,
    )


def body_to_base_link(points_body: np.ndarray) -> np.ndarray:
    """(N, 3) body points (x forward, y right, z down) in REP 103 ``base_link`` (x forward, y left, z up)."""
    return np.asarray(points_body, dtype=float) @ B_FLU_FROM_FRD.T


def ned_to_map(points_ned: np.ndarray) -> np.ndarray:
    """(N, 3) NED points in the ENU ``map`` frame."""
    return np.asarray(points_ned, dtype=float) @ A_ENU_FROM_NED.T


def pose_stamped(node: Ros2Node, pose: Pose, stamp_ns: int) -> Any | None:
    """``geometry_msgs/msg/PoseStamped`` of ``base_link`` in ``map``; None without a horizontal position."""
    if not (math.isfinite(pose.north_m) and math.isfinite(pose.east_m)):
        return None
    p = ned_to_map(pose.p_ned[None, :])[0]
    w, x, y, z = (float(v) for v in quat_from_R(A_ENU_FROM_NED @ pose.R_ned_from_body @ B_FLU_FROM_FRD))
    msg_pose = build(
        node,
        "geometry_msgs/msg/Pose",
        position=build(node, "geometry_msgs/msg/Point", x=float(p[0]), y=float(p[1]), z=float(p[2])),
        orientation=build(node, "geometry_msgs/msg/Quaternion", x=x, y=y, z=z, w=w),
    )
    return build(node, "geometry_msgs/msg/PoseStamped", header=header(node, stamp_ns, MAP_FRAME), pose=msg_pose)


def plane_markers(node: Ros2Node, planes: list[dict[str, Any]], stamp_ns: int) -> Any:
    """``visualization_msgs/msg/MarkerArray`` of map planes (the map keys' JSON) in ``map``."""
    r, g, b, a = PLANE_RGBA
    markers = []
    for plane in planes:
        common = {"header": header(node, stamp_ns, MAP_FRAME), "ns": "planes", "id": int(plane["id"])}
        if plane.get("removed"):
            markers.append(build(node, "visualization_msgs/msg/Marker", action=DELETE, **common))
            continue
        corners = plane.get("extent", {}).get("corners") or []
        if len(corners) != 4:
            continue
        c = ned_to_map(np.asarray(corners, dtype=float))
        pts = [
            build(node, "geometry_msgs/msg/Point", x=float(q[0]), y=float(q[1]), z=float(q[2]))
            for q in c[[0, 1, 2, 0, 2, 3]]
        ]
        identity = build(node, "geometry_msgs/msg/Pose", orientation=build(node, "geometry_msgs/msg/Quaternion", w=1.0))
        markers.append(
            build(
                node,
                "visualization_msgs/msg/Marker",
                type=TRIANGLE_LIST,
                action=ADD,
                pose=identity,
                scale=build(node, "geometry_msgs/msg/Vector3", x=1.0, y=1.0, z=1.0),
                color=build(node, "std_msgs/msg/ColorRGBA", r=r, g=g, b=b, a=a),
                points=pts,
                **common,
            )
        )
    return build(node, "visualization_msgs/msg/MarkerArray", markers=markers)


class Ros2ScanPublisher:
    """The ROV's scans as ``sensor_msgs/msg/PointCloud2`` on ``/<prefix>/<fleet>/<robot>/points`` in
    ``<robot>/base_link``.

    Args:
        node: the ROS 2 node (on the robot's Zenoh session).
        root: the fleet's key root ``<prefix>/<fleet>`` (the topic's namespace).
        robot: the robot's name.
    """

    def __init__(self, node: Ros2Node, root: str, robot: str) -> None:
        self.node = node
        self.robot = robot
        self.publisher = node.publisher(f"/{root}/{robot}/points", "sensor_msgs/msg/PointCloud2")

    def publish(self, t_ns: int, points_body: np.ndarray) -> None:
        """Publish one scan: (N, 3) body points, metres, captured at ``t_ns``."""
        pts = body_to_base_link(points_body)
        self.publisher.publish(pointcloud2(self.node, pts, t_ns, base_link(self.robot)))


class Ros2ScanView:
    """``lrsensor rov --ros2``: the robot's own ROS 2 node (``lrsensor_<robot>``) publishing its scans.

    Args:
        session: the robot's Zenoh session.
        root: the fleet's key root ``<prefix>/<fleet>``.
        robot: the robot's name (its topic ``/<root>/<robot>/points`` must be a valid ROS 2 name).
        domain: the ROS domain id.
    """

    def __init__(self, session: Any, root: str, robot: str, domain: int = 0) -> None:
        safe = "".join(ch if ch.isalnum() else "_" for ch in robot)
        self.node = Ros2Node(session, name=f"lrsensor_{safe}", domain=domain)
        try:
            self.scans = Ros2ScanPublisher(self.node, root, robot)
        except Exception:
            self.node.close()
            raise
        self.publisher = self.scans.publisher

    def on_scan(self, t_ns: int, scan: Scan) -> None:
        """Publish one scan (the ROV calls it after each cloud)."""
        self.scans.publish(t_ns, scan.points)

    def close(self) -> None:
        """Withdraw the node and its publisher."""
        self.node.close()


class Ros2FleetSink:
    """The base station's ROS 2 view, a :class:`~services.fleet_tap.TapSink`: per robot its clouds in ``map``
    (``/<root>/<robot>/points_map``) and its pose (``/<root>/<robot>/pose``, clouds with a horizontal position
    only), and the map's planes (``/<root>/map/planes``, a MarkerArray of the planes that changed).
    """

    def __init__(self, node: Ros2Node, root: str) -> None:
        self.node = node
        self.root = root
        self._pubs: dict[str, Any] = {}
        self._planes = node.publisher(f"/{root}/map/planes", "visualization_msgs/msg/MarkerArray")

    def _pub(self, topic: str, typename: str) -> Any:
        pub = self._pubs.get(topic)
        if pub is None:
            pub = self._pubs[topic] = self.node.publisher(topic, typename)
        return pub

    def raw_cloud(self, robot: str, payload: bytes, log_ns: int) -> None:
        """Not shown in ROS (the decoded cloud is)."""

    def calibration(self, robot: str, calibration: Calibration, log_ns: int) -> None:
        """Not shown in ROS."""

    def status(self, data: dict[str, Any], log_ns: int) -> None:
        """Not shown in ROS."""

    def cloud(self, msg: CloudMsg, log_ns: int) -> None:
        """Publish the cloud in ``map`` and the robot's pose (when the cloud has a horizontal position)."""
        pose_msg = pose_stamped(self.node, msg.pose, msg.t_ns)
        if pose_msg is None:
            return
        pts = ned_to_map(body_to_ned(msg.points_body.astype(float), msg.pose))
        cloud = pointcloud2(self.node, pts, msg.t_ns, MAP_FRAME)
        self._pub(f"/{self.root}/{msg.robot}/points_map", "sensor_msgs/msg/PointCloud2").publish(cloud)
        self._pub(f"/{self.root}/{msg.robot}/pose", "geometry_msgs/msg/PoseStamped").publish(pose_msg)

    def map_update(self, planes: list[dict[str, Any]], t_ns: int, log_ns: int) -> None:
        """Publish the changed planes as markers."""
        self._planes.publish(plane_markers(self.node, planes, t_ns))
