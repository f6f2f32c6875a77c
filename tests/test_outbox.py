"""The ROV's disk-backed outbox: bounds, drop policy, acks, reload, crash safety (unit + property tests)."""

from __future__ import annotations

import json
import shutil
import signal
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest
from hypothesis import HealthCheck, settings
from hypothesis import strategies as st
from hypothesis.stateful import RuleBasedStateMachine, invariant, precondition, rule

from services.outbox import STATE_FILE, Outbox, OutboxError


def _payload(seq: int, size: int = 10) -> bytes:
    return (f"#{seq}:".encode() * size)[:size]


def test_append_get_ack_and_reload(tmp_path: Path) -> None:
    box = Outbox(tmp_path, fsync=False)
    assert box.next_seq == 0
    for seq in range(5):
        assert box.append(seq, _payload(seq)) == []
    assert box.pending() == [0, 1, 2, 3, 4]
    assert box.get(3) == _payload(3)
    assert list(box.iter_pending(after=2)) == [(3, _payload(3)), (4, _payload(4))]
    assert box.ack(1)
    assert not box.ack(1)  # already gone
    assert box.ack_upto(2) == 2
    assert box.pending() == [3, 4]
    assert box.get(0) is None
    again = Outbox(tmp_path)  # a restart
    assert again.pending() == [3, 4]
    assert again.get(4) == _payload(4)
    assert again.next_seq == 5
    s = again.stats()
    assert (s.appended, s.acked, s.dropped, s.pending, s.pending_bytes) == (5, 3, 0, 2, 20)


def test_next_seq_survives_an_empty_outbox(tmp_path: Path) -> None:
    box = Outbox(tmp_path, fsync=False)
    for seq in range(3):
        box.append(seq, b"x")
    box.ack_upto(10)
    assert Outbox(tmp_path).next_seq == 3  # numbers are never reused, even with nothing pending


def test_sequence_numbers_must_increase(tmp_path: Path) -> None:
    box = Outbox(tmp_path, fsync=False)
    box.append(7, b"a")
    with pytest.raises(OutboxError, match="not above 7"):
        box.append(7, b"b")
    with pytest.raises(OutboxError, match="not above 7"):
        box.append(3, b"b")
    box.append(9, b"c")  # gaps are allowed (a frame skipped on the ROV)
    assert box.pending() == [7, 9]


def test_full_by_count_drops_oldest_and_counts_them(tmp_path: Path) -> None:
    box = Outbox(tmp_path, max_messages=3, fsync=False)
    dropped = [box.append(seq, _payload(seq)) for seq in range(6)]
    assert dropped == [[], [], [], [0], [1], [2]]
    assert box.pending() == [3, 4, 5]
    s = box.stats()
    assert s.dropped == 3
    assert s.dropped_ranges == ((0, 2),)
    reloaded = Outbox(tmp_path, max_messages=3).stats()
    assert (reloaded.dropped, reloaded.dropped_ranges, reloaded.pending) == (3, ((0, 2),), 3)
    assert sorted(p.name for p in tmp_path.glob("*.msg")) == [f"{s:020d}.msg" for s in (3, 4, 5)]


def test_full_by_bytes_drops_as_many_as_needed(tmp_path: Path) -> None:
    box = Outbox(tmp_path, max_bytes=100, fsync=False)
    for seq in range(4):
        box.append(seq, _payload(seq, 25))
    assert box.append(4, _payload(4, 60)) == [0, 1, 2]
    assert box.pending() == [3, 4]
    assert box.stats().pending_bytes == 85
    with pytest.raises(OutboxError, match="exceeds max_bytes"):
        box.append(5, b"x" * 101)
    assert box.pending() == [3, 4]  # a refused message drops nothing


def test_ack_ranges(tmp_path: Path) -> None:
    box = Outbox(tmp_path, fsync=False)
    for seq in range(10):
        box.append(seq, b"p")
    assert box.ack_ranges([[0, 2], [5, 5], [8, 100]]) == 6
    assert box.pending() == [3, 4, 6, 7]
    assert box.ack_ranges([[0, 2]]) == 0


