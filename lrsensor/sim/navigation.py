"""Realistic navigation for simulated dives: what a small ROV's pose source reports, given its true motion.

Three modes (``NAV_MODES``), selected wherever dives are simulated (:func:`lrsensor.sim.dive.simulate_imu`,
:func:`lrsensor.sim.dive.record_dive`, :func:`mapping.synth.simulate_dive`):

- ``good``: today's navigation solution (:class:`lrsensor.sim.dive.ImuNoise`: a few cm of position noise).
- ``drift``: DVL + compass dead reckoning (:class:`DriftNoise`). The DVL measures the velocity in the body frame
  with a scale error of about 1 %; it is turned into NED with the compass heading, whose bias wanders by 1-2 deg;
  a slow velocity bias (as the drag of a current of a few cm/s) and white noise are added; the result is
  integrated from the launch point. The horizontal position error grows past 0.5 m over a one- to two-minute
  dive. Attitude, heading (with the same compass bias) and depth are reported as measured.
- ``depth-only``: attitude with the slowly varying compass bias, depth, and a horizontal fix at launch only
  (the first sample, or the first ``launch_fix_s``); every later sample has no horizontal position (NaN here,
  an empty ``north_m``/``east_m`` in the CSV of CONVENTIONS "Pose sources").

Everything is vectorized over the samples and seeded by the caller's generator. Angles in radians, SI units.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ..errors import SimulationError

FloatArray = NDArray[np.float64]

#: The navigation modes a simulated dive can have.
NAV_MODES = ("good", "drift", "depth-only")


@dataclass(frozen=True)
class DriftNoise:
    """Errors of a dead-reckoning (DVL + compass) or attitude-and-depth pose source (SI units, radians).

    Attributes:
        scale_error: magnitude of the DVL's distance scale error (its sign drawn from the seed).
        heading_bias_rad: magnitude of the compass's mean heading bias (sign from the seed).
        heading_wander_rad: amplitude of the bias's slow wandering (sum of sinusoids, periods 30-150 s).
        current_m_s: amplitude of the slow velocity bias (a current's drag; periods 40-160 s).
        current_offset_m_s: its constant part, in a direction drawn from the seed.
        velocity_sigma_m_s: white noise on each DVL velocity sample.
        attitude_sigma_rad: white noise on roll, pitch and heading.
        depth_sigma_m: white noise of the depth sensor.
        position_sigma_m: white noise of the launch fix (``depth-only``) and of the reported position.
    """

    scale_error: float = 0.01
    heading_bias_rad: float = math.radians(1.5)
    heading_wander_rad: float = math.radians(0.5)
    current_m_s: float = 0.01
    current_offset_m_s: float = 0.004
    velocity_sigma_m_s: float = 0.01
    attitude_sigma_rad: float = math.radians(0.15)
    depth_sigma_m: float = 0.01
    position_sigma_m: float = 0.005


def check_mode(mode: str) -> str:
    """``mode`` if it is one of :data:`NAV_MODES`, else :class:`~lrsensor.errors.SimulationError`."""
    if mode not in NAV_MODES:
        msg = f"navigation must be one of {', '.join(NAV_MODES)}, got {mode!r}"
        raise SimulationError(msg)
    return mode


def slow_signal(
    rng: np.random.Generator, t_s: FloatArray, period_s: tuple[float, float], n_waves: int = 3
) -> FloatArray:
    """A smooth zero-mean signal of unit RMS: ``n_waves`` sinusoids with periods in ``period_s`` (seconds)."""
    out = np.zeros_like(t_s)
    for _ in range(n_waves):
        f = 1.0 / rng.uniform(*period_s)
        out += np.sin(2 * math.pi * f * t_s + rng.uniform(0, 2 * math.pi))
    return out * math.sqrt(2.0 / n_waves)


def heading_bias(rng: np.random.Generator, t_s: FloatArray, noise: DriftNoise) -> FloatArray:
    """The compass's heading bias over time (M,), radians: a constant of random sign plus a slow wander."""
    sign = 1.0 if rng.uniform() < 0.5 else -1.0
    return sign * noise.heading_bias_rad + noise.heading_wander_rad * slow_signal(rng, t_s, (30.0, 150.0))


def dead_reckon(
    rng: np.random.Generator,
    t_s: FloatArray,
    north_m: FloatArray,
    east_m: FloatArray,
    bias_rad: FloatArray,
    noise: DriftNoise,
) -> tuple[FloatArray, FloatArray]:
    """North/east (M,) integrated from the true launch point with DVL velocities and the biased compass.

    Args:
        t_s: sample times (M,), seconds, increasing.
        north_m, east_m: the true track (M,), metres.
        bias_rad: the compass bias at each sample (M,), radians: the DVL's body-frame velocity is turned into
            NED with the biased heading, so the whole velocity is turned by it.
    """
    m = t_s.size
    if m < 2:
        return north_m.copy(), east_m.copy()
    dt = np.diff(t_s)
    v_n = np.diff(north_m) / dt
    v_e = np.diff(east_m) / dt
    b = 0.5 * (bias_rad[1:] + bias_rad[:-1])
    scale = 1.0 + noise.scale_error * (1.0 if rng.uniform() < 0.5 else -1.0)
    c, s = np.cos(b), np.sin(b)
    mv_n = scale * (c * v_n - s * v_e)
    mv_e = scale * (s * v_n + c * v_e)
    tm = 0.5 * (t_s[1:] + t_s[:-1])
    a = rng.uniform(0, 2 * math.pi)
    mv_n += noise.current_offset_m_s * math.cos(a) + noise.current_m_s * slow_signal(rng, tm, (40.0, 160.0))
    mv_e += noise.current_offset_m_s * math.sin(a) + noise.current_m_s * slow_signal(rng, tm, (40.0, 160.0))
    mv_n += noise.velocity_sigma_m_s * rng.standard_normal(m - 1)
    mv_e += noise.velocity_sigma_m_s * rng.standard_normal(m - 1)
    n = north_m[0] + np.concatenate([[0.0], np.cumsum(mv_n * dt)])
    e = east_m[0] + np.concatenate([[0.0], np.cumsum(mv_e * dt)])
    return n, e


def simulate_navigation(
    mode: str,
    t_s: FloatArray,
    truth: dict[str, FloatArray],
    rng: np.random.Generator,
    noise: DriftNoise | None = None,
    launch_fix_s: float = 0.0,
) -> dict[str, FloatArray]:
    """What a ``drift`` or ``depth-only`` pose source reports along a true track.

    Args:
        mode: ``drift`` or ``depth-only`` (``good`` is :func:`lrsensor.sim.dive.simulate_imu`'s own model).
        t_s: sample times (M,), seconds, increasing.
        truth: the true ``north_m``, ``east_m``, ``down_m``, ``roll_rad``, ``pitch_rad``, ``yaw_rad`` (M,) each.
        rng: the random generator (the caller's seed).
        noise: the error magnitudes (default :class:`DriftNoise`).
        launch_fix_s: ``depth-only``: the samples within this time of the first keep the launch fix (the
            robot sits at its known launch point until its dive starts; a recorded dive's first frame needs
            fixes around it to be posed with one).

    Returns:
        The same six keys, as reported; ``north_m``/``east_m`` are NaN where the source has no horizontal fix
        (``depth-only``: every sample but the first).
    """
    if check_mode(mode) == "good":
        msg = "simulate_navigation models 'drift' and 'depth-only'; 'good' is simulate_imu's ImuNoise"
        raise SimulationError(msg)
    noise = noise or DriftNoise()
    t = np.asarray(t_s, dtype=float)
    m = t.size
    bias = heading_bias(rng, t - t[0], noise)
    att = noise.attitude_sigma_rad
    out = {
        "roll_rad": truth["roll_rad"] + att * rng.standard_normal(m),
        "pitch_rad": truth["pitch_rad"] + att * rng.standard_normal(m),
        "yaw_rad": truth["yaw_rad"] + bias + att * rng.standard_normal(m),
        "down_m": truth["down_m"] + noise.depth_sigma_m * rng.standard_normal(m),
    }
    if mode == "drift":
        n, e = dead_reckon(rng, t - t[0], truth["north_m"], truth["east_m"], bias, noise)
        out["north_m"] = n + noise.position_sigma_m * rng.standard_normal(m)
        out["east_m"] = e + noise.position_sigma_m * rng.standard_normal(m)
    else:
        out["north_m"] = np.full(m, np.nan)
        out["east_m"] = np.full(m, np.nan)
        if m:
            launch = t - t[0] <= launch_fix_s
            err = noise.position_sigma_m * rng.standard_normal(2)
            out["north_m"][launch] = truth["north_m"][launch] + err[0]
            out["east_m"][launch] = truth["east_m"][launch] + err[1]
    return out
