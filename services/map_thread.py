"""The base station's one map thread: clouds in capture order -> navigation -> the map builder -> map changes.

Part of :class:`services.mapfeed.MapFeed` (its ``feed`` below; the module docstring there gives the design: the
queue and its back-pressure, when a cloud reaches the map, the clouds the map cannot place). :func:`run` is the
thread's loop (``MapBuilder.add_cloud`` is single-writer, so one thread feeds the map): it takes the clouds in
capture order across robots (:class:`~services.capture_order.CaptureOrder`), places each with :func:`map_one`
(with navigation: the pose corrected from the scan, the clouds a robot's pose graph held until its track's next
check released, the smoother's runs), and when the fleet is quiet settles the held clouds of silent robots
(:func:`settle_silent`) or, at the end of a dive, every window (:func:`end_of_dive`). With plane workers
(:mod:`services.map_workers`) it only dispatches; the workers commit later.

Every failure is counted (``map.errors``) and logged: the map must never stop the ingest.
"""

from __future__ import annotations

import logging
import queue
import time
from typing import TYPE_CHECKING, Any

import numpy as np

from lrsensor.frames import body_to_ned

from .wire import CloudMsg

if TYPE_CHECKING:
    from .mapfeed import MapFeed

log = logging.getLogger(__name__)

#: Marker in the map queue: flush the map.
FLUSH: Any = object()
#: how often an idle map thread looks for silent robots whose clouds wait in their hold (s)
SILENT_CHECK_S = 1.0


def run(feed: MapFeed) -> None:
    """The one thread that feeds the map (``MapBuilder.add_cloud`` is single-writer)."""
    while True:
        try:
            msg = feed._order.next_from(feed._queue, SILENT_CHECK_S)
        except queue.Empty:
            try:
                settle_silent(feed)
                if feed.pool is None and feed.quiet.due(time.monotonic()):
                    end_of_dive(feed)
                    feed.quiet.flushed()
            except Exception as err:  # the map must never stop the ingest
                feed.errors += 1
                log.exception("settling a silent robot's held clouds failed: %s", err)
            continue
        deferred = False
        try:
            if msg is None:
                return
            if msg is FLUSH:
                end_of_dive(feed)
                continue
            feed.quiet.cloud(time.monotonic())
            deferred = feed._map_one(msg)
        except Exception as err:  # the map must never stop the ingest
            feed.errors += 1
            log.exception("map update failed: %s", err)
        finally:
            # taken in (or refused by the map): acknowledgeable; with workers, once committed (_commit_done)
            if isinstance(msg, CloudMsg) and not deferred:
                feed.on_mapped(msg.robot, msg.seq)
            feed._queue.task_done()


def end_of_dive(feed: MapFeed) -> None:
    """A flush (:meth:`MapFeed.flush`, or the fleet silent for ``QuietFlush.quiet_s``): held clouds settled, every
    window extracted, the smoothers' last run, the pending clouds committed."""
    if feed.builder is not None:
        settle(feed)
    feed._publish_changes(None, feed.builder.flush() if feed.builder is not None else [])
    if feed.fleet is not None:  # the map as the last smoothing leaves it
        feed._publish_changes(None, feed.fleet.step("", 0, force=True))
        assert feed.navigator is not None
        feed._frame = feed.navigator.frame()
    for robot in list(feed._pending):
        feed._commit(robot)


