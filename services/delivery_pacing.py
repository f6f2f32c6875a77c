"""What a ROV's delivery may send now: room for a live cloud, the re-sends of a cycle, a probe after a stall.

Three decisions, each a pure function of the :class:`~services.delivery_book.DeliveryBook` (what went out
when), its :class:`~services.delivery_link.AckClock` (what the acknowledgements show of the link) and the
caller's clock; the sink (:mod:`services.delivery`) holds its lock around each call and acts on the answer.

* **In flight** (:func:`in_flight_bytes`): the bytes sent after the newest acknowledged send and not yet timed
  out, unheard copies excluded (they reached no subscriber, so they hold no room on the link).
* **Live room** (:func:`live_room`): a new cloud goes out live while the bytes in flight leave room for it:
  while nothing is queued, :data:`LIVE_GAIN` times what the link delivers per retransmission timeout (at least
  :data:`MIN_LIVE_WINDOW_BYTES`), so a link that keeps up is never thinned; while a backlog is queued, half
  the re-send window, so that the other half forwards the backlog and the live stream is thinned to what the
  link carries. A cloud with nothing in flight always goes.
* **Re-sends** (:func:`choose_resends`): oldest first, every pending cloud that is unheard (or never sent by
  this process) or evidently lost (sent before ``lost_before``), while the bytes in flight stay within the
  pacing window (the first always goes unless the window is already full), at most ``max_count`` a cycle;
  none while the link looks down. When none is due and the acknowledgements stalled for the (backed-off)
  retransmission timeout (at least ``stall_s``), one probe: the oldest pending cloud, and the timeout doubles.

Why a window and not a timer: a backlog after an outage drains at the link's rate instead of filling the
link with copies that keep the acknowledgements behind them, and a base station that is only slow keeps
acknowledging in order and gets no duplicates (docs/reliability.md, "Store and forward").
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

from .delivery_book import DeliveryBook

#: While no backlog is queued, a new cloud goes out live while the bytes in flight stay under this many
#: times what the link delivers per retransmission timeout (at least :data:`MIN_LIVE_WINDOW_BYTES`): a link
#: that keeps up never holds more than one timeout's worth in flight, so the live stream is only thinned
#: when the sensor offers more than the link carries.
LIVE_GAIN = 2.0
MIN_LIVE_WINDOW_BYTES = 512 * 1024


class ResendChoice(NamedTuple):
    """The clouds to send again this cycle, oldest first; ``probe`` when it is the stall probe (one cloud)."""

    seqs: list[int]
    probe: bool


def in_flight_bytes(book: DeliveryBook, now: float, timeout: float) -> int:
    """Bytes sent after the newest acknowledged send and less than ``timeout`` seconds before ``now``."""
    acked_t = book.acked_sent_t
    return sum(
        book.sizes.get(s, 0)
        for s, t in book.last_sent.items()
        if t > acked_t and now - t < timeout and s not in book.unheard
    )


def live_room(book: DeliveryBook, size: int, now: float) -> bool:
    """True when a new cloud of ``size`` bytes may go out live at ``now`` (see the module docstring)."""
    clock = book.clock
    timeout = clock.timeout()
    if book.counters.queued:
        limit = clock.window() / 2
    else:
        limit = max(MIN_LIVE_WINDOW_BYTES, LIVE_GAIN * clock.rate() * timeout)
    in_flight = in_flight_bytes(book, now, timeout)
    return in_flight == 0 or in_flight + size <= limit


def choose_resends(
    book: DeliveryBook, pending: Sequence[int], now: float, *, suspect: bool, max_count: int, stall_s: float
) -> ResendChoice:
    """The pending clouds (``pending``, oldest first) to send again at ``now``, within the pacing window.

    ``suspect``: the link looks down (no answer to the ack polls): no re-sends, only a probe when one is due.
    A probe backs the clock's timeout off (:meth:`~services.delivery_link.AckClock.stalled`).
    """
    clock = book.clock
    timeout = clock.timeout()
    window = clock.window()
    lost_before = book.lost_before
    in_flight = in_flight_bytes(book, now, timeout)
    chosen: list[int] = []
    for seq in [] if suspect else pending:
        if len(chosen) >= max_count:
            break
        last = book.last_sent.get(seq)
        # unheard (or never sent by this process) / sent before a cloud acknowledged a poll ago
        if not (seq in book.unheard or last is None or last < lost_before):
            continue
        size = book.sizes.get(seq, 0)
        if chosen and in_flight + size > window:
            break
        if not chosen and in_flight >= window:
            break
        chosen.append(seq)
        in_flight += size
    if chosen:
        return ResendChoice(chosen, probe=False)
    # nothing evidently lost; a probe when acknowledgements stalled for the (backed-off) timeout
    stalled_for = now - book.last_progress
    if pending and stalled_for >= max(stall_s, timeout):
        oldest = pending[0]
        last_oldest = book.last_sent.get(oldest, 0.0)
        if now - last_oldest >= max(stall_s, timeout):
            clock.stalled()
            return ResendChoice([oldest], probe=True)
    return ResendChoice([], probe=False)


__all__ = ["LIVE_GAIN", "MIN_LIVE_WINDOW_BYTES", "ResendChoice", "choose_resends", "in_flight_bytes", "live_room"]
