"""NumPy reference implementations of the body's force laws, for the tests only.

Vectorised NumPy twins of :mod:`softgrasp.physics.springs`, :mod:`softgrasp.physics.volume` and the
body-level sums of :class:`softgrasp.physics.body.Body`, written independently of the compiled
kernels (edge and tet geometry by array operations, node sums by ``bincount``): the tests compare the
kernels with them to round-off. Nothing in ``src/`` imports this.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from softgrasp.model.material import StressStrainLaw
from softgrasp.physics.body import Body
from softgrasp.physics.forces import assemble_blocks
from softgrasp.physics.springs import spring_pairs
from softgrasp.physics.volume import volume_pairs


def scatter_add(n_nodes: int, index: NDArray[np.int64], values: NDArray[np.float64]) -> NDArray[np.float64]:
    """Sum of the rows of ``values`` (K, 3) at the nodes ``index`` (K,): (n_nodes, 3). The same as
    ``np.add.at`` on zeros, by three ``bincount`` calls (several times faster)."""
    out = np.empty((n_nodes, 3))
    for k in range(3):
        out[:, k] = np.bincount(index, weights=values[:, k], minlength=n_nodes)
    return out


def _edge_pairs_scatter(
    n_nodes: int, edges: NDArray[np.int64], fe: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Node forces of edge forces ``fe`` (E, 3) acting on each edge's node 0, and their opposite on
    node 1."""
    return scatter_add(n_nodes, edges.T.ravel(), np.concatenate([fe, -fe]))


