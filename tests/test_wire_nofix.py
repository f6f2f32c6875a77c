"""A pose without a horizontal fix on the wire: ``north_m``/``east_m`` null in both cloud schemas, round trips,
and refusal of half-known positions; the ROV status's ``unplaced`` counter."""

from __future__ import annotations

import dataclasses
import math

import msgpack
import pytest
from test_wire import make_cloud
from test_wire_stripe import make_stripe

from lrsensor.frames import Pose
from services.errors import WireError
from services.posetrack import has_fix
from services.wire import CloudMsg, StatusMsg, StripeMsg, decode_cloud

NO_FIX = Pose(math.nan, math.nan, 3.0, 0.01, -0.02, 2.5)


def clouds() -> list[CloudMsg | StripeMsg]:
    return [dataclasses.replace(make_cloud(), pose=NO_FIX), dataclasses.replace(make_stripe(), pose=NO_FIX)]


@pytest.mark.parametrize("index", [0, 1], ids=["schema1", "schema2"])
def test_a_cloud_without_a_fix_round_trips_with_null_north_east(index: int) -> None:
    m = clouds()[index]
    data = m.to_bytes()
    pose = msgpack.unpackb(data, raw=False)["pose"]
    assert pose["north_m"] is None
    assert pose["east_m"] is None
    assert (pose["down_m"], pose["yaw_rad"]) == (3.0, 2.5)
    back = decode_cloud(data)
    assert type(back) is type(m)
    assert not has_fix(back.pose)
    assert (back.pose.down_m, back.pose.roll_rad, back.pose.pitch_rad, back.pose.yaw_rad) == (3.0, 0.01, -0.02, 2.5)
    assert back.to_bytes() == data


@pytest.mark.parametrize("index", [0, 1], ids=["schema1", "schema2"])
@pytest.mark.parametrize(("north", "east"), [(None, 1.0), (1.0, None)])
def test_one_null_horizontal_coordinate_is_refused(index: int, north: float | None, east: float | None) -> None:
    obj = msgpack.unpackb(clouds()[index].to_bytes(), raw=False)
    obj["pose"].update(north_m=north, east_m=east)
    with pytest.raises(WireError, match="null but not the other"):
        decode_cloud(msgpack.packb(obj, use_bin_type=True))


@pytest.mark.parametrize("field", ["down_m", "yaw_rad"])
def test_depth_and_attitude_may_not_be_null(field: str) -> None:
    obj = msgpack.unpackb(clouds()[0].to_bytes(), raw=False)
    obj["pose"][field] = None
    with pytest.raises(WireError, match=field):
        CloudMsg.from_bytes(msgpack.packb(obj, use_bin_type=True))


@pytest.mark.parametrize("pose", [Pose(math.nan, 0.0, 1, 0, 0, 0), Pose(math.inf, math.inf, 1, 0, 0, 0)])
def test_half_known_or_infinite_positions_are_not_encoded(pose: Pose) -> None:
    for m in clouds():
        with pytest.raises(WireError, match="pose is not finite"):
            dataclasses.replace(m, pose=pose).to_bytes()


def test_status_carries_unplaced_and_reads_older_status() -> None:
    st = StatusMsg("rov1", 5, "running", frames=10, published=9, skipped=1, last_seq=8, unplaced=7)
    back = StatusMsg.from_bytes(st.to_bytes())
    assert back == st
    assert back.to_json_dict()["unplaced"] == 7
    obj = msgpack.unpackb(st.to_bytes(), raw=False)
    del obj["unplaced"]  # a status from a ROV before the counter existed
    assert StatusMsg.from_bytes(msgpack.packb(obj, use_bin_type=True)).unplaced == 0


def test_status_carries_the_link_budget_counters_and_reads_older_status() -> None:
    counts = {"live": 30, "queued": 4, "forwarded": 5, "dropped_budget": 1, "released": 2, "reloaded": 0}
    st = StatusMsg("rov1", 5, "running", frames=40, published=40, last_seq=39, delivery=counts)
    back = StatusMsg.from_bytes(st.to_bytes())
    assert back == st
    shown = back.to_json_dict()
    assert {k: shown[k] for k in counts} == counts
    obj = msgpack.unpackb(st.to_bytes(), raw=False)
    del obj["delivery"]  # a ROV without an outbox, or from before the counters
    old = StatusMsg.from_bytes(msgpack.packb(obj, use_bin_type=True))
    assert old.delivery is None
    assert "live" not in old.to_json_dict()
    for bad in ({**counts, "live": -1}, {"live": 1}, [1, 2], {**counts, "queued": "x"}):
        obj["delivery"] = bad
        with pytest.raises(WireError):
            StatusMsg.from_bytes(msgpack.packb(obj, use_bin_type=True))
