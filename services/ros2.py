"""ROS 2 over Zenoh without a bridge: publishers whose samples are exactly what ``rmw_zenoh_cpp`` carries.

ROS 2 Jazzy nodes on ``rmw_zenoh_cpp`` (0.2.4 or later) talk over a Zenoh router (``rmw_zenohd``, by default
``tcp/localhost:7447``). A sample is theirs when it has (docs/ros2.md has the details and their sources):

* the data key ``<domain>/<topic without the leading '/'>/<DDS type name>/<RIHS01 type hash>``, e.g.
  ``0/lrs/tank/rov1/points/sensor_msgs::msg::dds_::PointCloud2_/RIHS01_9198...``: a wrong hash delivers
  nothing;
* a CDR little-endian payload with its 4-byte encapsulation header (``00 01 00 00``), serialized by rosbags;
* an attachment of exactly 33 bytes: int64 LE sequence number (from 1), int64 LE publish time (wall clock, ns
  since the epoch), the byte 16 (the GID's length), the 16-byte GID of the publisher (constant);
* the publisher's liveliness token ``@ros2_lv/<domain>/<zid>/<node id>/<entity id>/MP/<enclave>/<namespace>/
  <node>/<topic>/<type>/<hash>/<qos>`` with ``/`` inside names written ``%``; the node has its own token
  (``NN``), so ``ros2 node list`` shows it.

rmw_zenoh derives the GID from an XXH3-128 hash of the token; any constant 16 bytes serve the same purpose
(subscribers only compare it), so a BLAKE2b digest of the token keeps the dependency list short.
"""

from __future__ import annotations

import argparse
import hashlib
import itertools
import logging
import struct
import threading
import time
from typing import Any

from .errors import ServiceError
from .zconfig import undeclare_all

log = logging.getLogger(__name__)

#: rmw_zenoh's liveliness admin space.
ADMIN_SPACE = "@ros2_lv"
#: QoS chunk of a token: reliable, volatile, keep last 10, no deadline, lifespan or liveliness lease (the
#: form ``rmw_zenoh_cpp`` writes for the default sensor publisher it is compared with).
DEFAULT_QOS = "1:2:1,10:,:,:,,"


class Ros2Error(ServiceError):
    """A ROS 2 name or type is invalid, or rosbags is missing."""


def add_ros2_arg(parser: argparse.ArgumentParser | argparse._ArgumentGroup, what: str) -> None:
    """Add ``--ros2 [DOMAIN]`` (off by default; the bare flag is domain 0) saying ``what`` it publishes."""
    parser.add_argument(
        "--ros2",
        metavar="DOMAIN",
        nargs="?",
        const=0,
        type=int,
        default=None,
        help=f"publish {what} as ROS 2 topics over Zenoh, as rmw_zenoh does (domain, default 0; docs/ros2.md)",
    )


def typestore() -> Any:
    """rosbags' ROS 2 Jazzy type store (serializer and type hashes)."""
    try:
        from rosbags.typesys import Stores, get_typestore
    except ImportError as err:
        msg = f"ROS 2 output needs rosbags (pip install 'lrsensor[ros2]'): {err}"
        raise Ros2Error(msg) from err
    return get_typestore(Stores.ROS2_JAZZY)


def dds_type_name(typename: str) -> str:
    """``sensor_msgs/msg/PointCloud2`` -> ``sensor_msgs::msg::dds_::PointCloud2_`` (the name rmw_zenoh keys)."""
    parts = typename.split("/")
    if len(parts) != 3 or not all(parts):
        msg = f"ROS 2 type must be package/msg/Name, got {typename!r}"
        raise Ros2Error(msg)
    pkg, kind, name = parts
    return f"{pkg}::{kind}::dds_::{name}_"


def mangle(name: str) -> str:
    """A ROS name as a key chunk: ``/`` written ``%`` (the default namespace ``/`` becomes ``%``)."""
    return name.replace("/", "%")


def check_topic(topic: str) -> str:
    """A fully qualified ROS 2 topic name (``/a/b_c``), or :class:`Ros2Error`."""
    chunks = topic.split("/")
    if (
        not topic.startswith("/")
        or topic.endswith("/")
        or any(not c or not (c[0].isalpha() or c[0] == "_") or not c.replace("_", "").isalnum() for c in chunks[1:])
    ):
        msg = f"invalid ROS 2 topic {topic!r}: /name/name with letters, digits and _, each starting with a letter"
        raise Ros2Error(msg)
    return topic


