"""The edge springs and dashpots of the mass-spring body: forces, energy and Jacobian.

The tension of edge e is ``T_e = k_e L0_e s(eps_e)`` with ``eps_e = L_e / L0_e - 1`` and s the
material's normalised stress-strain law (so ``T = k (L - L0)`` for the linear law); its energy is
``k L0^2 w(eps)`` with ``w' = s``. An edge dashpot adds ``c_e ((v1 - v0) . n) n``: it acts only on
the stretching rate, so rigid motions (translation and rotation) are undamped. Forces are on the
nodes, (N, 3) [N]; ``d f / d x`` is given as 3x3 node blocks at :func:`spring_pairs`.

The stress-strain law stays a general Python object (:class:`softgrasp.model.material.StressStrainLaw`):
the two laws softgrasp defines as polynomials (:class:`~softgrasp.model.material.Linear`,
:class:`~softgrasp.model.material.Polynomial`, exact types only, so a subclass overriding ``stress`` is
never mistaken for one) are evaluated inside the compiled force kernel in one pass; for any other law
the kernels compute the edge lengths, NumPy evaluates ``law.stress`` / ``law.tangent`` /
``law.energy`` over all edges at once, and compiled kernels turn the tensions into node forces or
Jacobian blocks.
"""

from __future__ import annotations

import math

import numpy as np
import scipy.sparse as sp

from softgrasp.model.material import Linear, Polynomial, StressStrainLaw
from softgrasp.physics.forces import assemble_blocks
from softgrasp.physics.jit import NO_ORDER, NO_POS, Array, IntArray, f64, fjit, i64, jit

__all__ = [
    "polynomial_coefficients",
    "edge_lengths",
    "spring_forces",
    "spring_pairs",
    "spring_jacobian_blocks",
    "spring_jacobian",
    "edge_damping_forces",
    "edge_damping_jacobian",
]


def polynomial_coefficients(law: StressStrainLaw) -> tuple[float, float] | None:
    """``(a2, a3)`` of ``s = eps + a2 eps^2 + a3 eps^3`` when ``law`` is exactly a
    :class:`~softgrasp.model.material.Linear` or :class:`~softgrasp.model.material.Polynomial`, else None."""
    if type(law) is Linear:
        return 0.0, 0.0
    if type(law) is Polynomial:
        return float(law.a2), float(law.a3)
    return None


@jit
def _edge_lengths(x, edges, out):  # pragma: no cover - compiled
    for e in range(edges.shape[0]):
        i = edges[e, 0]
        j = edges[e, 1]
        dx = x[j, 0] - x[i, 0]
        dy = x[j, 1] - x[i, 1]
        dz = x[j, 2] - x[i, 2]
        out[e] = math.sqrt(dx * dx + dy * dy + dz * dz)


@fjit
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


@jit
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


@jit
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



def edge_lengths(x: Array, edges: IntArray) -> Array:
    """Current edge lengths [m], (E,)."""
    out = np.empty(edges.shape[0])
    _edge_lengths(f64(x), i64(edges), out)
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
        damped, vv, cc = True, f64(v), f64(c)
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
    _springs_tension(x, vv, edges, L, f64(T), cc, damped, out)
    return float(np.sum(k * rest**2 * law.energy(eps))) if want_energy else 0.0


def spring_forces(
    x: Array, edges: IntArray, rest_length: Array, stiffness: Array, law: StressStrainLaw
) -> tuple[Array, float]:
    """Non-linear edge spring forces on the nodes and their energy: (forces (N, 3) [N], energy
    [J]), with the tension ``T = k L0 s(L / L0 - 1)`` (the module's description).

    Parameters
    ----------
    x: node positions [m], (N, 3).  edges: (E, 2).  rest_length: (E,) [m].
    stiffness: (E,) [N/m].  law: normalised stress-strain law.
    """
    x = f64(x)
    out = np.zeros_like(x)
    e = _add_springs(out, x, None, i64(edges), f64(rest_length), f64(stiffness), None, law, True)
    return out, e


