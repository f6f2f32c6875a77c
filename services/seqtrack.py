"""Per-robot sequence tracking on the base station: what arrived, what is still missing, what came twice.

Each robot numbers its clouds 0, 1, 2, ... and never reuses a number (the ROV's outbox keeps the counter
across restarts). :class:`SeqTracker` keeps, per robot, the set of distinct numbers received as closed
intervals (:class:`services.seqset.SeqSet`), so memory grows with the number of gaps, not of messages, and
the result does not depend on the order of arrival:

- ``received``: distinct sequence numbers ever accepted;
- ``missed``: numbers in ``[0, highest]`` not received (the gaps still open; a redelivery closes them);
- ``duplicates``: arrivals of a number already held (redeliveries after a lost ack; harmless, dropped).

The tracker persists as JSON (written atomically: temporary file, fsync, rename) so a base station killed
and restarted with the same state folder keeps its counts, and acks only what it has persisted.
Thread-safe (one lock).
"""

from __future__ import annotations

import json
import os
import threading
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from .errors import ServiceError
from .keys import check_robot_name
from .outbox import atomic_write
from .seqset import SeqSet

FORMAT_NAME = "lrsensor-seqtrack"
FORMAT_VERSION = 1


class SeqTrackError(ServiceError):
    """A sequence-tracker state file is unreadable or inconsistent."""


class _Robot:
    __slots__ = ("duplicates", "seen")

    def __init__(self, seen: SeqSet | None = None, duplicates: int = 0) -> None:
        self.seen = seen if seen is not None else SeqSet()
        self.duplicates = duplicates


