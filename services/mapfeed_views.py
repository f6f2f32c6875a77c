"""What the map feed shows: the wire form of map changes, the status's ``map`` part, a robot's navigation status.

Part of :class:`services.mapfeed.MapFeed` (its ``feed`` below), whose methods of the same names serve these.

Wire form of the updates (``<root>/map/updates``, JSON, one message per cloud that changed the map)::

    {"t_ns": capture time of the cloud (or publication time for a flush), "robot", "seq",
     "planes": [plane as in the map JSON, or {"id", "removed": true, "merged_into"}]}

The builder returns typed :class:`mapping.MapChange` values; they become JSON only here, at the wire
(:func:`change_json`), and only when the base publishes. With navigation the planes and poses are served turned by
the fleet's frame (:class:`mapping.navigation.NavFrame`).

Also here: the end-to-end latency statistics (capture time to the moment a cloud is handed to the map) and the
publication-to-base transit times (:class:`LatencyStats`), which the status reports.
"""

from __future__ import annotations

import collections
import json
import threading
from collections.abc import Iterable
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from mapping import MapChange
    from mapping.smoother import FleetPlacements

    from .mapfeed import MapFeed


class LatencyStats:
    """End-to-end latencies (base processing time minus capture time), ns, of the most recent clouds.

    Thread-safe: any thread may :meth:`add` while another asks for percentiles.
    """

    def __init__(self, maxlen: int = 200_000) -> None:
        self.values: collections.deque[int] = collections.deque(maxlen=maxlen)
        self.transit: collections.deque[int] = collections.deque(maxlen=maxlen)
        self._lock = threading.Lock()

    def add(self, latency_ns: int, transit_ns: int | None) -> None:
        """Record one cloud."""
        with self._lock:
            self.values.append(latency_ns)
            if transit_ns is not None:
                self.transit.append(transit_ns)

    def percentiles_ms(self, qs: Iterable[float] = (50, 99), transit: bool = False) -> dict[str, float]:
        """Percentiles in ms (NaN when empty) of the end-to-end latencies, or with ``transit`` of the
        publication-to-base times (meaningful also when a recorded dive with old capture times is replayed)."""
        with self._lock:
            arr = np.asarray(self.transit if transit else self.values, dtype=float)
        return {f"p{q:g}": float(np.percentile(arr, q) / 1e6) if arr.size else float("nan") for q in qs}


def change_json(change: MapChange) -> dict[str, Any]:
    """The wire form of one map change: the plane's serving dict, or ``{"id", "removed", "merged_into"}``."""
    if change.plane is not None:
        return change.plane.to_json()
    return {"id": change.plane_id, "removed": True, "merged_into": change.merged_into}


def json_default(obj: Any) -> Any:
    """``json.dumps`` fallback for numpy values and sets in map data."""
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, set | frozenset | tuple):
        return list(obj)
    msg = f"not JSON serialisable: {type(obj).__name__}"
    raise TypeError(msg)


def map_json(feed: MapFeed) -> dict[str, Any]:
    """The whole map as JSON-ready data (``{"planes": [], "enabled": False}`` when the map is off)."""
    if feed.builder is None:
        return {"planes": [], "enabled": False}
    data: dict[str, Any] = feed.builder.map_json()
    if feed.navigator is not None:
        frame = feed._frame
        data["planes"] = [frame.plane_json(p) for p in data.get("planes", [])]
        data["nav_frame"] = frame.to_json()
    feed._planes = len(data.get("planes", []))
    feed._planes_stale = False
    out: dict[str, Any] = json.loads(json.dumps(data, default=json_default))
    return out


