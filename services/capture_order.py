"""The map thread's clouds in capture-time order across robots, within a bounded wait.

The base's ingest workers hand the robots' clouds to the map in the order they finish decoding them, and each
robot's clouds go through the worker its key hashes to. While the map keeps up that is capture order; when it is
behind (a replay fed faster than real time, a fleet catching up after a link outage) one worker's robots can run
tens of seconds of capture time ahead of another's. A depth-only robot's pose graph then checks its scans against
a map the others have not built yet, and the fleet's heading estimate, taken over every graph robot's first
second, is made before some robots have started: the map depends on how fast it was fed
(docs/navigation-design.md, "Capture order").

:class:`CaptureOrder` restores the order: the map thread puts every cloud it takes from its queue here, and takes
out the oldest (smallest capture time) once every robot heard from within ``quiet_s`` has sent a cloud at least as
recent, so no robot's cloud is mapped before an older one of another robot that is on its way. Clouds of the same
capture time (robots on one frame clock) go by robot name: which arrived first would otherwise change the map. A
cloud waits at most ``max_wait_s`` (a robot whose clock is off, or that has gone quiet, holds the others back no
longer), and
the buffer holds at most ``limit`` clouds (beyond, the oldest goes at once: the bounded backlog stays bounded).
Times: capture times in ns (the robots' clocks), waits in monotonic seconds (the base's clock).
"""

from __future__ import annotations

import heapq
import itertools
import queue
import time
from typing import Any

#: how long a cloud waits for an older cloud of another robot at most (s, wall time)
MAX_WAIT_S = 1.0
#: a robot silent this long (s, wall time) is not waited for
QUIET_S = 1.0
#: how often a map thread holding clouds looks again (s)
POLL_S = 0.05
#: no marker (a flush, a stop) waits behind the clouds held
_NONE: Any = object()
#: the whole fleet silent this long (s, wall time) ends a dive: the map is flushed as at the base's close
QUIET_FLUSH_S = 5.0


class CaptureOrder:
    """Clouds (anything with ``robot`` and ``t_ns``) released oldest first once no robot can send an older one.

    Args:
        limit: the most clouds held; beyond, the oldest is released at once.
        max_wait_s: the longest a cloud is held (s, monotonic).
        quiet_s: a robot that sent nothing for this long (s, monotonic) is not waited for.
    """

    def __init__(self, limit: int, max_wait_s: float = MAX_WAIT_S, quiet_s: float = QUIET_S) -> None:
        self.limit = max(1, int(limit))
        self.max_wait_s = max_wait_s
        self.quiet_s = quiet_s
        #: (capture time ns, robot, arrival order, arrival time s, cloud): clouds of one capture time go by robot
        #: name, not by which came first (robots sharing a frame clock, a replay), so the map does not depend on it
        self._heap: list[tuple[int, str, int, float, Any]] = []
        self._count = itertools.count()
        #: robot -> newest capture time received (ns) and when its last cloud came (s)
        self._newest: dict[str, int] = {}
        self._seen: dict[str, float] = {}
        #: clouds released before their turn: by ``max_wait_s`` or by ``limit``
        self.forced = 0
        #: a marker taken from the queue (anything without ``robot`` and ``t_ns``): it goes after the clouds held
        self._marker: Any = _NONE

    def __len__(self) -> int:
        return len(self._heap)

    def push(self, msg: Any, now: float) -> None:
        """``msg`` (``msg.robot``, ``msg.t_ns``) came at ``now`` (s)."""
        t = int(msg.t_ns)
        heapq.heappush(self._heap, (t, str(msg.robot), next(self._count), now, msg))
        self._newest[msg.robot] = max(t, self._newest.get(msg.robot, t))
        self._seen[msg.robot] = now

    def pop_ready(self, now: float) -> Any | None:
        """The oldest cloud held if its turn has come at ``now`` (s), else None."""
        if not self._heap:
            return None
        t, _, _, came, _ = self._heap[0]
        waiting = any(newest < t and now - self._seen[robot] < self.quiet_s for robot, newest in self._newest.items())
        if waiting and len(self._heap) <= self.limit and now - came < self.max_wait_s:
            return None
        if waiting:
            self.forced += 1
        return heapq.heappop(self._heap)[4]

    def pop(self) -> Any:
        """The oldest cloud held, whatever the others (a flush: nothing more is coming)."""
        return heapq.heappop(self._heap)[4]

    def next_from(self, q: queue.Queue[Any], idle_s: float) -> Any:
        """The map thread's next item from its queue ``q``: a cloud in capture order, or a marker (a flush, a stop)
        once every cloud taken before it is out. Raises ``queue.Empty`` after ``idle_s`` with nothing held."""
        while True:
            # all that has come first: a lagging robot's older clouds may be behind the others' in the queue
            while self._marker is _NONE and len(self._heap) < self.limit:
                try:
                    self._take(q.get_nowait())
                except queue.Empty:
                    break
            if self._marker is not _NONE:
                if self._heap:
                    return self.pop()
                item, self._marker = self._marker, _NONE
                return item
            msg = self.pop_ready(time.monotonic())
            if msg is not None:
                return msg
            self._take(q.get(timeout=POLL_S if self._heap else idle_s))

    def _take(self, item: Any) -> None:
        if hasattr(item, "robot") and hasattr(item, "t_ns"):
            self.push(item, time.monotonic())
        else:
            self._marker = item


class QuietFlush:
    """When a live base's dive ends: every robot heard from has been silent for ``quiet_s`` (wall time) since clouds
    last came. The map is then flushed once as a stopping base flushes it (the robots' last windows extracted, the
    held clouds settled, the smoothers' last run), so the map served between dives is the finished one, not the
    one of the dive's last seconds; a cloud arriving afterwards starts a new dive.

    Args:
        quiet_s: how long the fleet must be silent (s, monotonic).
    """

    def __init__(self, quiet_s: float = QUIET_FLUSH_S) -> None:
        self.quiet_s = quiet_s
        #: when the last cloud came (s, monotonic); None once flushed (or before any cloud)
        self._last: float | None = None
        #: the flushes done so far (:meth:`flushed`)
        self.count = 0

    def cloud(self, now: float) -> None:
        """A cloud came at ``now`` (s)."""
        self._last = now

    def due(self, now: float) -> bool:
        """Whether the fleet has been silent long enough at ``now`` (s) for its flush; True once per silence."""
        if self._last is None or now - self._last < self.quiet_s:
            return False
        self._last = None
        return True

    def flushed(self) -> None:
        """The flush :meth:`due` asked for is done (counted in :attr:`count`)."""
        self.count += 1
