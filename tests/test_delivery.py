"""Store-and-forward delivery (OutboxSink) against a stand-in base station on a real loopback zenoh network."""

from __future__ import annotations

import json
import socket
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

zenoh = pytest.importorskip("zenoh")

from waiting import wait_until  # noqa: E402

from lrsensor.frames import Pose  # noqa: E402
from services.delivery import OutboxSink, parse_ack_reply  # noqa: E402
from services.keys import FleetKeys  # noqa: E402
from services.outbox import Outbox  # noqa: E402
from services.seqset import SeqSet  # noqa: E402
from services.wire import CloudMsg  # noqa: E402

KEYS = FleetKeys("t1")
WAIT_S = 15.0  # how long a test waits for the base station to show up


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _conf(mode: str, port: int) -> Any:
    c: dict[str, Any] = {"mode": mode, "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}}}
    if mode == "router":
        c["listen"] = {"endpoints": [f"tcp/127.0.0.1:{port}"]}
    else:
        c["connect"] = {"endpoints": [f"tcp/127.0.0.1:{port}"]}
    return zenoh.Config.from_json5(json.dumps(c))


def _cloud(seq: int, n: int = 5) -> CloudMsg:
    rng = np.random.default_rng(seq)
    return CloudMsg(
        "rov1",
        seq,
        1_700_000_000_000_000_000 + seq,
        Pose(0.0, 0.0, 1.0, 0.0, 0.0, 0.0),
        rng.normal(size=(n, 3)).astype(np.float32),
        np.zeros(n, np.uint8),
        np.ones(n, np.float32),
    )


class FakeBase:
    """Subscribes to clouds and answers acks with what it holds; can ignore chosen deliveries."""

    def __init__(self, session: Any, lose: Callable[[int, int], bool] = lambda seq, n: False) -> None:
        self.session = session
        self.seqs = SeqSet()
        self.arrivals: dict[int, int] = {}
        self.lose = lose
        self.lock = threading.Lock()
        self.sub = session.declare_subscriber(KEYS.all_clouds, self._on_cloud)
        self.q = session.declare_queryable(KEYS.base_acks_all, self._on_acks)

    def _on_cloud(self, sample: Any) -> None:
        msg = CloudMsg.from_bytes(sample.payload.to_bytes())
        with self.lock:
            n = self.arrivals.get(msg.seq, 0)
            self.arrivals[msg.seq] = n + 1
            if not self.lose(msg.seq, n):
                self.seqs.add(msg.seq)

    def _on_acks(self, query: Any) -> None:
        with self.lock:
            body = {"robot": "rov1", "ranges": self.seqs.ranges()}
        query.reply(query.key_expr, json.dumps(body))

    def close(self) -> None:
        self.q.undeclare()
        self.sub.undeclare()


@pytest.fixture
def net() -> Iterator[tuple[Any, Any]]:
    port = _free_port()
    with zenoh.open(_conf("router", port)) as router, zenoh.open(_conf("client", port)) as rov:
        yield router, rov


def test_delivered_and_acked(net: tuple[Any, Any], tmp_path: Path) -> None:
    router, rov = net
    base = FakeBase(router)
    box = Outbox(tmp_path / "outbox", fsync=False)
    with OutboxSink(rov, KEYS, "rov1", box, ack_period_s=0.1) as sink:
        assert wait_until(sink.base_present, WAIT_S)
        for seq in range(50):
            sink.send(_cloud(seq))
        assert sink.wait_empty(15.0)
        stats = sink.stats()
    assert len(base.seqs) == 50
    assert stats["sent"] == 50
    assert stats["acked"] == 50
    assert stats["outbox"]["pending"] == 0
    base.close()


def test_base_absent_then_present(net: tuple[Any, Any], tmp_path: Path) -> None:
    router, rov = net
    box = Outbox(tmp_path / "outbox", fsync=False)
    with OutboxSink(rov, KEYS, "rov1", box, ack_period_s=0.1, resend_after_s=60.0) as sink:
        for seq in range(30):
            sink.send(_cloud(seq))  # nobody listens: nothing on the wire reaches anyone
        time.sleep(0.3)
        assert box.pending() == list(range(30))
        base = FakeBase(router)  # the base station appears: everything is re-sent at once
        assert sink.wait_empty(15.0)
        assert sink.stats()["base_seen"] >= 1
    assert len(base.seqs) == 30
    base.close()


def test_lost_deliveries_are_resent(net: tuple[Any, Any], tmp_path: Path) -> None:
    router, rov = net
    base = FakeBase(router, lose=lambda seq, n: seq % 3 == 0 and n == 0)  # first copy of every third is lost
    box = Outbox(tmp_path / "outbox", fsync=False)
    with OutboxSink(rov, KEYS, "rov1", box, ack_period_s=0.1, resend_after_s=0.5) as sink:
        assert wait_until(sink.base_present, WAIT_S)
        for seq in range(30):
            sink.send(_cloud(seq))
        assert sink.wait_empty(15.0)
        assert sink.stats()["resent"] >= 10
    assert len(base.seqs) == 30
    assert base.seqs.missed() == 0
    base.close()


def test_pending_clouds_survive_a_rov_restart(net: tuple[Any, Any], tmp_path: Path) -> None:
    router, rov = net
    box = Outbox(tmp_path / "outbox", fsync=False)
    with OutboxSink(rov, KEYS, "rov1", box, ack_period_s=0.1) as sink:
        for seq in range(10):
            sink.send(_cloud(seq))
    # "restart": a new outbox object on the same folder, then the base station shows up
    box2 = Outbox(tmp_path / "outbox")
    assert box2.pending() == list(range(10))
    assert box2.next_seq == 10
    base = FakeBase(router)
    with OutboxSink(rov, KEYS, "rov1", box2, ack_period_s=0.1) as sink2:
        sink2.send(_cloud(box2.next_seq))
        assert sink2.wait_empty(15.0)
    assert base.seqs.ranges() == [[0, 10]]
    base.close()


@pytest.mark.parametrize(
    "payload",
    [
        b"",
        b"[]",
        b"{}",
        b'{"robot": "rov2", "ranges": []}',
        b'{"robot": "rov1", "ranges": [[2, 1]]}',
        b'{"robot": "rov1", "ranges": [[0, true]]}',
        b'{"robot": "rov1", "ranges": "x"}',
        b"\xff",
    ],
)
def test_bad_ack_answers_are_refused(payload: bytes) -> None:
    with pytest.raises(ValueError):
        parse_ack_reply(payload, "rov1")


def test_good_ack_answer() -> None:
    assert parse_ack_reply(b'{"robot": "rov1", "ranges": [[0, 4], [6, 6]]}', "rov1") == [[0, 4], [6, 6]]


def test_a_slow_base_gets_no_duplicates(net: tuple[Any, Any], tmp_path: Path) -> None:
    """Acks lag 1.5 s behind (a saturated base) but keep coming in order: nothing is re-sent."""
    router, rov = net
    base = FakeBase(router)
    held_at: dict[int, float] = {}

    def lagging_acks(query: Any) -> None:
        now = time.monotonic()
        with base.lock:
            for s in list(base.arrivals):
                held_at.setdefault(s, now)
            ripe = SeqSet()
            for s, t in held_at.items():
                if now - t >= 1.5:
                    ripe.add(s)
            ranges = ripe.ranges()
        query.reply(query.key_expr, json.dumps({"robot": "rov1", "ranges": ranges}))

    base.q.undeclare()
    base.q = router.declare_queryable(KEYS.base_acks_all, lagging_acks)
    box = Outbox(tmp_path / "outbox", fsync=False)
    with OutboxSink(rov, KEYS, "rov1", box, ack_period_s=0.1, resend_after_s=0.5, stall_s=5.0) as sink:
        assert wait_until(sink.base_present, WAIT_S)
        for seq in range(40):
            sink.send(_cloud(seq))
            time.sleep(0.05)
        assert sink.wait_empty(15.0)
        assert sink.stats()["resent"] == 0
    assert all(n == 1 for n in base.arrivals.values())
    base.close()


def test_a_lost_last_cloud_is_resent_after_a_stall(net: tuple[Any, Any], tmp_path: Path) -> None:
    router, rov = net
    base = FakeBase(router, lose=lambda seq, n: seq == 9 and n == 0)  # the last one's first copy is lost
    box = Outbox(tmp_path / "outbox", fsync=False)
    with OutboxSink(rov, KEYS, "rov1", box, ack_period_s=0.1, resend_after_s=0.3, stall_s=1.0) as sink:
        assert wait_until(sink.base_present, WAIT_S)
        for seq in range(10):
            sink.send(_cloud(seq))
        assert sink.wait_empty(15.0)
        assert sink.stats()["resent"] == 1
    assert base.seqs.ranges() == [[0, 9]]
    base.close()


def test_a_base_that_never_acknowledges_gets_probes_not_floods(net: tuple[Any, Any], tmp_path: Path) -> None:
    router, rov = net
    base = FakeBase(router)
    base.q.undeclare()  # receives, never acknowledges
    box = Outbox(tmp_path / "outbox", fsync=False)
    with OutboxSink(rov, KEYS, "rov1", box, ack_period_s=0.1, resend_after_s=0.2, stall_s=0.3) as sink:
        assert wait_until(sink.base_present, WAIT_S)
        for seq in range(100):
            sink.send(_cloud(seq))
        t0 = time.monotonic()
        time.sleep(1.5)
        cycles = (time.monotonic() - t0) / 0.1 + 2
        resent = sink.stats()["resent"]
    assert 0 < resent <= 10 * cycles < 100 * 1.5 / 0.2  # a flood would re-send all 100 every 0.2 s
    assert min(base.arrivals) == 0  # the probes are the oldest
    base.sub.undeclare()


# ------------------------------------------------------------------------------------- the link budget
def _identity(sink: OutboxSink) -> None:
    """Both identities of the link-budget counters (docs/reliability.md) hold."""
    st = sink.stats()
    assert st["sent"] + st["reloaded"] == st["live"] + st["forwarded"] + st["queued"] + st["dropped_budget"], st
    assert st["live"] + st["forwarded"] + st["queued"] == (
        st["acked"] + st["outbox"]["pending"] + st["released"] + st["unstored"]
    ), st
    assert st["dropped_budget"] + st["released"] == st["dropped"]


def test_every_cloud_is_counted_once_live(net: tuple[Any, Any], tmp_path: Path) -> None:
    router, rov = net
    base = FakeBase(router)
    with OutboxSink(rov, KEYS, "rov1", Outbox(tmp_path / "outbox", fsync=False), ack_period_s=0.1) as sink:
        assert wait_until(sink.base_present, WAIT_S)
        for seq in range(20):
            sink.send(_cloud(seq))
            _identity(sink)
        assert sink.wait_empty(15.0)
        _identity(sink)
        assert sink.budget_counts() == {
            "live": 20,
            "queued": 0,
            "forwarded": 0,
            "dropped_budget": 0,
            "released": 0,
            "reloaded": 0,
        }
    base.close()


def test_only_the_budget_drops_and_the_rest_is_forwarded(net: tuple[Any, Any], tmp_path: Path) -> None:
    """No base station while 30 clouds are published into a budget of 10: the 20 oldest are dropped (counted),
    the 10 newest queued and forwarded once it appears; the base lacks exactly the dropped ones."""
    router, rov = net
    box = Outbox(tmp_path / "outbox", max_messages=10, fsync=False)
    with OutboxSink(rov, KEYS, "rov1", box, ack_period_s=0.1) as sink:
        for seq in range(30):
            sink.send(_cloud(seq))
            _identity(sink)
        assert sink.budget_counts() == {
            "live": 0,
            "queued": 10,
            "forwarded": 0,
            "dropped_budget": 20,
            "released": 0,
            "reloaded": 0,
        }
        assert box.stats().dropped_ranges == ((0, 19),)
        base = FakeBase(router)
        assert sink.wait_empty(15.0)
        _identity(sink)
        assert sink.budget_counts() == {
            "live": 0,
            "queued": 0,
            "forwarded": 10,
            "dropped_budget": 20,
            "released": 0,
            "reloaded": 0,
        }
    assert base.seqs.ranges() == [[20, 29]]
    base.close()


def test_the_budget_drops_sent_clouds_before_unsent_ones(net: tuple[Any, Any], tmp_path: Path) -> None:
    """A base that receives and never acknowledges, a budget of 5: the 12 live clouds' disk copies go oldest
    first (released, not lost: they arrived); once the base looks away (no subscriber), the clouds kept
    unsent outlive the sent ones."""
    router, rov = net
    base = FakeBase(router)
    base.q.undeclare()  # receives, never acknowledges: the live copies stay pending until the budget drops them
    box = Outbox(tmp_path / "outbox", max_messages=5, fsync=False)
    with OutboxSink(rov, KEYS, "rov1", box, ack_period_s=0.1, resend_after_s=30.0, stall_s=30.0) as sink:
        assert wait_until(sink.base_present, WAIT_S)
        for seq in range(12):
            sink.send(_cloud(seq))
            _identity(sink)
        c = sink.budget_counts()
        assert (c["live"], c["released"], c["dropped_budget"]) == (12, 7, 0)
        assert box.pending() == list(range(7, 12))
        assert wait_until(lambda: len(base.arrivals) == 12, WAIT_S)  # the live copies arrived before it looks away
        base.sub.undeclare()
        assert wait_until(lambda: not sink.base_present(), WAIT_S)
        for seq in range(12, 15):  # unsent: they push out the three oldest sent ones, not each other
            sink.send(_cloud(seq))
            _identity(sink)
        assert box.pending() == [10, 11, 12, 13, 14]
        for seq in range(15, 18):  # only unsent ones left to drop but the two sent: those go first
            sink.send(_cloud(seq))
            _identity(sink)
        assert box.pending() == [13, 14, 15, 16, 17]
        c = sink.budget_counts()
        assert (c["live"], c["queued"], c["released"], c["dropped_budget"]) == (12, 5, 12, 1)
    assert base.arrivals.keys() == set(range(12))


def test_a_link_that_does_not_keep_up_thins_the_live_stream(net: tuple[Any, Any], tmp_path: Path) -> None:
    """Acknowledgements withheld while large clouds are published: once the live window is full the next
    clouds are queued on disk (thinned), and when the acknowledgements come the backlog is forwarded; every
    cloud arrives, each counted once."""
    router, rov = net
    base = FakeBase(router)
    gate = threading.Event()

    def gated_acks(query: Any) -> None:
        with base.lock:
            ranges = base.seqs.ranges() if gate.is_set() else []
        query.reply(query.key_expr, json.dumps({"robot": "rov1", "ranges": ranges}))

    base.q.undeclare()
    base.q = router.declare_queryable(KEYS.base_acks_all, gated_acks)
    box = Outbox(tmp_path / "outbox", fsync=False)
    with OutboxSink(rov, KEYS, "rov1", box, ack_period_s=0.1, resend_after_s=30.0, stall_s=30.0) as sink:
        assert wait_until(sink.base_present, WAIT_S)
        clouds = [_cloud(seq, n=10_000) for seq in range(12)]  # about 170 kB each: 3 fill the live window
        for m in clouds:
            sink.send(m)
            _identity(sink)
        st = sink.stats()
        assert 1 <= st["live"] < 12, st
        assert st["thinned"] == st["queued"] == 12 - st["live"], st
        assert wait_until(lambda: len(base.seqs) == st["live"], 10.0)  # the queued ones are not on the link
        time.sleep(0.5)
        assert len(base.seqs) == st["live"]
        gate.set()
        assert sink.wait_empty(20.0)
        _identity(sink)
        c = sink.budget_counts()
        assert c["queued"] == 0
        assert c["forwarded"] + c["live"] == 12
        assert c["forwarded"] >= 12 - st["live"]
    assert base.seqs.ranges() == [[0, 11]]
    assert all(n == 1 for n in base.arrivals.values())  # forwarded, not re-sent
    base.close()


def test_reloaded_clouds_are_counted_as_queued_then_forwarded(net: tuple[Any, Any], tmp_path: Path) -> None:
    router, rov = net
    box = Outbox(tmp_path / "outbox", fsync=False)
    for seq in range(6):
        box.append(seq, _cloud(seq).to_bytes())
    base = FakeBase(router)
    with OutboxSink(rov, KEYS, "rov1", Outbox(tmp_path / "outbox", fsync=False), ack_period_s=0.1) as sink:
        assert sink.budget_counts()["reloaded"] == sink.budget_counts()["queued"] == 6
        _identity(sink)
        assert wait_until(sink.base_present, WAIT_S)
        sink.send(_cloud(6))
        assert sink.wait_empty(15.0)
        _identity(sink)
        c = sink.budget_counts()
        assert (c["forwarded"], c["queued"], c["live"]) == (6, 0, 1)
    base.close()


def _next_seq_on_disk(folder: Path) -> int:
    """The number a new :class:`Outbox` on ``folder`` would continue from (read only: ``state.json`` and the
    message files, as its reload does)."""
    n = 0
    if (folder / "state.json").exists():
        n = int(json.loads((folder / "state.json").read_text())["next_seq"])
    return max([n] + [int(p.name[:-4]) + 1 for p in folder.glob("*.msg")])


class _RecordingPublisher:
    """Stands in for the sink's publisher: notes, at each put, the number a ROV restarted at that moment would
    continue from (a new :class:`Outbox` on the same folder: what a SIGKILL right after the put leaves)."""

    def __init__(self, inner: Any, folder: Path) -> None:
        self.inner = inner
        self.folder = folder
        self.seen: list[tuple[int, int]] = []  # (seq put, the restarted outbox's next_seq)

    def put(self, payload: bytes) -> None:
        seq = CloudMsg.from_bytes(payload).seq
        self.seen.append((seq, _next_seq_on_disk(self.folder)))
        self.inner.put(payload)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)


