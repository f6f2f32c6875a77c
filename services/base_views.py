"""The base station's optional views for other tools: Foxglove live view, MCAP recording, ROS 2 topics.

``lrsensor base`` starts each view its flags ask for, on the base's own Zenoh session, and closes them (the
recording finished, the server stopped, the ROS 2 tokens withdrawn) when the base stops:

* ``--foxglove [HOST:]PORT``: :class:`~services.liveview.LiveView` (Foxglove WebSocket protocol);
* ``--record FILE.mcap``: :class:`~services.record.Recorder`;
* ``--ros2 [DOMAIN]``: a :class:`~services.fleet_tap.FleetTap` feeding
  :class:`~services.ros2_views.Ros2FleetSink` (clouds and poses in ``map``, the planes as markers).

Each view is a subscriber of the fleet like any other client, so it sees what the base sees without touching
the base's ingest, ledger or map threads.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
from pathlib import Path
from typing import Any

from .keys import FleetKeys

log = logging.getLogger(__name__)


def add_view_args(parser: argparse.ArgumentParser) -> None:
    """Add ``--foxglove``, ``--record`` and ``--ros2`` to ``lrsensor base``."""
    g = parser.add_argument_group("views for other tools")
    g.add_argument(
        "--foxglove",
        metavar="[HOST:]PORT",
        default=None,
        help="serve a Foxglove live view (WebSocket) here, e.g. 8765 (localhost) or 0.0.0.0:8765",
    )
    g.add_argument("--record", metavar="FILE.mcap", default=None, help="record the fleet into this MCAP file")
    g.add_argument(
        "--ros2",
        metavar="DOMAIN",
        nargs="?",
        const=0,
        type=int,
        default=None,
        help="publish the fleet's clouds, poses and planes as ROS 2 topics over Zenoh (domain, default 0)",
    )


def open_views(session: Any, keys: FleetKeys, args: argparse.Namespace) -> contextlib.ExitStack:
    """Start the views ``args`` ask for; closing the returned stack closes them (in reverse order)."""
    stack = contextlib.ExitStack()
    try:
        if args.record:
            from .record import Recorder

            recorder = stack.enter_context(Recorder(session, keys, Path(args.record)))
            print(f"recording the fleet into {recorder.path}", flush=True)
        if args.foxglove:
            from .liveview import LiveView, parse_host_port

            host, port = parse_host_port(args.foxglove)
            view = stack.enter_context(LiveView(session, keys, host, port))
            print(f"Foxglove live view on {view.url} (Open connection > Foxglove WebSocket)", flush=True)
        if args.ros2 is not None:
            from .fleet_tap import FleetTap
            from .ros2 import Ros2Node
            from .ros2_views import Ros2FleetSink

            node = Ros2Node(session, name="lrsensor_base", domain=args.ros2)
            stack.callback(node.close)
            tap = FleetTap(session, keys, [Ros2FleetSink(node, keys.root)])
            stack.callback(tap.close)
            print(
                f"ROS 2 topics /{keys.root}/... on domain {args.ros2} (share this router with rmw_zenohd)", flush=True
            )
    except BaseException:
        stack.close()
        raise
    return stack
