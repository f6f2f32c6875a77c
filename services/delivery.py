"""Store-and-forward delivery of a ROV's clouds: outbox first, publish, re-send until the base acknowledges.

Protocol (chosen over zenoh-ext's advanced publisher/subscriber, whose history cache lives in the
publisher's memory: it is lost when the ROV restarts and knows nothing of what the base station has
persisted):

1. :meth:`OutboxSink.send` encodes the cloud, publishes it on ``<root>/<robot>/cloud`` with BLOCK
   congestion control and appends it to the robot's disk-backed :class:`~services.outbox.Outbox`
   (fsync'ed by default) where it stays until acknowledged.
2. The base station de-duplicates by sequence number and, once a cloud is persisted in its ``--state``,
   lists it in the JSON answered on ``<root>/base/acks/<robot>`` (``{"ranges": [[lo, hi], ...]}``).
3. A background thread of the ROV asks that queryable every ``ack_period_s`` and removes the acknowledged
   messages from the outbox. While the base station's cloud subscriber is present (the publisher's
   ``matching_status``) it re-sends, oldest first and at most ``max_resend_per_cycle`` per cycle:
   at once, every cloud published while no subscriber matched (router restart, tether cut, base
   restarted: zenoh sent nothing); and every cloud unacknowledged for ``resend_after_s`` that is evidently
   lost: a later cloud was acknowledged, or no acknowledgement moved on for ``stall_s``. A base station
   that is only slow (saturated) keeps acknowledging in order and is not flooded with duplicates.

Nothing is lost silently: a full outbox drops its oldest messages and counts them (see
:mod:`services.outbox`), and the base station shows them as ``missed``.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from dataclasses import dataclass
from typing import Any

from .keys import FleetKeys, check_robot_name
from .outbox import Outbox, OutboxError
from .wire import ENCODING, AnyCloud

log = logging.getLogger(__name__)

#: Re-sends per cycle while acknowledgements are stalled: a probe, not a flood (a base that never
#: acknowledges must not receive the whole outbox every few seconds).
STALL_PROBES = 10


@dataclass
class DeliveryCounters:
    """Counters of an :class:`OutboxSink`.

    Attributes:
        sent: clouds published the first time.
        resent: re-publications of pending clouds.
        acked: clouds acknowledged by the base station (removed from the outbox).
        dropped: clouds dropped because the outbox was full.
        ack_polls: acknowledgement queries answered.
        base_seen: times the base station's subscriber (re)appeared.
        unstored: clouds published live but not kept in the outbox (disk write failed).
        sent_bytes: bytes of the clouds published the first time (the clouds' own size).
        resent_bytes: bytes re-published.
    """

    sent: int = 0
    resent: int = 0
    acked: int = 0
    dropped: int = 0
    ack_polls: int = 0
    base_seen: int = 0
    unstored: int = 0
    sent_bytes: int = 0
    resent_bytes: int = 0


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
        outbox: the robot's outbox (its ``next_seq`` is where the robot's numbering continues).
        ack_period_s: how often the acknowledgements are fetched and overdue clouds re-sent, seconds.
        resend_after_s: a pending cloud is sent again when it was last sent this long ago, seconds.
        max_resend_per_cycle: at most this many re-sends per cycle (spreads a long backlog).
        stall_s: when no acknowledgement moved on for this long while clouds are pending, overdue clouds are
            re-sent even if no later cloud was acknowledged (the lost cloud was the last one), seconds.
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
        self.counters = DeliveryCounters()
        self.publisher = session.declare_publisher(
            keys.cloud(self.robot),
            encoding=zenoh.Encoding(ENCODING),
            congestion_control=zenoh.CongestionControl.BLOCK,
            reliability=zenoh.Reliability.RELIABLE,
        )
        self._lock = threading.Lock()
        self._pub_lock = threading.Lock()  # one put at a time: live sends and re-sends interleave cleanly
        self._last_sent: dict[int, float] = {}
        self._unheard: set[int] = set()  # published while no subscriber matched
        self._stop = threading.Event()
        self._wake = threading.Event()
        self._base_present = False
        self._acked_high = -1  # highest sequence number the base station has acknowledged
        self._last_progress = time.monotonic()  # last time the acknowledgements moved on
        self._thread = threading.Thread(target=self._loop, name=f"delivery-{robot}", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------------------------------- sink
    def send(self, msg: AnyCloud) -> None:
        """Publish ``msg`` and store it in the outbox (durably) until the base station acknowledges it.

        The live copy goes first so that the disk write (fsync) adds nothing to the live latency; an
        acknowledgement that arrives before the append finishes is applied at the next poll (the base
        station's answer always lists everything it holds). A failed disk write is logged and counted
        (``unstored``), never raised: the robot keeps running and the live copy is on its way.
        """
        payload = msg.with_sent_ns(time.time_ns()).to_bytes()
        heard = self.base_present()  # no matching subscriber: zenoh sends nothing, re-send on reappearance
        with self._lock:
            self._last_sent[msg.seq] = time.monotonic()
            if not heard:
                self._unheard.add(msg.seq)
            self.counters.sent += 1
            self.counters.sent_bytes += len(payload)
        self._put(payload)
        try:
            dropped = self.outbox.append(msg.seq, payload)
        except OutboxError as err:
            with self._lock:
                self.counters.unstored += 1
                self._last_sent.pop(msg.seq, None)
                self._unheard.discard(msg.seq)
            log.error("rov %s: cloud #%d not kept for re-sending: %s", self.robot, msg.seq, err)
            return
        if dropped:
            with self._lock:
                self.counters.dropped += len(dropped)
                for d in dropped:
                    self._last_sent.pop(d, None)
                    self._unheard.discard(d)

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

    def poll_acks(self, timeout_s: float = 1.0) -> int:
        """Ask the base station what it holds and forget those clouds; returns how many were removed."""
        removed = 0
        for reply in self.session.get(self.keys.base_acks(self.robot), timeout=timeout_s):
            if reply.ok is None:
                continue
            try:
                ranges = parse_ack_reply(reply.ok.payload.to_bytes(), self.robot)
            except ValueError as err:
                log.warning("rov %s: ignored an ack answer: %s", self.robot, err)
                continue
            top = max((r[1] for r in ranges), default=-1)
            with self._lock:
                if top > self._acked_high:
                    self._acked_high = top
                    self._last_progress = time.monotonic()
            pending = self.outbox.pending()
            if not pending:
                break
            lo, hi = pending[0], pending[-1]
            relevant = [r for r in ranges if r[1] >= lo and r[0] <= hi]
            n = self.outbox.ack_ranges(relevant)
            removed += n
            with self._lock:
                self.counters.ack_polls += 1
                self.counters.acked += n
                if n:
                    self._last_progress = time.monotonic()
                    # forget what was acknowledged; numbers above ``hi`` may be published but not yet
                    # appended (send publishes first), so they are kept
                    held = set(self.outbox.pending())
                    for s in [s for s in self._last_sent if s <= hi and s not in held]:
                        del self._last_sent[s]
                        self._unheard.discard(s)
        return removed

    def cycle(self) -> None:
        """One round: fetch acks, re-send overdue clouds when the base station is present."""
        present = self.base_present()
        came_back = present and not self._base_present
        self._base_present = present
        if came_back:
            with self._lock:
                self.counters.base_seen += 1
            log.info("rov %s: base station present; %d clouds pending", self.robot, len(self.outbox))
        if not len(self.outbox):
            return
        if present:
            self.poll_acks()
        if not present or not len(self.outbox):
            return
        now = time.monotonic()
        budget = self.max_resend_per_cycle
        probes = STALL_PROBES  # while acks are stalled, only a few of the oldest go (the base may not ack)
        with self._lock:
            acked_high = self._acked_high
            stalled = now - self._last_progress >= self.stall_s
        for seq in self.outbox.pending():
            if budget <= 0 or self._stop.is_set():
                break
            with self._lock:
                last = self._last_sent.get(seq, 0.0)
                unheard = seq in self._unheard
            # Re-send what was published while nobody listened, and what is overdue AND evidently lost: a
            # later cloud was acknowledged, or acknowledgements stalled altogether. A base station that is
            # merely slow keeps acknowledging in order, and gets no duplicates to make it slower still.
            overdue = now - last >= self.resend_after_s
            lost = overdue and seq < acked_high
            if not unheard and not lost:
                if not (overdue and stalled and probes > 0):
                    continue
                probes -= 1
            payload = self.outbox.get(seq)  # read from disk only what goes out
            if payload is None:  # acknowledged meanwhile
                continue
            self._put(payload)
            budget -= 1
            with self._lock:
                self._last_sent[seq] = time.monotonic()
                self._unheard.discard(seq)
                self.counters.resent += 1
                self.counters.resent_bytes += len(payload)

    def wait_empty(self, timeout_s: float, stop: threading.Event | None = None) -> bool:
        """Wait until every cloud is acknowledged (the outbox is empty); False on timeout or ``stop``."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if not len(self.outbox):
                return True
            if stop is not None and stop.is_set():
                return False
            self._wake.set()
            time.sleep(min(0.1, self.ack_period_s))
        return not len(self.outbox)

    def stats(self) -> dict[str, Any]:
        """Delivery counters and the outbox's, JSON-ready."""
        with self._lock:
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


__all__ = ["DeliveryCounters", "OutboxError", "OutboxSink", "parse_ack_reply"]
