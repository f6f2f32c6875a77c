"""A bounded, disk-backed store-and-forward outbox: the ROV keeps every encoded cloud until the base acks it.

Layout of the outbox directory::

    DIR/<seq:020d>.msg      one message per file, written atomically (temporary file, fsync, rename)
    DIR/state.json          counters that must survive a restart (written atomically): highest sequence
                            number ever appended, acked and dropped counts, the dropped sequence ranges
    DIR/lock                the pid of the process that holds the folder (an advisory ``flock``)

A message file is ``MAGIC (8 bytes) | seq (u64 LE) | length (u64 LE) | crc32 (u32 LE) | payload``. On reload
every ``*.msg`` file is checked (magic, name, length, CRC); a damaged one (a crash can only leave a
``.tmp`` file, but a disk can do worse) is moved to ``DIR/corrupt/`` and counted, never silently skipped.

Policy when full (the disk budget): the outbox holds at most ``max_messages`` messages and ``max_bytes``
payload bytes. An append that would exceed either bound first drops pending messages until the new one
fits: the oldest of those the caller names **expendable** (a copy already went out on the link, so it
arrives unless that copy is lost), then the **oldest** of the rest (lowest sequence numbers); every dropped
sequence number is counted (``dropped``) and kept as ranges (``dropped_ranges``) in ``state.json``, logged at
WARNING, and returned to the caller so it can report them. Among messages never sent the newest win because
a ROV that lost its link for long still wants its latest view of the world, and the base station sees the
dropped numbers as open gaps (``missed``) in its counters: loss is never silent.

Durability: with ``fsync=True`` (default) each message is on disk before :meth:`Outbox.append` returns, so
it survives a power cut; with ``fsync=False`` it survives a crash of the process but not of the machine.

Sequence numbers are strictly increasing and never reused, also across restarts: :attr:`Outbox.next_seq`
is one past the highest number ever appended (kept in ``state.json`` before any file is removed).

One process per outbox: an :class:`Outbox` holds an exclusive ``flock`` on ``DIR/lock`` from its creation to
:meth:`Outbox.close` (or its collection), so a second process opening the folder fails at once with
:class:`OutboxInUseError`, naming the holder's pid, instead of two writers numbering from the same
``next_seq``. The kernel releases the lock when the process ends, however (SIGKILL included): a stale lock
file never blocks a restart. Outboxes of one process on one folder share the lock (the tests reopen a folder
to play a restart); keeping them apart is the caller's business. The lock is advisory: it orders processes
that use this class, nothing else.

:func:`default_outbox_dir` is where ``lrsensor rov`` keeps a robot's outbox when no ``--outbox`` is given:
``$XDG_STATE_HOME/lrsensor/outbox/<fleet>/<robot>`` (``~/.local/state/...`` by default), so that a plain
restart continues the numbering. The class is thread-safe (one lock).
"""

from __future__ import annotations

import bisect
import fcntl
import json
import logging
import os
import pwd
import struct
import threading
import weakref
import zlib
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from lrsensor.atomic import atomic_write

from .errors import ServiceError

log = logging.getLogger(__name__)

MAGIC = b"LRSOBX1\n"
_HEADER = struct.Struct("<8sQQI")
STATE_FILE = "state.json"
SUFFIX = ".msg"
LOCK_FILE = "lock"
#: Default bounds: 20k messages or 1 GiB, whichever comes first (about 11 min of 30 Hz clouds).
DEFAULT_MAX_MESSAGES = 20_000
DEFAULT_MAX_BYTES = 1 << 30
#: How many dropped ranges ``state.json`` keeps (older ones are merged into the count only).
MAX_DROPPED_RANGES = 1000


class OutboxError(ServiceError):
    """The outbox directory cannot be used, or an append breaks its rules (sequence order, size)."""


class OutboxInUseError(OutboxError):
    """Another process holds the outbox folder (one process per outbox).

    Attributes:
        directory: the outbox folder.
        pid: the holder's process id as it wrote it in ``DIR/lock`` (None if not readable yet).
    """

    def __init__(self, directory: Path, pid: int | None) -> None:
        self.directory = directory
        self.pid = pid
        holder = f"process {pid}" if pid is not None else "another process (its pid not written yet)"
        super().__init__(f"outbox {directory} is in use by {holder}: one process per outbox")