def _edge_geometry(
    x: NDArray[np.float64], edges: NDArray[np.int64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    d = x[edges[:, 1]] - x[edges[:, 0]]
    L = np.linalg.norm(d, axis=1)
    return d / L[:, None], L


def spring_forces(
    x: NDArray[np.float64],
    edges: NDArray[np.int64],
    rest_length: NDArray[np.float64],
    stiffness: NDArray[np.float64],
    law: StressStrainLaw,
) -> tuple[NDArray[np.float64], float]:
    """Non-linear edge spring forces and their energy.

    The tension of edge e is ``T_e = k_e L0_e s(eps_e)`` with ``eps_e = L_e / L0_e - 1`` and s the
    material's normalised stress-strain law, so for a linear law ``T = k (L - L0)``; the energy is
    ``k L0^2 w(eps)`` with ``w' = s``.

    Parameters
    ----------
    x: node positions [m], (N, 3).  edges: (E, 2).  rest_length: (E,) [m].
    stiffness: (E,) [N/m].  law: normalised stress-strain law.

    Returns
    -------
    (forces (N, 3) [N], energy [J])
    """
    n, L = _edge_geometry(x, edges)
    eps = L / rest_length - 1.0
    T = stiffness * rest_length * law.stress(eps)
    fe = T[:, None] * n  # force on node 0 of each edge (pulled toward node 1 under tension)
    f = _edge_pairs_scatter(x.shape[0], edges, fe)
    energy = float(np.sum(stiffness * rest_length**2 * law.energy(eps)))
    return f, energy


def spring_jacobian(
    x: NDArray[np.float64],
    edges: NDArray[np.int64],
    rest_length: NDArray[np.float64],
    stiffness: NDArray[np.float64],
    law: StressStrainLaw,
    *,
    psd: bool = False,
) -> sp.csr_matrix:
    """``d f / d x`` of :func:`spring_forces`, sparse (3N, 3N).

    With ``psd=True`` the geometric term of compressed springs is dropped, which makes the stiffness
    positive semi-definite (a Newton preconditioner), at the cost of exactness.
    """
    rows, cols = spring_pairs(edges)
    blocks = spring_jacobian_blocks(x, edges, rest_length, stiffness, law, psd=psd)
    return assemble_blocks(x.shape[0], rows, cols, blocks)


def spring_jacobian_blocks(
    x: NDArray[np.float64],
    edges: NDArray[np.int64],
    rest_length: NDArray[np.float64],
    stiffness: NDArray[np.float64],
    law: StressStrainLaw,
    *,
    psd: bool = False,
) -> NDArray[np.float64]:
    """The 3x3 blocks of :func:`spring_jacobian` at the node pairs of :func:`spring_pairs`, (4E, 3, 3)."""
    n, L = _edge_geometry(x, edges)
    eps = L / rest_length - 1.0
    T = stiffness * rest_length * law.stress(eps)
    dT = stiffness * law.tangent(eps)
    geo = T / L
    if psd:
        geo = np.maximum(geo, 0.0)
    nn = n[:, :, None] * n[:, None, :]
    K = dT[:, None, None] * nn + geo[:, None, None] * (np.eye(3)[None] - nn)  # d f0 / d x1
    return np.concatenate([K, K, -K, -K])


def psi(J: NDArray[np.float64], barrier: bool) -> tuple[NDArray[np.float64], ...]:
    """Volume energy density psi(J) and its first two derivatives, with psi(1) = psi'(1) = 0 and
    psi''(1) = 1.

    ``barrier=True``: psi = J - 1 - ln J (infinite as J -> 0, resists inversion);
    ``barrier=False``: psi = (J - 1)^2 / 2 (used when kappa < 0, i.e. nu < 1/4).
    """
    if barrier:
        Jc = np.maximum(J, 1e-12)
        return J - 1.0 - np.log(Jc), 1.0 - 1.0 / Jc, 1.0 / Jc**2
    return 0.5 * (J - 1.0) ** 2, J - 1.0, np.ones_like(J)


def _tet_gradients(x: NDArray[np.float64], tets: NDArray[np.int64]) -> tuple[NDArray[np.float64], ...]:
    p = x[tets]
    a1, a2, a3 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]
    g1 = np.cross(a2, a3) / 6.0
    g2 = np.cross(a3, a1) / 6.0
    g3 = np.cross(a1, a2) / 6.0
    g0 = -(g1 + g2 + g3)
    V = np.einsum("ij,ij->i", a1, g1)
    return V, np.stack([g0, g1, g2, g3], axis=1), (a1, a2, a3)


def volume_forces(
    x: NDArray[np.float64],
    tets: NDArray[np.int64],
    rest_volume: NDArray[np.float64],
    kappa: float,
    barrier: bool = True,
) -> tuple[NDArray[np.float64], float]:
    """Forces of the per-tet volume energy ``kappa V0 psi(V / V0)`` and its total [J].

    Under small strain it adds ``kappa (tr eps)^2 / 2`` to the energy density, i.e. kappa to Lame's
    lambda (see :mod:`softgrasp.model.network`).
    """
    V, g, _ = _tet_gradients(x, tets)
    w, dw, _ = psi(V / rest_volume, barrier)
    ft = -(kappa * dw)[:, None, None] * g  # (M, 4, 3)
    f = scatter_add(x.shape[0], tets.ravel(), ft.reshape(-1, 3))
    return f, float(kappa * np.sum(rest_volume * w))


def _skew(a: NDArray[np.float64]) -> NDArray[np.float64]:
    z = np.zeros(a.shape[0])
    return np.stack(
        [
            np.stack([z, -a[:, 2], a[:, 1]], axis=1),
            np.stack([a[:, 2], z, -a[:, 0]], axis=1),
            np.stack([-a[:, 1], a[:, 0], z], axis=1),
        ],
        axis=1,
    )


def volume_jacobian(
    x: NDArray[np.float64],
    tets: NDArray[np.int64],
    rest_volume: NDArray[np.float64],
    kappa: float,
    barrier: bool = True,
) -> sp.csr_matrix:
    """``d f / d x`` of :func:`volume_forces`, sparse (3N, 3N)."""
    rows, cols = volume_pairs(tets)
    return assemble_blocks(
        x.shape[0], rows, cols, volume_jacobian_blocks(x, tets, rest_volume, kappa, barrier)
    )


def volume_jacobian_blocks(
    x: NDArray[np.float64],
    tets: NDArray[np.int64],
    rest_volume: NDArray[np.float64],
    kappa: float,
    barrier: bool = True,
) -> NDArray[np.float64]:
    """The 3x3 blocks of :func:`volume_jacobian` at the node pairs of :func:`volume_pairs`, (16M, 3, 3)."""
    V, g, (a1, a2, a3) = _tet_gradients(x, tets)
    _, dw, d2w = psi(V / rest_volume, barrier)
    # Hessian of V with respect to a1..a3 (node 0 follows from translation invariance).
    H = np.zeros((len(V), 4, 4, 3, 3))
    S1, S2, S3 = _skew(a1) / 6.0, _skew(a2) / 6.0, _skew(a3) / 6.0
    H[:, 1, 2], H[:, 2, 1] = -S3, S3
    H[:, 1, 3], H[:, 3, 1] = S2, -S2
    H[:, 2, 3], H[:, 3, 2] = -S1, S1
    H[:, 0, 1:] = -H[:, 1:, 1:].sum(axis=1)
    H[:, 1:, 0] = -H[:, 1:, 1:].sum(axis=2)
    H[:, 0, 0] = H[:, 1:, 1:].sum(axis=(1, 2))
    gg = g[:, :, None, :, None] * g[:, None, :, None, :]  # (M, 4, 4, 3, 3)
    hess = (kappa * d2w / rest_volume)[:, None, None, None, None] * gg + (kappa * dw)[
        :, None, None, None, None
    ] * H
    return -hess.reshape(-1, 3, 3)


def edge_damping_forces(
    x: NDArray[np.float64], v: NDArray[np.float64], edges: NDArray[np.int64], damping: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Dashpots along the edges: ``f0 = c_e ((v1 - v0) · n) n`` [N], (N, 3).

    They act only on the stretching rate, so rigid motions (translation and rotation) are undamped.
    """
    n, _ = _edge_geometry(x, edges)
    rate = np.einsum("ij,ij->i", v[edges[:, 1]] - v[edges[:, 0]], n)
    fe = (damping * rate)[:, None] * n
    return _edge_pairs_scatter(x.shape[0], edges, fe)


def block_pattern_arrays(
    n_nodes: int, rows: NDArray[np.int64], cols: NDArray[np.int64]
) -> tuple[NDArray[np.int64], NDArray[np.int64], int, NDArray, NDArray]:
    """The CSR layout :class:`softgrasp.physics.forces.BlockPattern` builds, by ``np.unique``:
    (block_base (K,), block_stride (K,), nnz, indptr, indices)."""
    rows = np.asarray(rows, dtype=np.int64)
    cols = np.asarray(cols, dtype=np.int64)
    pairs, inv = np.unique(rows * n_nodes + cols, return_inverse=True)  # by row, then column
    brow, bcol = np.divmod(pairs, n_nodes)
    count = np.bincount(brow, minlength=n_nodes)  # blocks per block row
    start = np.concatenate([[0], np.cumsum(count)])  # first block of each block row
    # Scalar row 3r + a holds 3 * count[r] entries: the blocks of block row r by column, three
    # columns each. Entry (a, b) of unique block u sits at 9 start[r] + 3 a count[r] + 3 (u -
    # start[r]) + b = base[u] + a stride[u] + b.
    u = np.arange(len(brow))
    base = 6 * start[brow] + 3 * u
    stride = 3 * count[brow]
    block_base = base[inv]  # of each input block, (K,)
    block_stride = stride[inv]
    nnz = 9 * len(brow)
    indptr = np.concatenate([[0], np.cumsum(np.repeat(3 * count, 3))]).astype(np.int64)
    a = np.arange(3)[None, :, None]
    b = np.arange(3)[None, None, :]
    cols_per_row = np.empty(nnz, dtype=np.int64)
    cols_per_row[(base[:, None, None] + a * stride[:, None, None] + b).ravel()] = (
        3 * bcol[:, None, None] + b + 0 * a
    ).ravel()
    index = np.int32 if max(nnz, 3 * n_nodes) < np.iinfo(np.int32).max else np.int64
    indptr = indptr.astype(index)
    indices = cols_per_row.astype(index)
    return block_base, block_stride, nnz, indptr, indices


def body_internal_forces(body, x: NDArray[np.float64], v: NDArray[np.float64] | None = None) -> NDArray[np.float64]:
    """:meth:`softgrasp.physics.body.Body.internal_forces` by the NumPy laws."""
    f, _ = spring_forces(x, body.edges, body.rest_length, body.stiffness, body.material.law)
    if body.kappa != 0.0:
        f += volume_forces(x, body.mesh.tets, body.mesh.volumes, body.kappa, body.barrier)[0]
    if v is not None and body.damping_time > 0:
        f += edge_damping_forces(x, v, body.edges, body.damping)
    return f


def body_internal_energy(body, x: NDArray[np.float64]) -> float:
    """:meth:`softgrasp.physics.body.Body.internal_energy` by the NumPy laws."""
    e = spring_forces(x, body.edges, body.rest_length, body.stiffness, body.material.law)[1]
    if body.kappa != 0.0:
        e += volume_forces(x, body.mesh.tets, body.mesh.volumes, body.kappa, body.barrier)[1]
    return e


def body_internal_jacobian(body, x: NDArray[np.float64]) -> sp.csr_matrix:
    """:meth:`softgrasp.physics.body.Body.internal_jacobian` by the NumPy laws, in the body's
    block pattern."""
    blocks = spring_jacobian_blocks(x, body.edges, body.rest_length, body.stiffness, body.material.law)
    if body.kappa != 0.0:
        vb = volume_jacobian_blocks(x, body.mesh.tets, body.mesh.volumes, body.kappa, body.barrier)
        blocks = np.concatenate([blocks, vb])
    return body._jacobian_pattern.assemble(blocks)


class OracleBody(Body):
    """A :class:`softgrasp.physics.body.Body` whose internal forces, energy and Jacobian are the
    NumPy laws of this module."""

    @classmethod
    def of(cls, body: Body) -> OracleBody:
        """The oracle twin of ``body`` (the same fields)."""
        return cls(**{f.name: getattr(body, f.name) for f in dataclasses.fields(body)})

    def internal_forces(self, x, v=None):
        return body_internal_forces(self, x, v)

    def internal_energy(self, x):
        return body_internal_energy(self, x)

    def internal_jacobian(self, x, threads: int = 1):
        return body_internal_jacobian(self, x)
