"""The fingertip's normal law with the object's compliance counted once (the default law).

A rigid sphere of radius R pressed into an elastic half-space follows Hertz: contact radius a,
approach ``delta_H = a^2 / R``, force ``F = K a^3 / R^1.5`` with ``K = 4/3 E* sqrt(R)`` (the
paper's Eq. 11 with Hertz's prefactor; Eq. 12 for E*). Its tangent compliance is
``d delta_H / dF = 2 / (3 K' a)`` with ``K' = K / sqrt(R)``.

softgrasp's object is a meshed elastic body that deforms under the contact load as well. Adding
the whole Hertz compliance at the contact (the paper's law) counts the object's compliance twice,
more so the finer the mesh. The mesh does, however, not resolve the stress field of a patch
smaller than its facets: a load on a patch of radius a deflects it like a patch of radius
``sqrt(a^2 + h^2)``, with ``h`` the mesh's resolution length at the contact. The contact law
therefore supplies only what the mesh does not resolve:

    d delta / dF = 2 / (3 K' a)  -  r * 2 / (3 K' sqrt(a^2 + h^2)),

the Hertz compliance of the pair minus the share ``r = E*_pair / E*_object`` of it that belongs to
the object (1 for a rigid fingertip, less for a soft one, whose own compliance the mesh never
resolves) as far as the mesh resolves it. Integrated over a (``dF = 3 K' a^2 da / R``):

    delta(a) = (a^2 - 2 r I2(a)) / R,    I2(a) = integral of t^2 / sqrt(t^2 + h(t)^2) over (0, a)

(Gauss-Legendre), increasing in a for every r < 1. On a coarse mesh (h >> a) it is Hertz's law
(the mesh is stiff at the patch's scale and the contact supplies the local compliance); as the
mesh resolves the patch (h << a) the law becomes a stiff penalty and the mesh's own deformation
is the indentation.
``r`` is capped at :data:`~softgrasp.physics.fingertip.laws.MAX_SHARE`: the law keeps at least
2 % of Hertz's tangent compliance, which bounds its stiffness at 50x Hertz's (the fully resolved
limit is reached within ~3 % of force) and brackets the root for a.

The resolution length ``h`` is the mesh's where the fingertip lands
(:mod:`softgrasp.physics.fingertip.landing`): the radius of the disc whose Hertz compliance
``1 / (2 E* h)`` equals the body's compliance to the load as the shape functions put it on the
nodes, ``h_land`` while the contact patch is smaller than the facet, moving to a single node's
``h_node`` as the patch covers it (:func:`_spread2`); the object's curvature there enters R_eff.
"""

from __future__ import annotations

import math

import numpy as np

from softgrasp import jitcache

__all__ = ["elastic_normal_value", "contact_radius_value", "penetration_value"]

_jit = jitcache.jit(fastmath=False, error_model="numpy")


#: Gauss-Legendre nodes and weights on [-1, 1] for the law's integrals over the contact radius.
_GL_X, _GL_W = np.polynomial.legendre.leggauss(16)


@_jit
def _spread2(t: float, h_node: float, h_land: float, size: float) -> float:
    """h(t)^2 [m^2]: the squared resolution length at contact radius t, from the landing point's
    ``h_land`` while the patch is smaller than the facet (of size ``size``, circumradius
    ``rho = size / sqrt(3)``) to a node's ``h_node`` once it covers it:
    ``h_node^2 + (h_land^2 - h_node^2) rho^2 / (rho^2 + t^2)``."""
    s2 = size * size / 3.0
    return h_node * h_node + (h_land * h_land - h_node * h_node) * s2 / (s2 + t * t)


@_jit
def _moments(a: float, h_node: float, h_land: float, size: float) -> tuple[float, float]:
    """The integrals of t^2 / s(t) and t^5 / s(t) over t from 0 to a, s = sqrt(t^2 + h(t)^2)
    (Gauss-Legendre on [0, min(a, 8 h)] and on the rest, where the integrands are smooth)."""
    split = min(a, 8.0 * max(h_node, h_land))
    i2 = 0.0
    i5 = 0.0
    for part in range(2):
        lo = 0.0 if part == 0 else split
        hi = split if part == 0 else a
        if hi <= lo:
            continue
        mid = 0.5 * (hi + lo)
        half = 0.5 * (hi - lo)
        for k in range(_GL_X.shape[0]):
            t = mid + half * _GL_X[k]
            w = half * _GL_W[k] / math.sqrt(t * t + _spread2(t, h_node, h_land, size))
            t2 = t * t
            i2 += w * t2
            i5 += w * t2 * t2 * t
    return i2, i5


