"""The base station's optional views: Foxglove live view, MCAP recording, ROS 2 topics, the status page.

``lrsensor base`` starts each view its flags ask for, on the base's own Zenoh session, and closes them (the
recording finished, the server stopped, the ROS 2 tokens withdrawn) when the base stops:

* ``--foxglove [HOST:]PORT``: :class:`~services.liveview.LiveView` (Foxglove WebSocket protocol);
* ``--record FILE.mcap``: :class:`~services.record.Recorder`;
* ``--ros2 [DOMAIN]``: a :class:`~services.fleet_tap.FleetTap` feeding
  :class:`~services.ros2_views.Ros2FleetSink` (clouds and poses in ``map``, the planes as markers);
* ``--http [HOST:]PORT``: :class:`~services.status_page.StatusPage` (the fleet table and a top view).

The first three are subscribers of the fleet like any other client, so they see what the base sees without
touching the base's ingest, ledger or map threads; the status page reads the base station's own status.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
from pathlib import Path
from typing import TYPE_CHECKING, Any

from .errors import ServiceError
from .keys import FleetKeys
from .ros2 import add_ros2_arg

if TYPE_CHECKING:
    from .base import BaseStation

log = logging.getLogger(__name__)


def add_view_args(parser: argparse.ArgumentParser) -> None:
    """Add ``--foxglove``, ``--record``, ``--ros2`` and ``--http`` to ``lrsensor base``."""
    g = parser.add_argument_group("views for other tools")
    g.add_argument(
        "--foxglove",
        metavar="[HOST:]PORT",
        default=None,
        help="serve a Foxglove live view (WebSocket) here, e.g. 8765 (localhost) or 0.0.0.0:8765",
    )
    g.add_argument("--record", metavar="FILE.mcap", default=None, help="record the fleet into this MCAP file")
    add_ros2_arg(g, "the fleet's clouds, poses and planes")
    g.add_argument(
        "--http",
        metavar="[HOST:]PORT",
        default=None,
        help="serve the status page (fleet table, top view of map and tracks) here, e.g. 8080",
    )


def open_views(
    session: Any, keys: FleetKeys, args: argparse.Namespace, station: BaseStation | None = None
) -> contextlib.ExitStack:
    """Start the views ``args`` ask for; closing the returned stack closes them (in reverse order).

    ``station`` is the running base station (needed by ``--http``).
    """
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
        if args.http:
            from .liveview import parse_host_port
            from .status_page import StatusPage

            if station is None:
                msg = "--http needs the base station"
                raise ServiceError(msg)
            host, port = parse_host_port(args.http, "--http")
            page = stack.enter_context(StatusPage(station.status, station.map_json, station.tracks, host, port))
            print(f"status page on {page.url}", flush=True)
    except BaseException:
        stack.close()
        raise
    return stack
