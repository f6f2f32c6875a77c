"""This robot's wall clock: ``time.time_ns()`` shifted by ``$LRS_CLOCK_OFFSET_S`` (a robot minutes off the base).

What the ROV stamps with :func:`wall_clock_ns` reaches the base station on the robot's own clock: a cloud's
publication time (``sent_ns``, stamped by the delivery, :mod:`services.delivery`) and the status message's
``t_ns`` (:mod:`services.rov`). Capture times come from the frame source, not from here. The offset exists for
tests and drills of a robot whose clock is off the base station's (docs/reliability.md, "A robot whose clock is
off"); it is read once, when this module is imported, so that every stamp of a process agrees.

Its own module because both the ROV loop and the delivery stamp with it, and neither owns the other's clock.
"""

from __future__ import annotations

import logging
import os
import time

log = logging.getLogger(__name__)

#: Environment variable that shifts this robot's wall clock by so many seconds (a robot whose clock is minutes
#: off the base station's, for tests: docs/reliability.md, "A robot whose clock is off").
CLOCK_OFFSET_ENV = "LRS_CLOCK_OFFSET_S"


def _clock_offset_ns() -> int:
    raw = os.environ.get(CLOCK_OFFSET_ENV, "").strip()
    if not raw:
        return 0
    try:
        return int(float(raw) * 1e9)
    except ValueError:
        log.warning("%s=%r is not a number of seconds; the clock is not shifted", CLOCK_OFFSET_ENV, raw)
        return 0


_CLOCK_OFFSET_NS = _clock_offset_ns()


def wall_clock_ns() -> int:
    """This robot's wall clock, ns since the epoch: ``time.time_ns()`` shifted by ``$LRS_CLOCK_OFFSET_S``.

    What the ROV stamps with it reaches the base station on the robot's clock: a cloud's publication time
    (``sent_ns``) and the status message's ``t_ns``. Capture times come from the frame source.
    """
    return time.time_ns() + _CLOCK_OFFSET_NS


__all__ = ["CLOCK_OFFSET_ENV", "wall_clock_ns"]
