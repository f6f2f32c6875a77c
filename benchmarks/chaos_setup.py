"""What a chaos soak is given (:mod:`benchmarks.bench_chaos`): its parameters and the network it runs over.

:class:`ChaosConfig` holds one soak's parameters; the tether between the robots' and the surface's namespaces
is ``tests/netlink.py``'s veth pair (:class:`netlink.NetLink`, impaired as :data:`TETHER`), or, without root
or ``iptables`` (:func:`netlink.unavailable`), :class:`Loopback`: everything on this host's loopback, without
impairments or flaps (:func:`open_net` picks one). The router is the bare router of ``tests/procs.py``. This
module puts ``tests/`` on the import path for those two and re-exports what the soak uses of them.
"""

from __future__ import annotations

import contextlib
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT / "tests") not in sys.path:  # tests/netlink.py and tests/procs.py, as a script or as -m
    sys.path.insert(0, str(ROOT / "tests"))

from netlink import LinkSpec, LoggedProcesses, NetLink, unavailable, zenoh_config  # noqa: E402
from procs import router_cmd  # noqa: E402

FLEET = "chaos"
#: The tether of the soak: moderate impairments (the link tests cover the harsh ones).
TETHER = LinkSpec(rate_mbit=10.0, loss=0.05, delay_ms=100.0)
ROUTER_PORT = 7447


@dataclass(frozen=True)
class ChaosConfig:
    """One soak's parameters.

    Attributes:
        fault_s: how long faults are injected, seconds.
        robots: how many robots.
        rate_hz: each robot's replay rate, frames/s.
        dive_frames: frames of the recorded dive every robot replays (a dive lasts ``dive_frames / rate_hz``).
        seed: the fault schedule's seed.
        fault_every_s: mean gap between two faults, seconds.
        flap_s: shortest and longest link flap, seconds.
        heal_s: how long the end waits for every robot to deliver everything, at most, seconds.
        ack_timeout_s: the robots' ``--ack-timeout-s``.
        spec: the tether's impairments.
        loopback: run on loopback even where namespaces are available.
        cloud_schema: the robots' ``--cloud-schema``.
    """

    fault_s: float = 1800.0
    robots: int = 3
    rate_hz: float = 5.0
    dive_frames: int = 300
    seed: int = 1
    fault_every_s: float = 45.0
    flap_s: tuple[float, float] = (10.0, 60.0)
    heal_s: float = 600.0
    ack_timeout_s: float = 60.0
    spec: LinkSpec = TETHER
    loopback: bool = False
    cloud_schema: int = 2


class Loopback(LoggedProcesses):
    """Everything on this host's loopback: the stand-in for :class:`netlink.NetLink` without root (no flaps)."""

    ns_base = ns_rov = ""

    def __init__(self, workdir: Path) -> None:
        from services.testnet import free_port

        super().__init__(workdir)
        self.zenoh_port = free_port()

    def rov_endpoint(self) -> str:
        return f"tcp/127.0.0.1:{self.zenoh_port}"

    def link_bytes(self) -> dict[str, int]:
        return {"up_bytes": 0, "down_bytes": 0, "up_packets": 0, "down_packets": 0}

    def set_up(self, up: bool) -> None:  # no link to take down on loopback
        return

    def close(self) -> None:
        self.stop_processes()


@contextlib.contextmanager
def open_net(cfg: ChaosConfig, workdir: Path) -> Iterator[NetLink | Loopback]:
    """The tether between namespaces, or loopback when namespaces are unavailable (or ``cfg.loopback``)."""
    if cfg.loopback or unavailable() is not None:
        net = Loopback(workdir)
        try:
            yield net
        finally:
            net.close()
        return
    with NetLink(cfg.spec, workdir) as link:
        yield link


__all__ = [
    "FLEET",
    "ROOT",
    "ROUTER_PORT",
    "TETHER",
    "ChaosConfig",
    "LinkSpec",
    "Loopback",
    "NetLink",
    "open_net",
    "router_cmd",
    "unavailable",
    "zenoh_config",
]
