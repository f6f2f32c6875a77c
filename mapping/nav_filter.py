"""The per-robot navigation filter, :class:`RobotNav`: its five states, prediction, fixes, compass pull, the
scan-to-map registration as the iterated Kalman update, and the estimate it reports.

The method is described in :mod:`mapping.navigation`; the tuning and the estimate are in :mod:`mapping.nav_config`.
"""

from __future__ import annotations

import logging
import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from lrsensor.frames import Pose, R_ned_from_body

from .landmarks import PlaneLandmarks, associate
from .nav_config import NavConfig, NavEstimate, registration_points, scan_constraint
from .nav_error import bound_error, consider_update, error_prediction, rate_gain, rate_weight, young_planes
from .nav_frame import rot2
from .nav_planes import PlaneErrors, PlaneJoint

__all__ = ["RobotNav"]

FloatArray = NDArray[np.float64]
log = logging.getLogger(__name__)


class RobotNav:
    """The estimator of one robot (the method: :mod:`mapping.navigation`). Not thread-safe: one thread feeds it."""

    def __init__(self, robot: str, cfg: NavConfig) -> None:
        self.robot = robot
        self.cfg = cfg
        #: north, east (m), two velocities (m/s: the dead reckoning's bias, or its rate of error with
        #: ``NavConfig.dr_error_state``), the yaw correction (rad), and with ``dr_error_state`` the dead reckoning's
        #: error (raw minus true position, north, east; m)
        self.n = 7 if cfg.dr_error_state else 5
        self.x = np.zeros(self.n)
        self.P = np.eye(self.n)
        self.t_ns: int | None = None
        self.last_raw_ne: FloatArray | None = None
        self.last_fix_ns: int | None = None
        self.latest: NavEstimate | None = None
        #: where the robot started (its first fix), and how many scans constrained its heading
        self.start_ne = np.zeros(2)
        self.yaw_scans = 0
        #: running mean square of the fixes' disagreement with the estimate, per axis (m^2)
        self.fix_err2 = 0.0
        #: running mean of the fixes' disagreement (north, east; m): a persistent one is a drift, not noise
        self.fix_mean = np.zeros(2)
        #: running mean velocity of the registrations' position corrections (north, east; m/s), see
        #: ``NavConfig.dr_bias_open_rate_m_s``; and the time since the previous update (s)
        self.corr_rate = np.zeros(2)
        self._dt = 0.0
        self.last_compass_ns: int | None = None
        #: no fix and an uncertainty past ``lost_std_m``: the scans are not trusted until the next fix
        self.lost = False
        #: the last update's prediction (state, covariance) and transition from the previous state (5x5): what a
        #: smoother (:mod:`mapping.smoother`) needs to run backward; None after a start
        self.prior: tuple[FloatArray, FloatArray] | None = None
        self.transition: FloatArray | None = None
        #: registrations rejected as beyond the motion model's error (see ``NavConfig.gate_chi2``)
        self.gated = 0
        #: whether the map joins this robot's part to another robot's (set by :class:`Navigator` before each update;
        #: see ``NavConfig.own_recent_turns_alone``)
        self.joined = True
        #: whether the velocity bias states are open: always with the bias in the model, with
        #: ``NavConfig.dr_bias_adaptive`` only once this robot's fixes showed a persistent disagreement (a drift)
        self.bias_open = cfg.dr_bias_sigma_m_s > 0 and not cfg.dr_bias_adaptive
        #: with ``NavConfig.dr_error_bound_fraction``: per axis (north, east) the dead reckoning's error when the
        #: scans last pinned the axis (m), the distance travelled (m) and the time (s) since; the last speed (m/s)
        self.pin_d = np.zeros(2)
        self.pin_dist = np.zeros(2)
        self.pin_time = np.zeros(2)
        self._speed = 0.0
        #: with ``NavConfig.plane_fix_jitter_m``: the raw position before the last (north, east; m), and the running
        #: mean square of the raw positions' second differences (m^2) with its weight (a bias-corrected mean)
        self.prev_raw_ne: FloatArray | None = None
        self.jit2 = 0.0
        self.jit_w = 0.0
        #: with ``NavConfig.plane_carry``: the state's cross-covariance with each plane's offset error
        self.planes = PlaneErrors(
            self.n, cfg.plane_sigma_m, cfg.plane_carry_min_corr, estimate=cfg.plane_carry == "estimate"
        )

    _STATE = (
        "t_ns",
        "gated",
        "last_raw_ne",
        "last_fix_ns",
        "start_ne",
        "yaw_scans",
        "fix_err2",
        "fix_mean",
        "last_compass_ns",
        "lost",
        "bias_open",
        "corr_rate",
        "pin_d",
        "pin_dist",
        "pin_time",
        "_speed",
        "prev_raw_ne",
        "jit2",
        "jit_w",
    )

    def snapshot(self) -> dict[str, Any]:
        """The estimator's whole state (a smoother restarts it from here to re-run later scans)."""
        out: dict[str, Any] = {k: getattr(self, k) for k in self._STATE}
        for k in ("pin_d", "pin_dist", "pin_time"):
            out[k] = out[k].copy()  # updated in place
        out.update(x=self.x.copy(), P=self.P.copy(), latest=self.latest, planes=self.planes.copy())
        return out

    def restore(self, snap: dict[str, Any]) -> None:
        """Back to a :meth:`snapshot`."""
        for k in self._STATE:
            setattr(self, k, snap[k])
        for k in ("pin_d", "pin_dist", "pin_time"):
            setattr(self, k, snap[k].copy())
        self.x = snap["x"].copy()
        self.P = snap["P"].copy()
        self.latest = snap["latest"]
        self.planes.restore(snap["planes"])

    @property
    def started(self) -> bool:
        """Whether the robot's position is known (it had a horizontal fix once)."""
        return self.t_ns is not None

    def _start(self, t_ns: int, raw_ne: FloatArray) -> None:
        cfg = self.cfg
        self.x = np.zeros(self.n)
        self.x[0:2] = raw_ne
        self.bias_open = cfg.dr_bias_sigma_m_s > 0 and not cfg.dr_bias_adaptive
        if cfg.dr_bias_sigma_m_s <= 0:
            bias = cfg.init_speed_sigma_m_s
        else:
            bias = cfg.dr_bias_sigma_m_s if self.bias_open else cfg.dr_bias_closed_sigma_m_s
        if cfg.dr_error_state:
            bias = cfg.dr_error_bias_sigma_m_s
        diag = [cfg.launch_sigma_m**2] * 2 + [bias**2] * 2 + [math.radians(cfg.init_yaw_sigma_deg) ** 2]
        if cfg.dr_error_state:
            # the dead reckoning starts at the launch fix: its error is the fix's own noise
            diag += [cfg.dr_error_fix_sigma_m**2] * 2
        self.P = np.diag(diag)
        self.t_ns = t_ns
        self.last_fix_ns = t_ns
        self.start_ne = raw_ne.copy()
        self.fix_err2 = cfg.launch_sigma_m**2
        self.fix_mean = np.zeros(2)
        self.corr_rate = np.zeros(2)
        self.pin_d = np.zeros(2)
        self.pin_dist = np.zeros(2)
        self.pin_time = np.zeros(2)
        self.planes.restore(None)
        self.prev_raw_ne = None
        self.jit2 = self.jit_w = 0.0

    def _jitter(self, raw_ne: FloatArray | None) -> None:
        """Keep the running mean square of the raw positions' second differences (``plane_fix_jitter_m``): an
        absolute fix (a USBL's, the good IMU's) has white errors, so its second differences are its noise times
        sqrt(6) per axis; a dead reckoning's track is smooth, its second differences the motion's millimetres."""
        if raw_ne is None or self.last_raw_ne is None:
            self.prev_raw_ne = None
            return
        if self.prev_raw_ne is not None:
            dd = raw_ne - 2.0 * self.last_raw_ne + self.prev_raw_ne
            a = min(1.0, max(self._dt, 1e-3) / self.cfg.fix_quality_s)
            self.jit2 = (1 - a) * self.jit2 + a * float(dd @ dd) / 2
            self.jit_w = (1 - a) * self.jit_w + a
        self.prev_raw_ne = self.last_raw_ne

    def _white_fixes(self) -> bool:
        """Whether the raw positions' jitter says they are absolute fixes (``plane_fix_jitter_m``; always without
        the option)."""
        lim = self.cfg.plane_fix_jitter_m
        if lim <= 0:
            return True
        if self.jit_w < 1.0 / max(self.cfg.fix_quality_s, 1.0):
            # taken as absolute until a second of fixes tells (the running mean's weight is the time over
            # fix_quality_s): a plane's error matters most while the first scans make the map, and a dead
            # reckoning has not drifted yet then. A robot without fixes rests on the map alone
            return self.last_raw_ne is not None
        return self.jit2 / self.jit_w > (lim * math.sqrt(6.0)) ** 2

    def _predict(self, dt: float, raw_ne: FloatArray | None) -> str:
        cfg = self.cfg
        n = self.n
        q = np.zeros((n, n))
        q[4, 4] = math.radians(cfg.yaw_walk_deg_per_sqrt_s) ** 2 * dt
        if raw_ne is not None and self.last_raw_ne is not None and cfg.dr_error_state:
            self._predict_error(dt, raw_ne - self.last_raw_ne, q)
            motion = "dead-reckoning"
        elif raw_ne is not None and self.last_raw_ne is not None:
            step = rot2(float(self.x[4])) @ (raw_ne - self.last_raw_ne)
            f = np.eye(n)
            # the increment turns with the yaw correction: d(step)/dc = ez x step
            f[0:2, 4] = [-step[1], step[0]]
            self.x[0:2] += step
            if cfg.dr_bias_sigma_m_s > 0 and dt > 0:
                # a current's drag (or any slow velocity bias) moves the robot by bias * dt beyond what the dead
                # reckoning says: the position's error grows with time along whatever no scan pins
                f[0, 2] = f[1, 3] = dt
                self.x[0:2] += self.x[2:4] * dt
                if self.bias_open:
                    q[2, 2] = q[3, 3] = cfg.dr_bias_walk_m_s_per_sqrt_s**2 * dt
            elif dt > 0:
                self.x[2:4] = step / dt
            self.transition = f
            self.P = f @ self.P @ f.T
            var = (cfg.dr_scale_sigma * float(np.hypot(*step))) ** 2 + (cfg.dr_velocity_sigma_m_s * dt) ** 2
            q[0, 0] = q[1, 1] = var
            motion = "dead-reckoning"
        else:
            # without dead reckoning the robot may be anywhere within its speed: a random walk. (A constant-
            # velocity prior looked better on paper; along a single wall its velocity is unobservable, and a
            # wrong one carried the robot metres away while the scans kept its std small across the wall.)
            if self.cfg.dr_bias_sigma_m_s <= 0 and not cfg.dr_error_state:
                self.x[2:4] = 0.0
            self.transition = np.eye(n)
            q[0:2, 0:2] = np.eye(2) * cfg.walk_speed_m_s**2 * max(dt, 1e-3)
            motion = "motion-prior"
        self.P = self.P + q
        if self.transition is not None:
            self.planes.transform(self.transition)
        return motion

    def _predict_error(self, dt: float, dr: FloatArray, q: FloatArray) -> None:
        """The prediction with the dead reckoning's error as a state (:func:`mapping.nav_error.error_prediction`)
        from the raw increment ``dr`` (north, east; m). Adds to ``q`` (the process noise, beside the yaw's), sets
        ``self.transition`` and counts the distance and time since each axis was last pinned."""
        self.pin_dist += float(np.hypot(*dr))
        self.pin_time += max(dt, 0.0)
        self._speed = float(np.hypot(*dr)) / dt if dt > 0 else 0.0
        self.x, f, q_err = error_prediction(self.x, dr, dt, self.cfg)
        self.transition = f
        self.P = f @ self.P @ f.T
        q += q_err

    def _pin(self, h3: FloatArray, inliers: int) -> None:
        """Restart the bound's distance and time along each horizontal axis this scan's registration pinned; d's
        value there is the bound's centre."""
        if not (self.cfg.dr_error_state and self.cfg.dr_error_bound_pins):
            return
        constrained, _, _ = scan_constraint(h3, inliers, self.cfg)
        for axis, name in enumerate(("north", "east")):
            if constrained[name]:
                self.pin_d[axis] = float(self.x[5 + axis])
                self.pin_dist[axis] = 0.0
                self.pin_time[axis] = 0.0

    def _compass(self, t_ns: int) -> None:
        """The compass's bias is bounded: a weak pull of the yaw correction toward zero, at most every
        ``fix_every_s`` (it keeps a heading the scans cannot hold from running away)."""
        cfg = self.cfg
        if self.last_compass_ns is not None and t_ns - self.last_compass_ns < cfg.fix_every_s * 1e9:
            return
        self.last_compass_ns = t_ns
        h = np.zeros((1, self.n))
        h[0, 4] = 1.0
        s = float(self.P[4, 4]) + math.radians(cfg.compass_bias_deg) ** 2
        k = (self.P @ h.T) / s
        self.planes.measured(k, h, np.array([[s]]), np.array([-float(self.x[4])]))
        self.x = self.x - (k * float(self.x[4])).ravel()
        self.P = (np.eye(self.n) - k @ h) @ self.P

    def _fix(self, t_ns: int, raw_ne: FloatArray) -> None:
        cfg = self.cfg
        if self.last_fix_ns is not None and t_ns - self.last_fix_ns < cfg.fix_every_s * 1e9:
            return
        self.last_fix_ns = t_ns
        if cfg.dr_error_state:
            # the raw position is the position plus the dead reckoning's error, at the fix's own white noise
            h = np.zeros((2, self.n))
            h[0, 0] = h[1, 1] = h[0, 5] = h[1, 6] = 1.0
            s = h @ self.P @ h.T + np.eye(2) * cfg.dr_error_fix_sigma_m**2
            k = self.P @ h.T @ np.linalg.inv(s)
            self.planes.measured(k, h, s, raw_ne - h @ self.x)
            self.x = self.x + k @ (raw_ne - h @ self.x)
            self.P = (np.eye(self.n) - k @ h) @ self.P
            return
        # how well the fixes agree with the estimate tells how good they are: a drifting dead reckoning drifts
        # away from what the scans say, a USBL or a good DVL does not
        innov = raw_ne - self.x[0:2]
        a = min(1.0, cfg.fix_every_s / cfg.fix_quality_s) if cfg.fix_every_s > 0 else 0.05
        self.fix_err2 = (1 - a) * self.fix_err2 + a * float(innov @ innov) / 2
        self.fix_mean = (1 - a) * self.fix_mean + a * innov
        err2 = self.fix_err2
        n_fixes = 1.0
        if cfg.dr_bias_sigma_m_s > 0 and not self.bias_open:
            self._open_bias()
        if self.bias_open and cfg.fix_persistence:
            # with the velocity bias in the model the covariance grows as a drift can, and a dead reckoning that
            # drifted away since is no better than its disagreement now (the running mean lags it by seconds)
            err2 = max(err2, float(innov @ innov) / 2)
            # a dead reckoning's error persists (a drift, not noise): its fixes over fix_quality_s are one
            # measurement, not one per fix_every_s; taken as independent they dragged the estimate back to the
            # drift as soon as no scan pinned an axis. Persistence: the disagreement's mean against its RMS
            # (white fixes, a USBL's: about 0; a drift: 1). A disagreement within fix_persist_min_m is what the
            # map's own offset from the fixes leaves (good navigation): those fixes stay independent
            persist = self._persistence()
            if math.sqrt(err2) > cfg.fix_persist_min_m:
                n_fixes = 1.0 + persist * cfg.fix_quality_s / max(cfg.fix_every_s, 1e-3)
        # a robot whose dead reckoning has not shown a drift keeps its fixes at the filter's weight: weighed as a
        # drift's, good fixes let scans registered to a wrong plane carry the estimate, and the fleet's heading, off
        factor = cfg.fix_quality_factor
        if self.bias_open and cfg.fix_quality_factor_open > 0:
            factor = cfg.fix_quality_factor_open
        sigma = min(cfg.fix_sigma_m, max(cfg.fix_min_sigma_m, factor * math.sqrt(err2)))
        sigma *= math.sqrt(n_fixes)
        h = np.zeros((2, self.n))
        h[0, 0] = h[1, 1] = 1.0
        s = h @ self.P @ h.T + np.eye(2) * sigma**2
        k = self.P @ h.T @ np.linalg.inv(s)
        self.planes.measured(k, h, s, raw_ne - self.x[0:2])
        self.x = self.x + k @ (raw_ne - self.x[0:2])
        self.P = (np.eye(self.n) - k @ h) @ self.P

    def _track_corrections(self, dx: FloatArray) -> None:
        """Keep the running mean velocity of the registrations' corrections of the position (north, east; m/s).

        A drifting dead reckoning's prediction runs ahead of the map by its drift every scan, so the scans correct
        it persistently, at the drift's velocity; scans that jump to a wrong plane correct once, by a lot. Each
        correction counts up to what a drift can do in the scan's time (``dr_drift_max_m_s``), so a jump weighs as
        one scan of the fastest drift, not as tens of seconds of one."""
        cfg = self.cfg
        dt = self._dt
        if dt <= 0:
            return
        lim = cfg.dr_drift_max_m_s * dt
        norm = float(np.hypot(*dx))
        v = (dx if norm <= lim else dx * (lim / norm)) / dt
        a = min(1.0, dt / cfg.fix_quality_s)
        self.corr_rate = (1 - a) * self.corr_rate + a * v

    def _persistence(self) -> float:
        """How much the fixes' disagreement persists, 0-1: its running mean against its RMS (white fixes, a USBL's:
        about 0; a drift: 1)."""
        rho = float(self.fix_mean @ self.fix_mean) / max(2.0 * self.fix_err2, 1e-12)
        return min(1.0, max(0.0, (rho - 0.1) / 0.9))

    def _open_bias(self) -> None:
        """With ``NavConfig.dr_bias_adaptive``: open the velocity bias once the fixes' disagreement persists beyond
        ``fix_persist_min_m`` (this robot's dead reckoning drifts), or with ``dr_bias_open_rate_m_s`` once the
        scans' corrections persist at that velocity (:meth:`_track_corrections`). Until then the bias stays held at
        zero: where the poses are good, a free bias only lets registrations against a map's own offsets bend the
        track."""
        cfg = self.cfg
        if cfg.dr_bias_open_rate_m_s > 0:
            # the scans say whether the dead reckoning drifts: their corrections' persistent velocity
            if float(np.hypot(*self.corr_rate)) < cfg.dr_bias_open_rate_m_s:
                return
        elif math.sqrt(self.fix_err2) <= cfg.fix_persist_min_m or self._persistence() < cfg.dr_bias_open_persist:
            return
        self.bias_open = True
        # the drift's velocity is unknown: its launch uncertainty, from now on (the cross terms stay: near zero)
        extra = max(cfg.dr_bias_sigma_m_s**2 - cfg.dr_bias_closed_sigma_m_s**2, 0.0)
        self.P[2, 2] += extra
        self.P[3, 3] += extra
        log.debug("%s: the dead reckoning drifts (fixes %.2f m off, persisting): velocity bias open", self.robot,
                  math.sqrt(self.fix_err2))  # fmt: skip

    def _plane_weights(self, t_ns: int, lm: PlaneLandmarks) -> tuple[FloatArray, NDArray[np.bool_]]:
        """(P,) information weight per plane: ``own_recent_weight`` for a plane only this robot made, first seen by
        it within ``own_recent_s`` (its own recent poses, no absolute information), 1 otherwise; and (P,) whether
        the plane may turn the heading (see ``NavConfig.own_recent_turns_alone``)."""
        cfg = self.cfg
        w = np.ones(len(lm))
        turns = np.ones(len(lm), dtype=bool)
        if not lm.contrib:
            return w, turns
        horizon = t_ns - int(cfg.own_recent_s * 1e9)
        recent_turns = self.joined or cfg.own_recent_turns_alone
        for i, c in enumerate(lm.contrib):
            mine = c.get(self.robot)
            if mine is None or len(c) != 1:
                continue
            if mine[1] >= horizon and (cfg.own_recent_weight < 1.0 or not recent_turns):
                w[i] = min(cfg.own_recent_weight, 1.0 - 1e-9)
                turns[i] = recent_turns
        return w, turns

    def _register(
        self, raw: Pose, points_body: FloatArray, lm: PlaneLandmarks, t_ns: int = 0
    ) -> tuple[FloatArray, int, tuple[int, ...]]:
        """Gauss-Newton MAP update of ``x``/``P`` from point-to-plane residuals; returns the registration's own
        information (3x3 over north, east, yaw correction), the inliers and the planes used."""
        cfg = self.cfg
        h3 = np.zeros((3, 3))
        if len(lm) == 0 or points_body.shape[0] < cfg.min_inliers:
            return h3, 0, ()
        idx = [0, 1, 4]
        x_pred = self.x.copy()
        p_inv = np.linalg.inv(self.P)
        x = x_pred.copy()
        pos_cov = self.P[np.ix_([0, 1], [0, 1])]
        nh = lm.normal[:, 0:2]
        along = np.einsum("pi,ij,pj->p", nh, pos_cov, nh)
        lever2 = 2.0**2 * self.P[4, 4]  # a point 2 m away moves by 2 m * yaw error
        gate = np.clip(3.0 * np.sqrt(along + lever2) + 0.05, cfg.gate_min_m, cfg.gate_max_m)
        inliers = 0
        used: tuple[int, ...] = ()
        plane_w, plane_turns = self._plane_weights(t_ns, lm)
        joint = None
        if cfg.plane_sigma_m > 0 and self._white_fixes():
            joint = PlaneJoint(self, lm)
        elif len(self.planes):
            self.planes.restore(None)
        for it in range(cfg.iterations):
            r_nb = R_ned_from_body(raw.roll_rad, raw.pitch_rad, raw.yaw_rad + float(x[4]))
            veh = np.array([x[0], x[1], raw.down_m])
            rel = points_body @ r_nb.T
            p = rel + veh
            k, dist = associate(p, veh, lm, gate, cfg)
            sel = k >= 0
            inliers = int(sel.sum())
            if inliers < cfg.min_inliers:
                return np.zeros((3, 3)), 0, ()
            n = lm.normal[k[sel]]
            r = dist[sel]
            relh = rel[sel]
            j = np.stack([n[:, 0], n[:, 1], -n[:, 0] * relh[:, 1] + n[:, 1] * relh[:, 0]], axis=1)
            pw = plane_w[k[sel]]
            if joint is not None:
                r = joint.residuals(k[sel], r)
            w = np.minimum(1.0, cfg.huber_m / np.maximum(np.abs(r), 1e-12)) * pw
            # a robot's own planes were placed with its own heading: they hold its position against the dead
            # reckoning's drift, but say nothing about the compass's bias (NavConfig.own_recent_turns_alone)
            j[~plane_turns[k[sel]], 2] = 0.0
            scale = min(1.0, cfg.max_independent_points / inliers) / cfg.point_sigma_m**2
            if joint is not None:
                x, h3 = joint.step(x_pred, x, j, scale * w, r)
            else:
                h3 = scale * (j.T * w) @ j
                g3 = scale * (j.T * w) @ r
                hf = np.zeros((self.n, self.n))
                hf[np.ix_(idx, idx)] = h3
                gf = np.zeros(self.n)
                gf[idx] = g3
                x = np.asarray(np.linalg.solve(p_inv + hf, p_inv @ x_pred + hf @ x - gf), dtype=np.float64)
            if it >= 1:
                # after the first pass the gate only needs to hold the residual noise and what is left
                gate = np.full(len(lm), max(cfg.gate_min_m, 4 * cfg.huber_m))
            used = tuple(int(i) for i in np.unique(lm.ids[k[sel]]))
            hit = k[sel]
        hf = np.zeros((self.n, self.n))
        hf[np.ix_(idx, idx)] = h3
        dx = (x - x_pred)[idx]
        p3 = self.P[np.ix_(idx, idx)]
        if cfg.gate_chi2 > 0 and float(dx @ np.linalg.solve(p3, dx)) > cfg.gate_chi2:
            # a correction the motion model's error cannot explain: a wrong association, not drift
            self.gated += 1
            return np.zeros((3, 3)), 0, ()
        if self.cfg.dr_bias_open_rate_m_s > 0:
            self._track_corrections((x - x_pred)[0:2])
        if joint is not None:
            cov = joint.posterior(lm)
            # the registration's information on the state, the planes' offsets marginalized (consider_update's)
            hf = np.linalg.inv(cov) - p_inv
            hf = 0.5 * (hf + hf.T)
        else:
            cov = np.asarray(np.linalg.inv(p_inv + hf), dtype=np.float64)
        young = cfg.dr_error_rate_young_s > 0 and bool(young_planes(lm, t_ns, cfg.dr_error_rate_young_s)[hit].any())
        w_rate = rate_weight(cfg, young)
        if w_rate < 1.0:
            # the correction moves the position, heading and d; the error's rate takes w_rate of its gain
            self.x, self.P = consider_update(x_pred, self.P, x, cov, hf, rate_gain(self.n, w_rate))
        else:
            self.x = x
            self.P = 0.5 * (cov + cov.T)
        return h3, inliers, used

    def update(self, t_ns: int, raw: Pose, points_body: Any, landmarks: PlaneLandmarks) -> NavEstimate:
        """One cloud: predict, apply a fix, register against ``landmarks``; returns the estimate.

        Args:
            t_ns: capture time, ns since the epoch.
            raw: the pose the robot sent (north/east NaN where it has no horizontal fix).
            points_body: (N, 3) the cloud in the body frame, metres.
            landmarks: the map's planes.

        A cloud older than the last one moves nothing: it is placed with the current correction.
        """
        cfg = self.cfg
        t = int(t_ns)
        pts = registration_points(points_body, cfg)
        raw_ne = np.array([raw.north_m, raw.east_m]) if math.isfinite(raw.north_m + raw.east_m) else None
        self.prior = self.transition = None
        if not self.started:
            if raw_ne is None:
                est = self._estimate(t, raw, np.zeros((3, 3)), 0, (), "unknown", known=False)
                self.latest = est
                return est
            self._start(t, raw_ne)
            self.last_raw_ne = raw_ne
            motion = "start"
        elif self.t_ns is not None and t < self.t_ns:
            return self._estimate(t, raw, np.zeros((3, 3)), 0, (), "late", known=True, keep=True)
        else:
            assert self.t_ns is not None
            dt = (t - self.t_ns) * 1e-9
            self._dt = dt
            if cfg.plane_fix_jitter_m > 0:
                self._jitter(raw_ne)
            motion = self._predict(dt, raw_ne)
            self.prior = (self.x.copy(), self.P.copy())
            self.t_ns = t
            self.last_raw_ne = raw_ne
            if raw_ne is not None:
                self._fix(t, raw_ne)
                self.lost = False
            if cfg.dr_error_state:
                pins = (self.pin_d, self.pin_dist, self.pin_time)
                p_before = self.P
                self.x, self.P = bound_error(self.x, self.P, *pins, self._speed, cfg)
                if len(self.planes) and self.P is not p_before:
                    # the bound's pseudo-measurements are Kalman updates: P_after = (I - K H) P_before
                    self.planes.transform(np.asarray(np.linalg.solve(p_before.T, self.P.T).T, dtype=np.float64))
            self._compass(t)
        if raw_ne is None and math.sqrt(max(float(self.P[0, 0]), float(self.P[1, 1]))) > cfg.lost_std_m:
            # the scans alone could now match the wrong wall of a symmetric tank (seen: placed 5 m off); no
            # scan is trusted again until a fix comes
            self.lost = True
        used: tuple[int, ...] = ()
        if self.lost:
            h3, inliers = np.zeros((3, 3)), 0
            motion = "lost"
        else:
            h3, inliers, used = self._register(raw, pts, landmarks, t)
            self._pin(h3, inliers)
        est = self._estimate(t, raw, h3, inliers, used, motion, known=True)
        self.yaw_scans += int(est.constrained["yaw"])
        self.latest = est
        return est

    def _estimate(
        self,
        t: int,
        raw: Pose,
        h3: FloatArray,
        inliers: int,
        used: tuple[int, ...],
        motion: str,
        *,
        known: bool,
        keep: bool = False,
    ) -> NavEstimate:
        cfg = self.cfg
        constrained, pinned, free_bearing = scan_constraint(h3, inliers, cfg)
        att = cfg.attitude_std_deg
        if not known:
            std = {"north_m": math.inf, "east_m": math.inf, "down_m": cfg.depth_std_m}
            std.update(roll_deg=att, pitch_deg=att, yaw_deg=math.inf)
            return NavEstimate(self.robot, t, None, std, constrained, False, motion)
        sd = np.sqrt(np.maximum(np.diag(self.P), 0.0))
        yaw_std = math.hypot(math.degrees(float(sd[4])), att)
        std = {"north_m": float(sd[0]), "east_m": float(sd[1]), "down_m": cfg.depth_std_m}
        std.update(roll_deg=att, pitch_deg=att, yaw_deg=yaw_std)
        pose = Pose(
            float(self.x[0]), float(self.x[1]), raw.down_m, raw.roll_rad, raw.pitch_rad, raw.yaw_rad + float(self.x[4])
        )
        if keep and self.last_raw_ne is not None and math.isfinite(raw.north_m + raw.east_m):
            # a late cloud: the raw position plus the current offset
            off = self.x[0:2] - self.last_raw_ne
            pose = Pose(
                raw.north_m + off[0], raw.east_m + off[1], pose.down_m, pose.roll_rad, pose.pitch_rad, pose.yaw_rad
            )
        corr = {"yaw_deg": math.degrees(float(self.x[4]))}
        if math.isfinite(raw.north_m + raw.east_m):
            corr.update(north_m=pose.north_m - raw.north_m, east_m=pose.east_m - raw.east_m)
        placed = max(float(sd[0]), float(sd[1])) <= cfg.place_std_m
        if not math.isfinite(raw.north_m + raw.east_m):
            # without a fix only a scan that pins both horizontal axes to the map places its cloud: a motion
            # prior's guess must not grow the map
            placed = placed and constrained["north"] and constrained["east"]
        return NavEstimate(
            self.robot, t, pose, std, constrained, placed, motion, inliers, used, corr, pinned, free_bearing
        )
