"""Store-and-forward delivery of a ROV's clouds: outbox first, publish, re-send until the base acknowledges.

Protocol (chosen over zenoh-ext's advanced publisher/subscriber, whose history cache lives in the
publisher's memory: it is lost when the ROV restarts and knows nothing of what the base station has
persisted):

1. :meth:`OutboxSink.send` encodes the cloud, appends it to the robot's disk-backed
   :class:`~services.outbox.Outbox` (written before the publication, so that a killed ROV never gives its
   number to another cloud; fsync'ed after it, by default), where it stays until acknowledged, and publishes
   it on ``<root>/<robot>/cloud`` (BLOCK congestion control, priority ``DATA_LOW``).
2. The base station de-duplicates by sequence number and, once a cloud is persisted in its ``--state``,
   lists it in the JSON answered on ``<root>/base/acks/<robot>`` (``{"ranges": [[lo, hi], ...]}``).
3. A background thread of the ROV asks that queryable every ``ack_period_s`` (priority ``INTERACTIVE_HIGH``,
   express: the question never waits behind queued clouds in Zenoh's transmission queues) and removes the
   acknowledged messages from the outbox. While the base station's cloud subscriber is present (the
   publisher's ``matching_status``) it re-sends, oldest first:

   * every cloud published while no subscriber matched (router restart, tether cut, base restarted: zenoh
     sent nothing), and every pending cloud reloaded from an earlier run;
   * every cloud that is evidently lost: a cloud *sent after it* was acknowledged (the stream is ordered, so
     its acknowledgement could have come back and did not). A cloud re-sent is not declared lost again until
     something sent after the re-send is acknowledged: no re-send before its acknowledgement could be back;
   * when no acknowledgement moved on for the retransmission timeout, one probe (the oldest cloud), and the
     timeout doubles for the next probe (capped at :data:`MAX_BACKOFF_S`) until an acknowledgement moves on.

   The timeout follows the measured acknowledgement round trip (:class:`AckClock`: send to the poll that
   first lists a cloud sent once, smoothed as TCP does: ``srtt + 4 rttvar``, at least ``resend_after_s`` and
   ``stall_s``). Re-sends are paced: they go out only while the bytes in flight (sent after the newest
   acknowledged send, not yet timed out) stay under twice what the acknowledgements show the link delivers
   per shortest round trip (at least :data:`MIN_WINDOW_BYTES`), so that a backlog after an outage drains at
   the link's rate instead of filling the link with copies and keeping the acknowledgements behind them.
   A base station that is only slow keeps acknowledging in order and gets no duplicates.

When the link is slower than the sensor (docs/reliability.md, "A link slower than the sensor"): every cloud
is kept on disk within the outbox's budget (``--outbox-max-mb``, ``--outbox-max-messages``); a new cloud
goes out live only while the bytes in flight leave room for it (:meth:`OutboxSink.live_room`: a generous
window while nothing is queued, half the re-send window while a backlog is), otherwise it is **queued** on
disk; the backlog is forwarded oldest first in the pacing window's room. Only the budget drops clouds,
logged and counted: first the oldest whose copy already went out (``released``: it arrives unless that copy
is lost), then the oldest never sent (``dropped_budget``: lost, the base station shows it as ``missed``).
Each cloud is counted once, in the category of its first copy (or of its loss)::

    published + reloaded = live + forwarded + queued + dropped_budget
    live + forwarded + queued = acked + pending + released + unstored

(``pending``: in the outbox; ``unstored``: published live but not written to disk, counted under ``live``).
Nothing is lost silently: a full outbox drops its oldest messages and counts them (see
:mod:`services.outbox`), and the base station shows them as ``missed``.

Layout: this module is the sink's Zenoh side (the publisher, the ack queries and their answer's format, the
delivery thread, the waits and the stats) and re-exports the rest, so that ``services.delivery`` stays the one
name callers import. Its parts, each a module without Zenoh, threads or locks:

* :mod:`services.delivery_link`: :class:`AckClock`, what the acknowledgements show of the link (round trip,
  delivery rate, retransmission timeout with its backoff, pacing window);
* :mod:`services.delivery_book`: :class:`~services.delivery_book.DeliveryBook`, what went out when and how
  often, what was acknowledged, and :class:`DeliveryCounters`, each cloud counted once;
* :mod:`services.delivery_pacing`: the decisions: room for a live cloud, the re-sends of a cycle, the probe;
* :mod:`services.wallclock`: the robot's wall clock that stamps ``sent_ns`` (:func:`wall_clock_ns`).

The sink holds one lock around every call into the book, the clock and the pacing.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from typing import Any

from .delivery_book import DeliveryBook, DeliveryCounters
from .delivery_link import (
    MAX_BACKOFF_S,
    MIN_RTT_MEMORY_S,
    MIN_WINDOW_BYTES,
    RATE_MEMORY_S,
    RATE_WINDOW_S,
    WINDOW_GAIN,
    AckClock,
)
from .delivery_pacing import LIVE_GAIN, MIN_LIVE_WINDOW_BYTES, choose_resends, live_room
from .keys import FleetKeys, check_robot_name
from .outbox import Outbox, OutboxError
from .wallclock import CLOCK_OFFSET_ENV, wall_clock_ns
from .wire import ENCODING, AnyCloud

log = logging.getLogger(__name__)

#: Without an answer to the ack polls for this long (or 3 query round trips, if longer) while clouds are
#: pending, the link is taken as down: new clouds go to the outbox only, forwarded once answers return, s.
SUSPECT_S = 1.5
#: An acknowledgement poll waits at least / at most this long for the answer, s.
MIN_POLL_TIMEOUT_S = 2.0
MAX_POLL_TIMEOUT_S = 20.0


def parse_ack_reply(payload: bytes, robot: str) -> list[list[int]]:
    """The ``ranges`` of a base station's ack answer; raises ValueError for anything malformed."""
    body = json.loads(payload)
    if not isinstance(body, dict) or body.get("robot") != robot:
        msg = f"ack answer is not for robot {robot!r}"
        raise ValueError(msg)
    ranges = body.get("ranges")
    if not isinstance(ranges, list):
        msg = "ack answer has no 'ranges' list"
        raise ValueError(msg)
    out: list[list[int]] = []
    for r in ranges:
        if (
            not isinstance(r, list)
            or len(r) != 2
            or not all(isinstance(v, int) and not isinstance(v, bool) for v in r)
            or not 0 <= r[0] <= r[1]
        ):
            msg = f"ack answer holds a bad range {r!r}"
            raise ValueError(msg)
        out.append([r[0], r[1]])
    return out


