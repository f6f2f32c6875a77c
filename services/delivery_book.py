"""Per-cloud bookkeeping of a ROV's delivery: what went out when, what the base acknowledged, what is counted.

:class:`DeliveryBook` is the memory of :class:`services.delivery.OutboxSink`; the sink does the talking
(Zenoh, the outbox on disk, its thread) and tells the book what happened. For each cloud pending in the outbox
the book keeps:

* ``last_sent``: the ``time.monotonic()`` of its latest copy, and ``sends``: how many copies went out (a cloud
  acknowledged after one send gives a round-trip sample to the :class:`~services.delivery_link.AckClock`; a
  re-sent one does not: Karn's rule);
* ``sizes``: its encoded size in bytes (what it weighs in flight, what its acknowledgement delivered);
* ``unheard``: the clouds none of whose copies can have reached the base station (published while no subscriber
  matched, held or thinned, or reloaded from an earlier run): sent again as soon as the base is present;
* ``fate``: the category of its first copy (``"live"``, ``"queued"``, ``"forwarded"``), so that each cloud is
  counted once in :class:`DeliveryCounters`, whatever happens to it later (acknowledged, dropped by the budget);

and, over all clouds, ``acked_sent_t`` (the latest send time among the clouds acknowledged so far),
``lost_before`` (the same as of the answer before the last: a cloud sent before it and still not acknowledged
one answer later is lost, since the stream is ordered and the base's workers may finish neighbouring clouds in
either order) and ``last_progress`` (when an acknowledgement last moved on).

The book decides nothing: what may go out, and when, is :mod:`services.delivery_pacing`. It holds no lock and
starts no thread; the sink holds its lock around every call. The counters' identities (docs/reliability.md,
"A link slower than the sensor") hold after every call::

    sent + reloaded == live + forwarded + queued + dropped_budget
    live + forwarded + queued == acked + pending + released + unstored
"""

from __future__ import annotations

import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

