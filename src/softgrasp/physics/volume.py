"""The volume term of the mass-spring body: per tet ``kappa V0 psi(V / V0)``.

Under small strain it adds ``kappa (tr eps)^2 / 2`` to the energy density, i.e. kappa to Lame's
lambda (see :mod:`softgrasp.model.network`). psi(J) has psi(1) = psi'(1) = 0 and psi''(1) = 1:
with the inversion barrier (kappa >= 0) ``psi = J - 1 - ln J`` (infinite as J -> 0, J floored at
:data:`J_FLOOR`), else the quadratic ``psi = (J - 1)^2 / 2`` (kappa < 0, i.e. nu < 1/4). The force
on node k is ``-kappa psi'(J) dV/dx_k``; ``d f / d x`` is given as 3x3 node blocks at
:func:`volume_pairs` (16 per tet).
"""

from __future__ import annotations

import math

import numpy as np
import scipy.sparse as sp

from softgrasp.physics.forces import assemble_blocks
from softgrasp.physics.jit import NO_ORDER, NO_POS, Array, IntArray, f64, fjit, i64, jit

__all__ = [
    "J_FLOOR",
    "count_inverted",
    "volume_forces",
    "volume_pairs",
    "volume_jacobian_blocks",
    "volume_jacobian",
]

#: Barrier floor of J in psi.
J_FLOOR = 1e-12


@jit
def psi(J, barrier):  # pragma: no cover - compiled
    """psi(J) of the module docstring: with the inversion barrier ``J - 1 - ln J`` (J floored at
    :data:`J_FLOOR` in ln J), else ``(J - 1)^2 / 2``."""
    if barrier:
        return J - 1.0 - math.log(J if J > J_FLOOR else J_FLOOR)
    d = J - 1.0
    return 0.5 * d * d


@jit
def psi_derivatives(J, barrier):  # pragma: no cover - compiled
    """(psi'(J), psi''(J)) of :func:`psi` (the barrier's J floored at :data:`J_FLOOR`); apart
    from psi, whose logarithm the force kernels need only for the energy."""
    if barrier:
        Jc = J if J > J_FLOOR else J_FLOOR
        return 1.0 - 1.0 / Jc, 1.0 / (Jc * Jc)
    return J - 1.0, 1.0


@fjit
def _volumes(x, tets, inv6v0, v0, kappa, barrier, want_energy, check, lo, hi, out):  # pragma: no cover
    """Volume-term forces of tets ``lo:hi`` added to ``out`` (N, 3): on node k
    ``-kappa psi'(J) c_k / 6``, with c_k the unscaled cross products, J = V / V0 and psi the
    barrier or the quadratic; ``1 / (6 V0)`` precomputed (one division per tet). Returns (energy
    (0 unless ``want_energy``), the number of tets with non-positive signed volume and the first
    of them (0 and -1 unless ``check``))."""
    energy = 0.0
    count = 0
    first = -1
    ck = -kappa / 6.0
    for t in range(np.uint64(lo), np.uint64(hi)):  # unsigned: no negative-index wrap-around per access
        p0 = np.uint64(tets[t, 0])
        p1 = np.uint64(tets[t, 1])
        p2 = np.uint64(tets[t, 2])
        p3 = np.uint64(tets[t, 3])
        x0 = x[p0, 0]
        y0 = x[p0, 1]
        z0 = x[p0, 2]
        ax = x[p1, 0] - x0
        ay = x[p1, 1] - y0
        az = x[p1, 2] - z0
        bx = x[p2, 0] - x0
        by = x[p2, 1] - y0
        bz = x[p2, 2] - z0
        cx = x[p3, 0] - x0
        cy = x[p3, 1] - y0
        cz = x[p3, 2] - z0
        c1x = by * cz - bz * cy
        c1y = bz * cx - bx * cz
        c1z = bx * cy - by * cx
        c2x = cy * az - cz * ay
        c2y = cz * ax - cx * az
        c2z = cx * ay - cy * ax
        c3x = ay * bz - az * by
        c3y = az * bx - ax * bz
        c3z = ax * by - ay * bx
        det = ax * c1x + ay * c1y + az * c1z
        if check and not det / 6.0 > 0.0:  # signed_volumes(x, tets) <= 0
            if first < 0:
                first = np.int64(t)
            count += 1
        J = det * inv6v0[t]
        dw, _ = psi_derivatives(J, barrier)
        if want_energy:
            energy += kappa * v0[t] * psi(J, barrier)
        s = ck * dw
        out[p1, 0] += s * c1x
        out[p1, 1] += s * c1y
        out[p1, 2] += s * c1z
        out[p2, 0] += s * c2x
        out[p2, 1] += s * c2y
        out[p2, 2] += s * c2z
        out[p3, 0] += s * c3x
        out[p3, 1] += s * c3y
        out[p3, 2] += s * c3z
        out[p0, 0] -= s * (c1x + c2x + c3x)
        out[p0, 1] -= s * (c1y + c2y + c3y)
        out[p0, 2] -= s * (c1z + c2z + c3z)
    return energy, count, first


