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

    delta(a) = (a^2 - r phi(a)) / R,    phi(a) = a sqrt(a^2 + h^2) - h^2 asinh(a / h),

increasing in a for every r < 1. On a coarse mesh (h >> a) it is Hertz's law (the mesh is stiff
at the patch's scale and the contact supplies the local compliance); as the mesh resolves the
patch (h << a) the law becomes a stiff penalty and the mesh's own deformation is the indentation.
``r`` is capped at :data:`~softgrasp.physics.fingertip.laws.MAX_SHARE`: the law keeps at least 2 % of Hertz's tangent compliance,
which bounds its stiffness at 50x Hertz's (the fully resolved limit is reached within ~3 % of
force) and keeps the root for a bracketed.

The resolution length ``h`` is the radius of the disc whose Hertz compliance ``1 / (2 E* h)``
equals the body's compliance to the contact load as the shape functions put it on the nodes of
the facet under the fingertip's deepest point (Eq. 17-20): ``h = (pi / 2) / sum_lm b_l b_m /
r_lm``, the half-space's ``1 / r`` between distinct nodes and, for a node's own deflection,
``r_ll = RESOLUTION x`` the facet's size (:data:`~softgrasp.physics.fingertip.laws.RESOLUTION`, a
property of the discretisation: linear tetrahedra, the calibrated spring network).
:func:`softgrasp.physics.fingertip.forces._resolution_length` computes it; it is continuous as the
point crosses an edge or a vertex. A load on one node is less resolved (smaller h) than one
spread on a facet's three.
"""

from __future__ import annotations

import math

from softgrasp import jitcache

__all__ = ["elastic_normal_value", "contact_radius_value"]

_jit = jitcache.jit(fastmath=False, error_model="numpy")


@_jit
def _phi(a: float, h: float) -> float:  # pragma: no cover - compiled
    """a sqrt(a^2 + h^2) - h^2 asinh(a / h) = h^2 (2/3 x^3 - 1/5 x^5 + ...), x = a / h."""
    if h <= 0.0:
        return a * a
    x = a / h
    if x < 0.1:
        x2 = x * x
        return h * h * x * x2 * (2.0 / 3.0 - x2 * (0.2 - x2 * (3.0 / 28.0 - x2 * 5.0 / 72.0)))
    return a * math.sqrt(a * a + h * h) - h * h * math.asinh(x)


@_jit
def _psi(a: float, h: float) -> float:
    """Integral of t^5 / sqrt(t^2 + h^2) over t from 0 to a."""
    if h <= 0.0:
        return a**5 / 5.0
    x = a / h
    if x < 0.5:
        # h^5 sum_k binom(-1/2, k) x^(6 + 2k) / (6 + 2k)
        x2 = x * x
        term = 1.0
        p = x2 * x2 * x2
        total = 0.0
        for k in range(40):
            total += term * p / (6.0 + 2.0 * k)
            term *= -(k + 0.5) / (k + 1.0)
            p *= x2
        return h**5 * total
    u = a * a + h * h
    su = math.sqrt(u)
    h2 = h * h
    return 0.5 * (0.4 * (u * u * su - h2 * h2 * h) - (4.0 / 3.0) * h2 * (u * su - h2 * h) + 2.0 * h2 * h2 * (su - h))


@_jit
def contact_radius_value(delta: float, radius: float, share: float, h: float) -> float:
    """The Hertz contact radius a [m] at which the law's penetration is ``delta`` [m] (> 0):
    the root of ``(a^2 - share phi(a)) / R = delta`` between ``sqrt(R delta)`` and
    ``sqrt(R delta / (1 - share))`` (safeguarded Newton)."""
    lo = math.sqrt(radius * delta)
    if share <= 0.0:
        return lo
    hi = math.sqrt(radius * delta / (1.0 - share))
    a = lo
    for _ in range(100):
        g = (a * a - share * _phi(a, h)) / radius - delta
        if g > 0.0:
            hi = a
        else:
            lo = a
        dg = 2.0 * a / radius * (1.0 - share * a / math.sqrt(a * a + h * h))
        step = g / dg if dg > 0.0 else 0.0
        nxt = a - step
        if not (lo < nxt < hi):
            nxt = 0.5 * (lo + hi)
        if abs(nxt - a) <= 1e-14 * nxt:
            return nxt
        a = nxt
    return a


@_jit
def elastic_normal_value(
    delta: float, radius: float, K: float, n: float, share: float, h: float
) -> tuple[float, float, float]:
    """Elastic normal force F [N], its derivative dF/d delta [N/m] and its energy (integral of F
    over the penetration) [J] of one fingertip at penetration ``delta`` [m]; zeros unless delta > 0.

    ``share = 0``: the paper's law ``K delta^n`` (Eq. 9-11). ``share > 0`` (then n = 3/2): the
    Hertz law less the object's compliance that the mesh resolves at resolution length ``h`` [m]
    (module docstring)."""
    if not delta > 0.0:
        return 0.0, 0.0, 0.0
    if share <= 0.0:
        dn = delta**n
        return K * dn, n * K * dn / delta, K * dn * delta / (n + 1.0)
    a = contact_radius_value(delta, radius, share, h)
    rs = math.sqrt(radius)
    F = K * a * a * a / (radius * rs)
    slope = 1.5 * K * a / rs / (1.0 - share * a / math.sqrt(a * a + h * h))
    W = 2.0 * K / (radius * radius * rs) * (a**5 / 5.0 - share * _psi(a, h))
    return F, slope, W
