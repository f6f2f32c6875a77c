"""The delivery's parts without Zenoh: the per-cloud book and its counters, the pacing decisions.

:class:`services.delivery_book.DeliveryBook` and :mod:`services.delivery_pacing` are driven here with made-up
``time.monotonic()`` seconds; the sink that calls them over a real network is tested in
``tests/test_delivery.py``.
"""

from __future__ import annotations

from services.delivery_book import DeliveryBook
from services.delivery_link import MIN_WINDOW_BYTES, AckClock
from services.delivery_pacing import MIN_LIVE_WINDOW_BYTES, ResendChoice, choose_resends, in_flight_bytes, live_room

KIB = 1024


def _identities_hold(book: DeliveryBook, pending: int) -> None:
    c = book.counters
    assert c.sent + c.reloaded == c.live + c.forwarded + c.queued + c.dropped_budget
    assert c.live + c.forwarded + c.queued == c.acked + pending + c.released + c.unstored


def test_each_cloud_is_counted_once_in_the_category_of_its_first_copy() -> None:
    book = DeliveryBook(reloaded=[0, 1], first_seq=2, clock=AckClock(min_rto_s=3.0))
    assert (book.counters.reloaded, book.counters.queued) == (2, 2)
    assert book.is_unheard(0)
    pending = {0, 1}
    for seq, heard, hold, thin in [(2, True, False, False), (3, True, True, False), (4, True, False, True)]:
        book.note_send(seq, 10 * KIB, float(seq), heard=heard, hold=hold, thin=thin)
        pending.add(seq)
        _identities_hold(book, len(pending))
    c = book.counters
    assert (c.live, c.queued, c.held, c.thinned) == (1, 4, 1, 1)
    assert not book.expendable(3)
    assert book.expendable(2)

    book.note_resend(3, 10 * KIB, 5.0, unheard=book.is_unheard(3))  # the backlog's first copy: forwarded
    assert (c.forwarded, c.queued, c.resent_unheard) == (1, 3, 1)
    assert not book.is_unheard(3)
    _identities_hold(book, len(pending))

    book.note_dropped([2, 4])  # 2 went out live: released; 4 never went out: lost to the budget
    pending -= {2, 4}
    assert (c.dropped, c.released, c.dropped_budget) == (2, 1, 1)
    _identities_hold(book, len(pending))

    book.note_acked([0, 3], now=6.0)  # 0: reloaded and acknowledged before this run sent it
    pending -= {0, 3}
    assert (c.acked, c.forwarded, c.ack_polls) == (2, 2, 1)
    assert book.last_progress == 6.0
    _identities_hold(book, len(pending))

    book.note_send(5, 10 * KIB, 7.0, heard=True, hold=False, thin=False)
    book.note_unstored(5)
    assert (c.unstored, c.live) == (1, 2)
    _identities_hold(book, len(pending))


def test_only_a_cloud_acknowledged_after_one_send_times_the_round_trip() -> None:
    clock = AckClock(min_rto_s=0.5)
    book = DeliveryBook(reloaded=[], first_seq=0, clock=clock)
    book.note_send(0, KIB, 1.0, heard=True, hold=False, thin=False)
    book.note_send(1, KIB, 1.0, heard=True, hold=False, thin=False)
    book.note_resend(1, KIB, 2.0, unheard=False)
    book.note_acked([1], now=2.5)  # re-sent: no sample (Karn's rule)
    assert clock.srtt is None
    book.note_acked([0], now=3.0)
    assert clock.srtt == 2.0
    assert book.acked_sent_t == 2.0


def test_live_room_thins_to_half_the_window_while_a_backlog_is_queued() -> None:
    book = DeliveryBook(reloaded=[], first_seq=0, clock=AckClock(min_rto_s=3.0))
    size = 200 * KIB
    assert live_room(book, 10 * MIN_LIVE_WINDOW_BYTES, 1.0)  # nothing in flight: a cloud always goes
    book.note_send(0, size, 1.0, heard=True, hold=False, thin=False)
    assert in_flight_bytes(book, 2.0, timeout=3.0) == size
    assert in_flight_bytes(book, 4.0, timeout=3.0) == 0  # timed out: no longer counted in flight
    assert live_room(book, size, 2.0)  # 400 KiB within the 512 KiB live floor
    book.note_send(1, size, 2.0, heard=True, hold=False, thin=True)  # queued: unheard, not in flight
    assert in_flight_bytes(book, 2.0, timeout=3.0) == size
    assert not live_room(book, size, 2.0)  # a backlog: half the 256 KiB re-send window


def test_resends_take_the_unheard_and_the_lost_then_a_probe_that_backs_off() -> None:
    clock = AckClock(min_rto_s=3.0)
    book = DeliveryBook(reloaded=[0], first_seq=1, clock=clock)
    for seq in (1, 2, 3):
        book.note_send(seq, KIB, float(seq), heard=True, hold=False, thin=False)
    assert choose_resends(book, [0, 1, 2, 3], 3.5, suspect=False, max_count=300, stall_s=10.0).seqs == [0]

    def choose(now: float, *, suspect: bool = False, max_count: int = 300) -> ResendChoice:
        return choose_resends(book, [0, 1, 2], now, suspect=suspect, max_count=max_count, stall_s=10.0)

    assert choose(3.5) == ([0], False)  # only the unheard one (3 is in flight, 1 and 2 not known lost)
    book.note_resend(0, KIB, 3.5, unheard=True)
    book.note_acked([3], now=4.0)
    book.note_answer()  # one answer later, 1 and 2 (sent before 3) are lost
    assert choose(4.5) == ([1, 2], False)
    assert choose(4.5, max_count=1).seqs == [1]
    assert choose(4.5, suspect=True) == ([], False)
    for seq in (1, 2):
        book.note_resend(seq, KIB, 4.5, unheard=False)
    assert choose(5.0) == ([], False)  # nothing due, no stall yet
    before = clock.timeout()
    assert choose(4.0 + 10.0, suspect=True) == ([0], True)  # stalled for stall_s: a probe, even while suspect
    assert clock.timeout() == 2 * before


def test_the_pacing_window_stops_the_resends_of_a_cycle() -> None:
    book = DeliveryBook(reloaded=range(8), first_seq=8, clock=AckClock(min_rto_s=3.0))
    for seq in range(8):
        book.note_resend(seq, 100 * KIB, 0.0, unheard=True)
        book.unheard.add(seq)  # as if those copies had reached no subscriber: all due again
    chosen = choose_resends(book, list(range(8)), 1.0, suspect=False, max_count=300, stall_s=10.0).seqs
    assert chosen == [0, 1]  # 200 KiB in flight; a third would pass the 256 KiB window
    assert MIN_WINDOW_BYTES == 256 * KIB