@jit
def _volume_blocks(
    x, tets, rest, kappa, barrier, base, stride, use_pos, offset, out, order, lo, hi
):  # pragma: no cover
    """Add the 16 blocks ``-d^2 (kappa V0 psi) / d x_a d x_b`` of the tets ``order[lo:hi]``
    (``lo:hi`` where ``order`` is empty) to ``out``: block B = offset + 16 t + 4 a + b (a, b local
    node indices), placed as in :func:`_spring_blocks`."""
    g = np.empty((4, 3))
    w = np.empty((4, 4, 3))  # d^2 V / d x_a d x_b = skew(w[a, b]) / 6
    one = np.uint64(1)
    two = np.uint64(2)
    av = np.empty((4, 3))  # av[1..3] = a1..a3
    for idx in range(lo, hi):
        t = order[idx] if order.shape[0] else idx
        n0 = np.uint64(tets[t, 0])
        for m in range(1, 4):
            nm = np.uint64(tets[t, m])
            for d in range(3):
                av[m, d] = x[nm, d] - x[n0, d]
        # g_k = (a_{k+1} x a_{k+2}) / 6 cyclically, g0 = -(g1 + g2 + g3)
        for m in range(1, 4):
            p = 1 + m % 3
            q = 1 + (m + 1) % 3
            g[m, 0] = (av[p, 1] * av[q, 2] - av[p, 2] * av[q, 1]) / 6.0
            g[m, 1] = (av[p, 2] * av[q, 0] - av[p, 0] * av[q, 2]) / 6.0
            g[m, 2] = (av[p, 0] * av[q, 1] - av[p, 1] * av[q, 0]) / 6.0
        for d in range(3):
            g[0, d] = -(g[1, d] + g[2, d] + g[3, d])
        V = av[1, 0] * g[1, 0] + av[1, 1] * g[1, 1] + av[1, 2] * g[1, 2]
        dw, d2w = psi_derivatives(V / rest[t], barrier)
        cg = kappa * d2w / rest[t]
        ch = kappa * dw / 6.0
        for d in range(3):
            w[0, 0, d] = 0.0
            w[1, 1, d] = 0.0
            w[2, 2, d] = 0.0
            w[3, 3, d] = 0.0
            w[1, 2, d] = -av[3, d]
            w[1, 3, d] = av[2, d]
            w[2, 3, d] = -av[1, d]
            w[0, 1, d] = av[2, d] - av[3, d]
            w[0, 2, d] = av[3, d] - av[1, d]
            w[0, 3, d] = av[1, d] - av[2, d]
            for a in range(4):
                for b in range(a + 1, 4):
                    w[b, a, d] = -w[a, b, d]
        for a in range(4):
            # entry (r, s) of block (a, b): -(cg g[a, r] g[b, s] + ch skew(w[a, b])[r, s]), with
            # skew(w) = [[0, -wz, wy], [wz, 0, -wx], [-wy, wx, 0]]; the products in this order
            ga0 = cg * g[a, 0]
            ga1 = cg * g[a, 1]
            ga2 = cg * g[a, 2]
            for b in range(4):
                wx = w[a, b, 0]
                wy = w[a, b, 1]
                wz = w[a, b, 2]
                gb0 = g[b, 0]
                gb1 = g[b, 1]
                gb2 = g[b, 2]
                # Unsigned positions: Numba then adds no negative-index wrap-around to each
                # access (0.25 of the kernel's time; the same sums).
                B = np.uint64(offset + 16 * t + 4 * a + b)
                if use_pos:
                    i0 = np.uint64(base[B])
                    st = np.uint64(stride[B])
                else:
                    i0 = np.uint64(9) * B
                    st = np.uint64(3)
                i1 = i0 + st
                i2 = i1 + st
                out[i0] += -(ga0 * gb0 + ch * 0.0)
                out[i0 + one] += -(ga0 * gb1 + ch * -wz)
                out[i0 + two] += -(ga0 * gb2 + ch * wy)
                out[i1] += -(ga1 * gb0 + ch * wz)
                out[i1 + one] += -(ga1 * gb1 + ch * 0.0)
                out[i1 + two] += -(ga1 * gb2 + ch * -wx)
                out[i2] += -(ga2 * gb0 + ch * -wy)
                out[i2 + one] += -(ga2 * gb1 + ch * wx)
                out[i2 + two] += -(ga2 * gb2 + ch * 0.0)



