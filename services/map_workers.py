"""The base station's side of the plane workers: who is alive, which worker serves which robot, what is in
flight, and the merge of what comes back.

Assignment rule (rendezvous hashing, also called highest random weight): robot ``r`` is served by the live worker
``w`` with the largest ``H(r, w)`` = the first 8 bytes of BLAKE2b(``r`` NUL ``w``) as an unsigned integer; ties are
impossible in practice and broken by name. The live workers are those whose liveliness token
``<root>/map/workers/<w>`` the base sees. Properties (tests/test_workers.py checks them): every base computes the
same owner from the same set; robots spread evenly (each worker gets about 1/n of them); when a worker joins, only
the robots it now wins move (to it); when a worker leaves or dies, only its robots move, each to its second choice.
No coordinator state, nothing to hand over.

In flight and exactly once: every cloud the base sends to a worker stays *in flight* (robot, seq, capture time,
pose, points) until observations that commit it come back. When a robot moves (a join, a leave, a death: the
token vanishes at once on a killed process's link), its epoch is bumped, the old owner is told to drop its window,
and every in-flight cloud of the robot is sent again, in order, to the new owner. Observations are taken only of
the robot's current epoch from its current owner, and a cloud leaves the in-flight table once: a late answer of
the old owner is ignored (counted as ``stale``), so no cloud is counted twice and none is lost while one worker is
alive. With no worker alive, clouds wait in flight (bounded: :meth:`WorkerPool.dispatch` blocks when
``max_in_flight`` is reached, which pushes back through the map queue to the robots) until one joins.

The merge: observations are decoded and merged on this module's thread (``MapBuilder.merge``: association and
exact addition of statistics, nothing per robot), then the committed clouds are reported (``on_commit``). The
merge is order-sensitive (which plane an observation joins depends on what the map holds), so the merger does not
merge in the order the workers happen to answer: each observation carries the capture time of the cloud that
triggered its extraction (``key_ns``), and it is held until no observation still to come can precede it (the
*frontier*: the earliest key each robot's in-flight clouds could still fire their window at, see
:meth:`WorkerPool._next_key_bound`); held observations are merged by (key, robot): the order one map thread fed in
capture order merges them in, whatever the number of workers. An observation waits at most ``MAX_HOLD_S``, and a
robot with nothing dispatched or committed for that long, its window's trigger still to come, holds nothing back.

Navigation in the workers (``navigate``; :mod:`services.map_worker_nav`): jobs carry the raw pose and the worker
corrects it. A registered scan uses the merged map's *snapshot* its capture time names (``snapshot(T)``, T =
:func:`mapping.landmarks.snapshot_time` of its capture time and ``snapshot_lag_s``: the map after exactly the
observations with a key before T). As the frontier passes each grid time T, the merger takes the planes before the
first merge at or after T and publishes them on ``<root>/map/landmarks``
(:func:`~services.map_worker_nav.encode_snapshots`; the last ``SNAPSHOTS_KEEP_NS`` again when a worker joins),
so the poses, and the map, do not depend on timing. It keeps each robot's navigation state from the observations
that commit its clouds, and hands that state to a robot's new worker (``adopt``) before re-sending its clouds.
Counted (``status_json()["snapshots"]``): the workers' waits and scans not exact, observations merged after their
snapshot was out (``late``) or past the hold cap (``forced``). The fleet heading of a depth-only fleet
(:attr:`WorkerPool.heading`): the views in the workers, the estimate here, at the cloud it is due at
(:mod:`services.map_worker_heading`).
"""

from __future__ import annotations

import hashlib
import heapq
import logging
import queue
import threading
import time
import uuid
from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from lrsensor.frames import Pose

from .errors import WireError
from .keys import FleetKeys
from .map_worker_nav import LANDMARKS_EVERY_S, SNAPSHOT_LAG_S, decode_state, encode_landmarks, encode_snapshots
from .map_worker_wire import (
    FLUSH_KEY,
    HeadingViews,
    MapControl,
    MapJob,
    NavReport,
    decode_obs,
    landmarks_key,
    obs_key,
    work_key,
    workers_key,
)
from .zconfig import undeclare_all

if TYPE_CHECKING:
    from mapping import MapBuilder, MapChange
    from mapping.landmarks import SnapshotRange

    from .map_worker_heading import HeadingRelay

log = logging.getLogger(__name__)