def map_one(feed: MapFeed, msg: CloudMsg) -> bool:
    """Place one cloud; True when plane workers will commit (and acknowledge) it later."""
    assert feed.builder is not None
    per_px = feed._per_px.pop((msg.robot, msg.seq), 0.0)
    feed.builder.set_range_error(msg.robot, per_px)  # its clouds' range noise, held ones' too
    if feed.pool is not None and feed.pool.navigate:  # the workers navigate (services.map_worker_nav)
        feed.pool.dispatch(msg.robot, msg.seq, msg.t_ns, msg.pose, msg.points_body, per_px)
        feed.clouds += 1
        return True
    points_body = msg.points_body.astype(np.float64)
    pose = msg.pose
    if feed.fleet is not None:
        # when the robot's smoother is due: past poses re-estimated, their clouds re-placed, the map rebuilt
        feed._publish_changes(None, feed.fleet.step(msg.robot, msg.t_ns))
    if feed.navigator is not None:
        lm = feed.builder.landmarks(feed.navigator.cfg.min_landmark_points)
        est = feed.navigator.update(msg.robot, msg.t_ns, msg.pose, points_body, lm)
        feed._frame = feed.navigator.frame()
        feed._nav_publish(est.turned(feed._frame))
        place_released(feed, msg.robot, feed.navigator.released(msg.robot))
        feed._last_seen[msg.robot] = time.monotonic()
        if est.held:  # received; it goes into the map once its track's next check passes (mapping.graph_hold)
            changes = feed.builder.advance_time(msg.robot, msg.t_ns)  # released clouds due by time
            if feed.builder.uncommitted(msg.robot) == 0:
                feed._commit(msg.robot)
            feed._publish_changes(msg, changes)
            return False
        if est.pose is None or not est.placed:
            feed._count_unplaced(
                msg,
                "navigation has no position for it yet"
                if est.pose is None
                else "navigation's position is too uncertain",
            )
            changes = feed.builder.advance_time(msg.robot, msg.t_ns)  # its placed clouds due by time
            if feed.builder.uncommitted(msg.robot) == 0:
                feed._commit(msg.robot)
            feed._publish_changes(msg, changes)
            return False
        pose = est.pose
        with feed._nav_lock:
            feed._nav_counts.setdefault(msg.robot, [0, 0])[0] += 1
    if feed.pool is not None:
        feed.pool.dispatch(msg.robot, msg.seq, msg.t_ns, pose, msg.points_body, per_px)
        feed.clouds += 1
        return True
    points_ned = body_to_ned(points_body, pose)
    skipped_before = feed.builder.rate_skipped
    changes = feed.builder.add_cloud(msg.robot, msg.t_ns, points_ned, pose)
    if feed.fleet is not None:
        feed.fleet.placed(msg.robot, msg.t_ns, pose)
    feed.clouds += 1
    if feed.builder.rate_skipped == skipped_before:  # not left out by an operator's cap
        with feed._count_lock:
            feed._pending.setdefault(msg.robot, []).append((msg.seq, msg.t_ns))
        if feed.builder.uncommitted(msg.robot) == 0:
            feed._commit(msg.robot)
    feed._publish_changes(msg, changes)
    return False


def place_released(feed: MapFeed, robot: str, released: list[tuple[int, Any, Any]]) -> None:
    """Put a held robot's clouds its last check vouched for into the map (they were acknowledged when they
    came: counted as placed, timed from their capture when their window commits)."""
    assert feed.builder is not None
    hold = feed.navigator.hold_counts(robot) if feed.navigator is not None else None
    dropped = int(hold["dropped"]) if hold is not None else 0
    gone = dropped - feed._dropped.get(robot, 0)
    if gone > 0:  # held clouds no check vouched for: never placed, counted as unplaced now
        feed._dropped[robot] = dropped
        feed.unplaced += gone
        with feed._nav_lock:
            feed._nav_counts.setdefault(robot, [0, 0])[1] += gone
    for t_ns, pose, pts in released:
        feed.clouds += 1
        changes = feed.builder.add_cloud(robot, t_ns, body_to_ned(pts.astype(np.float64), pose), pose)
        if feed.fleet is not None:
            feed.fleet.placed(robot, t_ns, pose)
        with feed._nav_lock:
            feed._nav_counts.setdefault(robot, [0, 0])[0] += 1
        with feed._count_lock:
            feed._pending.setdefault(robot, []).append((-1, t_ns))
        if feed.builder.uncommitted(robot) == 0:
            feed._commit(robot)
        feed._publish_changes(None, changes)


def settle_silent(feed: MapFeed) -> None:
    """Without plane workers: each robot silent for ``IDLE_FLUSH_S`` whose clouds wait in its hold gets them
    checked alone (no later check will come), and its window extracted."""
    if feed.builder is None or feed.navigator is None or feed.pool is not None:
        return
    from .map_workers import IDLE_FLUSH_S

    now = time.monotonic()
    for robot, nav in sorted(feed.navigator.robots.items()):
        hold = getattr(nav, "hold", None)
        if hold is None or not hold.clouds or now - feed._last_seen.get(robot, now) < IDLE_FLUSH_S:
            continue
        lm = feed.builder.landmarks(feed.navigator.cfg.min_landmark_points)
        place_released(feed, robot, feed.navigator.settle(robot, lm))
        feed._publish_changes(None, feed.builder.merge(feed.builder.flush_robot_observations(robot)))
        if feed.builder.uncommitted(robot) == 0:
            feed._commit(robot)


def settle(feed: MapFeed) -> None:
    """The end of a dive: each robot's held clouds checked alone, those vouched for into the map."""
    assert feed.builder is not None
    if feed.navigator is None or feed.pool is not None:
        return
    lm = feed.builder.landmarks(feed.navigator.cfg.min_landmark_points)
    for robot in sorted(feed.navigator.robots):
        place_released(feed, robot, feed.navigator.settle(robot, lm))