from .delivery_link import AckClock


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
        resent_unheard: re-publications of clouds whose earlier copies reached no subscriber (published while
            the base station was away, or reloaded from an earlier run): the first copy to go out on the link.
        held: clouds not published live because the ack polls went unanswered (the link looked down): kept
            in the outbox and forwarded from there (counted in ``resent_unheard`` then).
        thinned: clouds not published live because the link was not keeping up (no room in the live window):
            queued in the outbox and forwarded from there.

    The link-budget counters count each cloud once, in the category of its first copy (identities:
    ``sent + reloaded == live + forwarded + queued + dropped_budget`` and ``live + forwarded + queued ==
    acked + pending + released + unstored``, ``pending`` being the outbox's):

    Attributes:
        live: clouds whose first copy went out live (the one published by :meth:`OutboxSink.send`); a cloud
            whose disk write failed is counted here.
        queued: clouds in the outbox of which no copy went out yet (held, thinned, published while no
            subscriber matched, or reloaded from an earlier run).
        forwarded: clouds whose first copy went out later, from the outbox (a reloaded cloud the base station
            acknowledges before it is sent again counts here: an earlier run forwarded it).
        reloaded: clouds pending in the outbox when this sink started (counted in ``queued`` first).
        dropped_budget: clouds the disk budget dropped before any copy went out (lost; part of ``dropped``).
        released: clouds the disk budget dropped after a copy went out, before their acknowledgement (they
            arrive unless that copy is lost; part of ``dropped``).
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
    resent_unheard: int = 0
    held: int = 0
    thinned: int = 0
    live: int = 0
    queued: int = 0
    forwarded: int = 0
    reloaded: int = 0
    dropped_budget: int = 0
    released: int = 0

    def budget(self) -> dict[str, int]:
        """The link-budget counters, as :class:`services.wire.StatusMsg` carries them."""
        return {
            "live": self.live,
            "queued": self.queued,
            "forwarded": self.forwarded,
            "dropped_budget": self.dropped_budget,
            "released": self.released,
            "reloaded": self.reloaded,
        }


class DeliveryBook:
    """What a sink knows of each pending cloud and of the acknowledgements (see the module docstring).

    Not thread-safe: the caller holds its lock around every call (reading :meth:`expendable` excepted).
    Times are ``time.monotonic()`` seconds, sizes bytes.

    Args:
        reloaded: the sequence numbers pending in the outbox when the sink starts (an earlier run's clouds:
            unheard, counted ``queued`` and ``reloaded``).
        first_seq: the outbox's ``next_seq`` when the sink starts: clouds numbered below it were reloaded.
        clock: the link's estimates, fed by the acknowledgements.
    """

    def __init__(self, reloaded: Iterable[int], first_seq: int, clock: AckClock) -> None:
        self.counters = DeliveryCounters()
        self.clock = clock
        self.last_sent: dict[int, float] = {}
        self.sends: dict[int, int] = {}  # how often each pending cloud went out (1: a round-trip sample)
        self.sizes: dict[int, int] = {}
        # published while no subscriber matched, or reloaded from an earlier run: sent once the base is present
        self.unheard: set[int] = set(reloaded)
        # each pending cloud's category: "live", "queued" or "forwarded" (DeliveryCounters)
        self.fate: dict[int, str] = dict.fromkeys(self.unheard, "queued")
        self.first_seq = first_seq  # clouds numbered below were reloaded from an earlier run
        self.counters.reloaded = self.counters.queued = len(self.fate)
        self.acked_sent_t = 0.0  # the latest send time among the clouds acknowledged so far
        # ... as of the poll before the last: a cloud sent before it and still not acknowledged one poll later
        # is lost (the base station's workers may finish neighbouring clouds in either order)
        self.lost_before = 0.0
        self.last_progress = time.monotonic()  # last time the acknowledgements moved on

    # ------------------------------------------------------------------------------------------- sends
    def note_send(self, seq: int, size: int, now: float, *, heard: bool, hold: bool, thin: bool) -> None:
        """A new cloud ``seq`` of ``size`` bytes, about to go out at ``now``.

        Its first copy goes out live when a subscriber matched (``heard``) and the link neither looks down
        (``hold``) nor lacks room (``thin``); otherwise it is queued in the outbox and unheard.
        """
        self.last_sent[seq] = now
        self.sends[seq] = 1
        self.sizes[seq] = size
        live = heard and not hold and not thin
        if not live:
            self.unheard.add(seq)
        self.fate[seq] = "live" if live else "queued"
        if live:
            self.counters.live += 1
        else:
            self.counters.queued += 1
        self.counters.sent += 1
        self.counters.sent_bytes += size
        self.counters.held += int(hold)
        self.counters.thinned += int(thin)

    def note_put(self, seq: int, now: float) -> None:
        """The live copy of ``seq`` left at ``now``: a put that blocked counts from when it went out."""
        if seq in self.sends:  # not acknowledged or dropped meanwhile
            self.last_sent[seq] = now

    def note_unstored(self, seq: int) -> None:
        """The disk write of new cloud ``seq`` failed: a live copy is all it gets (counted ``live``)."""
        self.counters.unstored += 1
        if self.fate.pop(seq, None) == "queued":
            self.counters.queued -= 1
            self.counters.live += 1
        self.forget(seq)

    def is_unheard(self, seq: int) -> bool:
        """True when no copy of ``seq`` can have reached the base station (or this process never sent it)."""
        return seq in self.unheard or seq not in self.sends

    def note_resend(self, seq: int, size: int, now: float, *, unheard: bool) -> None:
        """A copy of pending ``seq`` (``size`` bytes) went out again at ``now``; ``unheard`` as it was before.

        The first copy of a queued cloud is counted ``forwarded`` (from the backlog).
        """
        if self.fate.get(seq) == "queued":  # its first copy on the link: forwarded from the backlog
            self.fate[seq] = "forwarded"
            self.counters.queued -= 1
            self.counters.forwarded += 1
        self.last_sent[seq] = now
        self.sends[seq] = self.sends.get(seq, 0) + 1
        self.counters.resent_unheard += int(unheard)
        self.sizes[seq] = size
        self.unheard.discard(seq)
        self.counters.resent += 1
        self.counters.resent_bytes += size

    # ------------------------------------------------------------------------------------------- budget
    def expendable(self, seq: int) -> bool:
        """True when a copy of pending ``seq`` went out (the budget drops those first); called by the outbox
        under its lock, so it reads without the caller's lock (a dict lookup is atomic)."""
        return self.fate.get(seq, "queued") != "queued"

    def note_dropped(self, seqs: Sequence[int]) -> None:
        """The outbox's budget dropped ``seqs``: each lost if no copy went out, else released."""
        self.counters.dropped += len(seqs)
        for seq in seqs:
            fate = self.fate.pop(seq, None)
            if fate == "queued":
                self.counters.queued -= 1
                self.counters.dropped_budget += 1
            elif fate is not None:
                self.counters.released += 1
            self.forget(seq)

    # ------------------------------------------------------------------------------------------- acks
    def note_answer(self) -> None:
        """An ack answer came: what was sent before the newest acknowledged send of the previous answers, and
        is still not acknowledged after this one, is lost."""
        self.lost_before = self.acked_sent_t

    def note_poll(self) -> None:
        """An ack answer came while nothing was pending."""
        self.counters.ack_polls += 1

    def note_acked(self, hit: Sequence[int], now: float) -> None:
        """An ack answer at ``now`` removed ``hit`` from the outbox (exactly those): count them, feed the clock.

        The clock gets the bytes acknowledged (0 for an answer that brought nothing new), a round-trip sample
        from the latest cloud acknowledged after one send, and the news that acknowledgements moved on.
        """
        self.counters.ack_polls += 1
        self.counters.acked += len(hit)
        acked_bytes = 0
        newest_single: float | None = None  # send time of the latest cloud acknowledged after one send
        for s in hit:
            if self.fate.pop(s, None) == "queued":  # acknowledged before this process sent it
                self.counters.queued -= 1
                if s < self.first_seq:  # an earlier run forwarded it
                    self.counters.forwarded += 1
                else:  # published while no subscriber matched, and yet it arrived: live
                    self.counters.live += 1
            t = self.last_sent.get(s)
            if t is not None:
                self.acked_sent_t = max(self.acked_sent_t, t)
                if self.sends.get(s) == 1 and s not in self.unheard:
                    newest_single = t if newest_single is None else max(newest_single, t)
            acked_bytes += self.sizes.get(s, 0)
            self.forget(s)
        self.clock.acked_bytes(now, acked_bytes)
        if newest_single is not None:
            self.clock.rtt_sample(now, now - newest_single)
        if hit:
            self.last_progress = now
            self.clock.progressed()

    def forget(self, seq: int) -> None:
        """Drop the records of ``seq`` (acknowledged, dropped or not stored); its ``fate`` is the caller's."""
        self.last_sent.pop(seq, None)
        self.sends.pop(seq, None)
        self.sizes.pop(seq, None)
        self.unheard.discard(seq)


__all__ = ["DeliveryBook", "DeliveryCounters"]
