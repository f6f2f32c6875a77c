"""One helper that turns the usual network flags into a ``zenoh.Config``.

Flags: ``--mode {peer,client,router}``, ``--connect ENDPOINT`` (repeatable), ``--listen ENDPOINT``
(repeatable), ``--config FILE.json5``. The file is read first; flags given on the command line override it.
Multicast scouting is switched off unless the configuration file sets it (containers and CI have no
multicast; explicit endpoints are the rule in this project).
"""

from __future__ import annotations

import argparse
import json
import logging
import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .errors import NetworkConfigError

log = logging.getLogger(__name__)

MODES = ("peer", "client", "router")
_ENDPOINT_RE = re.compile(r"^(tcp|udp|tls|quic|ws|unixsock-stream|serial)/\S+$")


@dataclass(frozen=True)
class NetworkOptions:
    """The network part of a service's configuration.

    Attributes:
        mode: Zenoh mode, or None for the service's default.
        connect: endpoints to connect to (``tcp/host:port``).
        listen: endpoints to listen on.
        config_file: a Zenoh JSON5 configuration file, read first.
        connect_timeout_ms: for client mode, how long opening waits for a router (-1 forever, 0 fail at once).
        tcp_send_buffer: the kernel send buffer of each TCP link, bytes (``transport/link/tcp/so_sndbuf``; None:
            the system's, which Linux grows to megabytes). Zenoh's priorities act in its own queues; what the
            kernel already holds goes out first whatever its priority, so a ROV on a slow link keeps this short
            (see docs/reliability.md). Not applied when the configuration file sets ``so_sndbuf``.
    """

    mode: str | None = None
    connect: tuple[str, ...] = ()
    listen: tuple[str, ...] = ()
    config_file: str | None = None
    connect_timeout_ms: int | None = None
    tcp_send_buffer: int | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.mode is not None and self.mode not in MODES:
            msg = f"unknown Zenoh mode {self.mode!r}; choose one of {MODES}"
            raise NetworkConfigError(msg)
        for ep in (*self.connect, *self.listen):
            if not _ENDPOINT_RE.match(ep):
                msg = f"invalid Zenoh endpoint {ep!r}: expected e.g. tcp/127.0.0.1:7447"
                raise NetworkConfigError(msg)


def add_network_args(parser: argparse.ArgumentParser, default_mode: str) -> None:
    """Add ``--mode --connect --listen --config`` to a sub-command's parser."""
    g = parser.add_argument_group("Zenoh network")
    g.add_argument("--mode", choices=MODES, default=None, help=f"Zenoh mode (default: {default_mode})")
    g.add_argument(
        "--connect", "-e", action="append", default=[], metavar="ENDPOINT", help="endpoint to connect to (repeat)"
    )
    g.add_argument(
        "--listen", "-l", action="append", default=[], metavar="ENDPOINT", help="endpoint to listen on (repeat)"
    )
    g.add_argument("--config", metavar="FILE.json5", default=None, help="Zenoh configuration file (JSON5)")


def options_from_args(args: argparse.Namespace, **overrides: Any) -> NetworkOptions:
    """The :class:`NetworkOptions` of parsed flags."""
    return NetworkOptions(
        mode=args.mode,
        connect=tuple(args.connect or ()),
        listen=tuple(args.listen or ()),
        config_file=args.config,
        **overrides,
    )


def make_config(options: NetworkOptions, default_mode: str = "peer") -> Any:
    """Build the ``zenoh.Config`` of ``options`` (file first, then flags; multicast scouting off)."""
    import zenoh

    if options.config_file:
        path = Path(options.config_file)
        if not path.is_file():
            msg = f"Zenoh configuration file {path} does not exist"
            raise NetworkConfigError(msg)
        try:
            conf = zenoh.Config.from_file(str(path))
        except Exception as err:
            msg = f"{path}: invalid Zenoh configuration: {err}"
            raise NetworkConfigError(msg) from err
        text = path.read_text(encoding="utf-8", errors="replace")
        scouting_set = "multicast" in text
        sndbuf_set = "so_sndbuf" in text
    else:
        conf = zenoh.Config()
        scouting_set = sndbuf_set = False
    try:
        if options.mode is not None or not options.config_file:
            conf.insert_json5("mode", json.dumps(options.mode or default_mode))
        if options.connect:
            conf.insert_json5("connect/endpoints", json.dumps(list(options.connect)))
        if options.listen:
            conf.insert_json5("listen/endpoints", json.dumps(list(options.listen)))
        if not scouting_set:
            conf.insert_json5("scouting/multicast/enabled", "false")
        if options.tcp_send_buffer is not None and not sndbuf_set:
            conf.insert_json5("transport/link/tcp/so_sndbuf", json.dumps(int(options.tcp_send_buffer)))
        if options.connect_timeout_ms is not None:
            conf.insert_json5("connect/timeout_ms", json.dumps(options.connect_timeout_ms))
        for key, value in options.extra.items():
            conf.insert_json5(key, json.dumps(value))
    except Exception as err:
        msg = f"cannot apply Zenoh network options {options}: {err}"
        raise NetworkConfigError(msg) from err
    return conf


def open_session(options: NetworkOptions, default_mode: str = "peer") -> Any:
    """Open a Zenoh session; connection failures become :class:`NetworkConfigError` with the endpoints."""
    import zenoh

    conf = make_config(options, default_mode)
    try:
        return zenoh.open(conf)
    except Exception as err:
        where = ", ".join(options.connect or options.listen) or options.config_file or "defaults"
        msg = f"cannot open a Zenoh session ({options.mode or default_mode}, {where}): {err}"
        raise NetworkConfigError(msg) from err


def endpoints(host: str, ports: Sequence[int]) -> list[str]:
    """``tcp/<host>:<port>`` for each port."""
    return [f"tcp/{host}:{p}" for p in ports]


def undeclare_all(entities: Iterable[Any], where: str) -> None:
    """Undeclare Zenoh entities (publishers, subscribers, queryables, tokens), in the given order.

    A failure (the session already closed, the router gone) is logged at debug level and the others are still
    undeclared: closing must not fail half way.
    """
    for entity in entities:
        try:
            entity.undeclare()
        except Exception as err:
            log.debug("%s: undeclare failed: %s", where, err)
