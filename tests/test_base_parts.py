"""The base station's parts without a network: the robot ledger (counting, state file, acknowledgements) and
the map feed (wire form of the map changes, clouds reported to the ledger, latency statistics)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from lrsensor.frames import Pose
from services.base import BaseStation
from services.errors import ServiceError
from services.keys import FleetKeys
from services.ledger import STATE_FORMAT, Ledger
from services.mapfeed import LatencyStats, MapFeed, change_json
from services.wire import CloudMsg


def a_cloud(robot: str, seq: int, n: int = 10, sent_ns: int = 0, fix: bool = True) -> CloudMsg:
    rng = np.random.default_rng(seq)
    msg = CloudMsg(
        robot,
        seq,
        1_700_000_000_000_000_000 + seq,
        Pose(1, 2, 3, 0, 0, 0.5) if fix else Pose(math.nan, math.nan, 3, 0, 0, 0.5),
        rng.normal(0, 1, (n, 3)).astype(np.float32),
        np.zeros(n, np.uint8),
        np.ones(n, np.float32),
    )
    return msg.with_sent_ns(sent_ns) if sent_ns else msg


def test_ledger_counts_duplicates_and_rejections() -> None:
    ledger = Ledger(None)
    assert ledger.accept(a_cloud("rov1", 0))
    assert ledger.accept(a_cloud("rov1", 2, n=5))
    assert not ledger.accept(a_cloud("rov1", 2))
    ledger.reject("rov1", "garbage")
    st = ledger.robots_json()["rov1"]
    assert (st["received"], st["missed"], st["duplicates"], st["rejected"], st["points"]) == (2, 1, 1, 1, 15)
    assert st["rejected_reasons"] == {"garbage": 1}
    assert ledger.tracks()["rov1"].shape == (2, 4)
    assert list(ledger.robots_json("rov2")) == []


def test_ledger_with_the_map_acknowledges_only_what_the_map_took(tmp_path: Path) -> None:
    saves: list[str] = []
    ledger = Ledger(tmp_path, save_map=lambda: saves.append("map"))
    for seq in range(4):
        ledger.accept(a_cloud("rov1", seq))
    ledger.mark_mapped("rov1", 0)
    ledger.mark_mapped("rov1", 1)
    ledger.ack_now("rov1")  # with the map only checkpoints acknowledge
    assert ledger.acks_json("rov1")["ranges"] == []
    ledger.checkpoint()
    assert saves == ["map"]
    assert ledger.acks_json("rov1") == {"robot": "rov1", "ranges": [[0, 1]], "received": 4}
    saved = json.loads((tmp_path / "fleet.json").read_text())
    assert saved["format"] == STATE_FORMAT
    assert saved["robots"]["rov1"]["ranges"] == [[0, 3]]
    assert saved["robots"]["rov1"]["acked"] == [[0, 1]]
    again = Ledger(tmp_path)
    assert again.records["rov1"].seqs.ranges() == [[0, 1]]  # 2 and 3 will come again from the outbox


def test_ledger_refuses_a_foreign_state_file(tmp_path: Path) -> None:
    (tmp_path / "fleet.json").write_text(json.dumps({"format": "other", "version": 1, "robots": {}}))
    with pytest.raises(ServiceError, match="not a base-station state file"):
        Ledger(tmp_path)
    with pytest.raises(ServiceError, match="not a base-station state file"):
        BaseStation(None, FleetKeys("t"), tmp_path, map_mode="off")


def test_map_feed_without_a_map_reports_each_cloud_at_once() -> None:
    mapped: list[tuple[str, int]] = []
    feed = MapFeed(None, lambda robot, seq: mapped.append((robot, seq)))
    feed.take(a_cloud("rov1", 7, sent_ns=1_700_000_000_000_000_000), 1_700_000_000_002_000_000)
    assert mapped == [("rov1", 7)]
    assert feed.idle()
    assert feed.status_json() == {
        "planes": 0,
        "enabled": False,
        "clouds": 0,
        "skipped": 0,
        "unplaced": 0,
        "queued": 0,
        "backlog": 0,
        "backlog_limit": 1024,
        "pending": 0,
        "rate_skipped": 0,
        "latency_ms": {"p50": None, "p99": None},
        "workers": 0,
        "errors": 0,
        "quiet_flushes": 0,
        "order_forced": 0,
    }
    assert feed.map_json() == {"planes": [], "enabled": False}
    assert feed.latency.percentiles_ms(transit=True) == {"p50": 2.0, "p99": 2.0}


class FakeMap:
    """Stands in for ``mapping.MapBuilder``: records what it is given."""

    def __init__(self) -> None:
        self.added: list[tuple[str, int, Pose]] = []
        self.n_planes = 0
        self.rate_skipped = 0

    def uncommitted(self, robot: str) -> int:
        return 0

    def set_range_error(self, robot: str, per_px: float) -> None:
        self.range_error = (robot, per_px)

    def add_cloud(self, robot: str, t_ns: int, points_ned: np.ndarray, pose: Pose) -> list[object]:
        assert np.all(np.isfinite(points_ned))
        self.added.append((robot, t_ns, pose))
        return []

    def flush(self) -> list[object]:
        return []

    def save(self) -> None:
        return None


def test_clouds_without_a_fix_are_counted_not_mapped(caplog: pytest.LogCaptureFixture) -> None:
    ledger = Ledger(None)
    fake = FakeMap()
    feed = MapFeed(fake, ledger.mark_mapped)  # type: ignore[arg-type]
    feed.start(None)
    try:
        for seq, fix in enumerate([True, False, False, True, False]):
            msg = a_cloud("rov1", seq, fix=fix)
            assert ledger.accept(msg)
            feed.take(msg, msg.t_ns)
        other = a_cloud("rov2", 0, fix=False)
        assert ledger.accept(other)
        feed.take(other, other.t_ns)
        feed.flush()
    finally:
        feed.close(save=False)
    assert [(robot, t_ns - 1_700_000_000_000_000_000) for robot, t_ns, _ in fake.added] == [("rov1", 0), ("rov1", 3)]
    assert feed.status_json()["unplaced"] == 4
    assert feed.status_json()["clouds"] == 2
    robots = ledger.robots_json()
    assert (robots["rov1"]["unplaced"], robots["rov2"]["unplaced"]) == (3, 1)
    assert robots["rov1"]["received"] == 5
    assert ledger.tracks()["rov1"].shape == (2, 4)  # no made-up position in the track either
    assert np.all(np.isfinite(ledger.tracks()["rov1"]))
    # every cloud is done with (acknowledgeable), and each robot is named once at warning level
    assert ledger.records["rov1"].mapped.ranges() == [[0, 4]]
    warned = [r.getMessage() for r in caplog.records if "no horizontal position" in r.getMessage()]
    assert len(warned) == 2
    assert all(r.levelname == "WARNING" for r in caplog.records if "no horizontal position" in r.getMessage())


def test_unplaced_count_survives_a_restart(tmp_path: Path) -> None:
    ledger = Ledger(tmp_path)
    ledger.accept(a_cloud("rov1", 0, fix=False))
    ledger.save_state()
    assert Ledger(tmp_path).robots_json()["rov1"]["unplaced"] == 1


def test_latency_percentiles_are_nan_when_empty() -> None:
    stats = LatencyStats()
    assert all(math.isnan(v) for v in stats.percentiles_ms().values())
    stats.add(1_000_000, None)
    stats.add(3_000_000, 500_000)
    assert stats.percentiles_ms((50,)) == {"p50": 2.0}
    assert stats.percentiles_ms((50,), transit=True) == {"p50": 0.5}


def test_map_changes_go_on_the_wire_as_before() -> None:
    from mapping import MapChange, MapConfig
    from mapping.plane_map import MapPlane, PlaneRecord

    rng = np.random.default_rng(1)
    points_q = np.rint(np.column_stack([np.full(500, 3.0), rng.uniform(0, 1, 500), rng.uniform(1, 1.3, 500)]) / 1e-4)
    rec = PlaneRecord.from_points(points_q.astype(np.int64), np.array([-1.0, 0, 0]), "rov1", 10, 20, MapConfig())
    plane = MapPlane(4, rec, MapConfig())
    assert change_json(MapChange.updated(plane)) == plane.to_json()
    assert change_json(MapChange.removed(5, merged_into=4)) == {"id": 5, "removed": True, "merged_into": 4}


def _dive(robot: str, n: int, rate_hz: float = 30.0) -> list[CloudMsg]:
    """``n`` clouds of ``robot`` at ``rate_hz`` of capture time (random points: nothing to extract)."""
    base = a_cloud(robot, 0, n=50)
    step = round(1e9 / rate_hz)
    return [
        CloudMsg(robot, s, base.t_ns + s * step, base.pose, base.points_body, base.laser, base.quality)
        for s in range(n)
    ]


@pytest.mark.parametrize("cap_hz", [0.0, 10.0])
def test_every_cloud_reaches_the_map_by_default_and_a_cap_is_counted(cap_hz: float) -> None:
    from mapping import MapBuilder, MapConfig

    ledger = Ledger(None)
    feed = MapFeed(MapBuilder(MapConfig(max_cloud_rate_hz=cap_hz)), ledger.mark_mapped)
    feed.start(None)
    try:
        for robot in ("rov1", "rov2"):
            for msg in _dive(robot, 45):  # 1.5 s at 30 Hz: windows of 10 extracted, then a partial one
                assert ledger.accept(msg)
                feed.take(msg, msg.t_ns)
        feed.flush()
    finally:
        feed.close(save=False)
    st = feed.status_json()
    if cap_hz == 0:
        assert (feed.mapped("rov1"), feed.mapped("rov2"), st["rate_skipped"]) == (45, 45, 0)
    else:  # 10 of 30 clouds a second taken: the rest counted, not hidden
        assert feed.mapped("rov1") == 15
        assert st["rate_skipped"] == 60
    assert st["backlog"] == 0
    assert st["pending"] == 0
    assert st["backlog_limit"] == 1024
    assert st["latency_ms"]["p50"] is not None
    assert st["latency_ms"]["p99"] >= st["latency_ms"]["p50"]
    assert ledger.records["rov1"].mapped.ranges() == [[0, 44]]  # acknowledgeable either way


def test_map_backlog_is_bounded_counted_and_shown() -> None:
    ledger = Ledger(None)
    fake = FakeMap()
    feed = MapFeed(fake, ledger.mark_mapped, queue_size=3, map_wait_s=0.01)  # type: ignore[arg-type]
    # the map thread is not started: the queue fills, then the map waits map_wait_s and counts what it leaves out
    for msg in _dive("rov1", 5):
        ledger.accept(msg)
        feed.take(msg, msg.t_ns)
    st = feed.status_json()
    assert (st["backlog"], st["backlog_limit"], st["skipped"]) == (3, 3, 2)