@_jit
def _sharpness(a: float, share: float, h_node: float, h_land: float, size: float) -> float:
    """1 - share a / s(a): the law's tangent compliance over Hertz's at contact radius a."""
    return 1.0 - share * a / math.sqrt(a * a + _spread2(a, h_node, h_land, size))


@_jit
def contact_radius_value(
    delta: float, radius: float, share: float, h_node: float, h_land: float, size: float
) -> float:
    """The Hertz contact radius a [m] at which the law's penetration is ``delta`` [m] (> 0):
    the root of ``(a^2 - 2 share I2(a)) / R = delta`` (I2 = integral of t^2 / s(t)) between
    ``sqrt(R delta)`` and ``sqrt(R delta / (1 - share))`` (safeguarded Newton)."""
    lo = math.sqrt(radius * delta)
    if share <= 0.0:
        return lo
    hi = math.sqrt(radius * delta / (1.0 - share))
    a = lo
    for _ in range(100):
        i2, _ = _moments(a, h_node, h_land, size)
        g = (a * a - 2.0 * share * i2) / radius - delta
        if g > 0.0:
            hi = a
        else:
            lo = a
        dg = 2.0 * a / radius * _sharpness(a, share, h_node, h_land, size)
        nxt = a - g / dg if dg > 0.0 else 0.5 * (lo + hi)
        if not (lo < nxt < hi):
            nxt = 0.5 * (lo + hi)
        if abs(nxt - a) <= 1e-13 * nxt or hi - lo <= 1e-13 * hi:
            return nxt
        a = nxt
    return a


@_jit
def elastic_normal_value(
    delta: float, radius: float, K: float, n: float, share: float, h_node: float, h_land: float, size: float
) -> tuple[float, float, float]:
    """Elastic normal force F [N], its derivative dF/d delta [N/m] and its energy (integral of F
    over the penetration) [J] of one fingertip at penetration ``delta`` [m]; zeros unless delta > 0.

    ``share = 0``: the paper's law ``K delta^n`` (Eq. 9-11). ``share > 0`` (then n = 3/2): the
    Hertz law less the object's compliance that the mesh resolves, with resolution lengths
    ``h_node`` and ``h_land`` [m] on a facet of size ``size`` [m] (module docstring)."""
    if not delta > 0.0:
        return 0.0, 0.0, 0.0
    if share <= 0.0:
        dn = delta**n
        return K * dn, n * K * dn / delta, K * dn * delta / (n + 1.0)
    a = contact_radius_value(delta, radius, share, h_node, h_land, size)
    rs = math.sqrt(radius)
    F = K * a * a * a / (radius * rs)
    slope = 1.5 * K * a / rs / _sharpness(a, share, h_node, h_land, size)
    _, i5 = _moments(a, h_node, h_land, size)
    W = 2.0 * K / (radius * radius * rs) * (a**5 / 5.0 - share * i5)
    return F, slope, W


@_jit
def penetration_value(
    force: float, radius: float, K: float, n: float, share: float, h_node: float, h_land: float, size: float
) -> float:
    """The penetration [m] at which :func:`elastic_normal_value` gives the normal force ``force``
    [N] (its inverse; 0 unless force > 0): ``(F / K)^(1/n)`` under the paper's law; under the
    resolved law the contact radius of Hertz's ``F = K a^3 / R^1.5`` and ``(a^2 - 2 share I2(a)) / R``.
    Against a rigid object this is the travel at which the fingertip meets the force; a meshed
    object adds its own deformation to it."""
    if not force > 0.0:
        return 0.0
    if share <= 0.0:
        return (force / K) ** (1.0 / n)
    a = (force * radius * math.sqrt(radius) / K) ** (1.0 / 3.0)
    i2, _ = _moments(a, h_node, h_land, size)
    return (a * a - 2.0 * share * i2) / radius
