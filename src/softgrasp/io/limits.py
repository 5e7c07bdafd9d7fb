"""The physical ranges of the numbers ``softgrasp execute`` reads: its options and the fields of a
``plan.json``, checked before any simulation (SI units).

A value outside its range is refused with a :class:`~softgrasp.errors.ConfigError` that names the
option or field, the range and the unit. The ranges are those of a soft object grasped by a
three-fingered hand and simulated by MuJoCo with a 2 ms step: a stiffness, friction or force far
outside them either means a unit slip in the file or cannot be simulated stably.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

from softgrasp.errors import ConfigError

__all__ = ["Range", "PLAN_RANGES", "EXECUTE_RANGES", "MAX_SETPOINT_N"]


class Range(NamedTuple):
    """An interval of physical values: ``lo`` .. ``hi`` [``unit``], ``lo`` excluded when
    ``open_lo``, ``hi`` excluded when ``open_hi``."""

    lo: float
    hi: float
    unit: str = ""
    open_lo: bool = False
    open_hi: bool = False

    def describe(self, name: str = "x") -> str:
        """The range in words, e.g. ``0 < x <= 0.5 m``."""
        lo = f"{self.lo:g} {'<' if self.open_lo else '<='}"
        hi = f"{'<' if self.open_hi else '<='} {self.hi:g}"
        return f"{lo} {name} {hi}{(' ' + self.unit) if self.unit else ''}"

    def contains(self, v: float) -> bool:
        """Whether ``v`` is a finite value inside the range."""
        if not math.isfinite(v):
            return False
        above = v > self.lo if self.open_lo else v >= self.lo
        below = v < self.hi if self.open_hi else v <= self.hi
        return above and below

    def check(self, value: Any, what: str, prefix: str = "") -> float:
        """``value`` as a float; :class:`ConfigError` (``prefix`` then ``what``, the option or
        field) unless it is a number inside the range."""
        try:
            v = math.nan if isinstance(value, bool) else float(value)
        except (TypeError, ValueError, OverflowError):
            v = math.nan
        if not isinstance(value, int | float) or not math.isfinite(v):
            raise ConfigError(f"{prefix}{what} must be a finite number, got {_short(value)}")
        if not self.contains(v):
            unit = f" {self.unit}" if self.unit else ""
            raise ConfigError(
                f"{prefix}{what} = {v:g}{unit} is not physical: it must be {self.describe(what)}"
            )
        return v


def _short(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


#: Largest set-point a fingertip is asked to press with [N] (after ``--scale``).
MAX_SETPOINT_N = 100.0

#: The range of each number of ``plan.json`` that ``execute`` reads.
PLAN_RANGES: dict[str, Range] = {
    "object.mass_kg": Range(0.0, 10.0, "kg", open_lo=True),
    "object.material.E_Pa": Range(1e2, 1e9, "Pa"),
    "object.material.nu": Range(0.0, 0.5, open_hi=True),
    "parameters.contact.mu": Range(0.0, 10.0),
    "parameters.fingertip_radius_m": Range(0.0, 0.05, "m", open_lo=True),
    "parameters.table_mu": Range(0.0, 10.0),
    "setpoint_N": Range(0.0, MAX_SETPOINT_N, "N", open_lo=True),
}

#: The range of each numeric option of ``softgrasp execute`` (and of :func:`softgrasp.execute`).
EXECUTE_RANGES: dict[str, Range] = {
    "--lift": Range(0.0, 0.5, "m", open_lo=True),
    "--hold": Range(0.0, 60.0, "s"),
    "--scale": Range(0.0, 10.0, open_lo=True),
}
