"""A depth-only robot's clouds go into the map only once its track is verified (``GraphConfig.hold_until_verified``).

A tracked pose graph (:data:`mapping.graph_config.TRACKED`) is checked every ``verify_every_s``: the scan's points
must match one place of the map alone, within ``verify_tol_m`` of the estimate. Between two checks the robot can
slide along a wall its scans do not pin while its marginal says a few centimetres; the check finds the slide, but
the clouds placed meanwhile would stay in the map as copies of its faces, and the other robots would lock onto
them. So a tracked robot's clouds are **held** (received and acknowledged, not in the map, not landmarks for
anyone) from one passed check to the next:

- **passed** (the scan's unique place agrees with the estimate): every held cloud is committed with the pose the
  graph now estimates for it (smoothed with every scan since);
- **slid** (the check re-anchored the track) or **broke** (the marginal passed ``track_break_std_m``), and at
  **the end** (a flush, a silent robot: :meth:`mapping.posegraph.GraphNav.settle`): each held cloud is checked on
  its own at the pose the graph now gives it. One whose scan matches one place alone
  (:func:`mapping.relocalize.unique_place` within ``hold_check_radius_m``) within ``verify_tol_m`` of that pose is
  re-placed with it. One whose scan pinned a single direction when it came (one wall: its points lie on surfaces
  facing that way, so a slide along the free direction copies none of them) is re-placed where its points fit the
  map's planes (:func:`mapping.relocalize.fits_at`). The others are dropped (counted: :attr:`CloudHold.dropped`).

Until a robot's first check passes its launch fix vouches for its clouds (they are placed at once: the map the
checks need is made from them). While clouds wait, a check that found no unique place (one scan along a wall) is
tried again every ``hold_retry_s``. The map then lags such a robot by about one check's period on average, longer
where no scan matches one place (benchmarks/results/nav.md). Robots with fixes are never held.

Frames and units: clouds in the body frame (M, 3, metres, float32), poses NED (map frame), times in ns.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from lrsensor.frames import Pose, R_ned_from_body

from .graph_gate import check_planes
from .landmarks import PlaneLandmarks
from .nav_config import registration_points
from .relocalize import RelocConfig, fits_at, unique_place

FloatArray = NDArray[np.float64]


@dataclass
class HeldCloud:
    """One held cloud: the graph's pose key, capture time (ns), raw pose (depth, roll, pitch measured) and its
    finite body-frame points (M, 3) float32."""

    key: int
    t_ns: int
    raw: Pose
    points: NDArray[np.float32]
    #: horizontal directions its scan pinned to the map when it came (:attr:`NavEstimate.pinned`)
    pinned: int = 0


@dataclass
class CloudHold:
    """The clouds of one graph robot held since its last passed check, what was released to the map (until the
    caller takes it: :meth:`take`) and the counts the status reports."""

    clouds: list[HeldCloud] = field(default_factory=list)
    #: (t_ns, pose, body points) to place now, in capture order
    out: list[tuple[int, Pose, NDArray[np.float32]]] = field(default_factory=list)
    #: clouds committed after a passed check, re-placed after a slide (checked alone), dropped
    committed: int = 0
    replaced: int = 0
    dropped: int = 0
    #: how long clouds waited (s, capture time of the scan that released them minus theirs): sum and largest
    lag_sum_s: float = 0.0
    lag_max_s: float = 0.0

    def take(self) -> list[tuple[int, Pose, NDArray[np.float32]]]:
        """The released clouds not taken yet (the caller places them: ``MapBuilder.add_cloud``)."""
        out, self.out = self.out, []
        return out

    def counts(self) -> dict[str, float]:
        """The plain numbers of the status: ``held`` now, ``committed``, ``replaced``, ``dropped``, the mean and
        largest wait (s)."""
        n = self.committed + self.replaced
        return {
            "held": len(self.clouds),
            "committed": self.committed,
            "replaced": self.replaced,
            "dropped": self.dropped,
            "lag_mean_s": self.lag_sum_s / n if n else 0.0,
            "lag_max_s": self.lag_max_s,
        }

    def state(self) -> dict[str, Any]:
        """Plain numbers and arrays for a snapshot (the held clouds move with the robot to another worker)."""
        return {
            "keys": [c.key for c in self.clouds],
            "t": [c.t_ns for c in self.clouds],
            "raw": [_raw(c.raw) for c in self.clouds],
            "points": [c.points for c in self.clouds],
            "pinned": [c.pinned for c in self.clouds],
            "n": [self.committed, self.replaced, self.dropped],
            "lag": [self.lag_sum_s, self.lag_max_s],
        }

    def load(self, snap: dict[str, Any]) -> None:
        """Back to a :meth:`state` (released clouds not taken are not part of it: the caller took them)."""
        keys = snap.get("keys", [])
        cols = (
            keys,
            snap.get("t", []),
            snap.get("raw", []),
            snap.get("points", []),
            snap.get("pinned", [0] * len(keys)),
        )
        self.clouds = [
            HeldCloud(int(k), int(t), Pose(*(float(v) for v in r)), np.asarray(p, np.float32).reshape(-1, 3), int(n))
            for k, t, r, p, n in zip(*cols, strict=True)
        ]
        self.committed, self.replaced, self.dropped = (int(v) for v in snap.get("n", [0, 0, 0]))
        self.lag_sum_s, self.lag_max_s = (float(v) for v in snap.get("lag", [0.0, 0.0]))


def _raw(p: Pose) -> list[float]:
    return [p.north_m, p.east_m, p.down_m, p.roll_rad, p.pitch_rad, p.yaw_rad]


def hold_step(g: Any, key: int, t: int, raw: Pose, points_body: Any, est: Any, lm: PlaneLandmarks, moved: bool) -> Any:
    """The hold's part of one scan of the graph ``g`` (pose ``key`` at ``t``; ``est`` its
    :class:`~mapping.nav_config.NavEstimate`, ``moved`` whether a check or re-localization re-anchored it): hold
    the cloud when it may be placed, and act on this scan's check. Returns ``est``, with ``placed`` False and
    ``held`` True when the hold took the cloud (what goes into the map then comes from :meth:`CloudHold.take`)."""
    track = g.track
    if track.broken and track.broke_ns == t:
        check_held(g, t, lm)  # the track broke: nothing after the last passed check vouches for the held ones
    if track.verified_ns == t and moved:
        check_held(g, t, lm)  # a slide found: each held cloud on its own, this one is where the check put it
    if track.first_verified_ns is None and track.verified_ns == t:
        track.first_verified_ns = t
    if est.placed and track.first_verified_ns is not None:
        # before the first check passed the launch fix vouches (the map the checks need is made from these clouds)
        hold_cloud(g, key, t, raw, points_body, est.pinned)
        est = replace(est, placed=False, held=True)
    if track.verified_ns == t:
        commit_held(g, t)
    return est


def check_due(g: Any, t: int) -> bool:
    """Whether the unbroken track of ``g`` is checked at the scan of ``t``: every ``verify_every_s``, and while it
    holds clouds, again every ``hold_retry_s`` until a check finds one place (one scan along a wall finds none: the
    next may, and the held clouds wait less)."""
    gcfg, track = g.gcfg, g.track
    if t - track.tried_ns >= gcfg.verify_every_s * 1e9:
        return True
    waiting = gcfg.hold_until_verified and bool(g.hold.clouds) and t - track.verified_ns >= gcfg.verify_every_s * 1e9
    return bool(waiting and t - track.tried_ns >= gcfg.hold_retry_s * 1e9)


def hold_cloud(g: Any, key: int, t: int, raw: Pose, points_body: Any, pinned: int = 0) -> None:
    """Hold the cloud of pose ``key`` of the graph ``g`` (:class:`mapping.posegraph.GraphNav`; ``pinned``: the
    horizontal directions its scan pinned)."""
    pts = np.asarray(points_body, dtype=np.float32).reshape(-1, 3)
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    g.hold.clouds.append(HeldCloud(int(key), int(t), raw, pts, int(pinned)))


def commit_held(g: Any, t: int) -> None:
    """A passed check at ``t``: every held cloud to the map, with the pose the graph estimates for it now (with
    ``GraphConfig.commit_at_place``: moved by the check's place minus the estimate, and frozen there)."""
    hold: CloudHold = g.hold
    dn, de = (float(v) for v in g.track.place_shift)
    g.track.place_shift = np.zeros(2)  # this check's alone
    if not hold.clouds:
        return
    poses = g.revised_poses()
    for c in hold.clouds:
        pose = poses.get(c.t_ns)
        if pose is None:  # left the graph's window: its scans are no longer re-estimated, nothing vouches for it
            hold.dropped += 1
            continue
        if dn or de:
            # at a passed check the place is nearer the truth than the graph's estimate, which keeps where its own
            # earlier scans put the planes: the clouds go in where the place says, and stay (the graph's later
            # estimates would take them back beside the faces)
            pose = replace(pose, north_m=pose.north_m + dn, east_m=pose.east_m + de)
            g.track.freeze({c.t_ns: np.array([pose.north_m, pose.east_m, pose.yaw_rad])})
        _release(hold, c, pose, t)
        hold.committed += 1
    hold.clouds = []


def check_held(g: Any, t: int, lm: PlaneLandmarks) -> None:
    """A slide or a broken track (or the end) at ``t``: each held cloud to the map where its own scan matches one
    place alone, within ``verify_tol_m`` of the pose the graph gives it now; the others dropped."""
    hold: CloudHold = g.hold
    if not hold.clouds:
        return
    poses = g.revised_poses()
    gcfg = g.gcfg
    lm = check_planes(lm, g.robot, gcfg)
    one_wall = RelocConfig(min_share=gcfg.hold_one_wall_share)
    for c in hold.clouds:
        pose = poses.get(c.t_ns)
        if pose is None:
            hold.dropped += 1
            continue
        pts = registration_points(c.points, g.cfg)
        rel = pts @ R_ned_from_body(c.raw.roll_rad, c.raw.pitch_rad, pose.yaw_rad).T
        at = np.array([pose.north_m, pose.east_m])
        place = unique_place(rel, c.raw.down_m, at, gcfg.hold_check_radius_m, lm)
        if place is not None:
            ok = float(np.hypot(*(place - at))) <= gcfg.verify_tol_m
        else:
            # no unique place: a scan that pinned one direction (one wall) sees surfaces facing that way only, so a
            # slide along the free one copies none of them; it goes in where its points fit the map's planes
            ok = c.pinned == 1 and fits_at(rel, c.raw.down_m, at, lm, one_wall)
        if not ok:
            hold.dropped += 1
            continue
        _release(hold, c, pose, t)
        hold.replaced += 1
    hold.clouds = []


def _release(hold: CloudHold, c: HeldCloud, pose: Pose, t: int) -> None:
    hold.out.append((c.t_ns, pose, c.points))
    lag = (int(t) - c.t_ns) * 1e-9
    hold.lag_sum_s += lag
    hold.lag_max_s = max(hold.lag_max_s, lag)
