"""The critical scale: the least multiple of the held state's normal forces that still holds.

The fingers close under force control to ``s`` times the normal forces of the closing's held
state and the hold check runs (:func:`~softgrasp.grasp.force_control.hold_setpoints`, the same
check as the closing's, on the same initial grasp); the critical scale is where held turns into
not held, found by bisection. The planner's set-points are ``safety_factor`` times the normal
forces at the critical scale (:func:`~softgrasp.grasp.planner.plan_grasp`), so a plan's margin
is its safety factor over the least force that holds in softgrasp's model.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from softgrasp.grasp.config import PlanConfig
from softgrasp.grasp.force_control import hold_setpoints
from softgrasp.grasp.setup import ClosingSetup, closing_setup
from softgrasp.linalg.solve import SolverCache
from softgrasp.physics.body import Body

__all__ = ["Margin", "critical_scale"]

#: Tolerances below the guess of the window the search tries first, from its middle.
WINDOW = 4


@dataclass(frozen=True)
class Margin:
    """The critical scale of the held state's normal forces.

    Attributes
    ----------
    scale: the least scale found held (the critical scale, within ``tolerance`` above it).
    not_held: the largest scale found not held (< scale), or 0 if every scale tried held.
    tolerance: the bisection's resolution in scale.
    checks: every scale tried and whether it held.
    systems: Newton systems the search solved (its settle, when made here, and every check's closing
        and hold).
    why_not: why the object was not held at ``not_held`` ("" when every scale tried held).
    """

    scale: float
    not_held: float
    tolerance: float
    checks: tuple[tuple[float, bool], ...]
    systems: int = 0
    why_not: str = ""

    def relative_to(self, factor: float) -> dict[str, object]:
        """The margin as ``plan.json`` states it: scales relative to set-points that are
        ``factor`` times the critical scale's forces (so its critical scale is 1 / factor)."""
        k = 1.0 / (factor * self.scale)
        return {
            "critical_scale": self.scale * k,
            "not_held_scale": self.not_held * k,
            "tolerance": self.tolerance * k,
            "safety_factor": factor,
            "checks": [{"scale": s * k, "held": h} for s, h in self.checks],
        }


def critical_scale(
    body: Body,
    config: PlanConfig,
    normal_N: NDArray[np.float64],
    *,
    guess: float = 1.0,
    lowest: float = 0.5,
    tolerance: float = 0.01,
    setup: ClosingSetup | None = None,
) -> Margin:
    """The least scale of the normal forces ``normal_N`` [N] (3,) at which the object is held
    under force control (``config``, whose ``grasp`` names the initial grasp to close from), to
    ``tolerance``, between ``lowest`` and 1; above 1 (up to 2) when force control does not hold
    at 1 (scale ``inf`` when not even at 2).

    The search starts from ``guess`` (the planner's: the rigid-body utilisation of the held
    squeeze, which lies near the critical scale). Below it, the scales tried lie on the grid
    ``guess - k tolerance`` (k = 0, 1, 2, ...), in the window k = 0..4 first, from its middle:
    k = 2; held there, k = 3 and 4, then doubling steps (k = 8, 16, ...) until a scale does not
    hold (or ``lowest`` does); not held, k = 0 and, held there, k = 1. The bracket found is
    bisected on the grid. (In twenty plans measured, spheres at frictions 0.05-0.8 and several
    meshes, cubes, boxes, cylinders and balls of foam and rubber, fourteen critical scales lay
    below the guess, ten of them 0-2 tolerances below: each of those takes two or three checks.)
    Not held at k = 2 nor at the guess, the search tries 1 (and up) and bisects that bracket to
    ``tolerance``. Where the verdicts grow monotonically with the scale, the bracket below the
    guess is the grid's whatever the order the scales are tried in; a scale is never checked
    twice."""
    setpoints = np.asarray(normal_N, dtype=np.float64)
    checks: dict[float, bool] = {}  # every scale tried, in order, and whether it held
    reasons: dict[float, str] = {}  # why each scale not held was not
    systems: list[int] = []  # the Newton systems of the settle (when made here) and of each check
    if setup is None:
        cache = SolverCache()
        setup = closing_setup(body, config, cache)  # every check closes from the same start
        systems.append(int(cache.stats["systems"]))

    def held(s: float) -> bool:
        if s not in checks:
            check = hold_setpoints(body, config, s * setpoints, setup=setup)
            checks[s] = bool(check.held)
            reasons[s] = "" if check.held else check.reason
            systems.append(check.systems)
        return checks[s]

    def margin(scale: float, not_held: float) -> Margin:
        why = reasons.get(not_held, "")
        return Margin(scale, not_held, tolerance, tuple(checks.items()), sum(systems), why)

    g = float(guess) if np.isfinite(guess) else 1.0
    g = min(max(g, lowest), 1.0)

    def at(k: int) -> float:  # the grid below the guess, down to lowest
        return max(g - k * tolerance, lowest)

    first = WINDOW // 2
    bracket: tuple[int, int | None] | None = None  # (a held k, a k above it not held, once found)
    if held(at(first)):
        bracket = (first, None)
    elif at(0) != at(first) and held(at(0)):
        bracket = (0, first)
    if bracket is not None:
        hi, lo = bracket
        while lo is None:  # down: the window's lower half, then doubling steps
            if at(hi) <= lowest:
                return margin(lowest, 0.0)
            k = hi + 1 if hi < WINDOW else 2 * hi
            if held(at(k)):
                hi = k
            else:
                lo = k
        while lo - hi > 1:  # bisect on the grid
            k = (lo + hi) // 2
            if held(at(k)):
                hi = k
            else:
                lo = k
        return margin(at(hi), at(lo))
    # not held at the guess: up to 1, then beyond (force control ends elsewhere than the closing)
    low, high = g, 1.0 if g < 1.0 else 1.0 / 0.9
    while not held(high):
        if high >= 2.0:
            return margin(float("inf"), high)
        low, high = high, min(2.0, high / 0.9)
    while high - low > tolerance * (1.0 + 1e-9):
        mid = 0.5 * (low + high)
        if held(mid):
            high = mid
        else:
            low = mid
    return margin(high, low)
