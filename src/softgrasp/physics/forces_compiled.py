"""Compiled (Numba) kernels of the body's forces, energies and Jacobians.

Same signatures and results (to round-off) as the NumPy reference in :mod:`softgrasp.physics.forces`, plus
fused body-level kernels (:func:`internal_forces`, :func:`internal_energy`,
:func:`internal_jacobian_data`) that :class:`softgrasp.physics.body.Body` calls.

The stress-strain law stays a general Python object (:class:`softgrasp.model.material.StressStrainLaw`):
the compiled kernels compute the edge lengths, NumPy evaluates ``law.stress`` / ``law.tangent`` /
``law.energy`` over all edges at once, and compiled kernels turn the tensions into node forces or
Jacobian blocks. The two laws softgrasp defines as polynomials (:class:`~softgrasp.model.material.Linear`,
:class:`~softgrasp.model.material.Polynomial`, exact types only, so a subclass overriding ``stress`` is
never mistaken for one) are evaluated inside the force kernel in one pass.

Kernels are compiled with ``cache=True`` (on-disk cache: only the first run compiles),
``fastmath=False`` (results match the reference to round-off) and ``error_model="numpy"`` (a
division by zero gives inf/nan like NumPy, which the blow-up monitor detects, rather than raising).
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numpy.typing import NDArray

from softgrasp.model.material import Linear, Polynomial, StressStrainLaw

__all__ = [
    "polynomial_coefficients",
    "edge_lengths",
    "spring_forces",
    "spring_jacobian_blocks",
    "volume_forces",
    "volume_jacobian_blocks",
    "edge_damping_forces",
    "internal_forces",
    "internal_energy",
    "internal_jacobian_data",
    "assembly_partition",
    "count_inverted",
    "partitioned_elements",
    "partitioned_forces",
    "PARTITIONED_MIN_NODES",
]

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]

_jit = numba.njit(cache=True, fastmath=False, error_model="numpy")
# The body-force kernels may fuse a * b + c into one FMA instruction ("contract": one rounding instead
# of two, so the forces differ from the NumPy reference's at round-off, 1e-14 relative). It removes a
# third of their floating-point instructions but only ~5 % of their time (measured): their scattered
# loads and read-modify-write stores bound them more. No other fast-math flag: NaN and infinity keep
# their meaning (the blow-up checks rely on them).
_fjit = numba.njit(cache=True, fastmath={"contract"}, error_model="numpy")

#: Barrier floor of J in psi (the same as :func:`softgrasp.physics.forces.psi`).
_J_FLOOR = 1e-12


def polynomial_coefficients(law: StressStrainLaw) -> tuple[float, float] | None:
    """``(a2, a3)`` of ``s = eps + a2 eps^2 + a3 eps^3`` when ``law`` is exactly a
    :class:`~softgrasp.model.material.Linear` or :class:`~softgrasp.model.material.Polynomial`, else None."""
    if type(law) is Linear:
        return 0.0, 0.0
    if type(law) is Polynomial:
        return float(law.a2), float(law.a3)
    return None


# ---------------------------------------------------------------------------------- edges
@_jit
def _edge_lengths(x, edges, out):  # pragma: no cover - compiled
    for e in range(edges.shape[0]):
        i = edges[e, 0]
        j = edges[e, 1]
        dx = x[j, 0] - x[i, 0]
        dy = x[j, 1] - x[i, 1]
        dz = x[j, 2] - x[i, 2]
        out[e] = math.sqrt(dx * dx + dy * dy + dz * dz)


@_fjit
def _springs(
    x, v, edges, rest, inv_rest, kl0, c, a2, a3, damped, want_energy, lo, hi, out
):  # pragma: no cover
    """Spring (+ dashpot) forces of edges ``lo:hi`` added to ``out`` (N, 3); returns their energy (0
    unless ``want_energy``). With ``1 / L0`` and ``k L0`` precomputed: one division and a square
    root per edge; multiply-adds may be fused (round-off)."""
    energy = 0.0
    a2_3 = a2 / 3.0
    a3_4 = 0.25 * a3
    for e in range(np.uint64(lo), np.uint64(hi)):  # unsigned: no negative-index wrap-around per access
        i = np.uint64(edges[e, 0])
        j = np.uint64(edges[e, 1])
        dx = x[j, 0] - x[i, 0]
        dy = x[j, 1] - x[i, 1]
        dz = x[j, 2] - x[i, 2]
        L = math.sqrt(dx * dx + dy * dy + dz * dz)
        inv = 1.0 / L
        eps = L * inv_rest[e] - 1.0
        e2 = eps * eps
        T = kl0[e] * (eps + a2 * e2 + a3 * e2 * eps)
        if want_energy:
            energy += kl0[e] * rest[e] * (0.5 * e2 + a2_3 * e2 * eps + a3_4 * e2 * e2)
        if damped:
            rate = ((v[j, 0] - v[i, 0]) * dx + (v[j, 1] - v[i, 1]) * dy + (v[j, 2] - v[i, 2]) * dz) * inv
            T += c[e] * rate
        s = T * inv
        out[i, 0] += s * dx
        out[i, 1] += s * dy
        out[i, 2] += s * dz
        out[j, 0] -= s * dx
        out[j, 1] -= s * dy
        out[j, 2] -= s * dz
    return energy


@_jit
def _springs_tension(x, v, edges, L, T, c, damped, out):  # pragma: no cover - compiled
    """Forces of edge tensions ``T`` (E,) at lengths ``L`` (+ dashpots), added to ``out``."""
    for e in range(edges.shape[0]):
        i = edges[e, 0]
        j = edges[e, 1]
        dx = x[j, 0] - x[i, 0]
        dy = x[j, 1] - x[i, 1]
        dz = x[j, 2] - x[i, 2]
        inv = 1.0 / L[e]
        t = T[e]
        if damped:
            t += c[e] * ((v[j, 0] - v[i, 0]) * dx + (v[j, 1] - v[i, 1]) * dy + (v[j, 2] - v[i, 2]) * dz) * inv
        s = t * inv
        out[i, 0] += s * dx
        out[i, 1] += s * dy
        out[i, 2] += s * dz
        out[j, 0] -= s * dx
        out[j, 1] -= s * dy
        out[j, 2] -= s * dz


@_jit
def _spring_blocks(
    x, edges, L, T, dT, psd, base, stride, use_pos, offset, out, order, lo, hi
):  # pragma: no cover
    """Add the blocks ``[K, K, -K, -K]`` of each edge (K = d f0 / d x1) to ``out``: entry
    (r, c) of block B = offset + (e, E + e, 2E + e, 3E + e) at ``base[B] + r stride[B] + c``
    (a :class:`softgrasp.physics.forces.BlockPattern`'s CSR data), or at ``9 B + 3 r + c`` when
    ``use_pos`` is false. The edges ``order[lo:hi]`` (``lo:hi`` where ``order`` is empty)."""
    E = edges.shape[0]
    for idx in range(lo, hi):
        e = order[idx] if order.shape[0] else idx
        i = edges[e, 0]
        j = edges[e, 1]
        Le = L[e]
        n0 = (x[j, 0] - x[i, 0]) / Le
        n1 = (x[j, 1] - x[i, 1]) / Le
        n2 = (x[j, 2] - x[i, 2]) / Le
        n = (n0, n1, n2)
        geo = T[e] / Le
        if psd and geo < 0.0:
            geo = 0.0
        a = dT[e] - geo
        for r in range(3):
            for s in range(3):
                val = a * n[r] * n[s]
                if r == s:
                    val += geo
                for q in range(4):
                    sign = 1.0 if q < 2 else -1.0
                    B = np.uint64(offset + q * E + e)  # unsigned: see _volume_blocks
                    if use_pos:
                        pos = np.uint64(base[B]) + np.uint64(r) * np.uint64(stride[B]) + np.uint64(s)
                    else:
                        pos = np.uint64(9) * B + np.uint64(3 * r + s)
                    out[pos] += sign * val


# ---------------------------------------------------------------------------------- tets
@_fjit
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
        if barrier:
            Jc = J if J > _J_FLOOR else _J_FLOOR
            dw = 1.0 - 1.0 / Jc
            if want_energy:
                energy += kappa * v0[t] * (J - 1.0 - math.log(Jc))
        else:
            dw = J - 1.0
            if want_energy:
                energy += kappa * v0[t] * (0.5 * dw * dw)
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


@_jit
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
        J = V / rest[t]
        if barrier:
            Jc = J if J > _J_FLOOR else _J_FLOOR
            dw = 1.0 - 1.0 / Jc
            d2w = 1.0 / (Jc * Jc)
        else:
            dw = J - 1.0
            d2w = 1.0
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


# ---------------------------------------------------------------------------------- wrappers
_NO_POS = np.zeros(1, dtype=np.int64)
_NO_ORDER = np.zeros(0, dtype=np.int64)  # the elements in their own order


def _f64(a: Array) -> Array:
    return np.ascontiguousarray(a, dtype=np.float64)


def _i64(a: IntArray) -> IntArray:
    return np.ascontiguousarray(a, dtype=np.int64)


@_jit
def _triple_product(ax, ay, az, bx, by, bz, cx, cy, cz):  # pragma: no cover - compiled
    """a . (b x c) without fused multiply-adds: six times a tet's signed volume, the same bits in
    every kernel that tests tets for inversion (:func:`_inverted` and the fused stepper's). On
    nearly flat tets its sign can differ from :func:`softgrasp.model.mesh.tetmesh.signed_volumes`'s,
    which NumPy sums in another order (17 of 200 000 random flat tets)."""
    return ax * (by * cz - bz * cy) + ay * (bz * cx - bx * cz) + az * (bx * cy - by * cx)


@_jit
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
    tets = _i64(tets)
    return int(_inverted(_f64(x), tets, 0, tets.shape[0])[0])


def edge_lengths(x: Array, edges: IntArray) -> Array:
    """Current edge lengths [m], (E,)."""
    out = np.empty(edges.shape[0])
    _edge_lengths(_f64(x), _i64(edges), out)
    return out


def _add_springs(
    out: Array,
    x: Array,
    v: Array | None,
    edges: IntArray,
    rest: Array,
    k: Array,
    c: Array | None,
    law: StressStrainLaw,
    want_energy: bool,
) -> float:
    """Spring (+ dashpot when v and c are given) forces added to ``out``; returns the energy
    (0 unless ``want_energy``)."""
    if v is not None and c is not None:
        damped, vv, cc = True, _f64(v), _f64(c)
    else:  # the kernels ignore vv and cc
        damped, vv, cc = False, x, rest
    coef = polynomial_coefficients(law)
    if coef is not None:
        n = edges.shape[0]
        return float(
            _springs(
                x, vv, edges, rest, 1.0 / rest, k * rest, cc, coef[0], coef[1], damped, want_energy, 0, n, out
            )
        )
    L = edge_lengths(x, edges)
    eps = L / rest - 1.0
    T = k * rest * law.stress(eps)
    _springs_tension(x, vv, edges, L, _f64(T), cc, damped, out)
    return float(np.sum(k * rest**2 * law.energy(eps))) if want_energy else 0.0


def spring_forces(
    x: Array, edges: IntArray, rest_length: Array, stiffness: Array, law: StressStrainLaw
) -> tuple[Array, float]:
    """Compiled :func:`softgrasp.physics.forces.spring_forces`: (forces (N, 3) [N], energy [J])."""
    x = _f64(x)
    out = np.zeros_like(x)
    e = _add_springs(out, x, None, _i64(edges), _f64(rest_length), _f64(stiffness), None, law, True)
    return out, e


def edge_damping_forces(x: Array, v: Array, edges: IntArray, damping: Array) -> Array:
    """Compiled :func:`softgrasp.physics.forces.edge_damping_forces`, (N, 3) [N]."""
    x = _f64(x)
    out = np.zeros_like(x)
    E = edges.shape[0]
    _springs_tension(x, _f64(v), _i64(edges), edge_lengths(x, edges), np.zeros(E), _f64(damping), True, out)
    return out


def _tet_volumes(
    x: Array, tets: IntArray, rest_volume: Array, kappa: float, barrier: bool, want_energy: bool, out: Array
) -> float:
    """Volume-term forces of every tet added to ``out``; returns the energy (0 unless wanted)."""
    v0 = _f64(rest_volume)
    tets = _i64(tets)
    e, _, _ = _volumes(
        x, tets, 1.0 / (6.0 * v0), v0, float(kappa), bool(barrier), want_energy, False, 0, tets.shape[0], out
    )
    return float(e)


def volume_forces(
    x: Array, tets: IntArray, rest_volume: Array, kappa: float, barrier: bool = True
) -> tuple[Array, float]:
    """Compiled :func:`softgrasp.physics.forces.volume_forces`: (forces (N, 3) [N], energy [J])."""
    x = _f64(x)
    out = np.zeros_like(x)
    e = _tet_volumes(x, tets, rest_volume, kappa, barrier, True, out)
    return out, float(e)


def _law_tensions(x: Array, edges: IntArray, rest: Array, k: Array, law) -> tuple[Array, Array, Array]:
    """Lengths L, tensions T = k L0 s(eps) and dT/dL = k s'(eps) of the edges, (E,) each."""
    L = edge_lengths(x, edges)
    eps = L / rest - 1.0
    return L, _f64(k * rest * law.stress(eps)), _f64(k * law.tangent(eps))


def spring_jacobian_blocks(
    x: Array,
    edges: IntArray,
    rest_length: Array,
    stiffness: Array,
    law: StressStrainLaw,
    *,
    psd: bool = False,
) -> Array:
    """Compiled :func:`softgrasp.physics.forces.spring_jacobian_blocks`, (4E, 3, 3)."""
    x, edges = _f64(x), _i64(edges)
    L, T, dT = _law_tensions(x, edges, _f64(rest_length), _f64(stiffness), law)
    out = np.zeros(36 * edges.shape[0])
    _spring_blocks(
        x, edges, L, T, dT, bool(psd), _NO_POS, _NO_POS, False, 0, out, _NO_ORDER, 0, edges.shape[0]
    )
    return out.reshape(-1, 3, 3)


def volume_jacobian_blocks(
    x: Array, tets: IntArray, rest_volume: Array, kappa: float, barrier: bool = True
) -> Array:
    """Compiled :func:`softgrasp.physics.forces.volume_jacobian_blocks`, (16M, 3, 3)."""
    out = np.zeros(144 * tets.shape[0])
    tets = _i64(tets)
    _volume_blocks(
        _f64(x),
        tets,
        _f64(rest_volume),
        float(kappa),
        bool(barrier),
        _NO_POS,
        _NO_POS,
        False,
        0,
        out,
        _NO_ORDER,
        0,
        tets.shape[0],
    )
    return out.reshape(-1, 3, 3)


# ---------------------------------------------------------------------------------- body level
def internal_forces(
    x: Array,
    v: Array | None,
    edges: IntArray,
    rest_length: Array,
    stiffness: Array,
    damping: Array | None,
    law: StressStrainLaw,
    tets: IntArray,
    rest_volume: Array,
    kappa: float,
    barrier: bool,
) -> Array:
    """Springs + volume term (if kappa != 0) + edge dashpots (if ``v`` and ``damping`` are given)
    [N], (N, 3): the fused :meth:`softgrasp.physics.body.Body.internal_forces`."""
    x = _f64(x)
    out = np.zeros_like(x)
    _add_springs(out, x, v, _i64(edges), _f64(rest_length), _f64(stiffness), damping, law, False)
    if kappa != 0.0:
        _tet_volumes(x, tets, rest_volume, kappa, barrier, False, out)
    return out


#: Bodies with at least this many nodes sum their forces in :func:`assembly_partition`'s order, its
#: first two groups side by side on Numba's threads (an evaluation of 2-4 ms at 27 749-33 969 nodes;
#: below, the thread hand-off would cost more than it saves): :func:`partitioned_elements`.
PARTITIONED_MIN_NODES = 10_000


def partitioned_elements(
    edges: IntArray,
    rest_length: Array,
    stiffness: Array,
    damping: Array,
    tets: IntArray,
    rest_volume: Array,
    partition: tuple,
) -> tuple:
    """The per-element arrays the force kernels read, in :func:`assembly_partition`'s order
    (``partition``), with its group bounds: (edges, L0, 1 / L0, k L0, c, edge bounds (4,), tets,
    1 / (6 V0), V0, tet bounds (4,)). Made once per body."""
    eo, eb, to, tb = partition
    rest = _f64(rest_length)[eo]
    v0 = _f64(rest_volume)[to]
    return (
        _i64(edges)[eo],
        rest,
        1.0 / rest,
        (_f64(stiffness)[eo] * rest),
        _f64(damping)[eo],
        np.asarray(eb, dtype=np.int64),
        _i64(tets)[to],
        1.0 / (6.0 * v0),
        v0,
        np.asarray(tb, dtype=np.int64),
    )


@numba.njit(cache=True, fastmath={"contract"}, error_model="numpy", parallel=True)
def _partitioned_forces(
    x,
    v,
    edges,
    rest,
    inv_rest,
    kl0,
    c,
    eb,
    tets,
    inv6v0,
    v0,
    tb,
    a2,
    a3,
    damped,
    kappa,
    barrier,
    want_energy,
    out,
):  # pragma: no cover - compiled
    """Springs (+ dashpots) and volume term into ``out``: the first two groups (their elements'
    nodes in disjoint halves: no force entry in common) side by side, then the third; the same sums
    on any number of threads. Returns the energy (0 unless ``want_energy``), the groups' in order."""
    energy = np.zeros(2)
    for g in numba.prange(2):
        e = _springs(x, v, edges, rest, inv_rest, kl0, c, a2, a3, damped, want_energy, eb[g], eb[g + 1], out)
        if kappa != 0.0:
            ev = _volumes(x, tets, inv6v0, v0, kappa, barrier, want_energy, False, tb[g], tb[g + 1], out)
            e += ev[0]
        energy[g] = e
    e = _springs(x, v, edges, rest, inv_rest, kl0, c, a2, a3, damped, want_energy, eb[2], eb[3], out)
    if kappa != 0.0:
        e += _volumes(x, tets, inv6v0, v0, kappa, barrier, want_energy, False, tb[2], tb[3], out)[0]
    return (energy[0] + energy[1]) + e


def partitioned_forces(
    x: Array,
    v: Array | None,
    elements: tuple,
    law: StressStrainLaw,
    kappa: float,
    barrier: bool,
    want_energy: bool = False,
) -> tuple[Array, float] | None:
    """:func:`internal_forces` (and, with ``want_energy``, :func:`internal_energy`) summed in the
    order of ``elements`` (:func:`partitioned_elements`), on the calling thread's Numba threads:
    (forces (N, 3) [N], energy [J] or 0); None for a law that is not a polynomial (the caller then
    takes :func:`internal_forces`)."""
    coef = polynomial_coefficients(law)
    if coef is None:
        return None
    edges, rest, inv_rest, kl0, c, eb, tets, inv6v0, v0, tb = elements
    x = _f64(x)
    damped = v is not None
    out = np.zeros_like(x)
    energy = _partitioned_forces(
        x, _f64(v) if damped else x, edges, rest, inv_rest, kl0, c, eb, tets, inv6v0, v0, tb,
        coef[0], coef[1], damped, float(kappa), bool(barrier), want_energy, out,
    )  # fmt: skip
    return out, float(energy)


def internal_energy(
    x: Array,
    edges: IntArray,
    rest_length: Array,
    stiffness: Array,
    law: StressStrainLaw,
    tets: IntArray,
    rest_volume: Array,
    kappa: float,
    barrier: bool,
) -> float:
    """Elastic energy of springs and volume term [J]."""
    x = _f64(x)
    scratch = np.zeros_like(x)
    e = _add_springs(scratch, x, None, _i64(edges), _f64(rest_length), _f64(stiffness), None, law, True)
    if kappa != 0.0:
        e += _tet_volumes(x, tets, rest_volume, kappa, barrier, True, scratch)
    return e


def assembly_partition(
    edges: IntArray, tets: IntArray, n_nodes: int
) -> tuple[IntArray, IntArray, IntArray, IntArray]:
    """The edges and tets in the order :func:`internal_jacobian_data` sums them: those whose
    nodes all lie in the first half of the node numbers, then those all in the second half (two
    groups that write no Jacobian block in common: one thread each), then the rest.

    Returns
    -------
    (edge order (E,), its group bounds (4,), tet order (M,), its group bounds (4,)).
    """

    def split(elements: IntArray) -> tuple[IntArray, IntArray]:
        half = n_nodes // 2
        low = (elements < half).all(axis=1)
        high = (elements >= half).all(axis=1)
        groups = [np.flatnonzero(low), np.flatnonzero(high), np.flatnonzero(~(low | high))]
        bounds = np.cumsum([0] + [len(g) for g in groups]).astype(np.int64)
        return np.concatenate(groups).astype(np.int64), bounds

    eo, eb = split(np.asarray(edges))
    to, tb = split(np.asarray(tets))
    return eo, eb, to, tb


@_jit
def _jacobian_group(
    x, edges, L, T, dT, tets, rest, kappa, barrier, base, stride, out, eo, eb, to, tb, g
):  # pragma: no cover - compiled
    """The spring then volume-term blocks of :func:`assembly_partition`'s group ``g``."""
    _spring_blocks(x, edges, L, T, dT, False, base, stride, True, 0, out, eo, eb[g], eb[g + 1])
    if kappa != 0.0:
        offset = 4 * edges.shape[0]
        _volume_blocks(x, tets, rest, kappa, barrier, base, stride, True, offset, out, to, tb[g], tb[g + 1])


@numba.njit(cache=True, fastmath=False, error_model="numpy", parallel=True)
def _jacobian_groups(
    x, edges, L, T, dT, tets, rest, kappa, barrier, base, stride, out, eo, eb, to, tb
):  # pragma: no cover - compiled
    """:func:`assembly_partition`'s first two groups side by side (they write no entry in
    common), then the third; the same sums on any number of threads."""
    for g in numba.prange(2):
        _jacobian_group(x, edges, L, T, dT, tets, rest, kappa, barrier, base, stride, out, eo, eb, to, tb, g)
    _jacobian_group(x, edges, L, T, dT, tets, rest, kappa, barrier, base, stride, out, eo, eb, to, tb, 2)


def internal_jacobian_data(
    x: Array,
    edges: IntArray,
    rest_length: Array,
    stiffness: Array,
    law: StressStrainLaw,
    tets: IntArray,
    rest_volume: Array,
    kappa: float,
    barrier: bool,
    block_base: IntArray,
    block_stride: IntArray,
    nnz: int,
    partition: tuple | None = None,
    threads: int = 1,
) -> Array:
    """CSR data (nnz,) of ``d f_internal / d x``: the spring blocks (then the volume term's, if
    kappa != 0) summed straight into the entries of a :class:`softgrasp.physics.forces.BlockPattern`
    built on :func:`softgrasp.physics.forces.spring_pairs` (then :func:`softgrasp.physics.forces.volume_pairs`)
    (its ``block_base`` and ``block_stride``), without forming the blocks; in the order of
    ``partition`` (:func:`assembly_partition`, computed here when None), its first two groups on
    ``threads`` threads (the result does not depend on it)."""
    from softgrasp.linalg.sparse import _Threads

    x, edges, tets = _f64(x), _i64(edges), _i64(tets)
    block_base, block_stride = _i64(block_base), _i64(block_stride)
    if partition is None:
        partition = assembly_partition(edges, tets, x.shape[0])
    data = np.zeros(nnz)
    L, T, dT = _law_tensions(x, edges, _f64(rest_length), _f64(stiffness), law)
    with _Threads(threads):
        _jacobian_groups(
            x,
            edges,
            L,
            T,
            dT,
            tets,
            _f64(rest_volume),
            float(kappa),
            bool(barrier),
            block_base,
            block_stride,
            data,
            *partition,
        )
    return data
