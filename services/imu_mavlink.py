"""A MAVLink pose source: ArduSub on a BlueROV2 (``lrsensor rov --imu mavlink:CONNECTION``).

``CONNECTION`` is a pymavlink connection string: ``udpin:127.0.0.1:14551`` (listen for a stream that BlueOS
or mavlink-router sends there; 14550 belongs to the ground station), ``udpout:HOST:PORT``, ``tcp:HOST:PORT``,
a serial device. The source only listens: it requests no streams, so the autopilot (or BlueOS) must already
send these messages, as ArduSub does for a ground station:

* ``ATTITUDE``: roll, pitch, yaw in radians (Fossen ZYX, as ours) at ``time_boot_ms``: attitude samples;
* ``GLOBAL_POSITION_INT``: ``relative_alt`` in mm, negative below the surface: depth ``-relative_alt / 1000``
  at ``time_boot_ms``; ``VFR_HUD.alt`` (m, negative below) serves instead while no ``GLOBAL_POSITION_INT``
  has arrived. ``VFR_HUD`` carries no time, so it is stamped with the autopilot time estimated from the last
  timed message plus the host time elapsed since it arrived;
* ``LOCAL_POSITION_NED``: ``x``, ``y`` (m, north and east from the EKF origin) at ``time_boot_ms``:
  horizontal fixes, only when the autopilot has a position source (DVL, USBL). Without it every pose has
  attitude and depth only, and its cloud travels with ``north_m``/``east_m`` null;
* ``SYSTEM_TIME``: ``time_unix_usec`` and ``time_boot_ms`` map the autopilot's boot clock to Unix time:
  ``t_ns = time_boot_ms * 1e6 + offset``, the offset the smallest ``time_unix_usec * 1000 - time_boot_ms *
  1e6`` of the last :data:`OFFSET_WINDOW` messages (``time_boot_ms`` is truncated to the millisecond, so the
  smallest is the closest). A message with ``time_unix_usec`` 0 (the autopilot's clock is not set) is not
  used. The autopilot's Unix time must agree with the camera host's clock (BlueOS sets both from the
  companion computer); the frames are stamped on the host.

Samples that arrive before the first usable ``SYSTEM_TIME`` are **held** (the last :data:`HOLD_S` seconds of
them, by autopilot time) and placed on the track when it arrives; older held ones are dropped and counted.
Messages are taken from one autopilot only: the first system whose ``HEARTBEAT`` names an autopilot (not a
ground station); messages before it, and from other systems, are ignored and counted. A ``time_boot_ms``
that goes back by more than a second means the autopilot rebooted: the clock mapping starts over.

The track keeps at least the last :data:`KEEP_S` seconds of samples, so a frame processed late (or replayed
while the stream runs) is posed from the samples around its capture time. Two attitude (or depth) samples
more than ``stale_s`` apart are never interpolated between, and a frame after the last sample waits at most
the ROV's live wait for the next one: a stale or silent link gives no pose (the ROV counts and logs the
skipped frames), never an old one. The reader logs when the link falls silent and when it comes back.

pymavlink is an optional dependency (``pip install 'lrsensor[mavlink]'``), imported when the source opens;
``MAVLINK20=1`` is set before the import, or ``mavutil`` would speak MAVLink 1.
"""

from __future__ import annotations

import collections
import logging
import math
import os
import threading
import time
from dataclasses import dataclass
from types import TracebackType
from typing import Any

from .errors import ImuError
from .posetrack import PoseTrack

log = logging.getLogger(__name__)

#: Seconds of samples the track keeps at least (a frame processed this late is still posed).
KEEP_S = 120.0
#: Default staleness limit, seconds: attitude or depth samples further apart are not interpolated between.
DEFAULT_STALE_S = 1.0
#: Seconds of samples held (by autopilot time) while the clock mapping is not known yet.
HOLD_S = 60.0
#: SYSTEM_TIME messages whose offsets are compared (the smallest wins).
OFFSET_WINDOW = 16
#: A SYSTEM_TIME offset further than this from the current one resets the mapping (clock set), ns.
OFFSET_JUMP_NS = 1_000_000_000
#: A time_boot_ms that goes back by more than this means the autopilot rebooted, ms.
REBOOT_BACKSTEP_MS = 1_000
#: Upper bound on samples per series kept (memory guard against a runaway stream).
MAX_SAMPLES = 200_000
_MAV_AUTOPILOT_INVALID = 8
_MAV_TYPE_GCS = 6
MESSAGE_TYPES = (
    "HEARTBEAT",
    "SYSTEM_TIME",
    "ATTITUDE",
    "GLOBAL_POSITION_INT",
    "VFR_HUD",
    "LOCAL_POSITION_NED",
)


