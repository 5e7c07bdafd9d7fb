"""What the grasp planner asks of a hand beyond its kinematics: which fingers it plans with and
their roles, and the coarse reach limits of the initial grasp's layout.

A three-finger grasp uses the fingers ``thumb``, ``first`` and ``middle`` (the thumb opposing the
other two, side by side); a two-finger grasp (a parallel-jaw gripper) the fingers ``left`` and
``right``, opposed across the object. :class:`HandReach` bounds the contacts' layout: the spread
between the side-by-side fingers' contacts and the aperture, the distance from the opposing
finger's contact to the others' midpoint (for two fingers: between the two contacts).
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass

from softgrasp.errors import ConfigError

__all__ = ["GRASP_FINGERS", "HandReach", "grasp_fingers"]

#: The finger sets the planner plans with, the opposing finger first.
GRASP_FINGERS: tuple[tuple[str, ...], ...] = (("thumb", "first", "middle"), ("left", "right"))


def grasp_fingers(names: Iterable[str], source: str = "the hand") -> tuple[str, ...]:
    """The planner's fingers among a hand's finger ``names``: thumb, first and middle when all
    three are there, else left and right; ConfigError naming what to map otherwise."""
    have = set(names)
    for fingers in GRASP_FINGERS:
        if have.issuperset(fingers):
            return fingers
    raise ConfigError(
        f"{source} has fingers {', '.join(sorted(have)) or 'none'}; softgrasp plans with thumb, first and "
        "middle (a three-finger hand) or left and right (a two-finger gripper): map them with "
        "--fingertips thumb=LINK,first=LINK,middle=LINK (or left=LINK,right=LINK)"
    )


@dataclass(frozen=True)
class HandReach:
    """Coarse reach limits of a hand's initial grasp [m] (defaults: a Shadow-like hand, whose
    first and middle fingers sit 22 mm apart at the knuckles and abduct to about 90 mm at the
    tips, with a 150 mm thumb-to-fingers aperture).

    Attributes
    ----------
    min_spread, max_spread: distance between the side-by-side fingers' contacts (three fingers).
    max_aperture: largest distance from the opposing finger's contact to the others' midpoint
        (two fingers: between the two contacts; a gripper's largest opening).
    """

    min_spread: float = 0.02
    max_spread: float = 0.09
    max_aperture: float = 0.15

    def __post_init__(self) -> None:
        values = (self.min_spread, self.max_spread, self.max_aperture)
        if not all(math.isfinite(v) for v in values) or not (
            0 < self.min_spread < self.max_spread and self.max_aperture > 0
        ):
            raise ConfigError(
                "hand reach needs 0 < min_spread < max_spread and max_aperture > 0, got "
                f"min_spread = {self.min_spread}, max_spread = {self.max_spread}, "
                f"max_aperture = {self.max_aperture} m"
            )