@jit
def _triple_product(ax, ay, az, bx, by, bz, cx, cy, cz):  # pragma: no cover - compiled
    """a . (b x c) without fused multiply-adds: six times a tet's signed volume, the same bits in
    every kernel that tests tets for inversion (:func:`_inverted` and the fused stepper's). On
    nearly flat tets its sign can differ from :func:`softgrasp.model.mesh.tetmesh.signed_volumes`'s,
    which NumPy sums in another order (17 of 200 000 random flat tets)."""
    return ax * (by * cz - bz * cy) + ay * (bz * cx - bx * cz) + az * (bx * cy - by * cx)


@jit
def _inverted(x, tets, lo, hi):  # pragma: no cover - compiled
    """Tets ``lo:hi`` with non-positive signed volume (as :func:`softgrasp.model.mesh.tetmesh.signed_volumes`):
    their number and the first of them (-1 if none); for bodies without the volume term."""
    count = 0
    first = -1
    for t in range(lo, hi):
        p0 = tets[t, 0]
        ax = x[tets[t, 1], 0] - x[p0, 0]
        ay = x[tets[t, 1], 1] - x[p0, 1]
        az = x[tets[t, 1], 2] - x[p0, 2]
        bx = x[tets[t, 2], 0] - x[p0, 0]
        by = x[tets[t, 2], 1] - x[p0, 1]
        bz = x[tets[t, 2], 2] - x[p0, 2]
        cx = x[tets[t, 3], 0] - x[p0, 0]
        cy = x[tets[t, 3], 1] - x[p0, 1]
        cz = x[tets[t, 3], 2] - x[p0, 2]
        det = _triple_product(ax, ay, az, bx, by, bz, cx, cy, cz)
        if not det / 6.0 > 0.0:
            if first < 0:
                first = t
            count += 1
    return count, first


def count_inverted(x: Array, tets: IntArray) -> int:
    """Number of tets whose signed volume at ``x`` is not positive (as
    :func:`softgrasp.model.mesh.tetmesh.signed_volumes` ``<= 0``, or NaN), without forming the volumes."""
    tets = i64(tets)
    return int(_inverted(f64(x), tets, 0, tets.shape[0])[0])



def _tet_volumes(
    x: Array, tets: IntArray, rest_volume: Array, kappa: float, barrier: bool, want_energy: bool, out: Array
) -> float:
    """Volume-term forces of every tet added to ``out``; returns the energy (0 unless wanted)."""
    v0 = f64(rest_volume)
    tets = i64(tets)
    e, _, _ = _volumes(
        x, tets, 1.0 / (6.0 * v0), v0, float(kappa), bool(barrier), want_energy, False, 0, tets.shape[0], out
    )
    return float(e)


def volume_forces(
    x: Array, tets: IntArray, rest_volume: Array, kappa: float, barrier: bool = True
) -> tuple[Array, float]:
    """Forces of the per-tet volume energy ``kappa V0 psi(V / V0)`` on the nodes and its total:
    (forces (N, 3) [N], energy [J]). ``barrier`` selects psi (the module's description)."""
    x = f64(x)
    out = np.zeros_like(x)
    e = _tet_volumes(x, tets, rest_volume, kappa, barrier, True, out)
    return out, float(e)


def volume_jacobian_blocks(
    x: Array, tets: IntArray, rest_volume: Array, kappa: float, barrier: bool = True
) -> Array:
    """The 3x3 blocks of ``d f / d x`` of :func:`volume_forces` at the node pairs of
    :func:`volume_pairs`, (16M, 3, 3): ``-(kappa psi''(J) / V0) g_a g_b^T - kappa psi'(J) d^2V/dx_a dx_b``
    with g_k = dV/dx_k."""
    out = np.zeros(144 * tets.shape[0])
    tets = i64(tets)
    _volume_blocks(
        f64(x),
        tets,
        f64(rest_volume),
        float(kappa),
        bool(barrier),
        NO_POS,
        NO_POS,
        False,
        0,
        out,
        NO_ORDER,
        0,
        tets.shape[0],
    )
    return out.reshape(-1, 3, 3)



def volume_pairs(tets: IntArray) -> tuple[IntArray, IntArray]:
    """Node pairs (rows, cols) of the blocks of :func:`volume_jacobian_blocks`: (t[a], t[b]) for
    a, b = 0..3 of each tet t."""
    return np.repeat(tets, 4, axis=1).ravel(), np.tile(tets, (1, 4)).ravel()


def volume_jacobian(
    x: Array, tets: IntArray, rest_volume: Array, kappa: float, barrier: bool = True
) -> sp.csr_matrix:
    """``d f / d x`` of :func:`volume_forces`, sparse (3N, 3N)."""
    rows, cols = volume_pairs(tets)
    return assemble_blocks(
        x.shape[0], rows, cols, volume_jacobian_blocks(x, tets, rest_volume, kappa, barrier)
    )
