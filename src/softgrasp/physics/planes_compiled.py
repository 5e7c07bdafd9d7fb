"""Compiled (Numba) law of the rigid planes' contact (:class:`softgrasp.physics.planes.PlaneContact`).

Per node, with penetration ``p = -(x - P) . n`` and the velocity relative to the plane ``w``:

* force: ``f_n = max(k p - c v_n, 0)`` along n; friction ``f_t = -k_t s - c_t v_t`` from the node's
  tangential stretch s off its anchor, capped at ``mu f_n``; zero for a node not touching;
* state update after a step (the paper's Algorithm 1): a free node's anchor follows it; a
  touching node keeps its anchor unless its stretch exceeds the Coulomb limit ``mu k p / k_t``,
  in which case the anchor is dragged to that limit.

:meth:`PlaneContact.forces` and :meth:`PlaneContact.update` call these kernels when the compiled
kernels are selected (:mod:`softgrasp.backend`), and so does the fused stepper
(:mod:`softgrasp.sim.fused`) on its own arrays. The kernels take node ranges ``lo:hi`` and rows of
any width >= 3 (the first three columns are x, y, z).
"""

from __future__ import annotations

import math

from softgrasp import jitcache

__all__ = ["plane_forces", "plane_update"]

_jit = jitcache.jit(fastmath=False, error_model="numpy")


@_jit
def plane_update(x, p0, normal, mu, k, kt, active, anchor, lo, hi):  # pragma: no cover - compiled
    """The friction state after a step, in place: ``active`` (N,) whether each node of ``lo:hi``
    touches the plane through ``p0`` (3,) with unit ``normal`` (3,), ``anchor`` (N, 3) its anchor
    relative to ``p0``; ``k``, ``kt`` (N,) the normal and tangential stiffnesses [N/m]."""
    nx = normal[0]
    ny = normal[1]
    nz = normal[2]
    for i in range(lo, hi):
        rx = x[i, 0] - p0[0]
        ry = x[i, 1] - p0[1]
        rz = x[i, 2] - p0[2]
        pen = -rx * nx + -ry * ny + -rz * nz
        touching = pen > 0.0
        rn = rx * nx + ry * ny + rz * nz
        tx = rx - rn * nx
        ty = ry - rn * ny
        tz = rz - rn * nz
        active[i] = touching
        if not touching or not mu > 0.0:  # the anchor follows a free node
            anchor[i, 0] = tx
            anchor[i, 1] = ty
            anchor[i, 2] = tz
            continue
        sx = tx - anchor[i, 0]
        sy = ty - anchor[i, 1]
        sz = tz - anchor[i, 2]
        s_norm = math.sqrt(sx * sx + sy * sy + sz * sz)
        limit = mu * k[i] * max(pen, 0.0) / max(kt[i], 1e-300)
        if s_norm > limit:  # slip: the anchor is dragged to the Coulomb limit
            q = limit / s_norm
            anchor[i, 0] = tx - sx * q
            anchor[i, 1] = ty - sy * q
            anchor[i, 2] = tz - sz * q


@_jit
def plane_forces(x, v, p0, normal, velocity, mu, k, c, kt, ct, anchor, lo, hi, out):  # pragma: no cover
    """Contact forces [N] of the plane through ``p0`` (3,) moving at ``velocity`` (3,) on nodes
    ``lo:hi`` added to ``out``, with the anchors ``anchor`` (N, 3) of the step's friction state and
    the per-node coefficients ``k``, ``c``, ``kt``, ``ct`` (N,). Returns the forces' power [W]."""
    nx = normal[0]
    ny = normal[1]
    nz = normal[2]
    power = 0.0
    for i in range(lo, hi):
        x0 = x[i, 0]
        x1 = x[i, 1]
        x2 = x[i, 2]
        pen = -(x0 - p0[0]) * nx + -(x1 - p0[1]) * ny + -(x2 - p0[2]) * nz
        if not pen > 0.0:
            continue
        v0 = v[i, 0]
        v1 = v[i, 1]
        v2 = v[i, 2]
        vrx = v0 - velocity[0]
        vry = v1 - velocity[1]
        vrz = v2 - velocity[2]
        vn = vrx * nx + vry * ny + vrz * nz
        fn = max(k[i] * pen - c[i] * vn, 0.0)
        fx = fn * nx
        fy = fn * ny
        fz = fn * nz
        if mu > 0.0:
            sx = x0 - (p0[0] + anchor[i, 0])
            sy = x1 - (p0[1] + anchor[i, 1])
            sz = x2 - (p0[2] + anchor[i, 2])
            sn = sx * nx + sy * ny + sz * nz
            sx = sx - sn * nx
            sy = sy - sn * ny
            sz = sz - sn * nz
            tx = -kt[i] * sx - ct[i] * (vrx - vn * nx)
            ty = -kt[i] * sy - ct[i] * (vry - vn * ny)
            tz = -kt[i] * sz - ct[i] * (vrz - vn * nz)
            mag = math.sqrt(tx * tx + ty * ty + tz * tz)
            cap = mu * fn
            if mag > cap:
                q = cap / max(mag, 1e-300)
                tx *= q
                ty *= q
                tz *= q
            fx += tx
            fy += ty
            fz += tz
        out[i, 0] += fx
        out[i, 1] += fy
        out[i, 2] += fz
        power += fx * v0 + fy * v1 + fz * v2
    return power