class OutboxSink:
    """A :class:`services.rov.CloudSink` that keeps every cloud until the base station acknowledges it.

    Args:
        session: an open Zenoh session (the caller owns it).
        keys: the fleet's key expressions.
        robot: this robot's name.
        outbox: the robot's outbox (its ``next_seq`` is where the robot's numbering continues; clouds pending
            in it from an earlier run are sent again once the base station is present).
        ack_period_s: how often the acknowledgements are fetched and lost clouds re-sent, seconds.
        resend_after_s: the shortest retransmission timeout, seconds (the measured one is usually longer).
        max_resend_per_cycle: at most this many re-sends per cycle (the pacing window usually stops earlier).
        stall_s: no probe is sent before acknowledgements have stalled this long, seconds.
        forward_now: re-send and forward from the outbox at once; False waits for :meth:`start_forwarding`
            (a ROV calls it once it serves its calibration: a base station that has just restarted triangulates
            the compact clouds of the backlog only with the calibration the robot serves, and refuses them
            until then).
    """

    def __init__(
        self,
        session: Any,
        keys: FleetKeys,
        robot: str,
        outbox: Outbox,
        *,
        ack_period_s: float = 0.5,
        resend_after_s: float = 3.0,
        max_resend_per_cycle: int = 300,
        stall_s: float = 10.0,
        forward_now: bool = True,
    ) -> None:
        import zenoh

        self.session = session
        self.keys = keys
        self.robot = check_robot_name(robot)
        self.outbox = outbox
        self.ack_period_s = ack_period_s
        self.resend_after_s = resend_after_s
        self.max_resend_per_cycle = max_resend_per_cycle
        self.stall_s = stall_s
        self.clock = AckClock(resend_after_s)
        # what went out when, what was acknowledged (clouds pending from an earlier run are unheard, queued)
        self.book = DeliveryBook(outbox.pending(), outbox.next_seq, self.clock)
        self.counters: DeliveryCounters = self.book.counters
        self._ack_priority = zenoh.Priority.INTERACTIVE_HIGH
        self.publisher = session.declare_publisher(
            keys.cloud(self.robot),
            encoding=zenoh.Encoding(ENCODING),
            congestion_control=zenoh.CongestionControl.BLOCK,
            reliability=zenoh.Reliability.RELIABLE,
            priority=zenoh.Priority.DATA_LOW,  # below the ack queries and the ROV's status
        )
        self._lock = threading.Lock()
        #: held over an acknowledgement's removal from the outbox and its counters, and by stats()
        self._ack_lock = threading.Lock()
        self._pub_lock = threading.Lock()  # one put at a time: live sends and re-sends interleave cleanly
        self._stop = threading.Event()
        self._forwarding = threading.Event()
        if forward_now:
            self._forwarding.set()
        self._wake = threading.Event()
        self._base_present = False
        self._last_answer = time.monotonic()  # the last answer to an ack poll (or an empty outbox)
        self._holding = False
        self._poll_timeout = MIN_POLL_TIMEOUT_S  # how long an ack poll waits for the answer (adapts)
        self._query_rtt: float | None = None  # smoothed time an ack poll took to be answered, s
        self._thread = threading.Thread(target=self._loop, name=f"delivery-{robot}", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------------------------------- sink
    def send(self, msg: AnyCloud) -> None:
        """Publish ``msg`` and store it in the outbox (durably) until the base station acknowledges it.

        The cloud is written to the outbox (not yet flushed) before its live copy goes, so that a ROV killed at
        any moment restarts with its number used (numbers are never given twice); the flush to disk (fsync)
        follows the put, so it adds nothing to the live latency. A failed disk write is logged and counted
        (``unstored``), never raised: the robot keeps running and a live copy goes out.

        No live copy goes out while the ack polls go unanswered (``held``) or the live window is full
        (``thinned``, :meth:`live_room`): the cloud is queued in the outbox and forwarded from there.
        """
        payload = msg.with_sent_ns(wall_clock_ns()).to_bytes()
        heard = self.base_present()  # no matching subscriber: zenoh sends nothing, re-send on reappearance
        hold = heard and self.link_suspect()  # a link that looks down gets no live copy to lose
        with self._lock:
            thin = heard and not hold and not self.live_room(len(payload), time.monotonic())
            self.book.note_send(msg.seq, len(payload), time.monotonic(), heard=heard, hold=hold, thin=thin)
            if thin and (self.counters.thinned in (1, 10, 100) or self.counters.thinned % 1000 == 0):
                log.info(
                    "rov %s: the link does not carry every cloud live; %d clouds queued on disk so far, forwarded "
                    "oldest first as it allows",
                    self.robot,
                    self.counters.thinned,
                )
        # On disk before any copy leaves: a ROV killed right after the put would otherwise restart without
        # knowing this number and give it to another cloud, which the base station, holding the first one,
        # would take for a duplicate and drop. Flushed to disk after the put (the live copy never waits for it).
        try:
            dropped = self.outbox.append(msg.seq, payload, self.book.expendable, sync=False)
        except OutboxError as err:
            with self._lock:
                self.book.note_unstored(msg.seq)
            log.error("rov %s: cloud #%d not kept for re-sending: %s", self.robot, msg.seq, err)
            self._put(payload)  # no copy on disk: a live one is better than none
            return
        if not (hold or thin):
            self._put(payload)
            with self._lock:
                self.book.note_put(msg.seq, time.monotonic())
        try:
            self.outbox.sync(msg.seq)
        except OutboxError as err:  # the file is written: a crash of the process keeps it, a power cut may not
            log.error("rov %s: %s", self.robot, err)
        if dropped:
            with self._lock:
                self.book.note_dropped(dropped)

    def live_room(self, size: int, now: float) -> bool:
        """True when a new cloud of ``size`` bytes may go out live; caller holds the lock.

        While nothing is queued: the bytes in flight stay under :data:`LIVE_GAIN` times what the link
        delivers per retransmission timeout (at least :data:`MIN_LIVE_WINDOW_BYTES`), so a link that keeps up
        is never thinned. While a backlog is queued: under half the re-send window, so that the other half
        forwards the backlog (oldest first) and the live stream is thinned to what the link carries
        (:func:`services.delivery_pacing.live_room`).
        """
        return live_room(self.book, size, now)

    def _put(self, payload: bytes) -> None:
        try:
            with self._pub_lock:
                self.publisher.put(payload)
        except Exception as err:  # the outbox keeps it; the next cycle re-sends
            log.warning("rov %s: publish failed (kept in the outbox): %s", self.robot, err)

    # ------------------------------------------------------------------------------------------- loop
    def _loop(self) -> None:
        while not self._stop.is_set():
            try:
                self.cycle()
            except Exception as err:  # never let the delivery thread die
                log.exception("rov %s: delivery cycle failed: %s", self.robot, err)
            self._wake.wait(self.ack_period_s)
            self._wake.clear()

    def base_present(self) -> bool:
        """True while a subscriber of this robot's clouds (the base station) is reachable."""
        try:
            return bool(self.publisher.matching_status.matching)
        except Exception:
            return False

    def link_suspect(self) -> bool:
        """True while the ack polls have gone unanswered for long (:data:`SUSPECT_S`): the link looks down."""
        with self._lock:
            silent = time.monotonic() - self._last_answer
            suspect = silent > max(SUSPECT_S, 3 * (self._query_rtt or 0.0))
            if suspect != self._holding:
                self._holding = suspect
                if suspect:
                    log.warning(
                        "rov %s: no answer from the base station for %.0f s; new clouds are kept in the outbox "
                        "and forwarded once it answers",
                        self.robot,
                        silent,
                    )
                else:
                    log.info("rov %s: the base station answers again", self.robot)
            return suspect

    def poll_acks(self, timeout_s: float | None = None) -> int:
        """Ask the base station what it holds and forget those clouds; returns how many were removed.

        ``timeout_s`` defaults to four times the query's recent round trip (at least :data:`MIN_POLL_TIMEOUT_S`),
        doubled after a poll that got no answer (at most :data:`MAX_POLL_TIMEOUT_S`): on a slow link the
        answer may take seconds, and a poll that always gives up too early would never learn that.
        """
        if timeout_s is None:
            timeout_s = self._poll_timeout
        removed = 0
        asked = time.monotonic()
        answered = False
        replies = self.session.get(
            self.keys.base_acks(self.robot), timeout=timeout_s, priority=self._ack_priority, express=True
        )
        for reply in replies:
            if reply.ok is None:  # an error, or zenoh's reply that the query timed out: no answer
                continue
            if not answered:
                answered = True
                self._last_answer = time.monotonic()
                took = time.monotonic() - asked
                self._query_rtt = took if self._query_rtt is None else 0.75 * self._query_rtt + 0.25 * took
                self._poll_timeout = min(MAX_POLL_TIMEOUT_S, max(MIN_POLL_TIMEOUT_S, 4 * self._query_rtt))
            try:
                ranges = parse_ack_reply(reply.ok.payload.to_bytes(), self.robot)
            except ValueError as err:
                log.warning("rov %s: ignored an ack answer: %s", self.robot, err)
                continue
            now = time.monotonic()
            with self._lock:
                self.book.note_answer()
            pending = self.outbox.pending()
            if not pending:
                with self._lock:
                    self.book.note_poll()
                break
            lo, hi = pending[0], pending[-1]
            relevant = [r for r in ranges if r[1] >= lo and r[0] <= hi]
            # the removal and its counters under one lock that stats() takes too: a reader never sees a cloud
            # gone from the outbox and not yet counted acknowledged
            with self._ack_lock:
                hit = self.outbox.take_acked_ranges(relevant) if relevant else []  # exactly those removed
                removed += len(hit)
                with self._lock:
                    self.book.note_acked(hit, now)
        if not answered:
            self._poll_timeout = min(MAX_POLL_TIMEOUT_S, 2 * self._poll_timeout)
        return removed

    def cycle(self) -> None:
        """One round: fetch acks, then re-send what is unheard or lost, paced, when the base is present."""
        present = self.base_present()
        came_back = present and not self._base_present
        self._base_present = present
        if came_back:
            with self._lock:
                self.counters.base_seen += 1
            log.info("rov %s: base station present; %d clouds pending", self.robot, len(self.outbox))
        if not len(self.outbox):
            with self._lock:
                self._last_answer = time.monotonic()  # nothing to ask about: no reason to doubt the link
            return
        if present:
            self.poll_acks()
        if not present or not len(self.outbox) or not self._forwarding.is_set():
            return
        for seq in self._choose_resends(time.monotonic()):
            if self._stop.is_set():
                break
            payload = self.outbox.get(seq)  # read from disk only what goes out
            if payload is None:  # acknowledged meanwhile
                continue
            with self._lock:
                unheard = self.book.is_unheard(seq)
            self._put(payload)
            with self._lock:
                self.book.note_resend(seq, len(payload), time.monotonic(), unheard=unheard)

    def _choose_resends(self, now: float) -> list[int]:
        """The clouds to send again this cycle, oldest first, within the pacing window (only a probe while the
        link looks down)."""
        pending = self.outbox.pending()
        suspect = self.link_suspect()
        with self._lock:
            choice = choose_resends(
                self.book,
                pending,
                now,
                suspect=suspect,
                max_count=self.max_resend_per_cycle,
                stall_s=self.stall_s,
            )
            if choice.probe:
                log.info(
                    "rov %s: no acknowledgement for %.0f s; probing with #%d (next timeout %.1f s)",
                    self.robot,
                    now - self.book.last_progress,
                    choice.seqs[0],
                    self.clock.timeout(),
                )
            return choice.seqs

    def start_forwarding(self) -> None:
        """Start re-sending and forwarding from the outbox (see ``forward_now``)."""
        self._forwarding.set()
        self._wake.set()

    def wait_empty(self, timeout_s: float, stop: threading.Event | None = None, *, idle: bool = False) -> bool:
        """Wait until every cloud is acknowledged (the outbox is empty); False on timeout or ``stop``.

        With ``idle`` the timeout counts from the last time an acknowledgement moved on, so that a backlog
        that is draining is not given up on.
        """
        return self._wait(lambda: not len(self.outbox), timeout_s, stop, idle)

    def wait_acked(
        self, first_seq: int, last_seq: int, timeout_s: float, stop: threading.Event | None = None, *, idle: bool = True
    ) -> bool:
        """Wait until no cloud numbered ``first_seq..last_seq`` is pending; ``idle`` as in :meth:`wait_empty`."""

        def done() -> bool:
            return not any(first_seq <= s <= last_seq for s in self.outbox.pending())

        return self._wait(done, timeout_s, stop, idle)

    def _wait(self, done: Any, timeout_s: float, stop: threading.Event | None, idle: bool) -> bool:
        start = time.monotonic()
        while True:
            if done():
                return True
            now = time.monotonic()
            with self._lock:
                since = max(start, self.book.last_progress) if idle else start
            if now - since >= timeout_s or (stop is not None and stop.is_set()):
                return bool(done())
            self._wake.set()
            time.sleep(min(0.1, self.ack_period_s))

    def budget_counts(self) -> dict[str, int]:
        """The link-budget counters (:meth:`DeliveryCounters.budget`), for the ROV's status."""
        with self._lock:
            return self.counters.budget()

    def stats(self) -> dict[str, Any]:
        """Delivery counters and the outbox's, JSON-ready."""
        with self._ack_lock, self._lock:
            c = self.counters
            out: dict[str, Any] = {
                "sent": c.sent,
                "resent": c.resent,
                "acked": c.acked,
                "dropped": c.dropped,
                "ack_polls": c.ack_polls,
                "base_seen": c.base_seen,
                "unstored": c.unstored,
                "sent_bytes": c.sent_bytes,
                "resent_bytes": c.resent_bytes,
                "resent_unheard": c.resent_unheard,
                "held": c.held,
                "thinned": c.thinned,
                **c.budget(),
                "link": self.clock.to_json(),
            }
            out["outbox"] = self.outbox.stats().to_json_dict()
        return out

    def close(self) -> None:
        """Stop the delivery thread and undeclare the publisher (pending clouds stay in the outbox)."""
        self._stop.set()
        self._wake.set()
        self._thread.join(timeout=5.0)
        try:
            self.publisher.undeclare()
        except Exception as err:
            log.debug("publisher undeclare failed: %s", err)

    def __enter__(self) -> OutboxSink:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


__all__ = [
    "CLOCK_OFFSET_ENV",
    "LIVE_GAIN",
    "MAX_BACKOFF_S",
    "MAX_POLL_TIMEOUT_S",
    "MIN_LIVE_WINDOW_BYTES",
    "MIN_POLL_TIMEOUT_S",
    "MIN_RTT_MEMORY_S",
    "MIN_WINDOW_BYTES",
    "RATE_MEMORY_S",
    "RATE_WINDOW_S",
    "SUSPECT_S",
    "WINDOW_GAIN",
    "AckClock",
    "DeliveryCounters",
    "OutboxError",
    "OutboxSink",
    "parse_ack_reply",
    "wall_clock_ns",
]