def status_json(feed: MapFeed) -> dict[str, Any]:
    """The ``map`` part of the status JSON."""
    if feed.builder is not None and feed._planes_stale:
        feed._planes = feed.builder.n_planes  # counted under the builder's lock, no JSON built
        feed._planes_stale = False
    with feed._count_lock:
        pending = sum(len(v) for v in feed._pending.values())
    lat = feed.map_latency.percentiles_ms()
    backlog = feed._queue.qsize() + len(feed._order)
    pool = feed.pool.status_json() if feed.pool is not None else None
    if pool is not None:
        pending = pool["in_flight"]  # sent to a worker (or waiting for one), not committed yet
    return (
        {
            "planes": feed._planes,
            "enabled": feed.builder is not None,
            "clouds": feed.clouds,
            "skipped": feed.skipped,
            "unplaced": feed.unplaced,
            "queued": backlog,
            "backlog": backlog,
            "backlog_limit": feed.queue_size,
            "pending": pending,
            "rate_skipped": feed.builder.rate_skipped if feed.builder is not None else 0,
            "latency_ms": {k: (None if v != v else round(v, 3)) for k, v in lat.items()},
            "workers": len(pool["workers"]) if pool is not None else 0,
            "errors": feed.errors,
            "quiet_flushes": feed.quiet.count,
            "order_forced": feed._order.forced,
        }
        | ({"navigation": feed.navigator is not None} if feed.builder is not None else {})
        | ({"smoothing": smoothing_json(feed.fleet)} if feed.fleet is not None else {})
        | ({"worker_pool": pool} if pool is not None else {})
    )


def smoothing_json(fleet: FleetPlacements | None) -> dict[str, Any]:
    """The smoother's runs, the longest and last run's wall time (ms), the longest the map thread was held by
    one (``max_hold_ms``: the runs themselves go on a thread of their own), and the observations re-placed."""
    if fleet is None:
        return {}
    runs = list(fleet.runs_s)
    holds = list(fleet.holds_s)
    return {
        "runs": len(runs),
        "last_ms": round(1e3 * runs[-1], 1) if runs else None,
        "max_ms": round(1e3 * max(runs), 1) if runs else None,
        "max_hold_ms": round(1e3 * max(holds), 1) if holds else None,
        "replaced": fleet.replaced,
    }


def nav_status(feed: MapFeed, robot: str) -> dict[str, Any] | None:
    """What the status says of a robot's navigation: ``placed``/``unplaced`` clouds, the axes its scans
    constrain now, ``position`` (``constrained``, ``partly`` (one horizontal direction: ``degenerate`` then
    gives the free one's bearing, ``{"free_bearing_deg"}``, e.g. along one flat wall), ``unconstrained``,
    ``lost`` (no fix and too uncertain to trust its scans until the next fix), ``unknown``), the horizontal
    and heading standard deviations, how it moved (``motion``); for a robot whose clouds wait for its track's
    checks (``GraphConfig.hold_until_verified``), ``hold``: clouds ``held`` now, ``committed``, ``replaced``,
    ``dropped`` (never placed: no check vouched for them), the mean and largest wait ``lag_mean_s``,
    ``lag_max_s``; ``heading``: for a robot on its pose graph, what its absolute heading rests on (``fixes``,
    ``launch-walls``, ``compass``: :func:`mapping.graph_fleet.heading_source`), else None. None when navigation
    is off or the robot sent nothing yet."""
    with feed._nav_lock:
        est = feed._nav_latest.get(robot)
        counts = list(feed._nav_counts.get(robot, [0, 0]))
    if feed.navigator is None or est is None:
        return None
    js = est.to_json()
    # horizontal directions the scan pinned (an oblique wall pins one, though neither axis alone)
    n_axes = max(est.pinned, sum(1 for a in ("north", "east") if est.constrained.get(a)))
    position = "unknown" if est.pose is None else ("constrained", "partly", "unconstrained")[2 - n_axes]
    if est.motion == "lost":
        position = "lost"
    hold = feed.navigator.hold_counts(robot)
    held = {} if hold is None else {"hold": {k: round(v, 2) if isinstance(v, float) else v for k, v in hold.items()}}
    return held | {
        "placed": counts[0],
        "unplaced": counts[1],
        "position": position,
        "constrained": js["constrained"],
        "unconstrained": js["unconstrained"],
        "north_m_std": js.get("north_m_std"),
        "east_m_std": js.get("east_m_std"),
        "yaw_deg_std": js.get("yaw_deg_std"),
        "motion": est.motion,
        "heading": js["heading"],
        "degenerate": js["degenerate"],
        "t_ns": est.t_ns,
    }
