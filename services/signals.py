"""SIGINT/SIGTERM -> a stop event, so that every entry point leaves its ``with zenoh.open(...)`` block and
closes its session (zenoh-python hangs at exit otherwise)."""

from __future__ import annotations

import logging
import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from types import FrameType
from typing import Any

log = logging.getLogger(__name__)


@contextmanager
def stop_on_signals(stop: threading.Event | None = None) -> Iterator[threading.Event]:
    """Within the block, SIGINT and SIGTERM set ``stop`` (a new event if None) instead of killing.

    A second signal of the same kind restores the default behaviour (so a stuck process can still be
    interrupted). Outside the main thread signals cannot be caught; the event is then only set by callers.
    """
    event = stop if stop is not None else threading.Event()
    if threading.current_thread() is not threading.main_thread():
        yield event
        return
    previous: dict[int, Any] = {}

    def handler(signum: int, _frame: FrameType | None) -> None:
        name = signal.Signals(signum).name
        if event.is_set():
            log.warning("second %s: giving up a clean shutdown", name)
            signal.signal(signum, previous.get(signum, signal.SIG_DFL))
            signal.raise_signal(signum)
            return
        log.info("%s received: stopping", name)
        event.set()

    for sig in (signal.SIGINT, signal.SIGTERM):
        previous[sig] = signal.signal(sig, handler)
    try:
        yield event
    finally:
        for signum, h in previous.items():
            signal.signal(signum, h)
