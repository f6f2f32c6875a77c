"""Waiting for something to happen in the tests (a message to arrive, a service to come up)."""

from __future__ import annotations

import time
from collections.abc import Callable


def wait_until(pred: Callable[[], object], timeout_s: float, interval_s: float = 0.02) -> bool:
    """Poll ``pred`` every ``interval_s`` until it is true or ``timeout_s`` have passed.

    Returns whether it became true; one last look at the deadline decides, so a condition that
    comes true while the last sleep runs still counts.
    """
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(interval_s)
    return bool(pred())