def edge_damping_forces(x: Array, v: Array, edges: IntArray, damping: Array) -> Array:
    """Dashpots along the edges: ``f0 = c_e ((v1 - v0) . n) n`` on each edge's node 0 and its
    opposite on node 1 [N], (N, 3); rigid motions are undamped."""
    x = f64(x)
    out = np.zeros_like(x)
    E = edges.shape[0]
    _springs_tension(x, f64(v), i64(edges), edge_lengths(x, edges), np.zeros(E), f64(damping), True, out)
    return out


def _law_tensions(x: Array, edges: IntArray, rest: Array, k: Array, law) -> tuple[Array, Array, Array]:
    """Lengths L, tensions T = k L0 s(eps) and dT/dL = k s'(eps) of the edges, (E,) each."""
    L = edge_lengths(x, edges)
    eps = L / rest - 1.0
    return L, f64(k * rest * law.stress(eps)), f64(k * law.tangent(eps))


def spring_jacobian_blocks(
    x: Array,
    edges: IntArray,
    rest_length: Array,
    stiffness: Array,
    law: StressStrainLaw,
    *,
    psd: bool = False,
) -> Array:
    """The 3x3 blocks of :func:`spring_jacobian` at the node pairs of :func:`spring_pairs`,
    (4E, 3, 3). ``psd``: the geometric term of compressed springs dropped (see
    :func:`spring_jacobian`)."""
    x, edges = f64(x), i64(edges)
    L, T, dT = _law_tensions(x, edges, f64(rest_length), f64(stiffness), law)
    out = np.zeros(36 * edges.shape[0])
    _spring_blocks(
        x, edges, L, T, dT, bool(psd), NO_POS, NO_POS, False, 0, out, NO_ORDER, 0, edges.shape[0]
    )
    return out.reshape(-1, 3, 3)


def spring_pairs(edges: IntArray) -> tuple[IntArray, IntArray]:
    """Node pairs (rows, cols) of the blocks of :func:`spring_jacobian_blocks`: for each edge
    (i, j) the blocks (i, j), (j, i), (i, i), (j, j), each group over all edges in turn."""
    i, j = edges[:, 0], edges[:, 1]
    return np.concatenate([i, j, i, j]), np.concatenate([j, i, i, j])


def spring_jacobian(
    x: Array,
    edges: IntArray,
    rest_length: Array,
    stiffness: Array,
    law: StressStrainLaw,
    *,
    psd: bool = False,
) -> sp.csr_matrix:
    """``d f / d x`` of :func:`spring_forces`, sparse (3N, 3N): per edge ``K = T'(L) n n^T +
    (T / L) (I - n n^T)`` (d f0 / d x1) at its four blocks ``[K, K, -K, -K]``.

    With ``psd=True`` the geometric term of compressed springs is dropped, which makes the stiffness
    positive semi-definite (a Newton preconditioner), at the cost of exactness.
    """
    rows, cols = spring_pairs(edges)
    blocks = spring_jacobian_blocks(x, edges, rest_length, stiffness, law, psd=psd)
    return assemble_blocks(x.shape[0], rows, cols, blocks)


def edge_damping_jacobian(x: Array, edges: IntArray, damping: Array) -> sp.csr_matrix:
    """``d f / d v`` of :func:`edge_damping_forces` (the negative damping matrix), (3N, 3N):
    ``c_e n n^T`` at each edge's four blocks."""
    d = x[edges[:, 1]] - x[edges[:, 0]]
    n = d / np.linalg.norm(d, axis=1)[:, None]
    C = np.asarray(damping)[:, None, None] * n[:, :, None] * n[:, None, :]
    rows, cols = spring_pairs(edges)
    return assemble_blocks(x.shape[0], rows, cols, np.concatenate([C, C, -C, -C]))