@dataclass
class MavlinkCounters:
    """What the MAVLink source received and what it did with it."""

    messages: int = 0
    attitude: int = 0
    depth: int = 0
    fixes: int = 0
    ignored: int = 0
    rejected: int = 0
    held: int = 0
    dropped_held: int = 0
    silences: int = 0
    reboots: int = 0


class MavlinkPoseAssembler:
    """Turns MAVLink messages into samples of a :class:`PoseTrack` (no I/O: the reader thread, or a test,
    feeds it messages with their host receive time).

    Args:
        track: where the samples go.
    """

    def __init__(self, track: PoseTrack) -> None:
        self.track = track
        self.counters = MavlinkCounters()
        self.system: tuple[int, int] | None = None
        self.offset_ns: int | None = None
        self._offsets: collections.deque[int] = collections.deque(maxlen=OFFSET_WINDOW)
        self._held: collections.deque[tuple[str, int, tuple[float, ...]]] = collections.deque()
        self._last_boot_ms: int | None = None
        self._last_boot_host_s = 0.0
        self._have_gpi = False
        self._warned_unset_clock = False

    # ------------------------------------------------------------------ input
    def feed(self, msg: Any, host_s: float) -> None:
        """Take one pymavlink message received at host monotonic time ``host_s``."""
        self.counters.messages += 1
        kind = msg.get_type()
        if kind == "BAD_DATA":
            self.counters.rejected += 1
            return
        src = (int(msg.get_srcSystem()), int(msg.get_srcComponent()))
        if kind == "HEARTBEAT":
            if self.system is None and msg.autopilot != _MAV_AUTOPILOT_INVALID and msg.type != _MAV_TYPE_GCS:
                self.system = src
                log.info("MAVLink: taking poses from system %d component %d", *src)
            return
        if self.system is None or src != self.system:
            self.counters.ignored += 1
            return
        boot_ms = getattr(msg, "time_boot_ms", None)
        if boot_ms is not None:
            self._note_boot(int(boot_ms), host_s)
        if kind == "SYSTEM_TIME":
            self._system_time(int(msg.time_unix_usec), int(msg.time_boot_ms))
        elif kind == "ATTITUDE":
            self._sample("attitude", int(msg.time_boot_ms), (float(msg.roll), float(msg.pitch), float(msg.yaw)))
        elif kind == "GLOBAL_POSITION_INT":
            self._have_gpi = True
            self._sample("depth", int(msg.time_boot_ms), (-float(msg.relative_alt) / 1000.0,))
        elif kind == "VFR_HUD":
            if not self._have_gpi and self._last_boot_ms is not None:
                est_ms = self._last_boot_ms + round((host_s - self._last_boot_host_s) * 1000.0)
                self._sample("depth", est_ms, (-float(msg.alt),))
        elif kind == "LOCAL_POSITION_NED":
            self._sample("fix", int(msg.time_boot_ms), (float(msg.x), float(msg.y)))

    def _note_boot(self, boot_ms: int, host_s: float) -> None:
        last = self._last_boot_ms
        if last is not None and boot_ms < last - REBOOT_BACKSTEP_MS:
            self.counters.reboots += 1
            log.warning("MAVLink: autopilot clock went back from %d to %d ms (reboot?): re-syncing", last, boot_ms)
            self.offset_ns = None
            self._offsets.clear()
            self._held.clear()
        if last is None or boot_ms >= last or boot_ms < last - REBOOT_BACKSTEP_MS:
            self._last_boot_ms = boot_ms
            self._last_boot_host_s = host_s

    def _system_time(self, unix_us: int, boot_ms: int) -> None:
        if unix_us <= 0:
            if not self._warned_unset_clock:
                self._warned_unset_clock = True
                log.warning("MAVLink: SYSTEM_TIME without Unix time (the autopilot's clock is not set): waiting")
            return
        offset = unix_us * 1000 - boot_ms * 1_000_000
        if self.offset_ns is not None and abs(offset - self.offset_ns) > OFFSET_JUMP_NS:
            log.warning("MAVLink: the autopilot's Unix time jumped by %.3f s", (offset - self.offset_ns) / 1e9)
            self._offsets.clear()
        self._offsets.append(offset)
        first = self.offset_ns is None
        self.offset_ns = min(self._offsets)
        if first:
            log.info("MAVLink: autopilot clock mapped to Unix time (%d samples held until now)", len(self._held))
            held, self._held = list(self._held), collections.deque()
            for kind, ms, values in held:
                self._put(kind, ms, values)

    def _sample(self, kind: str, boot_ms: int, values: tuple[float, ...]) -> None:
        if not all(math.isfinite(v) for v in values):
            self.counters.rejected += 1
            return
        if self.offset_ns is None:
            self.counters.held += 1
            self._held.append((kind, boot_ms, values))
            while self._held and self._held[0][1] < boot_ms - HOLD_S * 1000:
                self._held.popleft()
                self.counters.dropped_held += 1
            return
        self._put(kind, boot_ms, values)

    def _put(self, kind: str, boot_ms: int, values: tuple[float, ...]) -> None:
        assert self.offset_ns is not None
        t_ns = boot_ms * 1_000_000 + self.offset_ns
        if kind == "attitude":
            ok = self.track.add_attitude(t_ns, *values)
            self.counters.attitude += ok
        elif kind == "depth":
            ok = self.track.add_depth(t_ns, values[0])
            self.counters.depth += ok
        else:
            ok = self.track.add_fix(t_ns, values[0], values[1])
            self.counters.fixes += ok
        if not ok:
            self.counters.rejected += 1

    def to_unix_ns(self, boot_ms: int) -> int | None:
        """The Unix time (ns) of an autopilot ``time_boot_ms``, or None while the mapping is unknown."""
        return None if self.offset_ns is None else boot_ms * 1_000_000 + self.offset_ns