def test_damaged_files_are_quarantined_and_counted(tmp_path: Path) -> None:
    box = Outbox(tmp_path, fsync=False)
    for seq in range(4):
        box.append(seq, _payload(seq, 50))
    f1 = tmp_path / f"{1:020d}.msg"
    f1.write_bytes(f1.read_bytes()[:-5])  # truncated
    f2 = tmp_path / f"{2:020d}.msg"
    raw = bytearray(f2.read_bytes())
    raw[-1] ^= 0xFF  # bit flip: CRC mismatch
    f2.write_bytes(bytes(raw))
    (tmp_path / f"{9:020d}.msg").write_bytes(b"garbage")
    (tmp_path / ".00000000000000000010.msg.abc.tmp").write_bytes(b"half")  # interrupted write
    again = Outbox(tmp_path)
    assert again.pending() == [0, 3]
    assert again.stats().corrupt == 3
    assert sorted(p.name for p in (tmp_path / "corrupt").iterdir()) == [
        f"{1:020d}.msg",
        f"{2:020d}.msg",
        f"{9:020d}.msg",
    ]
    assert not list(tmp_path.glob(".*.tmp"))
    assert again.stats().appended == 5  # 2 pending + 3 corrupt: nothing vanishes from the books


def test_unreadable_state_is_an_error(tmp_path: Path) -> None:
    Outbox(tmp_path, fsync=False).append(0, b"x")
    (tmp_path / STATE_FILE).write_text("{not json")
    with pytest.raises(OutboxError, match="unreadable"):
        Outbox(tmp_path)


def test_bad_arguments(tmp_path: Path) -> None:
    with pytest.raises(OutboxError):
        Outbox(tmp_path, max_messages=0)
    with pytest.raises(OutboxError):
        Outbox(tmp_path / "f", max_bytes=0)
    box = Outbox(tmp_path, fsync=False)
    with pytest.raises(OutboxError, match="bytes"):
        box.append(0, "text")  # type: ignore[arg-type]
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(OutboxError, match="cannot create"):
        Outbox(blocker / "sub")


_WRITER = """
import sys
from services.outbox import Outbox
box = Outbox(sys.argv[1], max_messages=100000, fsync=True)
seq = box.next_seq
while True:
    box.append(seq, bytes([seq % 251]) * (1000 + seq % 5000))
    print(seq, flush=True)
    seq += 1
"""


def test_sigkill_while_appending_loses_nothing_that_was_appended(tmp_path: Path) -> None:
    """A writer killed with SIGKILL mid-stream: every append that returned is on disk and valid."""
    proc = subprocess.Popen([sys.executable, "-c", _WRITER, str(tmp_path)], stdout=subprocess.PIPE, text=True)
    assert proc.stdout is not None
    confirmed: list[int] = []
    for line in proc.stdout:
        confirmed.append(int(line))
        if len(confirmed) >= 150:
            break
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=10)
    # the writer went on appending until the signal landed: its confirmations still in the pipe count too
    confirmed.extend(int(line) for line in proc.stdout.read().splitlines() if line.strip())
    box = Outbox(tmp_path)
    pending = box.pending()
    assert set(confirmed) <= set(pending)
    assert pending == list(range(len(pending)))  # at most the one in flight beyond what was confirmed
    assert len(pending) - len(confirmed) in (0, 1)
    assert box.stats().corrupt == 0
    for seq in confirmed[::17]:
        assert box.get(seq) == bytes([seq % 251]) * (1000 + seq % 5000)
    assert box.next_seq == pending[-1] + 1


