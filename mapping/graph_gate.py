"""What a robot's pose graph may place in the map: an unbroken track, and associations that are not guesses.

A depth-only robot's pose graph (:mod:`mapping.posegraph`) tracks it from its launch fix while its scans pin both
horizontal directions. Along one wall the direction along it is held by nothing but the velocity prior, and the
marginal grows to 0.1-0.3 m; when the robot then sees a corner again, the graph re-pins it to *a* place of the
symmetric tank, often the wrong one (0.3-0.6 m off) with a marginal of 2-5 cm. Its placed clouds then make wrong
planes, and the other robots' graphs lock onto those. The marginal after such a lock says nothing about whether the
lock is right: only the track before it does.

So a graph places a cloud only while its **track is unbroken**: from the launch on, the marginal's horizontal
standard deviation has stayed below ``GraphConfig.track_break_std_m``. Once it passes that, the track is broken:
nothing more is placed (the status says ``lost``), the graph goes on estimating, and the poses of the clouds placed
before are frozen as they were (a later wrong lock, smoothed backward, would drag them too). A broken track is
taken up again only by a re-localization that matches one place alone (:func:`unique_fix`, with
``GraphConfig.relocalize``).

:func:`ambiguous` is the second hypothesis of a single plane factor (``GraphConfig.second_hypothesis``).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from lrsensor.frames import Pose, R_ned_from_body

from .graph_factors import rot
from .landmarks import PlaneLandmarks, take_planes
from .relocalize import unique_place

FloatArray = NDArray[np.float64]

#: the lever (m) that turns a heading into a distance where directions over position and heading are compared
LEVER_M = 2.0


def ambiguous(
    pid: int,
    n: FloatArray,
    d: float,
    c: FloatArray,
    x: FloatArray,
    down_m: float,
    cov: FloatArray,
    lm: PlaneLandmarks,
    margins: tuple[float, float],
) -> bool:
    """Whether another plane of ``lm`` (facing the same way, a different surface: more than 5 cm from plane ``pid``
    where the scan saw it) would explain the scan's points on ``pid`` as well, within the pose's marginal ``cov``
    (3x3, north/east/heading; 3 sigma along its normal + 5 cm, the heading at a 2 m lever): in a symmetric tank a
    robot that slid along a wall finds a face where it thinks it is, and only the next candidate's distance tells
    the association is a guess.

    Args: ``n``, ``d`` the plane (normal (3,), offset), ``c`` the mean of the scan's points on it in the level
    frame (3,), ``x`` the pose (north, east, heading), ``down_m`` the vehicle's depth, ``margins`` the extent
    margins (across, down; m).
    """
    p = np.array([*(x[0:2] + rot(float(x[2])) @ c[0:2]), down_m + float(c[2])])
    veh = np.array([x[0], x[1], down_m])
    own = float(n @ p) + d
    dist = lm.normal @ p + lm.d
    same_way = lm.normal @ n >= math.cos(math.radians(15.0))
    facing = (veh - p) @ lm.normal.T > 0.0
    rel = p[None, :] - lm.centroid
    pu = np.einsum("pk,pk->p", rel, lm.u)
    pv = np.einsum("pk,pk->p", rel, lm.v)
    m, md = margins
    inside = (pu >= lm.u_range[:, 0] - m) & (pu <= lm.u_range[:, 1] + m)
    inside &= (pv >= lm.v_range[:, 0] - md) & (pv <= lm.v_range[:, 1] + md)
    nh = lm.normal[:, 0:2]
    along = np.einsum("pi,ij,pj->p", nh, cov[0:2, 0:2], nh) + LEVER_M**2 * cov[2, 2]
    gate = 3.0 * np.sqrt(along) + 0.05
    other = (lm.ids != pid) & same_way & facing & inside & (np.abs(dist - own) > 0.05)
    return bool(np.any(other & (np.abs(dist) <= gate)))


class TrackGate:
    """Whether a graph's track is unbroken (see the module docstring), and the placed poses it froze.

    ``break_std_m``: the marginal's horizontal standard deviation (m, the larger axis) past which the track breaks
    (``inf``: never, the behaviour before the gate)."""

    def __init__(self, break_std_m: float) -> None:
        self.break_std_m = float(break_std_m)
        self.broken = False
        #: times the track broke, and was taken up again by a unique re-localization
        self.breaks = 0
        self.relocalized = 0
        #: capture time (ns) -> (north, east, heading) of each placed pose as it was when the track broke
        self.frozen: dict[int, FloatArray] = {}
        #: when the track last broke (ns) and the std then (m); when a re-localization was last tried (ns)
        self.broke_ns = 0
        self.std_at_break = 0.0
        self.tried_ns = -(10**18)
        #: when a scan last matched one place alone (a re-localization or a verification), ns
        self.verified_ns = -(10**18)
        #: when a check first passed (None: not yet; until then the launch fix vouches for the placed clouds)
        self.first_verified_ns: int | None = None
        #: the last passed check's place minus the estimate there (north, east; m) with
        #: ``GraphConfig.commit_at_place``: where its held clouds go in relative to the graph's poses (zero otherwise)
        self.place_shift = np.zeros(2)

    def step(self, std_m: float, t_ns: int) -> bool:
        """The marginal's horizontal std after the scan at ``t_ns``; returns True when this scan broke the track."""
        if self.broken or std_m <= self.break_std_m:
            return False
        self.broken = True
        self.breaks += 1
        self.broke_ns = int(t_ns)
        self.std_at_break = float(std_m)
        return True

    def reach_m(self, t_ns: int, max_speed_m_s: float) -> float:
        """How far (m) a robot whose track broke can be at ``t_ns`` from where its graph placed it at the break: 3
        standard deviations then, the speed bound ``max_speed_m_s`` since, and 10 cm. The re-localization searches
        within it (capped), and the status reports a third of it as the broken track's standard deviation: the
        graph's own marginal then rests on scan odometry that walks off by decimetres while it claims centimetres
        (docs/navigation-design.md, "The odometry while the track is broken")."""
        return 3.0 * self.std_at_break + max_speed_m_s * max(0, int(t_ns) - self.broke_ns) * 1e-9 + 0.1

    def break_now(self, std_m: float, t_ns: int) -> None:
        """Break the track at ``t_ns`` whatever the std (a surprising correction)."""
        if not self.broken:
            self.broken = True
            self.breaks += 1
            self.broke_ns = int(t_ns)
            self.std_at_break = float(std_m)

    def freeze(self, poses: dict[int, FloatArray]) -> None:
        """Keep ``poses`` (t_ns -> north, east, heading) as the clouds placed before a break are (first value
        wins: a pose frozen at an earlier break stays)."""
        for t, x in poses.items():
            self.frozen.setdefault(int(t), np.asarray(x, dtype=np.float64).copy())

    def resume(self) -> None:
        """A unique re-localization: the track is whole again from this scan on."""
        self.broken = False
        self.relocalized += 1

    def state(self) -> dict[str, object]:
        """Plain numbers for a snapshot."""
        return {
            "broken": self.broken,
            "breaks": self.breaks,
            "relocalized": self.relocalized,
            "broke_ns": self.broke_ns,
            "std_at_break": self.std_at_break,
            "tried_ns": self.tried_ns,
            "verified_ns": self.verified_ns,
            "first_verified_ns": self.first_verified_ns,
            "frozen_t": sorted(self.frozen),
            "frozen": [self.frozen[t].tolist() for t in sorted(self.frozen)],
        }

    def load(self, snap: dict[str, object]) -> None:
        """Back to a :meth:`state`."""
        self.broken = bool(snap.get("broken", False))
        self.breaks = int(snap.get("breaks", 0))  # type: ignore[call-overload]
        self.relocalized = int(snap.get("relocalized", 0))  # type: ignore[call-overload]
        self.broke_ns = int(snap.get("broke_ns", 0))  # type: ignore[call-overload]
        self.std_at_break = float(snap.get("std_at_break", 0.0))  # type: ignore[arg-type]
        self.tried_ns = int(snap.get("tried_ns", -(10**18)))  # type: ignore[call-overload]
        self.verified_ns = int(snap.get("verified_ns", -(10**18)))  # type: ignore[call-overload]
        first = snap.get("first_verified_ns")
        self.first_verified_ns = None if first is None else int(first)  # type: ignore[call-overload]
        ts = snap.get("frozen_t", [])
        xs = snap.get("frozen", [])
        self.frozen = {int(t): np.asarray(x, dtype=np.float64) for t, x in zip(ts, xs, strict=True)}  # type: ignore[call-overload]


