"""``lrsensor base``: run the base station (a Zenoh router in-process by default)."""

from __future__ import annotations

import argparse
import logging
import time

from .base_views import add_view_args
from .zconfig import add_network_args

log = logging.getLogger(__name__)

DEFAULT_LISTEN = "tcp/0.0.0.0:7447"


def configure(parser: argparse.ArgumentParser) -> None:
    """Add the flags of ``lrsensor base``."""
    parser.add_argument("--fleet", required=True, help="fleet name (the <fleet> chunk of every key)")
    parser.add_argument("--prefix", default="lrs", help="key prefix (default: lrs)")
    parser.add_argument(
        "--state", metavar="DIR", default=None, help="persist counters, calibrations and the map here (atomic files)"
    )
    parser.add_argument(
        "--map", choices=("auto", "on", "off"), default="auto", help="build the shared map (needs Open3D; default auto)"
    )
    parser.add_argument(
        "--nav",
        choices=("on", "filter", "off"),
        default="on",
        help="correct each robot's horizontal position and heading from its scans before mapping; on (default): "
        "correct each cloud and smooth past poses on a thread of their own, re-placing their clouds; filter: "
        "correct each cloud once (no re-placing); off: trust the poses (clouds without a horizontal fix are "
        "unplaced); docs/navigation.md",
    )
    parser.add_argument(
        "--no-fix",
        choices=("graph", "lost"),
        default=None,
        help="with --nav on/filter, a robot without a horizontal fix after its launch (attitude and depth only, e.g. "
        "an ROV without a DVL): graph (default): navigated by its gated pose graph (needs GTSAM: pip install "
        "'lrsensor[graph]'; without it the default is lost, with a warning), which places its faces but can "
        "place a face twice or a spurious plane when every robot lacks a fix; lost: reported lost, its clouds "
        "unplaced, an empty part of the map rather than a wrong one; in the map thread and in plane workers "
        "alike; docs/navigation.md, 'Choosing --no-fix'",
    )
    parser.add_argument(
        "--smoother",
        choices=("thread", "wait"),
        default="thread",
        help="with --nav on, the smoother's runs (every 10 s): thread (default): on a thread of their own while the "
        "map thread goes on, handed over at the first cloud after they finish; wait: the map thread waits for each "
        "run and takes it over at once (the map the in-process benchmarks make, whatever the machine's speed; the "
        "map lags by a run); docs/navigation.md",
    )
    parser.add_argument("--robots", default=None, help="comma-separated fleet members; others are rejected")
    parser.add_argument("--workers", type=int, default=2, help="ingest worker threads (default 2)")
    parser.add_argument(
        "--map-workers",
        type=int,
        default=None,
        metavar="N",
        help="plane-worker processes to start here (default: 0 under --nav on, whose smoother runs only in the "
        "base process; cores - 2 under --nav filter or off; see docs/scaling.md)",
    )
    parser.add_argument(
        "--remote-map-workers",
        action="store_true",
        help="send the per-robot map work to plane workers (lrsensor map-worker) even with --map-workers 0",
    )
    parser.add_argument(
        "--status-every-s", type=float, default=10.0, help="log a status line this often (0: never; default 10)"
    )
    add_view_args(parser)
    add_network_args(parser, default_mode="router")
    parser.epilog = f"Without --listen/--connect/--config the router listens on {DEFAULT_LISTEN}."


def run(args: argparse.Namespace) -> int:
    """Run until SIGINT/SIGTERM; returns 0 after a clean shutdown."""
    from .base import BaseStation
    from .base_views import open_views
    from .keys import FleetKeys
    from .signals import stop_on_signals
    from .zconfig import open_session, options_from_args

    keys = FleetKeys(args.fleet, args.prefix)
    options = options_from_args(args)
    mode = args.mode or "router"
    if mode == "router" and not (options.listen or options.connect or options.config_file):
        options = options_from_args(args)
        options = type(options)(mode=options.mode, listen=(DEFAULT_LISTEN,))
    robots = [r.strip() for r in args.robots.split(",") if r.strip()] if args.robots else None
    from .map_worker_procs import default_map_workers, local_endpoint

    n_workers = args.map_workers if args.map_workers is not None else default_map_workers(nav=args.nav)
    endpoint = local_endpoint(options.listen) or (options.connect[0] if options.connect else None)
    with stop_on_signals() as stop, open_session(options, default_mode="router") as session:
        station = BaseStation(
            session,
            keys,
            args.state,
            map_mode=args.map,
            robots=robots,
            workers=args.workers,
            navigation=args.nav != "off",
            map_workers=n_workers if endpoint is not None else 0,
            worker_endpoint=endpoint,
            remote_workers=args.remote_map_workers,
            no_fix=args.no_fix,
        )
        if args.nav == "filter":
            station.feed.set_smoothing(False)
        elif args.smoother == "wait":
            station.feed.set_smoothing(True, wait=True)
        with station, open_views(session, keys, args, station):
            print(f"base station of fleet {keys.fleet!r} running ({mode}); Ctrl-C to stop", flush=True)
            last = time.monotonic()
            while not stop.wait(0.2):
                if args.status_every_s > 0 and time.monotonic() - last >= args.status_every_s:
                    last = time.monotonic()
                    st = station.status()
                    parts = [
                        f"{r}: {v['received']} rx, {v['missed']} missed, {v['rejected']} rej"
                        + (f", position {v['nav']['position']}" if "nav" in v else "")
                        + ("" if v["alive"] else " (gone)")
                        for r, v in st["robots"].items()
                    ]
                    log.warning("status: %s; map planes %d", "; ".join(parts) or "no robot yet", st["map"]["planes"])
        st = station.status()
    total = sum(v["received"] for v in st["robots"].values())
    print(f"base station stopped: {total} clouds received from {len(st['robots'])} robots", flush=True)
    return 0