class OutboxMachine(RuleBasedStateMachine):
    """Random appends, acks and restarts against a plain-Python model of the policy."""

    def __init__(self) -> None:
        super().__init__()
        self.dir = Path(tempfile.mkdtemp(prefix="outbox-prop-"))
        self.max_messages = 6
        self.max_bytes = 200
        self.box = Outbox(self.dir, max_messages=self.max_messages, max_bytes=self.max_bytes, fsync=False)
        self.model: dict[int, bytes] = {}
        self.next = 0
        self.dropped: list[int] = []
        self.acked = 0

    def teardown(self) -> None:
        shutil.rmtree(self.dir, ignore_errors=True)

    @rule(gap=st.integers(0, 3), size=st.integers(0, 120))
    def append(self, gap: int, size: int) -> None:
        seq = self.next + gap
        payload = bytes([seq % 256]) * size
        expected: list[int] = []
        model = dict(self.model)
        while model and (len(model) + 1 > self.max_messages or sum(map(len, model.values())) + size > self.max_bytes):
            oldest = min(model)
            expected.append(oldest)
            del model[oldest]
        model[seq] = payload
        assert self.box.append(seq, payload) == expected
        self.model = model
        self.dropped += expected
        self.next = seq + 1

    @precondition(lambda self: bool(self.model))
    @rule(data=st.data())
    def ack_one(self, data: st.DataObject) -> None:
        seq = data.draw(st.sampled_from(sorted(self.model)))
        assert self.box.ack(seq)
        del self.model[seq]
        self.acked += 1

    @rule(upto=st.integers(-1, 40))
    def ack_upto(self, upto: int) -> None:
        gone = [s for s in self.model if s <= upto]
        assert self.box.ack_upto(upto) == len(gone)
        for s in gone:
            del self.model[s]
        self.acked += len(gone)

    @rule(lo=st.integers(0, 40), width=st.integers(0, 6))
    def ack_range(self, lo: int, width: int) -> None:
        gone = [s for s in self.model if lo <= s <= lo + width]
        assert self.box.ack_ranges([[lo, lo + width]]) == len(gone)
        for s in gone:
            del self.model[s]
        self.acked += len(gone)

    @rule()
    def restart(self) -> None:
        self.box = Outbox(self.dir, max_messages=self.max_messages, max_bytes=self.max_bytes, fsync=False)

    @invariant()
    def matches_model(self) -> None:
        assert self.box.pending() == sorted(self.model)
        s = self.box.stats()
        assert s.pending_bytes == sum(map(len, self.model.values())) <= self.max_bytes
        assert s.pending <= self.max_messages
        assert s.dropped == len(self.dropped)
        assert s.acked == self.acked
        assert s.next_seq == self.next
        assert s.appended == s.acked + s.dropped + s.pending
        dropped_set = {x for lo, hi in s.dropped_ranges for x in range(lo, hi + 1)}
        assert dropped_set == set(self.dropped)
        for seq in list(self.model)[:2]:
            assert self.box.get(seq) == self.model[seq]


TestOutboxMachine = OutboxMachine.TestCase
TestOutboxMachine.settings = settings(
    max_examples=60, stateful_step_count=30, deadline=None, suppress_health_check=[HealthCheck.too_slow]
)


def test_state_file_is_json(tmp_path: Path) -> None:
    box = Outbox(tmp_path, max_messages=1, fsync=False)
    box.append(0, b"a")
    box.append(1, b"b")
    state = json.loads((tmp_path / STATE_FILE).read_text())
    assert state["dropped"] == 1
    assert state["dropped_ranges"] == [[0, 0]]
    assert state["next_seq"] == 2


def test_take_acked_names_exactly_what_it_removed_never_what_the_budget_dropped(tmp_path: Path) -> None:
    box = Outbox(tmp_path / "o", max_messages=4, fsync=False)
    dropped: list[int] = []
    for seq in range(6):
        dropped += box.append(seq, _payload(seq))
    assert dropped == [0, 1]  # the budget: the oldest, counted
    assert box.take_acked_ranges([[0, 3]]) == [2, 3]  # 0 and 1 were dropped, not acknowledged
    assert box.take_acked([5, 5, 9]) == [5]
    s = box.stats()
    assert (s.acked, s.dropped, s.pending) == (3, 2, 1)
    assert s.appended == s.acked + s.dropped + s.pending


def test_the_budget_drops_expendable_messages_first_then_the_oldest(tmp_path: Path) -> None:
    box = Outbox(tmp_path / "o", max_messages=4, fsync=False)
    sent = {1, 2}
    for seq in range(4):
        assert box.append(seq, _payload(seq), sent.__contains__) == []
    assert box.append(4, _payload(4), sent.__contains__) == [1]  # the oldest sent one, not #0
    assert box.append(5, _payload(5), sent.__contains__) == [2]
    assert box.append(6, _payload(6), sent.__contains__) == [0]  # none sent left: the oldest
    assert box.pending() == [3, 4, 5, 6]
    assert box.stats().dropped_ranges == ((0, 2),)
    assert Outbox(tmp_path / "o").stats().dropped == 3


def test_an_append_without_sync_is_on_disk_for_a_restart_and_sync_flushes_it(tmp_path: Path) -> None:
    box = Outbox(tmp_path / "ob", fsync=True)
    box.append(0, b"a", sync=False)
    assert Outbox(tmp_path / "ob").next_seq == 1  # renamed at once: a process killed now restarts after it
    box.sync(0)
    assert box.ack(0)
    box.sync(0)  # no longer pending: nothing to flush
    assert box.get(0) is None
