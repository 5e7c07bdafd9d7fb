"""Pure contact laws of the paper's Sec. 3.3: Hunt-Crossley normal force and Coulomb friction.

SI units; equation numbers are the paper's. The per-contact laws are written once, as scalar
functions (:func:`normal_force_value`, :func:`coulomb_slip_value`) that the compiled contact
kernels compile with Numba (:mod:`softgrasp.physics.fingertip.forces`) and that
:func:`normal_force` and :func:`slip_force` apply element by element to arrays. The elastic
normal law itself is :mod:`softgrasp.physics.fingertip.resolved`.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from softgrasp.errors import ContactError

__all__ = [
    "normal_force_value",
    "coulomb_slip_value",
    "effective_modulus",
    "contact_stiffness",
    "contact_damping",
    "normal_force",
    "mindlin_ratio",
    "slip_force",
    "restitution_hunt_crossley",
    "PAPER_PREFACTOR",
    "HERTZ_PREFACTOR",
    "RESOLUTION",
    "MAX_SHARE",
    "LAW_COLUMNS",
    "resolved_share",
]

#: K = 2 Psi sqrt(R) (Eq. 11).
PAPER_PREFACTOR = 2.0
#: Hertz's sphere-on-half-space K = 4/3 E* sqrt(R).
HERTZ_PREFACTOR = 4.0 / 3.0
#: The radius, over its facet's size (the edge of the equilateral triangle of its area), of the
#: disc whose half-space deflection equals a boundary node's own deflection under a point load on
#: it: the mesh's resolution at a contact for the default law
#: (:mod:`softgrasp.physics.fingertip.resolved`), a property of the discretisation.
RESOLUTION = 0.2
#: Largest share of the pair's Hertz compliance the mesh may take over (the default law keeps at
#: least 2 % of Hertz's tangent compliance: its stiffness stays below 50x Hertz's).
MAX_SHARE = 0.98


#: Columns of the per-finger normal law table the compiled kernels take: K, the resolved share r,
#: the mesh's resolution under the fingertip (h_node, h_land, the facet size [m]) and Hertz's
#: radius [m] (:meth:`softgrasp.physics.fingertip.contact.FingertipContact.law_table`).
LAW_COLUMNS = 6


def resolved_share(psi_pair: float, psi_object: float) -> float:
    """r = E*_pair / E*_object (Eq. 12), capped at :data:`MAX_SHARE`: the share of the pair's
    Hertz compliance that is the object's (1 for a rigid fingertip) and that the mesh resolves
    as far as its resolution allows (:mod:`softgrasp.physics.fingertip.resolved`)."""
    return min(psi_pair / psi_object, MAX_SHARE)


def effective_modulus(E1: float, nu1: float, E2: float, nu2: float) -> float:
    """Psi = 1 / ((1 - nu1^2)/E1 + (1 - nu2^2)/E2) [Pa] (Eq. 12).

    ``E1 = inf`` stands for a rigid body (its term vanishes).
    """
    for E, nu, who in ((E1, nu1, "finger"), (E2, nu2, "object")):
        if not (E > 0 and -1.0 < nu < 0.5):
            raise ContactError(f"{who}: E = {E} Pa and nu = {nu} must satisfy E > 0 and -1 < nu < 0.5")
    c1 = 0.0 if math.isinf(E1) else (1.0 - nu1**2) / E1
    c2 = 0.0 if math.isinf(E2) else (1.0 - nu2**2) / E2
    if c1 + c2 == 0.0:
        raise ContactError("both bodies are rigid: the contact stiffness would be infinite")
    return 1.0 / (c1 + c2)


def contact_stiffness(psi: float, radius: float, prefactor: float = PAPER_PREFACTOR) -> float:
    """K = c Psi sqrt(R) [N/m^1.5] (Eq. 11 with c = 2; Hertz has c = 4/3)."""
    if not radius > 0:
        raise ContactError(f"fingertip radius = {radius} m is invalid: it must be > 0")
    if not prefactor > 0:
        raise ContactError(f"stiffness prefactor = {prefactor} must be > 0")
    return prefactor * psi * math.sqrt(radius)


def contact_damping(radius: float, gamma: float) -> float:
    """C = 4 pi R gamma [N s/m] (Eq. 13)."""
    if not gamma >= 0:
        raise ContactError(f"damping constant gamma = {gamma} must be >= 0")
    return 4.0 * math.pi * radius * gamma


def normal_force_value(
    delta: float, elastic: float, delta_n: float, rate: float, C: float, hunt_crossley: bool
) -> float:
    """Normal contact force magnitude [N] of one contact (Eq. 9), given its elastic force
    ``elastic`` (K delta^n for the paper's law) and ``delta_n = max(delta, 0)^n``.

    Linear damping (the paper): ``max(0, F_e + C delta_dot)``; Hunt and Crossley's form (no
    force jump at first touch): ``max(0, F_e + C delta^n delta_dot)``. Zero unless delta > 0.
    """
    raw = elastic + C * delta_n * rate if hunt_crossley else elastic + C * rate
    return max(raw, 0.0) if delta > 0.0 else 0.0


def coulomb_slip_value(f_n: float, vx: float, vy: float, vz: float, mu: float) -> tuple[float, float, float]:
    """Coulomb sliding friction on the finger, ``-mu f_n V_t / |V_t|`` (Eq. 15), of one contact
    sliding at tangential velocity V_t = (vx, vy, vz) [m/s]; zero when it does not slide."""
    speed = math.sqrt(vx * vx + vy * vy + vz * vz)
    if not speed > 0.0:
        return 0.0, 0.0, 0.0
    return -mu * f_n * (vx / speed), -mu * f_n * (vy / speed), -mu * f_n * (vz / speed)


def normal_force(
    delta: ArrayLike,
    delta_rate: ArrayLike,
    K: ArrayLike,
    C: ArrayLike,
    n: float = 1.5,
    *,
    damping: str = "linear",
) -> NDArray[np.float64]:
    """Normal contact force magnitudes [N] (Eq. 9, :func:`normal_force_value`) over arrays.

    ``damping="linear"`` (the paper): f_n = max(0, K delta^n + C delta_dot);
    ``damping="hunt-crossley"`` (classic form, no force jump at first touch):
    f_n = max(0, K delta^n + C delta^n delta_dot), so that C plays the role of Hunt and Crossley's
    lambda [N s/m^(n+1)]. Zero where delta <= 0.
    """
    if damping not in ("linear", "hunt-crossley"):
        raise ContactError(f"unknown damping form {damping!r}; use 'linear' or 'hunt-crossley'")
    d = np.asarray(delta, dtype=np.float64)
    dn = np.maximum(d, 0.0) ** n
    law = np.vectorize(normal_force_value, otypes=[np.float64])
    return law(d, np.asarray(K) * dn, dn, np.asarray(delta_rate, dtype=np.float64), C, damping == "hunt-crossley")


def mindlin_ratio(nu: float) -> float:
    """k_t / k_n = 2 (1 - nu) / (2 - nu) for a sphere on a half-space (Mindlin 1949)."""
    return 2.0 * (1.0 - nu) / (2.0 - nu)


def slip_force(f_n: ArrayLike, v_t: NDArray[np.float64], mu: float) -> NDArray[np.float64]:
    """Coulomb sliding friction on the finger, -mu f_n V_t / |V_t| (Eq. 15,
    :func:`coulomb_slip_value`), shape (k, 3). Zero where the sliding speed is zero."""
    v = np.asarray(v_t, dtype=np.float64).reshape(-1, 3)
    fn = np.broadcast_to(np.asarray(f_n, dtype=np.float64), v.shape[:1])
    out = np.array([coulomb_slip_value(float(f), *map(float, w), mu) for f, w in zip(fn, v)]).reshape(-1, 3)
    return out.reshape(np.shape(v_t))


def restitution_hunt_crossley(beta_v_in: float) -> float:
    """Coefficient of restitution of a Hunt-Crossley impact with damping lambda = beta K.

    Solves ``-b_out - ln(1 - b_out) = b_in - ln(1 + b_in)`` for ``b_out = beta v_out`` given
    ``b_in = beta v_in`` and returns e = v_out / v_in. Closed form of the energy balance of
    m x'' = -K x^n (1 + beta x'), independent of m, K and n.
    """
    from scipy.optimize import brentq

    b = float(beta_v_in)
    if not b > 0:
        raise ContactError(f"beta v_in = {b} must be > 0")
    rhs = b - math.log1p(b)
    g = lambda y: -y - math.log1p(-y) - rhs  # noqa: E731 - increasing on (0, 1)
    return brentq(g, 1e-15, 1.0 - 1e-15, xtol=1e-15) / b
