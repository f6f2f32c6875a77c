"""``lrsensor record``: record a fleet's clouds, poses and map into an MCAP file (Foxglove's schemas)."""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from .zconfig import add_network_args


def configure(parser: argparse.ArgumentParser) -> None:
    """Add the flags of ``lrsensor record``."""
    parser.add_argument("--fleet", required=True, help="fleet name")
    parser.add_argument("--prefix", default="lrs", help="key prefix (default: lrs)")
    parser.add_argument("--out", required=True, metavar="FILE.mcap", help="the recording to write")
    parser.add_argument("--overwrite", action="store_true", help="replace --out if it exists")
    parser.add_argument(
        "--duration-s", type=float, default=None, help="stop after this many seconds (default: until Ctrl-C)"
    )
    add_network_args(parser, default_mode="client")


def run(args: argparse.Namespace) -> int:
    """Record until the duration ends or a signal arrives; prints what was written."""
    from .keys import FleetKeys
    from .record import Recorder
    from .signals import stop_on_signals
    from .zconfig import open_session, options_from_args

    keys = FleetKeys(args.fleet, args.prefix)
    out = Path(args.out)
    with stop_on_signals() as stop, open_session(options_from_args(args), default_mode="client") as session:
        recorder = Recorder(session, keys, out, overwrite=args.overwrite)
        print(f"lrsensor record: recording fleet {keys.root} into {out} (Ctrl-C ends)", flush=True)
        end = None if args.duration_s is None else time.monotonic() + args.duration_s
        last = 0.0
        while not stop.is_set():
            if end is not None and time.monotonic() >= end:
                break
            stop.wait(0.5 if end is None else max(0.0, min(0.5, end - time.monotonic())))
            if time.monotonic() - last >= 10.0:
                last = time.monotonic()
                st = recorder.stats()
                print(f"  {st['total_clouds']} clouds, {st['map_updates']} map updates", flush=True)
        stats = recorder.close()
    print(f"lrsensor record: {out}: {json.dumps(stats)}", flush=True)
    return 0