#: Clouds in flight (sent, not yet committed) before :meth:`WorkerPool.dispatch` waits.
MAX_IN_FLIGHT = 2048


def score(robot: str, worker: str) -> int:
    """The rendezvous weight of ``worker`` for ``robot`` (see the module docstring)."""
    return int.from_bytes(hashlib.blake2b(f"{robot}\0{worker}".encode(), digest_size=8).digest(), "big")


def owner(robot: str, workers: Iterable[str]) -> str | None:
    """The worker that serves ``robot`` among the live ``workers`` (None: none alive)."""
    best: tuple[int, str] | None = None
    for w in workers:
        key = (score(robot, w), w)
        if best is None or key > best:
            best = key
    return best[1] if best is not None else None


#: Longest an observation is held for the canonical order, seconds: a robot that went silent with clouds in its
#: worker's window (extracted only at the next flush) must not stall the others' merge. A robot with nothing
#: dispatched and nothing committed for this long holds neither the merge nor the snapshots back.
MAX_HOLD_S = 2.0
#: A robot with clouds in flight and nothing dispatched for this long (seconds) has gone silent (the end of its
#: dive, an outage): its worker is asked to extract its last window, which no later cloud will trigger, so that
#: its clouds are committed and acknowledged (the robot waits for them). Longer than a stream's gaps; shorter than
#: a robot's patience (``lrsensor rov`` gives up after 60 s without progress).
IDLE_FLUSH_S = 5.0
#: The merger keeps its snapshots this far back (capture time, ns) to send them to a worker that joins.
SNAPSHOTS_KEEP_NS = 5_000_000_000

#: An observation held for the canonical merge order: (key_ns, robot, arrival number, records, [(seq, t_ns)],
#: unplaced seqs, navigation state).
_Held = tuple[int, str, int, list[Any], list[tuple[int, int]], tuple[int, ...], bytes]


@dataclass
class _InFlight:
    seq: int
    t_ns: int
    pose: Pose
    points_body: NDArray[np.float32]
    heading: str = ""
    range_error_per_px: float = 0.0


