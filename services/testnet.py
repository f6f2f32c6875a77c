"""The in-process test network: a Zenoh router, a base station and N ROVs in one process on loopback.

Used by the tests and by ``lrsensor demo``::

    with TestNetwork("demo") as net:
        base = net.start_base(state_dir)                 # the base station on the router's session
        rov = net.start_rov("rov1", source, imu, calib)  # a client session + RovService in a thread
        rov.join(timeout=60)
        print(base.status())

Ports are chosen free at run time on 127.0.0.1, multicast scouting is off, every session is closed on exit.
"""

from __future__ import annotations

import logging
import socket
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from lrsensor.calibration import Calibration

from .base import BaseStation
from .errors import NetworkConfigError, ServiceError
from .imu import ImuSource
from .keys import FleetKeys
from .rov import RovCounters, RovService
from .sources import FrameSource
from .zconfig import NetworkOptions, open_session

log = logging.getLogger(__name__)


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port that was free a moment ago on ``host``."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


@dataclass
class RovHandle:
    """A ROV running in a thread of the test network."""

    robot: str
    service: RovService
    thread: threading.Thread
    stop: threading.Event
    session: Any
    result: RovCounters | None = None
    error: BaseException | None = None
    done: threading.Event = field(default_factory=threading.Event)

    def join(self, timeout: float | None = None) -> bool:
        """Wait for the ROV's run to end; True if it ended."""
        return self.done.wait(timeout)


class TestNetwork:
    """Router + base station + ROVs in one process (a context manager).

    Args:
        fleet: fleet name.
        prefix: key prefix.
        host: loopback address to listen on.
    """

    __test__ = False  # not a pytest test class

    def __init__(self, fleet: str = "test", prefix: str = "lrs", host: str = "127.0.0.1") -> None:
        self.keys = FleetKeys(fleet, prefix)
        self.host = host
        self.port = 0
        self.router: Any = None
        self.base: BaseStation | None = None
        self.rovs: dict[str, RovHandle] = {}
        self._sessions: list[Any] = []

    @property
    def endpoint(self) -> str:
        """The router's endpoint, ``tcp/127.0.0.1:<port>``."""
        return f"tcp/{self.host}:{self.port}"

    def __enter__(self) -> TestNetwork:
        last: Exception | None = None
        for _ in range(5):
            self.port = free_port(self.host)
            try:
                self.router = open_session(NetworkOptions(mode="router", listen=(self.endpoint,)), "router")
                break
            except NetworkConfigError as err:  # port taken between the probe and the bind
                last = err
        else:
            msg = f"could not start the test router on {self.host}: {last}"
            raise ServiceError(msg)
        log.info("test router listening on %s", self.endpoint)
        return self

    def session(self, mode: str = "client") -> Any:
        """A new session connected to the router (closed when the network closes)."""
        s = open_session(NetworkOptions(mode=mode, connect=(self.endpoint,)), mode)
        self._sessions.append(s)
        return s

    def start_base(self, state_dir: str | Path | None = None, **kwargs: Any) -> BaseStation:
        """Start the base station on the router's own session (as in the fleet deployment)."""
        if self.base is not None:
            msg = "the test network already has a base station"
            raise ServiceError(msg)
        self.base = BaseStation(self.router, self.keys, state_dir, **kwargs)
        self.base.start()
        return self.base

    def start_rov(
        self,
        robot: str,
        source: FrameSource,
        imu: ImuSource,
        calibration: Calibration,
        **kwargs: Any,
    ) -> RovHandle:
        """Start a ROV on its own client session in a thread."""
        session = self.session("client")
        service = RovService(session, self.keys, robot, source, imu, calibration, **kwargs)
        stop = threading.Event()
        handle = RovHandle(robot, service, threading.Thread(), stop, session)

        def target() -> None:
            try:
                handle.result = service.run(stop)
            except BaseException as err:  # reported by the caller through handle.error
                handle.error = err
                log.error("rov %s failed: %s", robot, err)
            finally:
                handle.done.set()

        handle.thread = threading.Thread(target=target, name=f"rov-{robot}", daemon=True)
        self.rovs[robot] = handle
        handle.thread.start()
        return handle

    def __exit__(self, *exc: object) -> None:
        for h in self.rovs.values():
            h.stop.set()
        for h in self.rovs.values():
            h.done.wait(timeout=30.0)
        if self.base is not None:
            self.base.close()
        for s in reversed(self._sessions):
            try:
                s.close()
            except Exception as err:
                log.debug("session close failed: %s", err)
        if self.router is not None:
            self.router.close()
