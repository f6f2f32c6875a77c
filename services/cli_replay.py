"""``lrsensor replay``: publish a recording back into a fleet, so that a base station rebuilds its map."""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

from .zconfig import add_network_args


def configure(parser: argparse.ArgumentParser) -> None:
    """Add the flags of ``lrsensor replay``."""
    parser.add_argument("recording", metavar="FILE.mcap", help="a recording of `lrsensor record`")
    parser.add_argument("--fleet", default=None, help="target fleet (default: the recorded one)")
    parser.add_argument("--prefix", default=None, help="key prefix (default: the recorded one)")
    parser.add_argument(
        "--rate", type=float, default=1.0, help="speed relative to the recording (default 1; 0: as fast as possible)"
    )
    parser.add_argument(
        "--ack-timeout-s", type=float, default=60.0, help="wait this long for the last acknowledgements (default 60)"
    )
    add_network_args(parser, default_mode="client")


def run(args: argparse.Namespace) -> int:
    """Replay; 0 when the base station acknowledged every cloud, 3 otherwise (the outboxes are named)."""
    from .keys import FleetKeys
    from .replay import read_recording, replay
    from .signals import stop_on_signals
    from .zconfig import open_session, options_from_args

    rec = read_recording(args.recording)
    keys = FleetKeys(args.fleet or rec.fleet or "replay", args.prefix or rec.prefix or "lrs")
    print(
        f"lrsensor replay: {len(rec.clouds)} clouds of {', '.join(rec.robots)} from {args.recording} into "
        f"{keys.root} at rate {args.rate:g}",
        flush=True,
    )
    folder = Path(tempfile.mkdtemp(prefix="lrs-replay-"))
    step = max(1, len(rec.clouds) // 10)

    def progress(done: int, total: int) -> None:
        if done % step == 0 or done == total:
            print(f"  sent {done}/{total}", flush=True)

    with stop_on_signals() as stop, open_session(options_from_args(args), default_mode="client") as session:
        res = replay(
            session, keys, rec, folder, rate=args.rate, ack_timeout_s=args.ack_timeout_s, stop=stop, progress=progress
        )
    if res.delivered:
        import shutil

        shutil.rmtree(folder, ignore_errors=True)
        print(f"lrsensor replay: all {sum(res.sent.values())} clouds acknowledged in {res.seconds:.1f} s", flush=True)
        return 0
    for robot, n in sorted(res.pending.items()):
        if n:
            print(
                f"lrsensor replay: {robot}: {n} clouds not acknowledged, kept in {res.outboxes[robot]}", file=sys.stderr
            )
    return 3  # as `lrsensor rov` when clouds are left unacknowledged
