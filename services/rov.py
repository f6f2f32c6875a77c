"""The ROV service: frames + IMU -> pose-tagged clouds published over Zenoh.

Per frame: the pose at the frame's capture time is interpolated from the IMU track (frames it cannot pose,
outside its span or in a silent link's gap, are skipped and counted, with a warning), the image goes
through :meth:`lrsensor.Sensor.process`, and the scan is published with BLOCK congestion control (never
dropped silently) as a compact :class:`~services.wire.StripeMsg` (cloud schema 2, the default: the stripe's
pixels, triangulated at the base with the calibration whose fingerprint it carries) or, with ``cloud_schema=1``, as a
:class:`~services.wire.CloudMsg` of float32 points. A scan that schema 2 cannot carry (columns that are not
whole pixels, as the paper's Algorithm 1 measures) goes out as schema 1, with a warning the first time.
While running the ROV holds its liveliness token ``<root>/<robot>/alive``, serves its calibration on
``<root>/<robot>/calib`` and publishes :class:`~services.wire.StatusMsg` counters on ``<root>/<robot>/status``
(with an outbox sink, also its link-budget counters: live, queued, forwarded, dropped by the budget).

A frame whose pose has attitude and depth but no horizontal fix (see :mod:`services.posetrack`) is still
processed and published, its pose's ``north_m``/``east_m`` null: the base station counts it as unplaced
instead of mapping it at a made-up position. The ROV counts such clouds (``unplaced`` in its status and
summary) and says so in its log once, then every 100th.

The sub-pixel extractor reads a compressed source's frames (a video file, a camera stream: colour stored at half
resolution) on the luma channel unless ``--channel`` was given (:func:`channel_choice`); the log says which.

This module does not import Open3D (the ROV install does not have it).
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, Protocol

from lrsensor.calibration import Calibration
from lrsensor.errors import LrsensorError
from lrsensor.extract import DEFAULT_METHOD
from lrsensor.extract.compile import ready as extractor_compiled
from lrsensor.frames import Pose
from lrsensor.scan import Scan
from lrsensor.sensor import Sensor

from .errors import CalibrationUnavailableError, WireError
from .imu import ImuSource
from .keys import FleetKeys, check_robot_name
from .posetrack import has_fix
from .sources import FrameSource
from .wallclock import wall_clock_ns
from .wire import CLOUD_SCHEMAS, ENCODING, AnyCloud, CalibMsg, CloudMsg, StatusMsg, StripeMsg, calibration_fingerprint

log = logging.getLogger(__name__)

#: How long a live frame waits for the IMU to catch up with its capture time, seconds: more than the period
#: of a 4 Hz depth or position message (a silent source is not waited for: see PoseTrack.wait_covering).
LIVE_IMU_WAIT_S = 0.5


@dataclass
class RovCounters:
    """Counters of one ROV run (also its final summary)."""

    frames: int = 0
    published: int = 0
    skipped: int = 0
    unplaced: int = 0
    failed: int = 0
    first_seq: int = -1
    last_seq: int = -1
    delivered: bool | None = None
    points: int = 0
    started_ns: int = field(default_factory=time.time_ns)

    def summary(self, robot: str) -> str:
        """The final one-line summary."""
        d = {None: "unknown", True: "confirmed", False: "NOT confirmed"}[self.delivered]
        return (
            f"rov {robot}: frames {self.frames}, published {self.published}, skipped (no pose) {self.skipped}, "
            f"no horizontal fix {self.unplaced}, failed {self.failed}, points {self.points}, delivery {d}"
        )


def channel_choice(
    source: object, method: str | None, process_options: Mapping[str, Any]
) -> tuple[dict[str, Any], str]:
    """The extractor options for ``source``'s frames and why: the sub-pixel extractor reads a ``compressed``
    source (JPEG/H.264: colour at half resolution) on the luma channel unless the options already name one."""
    options = dict(process_options)
    if (method or DEFAULT_METHOD) != "subpixel":
        return options, f"extractor {method} (no channel option)"
    if "channel" in options:
        return options, f"channel {options['channel']} (given with --channel)"
    if getattr(source, "compressed", False):
        options["channel"] = "luma"
        return options, "channel luma (compressed frames store colour at half resolution; --channel green overrides)"
    return options, "channel green (the default for uncompressed frames)"


class CloudSink(Protocol):
    """Where the ROV puts its clouds (a Zenoh publisher; issue 7 puts an outbox in front of it)."""

    def send(self, msg: AnyCloud) -> None: ...


class ZenohCloudSink:
    """Publishes clouds on ``<root>/<robot>/cloud``: reliable, BLOCK congestion control, msgpack."""

    def __init__(self, session: Any, key: str) -> None:
        import zenoh

        self.publisher = session.declare_publisher(
            key,
            encoding=zenoh.Encoding(ENCODING),
            congestion_control=zenoh.CongestionControl.BLOCK,
            reliability=zenoh.Reliability.RELIABLE,
            priority=zenoh.Priority.DATA_LOW,  # below status and queries (docs/reliability.md)
        )

    def send(self, msg: AnyCloud) -> None:
        """Publish one cloud (stamped with its publication time)."""
        self.publisher.put(msg.with_sent_ns(wall_clock_ns()).to_bytes())


def fetch_calibration(
    session: Any, keys: FleetKeys, robot: str, timeout_s: float = 10.0, stop: threading.Event | None = None
) -> Calibration:
    """Ask the base station's fleet calibration queryable for ``robot``'s calibration, with retries.

    Raises :class:`CalibrationUnavailableError` when the base station answers that it has none, or when no
    answer came within ``timeout_s``.
    """
    key = keys.base_calib(robot)
    deadline = time.monotonic() + timeout_s
    attempt = 0
    last_problem = "no base station answered"
    while True:
        attempt += 1
        remaining = deadline - time.monotonic()
        for reply in session.get(key, timeout=max(0.5, min(2.0, remaining))):
            if reply.ok is not None:
                try:
                    msg = CalibMsg.from_bytes(reply.ok.payload.to_bytes())
                except WireError as err:
                    last_problem = f"invalid answer: {err}"
                    continue
                if msg.robot != robot:
                    last_problem = f"answer is the calibration of {msg.robot!r}"
                    continue
                log.info("calibration of %s fetched from %s (attempt %d)", robot, key, attempt)
                return msg.calibration
            err_text = reply.err.payload.to_string() if reply.err is not None else "error"
            msg_ = f"the base station has no calibration for robot {robot!r} ({key}): {err_text}"
            raise CalibrationUnavailableError(msg_)
        if time.monotonic() >= deadline or (stop is not None and stop.is_set()):
            break
        if stop is not None:
            stop.wait(0.25)
        else:
            time.sleep(0.25)
    msg_ = (
        f"no calibration for robot {robot!r}: none given with --calib and none fetched from {key} within "
        f"{timeout_s:.0f} s ({last_problem}); give --calib FILE or store it at the base station "
        f"(--state DIR/calib/{robot}.json)"
    )
    raise CalibrationUnavailableError(msg_)


def wait_delivered(
    session: Any,
    keys: FleetKeys,
    robot: str,
    first_seq: int,
    last_seq: int,
    timeout_s: float,
    stop: threading.Event | None = None,
) -> bool:
    """Poll the base station's acknowledgements until it holds every seq in ``[first_seq, last_seq]``."""
    key = keys.base_acks(robot)
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        for reply in session.get(key, timeout=1.0):
            if reply.ok is None:
                continue
            try:
                ranges = json.loads(reply.ok.payload.to_bytes())["ranges"]
                if any(int(lo) <= first_seq and last_seq <= int(hi) for lo, hi in ranges):
                    return True
            except (ValueError, KeyError, TypeError):
                continue
        if stop is not None and stop.is_set():
            return False
        time.sleep(0.05)
    return False


