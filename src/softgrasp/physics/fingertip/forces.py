"""Compiled fingertip contact forces of the touching pairs (paper Eq. 1-20).

For each pair (as :mod:`softgrasp.physics.fingertip.detect` finds it), :func:`_pair_forces`
evaluates the relative velocity at the contact point (Eq. 1-8, :func:`_relative_velocity`), the
normal force ``f_n = w max(0, K delta^n + C delta_dot)`` (or Hunt-Crossley's ``delta^n (K + C
delta_dot)``) along the facet's inward normal (Eq. 9-14) with the patch rule's weight w and the
finger's deepest penetration (:func:`_patch`, :func:`_finger_laws`, :func:`_weight_depth`) or the
literal per-facet rule, the elastic-slider friction ``-w (k_t v + c_t V_t)`` capped by Coulomb's
``mu f_n`` (Eq. 15-16, Algorithm 1, :mod:`softgrasp.physics.fingertip.friction`; sliding along
``-V_t`` when moving, the stick force scaled to the cap at rest), and spreads the pair's force on
the facet's nodes by the shape functions, ``f_l = b_l f_pj`` (Eq. 17-20), so that nodal forces
balance the fingertip's force and moment.
"""

from __future__ import annotations

import math

import numpy as np

from softgrasp import jitcache
from softgrasp.physics.fingertip import laws
from softgrasp.physics.fingertip.friction import _elastic, _stick, _tangential_stiffness

__all__: list[str] = []

_jit = jitcache.jit(fastmath=False, error_model="numpy")
#: The normal force law, Eq. 9 (:func:`softgrasp.physics.fingertip.laws.normal_force_value`).
_normal_force = _jit(laws.normal_force_value)
#: Coulomb sliding, Eq. 15 (:func:`softgrasp.physics.fingertip.laws.coulomb_slip_value`).
_coulomb_slip = _jit(laws.coulomb_slip_value)


@_jit
def _patch(finger, val, nf):  # pragma: no cover - compiled
    """Each finger's deepest pair (the first of largest depth; -1 without pairs) and the sum of
    its pairs' patch weights ``area x depth x facing``."""
    deep = np.full(nf, -1, np.int64)
    total = np.zeros(nf)
    for p in range(finger.shape[0]):
        f = finger[p]
        if deep[f] < 0 or val[p, 10] > val[deep[f], 10]:
            deep[f] = p
        total[f] += val[p, 11] * val[p, 10] * val[p, 12]
    return deep, total


@_jit
def _law_values(depth, f, radii, law, n_exp, ratio, min_depth_ratio):  # pragma: no cover - compiled
    """Finger f's normal law at ``depth``: (elastic force F [N], dF/d delta [N/m], energy [J],
    ``max(delta, 0)^n``, k_t [N/m])."""
    F, slope, W = _elastic(depth, f, radii, law, n_exp)
    kt = _tangential_stiffness(depth, f, radii, law, n_exp, ratio, min_depth_ratio)
    return F, slope, W, max(depth, 0.0) ** n_exp, kt


@_jit
def _finger_laws(deep, val, radii, law, n_exp, ratio, min_depth_ratio):  # pragma: no cover
    """Per finger (n_f, 5), its normal law (:func:`_law_values`) at its deepest pair's depth, zeros
    without pairs: the patch rule evaluates every pair of a finger there, so the law is evaluated
    once a finger instead of once a pair."""
    nf = deep.shape[0]
    fl = np.zeros((nf, 5))
    for f in range(nf):
        p = deep[f]
        if p >= 0:
            F, slope, W, dn, kt = _law_values(val[p, 10], f, radii, law, n_exp, ratio, min_depth_ratio)
            fl[f, 0] = F
            fl[f, 1] = slope
            fl[f, 2] = W
            fl[f, 3] = dn
            fl[f, 4] = kt
    return fl


@_jit
def _pair_normal_law(p, f, val, radii, law, n_exp, ratio, min_depth_ratio, patch, fl):  # pragma: no cover
    """Pair p's normal law values (:func:`_law_values`): its finger's (``fl``) under the patch rule,
    at its own depth under the literal one."""
    if patch:
        return fl[f, 0], fl[f, 1], fl[f, 2], fl[f, 3], fl[f, 4]
    return _law_values(val[p, 10], f, radii, law, n_exp, ratio, min_depth_ratio)


@_jit
def _weight_depth(p, f, val, deep, total, patch):  # pragma: no cover - compiled
    """Pair p's weight w_j and the penetration its normal law is evaluated at."""
    if patch:
        return val[p, 11] * val[p, 10] * val[p, 12] / total[f], val[deep[f], 10]
    return 1.0, val[p, 10]


