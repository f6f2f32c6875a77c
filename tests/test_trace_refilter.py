"""benchmarks.trace_refilter: the live filter and a smoothing run's re-filter, scan by scan."""

from __future__ import annotations

from test_navigation import scene_landmarks

from benchmarks.trace_refilter import RefilterTrace, describe, partings
from lrsensor.frames import Pose
from mapping import smoother as sm
from mapping.navigation import NavConfig
from mapping.smoother import RobotSmoother, SmootherConfig
from mapping.synth import simulate_dive, tank, three_rov_plans


def test_a_run_against_a_map_the_live_filter_lacked_parts_where_it_lacked_it() -> None:
    """The first 30 scans see no map live, the run re-filters them against the tank:
    it parts (by over 1 cm: the fixes hold both) there, not later."""
    scene = tank()
    lm = scene_landmarks(scene)
    empty = type(lm).empty()
    frames = simulate_dive(scene, three_rov_plans()[:1], duration_s=6.0, rate_hz=10.0, n_rays=300, seed=3)
    update = sm.RobotSmoother.update
    with RefilterTrace("r") as trace:
        s = RobotSmoother("r", NavConfig(), SmootherConfig(every_s=1.0, every_fraction=0.0))
        for i, f in enumerate(frames):
            p = f.pose_true
            # dead reckoning 20 cm off north from the second scan on
            raw = Pose(p.north_m + (0.2 if i else 0.0), p.east_m, p.down_m, p.roll_rad, p.pitch_rad, p.yaw_rad)
            s.update(f.t_ns, raw, f.points_body, empty if i < 30 else lm)
        s.smooth(lm)
    assert sm.RobotSmoother.update is update  # the hooks are gone
    assert len(trace.live) == len(frames)
    assert len(trace.runs) == 1
    assert len(trace.runs[0].steps) == len(frames)
    (found,) = partings(trace, 0.01)
    assert found is not None
    _, step, live = found
    assert step.t_ns < frames[30].t_ns
    assert step.planes
    assert not live.planes
    assert partings(trace, 10.0) == [None]
    assert "parts at" in describe(trace, frames[0].t_ns, 0.01)[0]
