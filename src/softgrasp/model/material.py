"""Materials: elastic constants, density, and the non-linear stress-strain law of the springs.

A law is expressed in *normalised* form ``s(eps) = sigma(eps) / E`` with ``s(0) = 0`` and
``s'(0) = 1``, so that E stays the small-strain Young's modulus and the law only shapes the curve.
Strain is engineering strain, positive in tension; compression tests report it with the opposite
sign at the I/O edge (:mod:`softgrasp.experiments.compression`).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from softgrasp.errors import MaterialError
from softgrasp.model.ranges import RANGES

__all__ = [
    "StressStrainLaw",
    "Linear",
    "Polynomial",
    "Tabulated",
    "Material",
    "PRESETS",
    "preset",
    "parse_material",
    "check_given",
]

#: Strain interval over which a non-linear law must be strictly increasing.
CHECK_RANGE = (-0.8, 0.8)


def _is_number(x: object) -> bool:
    return isinstance(x, (int, float, np.integer, np.floating)) and not isinstance(x, bool)


@runtime_checkable
class StressStrainLaw(Protocol):
    """Normalised uniaxial law ``s(eps) = sigma / E`` of the edge springs."""

    def stress(self, strain: NDArray[np.float64]) -> NDArray[np.float64]:
        """Normalised stress s (dimensionless) at engineering strain ``strain``."""
        ...

    def tangent(self, strain: NDArray[np.float64]) -> NDArray[np.float64]:
        """ds/deps (dimensionless), the normalised tangent modulus."""
        ...

    def energy(self, strain: NDArray[np.float64]) -> NDArray[np.float64]:
        """Normalised strain energy w(eps) = integral of s from 0 to eps (dimensionless)."""
        ...

    def describe(self) -> dict[str, object]:
        """JSON-ready description (kind and parameters)."""
        ...


@dataclass(frozen=True)
class Linear:
    """Hooke's law, ``s = eps``."""

    def stress(self, strain: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.asarray(strain, dtype=np.float64)

    def tangent(self, strain: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.ones_like(np.asarray(strain, dtype=np.float64))

    def energy(self, strain: NDArray[np.float64]) -> NDArray[np.float64]:
        e = np.asarray(strain, dtype=np.float64)
        return 0.5 * e**2

    def describe(self) -> dict[str, object]:
        return {"kind": "linear"}


@dataclass(frozen=True)
class Polynomial:
    """``s = eps + a2 eps^2 + a3 eps^3``.

    ``a3 > 0`` stiffens under large tension and compression, ``a3 < 0`` softens; ``a2`` makes
    the law asymmetric (``a2 < 0`` stiffens in compression and softens in tension). The law must be
    strictly increasing on :data:`CHECK_RANGE` (a spring must never lose stiffness entirely).
    """

    a2: float = 0.0
    a3: float = 0.0

    def __post_init__(self) -> None:
        for k in ("a2", "a3"):
            v = getattr(self, k)
            if not math.isfinite(v):
                raise MaterialError(f"polynomial law coefficient {k} must be finite, got {v}")
        e = np.linspace(*CHECK_RANGE, 1601)
        t = self.tangent(e)
        if (t <= 0).any():
            bad = e[np.argmax(t <= 0)]
            raise MaterialError(
                f"polynomial law (a2={self.a2}, a3={self.a3}) is not increasing at strain {bad:.3f}; "
                f"its slope 1 + 2 a2 e + 3 a3 e^2 must stay > 0 for strains in {CHECK_RANGE}"
            )

    def stress(self, strain: NDArray[np.float64]) -> NDArray[np.float64]:
        e = np.asarray(strain, dtype=np.float64)
        return e + self.a2 * e**2 + self.a3 * e**3

    def tangent(self, strain: NDArray[np.float64]) -> NDArray[np.float64]:
        e = np.asarray(strain, dtype=np.float64)
        return 1.0 + 2.0 * self.a2 * e + 3.0 * self.a3 * e**2

    def energy(self, strain: NDArray[np.float64]) -> NDArray[np.float64]:
        e = np.asarray(strain, dtype=np.float64)
        return 0.5 * e**2 + self.a2 * e**3 / 3.0 + 0.25 * self.a3 * e**4

    def describe(self) -> dict[str, object]:
        return {"kind": "polynomial", "a2": self.a2, "a3": self.a3}


@dataclass(frozen=True, eq=False)
class Tabulated:
    """A measured (strain, stress [Pa]) curve, normalised by its initial slope.

    Points must have strictly increasing strain and stress. The curve passes through (0, 0) (the
    point is added if missing). If it covers only one sign of strain, the other side is its odd
    mirror image. Between points it is a monotone cubic (PCHIP); outside, linear with the end slope.

    Attributes
    ----------
    E0:
        Initial slope [Pa] of the curve (the modulus used to normalise it).
    """

    strain: NDArray[np.float64]
    stress_Pa: NDArray[np.float64]
    E0: float = field(init=False)

    def __post_init__(self) -> None:
        from scipy.interpolate import PchipInterpolator

        e = np.asarray(self.strain, dtype=np.float64).ravel()
        s = np.asarray(self.stress_Pa, dtype=np.float64).ravel()
        if e.size != s.size:
            raise MaterialError(f"stress-strain table has {e.size} strains but {s.size} stresses")
        if e.size < 2:
            raise MaterialError("stress-strain table needs at least 2 points besides (0, 0)")
        if not (np.isfinite(e).all() and np.isfinite(s).all()):
            raise MaterialError("stress-strain table contains a non-finite value")
        if not (e == 0).any():
            e = np.append(e, 0.0)
            s = np.append(s, 0.0)
        order = np.argsort(e, kind="stable")
        e, s = e[order], s[order]
        de, ds = np.diff(e), np.diff(s)
        if (de <= 0).any():
            i = int(np.argmax(de <= 0))
            raise MaterialError(f"stress-strain table repeats strain {e[i]:g}; strains must be distinct")
        if (ds <= 0).any():
            i = int(np.argmax(ds <= 0))
            raise MaterialError(
                f"stress-strain table is not monotonic: stress {s[i + 1]:g} Pa at strain {e[i + 1]:g} "
                f"does not exceed {s[i]:g} Pa at strain {e[i]:g}; stress must increase with strain"
            )
        if abs(s[e == 0][0]) > 1e-12 * np.abs(s).max():
            raise MaterialError("stress-strain table must have zero stress at zero strain")
        if e.min() >= 0:
            e = np.concatenate([-e[:0:-1], e])
            s = np.concatenate([-s[:0:-1], s])
        elif e.max() <= 0:
            e = np.concatenate([e, -e[-2::-1]])
            s = np.concatenate([s, -s[-2::-1]])
        spline = PchipInterpolator(e, s, extrapolate=False)
        E0 = float(spline.derivative()(0.0))
        if not E0 > 0:
            raise MaterialError("stress-strain table has zero slope at zero strain")
        object.__setattr__(self, "strain", e)
        object.__setattr__(self, "stress_Pa", s)
        object.__setattr__(self, "E0", E0)
        object.__setattr__(self, "_spline", spline)
        object.__setattr__(self, "_dspline", spline.derivative())
        d = self._dspline
        object.__setattr__(self, "_end_slopes", (float(d(e[0])), float(d(e[-1]))))
        anti = spline.antiderivative()
        object.__setattr__(self, "_anti", anti)
        object.__setattr__(
            self, "_end_energy", (float(anti(e[0]) - anti(0.0)), float(anti(e[-1]) - anti(0.0)))
        )

    def stress(self, strain: NDArray[np.float64]) -> NDArray[np.float64]:
        x = np.asarray(strain, dtype=np.float64)
        e, s = self.strain, self.stress_Pa
        lo, hi = self._end_slopes  # type: ignore[attr-defined]
        out = np.where(x < e[0], s[0] + lo * (x - e[0]), np.where(x > e[-1], s[-1] + hi * (x - e[-1]), 0.0))
        inside = (x >= e[0]) & (x <= e[-1])
        out = np.where(inside, np.nan_to_num(self._spline(np.clip(x, e[0], e[-1]))), out)  # type: ignore[attr-defined]
        return out / self.E0

    def tangent(self, strain: NDArray[np.float64]) -> NDArray[np.float64]:
        x = np.asarray(strain, dtype=np.float64)
        e = self.strain
        lo, hi = self._end_slopes  # type: ignore[attr-defined]
        inner = np.nan_to_num(self._dspline(np.clip(x, e[0], e[-1])))  # type: ignore[attr-defined]
        return np.where(x < e[0], lo, np.where(x > e[-1], hi, inner)) / self.E0

    def energy(self, strain: NDArray[np.float64]) -> NDArray[np.float64]:
        x = np.asarray(strain, dtype=np.float64)
        e, s = self.strain, self.stress_Pa
        lo, hi = self._end_slopes  # type: ignore[attr-defined]
        w_lo, w_hi = self._end_energy  # type: ignore[attr-defined]
        anti = self._anti  # type: ignore[attr-defined]
        inner = np.nan_to_num(anti(np.clip(x, e[0], e[-1]))) - float(anti(0.0))
        dl = x - e[0]
        dh = x - e[-1]
        out = np.where(
            x < e[0],
            w_lo + s[0] * dl + 0.5 * lo * dl**2,
            np.where(x > e[-1], w_hi + s[-1] * dh + 0.5 * hi * dh**2, inner),
        )
        return out / self.E0

    def describe(self) -> dict[str, object]:
        return {
            "kind": "tabulated",
            "E0_Pa": self.E0,
            "strain": self.strain.tolist(),
            "stress_Pa": self.stress_Pa.tolist(),
        }


@dataclass(frozen=True, init=False)
class Material:
    """An isotropic soft material.

    Parameters
    ----------
    E:
        Small-strain Young's modulus [Pa], > 0 (keyword ``E_Pa`` as well).
    nu:
        Poisson's ratio, in (-1, 0.5).
    density:
        Mass density [kg/m^3], > 0 (keyword ``density_kg_m3`` as well); ``None`` when the
        object's total mass is given instead.
    law:
        Normalised stress-strain law of the edge springs (default: linear).
    name:
        Label written to output files.
    """

    E: float
    nu: float
    density: float | None = None
    law: StressStrainLaw = field(default_factory=Linear)
    name: str = "custom"

    def __init__(
        self,
        E: float | None = None,
        nu: float | None = None,
        density: float | None = None,
        law: StressStrainLaw | None = None,
        name: str = "custom",
        *,
        E_Pa: float | None = None,
        density_kg_m3: float | None = None,
    ) -> None:
        if E_Pa is not None:
            if E is not None:
                raise TypeError("Material: give E or E_Pa, not both")
            E = E_Pa
        if density_kg_m3 is not None:
            if density is not None:
                raise TypeError("Material: give density or density_kg_m3, not both")
            density = density_kg_m3
        if E is None or nu is None:
            raise TypeError("Material needs E (E_Pa) [Pa] and nu")
        object.__setattr__(self, "E", E)
        object.__setattr__(self, "nu", nu)
        object.__setattr__(self, "density", density)
        object.__setattr__(self, "law", Linear() if law is None else law)
        object.__setattr__(self, "name", name)
        self.__post_init__()

    @property
    def E_Pa(self) -> float:
        """Young's modulus [Pa] (the same as ``E``)."""
        return self.E

    @property
    def density_kg_m3(self) -> float | None:
        """Mass density [kg/m^3] (the same as ``density``)."""
        return self.density

    def __post_init__(self) -> None:
        if not (_is_number(self.E) and math.isfinite(self.E) and self.E > 0):
            raise MaterialError(f"Young's modulus E = {self.E} Pa is invalid: it must be > 0 Pa")
        if not (_is_number(self.nu) and math.isfinite(self.nu) and -1.0 < self.nu < 0.5):
            raise MaterialError(
                f"Poisson's ratio nu = {self.nu} is invalid: it must lie in (-1, 0.5) "
                "(0.5 is perfectly incompressible, which a mass-spring body cannot represent; "
                "use e.g. 0.49)"
            )
        if self.density is not None and not (
            _is_number(self.density) and math.isfinite(self.density) and self.density > 0
        ):
            raise MaterialError(f"density = {self.density} kg/m^3 is invalid: it must be > 0")
        if not isinstance(self.law, StressStrainLaw):
            raise MaterialError(f"law must provide stress/tangent/describe, got {type(self.law).__name__}")

    @property
    def shear_modulus(self) -> float:
        """mu = E / (2 (1 + nu)) [Pa]."""
        return self.E / (2.0 * (1.0 + self.nu))

    @property
    def lame_lambda(self) -> float:
        """lambda = E nu / ((1 + nu)(1 - 2 nu)) [Pa]."""
        return self.E * self.nu / ((1.0 + self.nu) * (1.0 - 2.0 * self.nu))

    @property
    def bulk_modulus(self) -> float:
        """K = E / (3 (1 - 2 nu)) [Pa]."""
        return self.E / (3.0 * (1.0 - 2.0 * self.nu))

    def with_density(self, density: float) -> Material:
        """A copy with another density [kg/m^3]."""
        return Material(self.E, self.nu, density, self.law, self.name)

    def describe(self) -> dict[str, object]:
        """JSON-ready description with units in the keys."""
        return {
            "name": self.name,
            "E_Pa": self.E,
            "nu": self.nu,
            "density_kg_m3": self.density,
            "law": self.law.describe(),
        }


#: Table 1 of the paper. Densities: the rubber sphere's from its mass 0.05 kg and radius 0.064 m;
#: the foam's from softgrasp's default cube (50 mm, 12.5 g), a dense polyurethane foam.
PRESETS: dict[str, Material] = {
    "foam": Material(E=4.9284e6, nu=0.39, density=100.0, name="foam"),
    "rubber": Material(E=0.0793e6, nu=0.45, density=0.05 / (4.0 / 3.0 * math.pi * 0.064**3), name="rubber"),
}


def check_given(material: Material, where: str = "") -> Material:
    """``material`` when its Young's modulus and density (if it has one) lie in their physical
    ranges (:data:`~softgrasp.model.ranges.RANGES`: a soft object's, where a user gives one);
    MaterialError otherwise, prefixed by ``where``. (A :class:`Material` itself takes any
    positive value: fits and bodies derive materials inside softgrasp.)"""
    for key, value, unit, label in (
        ("E", material.E, "Pa", "Young's modulus E"),
        ("density", material.density, "kg/m^3", "density"),
    ):
        r = RANGES[key]
        if value is not None and not r.contains(float(value)):
            raise MaterialError(
                f"{where}{label} = {float(value):g} {unit} is invalid: it must lie in {r.text} ({r.why})"
            )
    return material


def preset(name: str) -> Material:
    """The named preset material (``foam`` or ``rubber``)."""
    try:
        return PRESETS[name]
    except KeyError:
        raise MaterialError(f"unknown material {name!r}; presets are {sorted(PRESETS)}") from None


_KEYS = {"E", "nu", "density", "a2", "a3"}


def parse_material(spec: str, *, need_mass: bool = True) -> tuple[Material, float | None]:
    """Parse a material spec from the command line.

    ``spec`` is a preset name (``foam``, ``rubber``) or ``key=value`` pairs separated by commas:
    ``E=80e3,nu=0.45,density=45`` with optional ``mass=0.05`` (total mass [kg], overriding the
    density) and polynomial law coefficients ``a2``, ``a3``. A preset name may come first and be
    followed by overrides: ``rubber,nu=0.4``.

    ``need_mass`` False accepts a list with neither density nor mass (the object's density or mass
    given apart, as ``--density``/``--mass``).

    Returns
    -------
    (Material, mass_kg or None)
    """
    parts = [p.strip() for p in spec.split(",") if p.strip()]
    if not parts:
        raise MaterialError("empty material spec; give a preset (foam, rubber) or E=..,nu=..,density=..")
    base: dict[str, float] = {}
    name = "custom"
    if "=" not in parts[0]:
        m = preset(parts[0])
        name = m.name
        base = {"E": m.E, "nu": m.nu}
        if m.density is not None:
            base["density"] = m.density
        parts = parts[1:]
    mass = None
    for p in parts:
        mt = re.fullmatch(r"([A-Za-z0-9_]+)\s*=\s*(\S+)", p)
        if not mt:
            raise MaterialError(f"cannot read {p!r} in material spec; expected key=value")
        k, v = mt.group(1), mt.group(2)
        try:
            val = float(v)
        except ValueError:
            raise MaterialError(f"material value {k}={v!r} is not a number") from None
        if k == "mass":
            r = RANGES["mass"]
            if not (math.isfinite(val) and r.contains(val)):
                raise MaterialError(f"mass = {val} kg is invalid: it must lie in {r.text} ({r.why})")
            mass = val
        elif k in ("a2", "a3"):
            base[k] = RANGES[k].check(f"material {k}", val, MaterialError)
        elif k in _KEYS:
            base[k] = val
        else:
            raise MaterialError(f"unknown material key {k!r}; known keys: E, nu, density, mass, a2, a3")
    for k in ("E", "nu"):
        if k not in base:
            raise MaterialError(f"material spec {spec!r} lacks {k}; e.g. E=80e3,nu=0.45,density=45")
    law: StressStrainLaw = Linear()
    if "a2" in base or "a3" in base:
        law = Polynomial(base.get("a2", 0.0), base.get("a3", 0.0))
    if "density" not in base and mass is None and need_mass:
        raise MaterialError(
            f"material spec {spec!r} needs density=.. [kg/m^3] or mass=.. [kg] (or --density, --mass)"
        )
    return check_given(Material(base["E"], base["nu"], base.get("density"), law, name)), mass