@_jit
def _relative_velocity(p, f, j, val, v, facets, centres, velocities, omegas):  # pragma: no cover
    """Tangential relative velocity V_t (3 floats) and the penetration rate d delta / dt of pair p
    (Eq. 1-8): the fingertip's velocity at the contact point ``V_c + Omega x (P - c)`` (Eq. 1)
    minus the facet's there, its nodes' velocities weighted by the shape functions
    ``sum_l (A_l / A_G) V_Nl`` (Eq. 4), is the relative velocity V_r (Eq. 5); its normal part
    ``(V_r . n) n`` (Eq. 6) closes the gap at ``d delta / dt = -V_r . n``, the rest is V_t (Eq. 7)."""
    nx = val[p, 6]
    ny = val[p, 7]
    nz = val[p, 8]
    # relative velocity at the contact point: finger (Eq. 1) minus facet (Eq. 4)
    rx = val[p, 3] - centres[f, 0]
    ry = val[p, 4] - centres[f, 1]
    rz = val[p, 5] - centres[f, 2]
    vrx = velocities[f, 0] + (omegas[f, 1] * rz - omegas[f, 2] * ry)
    vry = velocities[f, 1] + (omegas[f, 2] * rx - omegas[f, 0] * rz)
    vrz = velocities[f, 2] + (omegas[f, 0] * ry - omegas[f, 1] * rx)
    for m in range(3):
        node = facets[j, m]
        vrx -= val[p, m] * v[node, 0]
        vry -= val[p, m] * v[node, 1]
        vrz -= val[p, m] * v[node, 2]
    vn = vrx * nx + vry * ny + vrz * nz
    vtx = vrx - vn * nx
    vty = vry - vn * ny
    vtz = vrz - vn * nz
    return vtx, vty, vtz, -vn


@_jit
def _pair_law(
    p, finger, facet, val, x, v, facets, centres, radii, velocities, omegas, law, C, mu, n_exp,
    hunt_crossley, patch, ratio, min_depth_ratio, active, anchor, offset, memory, static, deep, total, fl,
):  # pragma: no cover - compiled
    """The contact law of pair p: its normal force f_n (Eq. 9-14: the patch rule's weight w times
    ``max(0, F_e + C delta_dot)``, or Hunt-Crossley's ``F_e + C delta^n delta_dot``, with F_e the
    elastic law (:mod:`softgrasp.physics.fingertip.resolved`; K delta^n for the paper's), zero
    unless delta > 0, never pulling) and its friction on the finger (Eq. 15-16, Algorithm 1: the
    elastic slider ``-w (k_t v + c_t V_t)`` with ``c_t = ratio C``, capped by ``mu f_n``: Coulomb
    sliding ``-mu f_n V_t / |V_t|`` when moving, the stick force scaled to the cap at rest).
    ``deep, total, fl``: each finger's deepest pair, weight sum and law values (:func:`_patch`,
    :func:`_finger_laws`). ``static``: no relative velocity.

    Returns (f_n, friction x, y, z, w, k_t, stick displacement x, y, z, mu f_n, slipping); k_t,
    the stick and the cap are 0 without friction."""
    f = finger[p]
    j = facet[p]
    vtx = 0.0
    vty = 0.0
    vtz = 0.0
    rate = 0.0
    if not static:
        vtx, vty, vtz, rate = _relative_velocity(p, f, j, val, v, facets, centres, velocities, omegas)
    w, depth = _weight_depth(p, f, val, deep, total, patch)
    # normal force (Eq. 9), zero unless delta > 0, never pulling
    elastic, _, _, dn, kt_law = _pair_normal_law(p, f, val, radii, law, n_exp, ratio, min_depth_ratio, patch, fl)
    fn = w * _normal_force(depth, elastic, dn, rate, C[f], hunt_crossley)
    ftx = 0.0
    fty = 0.0
    ftz = 0.0
    kt = 0.0
    sx = 0.0
    sy = 0.0
    sz = 0.0
    cap = 0.0
    slipping = False
    if mu > 0.0:
        sx, sy, sz, _, _, _, _ = _stick(p, f, j, val, x, facets, centres, active, anchor, offset, memory)
        kt = kt_law
        a = -(w * kt)
        b = w * (ratio * C[f])
        ftx = a * sx - b * vtx
        fty = a * sy - b * vty
        ftz = a * sz - b * vtz
        cap = mu * fn
        mag = math.sqrt(ftx * ftx + fty * fty + ftz * ftz)
        if mag > cap:
            slipping = True
            speed = math.sqrt(vtx * vtx + vty * vty + vtz * vtz)
            if speed > 0.0:  # Coulomb slip (Eq. 15)
                ftx, fty, ftz = _coulomb_slip(fn, vtx, vty, vtz, mu)
            else:
                r = cap / mag
                ftx *= r
                fty *= r
                ftz *= r
    return fn, ftx, fty, ftz, w, kt, sx, sy, sz, cap, slipping