def test_a_rov_killed_after_a_put_never_reuses_the_number(net: tuple[Any, Any], tmp_path: Path) -> None:
    """Found by the chaos soak's robot kills: the live copy went out before the outbox append, so a ROV killed
    between the two restarted with that number unused and gave it to its next cloud, which the base station
    (holding the first) dropped as a duplicate and acknowledged: a cloud lost without a trace."""
    router, rov = net
    base = FakeBase(router)
    folder = tmp_path / "outbox"
    box = Outbox(folder, fsync=True)
    with OutboxSink(rov, KEYS, "rov1", box, ack_period_s=0.1) as sink:
        assert wait_until(sink.base_present, WAIT_S)
        recorder = _RecordingPublisher(sink.publisher, folder)
        sink.publisher = recorder
        for seq in range(20):
            sink.send(_cloud(seq))
        assert sink.wait_empty(15.0)
    live = [(seq, nxt) for seq, nxt in recorder.seen if seq >= 0]
    assert [s for s, _ in live][:20] == list(range(20))
    assert all(nxt > seq for seq, nxt in live), live  # every number put was already on disk
    assert len(base.seqs) == 20
    base.close()


def test_the_backlog_waits_for_start_forwarding(net: tuple[Any, Any], tmp_path: Path) -> None:
    """Found by the chaos soak: a restarted ROV forwarded its backlog before it served its calibration, and a
    base station restarted meanwhile refused the compact clouds (no calibration yet): 92 re-sends."""
    router, rov = net
    box = Outbox(tmp_path / "outbox", fsync=False)
    for seq in range(5):  # pending from an earlier run
        box.append(seq, _cloud(seq).to_bytes())
    base = FakeBase(router)
    with OutboxSink(rov, KEYS, "rov1", box, ack_period_s=0.1, forward_now=False) as sink:
        assert wait_until(sink.base_present, WAIT_S)
        time.sleep(1.0)
        assert len(base.arrivals) == 0  # held back
        sink.start_forwarding()
        assert sink.wait_empty(15.0)
    assert base.seqs.ranges() == [[0, 4]]
    base.close()