class SeqTracker:
    """Distinct received sequence numbers per robot, their open gaps and duplicate arrivals."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._robots: dict[str, _Robot] = {}
        self._version = 0  # bumps on every change; a saver compares it to what it saved
        self._saved_version = 0

    # ------------------------------------------------------------------------------------------- updates
    def add(self, robot: str, seq: int) -> bool:
        """Record that ``robot`` delivered ``seq``; True if new, False for a duplicate (counted).

        Raises:
            SeqTrackError: ``seq`` is negative or not an integer.
        """
        if not isinstance(seq, int) or isinstance(seq, bool) or seq < 0:
            msg = f"sequence number of {robot!r} must be a non-negative integer, got {seq!r}"
            raise SeqTrackError(msg)
        with self._lock:
            entry = self._robots.get(robot)
            if entry is None:
                entry = self._robots[robot] = _Robot()
            self._version += 1
            if entry.seen.add(seq):
                return True
            entry.duplicates += 1
            return False

    def ensure(self, robot: str) -> None:
        """Start tracking ``robot`` with nothing received (so it shows in the counters)."""
        with self._lock:
            if robot not in self._robots:
                self._robots[robot] = _Robot()
                self._version += 1

    # ------------------------------------------------------------------------------------------- queries
    def robots(self) -> list[str]:
        """The robots tracked, sorted."""
        with self._lock:
            return sorted(self._robots)

    def __contains__(self, item: object) -> bool:
        """``(robot, seq) in tracker``: was that number received?"""
        if not (isinstance(item, tuple) and len(item) == 2):
            return False
        robot, seq = item
        with self._lock:
            entry = self._robots.get(robot)  # type: ignore[arg-type]
            return entry is not None and seq in entry.seen

    def received(self, robot: str) -> int:
        """Distinct sequence numbers received from ``robot``."""
        with self._lock:
            entry = self._robots.get(robot)
            return len(entry.seen) if entry else 0

    def highest(self, robot: str) -> int:
        """The largest number received from ``robot``, -1 if none."""
        with self._lock:
            entry = self._robots.get(robot)
            return entry.seen.highest if entry else -1

    def missed(self, robot: str) -> int:
        """Numbers in ``[0, highest]`` not received from ``robot`` (open gaps)."""
        with self._lock:
            entry = self._robots.get(robot)
            return entry.seen.missed(0) if entry else 0

    def duplicates(self, robot: str) -> int:
        """Arrivals of numbers already held."""
        with self._lock:
            entry = self._robots.get(robot)
            return entry.duplicates if entry else 0

    def ranges(self, robot: str) -> list[list[int]]:
        """The received numbers of ``robot`` as ``[[lo, hi], ...]`` (closed, increasing)."""
        with self._lock:
            entry = self._robots.get(robot)
            return entry.seen.ranges() if entry else []

    def gaps(self, robot: str, limit: int | None = None) -> list[list[int]]:
        """The open gaps of ``robot`` in ``[0, highest]`` as ``[[lo, hi], ...]``, the first ``limit`` of them."""
        out: list[list[int]] = []
        nxt = 0
        for lo, hi in self.ranges(robot):
            if lo > nxt:
                out.append([nxt, lo - 1])
                if limit is not None and len(out) >= limit:
                    break
            nxt = hi + 1
        return out

    def counters(self, robot: str) -> dict[str, int]:
        """``{"received", "missed", "duplicates", "highest"}`` of one robot."""
        with self._lock:
            entry = self._robots.get(robot)
            if entry is None:
                return {"received": 0, "missed": 0, "duplicates": 0, "highest": -1}
            return {
                "received": len(entry.seen),
                "missed": entry.seen.missed(0),
                "duplicates": entry.duplicates,
                "highest": entry.seen.highest,
            }

    # ------------------------------------------------------------------------------------------- persistence
    def to_dict(self) -> dict[str, Any]:
        """JSON-ready state: ``{"format", "version", "robots": {name: {"ranges", "duplicates"}}}``."""
        with self._lock:
            return {
                "format": FORMAT_NAME,
                "version": FORMAT_VERSION,
                "robots": {
                    name: {"ranges": e.seen.ranges(), "duplicates": e.duplicates}
                    for name, e in sorted(self._robots.items())
                },
            }

    @classmethod
    def from_dict(cls, data: Any, source: str = "seqtrack") -> SeqTracker:
        """Rebuild from :meth:`to_dict`'s mapping; raises :class:`SeqTrackError` naming what is wrong."""
        if not isinstance(data, Mapping):
            msg = f"{source}: top level must be a JSON object"
            raise SeqTrackError(msg)
        if data.get("format") != FORMAT_NAME or data.get("version") != FORMAT_VERSION:
            msg = (
                f"{source}: not a {FORMAT_NAME} v{FORMAT_VERSION} file "
                f"(format={data.get('format')!r}, version={data.get('version')!r})"
            )
            raise SeqTrackError(msg)
        robots = data.get("robots")
        if not isinstance(robots, Mapping):
            msg = f"{source}: 'robots' must be an object"
            raise SeqTrackError(msg)
        tracker = cls()
        for name, entry in robots.items():
            where = f"{source}: robot {name!r}"
            try:
                check_robot_name(name)
            except ServiceError as err:
                msg = f"{where}: {err}"
                raise SeqTrackError(msg) from err
            if not isinstance(entry, Mapping):
                msg = f"{where}: entry must be an object"
                raise SeqTrackError(msg)
            dup = entry.get("duplicates", 0)
            if not isinstance(dup, int) or isinstance(dup, bool) or dup < 0:
                msg = f"{where}: 'duplicates' must be a non-negative integer, got {dup!r}"
                raise SeqTrackError(msg)
            ranges = entry.get("ranges")
            if not isinstance(ranges, list) or not all(_is_range(r) for r in ranges):
                msg = f"{where}: 'ranges' must be a list of [lo, hi] non-negative integers with lo <= hi"
                raise SeqTrackError(msg)
            tracker._robots[name] = _Robot(SeqSet(ranges), dup)
        return tracker

    def save(self, path: str | os.PathLike[str], *, fsync: bool = True) -> None:
        """Write the state to ``path`` atomically (and durably with ``fsync``)."""
        with self._lock:
            version = self._version
        data = json.dumps(self.to_dict(), separators=(",", ":")).encode()
        p = Path(path)
        p.parent.mkdir(parents=True, exist_ok=True)
        atomic_write(p, data, fsync=fsync)
        with self._lock:
            self._saved_version = max(self._saved_version, version)

    @property
    def dirty(self) -> bool:
        """True if something changed since the last :meth:`save`."""
        with self._lock:
            return self._version != self._saved_version

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> SeqTracker:
        """Read a saved state; a missing file gives an empty tracker. Raises :class:`SeqTrackError`."""
        p = Path(path)
        if not p.exists():
            return cls()
        try:
            data = json.loads(p.read_bytes())
        except (OSError, ValueError) as err:
            msg = f"sequence state {p} is unreadable: {err}"
            raise SeqTrackError(msg) from err
        return cls.from_dict(data, str(p))

    def merge(self, robot: str, seqs: Iterable[int]) -> int:
        """Add many numbers; returns how many were new."""
        return sum(1 for s in seqs if self.add(robot, s))


def _is_range(r: Any) -> bool:
    return (
        isinstance(r, list | tuple)
        and len(r) == 2
        and all(isinstance(v, int) and not isinstance(v, bool) for v in r)
        and 0 <= r[0] <= r[1]
    )
