"""Navigation in the plane workers: each robot's estimator runs in the worker that owns the robot.

The worker that extracts a robot's planes also corrects its poses (:class:`WorkerNav`, one
:class:`mapping.navigation.RobotNav` per robot, used only through its public methods). A registered scan uses the
merged map's *snapshot* its capture time names: ``snapshot(T)``, T the grid time at or before its capture time minus
:data:`SNAPSHOT_LAG_S` (:func:`mapping.landmarks.snapshot_time`), the map after exactly the observations before T
in the canonical merge order. The base's merger publishes each snapshot once it is final (:func:`encode_snapshots`,
``<root>/map/landmarks``); a worker holds a robot whose snapshot has not come yet, at most :data:`SNAPSHOT_WAIT_S`
(:mod:`services.map_worker`). One process follows the same rule (``MapBuilder.snapshot_landmarks``), so a scan's
pose, and the map, do not depend on timing. (Jobs without a lag use a mirror of the planes of the moment, sent at
most every :data:`LANDMARKS_EVERY_S`: :func:`encode_landmarks`.)

**Registration stride.** Consecutive scans of a robot at 30 Hz overlap almost fully and its correction (the offset
from the raw fix, the heading correction) changes slowly, so a robot's scan is registered (``RobotNav.update``)
only when at least ``register_every_s`` of capture time passed since its last registration (default 0.19 s: every
sixth scan at 30 Hz, every second at 10 Hz; 5 Hz, the rate the base publishes each robot's estimate at). A scan
in between is placed with the latest correction: the raw position plus the latest offset from the raw fix (without
a fix: the latest corrected position moved on at the velocity of the last two registered positions, at most
:data:`EXTRAPOLATE_S` apart) and the raw heading plus the latest heading correction; it is placed (mapped) when the
latest estimate was. Every cloud still reaches the map.

**State across workers.** Each observation message carries the robot's navigation state after the last cloud it
commits (:meth:`WorkerNav.snapshot`: ``RobotNav.snapshot()`` and the stride's bookkeeping, encoded by
:func:`encode_state`); the base keeps the latest. When the robot moves to another worker, the base sends that state
first and then every cloud not committed yet, so the new worker continues the estimator exactly where the
committed clouds left it (the state is not lost with a SIGKILLed worker). A state that does not encode (a future
estimator with foreign objects in its snapshot) is not sent: the new worker then restarts the robot's estimator
from its next fix, and says so in its log.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from typing import Any

import msgpack
import numpy as np

from lrsensor.frames import Pose

from .errors import ServiceError, WireError

log = logging.getLogger(__name__)

#: The merger publishes its planes to the workers at most this often after a change, seconds (the mirror of
#: the moment, for jobs without a snapshot lag).
LANDMARKS_EVERY_S = 0.1
#: A scan captured at t registers against ``snapshot(T)``, T the grid time at or before t minus this lag (capture
#: time, seconds; :func:`mapping.landmarks.snapshot_time`). A scan waits only when some robot's window that fires
#: before T is not merged yet, i.e. when the workers' queues differ by more than this lag minus a window period
#: (1/3 s at 30 Hz): longer waits less; the registration needs planes, not their last second of change.
SNAPSHOT_LAG_S = 0.7
#: A scan waits at most this long (wall time, seconds) for its snapshot; then it registers against the newest
#: snapshot before it and is counted ``not_exact`` (longer than the merge's hold cap, 2 s, plus transit).
SNAPSHOT_WAIT_S = 3.0
#: Register a robot's scan when at least this much capture time passed since its last registration, seconds.
REGISTER_EVERY_S = 0.19
#: Without a fix, scans between registrations move on at the velocity of the last two registered positions when
#: these are at most this far apart (capture time, seconds); otherwise they keep the latest position.
EXTRAPOLATE_S = 0.5
#: What the base does with a robot that has no horizontal fix after its launch (``lrsensor base --no-fix``):
#: ``lost`` (reported lost, its clouds unplaced) or ``graph`` (its gated pose graph,
#: :data:`mapping.graph_config.TRACKED`, with the graphs' launch frame; docs/navigation-design.md,
#: "Tracked anchors").
NO_FIX_CHOICES = ("lost", "graph")
#: The base's choice when none is given (:func:`resolve_no_fix`; ``lost`` where GTSAM is missing). A worker reads a
#: job without the choice as ``lost`` (:class:`services.map_worker_wire.MapJob`): the base always sends it.
NO_FIX_DEFAULT = "graph"


def resolve_no_fix(no_fix: str | None, navigated: bool = True) -> str:
    """The base's ``--no-fix`` choice (:data:`NO_FIX_CHOICES`) from the one asked for, ``no_fix`` (None: the
    default, :data:`NO_FIX_DEFAULT`).

    ``graph`` needs GTSAM (the ``graph`` extra). By default, where it does not import, the base falls back to
    ``lost`` with one warning naming the extra: a base installed without it still runs, and a depth-only robot's
    clouds stay unplaced rather than crash it. Asked for explicitly, ``graph`` without GTSAM raises
    :class:`~services.errors.ServiceError`: the choice would otherwise leave each such robot on the filter, lost,
    with only a warning when its first clouds arrive. ``navigated`` False (``--nav off`` or no map: no navigator
    runs) skips the check, and the choice stays as asked. Another value raises ``ServiceError``."""
    if no_fix is not None and no_fix not in NO_FIX_CHOICES:
        msg = f"no_fix must be one of {', '.join(NO_FIX_CHOICES)}, got {no_fix!r}"
        raise ServiceError(msg)
    choice = NO_FIX_DEFAULT if no_fix is None else no_fix
    if choice != "graph" or not navigated:
        return choice
    from mapping import posegraph
    from mapping.errors import MapInputError

    try:
        posegraph.gtsam_module()
    except MapInputError as err:
        if no_fix is not None:
            msg = f"--no-fix graph: {err}"
            raise ServiceError(msg) from err
        log.warning("--no-fix defaults to lost (robots without a horizontal fix unplaced): %s", err)
        return "lost"
    return choice


def no_fix_config(cfg: Any, no_fix: str) -> tuple[Any, Any]:
    """``(NavConfig, GraphConfig or None)`` for the choice ``no_fix`` of :data:`NO_FIX_CHOICES` on top of the
    navigation's ``cfg``: ``lost`` leaves ``cfg`` as it is (no graph); ``graph`` turns on
    ``graph_without_fix`` and ``frame_graph_launches`` with :data:`mapping.graph_config.TRACKED`. Raises
    :class:`~services.errors.WireError` (a :class:`~services.errors.ServiceError`) on another value."""
    if no_fix == "lost":
        return cfg, None
    if no_fix == "graph":
        from mapping.graph_config import TRACKED

        return dataclasses.replace(cfg, graph_without_fix=True, frame_graph_launches=True), TRACKED
    msg = f"no-fix choice must be one of {', '.join(NO_FIX_CHOICES)}, got {no_fix!r}"
    raise WireError(msg)


# ---------------------------------------------------------------------------------------------- codec
def _enc(obj: Any) -> Any:
    """A msgpack-ready form of a snapshot value: numbers, strings, None, lists, dicts, ndarrays, tuples, a Pose
    and the navigation's dataclasses (tagged); anything else raises :class:`WireError`."""
    if obj is None or isinstance(obj, bool | int | float | str):
        return obj
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        a = np.ascontiguousarray(obj)
        return {"__nd__": [a.dtype.str, list(a.shape), a.tobytes()]}
    if isinstance(obj, tuple):
        return {"__tuple__": [_enc(v) for v in obj]}
    if isinstance(obj, list):
        return [_enc(v) for v in obj]
    if isinstance(obj, dict):
        return {"__dict__": [[_enc(k), _enc(v)] for k, v in obj.items()]}
    if dataclasses.is_dataclass(obj) and type(obj).__name__ in _classes():
        fields = {f.name: _enc(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
        return {"__dc__": [type(obj).__name__, fields]}
    msg = f"navigation state: cannot encode a {type(obj).__name__}"
    raise WireError(msg)


def _dec(obj: Any) -> Any:
    if isinstance(obj, list):
        return [_dec(v) for v in obj]
    if not isinstance(obj, dict):
        return obj
    if "__nd__" in obj:
        dt, shape, raw = obj["__nd__"]
        return np.frombuffer(raw, dtype=np.dtype(dt)).reshape(shape).copy()
    if "__tuple__" in obj:
        return tuple(_dec(v) for v in obj["__tuple__"])
    if "__dict__" in obj:
        return {_dec(k): _dec(v) for k, v in obj["__dict__"]}
    if "__dc__" in obj:
        name, fields = obj["__dc__"]
        cls = _classes().get(name)
        if cls is None:
            msg = f"navigation state: unknown type {name!r}"
            raise WireError(msg)
        return cls(**{k: _dec(v) for k, v in fields.items()})
    msg = "navigation state: untagged map"
    raise WireError(msg)


def _classes() -> dict[str, type]:
    from mapping.fleet_heading import View
    from mapping.navigation import NavEstimate

    return {"Pose": Pose, "NavEstimate": NavEstimate, "View": View}


def encode_state(state: Any) -> bytes:
    """Bytes of a navigation state (:meth:`WorkerNav.snapshot`, an estimate); raises :class:`WireError` when it
    holds a type this codec does not know."""
    return bytes(msgpack.packb(_enc(state)))


def decode_state(payload: bytes) -> Any:
    """The value :func:`encode_state` encoded (raises :class:`WireError`)."""
    try:
        return _dec(msgpack.unpackb(payload, raw=False, strict_map_key=False))
    except (ValueError, TypeError, KeyError, msgpack.UnpackException) as err:
        msg = f"navigation state does not decode: {err!r}"
        raise WireError(msg) from err


def encode_landmarks(lm: Any, version: int) -> bytes:
    """The map's planes as registration targets (:class:`~mapping.navigation.PlaneLandmarks`), with the map's
    version: what ``<root>/map/landmarks`` carries."""
    fields = {f.name: _enc(getattr(lm, f.name)) for f in dataclasses.fields(lm)}
    return bytes(msgpack.packb({"v": 1, "type": "landmarks", "version": version, "fields": fields}))


def decode_landmarks(payload: bytes) -> tuple[int, Any]:
    """``(version, PlaneLandmarks)`` of :func:`encode_landmarks` (raises :class:`WireError`)."""
    from mapping.navigation import PlaneLandmarks

    try:
        d = msgpack.unpackb(payload, raw=False, strict_map_key=False)
        if d.get("type") != "landmarks":
            msg = "not a landmarks message"
            raise WireError(msg)
        return int(d["version"]), PlaneLandmarks(**{k: _dec(v) for k, v in d["fields"].items()})
    except (ValueError, TypeError, KeyError, AttributeError, msgpack.UnpackException) as err:
        msg = f"landmarks do not decode: {err!r}"
        raise WireError(msg) from err


def encode_snapshots(base_id: str, ranges: list[Any]) -> bytes:
    """Snapshots of the merged map (:class:`~mapping.landmarks.SnapshotRange`) from the merger ``base_id`` (a
    name unique to the merger's run): what ``<root>/map/landmarks`` carries with the snapshot rule."""
    rows = []
    for r in ranges:
        fields = {f.name: _enc(getattr(r.landmarks, f.name)) for f in dataclasses.fields(r.landmarks)}
        rows.append([r.lo_ns, r.hi_ns, r.exact, fields])
    return bytes(msgpack.packb({"v": 1, "type": "snapshots", "base": base_id, "ranges": rows}))


def decode_mirror(payload: bytes) -> tuple[str, Any, Any]:
    """A ``<root>/map/landmarks`` message: ``("snapshots", base_id, [SnapshotRange, ...])`` of
    :func:`encode_snapshots`, or ``("landmarks", version, PlaneLandmarks)`` of :func:`encode_landmarks` (raises
    :class:`WireError`)."""
    from mapping.landmarks import PlaneLandmarks, SnapshotRange

    try:
        d = msgpack.unpackb(payload, raw=False, strict_map_key=False)
        kind = d.get("type")
        if kind == "landmarks":
            return "landmarks", int(d["version"]), PlaneLandmarks(**{k: _dec(v) for k, v in d["fields"].items()})
        if kind != "snapshots":
            msg = f"not a landmarks message: {kind!r}"
            raise WireError(msg)
        out = [
            SnapshotRange(int(lo), int(hi), PlaneLandmarks(**{k: _dec(v) for k, v in f.items()}), bool(exact))
            for lo, hi, exact, f in d["ranges"]
        ]
        return "snapshots", str(d["base"]), out
    except (ValueError, TypeError, KeyError, AttributeError, msgpack.UnpackException) as err:
        msg = f"landmarks do not decode: {err!r}"
        raise WireError(msg) from err


# ---------------------------------------------------------------------------------------------- the estimators
@dataclasses.dataclass(frozen=True)
class NavStep:
    """What navigation decided for one cloud.

    Attributes:
        pose: the pose to place the cloud with (NED, map frame); None: no position.
        placed: whether the cloud goes into the map.
        estimate: the registration's :class:`~mapping.navigation.NavEstimate` when this scan was registered
            (None for a scan placed with the latest correction).
    """

    pose: Pose | None
    placed: bool
    estimate: Any = None


class WorkerNav:
    """The estimators of the robots one worker serves, with the registration stride (see the module docstring).

    Args:
        cfg: the navigation's configuration (default ``NavConfig()``, the base's ``--nav filter``).
        register_every_s: the stride, seconds of capture time (0: register every scan).
        graph_cfg: the pose graphs' tuning (:class:`mapping.graph_config.GraphConfig`; None: its default).

    The base's ``--no-fix`` choice comes with each job (:meth:`set_no_fix`): a worker started on another machine
    navigates as the base says.
    """

    def __init__(self, cfg: Any = None, register_every_s: float = REGISTER_EVERY_S, graph_cfg: Any = None) -> None:
        from mapping.navigation import NavConfig

        self.cfg = cfg or NavConfig()
        self.graph_cfg = graph_cfg
        #: the ``--no-fix`` choice applied last (:meth:`set_no_fix`), the configuration it was applied to
        self.no_fix = "lost"
        self._base_cfg = self.cfg
        self.register_every_s = register_every_s
        self._navs: dict[str, Any] = {}
        #: per robot: capture time of the last registered scan; the registered estimate before the latest
        self._last_reg: dict[str, int] = {}
        self._before: dict[str, Any] = {}
        #: scans registered, scans placed with the latest correction
        self.registered = 0
        self.strided = 0
        #: each robot's launch cloud until its next one says whether it has fixes (a robot without goes to a pose
        #: graph, mapping.posegraph, as in the map thread's Navigator)
        self._launch: dict[str, tuple[int, Pose, Any]] = {}
        self._first_fix: dict[str, int] = {}
        #: the graph robots' views for the fleet heading (services.map_worker_heading: the base estimates it)
        self.heading: Any = None

    def set_no_fix(self, no_fix: str) -> None:
        """Apply the base's ``--no-fix`` choice (:data:`NO_FIX_CHOICES`, :func:`no_fix_config`) to the robots
        whose estimator starts from now on; raises :class:`~services.errors.WireError` on an unknown value."""
        if no_fix == self.no_fix:
            return
        self.cfg, self.graph_cfg = no_fix_config(self._base_cfg, no_fix)
        self.no_fix = no_fix
        self.heading = None

    def _nav(self, robot: str) -> Any:
        nav = self._navs.get(robot)
        if nav is None:
            from mapping.navigation import RobotNav

            nav = self._navs[robot] = RobotNav(robot, self.cfg)
        return nav

    def _to_graph(self, robot: str, nav: Any, raw: Pose, landmarks: Any) -> Any:
        """A robot whose cloud after its launch has no fix: its pose graph from the launch on (without GTSAM it
        keeps the filter)."""
        if not self._graph_next(robot, raw):
            return nav
        launch = self._launch.pop(robot)
        from mapping.errors import MapInputError
        from mapping.posegraph import start_graph

        try:
            graph = self._navs[robot] = start_graph(robot, self.cfg, self.graph_cfg, launch, landmarks)
        except MapInputError as err:
            log.warning("%s: %s; it keeps the filter", robot, err)
            return nav
        if self.heading is not None:
            self.heading.started(robot)
        return graph

    def _graph_next(self, robot: str, raw: Pose) -> bool:
        """Whether ``robot``'s cloud with the raw pose ``raw`` turns it to a pose graph (:meth:`_to_graph`)."""
        return not math.isfinite(raw.north_m + raw.east_m) and robot in self._launch and self.cfg.graph_without_fix

    def due(self, robot: str, t_ns: int, raw: Pose | None = None) -> bool:
        """Whether :meth:`step` registers ``robot``'s scan captured at ``t_ns`` with the raw pose ``raw`` (then it
        needs the landmarks; a pose graph takes every cloud)."""
        nav = self._navs.get(robot)
        if nav is None or (raw is not None and self._graph_next(robot, raw)):
            return True
        last = self._last_reg.get(robot)
        latest = nav.latest
        return (
            last is None
            or not nav.started
            or latest is None
            or latest.pose is None
            or not 0 <= t_ns - last < self.register_every_s * 1e9
            or hasattr(nav, "revised_poses")
        )

    def step(self, robot: str, t_ns: int, raw: Pose, points_body: Any, landmarks: Any, heading: str = "") -> NavStep:
        """One cloud of ``robot``: registered (against ``landmarks``), or placed with the latest correction (a pose
        graph takes every cloud: its odometry pairs consecutive scans). ``heading`` (``MapJob.heading``, the base's
        word): ``collect`` keeps a graph robot's scan for the fleet heading, ``hold`` also holds its cloud until
        the base sends the fleet's biases (:meth:`give_heading`)."""
        nav = self._to_graph(robot, self._nav(robot), raw, landmarks)
        due = self.due(robot, t_ns, raw)
        latest = nav.latest
        if due:
            est = nav.update(t_ns, raw, points_body, landmarks)
            self._keep_launch(robot, nav, t_ns, raw, points_body)
            if heading and hasattr(nav, "revised_poses"):
                est = self._tracker().keep(robot, t_ns, raw, points_body, nav, est, heading == "hold")
            self._last_reg[robot] = t_ns
            self._before[robot] = latest
            self.registered += 1
            return NavStep(est.pose, bool(est.placed and est.pose is not None), est)
        self._keep_launch(robot, nav, t_ns, raw, points_body)
        self.strided += 1
        return NavStep(corrected(latest, raw, self._before.get(robot), t_ns), bool(latest.placed))

    def _keep_launch(self, robot: str, nav: Any, t_ns: int, raw: Pose, points_body: Any) -> None:
        """A cloud with a fix of a robot on the filter: while its fixes are only its launch's, every such cloud (as
        the map thread's ``Navigator``, registered or not) is where its graph starts if they stop."""
        if not nav.started or hasattr(nav, "revised_poses") or not math.isfinite(raw.north_m + raw.east_m):
            return
        first = self._first_fix.setdefault(robot, int(t_ns))
        if t_ns - first <= self.cfg.launch_window_s * 1e9:
            self._launch[robot] = (int(t_ns), raw, points_body)
            if self.cfg.graph_without_fix and self.cfg.fleet_heading:
                self._tracker().launch(robot, int(t_ns), raw, points_body)
        else:
            self._launch.pop(robot, None)

    def _tracker(self) -> Any:
        if self.heading is None:
            from mapping.graph_fleet import FleetHeadingTracker

            self.heading = FleetHeadingTracker(self.cfg)
        return self.heading

    def heading_views(self, robot: str) -> list[Any]:
        """``robot``'s views kept for the fleet heading (:class:`mapping.fleet_heading.View`; empty: none here)."""
        got = self.heading.views.get(robot) if self.heading is not None else None
        return list(got[1]) if got is not None else []

    def give_heading(self, robot: str, bias_rad: float, sd_rad: float, t_ns: int) -> None:
        """The base's estimate of ``robot``'s compass bias (and its standard deviation, radians) at the cloud
        captured at ``t_ns``: its graph retuned and its held clouds committed, as in one process
        (:func:`mapping.graph_fleet.give`); they go into the map with the robot's next cloud (:meth:`released`)."""
        from mapping.graph_fleet import give

        tracker = self._tracker()
        tracker.views.pop(robot, None)
        give(self._navs.get(robot), bias_rad, sd_rad, math.radians(tracker.est_cfg.bias_prior_deg), t_ns)

    def released(self, robot: str) -> list[tuple[int, Pose, Any]]:
        """``robot``'s held clouds its pose graph's last check released to the map (t_ns, pose, body points), in
        capture order (:mod:`mapping.graph_hold`); empty for any other robot."""
        hold = getattr(self._navs.get(robot), "hold", None)
        return hold.take() if hold is not None else []

    def settle(self, robot: str, landmarks: Any) -> list[tuple[int, Pose, Any]]:
        """The robot went silent or the dive ends: its held clouds checked alone; those released (as
        :meth:`released`)."""
        nav = self._navs.get(robot)
        if getattr(nav, "hold", None) is None:
            return []
        nav.settle(landmarks)  # type: ignore[union-attr]
        return self.released(robot)

    def robots(self) -> list[str]:
        """The robots navigated here."""
        return sorted(self._navs)

    def snapshot(self, robot: str) -> dict[str, Any] | None:
        """The robot's whole navigation state (None: it has none here)."""
        nav = self._navs.get(robot)
        if nav is None:
            return None
        return {"nav": nav.snapshot(), "last_reg": self._last_reg.get(robot), "before": self._before.get(robot)}

    def restore(self, robot: str, state: dict[str, Any]) -> None:
        """Continue ``robot`` from a :meth:`snapshot` (of this worker or another)."""
        from mapping.posegraph import GraphNav, is_graph_state

        if is_graph_state(state["nav"]):
            self._navs[robot] = GraphNav(robot, self.cfg, self.graph_cfg)
        self._nav(robot).restore(state["nav"])
        self._before[robot] = state.get("before")
        if state.get("last_reg") is None:
            self._last_reg.pop(robot, None)
        else:
            self._last_reg[robot] = int(state["last_reg"])

    def forget(self, robot: str) -> None:
        """Drop the robot's estimator (it moved away, or restarts)."""
        self._navs.pop(robot, None)
        self._launch.pop(robot, None)
        self._first_fix.pop(robot, None)
        if self.heading is not None:
            self.heading.views.pop(robot, None)
        self._last_reg.pop(robot, None)
        self._before.pop(robot, None)


def corrected(latest: Any, raw: Pose, before: Any = None, t_ns: int | None = None) -> Pose | None:
    """``raw`` at ``t_ns`` with the latest estimate's correction: the raw position plus its offset from the raw fix;
    without a fix now or then, the latest corrected position, moved on at the velocity from the registered estimate
    ``before`` it (when both have a position and are at most ``EXTRAPOLATE_S`` apart); depth and attitude raw, the
    heading plus its correction."""
    if latest.pose is None:
        return None
    corr = latest.correction
    yaw = raw.yaw_rad + math.radians(float(corr.get("yaw_deg", 0.0)))
    if math.isfinite(raw.north_m + raw.east_m) and "north_m" in corr and "east_m" in corr:
        north, east = raw.north_m + float(corr["north_m"]), raw.east_m + float(corr["east_m"])
    else:
        north, east = latest.pose.north_m, latest.pose.east_m
        span = (latest.t_ns - before.t_ns) * 1e-9 if before is not None and before.pose is not None else 0.0
        if t_ns is not None and 0 < span <= EXTRAPOLATE_S:
            ahead = (t_ns - latest.t_ns) * 1e-9 / span
            north += (latest.pose.north_m - before.pose.north_m) * ahead
            east += (latest.pose.east_m - before.pose.east_m) * ahead
    return Pose(north, east, raw.down_m, raw.roll_rad, raw.pitch_rad, yaw)
