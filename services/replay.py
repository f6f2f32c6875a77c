"""Replaying a recording into a fleet (``lrsensor replay FILE.mcap``): a base station rebuilds the same map.

A recording (:mod:`services.record`) holds each cloud's wire payload on ``<prefix>/<fleet>/<robot>/cloud``
and each calibration a robot measured with on ``<prefix>/<fleet>/<robot>/calib``. The replay plays every
recorded robot back as that robot would have sent it:

* it holds the robot's liveliness token and serves its recorded calibration on ``<root>/<robot>/calib`` (a
  compact cloud is triangulated at the base with it);
* it sends the clouds in their recorded order, spaced as they were received divided by ``rate`` (0: as fast as
  the link takes them), through the same store-and-forward delivery as a robot
  (:class:`~services.delivery.OutboxSink`): every cloud is re-sent until the base station acknowledges it;
* it ends when every cloud is acknowledged, or after ``ack_timeout_s`` with the clouds still pending named.

The clouds keep their robots, sequence numbers, capture times and raw poses; only the fleet may change
(``--fleet``). A base station that already holds them counts them as duplicates and changes nothing.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from lrsensor.calibration import Calibration
from lrsensor.errors import CalibrationFileError

from .errors import ServiceError, WireError
from .keys import FleetKeys
from .record import RAW_SCHEMA_NAME
from .wire import CalibMsg, CloudMsg, StripeMsg, decode_cloud
from .zconfig import undeclare_all

log = logging.getLogger(__name__)


class ReplayError(ServiceError):
    """The recording cannot be read or holds nothing to replay."""


@dataclass
class Recording:
    """The replayable content of a recording.

    Attributes:
        prefix: the key prefix the fleet used when recorded.
        fleet: the recorded fleet's name.
        clouds: ``(log_time_ns, robot, payload)`` in the recorded order.
        calibrations: robot -> the calibrations it measured with, in the recorded order.
    """

    prefix: str
    fleet: str
    clouds: list[tuple[int, str, bytes]] = field(default_factory=list)
    calibrations: dict[str, list[Calibration]] = field(default_factory=dict)

    @property
    def robots(self) -> list[str]:
        """The recorded robots, sorted."""
        return sorted({robot for _, robot, _ in self.clouds})


def _robot_of_topic(topic: str, kind: str) -> str | None:
    parts = topic.split("/")
    if len(parts) >= 4 and parts[-1] == kind:
        return parts[-2]
    return None


def read_recording(path: str | Path) -> Recording:
    """Read the wire channels of an MCAP recording (the ``mcap`` reader; foxglove views are skipped).

    Raises:
        ReplayError: the file is missing, not MCAP, or has no recorded clouds.
    """
    try:
        from mcap.exceptions import McapError
        from mcap.reader import make_reader
    except ImportError as err:
        msg = f"replay needs the mcap package (pip install 'lrsensor[all]'): {err}"
        raise ReplayError(msg) from err
    p = Path(path)
    if not p.is_file():
        msg = f"recording {p} does not exist"
        raise ReplayError(msg)
    prefix, fleet = "", ""
    rec = Recording(prefix="", fleet="")
    try:
        with p.open("rb") as f:
            reader = make_reader(f)
            for name, meta in ((m.name, m.metadata) for m in reader.iter_metadata()):
                if name == "lrsensor":
                    prefix, fleet = meta.get("prefix", ""), meta.get("fleet", "")
            f.seek(0)
            reader = make_reader(f)
            for schema, channel, message in reader.iter_messages(log_time_order=True):
                robot = _robot_of_topic(channel.topic, "cloud")
                if robot is not None and schema is not None and schema.name == RAW_SCHEMA_NAME:
                    rec.clouds.append((int(message.log_time), robot, bytes(message.data)))
                    continue
                robot = _robot_of_topic(channel.topic, "calib")
                if robot is not None and channel.message_encoding == "json":
                    where = f"{p}: calibration of {robot}"
                    calib = Calibration.from_dict(json.loads(message.data), where)
                    rec.calibrations.setdefault(robot, []).append(calib)
    except (McapError, OSError, ValueError, CalibrationFileError) as err:
        msg = f"recording {p} cannot be read: {err}"
        raise ReplayError(msg) from err
    if not rec.clouds:
        msg = f"recording {p} holds no clouds (channels named <prefix>/<fleet>/<robot>/cloud)"
        raise ReplayError(msg)
    rec.prefix, rec.fleet = prefix, fleet
    return rec


@dataclass
class ReplayResult:
    """How a replay went.

    Attributes:
        sent: clouds sent, by robot.
        pending: clouds not acknowledged when the replay ended, by robot (empty: all delivered).
        outboxes: robot -> the outbox folder that still holds its pending clouds.
        seconds: wall time of the replay.
    """

    sent: dict[str, int]
    pending: dict[str, int]
    outboxes: dict[str, str]
    seconds: float

    @property
    def delivered(self) -> bool:
        """True when the base station acknowledged every replayed cloud."""
        return not any(self.pending.values())


class _RobotPlayer:
    """One recorded robot on the fleet: its token, its calibration queryable, its delivery."""

    def __init__(self, session: Any, keys: FleetKeys, robot: str, calibs: list[Calibration], outbox_dir: Path):
        from .delivery import OutboxSink
        from .outbox import Outbox

        self.robot = robot
        self.calibration = calibs[-1] if calibs else None
        if len(calibs) > 1:
            log.warning("replay: %s measured with %d calibrations; serving the last one", robot, len(calibs))
        self.outbox_dir = outbox_dir
        self.queryable = session.declare_queryable(keys.calib(robot), self._on_calib)
        # A folder of this replay (``lrsensor replay`` makes a temporary one), not the robot's persistent outbox
        # of ``lrsensor rov``: the clouds keep their recorded numbers, which a robot's outbox has used already
        # (an outbox takes only numbers above its next_seq), and a replay into another fleet must not mix
        # with what the real robot still has to deliver. What is left unacknowledged is named at the end.
        self.outbox = Outbox(outbox_dir, fsync=False)
        self.sink = OutboxSink(session, keys, robot, self.outbox)
        self.token = session.liveliness().declare_token(keys.alive(robot))
        self.sent = 0

    def _on_calib(self, query: Any) -> None:
        if self.calibration is None:
            return
        try:
            query.reply(query.key_expr, CalibMsg(self.robot, self.calibration).to_bytes())
        except Exception as err:
            log.warning("replay: calibration query of %s failed: %s", self.robot, err)

    def send(self, msg: CloudMsg | StripeMsg) -> None:
        self.sink.send(msg)
        self.sent += 1

    def close(self) -> None:
        self.sink.close()
        self.outbox.close()  # its lock
        undeclare_all((self.token, self.queryable), f"replay of {self.robot}")


def _schedule(clouds: list[tuple[int, str, bytes]], rate: float) -> Iterator[tuple[float, str, bytes]]:
    """``(seconds after the start, robot, payload)``: recorded spacing divided by ``rate`` (0: no waiting)."""
    t0 = clouds[0][0]
    for t, robot, payload in clouds:
        yield ((t - t0) / 1e9 / rate if rate > 0 else 0.0), robot, payload


def replay(
    session: Any,
    keys: FleetKeys,
    recording: Recording,
    outbox_root: Path,
    *,
    rate: float = 1.0,
    ack_timeout_s: float = 60.0,
    stop: threading.Event | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> ReplayResult:
    """Play ``recording`` into the fleet of ``keys`` (see the module docstring).

    Args:
        session: an open Zenoh session (the caller owns it).
        keys: the target fleet's key expressions.
        recording: what :func:`read_recording` read.
        outbox_root: a folder for the robots' outboxes (one sub-folder per robot).
        rate: speed relative to the recording (2: twice as fast; 0: as fast as possible).
        ack_timeout_s: after the last cloud, wait this long for the acknowledgements.
        stop: set to end early (pending clouds stay in the outboxes).
        progress: called with ``(sent, total)`` after each cloud.
    """
    if rate < 0:
        msg = f"rate must be >= 0 (0: as fast as possible), got {rate}"
        raise ReplayError(msg)
    stop = stop or threading.Event()
    start = time.monotonic()
    players = {
        r: _RobotPlayer(session, keys, r, recording.calibrations.get(r, []), outbox_root / r) for r in recording.robots
    }
    total = len(recording.clouds)
    done = 0
    try:
        for at_s, robot, payload in _schedule(recording.clouds, rate):
            wait_s = start + at_s - time.monotonic()
            if wait_s > 0 and stop.wait(wait_s):
                break
            if stop.is_set():
                break
            try:
                cloud = decode_cloud(payload)
            except WireError as err:
                log.warning("replay: recorded cloud of %s skipped: %s", robot, err)
                continue
            players[robot].send(cloud)
            done += 1
            if progress is not None:
                progress(done, total)
        deadline = time.monotonic() + ack_timeout_s
        for player in players.values():
            player.sink.wait_empty(max(0.0, deadline - time.monotonic()), stop)
    finally:
        for player in players.values():
            player.close()
    pending = {r: len(p.sink.outbox) for r, p in players.items()}
    return ReplayResult(
        sent={r: p.sent for r, p in players.items()},
        pending=pending,
        outboxes={r: str(p.outbox_dir) for r, p in players.items() if pending[r]},
        seconds=time.monotonic() - start,
    )
