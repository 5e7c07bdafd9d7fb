"""Grasp without crushing: the held grasp's peak contact pressure and peak strain, and the limits a
user sets on them (fruit and tissue bruise above a pressure or a strain).

* **Peak contact pressure** of each fingertip: Hertz's, ``p0 = 3 F / (2 pi a^2)`` with the contact
  radius ``a = (3 F R_eff / (4 E*))^(1/3)`` of its normal force F, the pair's effective modulus E*
  (Eq. 12) and radius ``R_eff`` (the fingertip's, with the object's curvature where it lands under
  the resolved law). It is the continuum's, independent of the mesh.
* **Peak strain** of the object: the largest principal engineering strain ``|lambda - 1|`` of any
  tetrahedron in the held state (lambda the principal stretches of its deformation gradient),
  compression or tension: resolved at the mesh's scale (a coarse mesh spreads a contact's strain
  over its elements).

The planner finds the least squeeze that holds the object; if that squeeze already exceeds a
limit, no squeeze of these contacts holds within it: :func:`check_limits` raises
:class:`~softgrasp.errors.InfeasibleGrasp` naming the limit. The plan reports the pressures of its
set-points (the safety factor above the least that holds), which must keep within the pressure
limit too, and the strain of the held state.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from softgrasp.errors import InfeasibleGrasp
from softgrasp.grasp.initial import FINGER_NAMES
from softgrasp.physics.body import Body
from softgrasp.physics.fingertip.contact import FingertipContact
from softgrasp.physics.fingertip.laws import effective_modulus

__all__ = [
    "Damage",
    "contact_radii",
    "hertz_peak_pressure",
    "principal_strains",
    "peak_strain",
    "grasp_damage",
    "check_limits",
    "patch_torsion",
]


@dataclass(frozen=True)
class Damage:
    """The held grasp's load on the object.

    Attributes
    ----------
    pressure: each finger's peak contact pressure [Pa], (3,).
    contact_radius: each finger's Hertz contact radius [m], (3,).
    strain: the object's peak principal strain (dimensionless, >= 0).
    strain_tet: the tetrahedron where it is.
    names: the fingers' names.
    """

    pressure: NDArray[np.float64]
    contact_radius: NDArray[np.float64]
    strain: float
    strain_tet: int
    names: tuple[str, ...] = FINGER_NAMES

    def describe(self) -> dict[str, object]:
        return {
            "peak_pressure_Pa": dict(zip(self.names, map(float, self.pressure), strict=True)),
            "contact_radius_m": dict(zip(self.names, map(float, self.contact_radius), strict=True)),
            "peak_strain": self.strain,
        }


def hertz_peak_pressure(
    normal_N: NDArray[np.float64], radius_m: NDArray[np.float64], E_star_Pa: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Hertz's peak pressure [Pa] and contact radius [m] of spheres of radius ``radius_m`` pressed
    with ``normal_N`` on a half-space of effective modulus ``E_star_Pa`` (element-wise):
    ``a = (3 F R / (4 E*))^(1/3)``, ``p0 = 3 F / (2 pi a^2)``; zeros where F = 0."""
    F = np.maximum(np.asarray(normal_N, dtype=np.float64), 0.0)
    R = np.asarray(radius_m, dtype=np.float64)
    a = np.cbrt(3.0 * F * R / (4.0 * np.asarray(E_star_Pa, dtype=np.float64)))
    p0 = np.divide(3.0 * F, 2.0 * math.pi * a * a, out=np.zeros_like(F), where=a > 0)
    return p0, a


def peak_strain(body: Body, x: NDArray[np.float64]) -> tuple[float, int]:
    """The largest principal engineering strain ``|lambda - 1|`` over the body's tetrahedra at
    positions ``x`` [m] (lambda: the singular values of each deformation gradient), and its tet."""
    strain = principal_strains(body, x)
    k = int(np.argmax(strain))
    return float(strain[k]), k


def principal_strains(body: Body, x: NDArray[np.float64]) -> NDArray[np.float64]:
    """Each tetrahedron's largest principal engineering strain ``|lambda - 1|`` at positions ``x``
    [m] (lambda: the singular values of its deformation gradient F from the body's rest mesh,
    the square roots of the eigenvalues of the right Cauchy-Green tensor F^T F), compression or
    tension, (M,)."""
    rest = np.asarray(body.mesh.points, dtype=np.float64)[body.mesh.tets]
    now = np.asarray(x, dtype=np.float64)[body.mesh.tets]
    Dm = np.stack([rest[:, k] - rest[:, 0] for k in (1, 2, 3)], axis=2)
    Ds = np.stack([now[:, k] - now[:, 0] for k in (1, 2, 3)], axis=2)
    F = Ds @ np.linalg.inv(Dm)
    stretch = np.sqrt(np.maximum(np.linalg.eigvalsh(np.swapaxes(F, 1, 2) @ F), 0.0))  # ascending
    return np.maximum(1.0 - stretch[:, 0], stretch[:, 2] - 1.0)