def _import_mavutil() -> Any:
    os.environ.setdefault("MAVLINK20", "1")  # before the import, or mavutil loads MAVLink 1
    try:
        from pymavlink import mavutil
    except ImportError as err:
        msg = f"--imu mavlink: needs pymavlink (pip install 'lrsensor[mavlink]' or 'pymavlink>=2.4'): {err}"
        raise ImuError(msg) from err
    return mavutil


class MavlinkImu:
    """A live MAVLink stream (see the module docstring) read by a background thread.

    Args:
        connection: a pymavlink connection string (``udpin:127.0.0.1:14551``).
        stale_s: staleness limit: attitude or depth samples further apart are not interpolated between, and
            a link silent for longer is reported.
    """

    live = True

    def __init__(self, connection: str, stale_s: float = DEFAULT_STALE_S) -> None:
        if not connection:
            msg = "mavlink IMU: no connection given (mavlink:udpin:127.0.0.1:14551)"
            raise ImuError(msg)
        if not stale_s > 0:
            msg = f"mavlink IMU: the staleness limit must be positive, got {stale_s}"
            raise ImuError(msg)
        self.connection = connection
        self.stale_s = stale_s
        self.name = f"mavlink:{connection}"
        self.track = PoseTrack(MAX_SAMPLES, keep_s=KEEP_S, max_gap_s=stale_s)
        self.assembler = MavlinkPoseAssembler(self.track)
        self._conn: Any = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.read_errors = 0

    @property
    def counters(self) -> MavlinkCounters:
        """What the source received and did (see :class:`MavlinkCounters`)."""
        return self.assembler.counters

    @property
    def rejected(self) -> int:
        """Messages refused: bad data (CRC), non-finite values, samples out of time order."""
        return self.assembler.counters.rejected

    def __enter__(self) -> MavlinkImu:
        mavutil = _import_mavutil()
        try:
            self._conn = mavutil.mavlink_connection(self.connection, source_system=255, source_component=0)
        except Exception as err:  # pymavlink raises OSError, ValueError, serial errors...
            msg = f"mavlink IMU {self.connection}: cannot open: {err}"
            raise ImuError(msg) from err
        self._thread = threading.Thread(target=self._read_loop, name=f"imu-{self.name}", daemon=True)
        self._thread.start()
        log.info("MAVLink pose source listening on %s (staleness limit %.2f s)", self.connection, self.stale_s)
        return self

    def _read_loop(self) -> None:
        conn = self._conn
        last_rx = time.monotonic()
        silent = False
        while not self._stop.is_set():
            try:
                msg = conn.recv_match(blocking=True, timeout=0.1)
            except Exception as err:
                self.read_errors += 1
                log.warning("mavlink IMU %s: read failed: %s", self.connection, err)
                if self._stop.wait(0.5):
                    break
                continue
            now = time.monotonic()
            if msg is None:
                if not silent and now - last_rx > self.stale_s:
                    silent = True
                    self.assembler.counters.silences += 1
                    log.warning(
                        "mavlink IMU %s: no message for %.1f s: frames get no pose until it is back",
                        self.connection,
                        now - last_rx,
                    )
                continue
            if silent:
                silent = False
                log.warning("mavlink IMU %s: messages again after %.1f s", self.connection, now - last_rx)
            last_rx = now
            self.assembler.feed(msg, now)

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        if self._conn is not None:
            self._conn.close()
        c = self.counters
        log.info(
            "mavlink IMU %s: %d messages, %d attitude, %d depth, %d fixes, %d ignored, %d rejected, %d silences",
            self.connection,
            c.messages,
            c.attitude,
            c.depth,
            c.fixes,
            c.ignored,
            c.rejected,
            c.silences,
        )