def default_outbox_dir(fleet: str, robot: str, environ: Mapping[str, str] | None = None) -> Path:
    """The persistent outbox folder of ``robot`` in ``fleet`` in the user's state directory.

    ``$XDG_STATE_HOME/lrsensor/outbox/<fleet>/<robot>``; ``XDG_STATE_HOME`` unset, empty or relative (the XDG
    base directory rules) means ``~/.local/state``. The names are the checked fleet and robot names (no
    separators). Nothing is created here.

    Raises:
        OutboxError: no usable state directory (``XDG_STATE_HOME`` not set and no home directory).
    """
    env = os.environ if environ is None else environ
    state = env.get("XDG_STATE_HOME", "")
    if state and Path(state).is_absolute():
        base = Path(state)
    else:
        home = Path(env.get("HOME", ""))
        if not home.is_absolute():  # unset: the password database's, as a login shell would set it
            try:
                home = Path(pwd.getpwuid(os.getuid()).pw_dir)
            except KeyError as err:
                msg = f"no state directory: XDG_STATE_HOME and HOME are not set and uid {os.getuid()} has no home"
                raise OutboxError(msg) from err
        base = home / ".local" / "state"
    return base / "lrsensor" / "outbox" / fleet / robot


#: Folder locks this process holds: (st_dev, st_ino) of a lock file -> [its descriptor, how many outboxes].
_HELD: dict[tuple[int, int], list[int]] = {}
_HELD_GUARD = threading.Lock()


def _read_pid(fd: int) -> int | None:
    try:
        return int(os.pread(fd, 32, 0).decode("ascii", "replace").strip())
    except (OSError, ValueError):
        return None


def _lock_folder(directory: Path) -> tuple[int, int]:
    """Take (or share, within this process) the exclusive lock of ``directory``; returns its key.

    Raises:
        OutboxInUseError: another process holds it.
        OutboxError: the lock file cannot be opened or locked.
    """
    path = directory / LOCK_FILE
    try:
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
    except OSError as err:
        msg = f"cannot open the outbox lock {path}: {err}"
        raise OutboxError(msg) from err
    with _HELD_GUARD:
        st = os.fstat(fd)
        key = (st.st_dev, st.st_ino)
        held = _HELD.get(key)
        if held is not None:
            os.close(fd)  # flock belongs to the first descriptor; closing another one leaves it held
            held[1] += 1
            return key
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            pid = _read_pid(fd)
            os.close(fd)
            raise OutboxInUseError(directory, pid) from None
        except OSError as err:
            os.close(fd)
            msg = f"cannot lock the outbox {path}: {err}"
            raise OutboxError(msg) from err
        try:  # who holds it, for the message of the next one that tries (the lock does not depend on it)
            os.ftruncate(fd, 0)
            os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        except OSError as err:
            log.debug("outbox %s: cannot write the pid into the lock file: %s", directory, err)
        _HELD[key] = [fd, 1]
        return key


def _unlock_folder(key: tuple[int, int]) -> None:
    """Drop one outbox's share of a folder lock; the last one closes the descriptor, which releases it."""
    with _HELD_GUARD:
        held = _HELD.get(key)
        if held is None:
            return
        held[1] -= 1
        if held[1] <= 0:
            del _HELD[key]
            os.close(held[0])


@dataclass(frozen=True)
class OutboxStats:
    """Counters of an outbox.

    Attributes:
        pending: messages held, not yet acknowledged.
        pending_bytes: their payload bytes.
        appended: messages appended since the outbox was created (kept across restarts).
        acked: messages acknowledged and removed (kept across restarts).
        dropped: messages dropped because the outbox was full (kept across restarts).
        corrupt: damaged message files found on reload (moved to ``corrupt/``).
        next_seq: the next sequence number to use.
        dropped_ranges: the dropped sequence numbers as ``[[lo, hi], ...]`` (most recent
            :data:`MAX_DROPPED_RANGES`).
    """

    pending: int
    pending_bytes: int
    appended: int
    acked: int
    dropped: int
    corrupt: int
    next_seq: int
    dropped_ranges: tuple[tuple[int, int], ...]

    def to_json_dict(self) -> dict[str, Any]:
        """JSON-ready mapping."""
        return {
            "pending": self.pending,
            "pending_bytes": self.pending_bytes,
            "appended": self.appended,
            "acked": self.acked,
            "dropped": self.dropped,
            "corrupt": self.corrupt,
            "next_seq": self.next_seq,
            "dropped_ranges": [list(r) for r in self.dropped_ranges],
        }


def _add_range(ranges: list[list[int]], seq: int) -> None:
    """Add ``seq`` to increasing, disjoint ``ranges`` (anywhere, merging neighbours); the list stays short in
    practice, as drops come in runs."""
    lo = bisect.bisect_right([r[0] for r in ranges], seq) - 1
    if lo >= 0 and ranges[lo][0] <= seq <= ranges[lo][1]:
        return
    if lo >= 0 and ranges[lo][1] + 1 == seq:
        ranges[lo][1] = seq
    else:
        lo += 1
        ranges.insert(lo, [seq, seq])
    if lo + 1 < len(ranges) and ranges[lo][1] + 1 >= ranges[lo + 1][0]:
        ranges[lo][1] = max(ranges[lo][1], ranges[lo + 1][1])
        del ranges[lo + 1]


