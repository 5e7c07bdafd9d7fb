"""The physical range of every number a user gives softgrasp, checked at the door.

One table (:data:`RANGES`) holds, for each option (named as in config files and sweeps), the
interval of values that describe a soft object a robot hand can grasp, and the unit; the command
line states it in ``--help`` and refuses a value outside it before any work, and config files,
sweep files and the Python API check the same intervals. :func:`check_object_size` refuses an
object whose size is outside :data:`OBJECT_SIZE_M`, naming the length unit (``--units``) that
would fit; :func:`check_object_mass` an object to grasp whose mass is outside
:data:`OBJECT_MASS_KG` (lighter than 1 g, or heavier than the hand's payload), naming ``--density``
and ``--mass``. SI units throughout.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Sequence
from dataclasses import dataclass

from softgrasp.errors import ConfigError, MeshError, SoftgraspError

__all__ = [
    "Range",
    "RANGES",
    "UNITS",
    "VOLUME_TERMS",
    "OBJECT_SIZE_M",
    "OBJECT_MASS_KG",
    "check",
    "check_units",
    "check_volume_term",
    "check_object_size",
    "check_object_mass",
]

#: Length units of mesh files and shape sizes: name -> metres per unit.
UNITS: dict[str, float] = {"m": 1.0, "cm": 1e-2, "mm": 1e-3}

#: The volume terms a body may have: one per tet or one per node
#: (:attr:`softgrasp.physics.body.Body.volume`).
VOLUME_TERMS = ("element", "nodal")

#: Sizes of an object a hand can grasp [m]: its thinnest side at least 1 mm (thinner is a film,
#: whose forces a mass-spring mesh cannot resolve), its largest at most 0.5 m (beyond a hand's span).
OBJECT_SIZE_M = (1e-3, 0.5)

#: Masses of an object a hand grasps and lifts [kg]: at least 1 g (lighter, its weight is below
#: what the fingertips' force sensing resolves and the grasp test decides nothing), at most 2 kg:
#: the payload of a fingertip grasp, whose three fingertips press some 10 N each (a dexterous
#: hand's, such as the Shadow hand's) and, with friction near 1, carry about 2 kg.
OBJECT_MASS_KG = (1e-3, 2.0)


def _g(x: float) -> str:
    return f"{x:g}"


@dataclass(frozen=True)
class Range:
    """The interval ``[low, high]`` of one option (an end excluded where ``low_open`` or
    ``high_open``), its unit, whether it takes integers only, and why its ends are where they are."""

    low: float
    high: float
    unit: str = ""
    low_open: bool = False
    high_open: bool = False
    integer: bool = False
    why: str = ""

    @property
    def text(self) -> str:
        """The interval for people: ``(0, 60] s``, ``1 to 60``."""
        if self.integer:
            return f"{int(self.low)} to {int(self.high)}"
        lo = "(" if self.low_open else "["
        hi = ")" if self.high_open else "]"
        interval = f"{lo}{_g(self.low)}, {_g(self.high)}{hi}"
        return f"{interval} {self.unit}" if self.unit else interval

    @property
    def expected(self) -> str:
        """What a value must be, for messages: ``a number in (0, 60] s``, ``an integer from 1 to 60``."""
        return f"an integer from {self.text}" if self.integer else f"a number in {self.text}"

    def contains(self, value: float) -> bool:
        """Whether the finite number ``value`` lies in the interval."""
        above = value > self.low if self.low_open else value >= self.low
        below = value < self.high if self.high_open else value <= self.high
        return above and below

    def check(self, name: str, value: object, error: type[SoftgraspError] = ConfigError) -> float:
        """``value`` as a float (an int for an integer range) when it is a finite number inside the
        interval; else ``error`` naming the option ``name``, the interval and the value."""
        if isinstance(value, bool) or not isinstance(value, numbers.Real):
            raise error(f"{name} must be {self.expected}, got {value!r}")
        try:
            v = float(value)
        except OverflowError:  # an integer beyond the floats
            v = math.inf
        if self.integer and not (isinstance(value, numbers.Integral) or v.is_integer()):
            raise error(f"{name} must be {self.expected}, got {value!r}")
        if not (math.isfinite(v) and self.contains(v)):
            shown = _g(v) + (f" {self.unit}" if self.unit else "")
            why = f" ({self.why})" if self.why else ""
            if self.unit == "m" and v > self.high and self.contains(v * 1e-3):
                why += f"; lengths are in metres: for {_g(v)} mm write {_g(v * 1e-3)}"
            raise error(f"{name} must be {self.expected}, got {shown}{why}")
        return int(value) if self.integer else v  # type: ignore[return-value]


#: Every numeric option's range, by its name in config files and sweeps (command-line flags are
#: the same names with dashes).
RANGES: dict[str, Range] = {
    # The object.
    "mesh_size": Range(1e-5, 0.25, "m", why="element size; at most half the object's thinnest side as well"),
    "E": Range(10.0, 1e9, "Pa", why="from the softest gels (tens of Pa) to stiff plastics (1 GPa)"),
    "nu": Range(-1.0, 0.5, low_open=True, high_open=True, why="0.5 is incompressible; use e.g. 0.49"),
    "density": Range(1.0, 25_000.0, "kg/m^3", why="from ultralight foams to the densest metals"),
    "mass": Range(1e-6, 100.0, "kg", why="from a milligram to what no hand lifts"),
    "a2": Range(-1000.0, 1000.0, why="a coefficient of the polynomial stress-strain law"),
    "a3": Range(-1000.0, 1000.0, why="a coefficient of the polynomial stress-strain law"),
    # The fingertips and their contact.
    "mu": Range(0.0, 5.0, why="friction coefficients of real surfaces stay below about 2"),
    "fingertip_radius": Range(5e-4, 0.1, "m", why="robot and human fingertips are 5-20 mm"),
    "radius": Range(5e-4, 0.1, "m", why="robot and human fingertips are 5-20 mm"),
    "plate_friction": Range(0.0, 5.0, why="friction coefficients of real surfaces stay below about 2"),
    # The plan.
    "step": Range(1e-6, 0.01, "m", why="closing increment; also smaller than the fingertip radius"),
    "safety_factor": Range(1.0, 20.0, why="a multiple of the least normal forces that hold"),
    "hold_time": Range(0.0, 60.0, "s", low_open=True, why="simulated holding time"),
    "max_squeeze": Range(0.0, 1.0, low_open=True, high_open=True, why="a fraction of each finger's reach"),
    "refine": Range(1, 60, integer=True),
    "max_pressure": Range(0.0, 1e9, "Pa", low_open=True),
    "max_strain": Range(0.0, 1.0, low_open=True),
    # The hand's layout limits (config files): contacts' spread and the aperture.
    "min_spread": Range(0.001, 0.5, "m", why="distance between side-by-side fingers' contacts"),
    "max_spread": Range(0.001, 0.5, "m", why="distance between side-by-side fingers' contacts"),
    "max_aperture": Range(0.001, 0.5, "m", why="opposing finger to the others, or a gripper's opening"),
    # Robust set-points and sweeps.
    "samples": Range(2, 100_000, integer=True),
    "quantile": Range(0.0, 1.0, low_open=True, high_open=True),
    "seed": Range(0, 2**32 - 1, integer=True),
    "workers": Range(1, 256, integer=True),
    # Material experiments.
    "depth": Range(1e-6, 0.1, "m", why="penetration past first contact; also less than the object's height"),
    "speed": Range(1e-6, 1.0, "m/s"),
    "indent_steps": Range(1, 100_000, integer=True),
    "compress_steps": Range(1, 10_000, integer=True),
    "strain": Range(0.0, 0.8, low_open=True, why="compressive strain"),
}


def check(
    key: str, value: object, name: str | None = None, error: type[SoftgraspError] = ConfigError
) -> float:
    """``value`` checked against ``RANGES[key]`` (:meth:`Range.check`), named ``name`` (default
    ``key``) in the error."""
    return RANGES[key].check(key if name is None else name, value, error)


def check_units(units: object, name: str = "units") -> float:
    """Metres per unit of the length unit ``units`` (``m``, ``cm``, ``mm``); ConfigError otherwise."""
    if not isinstance(units, str) or units not in UNITS:
        raise ConfigError(f"{name} must be one of {', '.join(UNITS)}, got {units!r}")
    return UNITS[units]


def check_volume_term(term: object, name: str = "volume_term") -> str:
    """``term`` when it names one of :data:`VOLUME_TERMS`; ConfigError otherwise."""
    if term not in VOLUME_TERMS:
        raise ConfigError(f"{name} must be {' or '.join(VOLUME_TERMS)}, got {term!r}")
    return str(term)


def _fits(extent: Sequence[float]) -> bool:
    return OBJECT_SIZE_M[0] <= min(extent) and max(extent) <= OBJECT_SIZE_M[1]


def check_object_size(extent_m: Sequence[float], what: str, scale: float | None = None) -> None:
    """Refuse an object whose extent ``(3,)`` [m] is outside :data:`OBJECT_SIZE_M` (thinnest side
    at least 1 mm, largest at most 0.5 m) with MeshError naming ``what`` and, where its numbers
    were read in a length unit (``scale`` metres per unit of the file or shape; None for an object
    of fixed size), the unit of ``--units`` that would make it fit."""
    ext = [float(e) for e in extent_m]
    if all(math.isfinite(e) for e in ext) and _fits(ext):
        return
    lo, hi = OBJECT_SIZE_M
    size = " x ".join(f"{e:.4g}" for e in ext)
    msg = (
        f"{what} measures {size} m: an object a hand grasps is {lo * 1e3:g} mm to {hi:g} m across "
        "(its thinnest and largest sides)"
    )
    if scale is not None and all(math.isfinite(e) and e > 0 for e in ext):
        raw = [e / scale for e in ext]
        fits = [u for u in ("mm", "cm", "m") if UNITS[u] != scale and _fits([r * UNITS[u] for r in raw])]
        current = next((u for u, f in UNITS.items() if f == scale), None)
        if fits:
            u = fits[0]
            msg += f"; its numbers read as {u} would fit: give --units {u} (API: units={u!r})"
        elif current is not None:
            msg += f"; its numbers were read in {current} (--units m, cm or mm)"
    raise MeshError(msg)


def check_object_mass(mass_kg: float, volume_m3: float, what: str = "the object") -> None:
    """Refuse an object to grasp whose mass ``mass_kg`` [kg] (of volume ``volume_m3`` [m^3]) is
    outside :data:`OBJECT_MASS_KG` (1 g to the hand's 2 kg payload) with ConfigError naming the
    mass, its mean density and the options that set it (``--density``, ``--mass``)."""
    lo, hi = OBJECT_MASS_KG
    if math.isfinite(mass_kg) and lo <= mass_kg <= hi:
        return
    shown = f"{mass_kg * 1e3:.4g} g" if mass_kg < 1.0 else f"{mass_kg:.4g} kg"
    rho = mass_kg / volume_m3 if volume_m3 > 0 else math.nan
    why = "lighter than a hand's fingertips can feel" if mass_kg < lo else "more than the hand can lift"
    raise ConfigError(
        f"{what} weighs {shown} (mean density {rho:.4g} kg/m^3 over {volume_m3 * 1e6:.4g} cm^3): {why}; "
        f"a hand grasps objects of {lo * 1e3:g} g to {hi:g} kg: give its --density KG_M3 or --mass KG "
        "(API: density_kg_m3=, mass_kg=), or check --units"
    )
