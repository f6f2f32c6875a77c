"""The base station's robot ledger: what it knows of each robot, what it holds durably, what it acknowledges.

Records: one :class:`RobotRecord` per robot name ever seen (also for payloads that were refused: a robot that
sends only garbage is still listed, with its rejections). A record holds the sequence numbers received
(``seqs``, a :class:`~services.seqset.SeqSet` of ranges, so a gap is a ``missed`` count and a repeat a
``duplicate``), those the map has taken in (``mapped``), those acknowledged (``acked``), counters, the
liveliness state, the ROV's last self-report and the track of accepted poses. A cloud whose pose has no
horizontal fix (``north_m``/``east_m`` null) is counted as ``unplaced`` and left out of the track.

State file: ``<state>/fleet.json``, written atomically (temporary file, fsync, rename)::

    {"format": "lrsensor-base-state", "version": 1, "saved_ns": ...,
     "robots": {r: {"ranges", "acked", "rejected", "duplicates", "reused", "points", "last_t_ns", "unplaced"}}}

On a restart only the ``acked`` ranges are reloaded as received: they are the only ones known to be in the
saved map too. Everything else is still in the robots' outboxes (a robot keeps every cloud until it is
acknowledged), arrives again and is taken, not dropped as a duplicate.

Acknowledgement protocol (issue 7: nothing acknowledged is ever lost). A :meth:`Ledger.checkpoint` notes the
ranges that are durable once saved (with the map: those the map has taken in, ``mapped``; without: all
received, ``seqs``), saves the map, then writes ``fleet.json`` with those ranges as ``acked``, and only then
serves them (``<root>/base/acks/<robot>``, see :meth:`Ledger.acks_json`). A robot therefore forgets a cloud
only once both the counters and the map hold it on disk. The periodic saver (:meth:`Ledger.run_saver`) writes
changed counters every ``save_period_s`` and checkpoints every ``ack_period_s``; without the map a checkpoint
is one small file, so an acknowledgement query writes it at once (:meth:`Ledger.ack_now`, at most every
0.2 s). Without a state folder nothing survives a restart anyway: what arrived is acknowledged at once.

Why not acknowledge on arrival: a base station killed between arrival and save would lose clouds the robots
had already deleted; with the map on, the map saves in seconds-long batches, so acknowledgements follow them.

Threading: one re-entrant lock guards the records; the file is written outside it, under a save lock that
orders snapshot, write and acknowledgement, so the file never lags the acknowledgements served.
"""

from __future__ import annotations

import collections
import json
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from lrsensor.atomic import atomic_write
from lrsensor.calibration import Calibration

from .errors import ServiceError
from .posetrack import has_fix
from .seqset import SeqSet
from .wire import CloudMsg, StatusMsg

log = logging.getLogger(__name__)

STATE_FORMAT = "lrsensor-base-state"
STATE_VERSION = 1
#: Robot name under which payloads on keys that name no valid robot are counted.
UNKNOWN_SENDER = "?"
#: Poses kept per robot for the track plot.
MAX_TRACK_POINTS = 20_000
#: Shortest interval between two acknowledgement-driven saves of the counters (no map), seconds.
ACK_SAVE_MIN_INTERVAL_S = 0.2
#: A robot's clock offset is estimated from the arrival of its latest status messages (one a second: a minute)
#: and of its latest clouds.
CLOCK_SAMPLES = 60
CLOUD_CLOCK_SAMPLES = 600
#: Capture times kept per robot to tell a re-sent cloud from a number given twice (the latest clouds taken).
RECENT_CAPTURES = 10_000
#: Beyond this offset a robot's clock is taken as off: its times are put on the base station's clock for the
#: latency figures (below it, the link's own transit is as large as the error of the estimate), seconds.
CLOCK_OFFSET_MIN_S = 2.0

Ranges = list[list[int]]


