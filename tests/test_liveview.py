"""The Foxglove live view (issue 28, item 4), checked with an independent WebSocket client.

The client is the ``websockets`` library speaking the Foxglove protocol (subprotocol ``foxglove.sdk.v1``) as a
Foxglove app does: it reads the advertised channels, subscribes, and decodes the binary message frames with
the protobuf schema the server advertised (``google.protobuf``), not with foxglove-sdk.
"""

from __future__ import annotations

import base64
import json
import struct
import time
from pathlib import Path
from typing import Any

import pytest

from lrsensor.calibration import Calibration
from services.imu import CsvImu
from services.liveview import LiveView, LiveViewError, parse_host_port
from services.simsource import record_sim_dive
from services.sources import FolderSource
from services.testnet import TestNetwork

pytest.importorskip("foxglove")
ws_client = pytest.importorskip("websockets.sync.client")

N_FRAMES = 20
SUBPROTOCOL = "foxglove.sdk.v1"


def message_class(channel: dict[str, Any]) -> Any:
    """The protobuf class of an advertised channel, built from the schema the server sent."""
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

    fds = descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(channel["schema"]))
    pool = descriptor_pool.DescriptorPool()
    for fd in fds.file:
        pool.Add(fd)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(channel["schemaName"]))


class FoxgloveClient:
    """A minimal Foxglove WebSocket client: advertised channels and decoded messages by topic."""

    def __init__(self, url: str) -> None:
        self.ws = ws_client.connect(url, subprotocols=[SUBPROTOCOL], open_timeout=10).__enter__()
        self.channels: dict[int, dict[str, Any]] = {}
        self.subscribed: dict[int, dict[str, Any]] = {}
        self.messages: dict[str, list[Any]] = {}

    def pump(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            try:
                frame = self.ws.recv(timeout=max(0.01, end - time.monotonic()))
            except TimeoutError:
                return
            if isinstance(frame, str):
                msg = json.loads(frame)
                if msg.get("op") == "advertise":
                    for ch in msg["channels"]:
                        self.channels[int(ch["id"])] = ch
            elif frame[0] == 0x01:  # message data: opcode, subscription id, log time, payload
                sub_id, _log_time = struct.unpack_from("<IQ", frame, 1)
                ch = self.subscribed[sub_id]
                payload = bytes(frame[13:])
                if ch["encoding"] == "protobuf":
                    decoded: Any = message_class(ch).FromString(payload)
                else:
                    decoded = json.loads(payload)
                self.messages.setdefault(ch["topic"], []).append(decoded)

    def subscribe(self, topics: set[str]) -> None:
        subs = []
        for cid, ch in self.channels.items():
            if ch["topic"] in topics and cid not in self.subscribed:
                self.subscribed[cid] = ch
                subs.append({"id": cid, "channelId": cid})
        if subs:
            self.ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))

    def close(self) -> None:
        self.ws.close()


@pytest.fixture(scope="module")
def dive(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return record_sim_dive(tmp_path_factory.mktemp("live") / "rov1", "rov1", n_frames=N_FRAMES, seed=2)


def test_a_foxglove_client_receives_point_clouds_map_tracks_and_status(dive: Path) -> None:
    with TestNetwork("live") as net:
        base = net.start_base(None, map_mode="on")
        view = LiveView(net.session(), net.keys, port=0, map_refresh_s=0.5, status_period_s=0.3)
        client = FoxgloveClient(view.url)
        try:
            client.pump(1.0)  # the map and status channels exist from the start
            wanted = {"/lrs/live/rov1/points", "/tf", "/lrs/live/map", "/lrs/live/tracks", "/lrs/live/status"}
            client.subscribe(wanted)
            calib = Calibration.load(dive / "calib.json")
            h = net.start_rov("rov1", FolderSource(dive), CsvImu(dive / "imu.csv"), calib, rate_hz=5.0)
            deadline = time.monotonic() + 60
            while time.monotonic() < deadline and not (wanted <= set(client.messages)):
                client.pump(0.3)
                client.subscribe(wanted)  # channels advertised as the first cloud arrives
            assert h.join(60)
            base.flush_map()
            client.pump(1.5)
        finally:
            client.close()
            view.close()
    got = client.messages
    assert wanted <= set(got), sorted(got)
    pc = got["/lrs/live/rov1/points"][0]
    assert pc.frame_id == "rov1/base_link"
    assert len(pc.data) == pc.point_stride * (len(pc.data) // pc.point_stride) > 0
    assert [f.name for f in pc.fields] == ["x", "y", "z", "laser"]
    assert all(t.parent_frame_id == "ned" and t.child_frame_id == "rov1/base_link" for t in got["/tf"])
    assert got["/lrs/live/tracks"][-1].entities[0].id == "track/rov1"
    status = got["/lrs/live/status"][-1]
    assert status["robots"]["rov1"]["received"] > 0
    planes = {e.id for m in got["/lrs/live/map"] for e in m.entities}
    assert planes  # the dive's walls reach the viewer as plane entities


def test_host_port_parsing_and_a_taken_port() -> None:
    assert parse_host_port("8765") == ("127.0.0.1", 8765)
    assert parse_host_port("0.0.0.0:9000") == ("0.0.0.0", 9000)
    for bad in ("x", ":80", "host:99999", "host:"):
        with pytest.raises(LiveViewError, match=r"\[HOST:\]PORT"):
            parse_host_port(bad)
    with TestNetwork("taken") as net:
        first = LiveView(net.session(), net.keys, port=0)
        try:
            with pytest.raises(LiveViewError, match="cannot listen"):
                LiveView(net.session(), net.keys, port=first.port)
        finally:
            first.close()