def contact_radii(
    body: Body, fingers: FingertipContact, normal_N: NDArray[np.float64], t: float = 0.0
) -> NDArray[np.float64]:
    """Each fingertip's Hertz contact radius [m] under the normal forces ``normal_N`` [N] at time
    ``t`` (the fingertips' landing points then): ``a = (3 F R_eff / (4 E*))^(1/3)`` with the pair's
    effective modulus E* (Eq. 12) and radius R_eff (:meth:`FingertipContact.law_table`)."""
    return _hertz(body, fingers, normal_N, t)[1]


def _hertz(
    body: Body, fingers: FingertipContact, normal_N: NDArray[np.float64], t: float
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """:func:`hertz_peak_pressure` of each fingertip's normal force on ``body`` at time ``t``."""
    m = body.material
    E_star = np.array([effective_modulus(f.E, f.nu, m.E, m.nu) for f in fingers.fingertips])
    radius = fingers.law_table(body, t)[:, 5]
    return hertz_peak_pressure(np.asarray(normal_N, dtype=np.float64), radius, E_star)


def grasp_damage(
    body: Body, fingers: FingertipContact, x: NDArray[np.float64], normal_N: NDArray[np.float64]
) -> Damage:
    """The load of the held grasp (fixed ``fingers``, positions ``x``, normal forces ``normal_N``)."""
    p0, a = _hertz(body, fingers, normal_N, 0.0)
    strain, tet = peak_strain(body, x)
    return Damage(p0, a, strain, tet, tuple(f.name for f in fingers.fingertips))


def patch_torsion(
    body: Body, fingers: FingertipContact, normal_N: NDArray[np.float64], mu: float
) -> NDArray[np.float64] | None:
    """The soft-finger torsion ``kappa`` [m] of each contact of a two-finger grasp, ``(2,)``: the
    largest moment about its normal per unit normal force, ``(3 pi / 16) mu a`` for Hertz's patch
    of radius ``a`` under the normal force ``normal_N`` sliding as a whole. None for more fingers
    (their point contacts resist every load already)."""
    if len(fingers.fingertips) != 2:
        return None
    return 3.0 * math.pi / 16.0 * mu * contact_radii(body, fingers, normal_N)


def check_limits(
    damage: Damage, max_pressure_Pa: float | None, max_strain: float | None, *, setpoints: bool = False
) -> None:
    """Raise :class:`InfeasibleGrasp` when the least squeeze that holds (or, ``setpoints``, the
    pressures of the set-points) exceeds a limit."""
    if setpoints and max_pressure_Pa is not None and damage.pressure.max() > max_pressure_Pa:
        j = int(np.argmax(damage.pressure))
        raise InfeasibleGrasp(
            f"the set-points press the {damage.names[j]} fingertip at {damage.pressure[j] / 1e3:.3g} kPa "
            f"(Hertz's peak), above --max-pressure {max_pressure_Pa / 1e3:.3g} kPa, though the least "
            "squeeze that holds keeps within it: lower --safety-factor (the margin above the least that "
            "holds), or use larger fingertips"
        )
    if max_pressure_Pa is not None and damage.pressure.max() > max_pressure_Pa:
        j = int(np.argmax(damage.pressure))
        raise InfeasibleGrasp(
            f"the least squeeze that holds the object presses the {damage.names[j]} fingertip at "
            f"{damage.pressure[j] / 1e3:.3g} kPa (Hertz's peak), above --max-pressure "
            f"{max_pressure_Pa / 1e3:.3g} kPa: no squeeze of these contacts holds within it; use larger "
            "fingertips, more friction, or a softer fingertip skin"
        )
    if max_strain is not None and damage.strain > max_strain:
        raise InfeasibleGrasp(
            f"the least squeeze that holds the object strains it by {damage.strain:.3g} (the largest "
            f"principal strain, tetrahedron {damage.strain_tet}), above --max-strain {max_strain:g}: "
            "no squeeze of these contacts holds within it; use larger fingertips or more friction"
        )