def relocalize(g: Any, key: int, t: int, raw: Pose, pts: FloatArray, lm: PlaneLandmarks) -> bool:
    """Take the broken track of the pose graph ``g`` (:class:`mapping.posegraph.GraphNav`; its pose ``key`` at
    ``t``, raw pose ``raw``, registration points ``pts`` (M, 3) in the body frame) up again where the scan matches
    one place alone (:func:`mapping.relocalize.unique_place`, within the speed bound since the break): that place
    becomes a prior on this pose. Returns whether it did."""
    gcfg = g.gcfg
    if t - g.track.tried_ns < gcfg.relocalize_every_s * 1e9:
        return False
    g.track.tried_ns = t
    x = g._est[key]
    radius = min(gcfg.relocalize_max_m, g.track.reach_m(t, gcfg.max_speed_m_s))
    rel = pts @ R_ned_from_body(raw.roll_rad, raw.pitch_rad, float(x[2])).T
    place = unique_place(rel, raw.down_m, x[0:2], radius, lm)
    if place is None:
        return False
    g._add("fix", (key,), (float(place[0]), float(place[1]), gcfg.relocalize_sigma_m))
    g._solve()
    g.lost = False
    g.track.resume()
    g.track.verified_ns = t
    return True


def verify(g: Any, key: int, t: int, raw: Pose, pts: FloatArray, lm: PlaneLandmarks) -> str | None:
    """Check the unbroken track of ``g`` (arguments as :func:`relocalize`) against the one place the scan matches
    alone, if any: one more than ``verify_tol_m`` away re-anchors the pose there (a slide or a wrong lock the
    marginal did not show). Returns the motion to report then (``relocalized``), else None."""
    g.track.tried_ns = t
    x = g._est[key]
    rel = pts @ R_ned_from_body(raw.roll_rad, raw.pitch_rad, float(x[2])).T
    place = unique_place(rel, raw.down_m, x[0:2], g.gcfg.verify_radius_m, check_planes(lm, g.robot, g.gcfg))
    if place is None:
        return None
    g.track.verified_ns = t
    off = float(np.hypot(*(place - x[0:2])))
    g.track.place_shift = np.zeros(2)
    if off <= g.gcfg.verify_tol_m:
        if off > g.gcfg.verify_anchor_m:  # passed, yet beside the map's faces: the held clouds go in on them
            g._add("fix", (key,), (float(place[0]), float(place[1]), g.gcfg.relocalize_sigma_m))
            g._solve()
        if g.gcfg.commit_at_place:
            g.track.place_shift = np.asarray(place - g._est[key, 0:2], dtype=np.float64)
        return None
    g._add("fix", (key,), (float(place[0]), float(place[1]), g.gcfg.relocalize_sigma_m))
    g._solve()
    g.track.relocalized += 1
    return "relocalized"


def check_planes(lm: PlaneLandmarks, robot: str, gcfg: Any) -> PlaneLandmarks:
    """The planes a check of ``robot``'s track is made against (:func:`verify`, the hold's
    :func:`mapping.graph_hold.check_held`): every plane but those it contributed more than
    ``GraphConfig.verify_own_share`` of the points to. A robot that slid builds copies of the faces it sees where
    it believes it is; checked against them, it finds itself where it believes it is, and its clouds are
    committed beside the others' faces. ``lm`` unchanged where the share is 1 or more or the contributors are
    unknown."""
    share = float(gcfg.verify_own_share)
    if share >= 1.0 or not lm.contrib:
        return lm
    keep = np.ones(len(lm), dtype=bool)
    for i, c in enumerate(lm.contrib):
        mine = c.get(robot)
        if mine is not None and mine[0] > share * sum(v[0] for v in c.values()):
            keep[i] = False
    return lm if keep.all() else take_planes(lm, keep)