@dataclass
class RobotRecord:
    """What the base station knows of one robot."""

    seqs: SeqSet = field(default_factory=SeqSet)
    #: clouds the map has taken in (or that had nothing for it); with the map saved after, they are durable
    mapped: SeqSet = field(default_factory=SeqSet)
    #: the sequence ranges persisted in ``--state`` (counters and map): what the base acknowledges
    acked: Ranges = field(default_factory=list)
    rejected: int = 0
    duplicates: int = 0
    #: duplicates whose capture time differs from the held cloud's: the robot gave a number twice (restarted
    #: without its outbox?); dropped like any duplicate, but counted and logged
    reused: int = 0
    #: capture times of the latest :data:`RECENT_CAPTURES` clouds taken, by sequence number
    captures: collections.OrderedDict[int, int] = field(default_factory=collections.OrderedDict)
    #: accepted clouds whose pose had no horizontal fix: the map cannot place them (see services.mapfeed)
    unplaced: int = 0
    points: int = 0
    alive: bool = False
    joined_ns: int = 0
    left_ns: int = 0
    last_t_ns: int = 0
    reported: StatusMsg | None = None
    rejected_reasons: collections.Counter[str] = field(default_factory=collections.Counter)
    track: list[tuple[int, float, float, float]] = field(default_factory=list)
    #: arrival (base clock) minus the robot's own ``t_ns`` of its latest status messages, ns
    clock_lags: collections.deque[int] = field(default_factory=lambda: collections.deque(maxlen=CLOCK_SAMPLES))
    #: the same of its latest clouds (arrival minus publication time, ``sent_ns``), ns
    cloud_lags: collections.deque[int] = field(default_factory=lambda: collections.deque(maxlen=CLOUD_CLOCK_SAMPLES))

    def clock_offset_ns(self) -> int | None:
        """The robot's wall clock minus the base station's, ns (None before anything stamped arrived).

        A status message or a cloud is stamped by the robot as it is published, so its arrival time minus its
        stamp is its transit plus the base's clock minus the robot's. The smallest such lag over the latest
        status messages (:data:`CLOCK_SAMPLES`; never re-sent: one arrives every second whatever the backlog)
        and clouds (:data:`CLOUD_CLOCK_SAMPLES`) is minus the offset up to the fastest transit: a late or re-sent
        one only makes it larger, and a cloud's own transit on the base's clock is never negative.
        """
        lags = [min(d) for d in (self.clock_lags, self.cloud_lags) if d]
        return -min(lags) if lags else None

    def clock_correction_ns(self) -> int:
        """What to subtract from the robot's times to put them on the base station's clock: its offset when
        beyond :data:`CLOCK_OFFSET_MIN_S`, else 0."""
        off = self.clock_offset_ns()
        return off if off is not None and abs(off) > CLOCK_OFFSET_MIN_S * 1e9 else 0

    @property
    def n_acked(self) -> int:
        """How many sequence numbers are acknowledged."""
        return sum(hi - lo + 1 for lo, hi in self.acked)

    def to_json(self) -> dict[str, Any]:
        """The robot's entry in the status JSON."""
        out: dict[str, Any] = {
            "received": len(self.seqs),
            "rejected": self.rejected,
            "missed": self.seqs.missed(),
            "duplicates": self.duplicates,
            "reused": self.reused,
            "unplaced": self.unplaced,
            "alive": self.alive,
            "last_seq": self.seqs.highest,
            "acked": self.n_acked,
            "last_t_ns": self.last_t_ns,
            "points": self.points,
        }
        if self.rejected_reasons:
            out["rejected_reasons"] = dict(self.rejected_reasons.most_common(8))
        if self.reported is not None:
            out["reported"] = self.reported.to_json_dict()
        offset = self.clock_offset_ns()
        if offset is not None:
            out["clock_offset_s"] = round(offset / 1e9, 3)
            out["clock_corrected"] = self.clock_correction_ns() != 0
        return out