class WorkerPool:
    """Dispatch to the live plane workers and merge their observations (see the module docstring).

    Args:
        session: the base's open Zenoh session.
        keys: the fleet's key expressions.
        builder: the shared map (the merger's; only :meth:`~mapping.MapBuilder.merge` is used).
        on_commit: called with ``(robot, [(seq, t_ns), ...], unplaced seqs)`` when clouds reached the map (or, the
            unplaced ones, were done with: navigation could not place them).
        on_changes: called with the map changes of each merge (the feed publishes them).
        max_in_flight: see the module docstring.
        navigate: whether the workers run the navigation (see the module docstring).
        landmark_min_points: with ``navigate``, planes with fewer points are not sent to the workers.
        snapshot_lag_s: with ``navigate``, the snapshot rule's lag (docs/scaling.md; 0: the workers register
            against a mirror of the planes of the moment, sent at most every ``LANDMARKS_EVERY_S``).
        no_fix: with ``navigate``, the base's ``--no-fix`` choice (``lost`` or ``graph``), sent with every job and
            adoption: the workers navigate a robot without a fix as the base says.
    """

    def __init__(
        self,
        session: Any,
        keys: FleetKeys,
        builder: MapBuilder,
        on_commit: Callable[[str, list[tuple[int, int]], tuple[int, ...]], None],
        on_changes: Callable[[list[MapChange]], None],
        max_in_flight: int = MAX_IN_FLIGHT,
        navigate: bool = False,
        landmark_min_points: int = 0,
        snapshot_lag_s: float = SNAPSHOT_LAG_S,
        no_fix: str = "lost",
    ) -> None:
        self.session = session
        self.keys = keys
        self.builder = builder
        self.on_commit = on_commit
        self.on_changes = on_changes
        self.max_in_flight = max_in_flight
        self.navigate = navigate
        self.landmark_min_points = landmark_min_points
        self.snapshot_lag_ns = round(snapshot_lag_s * 1e9)
        self.no_fix = no_fix
        #: the snapshot rule (merger thread): this merger's name, the last grid time published, keys up to which
        #: the published snapshots are not exact, the ranges kept for a joining worker
        self._base_id = uuid.uuid4().hex[:12]
        self._snap_upto: int | None = None
        self._inexact_to = -1
        self._kept: deque[SnapshotRange] = deque()
        #: per robot: when it last had a cloud dispatched or committed (monotonic s); the newest capture time sent
        self._active: dict[str, float] = {}
        self._newest_t: int | None = None
        #: per robot: when its worker was last asked to extract a silent robot's last window (monotonic s); when
        #: the merger last looked for silent robots; how many such asks were sent
        self._silent_asked: dict[str, float] = {}
        #: robots whose clouds wait in their owner's hold (see :meth:`holding`)
        self._holding: set[str] = set()
        self._silent_checked = 0.0
        self.silent_flushes = 0
        #: observations merged after a snapshot that should hold them was published (a robot late past the hold),
        #: observations merged past their hold cap; per worker: its snapshot counters (waited, longest wait ms,
        #: not exact)
        self.snap_late = 0
        self.snap_forced = 0
        self._snap_counts: dict[str, tuple[int, int, int]] = {}
        #: with ``navigate``: called with ``(robot, state)`` as the clouds an observation commits are merged, and
        #: with ``(robot, NavEstimate)`` for each estimate a worker reports
        self.on_nav_state: Callable[[str, bytes], None] = lambda robot, state: None
        self.on_nav_report: Callable[[str, Any], None] = lambda robot, est: None
        #: per robot: the navigation state after its last committed cloud (carried to its next worker)
        self._nav_state: dict[str, bytes] = {}
        #: with ``navigate`` and a navigator (set by the feed): the fleet heading's base half
        self.heading: HeadingRelay | None = None
        self._lm_pub: Any = None
        self._lm_sent: tuple[int, float] = (-1, 0.0)
        self._cond = threading.Condition()
        self._workers: set[str] = set()
        self._pubs: dict[str, Any] = {}
        self._owner: dict[str, str | None] = {}
        self._epoch: dict[str, int] = {}
        self._in_flight: dict[str, dict[int, _InFlight]] = {}
        self._n_in_flight = 0
        self._held: list[_Held] = []
        self._held_since: dict[int, float] = {}
        self._seq = 0
        self._events: queue.Queue[tuple[str, Any] | None] = queue.Queue()
        self._thread: threading.Thread | None = None
        self._entities: list[Any] = []
        #: observations merged, stale answers ignored, malformed ones, robots moved, clouds sent again
        self.merged = 0
        self.stale = 0
        self.errors = 0
        self.moves = 0
        self.resent = 0
        #: per worker: clouds committed by it
        self.committed: dict[str, int] = {}

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> None:
        """Subscribe to the observations and to the workers' liveliness (with history: workers already up)."""
        self._thread = threading.Thread(target=self._run, name="base-merger", daemon=True)
        self._thread.start()
        s = self.session
        if self.navigate:
            import zenoh

            # snapshots must arrive (a scan waits for its own); the mirror of the moment may skip one
            cc = zenoh.CongestionControl.BLOCK if self.snapshot_lag_ns > 0 else zenoh.CongestionControl.DROP
            self._lm_pub = s.declare_publisher(landmarks_key(self.keys), congestion_control=cc)
            self._entities.append(self._lm_pub)
        self._entities += [
            s.declare_subscriber(obs_key(self.keys), lambda sample: self._events.put(("obs", sample))),
            s.liveliness().declare_subscriber(
                workers_key(self.keys), lambda sample: self._events.put(("alive", sample)), history=True
            ),
        ]

    def close(self) -> None:
        """Stop listening and stop the merger thread (what is in flight stays uncommitted: not acknowledged)."""
        undeclare_all(reversed(self._entities), "map workers")
        self._entities.clear()
        if self._thread is not None:
            self._events.put(None)
            self._thread.join(timeout=10.0)
            self._thread = None
        with self._cond:
            undeclare_all(self._pubs.values(), "map workers")
            self._pubs.clear()
            self._cond.notify_all()

    # ------------------------------------------------------------------ views
    @property
    def workers(self) -> list[str]:
        """The live workers, sorted."""
        with self._cond:
            return sorted(self._workers)

    @property
    def in_flight(self) -> int:
        """Clouds sent (or waiting for a worker) and not yet committed."""
        with self._cond:
            return self._n_in_flight

    def assignment(self) -> dict[str, str | None]:
        """Robot -> the worker serving it now (None: no worker alive)."""
        with self._cond:
            return dict(sorted(self._owner.items()))

    def status_json(self) -> dict[str, Any]:
        """Per worker: robots served, clouds committed; and the pool's counters."""
        with self._cond:
            per = {
                w: {
                    "robots": sorted(r for r, o in self._owner.items() if o == w),
                    "committed": self.committed.get(w, 0),
                }
                for w in sorted(self._workers)
            }
            out: dict[str, Any] = {
                "workers": per,
                "in_flight": self._n_in_flight,
                "stale": self.stale,
                "moves": self.moves,
                "resent": self.resent,
                "silent_flushes": self.silent_flushes,
            } | ({"fleet_heading": self.heading.status_json()} if self.heading is not None and self.heading.t0 else {})
            if self.navigate and self.snapshot_lag_ns > 0:
                counts = [self._snap_counts.get(w, (0, 0, 0)) for w in sorted(self._workers)]
                out["snapshots"] = {
                    "lag_ms": round(self.snapshot_lag_ns / 1e6),
                    "waited": sum(c[0] for c in counts),
                    "max_wait_ms": max((c[1] for c in counts), default=0),
                    "not_exact": sum(c[2] for c in counts),
                    "late": self.snap_late,
                    "forced": self.snap_forced,
                }
            return out

    def wait_for_workers(self, n: int, timeout_s: float) -> bool:
        """Wait until at least ``n`` workers are alive; False on timeout."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while len(self._workers) < n:
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._cond.wait(left)
        return True

    # ------------------------------------------------------------------ input (the map thread)
    def dispatch(
        self,
        robot: str,
        seq: int,
        t_ns: int,
        pose: Pose,
        points_body: NDArray[np.float32],
        range_error_per_px: float = 0.0,
    ) -> None:
        """Send one cloud to its robot's worker (or hold it until one is alive); blocks while ``max_in_flight``
        clouds are in flight. ``range_error_per_px``: its calibration's (:class:`MapJob`; 0: none known)."""
        heading = self.heading.phase(robot, t_ns, pose) if self.heading is not None and self.navigate else ""
        pts = np.ascontiguousarray(points_body, np.float32)
        item = _InFlight(seq, t_ns, pose, pts, heading, range_error_per_px)
        with self._cond:
            while self._n_in_flight >= self.max_in_flight and self._thread is not None:
                self._cond.wait(0.5)
            table = self._in_flight.setdefault(robot, {})
            if seq in table:
                return  # already in flight (the ledger de-duplicates; this is a second guard)
            table[seq] = item
            self._n_in_flight += 1
            self._active[robot] = time.monotonic()
            self._newest_t = t_ns if self._newest_t is None else max(self._newest_t, t_ns)
            if robot not in self._owner:
                self._owner[robot] = owner(robot, self._workers)
                self._epoch[robot] = 0
            self._send(robot, [item])
        if self.heading is not None and self.heading.due():  # every graph robot past its span: the biases now
            self.heading.settle(self.control)

    def control(self, robot: str, kind: str, state: bytes = b"") -> None:
        """Send ``robot``'s owner the control ``kind`` (with ``state``) under the robot's epoch, after its jobs."""
        with self._cond:
            if self._owner.get(robot) is not None:
                self._put(str(self._owner[robot]), MapControl(kind, robot, self._epoch[robot], state).to_bytes())

    def flush(self, timeout_s: float) -> bool:
        """Ask every worker to extract its pending windows and wait until nothing is in flight; False on
        timeout or at once when no worker is alive."""
        with self._cond:
            for w in sorted(self._workers):
                self._put(w, MapControl("flush").to_bytes())
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while self._n_in_flight > 0:
                left = deadline - time.monotonic()
                if left <= 0 or not self._workers:  # nobody to flush: what is in flight stays unacknowledged
                    stuck = {r: (self._owner.get(r), sorted(t)[:5], len(t)) for r, t in self._in_flight.items() if t}
                    log.warning("map workers: flush timed out; in flight (owner, first seqs, n): %s", stuck)
                    return False
                self._cond.wait(min(left, 0.5))
        return True

    # ------------------------------------------------------------------ under the lock
    def _put(self, worker: str, payload: bytes) -> None:
        pub = self._pubs.get(worker)
        if pub is None:
            return
        try:
            pub.put(payload)
        except Exception as err:  # the worker's liveliness decides; its clouds stay in flight
            log.warning("job for map worker %s not sent: %s", worker, err)

    def _send(self, robot: str, items: list[_InFlight]) -> None:
        w = self._owner.get(robot)
        if w is None:
            return
        epoch = self._epoch[robot]
        lag = self.snapshot_lag_ns if self.navigate else 0
        for it in items:
            job = MapJob(robot, it.seq, it.t_ns, epoch, it.pose, it.points_body, self.navigate, lag, self.no_fix,
                         it.heading, it.range_error_per_px)  # fmt: skip
            self._put(w, job.to_bytes())

    def _flush_silent(self) -> None:
        """Under the lock: ask the owner of each robot silent for :data:`IDLE_FLUSH_S` with clouds in flight to
        extract its last window (again every :data:`IDLE_FLUSH_S` while it stays so: a worker declines while the
        robot has a scan waiting for its snapshot)."""
        now = time.monotonic()
        self._silent_checked = now
        for robot in sorted(set(self._in_flight) | self._holding):
            table = self._in_flight.get(robot)
            if not (table or robot in self._holding) or now - self._active.get(robot, now) < IDLE_FLUSH_S:
                continue
            if now - self._silent_asked.get(robot, 0.0) < IDLE_FLUSH_S:
                continue
            w = self._owner.get(robot)
            if w is None:
                continue
            self._silent_asked[robot] = now
            self._holding.discard(robot)  # asked once: a newer state says so again if it still holds
            self.silent_flushes += 1
            self._put(w, MapControl("flush", robot, self._epoch[robot]).to_bytes())

    def holding(self, robot: str, held: bool) -> None:
        """Whether ``robot``'s newest navigation state holds clouds until its track's next check
        (:mod:`mapping.graph_hold`): its clouds are acknowledged, none is in flight, yet once it goes silent its
        owner must be asked to settle them as for a silent robot's last window."""
        with self._cond:
            if held:
                self._holding.add(robot)
            else:
                self._holding.discard(robot)

    def _reassign(self) -> None:
        """Move every robot whose rendezvous owner changed; re-send its in-flight clouds to the new owner."""
        for robot, old in list(self._owner.items()):
            new = owner(robot, self._workers)
            if new == old:
                continue
            self._owner[robot] = new
            self._epoch[robot] += 1
            self.moves += 1
            if old is not None and old in self._workers:
                self._put(old, MapControl("drop", robot, self._epoch[robot]).to_bytes())
            items = [self._in_flight[robot][s] for s in sorted(self._in_flight.get(robot, {}))]
            self.resent += len(items) if new is not None else 0
            if self.navigate and new is not None:  # its navigation continues after its last committed cloud
                state = self._nav_state.get(robot, b"")
                self._put(new, MapControl("adopt", robot, self._epoch[robot], state, self.no_fix).to_bytes())
            self._send(robot, items)
            log.info("robot %s moves from map worker %s to %s (%d clouds again)", robot, old, new, len(items))

    # ------------------------------------------------------------------ the merger thread
    def _run(self) -> None:
        while True:
            try:
                ev = self._events.get(timeout=0.25 if not self.navigate else LANDMARKS_EVERY_S)
            except queue.Empty:
                with self._cond:
                    self._flush_silent()
                    ready, frontier = self._ready()
                self._merge(ready, frontier)
                continue
            if ev is None:
                return
            if time.monotonic() - self._silent_checked >= 0.5:  # a busy fleet never leaves the queue empty
                with self._cond:
                    self._flush_silent()
            kind, sample = ev
            try:
                if kind == "alive":
                    self._on_alive(sample)
                else:
                    self._on_obs(sample.payload.to_bytes())
            except Exception as err:  # the merger must not stop
                self.errors += 1
                log.exception("map merger: %s", err)

    def _on_alive(self, sample: Any) -> None:
        import zenoh

        name = str(sample.key_expr).rsplit("/", 1)[-1]
        with self._cond:
            if sample.kind == zenoh.SampleKind.PUT:
                if name in self._workers:
                    return
                self._pubs[name] = self.session.declare_publisher(
                    work_key(self.keys, name), congestion_control=zenoh.CongestionControl.BLOCK
                )
                self._workers.add(name)
                log.info("map worker %s joined (%d alive)", name, len(self._workers))
                self._lm_sent = (-1, 0.0)  # the newcomer needs the planes now
                if self._kept:
                    self._publish_snapshots(list(self._kept))
            else:
                if name not in self._workers:
                    return
                self._workers.discard(name)
                pub = self._pubs.pop(name, None)
                if pub is not None:
                    pub.undeclare()
                log.warning("map worker %s left (%d alive): its robots move", name, len(self._workers))
            self._reassign()
            self._cond.notify_all()

    def _on_obs(self, payload: bytes) -> None:
        from mapping.plane_map import record_from_wire

        try:
            obs = decode_obs(payload)
            if isinstance(obs, NavReport | HeadingViews):
                self._on_nav(obs)
                return
            records = [record_from_wire(r) for r in obs.records]
        except (WireError, KeyError, TypeError, ValueError) as err:
            self.errors += 1
            log.warning("plane observations refused: %s", err)
            return
        with self._cond:
            if self._owner.get(obs.robot) != obs.worker or self._epoch.get(obs.robot) != obs.epoch:
                self.stale += 1
                return
            table = self._in_flight.get(obs.robot, {})
            done = [(s, table.pop(s).t_ns) for s in obs.seqs if s in table]
            self.committed[obs.worker] = self.committed.get(obs.worker, 0) + len(done)
            if obs.nav_state:
                self._nav_state[obs.robot] = obs.nav_state
            self._snap_counts[obs.worker] = (obs.snap_waited, obs.snap_wait_ms, obs.snap_not_exact)
            self._active[obs.robot] = time.monotonic()
            self._seq += 1
            self._held_since[self._seq] = time.monotonic()
            item = (obs.key_ns, obs.robot, self._seq, records, done, obs.unplaced, obs.nav_state)
            heapq.heappush(self._held, item)
            ready, frontier = self._ready()
        self._merge(ready, frontier)

    def _on_nav(self, report: NavReport | HeadingViews) -> None:
        with self._cond:
            if self._owner.get(report.robot) != report.worker or self._epoch.get(report.robot) != report.epoch:
                return
        if isinstance(report, HeadingViews):
            if self.heading is not None:
                self.heading.take_views(report.robot, decode_state(report.views))
            return
        self.on_nav_report(report.robot, decode_state(report.estimate))

    def _publish_landmarks(self) -> None:
        """With ``navigate`` and no snapshot lag: the map's planes to the workers, when they changed, at most every
        ``LANDMARKS_EVERY_S``."""
        if self._lm_pub is None or self.snapshot_lag_ns > 0:
            return
        version = self.builder.version
        sent, at = self._lm_sent
        now = time.monotonic()
        if version == sent or now - at < LANDMARKS_EVERY_S:
            return
        self._lm_sent = (version, now)
        try:
            self._lm_pub.put(encode_landmarks(self.builder.landmarks(self.landmark_min_points), version))
        except Exception as err:  # the workers keep their mirror; the next change sends it again
            log.warning("map planes not sent to the workers: %s", err)

    def _ready(self) -> tuple[list[_Held], int | None]:
        """Under the lock: the held observations that no observation still to come can precede (canonical order),
        and that bound, the *frontier* (no observation still to come has a key before it; None: nothing sent
        yet). An observation without planes adds nothing, so its place in the order does not matter. A robot with
        nothing dispatched or committed for ``MAX_HOLD_S`` whose window's trigger is still to come (gone silent with
        clouds in its window) holds nothing back: its late observation is merged when it comes (counted ``late``
        when a snapshot was past it). A robot whose window is due waits, however slow its worker."""
        quiet = time.monotonic() - MAX_HOLD_S
        bounds = []
        for r, t in self._in_flight.items():
            if t:
                bound, triggered = self._key_bound(t)
                if triggered or self._active.get(r, 0.0) >= quiet:  # a due window comes, however slow its worker
                    bounds.append(bound)
        mark = min(bounds) if bounds else None
        # nothing in flight: a robot's next cloud is assumed no older than the newest one sent (capture order)
        frontier = mark if mark is not None else self._newest_t
        if not self._held:
            return [], frontier
        out = []
        oldest = time.monotonic() - MAX_HOLD_S
        while self._held and (mark is None or self._held[0][0] < mark or min(self._held_since.values()) < oldest):
            item = heapq.heappop(self._held)
            self._held_since.pop(item[2], None)
            out.append(item)
            if mark is not None and item[0] >= mark and item[3] and item[0] != FLUSH_KEY:
                # past its hold cap: the snapshots up to its key, published later, hold it too early
                self.snap_forced += 1
                self._inexact_to = max(self._inexact_to, item[0])
        # the empty ones behind the first that must wait: commit them now (acknowledgements, latency)
        keep = [h for h in self._held if h[3]]
        if len(keep) < len(self._held):
            out += [h for h in self._held if not h[3]]
            for h in self._held:
                if not h[3]:
                    self._held_since.pop(h[2], None)
            self._held = keep
            heapq.heapify(self._held)
        return out, frontier

    def _next_key_bound(self, table: dict[int, _InFlight]) -> int:
        """The earliest merge key a robot's next observation with planes can have: the capture time of the first
        of its in-flight clouds (oldest first) at which its window's extraction could fire (the builder's rules,
        ``MapConfig.extract_every_*``, counted on every in-flight cloud and on the points before thinning, so that
        it fires no later than the worker's window does), or its newest in-flight cloud's (the trigger is still
        to come, and a robot's clouds come in capture order)."""
        return self._key_bound(table)[0]

    def _key_bound(self, table: dict[int, _InFlight]) -> tuple[int, bool]:
        """:meth:`_next_key_bound`, and whether a cloud in flight fires the window (False: the trigger is still to
        come, from a robot that may have gone silent)."""
        cfg = self.builder.cfg
        points = 0
        first = last = 0
        for n, it in enumerate(table.values(), start=1):
            points += it.points_body.shape[0]
            if n == 1:
                first = it.t_ns
            last = it.t_ns
            if n >= cfg.extract_every_clouds or points >= cfg.extract_every_points:
                return it.t_ns, True
            if cfg.extract_every_s > 0 and n >= 2 and it.t_ns - first >= cfg.extract_every_s * 1e9:
                return it.t_ns, True
        return last, False

    def _merge(self, ready: list[_Held], frontier: int | None) -> None:
        """Merge the ready observations in their order; with the snapshot rule, publish the snapshots they finalize
        (the planes before the first merge whose key is at or after a grid time, for the grid times up to the
        frontier)."""
        snaps = self._lm_pub is not None and self.snapshot_lag_ns > 0
        out: list[SnapshotRange] = []
        for key, robot, _n, records, done, unplaced, nav_state in ready:
            if snaps and records:
                if frontier is not None:
                    out += self._close(min(key, frontier))
                if key != FLUSH_KEY and self._snap_upto is not None and key < self._snap_upto:
                    self.snap_late += 1  # a snapshot that should hold it is out: the workers' maps differ
            try:
                changes = self.builder.merge(records) if records else []
                self.merged += len(records)
                if changes:
                    self.on_changes(changes)
                if nav_state:
                    self.on_nav_state(robot, nav_state)
                if done:
                    self.on_commit(robot, done, unplaced)
            finally:  # counted out of flight only once merged and reported: flush() then sees them done
                with self._cond:
                    self._n_in_flight -= len(done)
                    self._cond.notify_all()
        if snaps:
            if frontier is not None:
                out += self._close(frontier)
            if out:
                self._publish_snapshots(out)
        else:
            self._publish_landmarks()

    def _close(self, upto_ns: int) -> list[SnapshotRange]:
        """The map's planes now are ``snapshot(T)`` of every grid time T not published yet up to ``upto_ns``
        (the caller knows every observation with a key before those T is merged, and none after): their ranges,
        kept for a joining worker."""
        from mapping.landmarks import SNAPSHOT_GRID_NS, SnapshotRange

        g = SNAPSHOT_GRID_NS
        hi = (upto_ns // g) * g
        lo = 0 if self._snap_upto is None else self._snap_upto + g
        if hi < lo:
            return []
        lm = self.builder.landmarks(self.landmark_min_points)
        out = []
        if lo <= self._inexact_to:  # an observation merged early sits in these: only the planes of about then
            cut = min(hi, (self._inexact_to // g) * g)
            out.append(SnapshotRange(lo, cut, lm, exact=False))
            lo = cut + g
        if hi >= lo:
            out.append(SnapshotRange(lo, hi, lm))
        self._snap_upto = hi
        self._kept.extend(out)
        while self._kept and self._kept[0].hi_ns < hi - SNAPSHOTS_KEEP_NS:
            self._kept.popleft()
        return out

    def _publish_snapshots(self, ranges: list[SnapshotRange]) -> None:
        try:
            self._lm_pub.put(encode_snapshots(self._base_id, ranges))
        except Exception as err:  # a worker's scan waits past its cap for these, counted not exact
            log.warning("map snapshots not sent to the workers: %s", err)