class RovService:
    """One ROV: a frame source, an IMU, a calibration, a Zenoh session.

    Args:
        session: an open Zenoh session (the caller owns and closes it).
        keys: the fleet's key expressions.
        robot: this robot's name.
        source: frames (context manager and iterator).
        imu: the pose track source (context manager).
        calibration: the sensor's calibration (served on ``<root>/<robot>/calib``).
        rate_hz: process at most this many frames per second (None: as fast as they come).
        method: stripe extractor name for :meth:`Sensor.process`.
        ack_timeout_s: at the end of a finite source, wait for the base station to acknowledge every published
            cloud; give up after this long without an acknowledgement (with an outbox sink: without one moving
            on) (0: do not wait).
        seq_start: the first sequence number (a restarted robot continues its numbering).
        sink: where clouds go (default: a Zenoh publisher on ``<root>/<robot>/cloud``).
        cloud_schema: 2 (compact: pixels and the calibration's fingerprint, the default) or 1 (float32 points).
        on_scan: called with ``(t_ns, scan)`` after each published cloud (the ROS 2 view); its errors are logged.
    """

    def __init__(
        self,
        session: Any,
        keys: FleetKeys,
        robot: str,
        source: FrameSource,
        imu: ImuSource,
        calibration: Calibration,
        *,
        rate_hz: float | None = None,
        method: str | None = None,
        process_options: Mapping[str, Any] | None = None,
        ack_timeout_s: float = 10.0,
        status_period_s: float = 1.0,
        seq_start: int = 0,
        sink: CloudSink | None = None,
        cloud_schema: int = 2,
        on_scan: Callable[[int, Scan], None] | None = None,
    ) -> None:
        if cloud_schema not in CLOUD_SCHEMAS:
            msg = f"cloud schema {cloud_schema} is not one of {CLOUD_SCHEMAS}"
            raise WireError(msg)
        self.session = session
        self.keys = keys
        self.robot = check_robot_name(robot)
        self.source = source
        self.imu = imu
        self.calibration = calibration
        # a live camera must not stall for a first compile: the numpy reference runs meanwhile (said in the log)
        self.sensor = Sensor(calibration, wait_for_kernels=False, stream=True)
        self.rate_hz = rate_hz
        self.method = method
        self.process_options, self.channel_note = channel_choice(source, method, process_options or {})
        self.ack_timeout_s = ack_timeout_s
        self.status_period_s = status_period_s
        self.seq = seq_start
        self.sink = sink
        self.cloud_schema = cloud_schema
        self.on_scan = on_scan
        self.calib_id = calibration_fingerprint(calibration)
        self._warned_schema = False
        self.counters = RovCounters()
        self.state = "starting"
        self._lock = threading.Lock()

    # ------------------------------------------------------------------ queryable / status
    def _on_calib_query(self, query: Any) -> None:
        try:
            fmt = query.parameters.get("format") if query.parameters is not None else None
            if fmt == "json":
                query.reply(query.key_expr, self.calibration.to_json(), encoding="application/json")
            else:
                query.reply(query.key_expr, CalibMsg(self.robot, self.calibration).to_bytes(), encoding=ENCODING)
        except Exception as err:
            log.warning("calibration query %s failed: %s", query.selector, err)

    def status(self) -> StatusMsg:
        """The current counters as a status message."""
        c = self.counters
        budget = getattr(self.sink, "budget_counts", None)  # an outbox sink's live/queued/forwarded/dropped
        delivery = budget() if callable(budget) else None
        with self._lock:
            return StatusMsg(
                self.robot,
                wall_clock_ns(),
                self.state,
                c.frames,
                c.published,
                c.skipped,
                c.failed,
                c.last_seq,
                c.unplaced,
                delivery,
            )

    # ------------------------------------------------------------------ main loop
    def run(self, stop: threading.Event | None = None) -> RovCounters:
        """Process the source until it ends or ``stop`` is set; returns the counters."""
        import zenoh

        stop = stop or threading.Event()
        c = self.counters
        queryable = self.session.declare_queryable(self.keys.calib(self.robot), self._on_calib_query)
        status_pub = self.session.declare_publisher(
            self.keys.rov_status(self.robot),
            encoding=zenoh.Encoding(ENCODING),
            congestion_control=zenoh.CongestionControl.BLOCK,
        )
        sink = self.sink or ZenohCloudSink(self.session, self.keys.cloud(self.robot))
        start_forwarding = getattr(sink, "start_forwarding", None)
        if callable(start_forwarding):  # the calibration is served now: a base can triangulate the backlog
            start_forwarding()
        # the token goes last: a robot seen alive already answers its calibration queryable
        token = self.session.liveliness().declare_token(self.keys.alive(self.robot))
        log.info(
            "rov %s: publishing on %s from %s; extractor: %s; %s",
            self.robot,
            self.keys.cloud(self.robot),
            self.source.name,
            "compiled" if extractor_compiled() else "numpy reference until the compiled kernels are built",
            self.channel_note,
        )
        try:  # a first status before any cloud: the base station learns this robot's clock offset from it
            status_pub.put(self.status().to_bytes())
        except Exception as err:
            log.debug("first status not published: %s", err)
        period_ns = int(1e9 / self.rate_hz) if self.rate_hz else 0
        next_ns = time.monotonic_ns()
        last_status = 0.0
        ended = False
        try:
            with self.imu, self.source:
                self.state = "running"
                for frame in self.source:
                    if stop.is_set():
                        break
                    if period_ns:
                        wait_s = (next_ns - time.monotonic_ns()) / 1e9
                        if wait_s > 0 and stop.wait(wait_s):
                            break
                        next_ns = max(next_ns + period_ns, time.monotonic_ns() - period_ns)
                    with self._lock:
                        c.frames += 1
                    self._process(frame.t_ns, frame.image, sink)
                    now = time.monotonic()
                    if now - last_status >= self.status_period_s:
                        last_status = now
                        status_pub.put(self.status().to_bytes())
                else:
                    ended = not stop.is_set()  # a live source that ends because we stop did not end
            if ended and self.ack_timeout_s > 0 and c.published > 0:
                waiter = getattr(sink, "wait_acked", None)
                if waiter is not None:  # an outbox: wait while its acknowledgements keep moving on
                    c.delivered = bool(waiter(c.first_seq, c.last_seq, self.ack_timeout_s, stop))
                else:
                    c.delivered = wait_delivered(
                        self.session, self.keys, self.robot, c.first_seq, c.last_seq, self.ack_timeout_s, stop
                    )
                if not c.delivered:
                    log.warning(
                        "rov %s: the base station did not acknowledge seq %d..%d (no progress for %.0f s)",
                        self.robot,
                        c.first_seq,
                        c.last_seq,
                        self.ack_timeout_s,
                    )
            self.state = "done" if ended else "stopped"
        except BaseException:
            self.state = "failed"
            raise
        finally:
            try:
                status_pub.put(self.status().to_bytes())
            except Exception as err:
                log.debug("final status not published: %s", err)
            queryable.undeclare()
            token.undeclare()
            status_pub.undeclare()
        log.info(c.summary(self.robot))
        return c

    def _process(self, t_ns: int, image: Any, sink: CloudSink) -> None:
        c = self.counters
        track = self.imu.track
        pose = track.pose_waiting(t_ns, LIVE_IMU_WAIT_S) if self.imu.live else track.pose_at(t_ns)
        if pose is None:
            with self._lock:
                c.skipped += 1
                n = c.skipped
            if n <= 3 or n % 100 == 0:
                why = self.imu.track.why_no_pose(t_ns)
                log.warning("rov %s: no pose for the frame at %d (%s): skipped (%d so far)", self.robot, t_ns, why, n)
            return
        try:
            options = dict(self.process_options)
            if self.method:
                options["method"] = self.method
            scan = self.sensor.process(image, **options)
            msg = self._message(t_ns, pose, scan)
        except LrsensorError as err:
            with self._lock:
                c.failed += 1
            log.warning("rov %s: frame at %d not processed: %s", self.robot, t_ns, err)
            return
        except Exception as err:  # an extractor bug must not stop the robot: count, log with traceback
            with self._lock:
                c.failed += 1
            log.exception("rov %s: frame at %d failed unexpectedly: %s", self.robot, t_ns, err)
            return
        sink.send(msg)
        if self.on_scan is not None:
            try:
                self.on_scan(t_ns, scan)
            except Exception as err:  # a view of the scan (ROS 2) must never stop the robot
                log.warning("rov %s: scan view failed for the frame at %d: %s", self.robot, t_ns, err)
        fixed = has_fix(pose)
        with self._lock:
            if not fixed:
                c.unplaced += 1
            if c.first_seq < 0:
                c.first_seq = self.seq
            c.last_seq = self.seq
            c.published += 1
            c.points += len(msg)
            n_unplaced = c.unplaced
        if not fixed and (n_unplaced == 1 or n_unplaced % 100 == 0):
            log.warning(
                "rov %s: %d clouds sent without a horizontal fix (north/east null; the base does not map them "
                "until it can place them), the latest at %d",
                self.robot,
                n_unplaced,
                t_ns,
            )
        self.seq += 1

    def _message(self, t_ns: int, pose: Pose, scan: Scan) -> AnyCloud:
        """The scan's cloud message in the configured schema (schema 1 when schema 2 cannot carry it)."""
        if self.cloud_schema == StripeMsg.VERSION:
            try:
                return StripeMsg.from_scan(self.robot, self.seq, t_ns, pose, scan, self.calib_id)
            except WireError as err:
                if not self._warned_schema:
                    self._warned_schema = True
                    log.warning("rov %s: %s; such clouds are sent as schema 1", self.robot, err)
        return CloudMsg.from_scan(self.robot, self.seq, t_ns, pose, scan)