class Outbox:
    """A bounded, crash-safe queue of encoded messages keyed by sequence number.

    Holds the folder's lock (one process per outbox) until :meth:`close`; usable as a context manager.

    Args:
        directory: the outbox folder (created; one outbox per robot).
        max_messages: at most this many messages pending (>= 1).
        max_bytes: at most this many payload bytes pending (>= 1).
        fsync: flush every message to disk before :meth:`append` returns.

    Raises:
        OutboxInUseError: another process holds the folder.
        OutboxError: the folder cannot be created or locked, its state is unreadable, or a bound is not positive.
    """

    def __init__(
        self,
        directory: str | os.PathLike[str],
        *,
        max_messages: int = DEFAULT_MAX_MESSAGES,
        max_bytes: int = DEFAULT_MAX_BYTES,
        fsync: bool = True,
    ) -> None:
        if max_messages < 1 or max_bytes < 1:
            msg = f"outbox bounds must be positive, got max_messages={max_messages}, max_bytes={max_bytes}"
            raise OutboxError(msg)
        self.directory = Path(directory)
        self.max_messages = int(max_messages)
        self.max_bytes = int(max_bytes)
        self.fsync = bool(fsync)
        self._lock = threading.RLock()
        self._seqs: list[int] = []  # sorted pending sequence numbers
        self._sizes: dict[int, int] = {}
        self._bytes = 0
        self._next_seq = 0
        self._appended = 0
        self._acked = 0
        self._dropped = 0
        self._corrupt = 0
        self._dropped_ranges: list[list[int]] = []
        self._closed = False
        try:
            self.directory.mkdir(parents=True, exist_ok=True)
        except OSError as err:
            msg = f"cannot create the outbox folder {self.directory}: {err}"
            raise OutboxError(msg) from err
        key = _lock_folder(self.directory)  # before reading anything: the state is the holder's
        self._release = weakref.finalize(self, _unlock_folder, key)  # also when dropped without close()
        try:
            self._reload()
        except BaseException:
            self._release()
            raise

    def close(self) -> None:
        """Release the folder's lock (idempotent); the outbox must not be appended to afterwards."""
        with self._lock:
            self._closed = True
            self._release()

    def __enter__(self) -> Outbox:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ----------------------------------------------------------------------------------------- persistence
    def _path(self, seq: int) -> Path:
        return self.directory / f"{seq:020d}{SUFFIX}"

    def _reload(self) -> None:
        state_path = self.directory / STATE_FILE
        if state_path.exists():
            try:
                state = json.loads(state_path.read_text())
                self._next_seq = int(state["next_seq"])
                self._appended = int(state["appended"])
                self._acked = int(state["acked"])
                self._dropped = int(state["dropped"])
                self._corrupt = int(state.get("corrupt", 0))
                self._dropped_ranges = [[int(a), int(b)] for a, b in state.get("dropped_ranges", [])]
            except (OSError, ValueError, KeyError, TypeError) as err:
                msg = f"outbox state {state_path} is unreadable ({err}); move it aside to start afresh"
                raise OutboxError(msg) from err
        for tmp in self.directory.glob(".*.tmp"):  # an interrupted atomic write: never renamed, not a message
            tmp.unlink(missing_ok=True)
        found: list[tuple[int, int]] = []
        for path in self.directory.glob(f"*{SUFFIX}"):
            seq, size = self._check_file(path)
            if seq < 0:
                self._quarantine(path)
                continue
            found.append((seq, size))
        found.sort()
        self._seqs = [s for s, _ in found]
        self._sizes = dict(found)
        self._bytes = sum(self._sizes.values())
        if self._seqs:
            self._next_seq = max(self._next_seq, self._seqs[-1] + 1)
        # Every message ever appended is now acked, dropped, pending or corrupt (the count is not saved on
        # each append, only on acks and drops).
        self._appended = max(self._appended, self._acked + self._dropped + self._corrupt + len(self._seqs))
        if found:
            log.info("outbox %s: reloaded %d pending messages (%d bytes)", self.directory, len(found), self._bytes)

    def _check_file(self, path: Path) -> tuple[int, int]:
        """(seq, payload size) of a valid message file, (-1, 0) for a damaged one."""
        try:
            name_seq = int(path.name[: -len(SUFFIX)])
            with path.open("rb") as f:
                header = f.read(_HEADER.size)
                magic, seq, length, crc = _HEADER.unpack(header)
                payload = f.read(length + 1)
        except (OSError, ValueError, struct.error) as err:
            log.warning("outbox %s: damaged message file %s (%s)", self.directory, path.name, err)
            return -1, 0
        if magic != MAGIC or seq != name_seq or len(payload) != length or zlib.crc32(payload) != crc:
            log.warning("outbox %s: damaged message file %s (header or checksum mismatch)", self.directory, path.name)
            return -1, 0
        return seq, length

    def _quarantine(self, path: Path) -> None:
        bad = self.directory / "corrupt"
        bad.mkdir(exist_ok=True)
        path.replace(bad / path.name)
        self._corrupt += 1

    def _save_state(self) -> None:
        state = {
            "format": "lrsensor-outbox",
            "version": 1,
            "next_seq": self._next_seq,
            "appended": self._appended,
            "acked": self._acked,
            "dropped": self._dropped,
            "corrupt": self._corrupt,
            "dropped_ranges": self._dropped_ranges[-MAX_DROPPED_RANGES:],
        }
        atomic_write(self.directory / STATE_FILE, json.dumps(state).encode(), fsync=self.fsync)

    def _remove(self, seqs: Sequence[int]) -> None:
        """Forget ``seqs`` (already in the state) and delete their files."""
        for seq in seqs:
            i = bisect.bisect_left(self._seqs, seq)
            if i < len(self._seqs) and self._seqs[i] == seq:
                del self._seqs[i]
                self._bytes -= self._sizes.pop(seq)
            self._path(seq).unlink(missing_ok=True)

    # ----------------------------------------------------------------------------------------- public API
    @property
    def next_seq(self) -> int:
        """One past the highest sequence number ever appended (0 for a new outbox)."""
        with self._lock:
            return self._next_seq

    def append(
        self, seq: int, payload: bytes, expendable: Callable[[int], bool] | None = None, *, sync: bool = True
    ) -> list[int]:
        """Store ``payload`` under ``seq``; returns the sequence numbers dropped to make room, in the order
        dropped: the oldest ``expendable`` ones first (a predicate on a pending number; it must not call the
        outbox), then the oldest of the rest.

        With ``sync=False`` the file is written and renamed but not flushed to disk: it survives a crash of
        the process at once, and a power cut only after :meth:`sync` (a caller that must not wait for the disk
        before doing something else, such as publishing the cloud, calls :meth:`sync` after it).

        Raises:
            OutboxError: ``seq`` is not above every number appended before, the payload alone is larger
                than ``max_bytes``, the disk write failed, or the outbox is closed.
        """
        if not isinstance(payload, bytes | bytearray | memoryview):
            msg = f"outbox payload must be bytes, got {type(payload).__name__}"
            raise OutboxError(msg)
        data = bytes(payload)
        with self._lock:
            if self._closed:
                msg = f"outbox {self.directory} is closed (its lock released)"
                raise OutboxError(msg)
            if seq < self._next_seq:
                msg = f"outbox {self.directory}: sequence number {seq} is not above {self._next_seq - 1}"
                raise OutboxError(msg)
            if len(data) > self.max_bytes:
                msg = f"outbox {self.directory}: message #{seq} of {len(data)} bytes exceeds max_bytes={self.max_bytes}"
                raise OutboxError(msg)
            dropped: list[int] = []
            first = 0  # the expendable ones are searched from here (those below are not)
            while self._seqs and (len(self._seqs) + 1 > self.max_messages or self._bytes + len(data) > self.max_bytes):
                i = len(self._seqs)
                if expendable is not None:
                    while first < len(self._seqs) and not expendable(self._seqs[first]):
                        first += 1
                    i = first
                dropped.append(self._seqs.pop(i if i < len(self._seqs) else 0))
                self._bytes -= self._sizes.pop(dropped[-1])
            header = _HEADER.pack(MAGIC, seq, len(data), zlib.crc32(data))
            self._next_seq = seq + 1
            if dropped:
                self._dropped += len(dropped)
                for d in sorted(dropped):
                    _add_range(self._dropped_ranges, d)
                del self._dropped_ranges[:-MAX_DROPPED_RANGES]
                log.warning(
                    "outbox %s full (%d messages, %d bytes max: the disk budget): dropped %d (#%d..#%d)",
                    self.directory,
                    self.max_messages,
                    self.max_bytes,
                    len(dropped),
                    min(dropped),
                    max(dropped),
                )
                self._save_state()  # next_seq and the drop are durable before any file goes
                for d in dropped:
                    self._path(d).unlink(missing_ok=True)
            try:
                atomic_write(self._path(seq), header + data, fsync=self.fsync and sync)
            except OSError as err:
                msg = f"outbox {self.directory}: cannot write message #{seq}: {err}"
                raise OutboxError(msg) from err
            self._seqs.append(seq)
            self._sizes[seq] = len(data)
            self._bytes += len(data)
            self._appended += 1
            return dropped

    def sync(self, seq: int) -> None:
        """Flush message ``seq`` (appended with ``sync=False``) and the folder entry to disk; a no-op without
        ``fsync`` or when it is no longer pending.

        Raises:
            OutboxError: the flush failed.
        """
        if not self.fsync or seq not in self:
            return
        try:
            fd = os.open(self._path(seq), os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)
            dfd = os.open(self.directory, os.O_RDONLY)
            try:
                os.fsync(dfd)
            finally:
                os.close(dfd)
        except FileNotFoundError:  # acknowledged (removed) meanwhile
            return
        except OSError as err:
            msg = f"outbox {self.directory}: cannot flush message #{seq}: {err}"
            raise OutboxError(msg) from err

    def pending(self) -> list[int]:
        """The pending sequence numbers, increasing."""
        with self._lock:
            return list(self._seqs)

    def __len__(self) -> int:
        with self._lock:
            return len(self._seqs)

    def __contains__(self, seq: object) -> bool:
        with self._lock:
            return isinstance(seq, int) and seq in self._sizes

    def get(self, seq: int) -> bytes | None:
        """The payload of a pending message, or None if it is not pending (acked, dropped, never appended)."""
        with self._lock:
            if seq not in self._sizes:
                return None
            try:
                raw = self._path(seq).read_bytes()
            except OSError as err:
                msg = f"outbox {self.directory}: cannot read message #{seq}: {err}"
                raise OutboxError(msg) from err
        return raw[_HEADER.size :]

    def iter_pending(self, after: int = -1, limit: int | None = None) -> Iterator[tuple[int, bytes]]:
        """(seq, payload) of pending messages with ``seq > after``, increasing; skips ones acked meanwhile."""
        with self._lock:
            i = bisect.bisect_right(self._seqs, after)
            seqs = self._seqs[i : i + limit] if limit is not None else self._seqs[i:]
        for seq in seqs:
            payload = self.get(seq)
            if payload is not None:
                yield seq, payload

    def ack(self, seq: int) -> bool:
        """Remove one message; True if it was pending."""
        return self.ack_many([seq]) == 1

    def ack_upto(self, seq: int) -> int:
        """Remove every pending message with a number <= ``seq``; returns how many."""
        with self._lock:
            i = bisect.bisect_right(self._seqs, seq)
            return self.ack_many(self._seqs[:i])

    def ack_ranges(self, ranges: Iterable[Sequence[int]]) -> int:
        """Remove every pending message inside any closed range ``[lo, hi]``; returns how many."""
        return len(self.take_acked_ranges(ranges))

    def ack_many(self, seqs: Iterable[int]) -> int:
        """Remove the given messages (those pending); returns how many were removed."""
        return len(self.take_acked(seqs))

    def take_acked(self, seqs: Iterable[int]) -> list[int]:
        """Remove the given messages (those pending); returns the numbers removed, increasing.

        Exactly these were acknowledged: a message dropped by the bounds meanwhile is not among them, so a
        caller that counts each message once (acknowledged or dropped) can rely on the two lists being disjoint.
        """
        with self._lock:
            hit = sorted({s for s in seqs if s in self._sizes})
            if not hit:
                return []
            self._acked += len(hit)
            self._save_state()
            self._remove(hit)
            return hit

    def take_acked_ranges(self, ranges: Iterable[Sequence[int]]) -> list[int]:
        """:meth:`take_acked` of every pending message inside any closed range ``[lo, hi]``."""
        with self._lock:
            hit: list[int] = []
            for lo, hi in ranges:
                i = bisect.bisect_left(self._seqs, int(lo))
                j = bisect.bisect_right(self._seqs, int(hi))
                hit.extend(self._seqs[i:j])
            return self.take_acked(hit)

    def stats(self) -> OutboxStats:
        """A snapshot of the counters."""
        with self._lock:
            return OutboxStats(
                pending=len(self._seqs),
                pending_bytes=self._bytes,
                appended=self._appended,
                acked=self._acked,
                dropped=self._dropped,
                corrupt=self._corrupt,
                next_seq=self._next_seq,
                dropped_ranges=tuple((a, b) for a, b in self._dropped_ranges),
            )
