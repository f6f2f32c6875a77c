"""IMU / navigation sources of an ROV: simulated, a CSV log, or a serial port speaking OpenROV telemetry.

Every source fills a :class:`~services.posetrack.PoseTrack` that the frame loop queries at each capture time.

* ``sim``: the simulator's trajectory with IMU noise (built by the frame source, see :mod:`services.sources`).
* ``csv:FILE``: header ``t_ns,roll_deg,pitch_deg,yaw_deg,north_m,east_m,down_m``, one sample per row;
  ``north_m`` and ``east_m`` both empty: that sample has attitude and depth but no horizontal fix.
* ``serial:PORT[@BAUD]``: a pyserial URL or device (``/dev/ttyUSB0``, ``loop://``, ``socket://...``) streaming
  OpenROV telemetry lines ``hdgd:<deg>;deep:<m>;pitc:<deg>;roll:<deg>;...``: heading is yaw, depth is down;
  no horizontal fix (OpenROV has none). Samples are stamped with the host receive time.
* ``mavlink:CONNECTION``: an ArduSub autopilot over MAVLink (:mod:`services.imu_mavlink`).

No source invents a horizontal position: where a sample has no fix the track knows none
(:mod:`services.posetrack` says how a frame's position is then interpolated or left unknown).

Malformed input is never fatal for a running source: each bad line is logged once with its reason and
counted in ``rejected`` (issue 7 surfaces the counters); only an unusable file (no header, no valid row)
raises :class:`~services.errors.ImuError`.
"""

from __future__ import annotations

import csv
import decimal
import logging
import math
import re
import threading
import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any, Protocol

from lrsensor.frames import Pose

from .errors import ImuError
from .posetrack import PoseTrack, has_fix

log = logging.getLogger(__name__)

CSV_HEADER = ("t_ns", "roll_deg", "pitch_deg", "yaw_deg", "north_m", "east_m", "down_m")
DEFAULT_BAUD = 115200
#: Longest accepted telemetry line, bytes; a longer run without newline is dropped as garbage.
MAX_LINE_BYTES = 1024
#: Samples kept by a live (serial) source: ~10 min at 50 Hz.
LIVE_TRACK_SAMPLES = 30_000


class ImuSource(Protocol):
    """What the ROV loop needs from an IMU: a pose track, liveness, counters, and a context."""

    track: PoseTrack
    live: bool

    @property
    def rejected(self) -> int: ...

    def __enter__(self) -> Any: ...

    def __exit__(self, *exc: Any) -> None: ...


class TrackImu:
    """An IMU whose whole track is known in advance (simulated dives, tests)."""

    live = False

    def __init__(self, track: PoseTrack, name: str = "track") -> None:
        self.track = track
        self.name = name

    @property
    def rejected(self) -> int:
        """Samples refused while building the track."""
        return self.track.rejected

    def __enter__(self) -> TrackImu:
        return self

    def __exit__(self, *exc: object) -> None:
        return None


