"""Zenoh key expressions of a fleet (CONVENTIONS.md): one place that builds and parses them.

Layout (prefix ``lrs`` by default)::

    <prefix>/<fleet>/<robot>/cloud        one CloudMsg per processed frame
    <prefix>/<fleet>/<robot>/calib        queryable: the robot's calibration (CalibMsg)
    <prefix>/<fleet>/<robot>/alive        liveliness token while the robot is up
    <prefix>/<fleet>/<robot>/status       StatusMsg publications of the robot (counters)
    <prefix>/<fleet>/<robot>/nav          the base's corrected pose of the robot (JSON; also a queryable)
    <prefix>/<fleet>/base/status          queryable: base-station counters as JSON
    <prefix>/<fleet>/base/calib/<robot>   queryable: the fleet's stored calibration of a robot (CalibMsg)
    <prefix>/<fleet>/base/acks/<robot>    queryable: JSON ranges of the sequence numbers the base holds
    <prefix>/<fleet>/map                  queryable: the whole map as JSON
    <prefix>/<fleet>/map/updates          publications: changed planes as JSON
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from .errors import KeyNameError

#: Names that may be used as prefix, fleet or robot: one key chunk, no wildcards or separators.
_NAME_RE = re.compile(r"^[A-Za-z0-9_.\-]{1,64}$")
#: Robot names that would collide with the fleet-level chunks.
RESERVED_ROBOT_NAMES = frozenset({"base", "map"})


def check_name(name: str, what: str) -> str:
    """Return ``name`` if it is a single safe key chunk (letters, digits, ``_ . -``), else raise."""
    if not isinstance(name, str) or not _NAME_RE.match(name) or name in {".", ".."}:
        msg = f"{what} {name!r} is not a valid name: use 1-64 letters, digits, '_', '.' or '-'"
        raise KeyNameError(msg)
    return name


def check_robot_name(name: str) -> str:
    """Like :func:`check_name`, and refuse the reserved chunks ``base`` and ``map``."""
    check_name(name, "robot")
    if name in RESERVED_ROBOT_NAMES:
        msg = f"robot name {name!r} is reserved (it names a fleet-level key); choose another"
        raise KeyNameError(msg)
    return name


@dataclass(frozen=True)
class FleetKeys:
    """The key expressions of one fleet under one prefix."""

    fleet: str
    prefix: str = "lrs"

    def __post_init__(self) -> None:
        check_name(self.prefix, "prefix")
        check_name(self.fleet, "fleet")

    @property
    def root(self) -> str:
        """``<prefix>/<fleet>``."""
        return f"{self.prefix}/{self.fleet}"

    def cloud(self, robot: str) -> str:
        """Cloud publications of one robot."""
        return f"{self.root}/{check_robot_name(robot)}/cloud"

    def calib(self, robot: str) -> str:
        """Calibration queryable served by the robot itself."""
        return f"{self.root}/{check_robot_name(robot)}/calib"

    def alive(self, robot: str) -> str:
        """Liveliness token of one robot."""
        return f"{self.root}/{check_robot_name(robot)}/alive"

    def rov_status(self, robot: str) -> str:
        """StatusMsg publications of one robot."""
        return f"{self.root}/{check_robot_name(robot)}/status"

    def nav(self, robot: str) -> str:
        """The robot's corrected pose as the base station's navigation estimates it (JSON)."""
        return f"{self.root}/{check_robot_name(robot)}/nav"

    @property
    def all_nav(self) -> str:
        """Every robot's corrected pose (the base's queryable)."""
        return f"{self.root}/*/nav"

    @property
    def all_clouds(self) -> str:
        """Every robot's clouds."""
        return f"{self.root}/*/cloud"

    @property
    def all_alive(self) -> str:
        """Every robot's liveliness token."""
        return f"{self.root}/*/alive"

    @property
    def all_rov_status(self) -> str:
        """Every robot's status publications."""
        return f"{self.root}/*/status"

    @property
    def base_status(self) -> str:
        """The base station's status queryable (JSON)."""
        return f"{self.root}/base/status"

    def base_calib(self, robot: str) -> str:
        """The fleet calibration of one robot, served by the base station."""
        return f"{self.root}/base/calib/{check_robot_name(robot)}"

    def base_acks(self, robot: str) -> str:
        """The base station's acknowledgement queryable of one robot: JSON ``{"ranges": [[lo, hi], ...]}``
        of the sequence numbers it holds."""
        return f"{self.root}/base/acks/{check_robot_name(robot)}"

    @property
    def base_acks_all(self) -> str:
        """The base station's acknowledgement queryable (all robots)."""
        return f"{self.root}/base/acks/*"

    @property
    def base_calib_all(self) -> str:
        """The base station's fleet-calibration queryable (all robots)."""
        return f"{self.root}/base/calib/*"

    @property
    def map(self) -> str:
        """The whole-map queryable (JSON)."""
        return f"{self.root}/map"

    @property
    def map_updates(self) -> str:
        """Map change publications (JSON)."""
        return f"{self.root}/map/updates"

    def robot_of(self, key: str) -> str | None:
        """The robot chunk of a per-robot key ``<prefix>/<fleet>/<robot>/...``, or None if it is not one."""
        parts = str(key).split("/")
        if len(parts) < 4 or parts[0] != self.prefix or parts[1] != self.fleet:
            return None
        robot = parts[2]
        if robot in RESERVED_ROBOT_NAMES or not _NAME_RE.match(robot):
            return None
        return robot

    def robot_of_base_key(self, key: str, kind: str) -> str | None:
        """The robot named by a ``<root>/base/<kind>/<robot>`` key (kind ``calib`` or ``acks``), or None."""
        parts = str(key).split("/")
        if len(parts) != 5 or "/".join(parts[:4]) != f"{self.root}/base/{kind}":
            return None
        robot = parts[4]
        if robot in RESERVED_ROBOT_NAMES or not _NAME_RE.match(robot):
            return None
        return robot
