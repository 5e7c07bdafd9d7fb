"""The plan's margin: the scale of its set-points below which the object is no longer held.

The fingers close under force control to ``s`` times the set-points and the hold check runs
(:func:`~softgrasp.grasp.force_control.hold_setpoints`, the same check as the plan's, on the
plan's contacts); the critical scale is where held turns into not held, found by bisection. A
plan made with ``safety_factor`` > 1 carries that factor's margin above it; a real hand's forces
and friction vary, and an independent engine (MuJoCo) needs a few per cent more.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from softgrasp.grasp.force_control import hold_setpoints
from softgrasp.grasp.result import GraspPlan
from softgrasp.physics.body import Body

__all__ = ["Margin", "critical_scale"]


@dataclass(frozen=True)
class Margin:
    """The critical scale of a plan's set-points.

    Attributes
    ----------
    scale: the least scale found held (the critical scale, within ``tolerance`` above it).
    not_held: the largest scale found not held (< scale), or 0 if every scale tried held.
    tolerance: the bisection's resolution in scale.
    checks: every scale tried and whether it held.
    """

    scale: float
    not_held: float
    tolerance: float
    checks: tuple[tuple[float, bool], ...]

    def describe(self) -> dict[str, object]:
        return {
            "critical_scale": self.scale,
            "not_held_scale": self.not_held,
            "tolerance": self.tolerance,
            "checks": [{"scale": s, "held": h} for s, h in self.checks],
        }


def critical_scale(body: Body, plan: GraspPlan, *, lowest: float = 0.5, tolerance: float = 0.02) -> Margin:
    """Bisect the scale of ``plan``'s normal-force set-points between ``lowest`` and 1 for the
    least that the object is held at (the hold check of the plan, under force control on the
    plan's contacts), to ``tolerance``."""
    cfg = replace(plan.config, grasp=plan.initial)
    setpoints = np.array([f.normal_force for f in plan.fingers])
    checks: list[tuple[float, bool]] = []

    def held(s: float) -> bool:
        ok = bool(hold_setpoints(body, cfg, s * setpoints).held)
        checks.append((s, ok))
        return ok

    hi = 1.0
    if not held(hi):  # force control ends elsewhere than the position-controlled closing
        hi = min(2.0, 1.0 / 0.9)
        while not held(hi):
            if hi >= 2.0:
                return Margin(float("inf"), hi, tolerance, tuple(checks))
            hi = min(2.0, hi / 0.9)
    lo = lowest
    if held(lo):
        return Margin(lo, 0.0, tolerance, tuple(checks))
    while hi - lo > tolerance:
        mid = 0.5 * (lo + hi)
        if held(mid):
            hi = mid
        else:
            lo = mid
    return Margin(hi, lo, tolerance, tuple(checks))
