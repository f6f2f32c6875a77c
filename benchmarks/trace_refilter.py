"""Where a smoother run's re-filter parts from the live filter (issue 27): one robot's states, scan by scan.

:class:`RefilterTrace` hooks :class:`mapping.smoother.RobotSmoother` and :class:`mapping.smoother.SmoothJob` for
the length of a ``with`` block (a diagnostic: the hooks are removed on exit) and records, for one robot, the state
after each scan in the live filter and in each run's re-filter (position, the velocity states, with
``NavConfig.dr_error_state`` the dead reckoning's error; the planes registered to). :func:`partings` gives per run
the first scan where the re-filter's position leaves the live filter's by more than a threshold, and the planes
it registered to there that the live filter did not; ``diag_extracted_poses --trace-refilter ROBOT`` prints them.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from types import TracebackType
from typing import Any

import numpy as np

from mapping import smoother as sm
from mapping.types import FloatArray


@dataclass(frozen=True)
class Step:
    """One scan through a filter: its capture time (ns), the state after it (S,) and its standard deviations
    (S,) (north, east m; the two velocity states m/s; yaw correction rad; with the error state d north, east m),
    the points registered and the planes registered to."""

    t_ns: int
    x: FloatArray
    std: FloatArray
    inliers: int
    planes: tuple[int, ...]


@dataclass
class Run:
    """One smoothing run of the traced robot: its re-filter's steps, whether its result was refused."""

    steps: list[Step] = field(default_factory=list)
    refused: bool = False


class RefilterTrace:
    """Records ``robot``'s live filter (:attr:`live`, t_ns -> :class:`Step`) and each run's re-filter
    (:attr:`runs`) while the ``with`` block runs."""

    def __init__(self, robot: str) -> None:
        self.robot = robot
        self.live: dict[int, Step] = {}
        self.runs: list[Run] = []
        self._saved: list[tuple[Any, str, Any]] = []

    def __enter__(self) -> RefilterTrace:
        trace = self
        update, run, refilter = sm.RobotSmoother.update, sm.SmoothJob.run, sm._refilter
        current: list[Run | None] = [None]

        def traced_update(self: sm.RobotSmoother, t_ns: int, raw: Any, points: Any, lm: Any) -> Any:
            est = update(self, t_ns, raw, points, lm)
            if self.robot == trace.robot:
                trace.live[int(t_ns)] = _step(self.nav, int(t_ns), est)
            return est

        def traced_refilter(nav: Any, scans: list[Any], lm: Any) -> None:
            rec = current[0]
            if rec is None:
                refilter(nav, scans, lm)
                return
            for s in scans:
                refilter(nav, [s], lm)
                if s.est is not None:
                    rec.steps.append(_step(nav, s.t_ns, s.est))

        def traced_run(self: sm.SmoothJob, lm: Any) -> None:
            if self.robot != trace.robot:
                run(self, lm)
                return
            current[0] = rec = Run()
            trace.runs.append(rec)
            try:
                run(self, lm)
            finally:
                current[0] = None
            rec.refused = self.refused

        hooks: list[tuple[Any, str, Any, Any]] = [
            (sm.RobotSmoother, "update", update, traced_update),
            (sm.SmoothJob, "run", run, traced_run),
            (sm, "_refilter", refilter, traced_refilter),
        ]
        for owner, name, _, hook in hooks:
            setattr(owner, name, hook)
        self._saved = [(owner, name, old) for owner, name, old, _ in hooks]
        return self

    def __exit__(self, kind: type[BaseException] | None, err: BaseException | None, tb: TracebackType | None) -> None:
        for owner, name, value in self._saved:
            setattr(owner, name, value)
        self._saved = []


def _step(nav: Any, t_ns: int, est: Any) -> Step:
    return Step(t_ns, nav.x.copy(), np.sqrt(np.diag(nav.P)), int(est.inliers), tuple(int(p) for p in est.planes))


def partings(trace: RefilterTrace, threshold_m: float = 0.1) -> list[tuple[int, Step, Step] | None]:
    """Per run of ``trace``: the first scan where its re-filter's horizontal position is over ``threshold_m`` (m)
    from the live filter's, as (run index, the re-filter's step, the live filter's step); None where it never is."""
    out: list[tuple[int, Step, Step] | None] = []
    for k, run in enumerate(trace.runs):
        found = None
        for s in run.steps:
            lv = trace.live.get(s.t_ns)
            if lv is not None and float(np.hypot(*(s.x[:2] - lv.x[:2]))) > threshold_m:
                found = (k, s, lv)
                break
        out.append(found)
    return out


def describe(trace: RefilterTrace, t0_ns: int, threshold_m: float = 0.1) -> list[str]:
    """One line per run: where its re-filter first parts from the live filter (s of the dive, cm, cm/s)."""
    lines = []
    for k, p in enumerate(partings(trace, threshold_m)):
        run = trace.runs[k]
        ends = [(run.steps[i].t_ns - t0_ns) * 1e-9 for i in (0, -1)] if run.steps else []
        span = f"{ends[0]:.1f}-{ends[1]:.1f} s" if ends else "-"
        if p is None:
            lines.append(f"run {k} ({span}): within {100 * threshold_m:.0f} cm of the live filter")
            continue
        _, s, lv = p
        new = sorted(set(s.planes) - set(lv.planes))
        lines.append(
            f"run {k} ({span}): parts at {(s.t_ns - t0_ns) * 1e-9:.1f} s by "
            f"{100 * float(np.hypot(*(s.x[:2] - lv.x[:2]))):.1f} cm; "
            f"rate {100 * s.x[2]:+.1f}, {100 * s.x[3]:+.1f} cm/s "
            f"(live {100 * lv.x[2]:+.1f}, {100 * lv.x[3]:+.1f}); planes {list(s.planes)} (live {list(lv.planes)}, "
            f"new {new})"
        )
    return lines
