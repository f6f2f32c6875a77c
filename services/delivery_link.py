"""What a ROV's acknowledgements show of its link: round trip, delivery rate, retransmission timeout, window.

The delivery (:mod:`services.delivery`) never measures the link directly: it learns it from the base
station's acknowledgements. :class:`AckClock` folds them into four estimates:

* the **round trip**, smoothed as TCP does (RFC 6298: ``srtt``, ``rttvar``) and the shortest over
  :data:`MIN_RTT_MEMORY_S`. A sample is the time from a cloud's only send to the ack poll that first lists it
  (Karn's rule: a re-sent cloud gives no sample), so it includes the base station's checkpoint and the queues
  on the way, which is what a re-send must wait for;
* the **delivery rate**, bytes acknowledged per second over at least :data:`RATE_WINDOW_S` (two shortest round
  trips if longer), the highest over :data:`RATE_MEMORY_S` (a quiet moment is not a slow link);
* the **retransmission timeout**, ``srtt + 4 rttvar`` within ``[min_rto_s, MAX_BACKOFF_S]``, doubled by each
  probe that brings no progress (:meth:`AckClock.stalled`) until an acknowledgement moves on;
* the **pacing window**: :data:`WINDOW_GAIN` times the bytes delivered per shortest round trip, at least
  :data:`MIN_WINDOW_BYTES`. How the window is spent (re-sends, the backlog, the live stream) is
  :mod:`services.delivery_pacing`'s business.

Pure bookkeeping on ``time.monotonic()`` seconds given by the caller: no thread, no Zenoh, no lock (the caller
holds its own), so the estimates can be driven by a test with made-up times.
"""

from __future__ import annotations

import collections
from typing import Any

#: Longest retransmission timeout while acknowledgements stall (the probes' backoff stops doubling here), s.
MAX_BACKOFF_S = 60.0
#: Bytes that may always be in flight for re-sends, whatever the measured rate (a link's first round trips).
MIN_WINDOW_BYTES = 256 * 1024
#: The pacing window is this many times the bytes the link delivered per shortest round trip.
WINDOW_GAIN = 2.0
#: Acknowledged bytes are summed over this long (at least) to measure the link's delivery rate, s.
RATE_WINDOW_S = 2.0
#: The delivery rate used is the highest measured over this long (a quiet moment is not a slow link), s.
RATE_MEMORY_S = 10.0
#: The shortest round trip is the minimum over this long, s.
MIN_RTT_MEMORY_S = 30.0


class AckClock:
    """What the acknowledgements show of the link: round trip (smoothed, shortest), delivery rate, backoff.

    Round-trip samples are the time from a cloud's only send to the ack poll that first lists it (Karn's rule:
    a re-sent cloud gives no sample); they include the base station's checkpoint and the queues on the way,
    which is what a re-send must wait for. Times are ``time.monotonic()`` seconds. Not thread-safe (the
    caller holds its lock).

    Args:
        min_rto_s: the retransmission timeout is never shorter, seconds.
    """

    def __init__(self, min_rto_s: float) -> None:
        self.min_rto_s = min_rto_s
        self.srtt: float | None = None
        self.rttvar = 0.0
        self.backoff = 1.0
        self._rtts: collections.deque[tuple[float, float]] = collections.deque()  # (t, sample)
        self._acked: collections.deque[tuple[float, int]] = collections.deque()  # (t, bytes acknowledged)
        self._rates: collections.deque[tuple[float, float]] = collections.deque()  # (t, bytes/s)

    def rtt_sample(self, now: float, rtt_s: float) -> None:
        """Fold one round-trip sample in (RFC 6298's smoothing)."""
        rtt_s = max(rtt_s, 1e-3)
        if self.srtt is None:
            self.srtt, self.rttvar = rtt_s, rtt_s / 2
        else:
            self.rttvar = 0.75 * self.rttvar + 0.25 * abs(self.srtt - rtt_s)
            self.srtt = 0.875 * self.srtt + 0.125 * rtt_s
        self._rtts.append((now, rtt_s))
        while self._rtts and now - self._rtts[0][0] > MIN_RTT_MEMORY_S:
            self._rtts.popleft()

    def acked_bytes(self, now: float, n_bytes: int) -> None:
        """Note ``n_bytes`` newly acknowledged at ``now`` (0 for a poll that brought nothing new)."""
        self._acked.append((now, n_bytes))
        span = max(RATE_WINDOW_S, 2 * self.min_rtt())
        while self._acked and now - self._acked[0][0] > span:
            self._acked.popleft()
        elapsed = max(now - self._acked[0][0], span / 2)
        self._rates.append((now, sum(b for _, b in self._acked) / elapsed))
        while self._rates and now - self._rates[0][0] > RATE_MEMORY_S:
            self._rates.popleft()

    def min_rtt(self) -> float:
        """The shortest recent round trip, seconds (0 before any sample)."""
        return min((r for _, r in self._rtts), default=0.0)

    def rate(self) -> float:
        """The link's recent delivery rate as the acknowledgements show it, bytes/s (0 before any)."""
        return max((r for _, r in self._rates), default=0.0)

    def rto(self) -> float:
        """The retransmission timeout without backoff, seconds."""
        if self.srtt is None:
            return self.min_rto_s
        return min(MAX_BACKOFF_S, max(self.min_rto_s, self.srtt + 4 * self.rttvar))

    def timeout(self) -> float:
        """The retransmission timeout with the current backoff, seconds."""
        return min(MAX_BACKOFF_S, self.rto() * self.backoff)

    def window(self) -> int:
        """Bytes that may be in flight: twice the delivered bytes per shortest round trip, at least a floor."""
        return int(max(MIN_WINDOW_BYTES, WINDOW_GAIN * self.rate() * self.min_rtt()))

    def stalled(self) -> None:
        """A timeout fired without progress: the next one waits twice as long (capped)."""
        self.backoff = min(self.backoff * 2, MAX_BACKOFF_S / max(self.rto(), 1e-3))

    def progressed(self) -> None:
        """Acknowledgements moved on: back to the measured timeout."""
        self.backoff = 1.0

    def to_json(self) -> dict[str, Any]:
        """The estimates, JSON-ready (seconds, bytes/s, bytes)."""
        return {
            "srtt_s": None if self.srtt is None else round(self.srtt, 3),
            "min_rtt_s": round(self.min_rtt(), 3),
            "timeout_s": round(self.timeout(), 3),
            "rate_bps": round(self.rate() * 8),
            "window_bytes": self.window(),
        }


__all__ = [
    "MAX_BACKOFF_S",
    "MIN_RTT_MEMORY_S",
    "MIN_WINDOW_BYTES",
    "RATE_MEMORY_S",
    "RATE_WINDOW_S",
    "WINDOW_GAIN",
    "AckClock",
]
