"""The ``Hand`` interface: what softgrasp's executor needs from a hand, simulated or real.

A backend implements a handful of methods. Positions of the fingertips are in the *palm frame*
(the hand's own frame, as a hand driver reports them); the base (the arm carrying the palm) and the
object are in the world frame. SI units: m, N, s.

The built-in backend is :class:`softgrasp.execution.mujoco.hand.MujocoHand`; a hardware driver wraps
its joint servos, its fingertip tactile sensors and the arm, and tracks the object with whatever
the lab has (motion capture, a camera) for :meth:`Hand.object_position`.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

__all__ = ["Hand"]


@runtime_checkable
class Hand(Protocol):
    """A multi-finger hand on a movable base, with fingertip force sensing."""

    @property
    def fingers(self) -> tuple[str, ...]:
        """Names of the fingers the executor drives (``thumb``, ``first``, ``middle``)."""
        ...

    @property
    def time(self) -> float:
        """Seconds since the start (simulated or wall clock)."""
        ...

    def fingertip_positions(self) -> Mapping[str, NDArray[np.float64]]:
        """Measured fingertip sphere centres [m], palm frame."""
        ...

    def fingertip_normal_forces(self) -> Mapping[str, float]:
        """What each fingertip's tactile sensor reads: the force pressing it normal to its skin,
        summed over its contact area [N] (>= 0)."""
        ...

    def fingertip_forces(self) -> Mapping[str, NDArray[np.float64]]:
        """Total force of each fingertip on the object [N], world frame (normal and friction)."""
        ...

    def command_fingertips(self, targets: Mapping[str, NDArray[np.float64]]) -> None:
        """Cartesian position targets of the fingertip centres [m], palm frame (the hand's own
        Cartesian controller, e.g. WDLS inverse kinematics, turns them into joint commands)."""
        ...

    def command_base(self, offset: NDArray[np.float64]) -> None:
        """Move the palm by ``offset`` [m] (world frame) from its starting pose."""
        ...

    def step(self, dt: float) -> None:
        """Let ``dt`` seconds pass with the current commands (simulate, or wait for hardware)."""
        ...

    def object_position(self) -> NDArray[np.float64]:
        """The object's centre of mass [m], world frame."""
        ...
