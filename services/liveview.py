"""The base station's live view: the fleet in Foxglove over its WebSocket protocol (``lrsensor base --foxglove``).

A :class:`~services.fleet_tap.FleetTap` with a :class:`~services.foxglove_views.FoxgloveSink` logs on a
foxglove context whose one sink is foxglove-sdk's WebSocket server (protocol ``foxglove.sdk.v1``, protobuf
messages). A Foxglove app connected to ``ws://HOST:PORT`` sees:

* ``/<prefix>/<fleet>/<robot>/points``: each cloud in ``<robot>/base_link`` (set the 3D panel's decay time to
  keep the last seconds), placed in ``ned`` through ``/tf`` where the robot has a horizontal position;
* ``/<prefix>/<fleet>/map``: the map's planes, the whole map every ``map_refresh_s`` for viewers that join
  late, and each update as it happens;
* ``/<prefix>/<fleet>/tracks``: each robot's track;
* ``/<prefix>/<fleet>/status``: the base station's status JSON every ``status_period_s``.

Viewers connect to the base station's machine only: the default host is 127.0.0.1; give another host to serve
a ship's network on purpose.
"""

from __future__ import annotations

from typing import Any

from .errors import ServiceError
from .fleet_tap import FleetTap
from .foxglove_views import FoxgloveSink, import_foxglove
from .keys import FleetKeys

#: The Foxglove live view's default port (Foxglove's own default).
DEFAULT_PORT = 8765


class LiveViewError(ServiceError):
    """The live view cannot start (a bad ``HOST:PORT``, the port is taken)."""


def parse_host_port(text: str, flag: str = "--foxglove", default_host: str = "127.0.0.1") -> tuple[str, int]:
    """``"[HOST:]PORT"`` -> ``(host, port)``; a clear :class:`LiveViewError` naming ``flag`` otherwise."""
    host, sep, port_s = text.rpartition(":")
    host = host if sep else default_host
    if not port_s.isdigit() or not 0 <= int(port_s) <= 65535 or (sep and not host):
        msg = f"{flag} takes [HOST:]PORT with a port 0-65535, got {text!r}"
        raise LiveViewError(msg)
    return host, int(port_s)


class LiveView:
    """A Foxglove WebSocket server showing the fleet of ``keys`` (see the module docstring).

    Args:
        session: an open Zenoh session (the caller owns it; the base station passes its own).
        keys: the fleet's key expressions.
        host: address to listen on.
        port: port to listen on (0: any free port, see :attr:`port`).
        map_refresh_s: the whole map is sent again this often, seconds.
        status_period_s: the base station's status is sent this often, seconds.
    """

    def __init__(
        self,
        session: Any,
        keys: FleetKeys,
        host: str = "127.0.0.1",
        port: int = DEFAULT_PORT,
        *,
        map_refresh_s: float = 5.0,
        status_period_s: float = 1.0,
    ) -> None:
        foxglove = import_foxglove()
        context = foxglove.Context()
        try:
            self.server = foxglove.start_server(name=f"lrsensor {keys.root}", host=host, port=port, context=context)
        except Exception as err:
            msg = f"the Foxglove live view cannot listen on {host}:{port}: {err}"
            raise LiveViewError(msg) from err
        self.host = host
        sink = FoxgloveSink(context, keys.root, raw=False, tracks=True, status=True)
        self.tap = FleetTap(session, keys, [sink], map_refresh_s=map_refresh_s, status_period_s=status_period_s)

    @property
    def port(self) -> int:
        """The port the server listens on."""
        return int(self.server.port)

    @property
    def url(self) -> str:
        """``ws://host:port`` for a Foxglove app's "Open connection"."""
        return f"ws://{self.host}:{self.port}"

    def stats(self) -> dict[str, Any]:
        """What the view has sent (:class:`~services.fleet_tap.TapCounters` as JSON)."""
        return self.tap.stats()

    def close(self) -> None:
        """Stop the tap and the server."""
        self.tap.close()
        self.server.stop()

    def __enter__(self) -> LiveView:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
