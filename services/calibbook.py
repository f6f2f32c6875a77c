"""The base station's calibration book: which calibration triangulates a robot's compact (schema-2) clouds.

A schema-2 cloud (:class:`~services.wire.StripeMsg`) carries pixels and the 64-bit fingerprint of the
calibration they were measured with (:func:`~services.wire.calibration_fingerprint`). The base station
triangulates it only with a calibration of exactly that fingerprint, looked up in this order:

1. the calibrations already known for the robot (kept in memory by fingerprint);
2. the robot's fleet calibration stored at the base (``<state>/calib/<robot>.json``, re-read when the file
   changes);
3. the calibration the robot itself serves on ``<root>/<robot>/calib`` (what its sensor runs with), asked at
   most once every ``retry_s`` per robot while a fingerprint is unknown.

Policy when none matches (the robot is gone and the base holds another calibration, or the robot was
recalibrated since it measured the cloud): the cloud is **refused**, counted as rejected with the reason
``calibration mismatch`` or ``no calibration``, and **not acknowledged**. The robot's outbox keeps it and its
delivery loop offers it again (a few probes per stall period, see :mod:`services.delivery`) until a base that
holds that calibration takes it: store the calibration the robot measured with as its fleet calibration, or
bring the robot up so that it serves it. A cloud is never placed with a calibration it was not measured with.

Why not the fleet calibration alone: a robot started with ``--calib FILE`` measures with that file, which the
base may not hold; schema 1 clouds were placed with the robot's own calibration too, so asking the robot keeps
the behaviour of schema 1 while the fingerprint makes the choice explicit and checked.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from pathlib import Path

from lrsensor.calibration import Calibration
from lrsensor.errors import LrsensorError

from .wire import calibration_fingerprint

log = logging.getLogger(__name__)

#: How often a robot is asked again for its calibration while a fingerprint stays unknown, seconds.
RETRY_S = 5.0


class CalibrationBook:
    """Calibrations by robot and fingerprint (see the module docstring).

    Args:
        stored_path: robot -> path of its stored fleet calibration (None: no state folder).
        fetch: robot -> the calibration the robot serves, or None when it does not answer (None: never ask).
        retry_s: shortest interval between two fetches for one robot, seconds.
    """

    def __init__(
        self,
        stored_path: Callable[[str], Path | None],
        fetch: Callable[[str], Calibration | None] | None = None,
        *,
        retry_s: float = RETRY_S,
    ) -> None:
        self.stored_path = stored_path
        self.fetch = fetch
        self.retry_s = retry_s
        self._known: dict[tuple[str, bytes], Calibration] = {}
        self._stored: dict[str, tuple[int, bytes | None]] = {}  # robot -> (file mtime_ns, fingerprint)
        self._asked_s: dict[str, float] = {}
        self._fetching: dict[str, threading.Lock] = {}
        self._lock = threading.Lock()

    def add(self, robot: str, calibration: Calibration) -> bytes:
        """Remember ``calibration`` for ``robot``; returns its fingerprint."""
        fp = calibration_fingerprint(calibration)
        with self._lock:
            self._known[(robot, fp)] = calibration
        return fp

    def lookup(self, robot: str, fingerprint: bytes) -> tuple[Calibration | None, str]:
        """The calibration of ``robot`` with ``fingerprint``, or ``(None, reason)``.

        The reason starts with ``no calibration`` or ``calibration mismatch`` (the rejection counter's key).
        """
        with self._lock:
            calib = self._known.get((robot, fingerprint))
        if calib is not None:
            return calib, ""
        stored_fp = self._refresh_stored(robot)
        with self._lock:
            calib = self._known.get((robot, fingerprint))
        if calib is not None:
            return calib, ""
        self._ask_robot(robot)
        with self._lock:
            calib = self._known.get((robot, fingerprint))
        if calib is not None:
            if stored_fp is not None and stored_fp != fingerprint:
                log.warning(
                    "robot %s measures with calibration %s, not its stored fleet calibration %s: its clouds are "
                    "triangulated with the calibration it serves",
                    robot,
                    fingerprint.hex(),
                    stored_fp.hex(),
                )
            return calib, ""
        with self._lock:
            held = sorted({fp.hex() for (r, fp) in self._known if r == robot})
        if not held:
            return None, (
                f"no calibration: cloud measured with calibration {fingerprint.hex()}; the base stores none for "
                f"{robot!r} and the robot does not serve it (kept in the robot's outbox)"
            )
        return None, (
            f"calibration mismatch: cloud measured with calibration {fingerprint.hex()}; the base holds "
            f"{', '.join(held)} for {robot!r} (kept in the robot's outbox)"
        )

    def _refresh_stored(self, robot: str) -> bytes | None:
        """Read the stored fleet calibration when its file changed; its fingerprint (None: none stored)."""
        path = self.stored_path(robot)
        if path is None:
            return None
        try:
            mtime_ns = path.stat().st_mtime_ns
        except OSError:
            return None
        with self._lock:
            seen = self._stored.get(robot)
        if seen is not None and seen[0] == mtime_ns:
            return seen[1]
        fp: bytes | None = None
        try:
            fp = self.add(robot, Calibration.load(path))
        except LrsensorError as err:
            log.warning("stored calibration of %s is invalid: %s", robot, err)
        with self._lock:
            self._stored[robot] = (mtime_ns, fp)
        return fp

    def _ask_robot(self, robot: str) -> bytes | None:
        """Ask the robot for the calibration it serves (at most once per ``retry_s``); its fingerprint."""
        if self.fetch is None:
            return None
        with self._lock:
            robot_lock = self._fetching.setdefault(robot, threading.Lock())
        with robot_lock:  # one question per robot at a time: the other workers wait for its answer
            now = time.monotonic()
            with self._lock:
                last = self._asked_s.get(robot)
                if last is not None and now - last < self.retry_s:
                    return None
                self._asked_s[robot] = now
            try:
                calib = self.fetch(robot)
            except Exception as err:  # a network failure is a missing answer, never an ingest failure
                log.debug("calibration of %s not fetched: %s", robot, err)
                return None
        if calib is None:
            return None
        fp = self.add(robot, calib)
        log.info("calibration %s of robot %s fetched from the robot", fp.hex(), robot)
        return fp
