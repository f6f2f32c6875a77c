"""``lrsensor map-worker``: one plane worker process joining a fleet's base station over Zenoh."""

from __future__ import annotations

import argparse
import os

from .zconfig import add_network_args


def configure(parser: argparse.ArgumentParser) -> None:
    """Add the flags of ``lrsensor map-worker``."""
    parser.add_argument("--fleet", required=True, help="fleet name (the <fleet> chunk of every key)")
    parser.add_argument("--prefix", default="lrs", help="key prefix (default: lrs)")
    parser.add_argument("--name", default=None, help="worker name (default: <host>-<pid>-<random>)")
    parser.add_argument("--parent-pid", type=int, default=None, help=argparse.SUPPRESS)  # stop when the base dies
    add_network_args(parser, default_mode="client")
    parser.epilog = "Connect to the base station's router: --connect tcp/BASE-HOST:7447 (see docs/scaling.md)."


def run(args: argparse.Namespace) -> int:
    """Serve until SIGINT/SIGTERM; returns 0 after a clean shutdown."""
    from .keys import FleetKeys
    from .map_worker import MapWorker
    from .signals import stop_on_signals
    from .zconfig import open_session, options_from_args

    keys = FleetKeys(args.fleet, args.prefix)
    with (
        stop_on_signals() as stop,
        open_session(options_from_args(args), default_mode="client") as session,
        MapWorker(session, keys, args.name) as worker,
    ):
        print(f"map worker {worker.name} of fleet {keys.fleet!r} running; Ctrl-C to stop", flush=True)
        while not stop.wait(0.2):
            if args.parent_pid is not None and os.getppid() != args.parent_pid:
                break  # the base that started this worker is gone
    print(f"map worker stopped: {worker.jobs} clouds, {worker.published} observations", flush=True)
    return 0
