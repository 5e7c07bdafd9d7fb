"""Calibration of the spring network and volume term to a target Young's modulus and Poisson ratio.

Under a homogeneous strain (Cauchy-Born), a network of edge springs with stiffness k_e and rest
length L_e in a body of volume V has the elasticity tensor

    C_ijkl = (1/V) sum_e k_e L_e^2 n_i n_j n_k n_l,                        (affine estimate)

which is fully symmetric, so its isotropic part always has lambda = mu (nu = 1/4). Van Gelder's rule
k_e = E sum_{t ∋ e} V_t / L_e^2 makes that isotropic part exactly E, because every tet has six
edges. Two problems remain and are fixed here:

1. **Anisotropy.** The quartic form D(m) = C:(m⊗m⊗m⊗m) of a real mesh is not constant over
   directions m (structured meshes are strongly cubic). Each spring is re-weighted by a positive
   quartic polynomial p(n_e) of its own direction, chosen by least squares so that D becomes
   constant: the network's affine tensor is then isotropic. On a BCC lattice this is exact.
2. **Poisson's ratio.** Springs are scaled so that their shear modulus is the target mu, and a
   volume term with modulus kappa = lambda - mu (see :mod:`softgrasp.physics.forces`) supplies the rest of
   the bulk stiffness, so lambda is the target too.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from softgrasp.errors import MaterialError
from softgrasp.model.mesh.tetmesh import TetMesh

__all__ = ["NetworkCalibration", "calibrate_network", "affine_tensor_quartic", "sphere_directions"]

#: Smallest spring re-weighting factor accepted before the correction is damped.
MIN_WEIGHT = 0.25
#: Springs per block of the moment sums (bounds the (springs x monomials) temporaries to ~10 MB
#: whatever the mesh size).
CHUNK = 20_000


def sphere_directions(n: int = 200) -> NDArray[np.float64]:
    """Quasi-uniform unit vectors on the sphere (Fibonacci lattice), shape ``(n, 3)``."""
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(1.0 - z**2)
    phi = np.pi * (1.0 + 5**0.5) * i
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def _exponents(degree: int) -> list[tuple[int, int, int]]:
    """Exponents (a, b, c), a + b + c = ``degree``, of the monomials x^a y^b z^c in a fixed order."""
    return [(a, b, degree - a - b) for a in range(degree + 1) for b in range(degree + 1 - a)]


_QUARTIC = _exponents(4)  # the 15 degree-4 monomials
_OCTIC = _exponents(8)  # the 45 degree-8 monomials (products of two quartic ones)
#: Multinomial coefficients 4! / (a! b! c!): (n . m)^4 = sum over the quartic monomials of
#: coefficient * n^alpha * m^alpha.
_MULTINOMIAL = np.array([24.0 / (math.factorial(a) * math.factorial(b) * math.factorial(c)) for a, b, c in _QUARTIC])
#: Position in _OCTIC of the product of quartic monomials q and r, (15, 15).
_PRODUCT = np.array([[_OCTIC.index(tuple(i + j for i, j in zip(q, r, strict=True))) for r in _QUARTIC] for q in _QUARTIC])


def _monomials(n: NDArray[np.float64], exponents: list[tuple[int, int, int]]) -> NDArray[np.float64]:
    """The monomials n_x^a n_y^b n_z^c of the rows of ``n`` (K, 3), shape ``(K, len(exponents))``."""
    top = max(max(e) for e in exponents)
    powers = np.ones((top + 1, len(n), 3))  # powers[k] = n**k by repeated products
    for k in range(1, top + 1):
        powers[k] = powers[k - 1] * n
    return np.stack([powers[a, :, 0] * powers[b, :, 1] * powers[c, :, 2] for a, b, c in exponents], axis=1)


def _quartic_monomials(n: NDArray[np.float64]) -> NDArray[np.float64]:
    """The 15 degree-4 monomials of unit vectors n, shape ``(len(n), 15)``."""
    return _monomials(n, _QUARTIC)


def _moments(weights: NDArray[np.float64], n: NDArray[np.float64], exponents) -> NDArray[np.float64]:
    """sum_e w_e n_e^alpha for each exponent alpha, in blocks of CHUNK rows."""
    out = np.zeros(len(exponents))
    for lo in range(0, len(n), CHUNK):
        out += weights[lo : lo + CHUNK] @ _monomials(n[lo : lo + CHUNK], exponents)
    return out


def affine_tensor_quartic(
    weights: NDArray[np.float64], directions: NDArray[np.float64], probe: NDArray[np.float64]
) -> NDArray[np.float64]:
    """D(m) = sum_e w_e (n_e · m)^4 at probe directions m, shape ``(len(probe),)``.

    With ``w_e = k_e L_e^2 / V`` this is C:(m⊗m⊗m⊗m) of the affine elasticity tensor [Pa].
    Computed exactly from the 15 fourth moments of the directions, sum_e w_e n_e^alpha, by the
    multinomial expansion of (n · m)^4: O(springs + probes) instead of their product.
    """
    return _quartic_monomials(probe) @ (_MULTINOMIAL * _moments(weights, directions, _QUARTIC))


def _reweighting_matrix(
    weights: NDArray[np.float64], directions: NDArray[np.float64], probe: NDArray[np.float64]
) -> NDArray[np.float64]:
    """G (P, 15): the columns give D(m) at the probes for springs re-weighted by each quartic
    monomial of their direction, G[p, q] = sum_e w_e (n_e · m_p)^4 n_e^q, from the 45 eighth
    moments of the directions (the multinomial expansion again)."""
    M8 = _moments(weights, directions, _OCTIC)
    return (_quartic_monomials(probe) * _MULTINOMIAL) @ M8[_PRODUCT]


@dataclass(frozen=True)
class NetworkCalibration:
    """How the springs and volume term of a body were calibrated.

    Attributes
    ----------
    stiffness:
        Spring constants [N/m], shape ``(E,)``.
    kappa:
        Volume-term modulus [Pa]: the volume energy is ``kappa V0 psi(V/V0)`` per tet.
    spring_scale:
        Mean factor applied to Van Gelder's constants (shear calibration).
    anisotropy_before:
        Relative spread (max - min) / mean of D(m) over directions for Van Gelder's springs.
    anisotropy_after:
        The same after re-weighting (0 for a perfectly isotropic affine tensor).
    min_weight, max_weight:
        Extremes of the per-spring direction weights p(n_e).
    """

    stiffness: NDArray[np.float64]
    kappa: float
    spring_scale: float
    anisotropy_before: float
    anisotropy_after: float
    min_weight: float
    max_weight: float

    def describe(self) -> dict[str, float]:
        """JSON-ready summary (units in the keys)."""
        return {
            "kappa_Pa": self.kappa,
            "spring_scale": self.spring_scale,
            "anisotropy_before": self.anisotropy_before,
            "anisotropy_after": self.anisotropy_after,
            "direction_weight_min": self.min_weight,
            "direction_weight_max": self.max_weight,
        }


def calibrate_network(mesh: TetMesh, E: float, nu: float, *, isotropize: bool = True) -> NetworkCalibration:
    """Spring constants and volume modulus giving the body the elastic constants (E, nu).

    Parameters
    ----------
    mesh:
        The body's tetrahedral mesh.
    E:
        Target Young's modulus [Pa].
    nu:
        Target Poisson ratio, in (-1, 0.5).
    isotropize:
        Re-weight springs by direction so the affine tensor is isotropic (default). When false,
        Van Gelder's constants are only scaled (the classical rule).

    Returns
    -------
    NetworkCalibration
    """
    if not (E > 0 and -1.0 < nu < 0.5):
        raise MaterialError(f"cannot calibrate springs for E = {E} Pa, nu = {nu}")
    L = mesh.edge_lengths
    d = mesh.points[mesh.edges[:, 1]] - mesh.points[mesh.edges[:, 0]]
    n = d / L[:, None]
    k0 = E * mesh.edge_volumes / L**2  # Van Gelder
    w0 = k0 * L**2 / mesh.volume  # contributions to C [Pa]
    probe = sphere_directions(240)
    D0 = affine_tensor_quartic(w0, n, probe)
    spread0 = float(np.ptp(D0) / D0.mean())

    weight = np.ones_like(L)
    if isotropize:
        # D(m) with springs weighted by p(n_e) = sum_q c_q mono_q(n_e) is linear in c.
        G = _reweighting_matrix(w0, n, probe)  # (P, 15)
        mono = _quartic_monomials(n)  # (E, 15)
        target = np.full(len(probe), D0.mean())
        c, *_ = np.linalg.lstsq(G, target, rcond=None)
        p = mono @ c
        # If the full correction would make a spring too soft, blend it with p = 1.
        for blend in (1.0, 0.75, 0.5, 0.25, 0.0):
            weight = 1.0 + blend * (p - 1.0)
            if weight.min() >= MIN_WEIGHT:
                break
        weight = np.maximum(weight, MIN_WEIGHT)
    w = w0 * weight
    D = affine_tensor_quartic(w, n, probe)
    spread = float(np.ptp(D) / D.mean())
    # Isotropic part of a fully symmetric tensor from its quartic form: D_mean = 3 s, lambda = mu = s.
    mu_springs = float(D.mean()) / 3.0
    mu = E / (2.0 * (1.0 + nu))
    lam = E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))
    scale = mu / mu_springs
    k = k0 * weight * scale
    return NetworkCalibration(
        stiffness=k,
        kappa=lam - mu,
        spring_scale=float(np.mean(weight * scale)),
        anisotropy_before=spread0,
        anisotropy_after=spread,
        min_weight=float(weight.min()),
        max_weight=float(weight.max()),
    )
