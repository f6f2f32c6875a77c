"""Child processes of the multi-process tests (`lrsensor base` / `lrsensor rov` / a bare router)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any


def client_session(port: int, timeout_s: float = 30.0) -> Any:
    """A Zenoh client session to a router on 127.0.0.1:``port``, retried until the router listens."""
    from services.zconfig import NetworkOptions, open_session

    deadline = time.monotonic() + timeout_s
    while True:
        try:
            return open_session(NetworkOptions(mode="client", connect=(f"tcp/127.0.0.1:{port}",)), "client")
        except Exception:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.1)


#: A bare Zenoh router on 127.0.0.1:<argv[1]> (scouting off) that ends cleanly on SIGTERM.
_ROUTER_SCRIPT = """
import json, signal, sys, threading, zenoh
port = int(sys.argv[1])
conf = {"mode": "router", "listen": {"endpoints": [f"tcp/127.0.0.1:{port}"]},
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}}}
stop = threading.Event()
signal.signal(signal.SIGTERM, lambda *_: stop.set())
with zenoh.open(zenoh.Config.from_json5(json.dumps(conf))):
    print("router up", flush=True)
    stop.wait()
"""


def router_cmd(port: int) -> list[str]:
    """The command line of a bare router on 127.0.0.1:``port`` (prints "router up" once it listens)."""
    return [sys.executable, "-c", _ROUTER_SCRIPT, str(port)]


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