def attachment(seq: int, publish_ns: int, gid: bytes) -> bytes:
    """rmw_zenoh's 33-byte sample attachment."""
    if len(gid) != 16:
        msg = f"a GID has 16 bytes, got {len(gid)}"
        raise Ros2Error(msg)
    return struct.pack("<qqB", seq, publish_ns, 16) + gid


class Ros2Node:
    """A ROS 2 node as rmw_zenoh announces it, on an open Zenoh session (the caller owns the session).

    Args:
        session: the Zenoh session (it must reach the ROS nodes' router).
        name: the node's name.
        namespace: the node's namespace (``/`` by default).
        domain: the ROS domain id (``ROS_DOMAIN_ID``, 0 by default).
    """

    _ids = itertools.count(0)

    def __init__(self, session: Any, name: str = "lrsensor", namespace: str = "/", domain: int = 0) -> None:
        if not name.replace("_", "").isalnum() or not (name[0].isalpha() or name[0] == "_"):
            msg = f"invalid ROS 2 node name {name!r}"
            raise Ros2Error(msg)
        if not 0 <= domain <= 232:
            msg = f"ROS domain id must be 0-232, got {domain}"
            raise Ros2Error(msg)
        self.session = session
        self.name = name
        self.namespace = namespace
        self.domain = domain
        self.zid = str(session.info.zid())
        self.node_id = next(self._ids)
        self._entities = itertools.count(self.node_id + 1)
        self._ts = typestore()
        self.token_key = "/".join(
            [
                ADMIN_SPACE,
                str(domain),
                self.zid,
                str(self.node_id),
                str(self.node_id),
                "NN",
                "%",
                mangle(namespace),
                name,
            ]
        )
        self._token = session.liveliness().declare_token(self.token_key)
        self.publishers: list[Ros2Publisher] = []

    def publisher(self, topic: str, typename: str, qos: str = DEFAULT_QOS) -> Ros2Publisher:
        """A publisher of ``typename`` (``package/msg/Name``) on ``topic``."""
        pub = Ros2Publisher(self, check_topic(topic), typename, next(self._entities), qos)
        self.publishers.append(pub)
        return pub

    def serialize(self, msg: Any, typename: str) -> bytes:
        """CDR (little endian, with its encapsulation header) of a rosbags message object."""
        return bytes(self._ts.serialize_cdr(msg, typename))

    def types(self) -> Any:
        """rosbags' message classes by type name (``node.types()['sensor_msgs/msg/PointCloud2']``)."""
        return self._ts.types

    def close(self) -> None:
        """Undeclare the publishers and the node's token."""
        for pub in self.publishers:
            pub.close()
        undeclare_all((self._token,), f"ros2 node {self.name}")


class Ros2Publisher:
    """One rmw_zenoh publisher (made by :meth:`Ros2Node.publisher`)."""

    def __init__(self, node: Ros2Node, topic: str, typename: str, entity_id: int, qos: str) -> None:
        import zenoh

        self.node = node
        self.topic = topic
        self.typename = typename
        dds = dds_type_name(typename)
        self.type_hash = node._ts.hash_rihs01(typename)
        self.key = f"{node.domain}/{topic.strip('/')}/{dds}/{self.type_hash}"
        self.token_key = "/".join(
            [
                ADMIN_SPACE,
                str(node.domain),
                node.zid,
                str(node.node_id),
                str(entity_id),
                "MP",
                "%",
                mangle(node.namespace),
                node.name,
                mangle(topic),
                dds,
                self.type_hash,
                qos,
            ]
        )
        self.gid = hashlib.blake2b(self.token_key.encode(), digest_size=16).digest()
        self._seq = 0
        self._lock = threading.Lock()
        self._pub = node.session.declare_publisher(
            self.key, congestion_control=zenoh.CongestionControl.DROP, reliability=zenoh.Reliability.RELIABLE
        )
        self._token = node.session.liveliness().declare_token(self.token_key)

    def publish(self, msg: Any) -> None:
        """Serialize and publish ``msg`` (a rosbags object of this publisher's type)."""
        payload = self.node.serialize(msg, self.typename)
        with self._lock:
            self._seq += 1
            att = attachment(self._seq, time.time_ns(), self.gid)
            self._pub.put(payload, attachment=att)

    def close(self) -> None:
        """Undeclare the publisher and its token."""
        undeclare_all((self._token, self._pub), f"ros2 publisher {self.topic}")