@_jit
def _pair_forces(
    finger, facet, val, x, v, facets, centres, radii, velocities, omegas, law, C, mu, n_exp,
    hunt_crossley, patch, ratio, min_depth_ratio, active, anchor, offset, memory, static, out,
):  # pragma: no cover - compiled
    """Forces of the pairs (finger, facet, val) (as :func:`_detect` gives them) added to ``out``
    (N, 3) (or wider: columns 0-2): each pair's law (:func:`_pair_law`: normal force, Eq. 9-14,
    patch or literal rule; elastic-slider friction with the Coulomb cap, Eq. 15-16, Algorithm 1)
    spread on its facet's nodes by the shape functions (Eq. 17-20). ``static``: at rest (no
    relative velocity: no damping, a slipping pair capped along its stick), as
    :meth:`softgrasp.physics.fingertip.contact.FingertipContact.static_forces`; ``v``, ``velocities`` and
    ``omegas`` are then not read."""
    deep, total = _patch(finger, val, centres.shape[0])
    fl = _finger_laws(deep, val, radii, law, n_exp, ratio, min_depth_ratio)
    for p in range(finger.shape[0]):
        fn, ftx, fty, ftz, _, _, _, _, _, _, _ = _pair_law(
            p, finger, facet, val, x, v, facets, centres, radii, velocities, omegas, law, C, mu, n_exp,
            hunt_crossley, patch, ratio, min_depth_ratio, active, anchor, offset, memory, static, deep, total,
            fl,
        )  # fmt: skip
        # the pair's force on the object, spread by the shape functions (Eq. 17-20)
        Fx = -fn * val[p, 6] - ftx
        Fy = -fn * val[p, 7] - fty
        Fz = -fn * val[p, 8] - ftz
        j = facet[p]
        for m in range(3):
            node = facets[j, m]
            out[node, 0] += val[p, m] * Fx
            out[node, 1] += val[p, m] * Fy
            out[node, 2] += val[p, m] * Fz


@_jit
def _pair_table(
    finger, facet, val, x, v, facets, centres, radii, velocities, omegas, law, C, mu, n_exp,
    hunt_crossley, patch, ratio, min_depth_ratio, active, anchor, offset, memory, static, table, slipping,
):  # pragma: no cover - compiled
    """Each pair's law (:func:`_pair_law`) into ``table`` (k, 15): f_n 0, friction on the finger
    1-3, weight w 4, k_t 5, stick displacement 6-8, cap mu f_n 9, the penetration delta the normal
    law is evaluated at 10 and the pair it is measured on 11 (its finger's deepest pair under the
    patch rule, itself under the literal one), the elastic law's force F_e 12, dF_e/d delta 13
    and energy 14 there (unweighted); whether it slips into ``slipping`` (k,)."""
    deep, total = _patch(finger, val, centres.shape[0])
    fl = _finger_laws(deep, val, radii, law, n_exp, ratio, min_depth_ratio)
    for p in range(finger.shape[0]):
        fn, ftx, fty, ftz, w, kt, sx, sy, sz, cap, slips = _pair_law(
            p, finger, facet, val, x, v, facets, centres, radii, velocities, omegas, law, C, mu, n_exp,
            hunt_crossley, patch, ratio, min_depth_ratio, active, anchor, offset, memory, static, deep, total,
            fl,
        )  # fmt: skip
        table[p, 0] = fn
        table[p, 1] = ftx
        table[p, 2] = fty
        table[p, 3] = ftz
        table[p, 4] = w
        table[p, 5] = kt
        table[p, 6] = sx
        table[p, 7] = sy
        table[p, 8] = sz
        table[p, 9] = cap
        at = deep[finger[p]] if patch else p
        table[p, 10] = val[at, 10]
        table[p, 11] = at
        F, slope, W, _, _ = _pair_normal_law(
            p, finger[p], val, radii, law, n_exp, ratio, min_depth_ratio, patch, fl
        )
        table[p, 12] = F
        table[p, 13] = slope
        table[p, 14] = W
        slipping[p] = slips
