"""Child processes of the multi-process tests (`lrsensor base` / `lrsensor rov` / a bare router)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path


def lrsensor_cmd(*args: str) -> list[str]:
    """The command line of ``lrsensor -v ARGS`` with this interpreter."""
    return [sys.executable, "-m", "lrsensor", "-v", *args]


class Proc:
    """A child process whose output is appended to a log file (a restarted service may share the log)."""

    def __init__(self, args: list[str], log: Path) -> None:
        self.log = log
        self.fh = log.open("ab")
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        self.p = subprocess.Popen(args, stdout=self.fh, stderr=subprocess.STDOUT, env=env)

    def output(self) -> str:
        if not self.fh.closed:
            self.fh.flush()
        return self.log.read_text(errors="replace")

    def wait(self, timeout_s: float) -> int:
        return self.p.wait(timeout_s)

    def stop(self, sig: int = signal.SIGTERM, timeout_s: float = 15.0) -> int:
        """Send ``sig`` (if still running) and return the exit code."""
        if self.p.poll() is None:
            self.p.send_signal(sig)
        try:
            return self.p.wait(timeout_s)
        finally:
            self.fh.close()

    def kill(self) -> None:
        if self.p.poll() is None:
            self.p.kill()
            self.p.wait(10)
        if not self.fh.closed:
            self.fh.close()
