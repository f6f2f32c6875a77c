"""An ArduSub-like MAVLink sender for the tests: a thread that plays, with pymavlink on loopback UDP, what a
BlueROV2's autopilot sends, from known truth (attitude, depth, position as functions of Unix time).

Rates (ArduSub's streams as a ground station gets them): HEARTBEAT 1 Hz, SYSTEM_TIME 1 Hz (first one 0.5 s in,
so the samples before it are held by the receiver), ATTITUDE 25 Hz, GLOBAL_POSITION_INT 5 Hz, VFR_HUD 5 Hz,
LOCAL_POSITION_NED 5 Hz (only with ``local_position=True``: a DVL or USBL).
"""

from __future__ import annotations

import math
import os
import socket
import threading
import time
from dataclasses import dataclass, field

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil

#: The autopilot had been up this long when the sender started, seconds.
UPTIME_S = 123.456
RATES_HZ = {
    "HEARTBEAT": 1.0,
    "SYSTEM_TIME": 1.0,
    "ATTITUDE": 25.0,
    "GLOBAL_POSITION_INT": 5.0,
    "VFR_HUD": 5.0,
    "LOCAL_POSITION_NED": 5.0,
}
PHASE_S = {"SYSTEM_TIME": 0.5}


def free_udp_port() -> int:
    """A UDP port on 127.0.0.1 that was free a moment ago."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@dataclass(frozen=True)
class Truth:
    """The dive the sender plays: angles in rad, depth and position in m, functions of seconds since ``t0_ns``."""

    t0_ns: int

    def s(self, t_ns: int) -> float:
        return (t_ns - self.t0_ns) / 1e9

    def attitude(self, t_ns: int) -> tuple[float, float, float]:
        s = self.s(t_ns)
        yaw = (1.0 + 0.2 * s + math.pi) % (2 * math.pi) - math.pi
        return 0.05 * math.sin(0.5 * s), 0.03 * math.cos(0.4 * s), yaw

    def depth_m(self, t_ns: int) -> float:
        return 1.5 + 0.1 * self.s(t_ns)

    def north_east_m(self, t_ns: int) -> tuple[float, float]:
        s = self.s(t_ns)
        return 0.3 * s, -0.1 * s


@dataclass
class Sent:
    """One message sent: its type, ``time_boot_ms`` and the Unix time (ns) that boot time truly is."""

    kind: str
    boot_ms: int
    unix_ns: int


@dataclass
class ArduSubSender:
    """Sends to ``udpout:127.0.0.1:PORT`` from a thread until :meth:`stop` (or :meth:`pause`)."""

    port: int
    local_position: bool = False
    sent: list[Sent] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.boot_epoch_ns = time.time_ns() - int(UPTIME_S * 1e9)
        self.truth = Truth(time.time_ns())
        self.conn = mavutil.mavlink_connection(f"udpout:127.0.0.1:{self.port}", source_system=1, source_component=1)
        self._stop = threading.Event()
        self._paused = threading.Event()
        self.lock = threading.Lock()
        self._sending = threading.Lock()
        self.thread = threading.Thread(target=self._run, name="ardusub-sender", daemon=True)

    def start(self) -> ArduSubSender:
        self.thread.start()
        return self

    def pause(self) -> None:
        """Fall silent (the link is cut) until :meth:`resume`; nothing is sent once this returns."""
        with self._sending:
            self._paused.set()

    def resume(self) -> None:
        self._paused.clear()

    def stop(self) -> None:
        self._stop.set()
        self.thread.join(5)
        self.conn.close()

    def last_unix_ns(self) -> int:
        with self.lock:
            return self.sent[-1].unix_ns if self.sent else 0

    def of(self, kind: str) -> list[Sent]:
        with self.lock:
            return [m for m in self.sent if m.kind == kind]

    def _run(self) -> None:
        kinds = [k for k in RATES_HZ if self.local_position or k != "LOCAL_POSITION_NED"]
        start = time.monotonic()
        due = {k: start + PHASE_S.get(k, 0.0) for k in kinds}
        while not self._stop.is_set():
            kind = min(kinds, key=lambda k: due[k])
            wait = due[kind] - time.monotonic()
            if wait > 0 and self._stop.wait(wait):
                return
            due[kind] += 1.0 / RATES_HZ[kind]
            with self._sending:
                if not self._paused.is_set():
                    self._send(kind)

    def _send(self, kind: str) -> None:
        now_ns = time.time_ns()
        boot_ms = (now_ns - self.boot_epoch_ns) // 1_000_000
        t_ns = self.boot_epoch_ns + boot_ms * 1_000_000  # the instant time_boot_ms stands for
        mav = self.conn.mav
        tr = self.truth
        if kind == "HEARTBEAT":
            mav.heartbeat_send(
                mavutil.mavlink.MAV_TYPE_SUBMARINE, mavutil.mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, 209, 19, 4
            )
        elif kind == "SYSTEM_TIME":
            mav.system_time_send(now_ns // 1000, boot_ms)
        elif kind == "ATTITUDE":
            mav.attitude_send(boot_ms, *tr.attitude(t_ns), 0.0, 0.0, 0.2)
        elif kind == "GLOBAL_POSITION_INT":
            rel_mm = round(-tr.depth_m(t_ns) * 1000)
            mav.global_position_int_send(boot_ms, 0, 0, 10_000 + rel_mm, rel_mm, 0, 0, 10, 9000)
        elif kind == "VFR_HUD":
            mav.vfr_hud_send(0.0, 0.1, 90, 50, -tr.depth_m(t_ns), -0.1)
        elif kind == "LOCAL_POSITION_NED":
            n, e = tr.north_east_m(t_ns)
            mav.local_position_ned_send(boot_ms, n, e, tr.depth_m(t_ns), 0.3, -0.1, 0.1)
        with self.lock:
            self.sent.append(Sent(kind, int(boot_ms), int(t_ns)))
