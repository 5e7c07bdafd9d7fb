"""A plan's progress: the phase it is in and the fraction of it done, a fraction that never goes
backwards.

The planner passes through :data:`PHASES` in order; each has a share of the whole
(:data:`SHARES`, about its usual share of the time). Within the closing the fraction done is how
far the squeeze has come towards the grasp test's passing (the larger of the travel's share of the
largest allowed and the inverse of the grasp test's least share ``s`` of the normal forces), so
the bar moves with the physics rather than with the largest allowed travel, which a grasp seldom
nears. The solves for the least passing travel step back and forth inside the last increment:
the fraction reported is the largest reached so far.
"""

from __future__ import annotations

from collections.abc import Callable

__all__ = ["PHASES", "SHARES", "PlanProgress"]

#: The planner's phases, in order.
PHASES = ("initial grasp", "closing", "hold check", "set-points")
#: Each phase's share of the plan's progress (they sum to 1).
SHARES = {"initial grasp": 0.15, "closing": 0.45, "hold check": 0.2, "set-points": 0.2}


class PlanProgress:
    """The planner's progress, reported to two optional callbacks: ``fraction`` (the fraction of
    the plan done, in [0, 1], never smaller than the one before) and ``phase`` (the name of each
    phase of :data:`PHASES` as it starts)."""

    def __init__(
        self,
        fraction: Callable[[float], None] | None = None,
        phase: Callable[[str], None] | None = None,
    ) -> None:
        self._fraction, self._phase = fraction, phase
        self.current: str | None = None
        self.done = 0.0

    def _start(self, name: str) -> float:
        """The fraction of the plan done when phase ``name`` starts."""
        return sum(SHARES[p] for p in PHASES[: PHASES.index(name)])

    def enter(self, name: str) -> None:
        """Phase ``name`` (one of :data:`PHASES`) starts."""
        self.current = name
        if self._phase is not None:
            self._phase(name)
        self.report(self._start(name))

    def report(self, fraction: float) -> None:
        """The plan is ``fraction`` done (a smaller fraction than reported before is not passed on)."""
        if fraction > self.done:
            self.done = min(float(fraction), 1.0)
            if self._fraction is not None:
                self._fraction(self.done)

    def within(self, name: str) -> Callable[[float], None]:
        """A callback taking the fraction done of phase ``name``; it reports only while that phase
        is the current one."""

        def update(fraction: float) -> None:
            if self.current == name:
                self.report(self._start(name) + SHARES[name] * min(max(fraction, 0.0), 1.0))

        return update

    def finish(self) -> None:
        """The plan is done."""
        self.report(1.0)