class Ledger:
    """The robot records, their state file and the acknowledgement protocol (see the module docstring).

    Args:
        state_dir: where ``fleet.json`` and ``calib/<robot>.json`` live (None: in memory only); the state file
            is reloaded here when present.
        save_map: writes the map to disk (None when the map is off: what arrived is then durable as soon as
            the counters are written).
        save_period_s: how often :meth:`run_saver` writes changed counters.
        ack_period_s: how often :meth:`run_saver` checkpoints (map and counters saved, then acknowledged).

    Raises:
        ServiceError: the state file exists but is not a readable base-station state.
    """

    def __init__(
        self,
        state_dir: Path | None,
        *,
        save_map: Callable[[], object] | None = None,
        save_period_s: float = 1.0,
        ack_period_s: float = 2.0,
    ) -> None:
        self.state_dir = state_dir
        self.save_map = save_map
        self.save_period_s = save_period_s
        self.ack_period_s = ack_period_s
        self.records: dict[str, RobotRecord] = {}
        #: (robot, "joined" or "left", time_ns) in the order liveliness reported them
        self.membership_events: list[tuple[str, str, int]] = []
        self.lock = threading.RLock()
        self._save_lock = threading.Lock()
        self._dirty = False
        self._last_ack_save_s = 0.0
        self._load()

    # ------------------------------------------------------------------ records
    def record(self, robot: str) -> RobotRecord:
        """The record of ``robot``, created when new."""
        with self.lock:
            rec = self.records.get(robot)
            if rec is None:
                rec = self.records[robot] = RobotRecord()
            return rec

    def reject(self, robot: str, reason: str) -> None:
        """Count a refused payload of ``robot`` (logged for the first five, then every hundredth)."""
        with self.lock:
            rec = self.record(robot)
            rec.rejected += 1
            short = reason.split(":")[0] if len(reason) > 60 else reason
            rec.rejected_reasons[short[:60]] += 1
            n = rec.rejected
            self._dirty = True
        if n <= 5 or n % 100 == 0:
            log.warning("payload from %s rejected (%d so far): %s", robot, n, reason)

    def accept(self, msg: CloudMsg) -> bool:
        """Count a valid cloud: False when its sequence number was already received (a duplicate)."""
        with self.lock:
            rec = self.record(msg.robot)
            if not rec.seqs.add(msg.seq):
                rec.duplicates += 1
                held_t = rec.captures.get(msg.seq)
                if held_t is not None and held_t != msg.t_ns:
                    rec.reused += 1
                    n = rec.reused
                    if n <= 5 or n % 100 == 0:
                        log.warning(
                            "%s sent cloud #%d again with another capture time (%d, held %d): it gives numbers "
                            "twice (restarted without its outbox?); the new cloud is dropped (%d so far)",
                            msg.robot,
                            msg.seq,
                            msg.t_ns,
                            held_t,
                            n,
                        )
                return False
            rec.captures[msg.seq] = msg.t_ns
            if len(rec.captures) > RECENT_CAPTURES:
                rec.captures.popitem(last=False)
            rec.points += len(msg)
            rec.last_t_ns = max(rec.last_t_ns, msg.t_ns)
            p = msg.pose
            if not has_fix(p):
                rec.unplaced += 1
            elif len(rec.track) < MAX_TRACK_POINTS:
                rec.track.append((msg.t_ns, p.north_m, p.east_m, p.down_m))
            self._dirty = True
            return True

    def mark_mapped(self, robot: str, seq: int) -> None:
        """The map took cloud ``seq`` of ``robot`` in (or will never take it): acknowledgeable at the next
        checkpoint."""
        with self.lock:
            self.record(robot).mapped.add(seq)

    def set_reported(self, robot: str, msg: StatusMsg, recv_ns: int | None = None) -> None:
        """Keep the ROV's latest self-report (shown as ``reported`` in the status); ``recv_ns``, its arrival on
        the base station's clock, is a sample of the robot's clock offset (:meth:`RobotRecord.clock_offset_ns`)."""
        with self.lock:
            rec = self.record(robot)
            rec.reported = msg
            if recv_ns is not None:
                rec.clock_lags.append(recv_ns - msg.t_ns)

    def clock_correction_ns(self, robot: str, cloud_lag_ns: int | None = None) -> int:
        """See :meth:`RobotRecord.clock_correction_ns`, after noting a cloud's arrival minus its publication
        time, ``cloud_lag_ns`` (when given)."""
        with self.lock:
            rec = self.record(robot)
            if cloud_lag_ns is not None:
                rec.cloud_lags.append(cloud_lag_ns)
            return rec.clock_correction_ns()

    def set_alive(self, robot: str, alive: bool, t_ns: int) -> None:
        """Note that ``robot`` joined (``alive``) or left the fleet at ``t_ns``."""
        with self.lock:
            rec = self.record(robot)
            rec.alive = alive
            if alive:
                rec.joined_ns = t_ns
            else:
                rec.left_ns = t_ns
            self.membership_events.append((robot, "joined" if alive else "left", t_ns))

    # ------------------------------------------------------------------ views
    def robots_json(self, robot: str | None = None) -> dict[str, Any]:
        """The ``robots`` part of the status JSON, sorted by name (one robot only when ``robot`` is given)."""
        with self.lock:
            return {r: rec.to_json() for r, rec in sorted(self.records.items()) if robot in (None, r)}

    def acks_json(self, robot: str) -> dict[str, Any]:
        """The answer to ``<root>/base/acks/<robot>``: ``{"robot", "ranges", "received"}``."""
        with self.lock:
            rec = self.records.get(robot)
            return {
                "robot": robot,
                # with --state: only what is durable (see checkpoint); without: nothing survives a
                # restart anyway, so what arrived is acknowledged at once
                "ranges": (rec.acked if self.state_dir is not None else rec.seqs.ranges()) if rec else [],
                "received": len(rec.seqs) if rec else 0,
            }

    def tracks(self) -> dict[str, np.ndarray]:
        """Per robot, the poses of its accepted clouds: (M, 4) ``t_ns, north_m, east_m, down_m``."""
        with self.lock:
            return {r: np.asarray(rec.track, dtype=float).reshape(-1, 4) for r, rec in self.records.items()}

    # ------------------------------------------------------------------ calibrations
    def calibration_path(self, robot: str) -> Path | None:
        """Where the fleet calibration of ``robot`` is stored."""
        return self.state_dir / "calib" / f"{robot}.json" if self.state_dir is not None else None

    def store_calibration(self, robot: str, calibration: Calibration) -> None:
        """Store a robot's fleet calibration (served on ``<root>/base/calib/<robot>``)."""
        path = self.calibration_path(robot)
        if path is None:
            msg = "the base station has no --state folder to store calibrations in"
            raise ServiceError(msg)
        calibration.save(path)

    # ------------------------------------------------------------------ state file
    @property
    def state_file(self) -> Path | None:
        """``<state>/fleet.json``, or None without a state folder."""
        return self.state_dir / "fleet.json" if self.state_dir is not None else None

    def _load(self) -> None:
        path = self.state_file
        if path is None or not path.exists():
            return
        try:
            data = json.loads(path.read_text(encoding="utf-8"))
            if data.get("format") != STATE_FORMAT or data.get("version") != STATE_VERSION:
                msg = f"{path}: not a base-station state file of version {STATE_VERSION}"
                raise ServiceError(msg)
            for robot, rec in data["robots"].items():
                # Only what was acknowledged is known to be in the saved map too: the rest is taken again
                # from the robots' outboxes (they keep every cloud until it is acknowledged).
                acked = rec.get("acked", rec.get("ranges", []))
                self.records[robot] = RobotRecord(
                    seqs=SeqSet(acked),
                    mapped=SeqSet(acked),
                    acked=SeqSet(acked).ranges(),
                    rejected=int(rec.get("rejected", 0)),
                    duplicates=int(rec.get("duplicates", 0)),
                    reused=int(rec.get("reused", 0)),
                    unplaced=int(rec.get("unplaced", 0)),
                    points=int(rec.get("points", 0)),
                    last_t_ns=int(rec.get("last_t_ns", 0)),
                )
        except (OSError, ValueError, KeyError, TypeError, AttributeError) as err:
            msg = f"{path}: cannot read the base station's state: {err}"
            raise ServiceError(msg) from err
        log.info("state reloaded from %s: %d robots", path, len(self.records))

    def checkpoint(self, save_map: bool = True) -> None:
        """Make what was received durable and acknowledge it (see the module docstring).

        The clouds the map has taken in are noted first, then the map is saved (unless ``save_map`` is False:
        the caller has just saved it), then the counters with those ranges as ``acked``; only after that are
        they served. Without the map the received ranges are acknowledged as soon as the counters are written.
        """
        with self.lock:
            if self.save_map is not None:
                acked = {r: rec.mapped.ranges() for r, rec in self.records.items()}
            else:
                acked = {r: rec.seqs.ranges() for r, rec in self.records.items()}
        if self.state_dir is None:
            with self.lock:
                for r, ranges in acked.items():
                    self.records[r].acked = ranges
            return
        if self.save_map is not None and save_map:
            self.save_map()
        self.save_state(acked)

    def save_state(self, acked: dict[str, Ranges] | None = None) -> None:
        """Write the counters to ``<state>/fleet.json`` atomically (no-op without a state folder).

        ``acked``: per robot, ranges now durable (see :meth:`checkpoint`); they are acknowledged once the
        file is written. Robots not in it keep their previous acknowledgement.
        """
        path = self.state_file
        if path is None:
            return
        with self._save_lock:  # snapshot, write and acknowledge in one order: the file never lags the acks
            self._save_state_locked(path, acked)

    def _save_state_locked(self, path: Path, acked: dict[str, Ranges] | None) -> None:
        with self.lock:
            acked_now = {r: (acked[r] if acked and r in acked else rec.acked) for r, rec in self.records.items()}
            data = {
                "format": STATE_FORMAT,
                "version": STATE_VERSION,
                "saved_ns": time.time_ns(),
                "robots": {
                    r: {
                        "ranges": rec.seqs.ranges(),
                        "acked": acked_now[r],
                        "rejected": rec.rejected,
                        "duplicates": rec.duplicates,
                        "reused": rec.reused,
                        "unplaced": rec.unplaced,
                        "points": rec.points,
                        "last_t_ns": rec.last_t_ns,
                    }
                    for r, rec in self.records.items()
                },
            }
            self._dirty = False
        atomic_write(path, json.dumps(data))
        with self.lock:
            for r, ranges in acked_now.items():
                if r in self.records:
                    self.records[r].acked = ranges

    def ack_now(self, robot: str) -> None:
        """Without the map a checkpoint is one small file: write it now (at most every
        ``ACK_SAVE_MIN_INTERVAL_S``) so that an acknowledgement query sees everything received. With the
        map, the saver's checkpoints answer."""
        if self.save_map is not None or self.state_dir is None:
            return
        with self.lock:
            rec = self.records.get(robot)
            if rec is None or len(rec.seqs) == rec.n_acked:
                return
            if time.monotonic() - self._last_ack_save_s < ACK_SAVE_MIN_INTERVAL_S:
                return
            self._last_ack_save_s = time.monotonic()
            ranges = rec.seqs.ranges()
        try:
            self.save_state({robot: ranges})
        except OSError as err:
            log.error("cannot save state: %s", err)

    def unacked(self) -> bool:
        """Whether any robot has received sequence numbers not yet acknowledged."""
        with self.lock:
            return any(len(rec.seqs) != rec.n_acked for rec in self.records.values())

    def run_saver(self, stop: threading.Event) -> None:
        """Until ``stop`` is set: write changed counters every ``save_period_s``; every ``ack_period_s`` a
        :meth:`checkpoint` (map saved, then counters with the acknowledged ranges). The map also autosaves."""
        last_checkpoint_s = time.monotonic()
        while not stop.wait(self.save_period_s):
            if not self._dirty and not self.unacked():
                continue
            try:
                if time.monotonic() - last_checkpoint_s >= self.ack_period_s:
                    last_checkpoint_s = time.monotonic()
                    self.checkpoint()
                elif self._dirty:
                    self.save_state()
            except Exception as err:  # a full disk must not stop the service; acks wait for the next try
                log.error("cannot save state: %s", err)
