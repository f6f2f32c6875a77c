"""Local plane-worker processes of a base station (``lrsensor base --map-workers N``).

Each is ``python -m lrsensor map-worker --fleet F --prefix P --connect EP --mode client``: a process of its own
(its own interpreter and GIL, its own Open3D), joining the base's router over TCP exactly as a worker on another
machine does; the base finds it by its liveliness token like any other (:mod:`services.map_workers`).
"""

from __future__ import annotations

import logging
import os
import subprocess
import sys

from .keys import FleetKeys

log = logging.getLogger(__name__)

#: How long a worker process gets to leave after SIGTERM before it is killed, seconds.
STOP_TIMEOUT_S = 10.0


def default_map_workers(cores: int | None = None, nav: str = "on") -> int:
    """Local worker processes by default: none under ``--nav on``, else the cores minus two (0 on a 2-core
    machine: one map thread in the base process).

    Workers navigate with the filter or the pose graphs only: they run no smoother, so under ``--nav on`` (the
    default) a fleet mapped by workers is not the fleet the base's map thread maps, and a drifting robot's clouds
    stay where the filter first placed them (docs/scaling.md). The map thread keeps up with a small fleet (a few
    robots at 30 Hz); a bigger one opts in with ``--map-workers N``. Under ``--nav filter`` or ``off`` workers map
    as one process does. Without workers the base process keeps about one core busy at a fleet's full rate on its
    own (Zenoh, decoding, the ledger, navigation, extraction, the merge); with workers it only ingests, dispatches
    and merges, and the workers extract and navigate. On two cores worker processes do raise throughput
    (benchmarks/results/workers.md), but they share the cores with everything else on the machine and delay
    acknowledgements until a window is committed: an operator opts in with ``--map-workers N``. From three cores
    on, each worker has a core of extraction to itself.

    Args:
        cores: the machine's cores (default ``os.cpu_count()``).
        nav: the base's ``--nav`` choice, ``on``, ``filter`` or ``off``.
    """
    if nav == "on":
        return 0
    n = cores if cores is not None else (os.cpu_count() or 1)
    return max(0, n - 2)


def start_local_workers(n: int, keys: FleetKeys, endpoint: str, verbose: int = 0) -> list[subprocess.Popen[bytes]]:
    """Start ``n`` worker processes connecting to ``endpoint`` (``tcp/host:port`` of the base's router)."""
    cmd = [sys.executable, "-m", "lrsensor", *(["-v"] * verbose), "map-worker"]
    cmd += ["--fleet", keys.fleet, "--prefix", keys.prefix, "--mode", "client", "--connect", endpoint]
    cmd += ["--parent-pid", str(os.getpid())]
    procs = []
    for _ in range(n):
        # a session of their own: a Ctrl-C in the base's terminal reaches the base only, which flushes the
        # workers' windows before it stops them
        procs.append(subprocess.Popen(cmd, start_new_session=True))
    log.info("started %d local map worker processes (%s)", n, endpoint)
    return procs


def stop_local_workers(procs: list[subprocess.Popen[bytes]]) -> None:
    """SIGTERM each process, wait for it, kill it when it does not leave in time."""
    for p in procs:
        if p.poll() is None:
            p.terminate()
    for p in procs:
        try:
            p.wait(timeout=STOP_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            log.warning("map worker process %d did not stop: killed", p.pid)
            p.kill()
            p.wait()


def local_endpoint(listen: tuple[str, ...] | list[str]) -> str | None:
    """Where local workers connect: the first TCP listen endpoint, with an any-address turned into loopback."""
    for ep in listen:
        if ep.startswith("tcp/"):
            host, _, port = ep[4:].rpartition(":")
            if host in ("0.0.0.0", "[::]", "::", ""):
                host = "127.0.0.1"
            return f"tcp/{host}:{port}"
    return None