# --------------------------------------------------------------------------- CSV logs
class CsvImu(TrackImu):
    """A recorded navigation log (CSV with :data:`CSV_HEADER`); bad rows are skipped and counted."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.bad_rows = 0
        track = PoseTrack()
        try:
            fh = self.path.open(newline="", encoding="utf-8")
        except OSError as err:
            msg = f"{self.path}: cannot open IMU log: {err.strerror or err}"
            raise ImuError(msg) from err
        with fh:
            reader = csv.reader(fh)
            try:
                header = next(reader)
            except StopIteration:
                msg = f"{self.path}: IMU log is empty (expected header {','.join(CSV_HEADER)})"
                raise ImuError(msg) from None
            except (csv.Error, UnicodeDecodeError) as err:
                msg = f"{self.path}: IMU log header unreadable: {err}"
                raise ImuError(msg) from err
            header = [h.strip() for h in header]
            missing = [h for h in CSV_HEADER if h not in header]
            if missing:
                msg = f"{self.path}: IMU log header lacks {missing}; expected {','.join(CSV_HEADER)}"
                raise ImuError(msg)
            col = {h: header.index(h) for h in CSV_HEADER}
            line = 1
            try:
                for row in reader:
                    line += 1
                    if not row or all(not c.strip() for c in row):
                        continue
                    reason = self._add_row(track, row, col)
                    if reason:
                        self.bad_rows += 1
                        if self.bad_rows <= 5:
                            log.warning("%s:%d: IMU row rejected: %s", self.path, line, reason)
            except (csv.Error, UnicodeDecodeError) as err:
                self.bad_rows += 1
                log.warning("%s:%d: IMU log unreadable from here on: %s", self.path, line, err)
        if len(track) == 0:
            msg = f"{self.path}: IMU log has no valid sample ({self.bad_rows} rows rejected)"
            raise ImuError(msg)
        if self.bad_rows:
            log.warning("%s: %d IMU rows rejected in total", self.path, self.bad_rows)
        super().__init__(track, f"csv:{self.path}")

    @property
    def rejected(self) -> int:
        """Rows refused (malformed, non-finite, or not after the previous sample)."""
        return self.bad_rows

    @staticmethod
    def _add_row(track: PoseTrack, row: list[str], col: dict[str, int]) -> str | None:
        try:
            t_ns = _parse_t_ns(row[col["t_ns"]])
            empty = {h for h in ("north_m", "east_m") if not row[col[h]].strip()}
            v = {h: math.nan if h in empty else float(row[col[h]]) for h in CSV_HEADER[1:]}
        except (ValueError, IndexError) as err:
            return f"malformed row {row!r}: {err}"
        if len(empty) == 1:
            return f"{empty.pop()} is empty but not the other horizontal coordinate in {row!r}"
        if not all(math.isfinite(x) for h, x in v.items() if h not in empty):
            return f"non-finite value in {row!r}"
        if t_ns < 0:
            return f"t_ns must not be negative, got {t_ns}"
        pose = Pose(
            v["north_m"],
            v["east_m"],
            v["down_m"],
            math.radians(v["roll_deg"]),
            math.radians(v["pitch_deg"]),
            math.radians(v["yaw_deg"]),
        )
        if not track.append(t_ns, pose):
            return f"t_ns {t_ns} is not after the previous sample"
        return None


def _parse_t_ns(text: str) -> int:
    """Integer ns since the epoch; a decimal like ``1700000000000000000.0`` is accepted when it is integral."""
    t = text.strip()
    try:
        return int(t)
    except ValueError:
        try:
            d = decimal.Decimal(t)
        except decimal.InvalidOperation:
            msg = f"t_ns {t!r} is not a number"
            raise ValueError(msg) from None
        if not d.is_finite() or d != d.to_integral_value():
            msg = f"t_ns {t!r} is not an integer number of nanoseconds"
            raise ValueError(msg) from None
        return int(d)


def write_csv(path: str | Path, t_ns: list[int], poses: list[Pose]) -> None:
    """Write a navigation log in the format :class:`CsvImu` reads (degrees for angles; a pose without a
    horizontal fix, NaN ``north_m``/``east_m``, leaves both empty)."""
    with Path(path).open("w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(CSV_HEADER)
        for t, p in zip(t_ns, poses, strict=True):
            w.writerow(
                [
                    int(t),
                    repr(math.degrees(p.roll_rad)),
                    repr(math.degrees(p.pitch_rad)),
                    repr(math.degrees(p.yaw_rad)),
                    repr(p.north_m) if has_fix(p) else "",
                    repr(p.east_m) if has_fix(p) else "",
                    repr(p.down_m),
                ]
            )


# --------------------------------------------------------------------------- OpenROV telemetry
@dataclass(frozen=True)
class OpenRovReading:
    """One attitude/depth reading: angles in radians, depth (down) in metres."""

    roll_rad: float
    pitch_rad: float
    yaw_rad: float
    down_m: float

    def pose(self) -> Pose:
        """As a pose without a horizontal fix (``north_m``/``east_m`` NaN: OpenROV has no position)."""
        return Pose(math.nan, math.nan, self.down_m, self.roll_rad, self.pitch_rad, self.yaw_rad)


_KEY_RE = re.compile(r"^[A-Za-z][A-Za-z0-9_]{0,31}$")
#: Telemetry key -> (field, accepted range in its unit).
_OPENROV_FIELDS: dict[str, tuple[str, float, float]] = {
    "hdgd": ("yaw", -360.0, 720.0),
    "pitc": ("pitch", -180.0, 180.0),
    "roll": ("roll", -180.0, 180.0),
    "deep": ("down", -50.0, 12_000.0),
}


class OpenRovParser:
    """Incremental parser of OpenROV telemetry bytes: partial lines are kept, garbage is counted.

    Lines are ``key:value;key:value;...`` terminated by ``\\n`` (``\\r`` ignored). A line that is not
    ASCII, has a part without ``:``, a bad key, a non-numeric or non-finite value, or an attitude/depth value
    out of range is rejected as a whole. Keys other than ``hdgd``, ``deep``, ``pitc``, ``roll`` are accepted and
    ignored. A reading is emitted for every line that updates one of the four once all four have been seen.
    """

    def __init__(self, max_line_bytes: int = MAX_LINE_BYTES) -> None:
        self._buf = bytearray()
        self._max = max_line_bytes
        self._last: dict[str, float] = {}
        self.lines = 0
        self.rejected = 0
        self.reasons: Counter[str] = Counter()

    def _reject(self, reason: str, line: bytes) -> None:
        self.rejected += 1
        self.reasons[reason] += 1
        if self.reasons[reason] <= 3:
            log.warning("telemetry line rejected (%s): %r", reason, bytes(line[:80]))

    def feed(self, data: bytes) -> list[OpenRovReading]:
        """Add received bytes; return the readings of the lines completed by them."""
        self._buf.extend(data)
        out: list[OpenRovReading] = []
        while True:
            nl = self._buf.find(b"\n")
            if nl < 0:
                if len(self._buf) > self._max:
                    self._reject("line too long", bytes(self._buf))
                    self._buf.clear()
                break
            line = bytes(self._buf[:nl])
            del self._buf[: nl + 1]
            if len(line) > self._max:
                self._reject("line too long", line)
                continue
            reading = self.parse_line(line)
            if reading is not None:
                out.append(reading)
        return out

    def parse_line(self, line: bytes) -> OpenRovReading | None:
        """Parse one line (without its newline); returns a reading or None (rejected or not attitude)."""
        text_b = line.strip(b"\r \t\x00")
        if not text_b:
            return None
        self.lines += 1
        try:
            text = text_b.decode("ascii")
        except UnicodeDecodeError:
            self._reject("not ASCII", line)
            return None
        values: dict[str, float] = {}
        for part in text.split(";"):
            part = part.strip()
            if not part:
                continue
            key, sep, raw = part.partition(":")
            if not sep or not _KEY_RE.match(key):
                self._reject("not key:value", line)
                return None
            if key not in _OPENROV_FIELDS:
                continue
            try:
                value = float(raw)
            except ValueError:
                self._reject(f"bad number for {key}", line)
                return None
            _, lo, hi = _OPENROV_FIELDS[key]
            if not math.isfinite(value) or not lo <= value <= hi:
                self._reject(f"{key} out of range", line)
                return None
            values[key] = value
        if not values:
            return None
        self._last.update(values)
        if len(self._last) < len(_OPENROV_FIELDS):
            return None
        v = self._last
        yaw_deg = (v["hdgd"] + 180.0) % 360.0 - 180.0
        return OpenRovReading(math.radians(v["roll"]), math.radians(v["pitc"]), math.radians(yaw_deg), v["deep"])


def parse_serial_spec(spec: str) -> tuple[str, int]:
    """``PORT[@BAUD]`` -> (port or pyserial URL, baud)."""
    port, sep, baud_s = spec.rpartition("@") if "@" in spec else (spec, "", "")
    if not sep:
        port = spec
    if not port:
        msg = f"serial IMU {spec!r}: no port given (serial:PORT[@BAUD])"
        raise ImuError(msg)
    baud = DEFAULT_BAUD
    if sep:
        try:
            baud = int(baud_s)
        except ValueError:
            msg = f"serial IMU {spec!r}: baud rate {baud_s!r} is not an integer"
            raise ImuError(msg) from None
        if baud <= 0:
            msg = f"serial IMU {spec!r}: baud rate must be positive"
            raise ImuError(msg)
    return port, baud


class SerialImu:
    """A live OpenROV telemetry stream read by a background thread (pyserial).

    Args:
        port: device path or pyserial URL (``loop://``, ``socket://host:port``, ``/dev/ttyUSB0``).
        baud: baud rate.
        serial_port: an already open pyserial port to read instead of opening ``port`` (tests).
    """

    live = True

    def __init__(self, port: str, baud: int = DEFAULT_BAUD, serial_port: Any | None = None) -> None:
        self.port = port
        self.baud = baud
        self.track = PoseTrack(max_samples=LIVE_TRACK_SAMPLES)
        self.parser = OpenRovParser()
        self._serial = serial_port
        self._own = serial_port is None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.read_errors = 0
        self._last_t_ns = 0

    @property
    def rejected(self) -> int:
        """Telemetry lines refused by the parser."""
        return self.parser.rejected

    def __enter__(self) -> SerialImu:
        if self._serial is None:
            import serial  # pyserial

            try:
                self._serial = serial.serial_for_url(self.port, baudrate=self.baud, timeout=0.1)
            except (serial.SerialException, ValueError, OSError) as err:
                msg = f"serial IMU {self.port}@{self.baud}: cannot open: {err}"
                raise ImuError(msg) from err
        self._thread = threading.Thread(target=self._read_loop, name=f"imu-{self.port}", daemon=True)
        self._thread.start()
        return self

    def _read_loop(self) -> None:
        assert self._serial is not None
        while not self._stop.is_set():
            try:
                waiting = int(getattr(self._serial, "in_waiting", 0) or 0)
                data = self._serial.read(max(1, min(waiting, 4096)))
            except Exception as err:
                self.read_errors += 1
                log.warning("serial IMU %s: read failed: %s", self.port, err)
                if self._stop.wait(0.5):
                    break
                continue
            if not data:
                continue
            t_ns = time.time_ns()
            for reading in self.parser.feed(data):
                # readings completed by the same chunk share a receive time: keep the stamps increasing
                t_ns = max(t_ns, self._last_t_ns + 1)
                self._last_t_ns = t_ns
                self.track.append(t_ns, reading.pose())

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        if self._own and self._serial is not None:
            self._serial.close()


def open_imu(spec: str, stale_s: float | None = None) -> ImuSource:
    """An IMU source from its command-line spec: ``csv:FILE``, ``serial:PORT[@BAUD]`` or
    ``mavlink:CONNECTION`` (``stale_s``: its staleness limit, seconds; None: the default).

    ``sim`` is not handled here: the simulated IMU comes with the simulated frame source.
    """
    kind, _, arg = spec.partition(":")
    if kind == "csv" and arg:
        return CsvImu(arg)
    if kind == "serial" and arg:
        port, baud = parse_serial_spec(arg)
        return SerialImu(port, baud)
    if kind == "mavlink" and arg:
        from .imu_mavlink import DEFAULT_STALE_S, MavlinkImu

        return MavlinkImu(arg, DEFAULT_STALE_S if stale_s is None else stale_s)
    msg = f"unknown IMU {spec!r}: use sim, csv:FILE, serial:PORT[@BAUD] or mavlink:CONNECTION"
    raise ImuError(msg)
