"""The node-averaged volume term: the body's volume energy on each node's share of its tets.

The per-tet volume term (:mod:`softgrasp.physics.volume`) asks every linear tet to keep its own
volume. A mesh has several tets per node (3.6 on the default sphere), so near incompressibility
those constraints outnumber what the nodes can follow and the body *locks*: it is stiffer than
the material under any load that is not uniform, the more so the nearer nu is to 1/2. Squeezed
2 mm between two 8 mm fingertips, the rubber sphere (nu = 0.45) gives 1.19-1.31 times Hertz's
force on meshes of 388 to 4 498 nodes; at nu = 0.3 the same meshes come within 3 % of it on the
two finer ones.

Here the volume is counted per node instead (Bonet and Burton's average nodal pressure tet): each
tet gives a quarter of its volume to each of its nodes, and the energy is

    sum over nodes n of  kappa V0_n psi(J_n),    J_n = V_n / V0_n,   V_n = sum_{t ∋ n} V_t / 4,

with psi and kappa as in :mod:`softgrasp.physics.volume`. One constraint per node instead of one
per tet: the body no longer locks. Under a uniform deformation every J_n equals every tet's J,
so the energy, forces and stiffness are the per-tet term's and the network's calibration to E
and nu (:mod:`softgrasp.model.network`) holds unchanged.

The force on node k is ``-sum_t p_t dV_t / dx_k`` with the tet's pressure
``p_t = kappa mean_{n ∈ t} psi'(J_n)``. Its derivative couples every two nodes that share a
neighbour (the pair's blocks lie in the node's *star*, the nodes of its tets):

    d f / d x = -sum_n (kappa psi''(J_n) / V0_n) g_n g_n^T - sum_t p_t d^2 V_t / d x^2,

``g_n = dV_n / dx`` (a quarter of the tets' volume gradients, summed over the tets of n). Its
sparsity (:func:`star_pairs`) has about four times the blocks of the per-tet term's.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from softgrasp.physics.jit import Array, IntArray, f64, i64, jit
from softgrasp.physics.volume import psi, psi_derivatives

__all__ = ["NodalVolume", "star_pairs"]


def _other_nodes() -> IntArray:
    """(4, 4, 2): for local nodes a != b, the other two (c, d) ordered so that (a, b, c, d) is an
    even permutation of (0, 1, 2, 3)."""
    out = np.zeros((4, 4, 2), dtype=np.int64)
    for a in range(4):
        for b in range(4):
            if a == b:
                continue
            c, d = (m for m in range(4) if m not in (a, b))
            perm = (a, b, c, d)
            inversions = sum(perm[i] > perm[j] for i in range(4) for j in range(i + 1, 4))
            out[a, b] = (c, d) if inversions % 2 == 0 else (d, c)
    return out


_OTHER = _other_nodes()


def _node_tets(tets: IntArray, n_nodes: int) -> tuple[IntArray, IntArray]:
    """The tets of each node as CSR (indptr (N + 1,), tet indices)."""
    owner = np.repeat(np.arange(len(tets), dtype=np.int64), 4)
    node = tets.ravel()
    order = np.argsort(node, kind="stable")
    indptr = np.zeros(n_nodes + 1, dtype=np.int64)
    np.cumsum(np.bincount(node, minlength=n_nodes), out=indptr[1:])
    return indptr, owner[order]


def _stars(tets: IntArray, n_nodes: int) -> sp.csr_matrix:
    """Each node's star, the nodes that share a tet with it (itself included), as the rows of a
    CSR pattern (N, N) with sorted indices."""
    inc = sp.csr_matrix(
        (np.ones(tets.size), (tets.ravel(), np.repeat(np.arange(len(tets)), 4))), shape=(n_nodes, len(tets))
    )
    star = (inc @ inc.T).tocsr()
    star.sort_indices()
    return star


def star_pairs(tets: IntArray, n_nodes: int) -> tuple[IntArray, IntArray]:
    """Node pairs (rows, cols) of the blocks of the nodal volume term's Jacobian: every (a, b)
    with a and b in the star of one node (both share a tet with it), each pair once."""
    star = _stars(tets, n_nodes)
    ring = (star @ star).tocoo()
    return ring.row.astype(np.int64), ring.col.astype(np.int64)


@jit
def _gradients(x, tets, t, g):  # pragma: no cover - compiled
    """Fill ``g`` (4, 3) with dV/dx of the tet ``t``'s nodes; returns its signed volume V."""
    n0 = tets[t, 0]
    a1x = x[tets[t, 1], 0] - x[n0, 0]
    a1y = x[tets[t, 1], 1] - x[n0, 1]
    a1z = x[tets[t, 1], 2] - x[n0, 2]
    a2x = x[tets[t, 2], 0] - x[n0, 0]
    a2y = x[tets[t, 2], 1] - x[n0, 1]
    a2z = x[tets[t, 2], 2] - x[n0, 2]
    a3x = x[tets[t, 3], 0] - x[n0, 0]
    a3y = x[tets[t, 3], 1] - x[n0, 1]
    a3z = x[tets[t, 3], 2] - x[n0, 2]
    g[1, 0] = (a2y * a3z - a2z * a3y) / 6.0
    g[1, 1] = (a2z * a3x - a2x * a3z) / 6.0
    g[1, 2] = (a2x * a3y - a2y * a3x) / 6.0
    g[2, 0] = (a3y * a1z - a3z * a1y) / 6.0
    g[2, 1] = (a3z * a1x - a3x * a1z) / 6.0
    g[2, 2] = (a3x * a1y - a3y * a1x) / 6.0
    g[3, 0] = (a1y * a2z - a1z * a2y) / 6.0
    g[3, 1] = (a1z * a2x - a1x * a2z) / 6.0
    g[3, 2] = (a1x * a2y - a1y * a2x) / 6.0
    for d in range(3):
        g[0, d] = -(g[1, d] + g[2, d] + g[3, d])
    return a1x * g[1, 0] + a1y * g[1, 1] + a1z * g[1, 2]


@jit
def _node_volumes(x, tets, n_nodes):  # pragma: no cover - compiled
    """V_n = sum of V_t / 4 over the tets of each node [m^3], (N,)."""
    out = np.zeros(n_nodes)
    g = np.empty((4, 3))
    for t in range(tets.shape[0]):
        q = 0.25 * _gradients(x, tets, t, g)
        for a in range(4):
            out[tets[t, a]] += q
    return out


@jit
def _forces(x, tets, v0n, kappa, barrier, out):  # pragma: no cover - compiled
    """Add the nodal volume term's forces to ``out`` (N, 3); returns its energy [J]."""
    n = v0n.shape[0]
    vn = _node_volumes(x, tets, n)
    dpsi = np.empty(n)
    energy = 0.0
    for k in range(n):
        J = vn[k] / v0n[k]
        energy += kappa * v0n[k] * psi(J, barrier)
        dpsi[k], _ = psi_derivatives(J, barrier)
    g = np.empty((4, 3))
    for t in range(tets.shape[0]):
        _gradients(x, tets, t, g)
        pt = 0.25 * kappa * (dpsi[tets[t, 0]] + dpsi[tets[t, 1]] + dpsi[tets[t, 2]] + dpsi[tets[t, 3]])
        for a in range(4):
            for d in range(3):
                out[tets[t, a], d] -= pt * g[a, d]
    return energy


def _block_positions(
    indptr: IntArray, indices: IntArray, rows: IntArray, cols: IntArray
) -> tuple[IntArray, IntArray]:
    """(first CSR entry, row stride) of the 3x3 blocks (rows, cols) of a CSR matrix of 3x3 blocks
    whose pattern holds them."""
    n3 = len(indptr) - 1
    row_of = np.repeat(np.arange(n3, dtype=np.int64), np.diff(indptr))
    keys = row_of * n3 + indices  # sorted: CSR rows in order, columns sorted within each
    r3 = 3 * rows.astype(np.int64)
    base = np.searchsorted(keys, r3 * n3 + 3 * cols.astype(np.int64))
    return base, (indptr[r3 + 1] - indptr[r3]).astype(np.int64)


@jit
def _jacobian(
    x, tets, v0n, kappa, barrier, ntp, nts, slot, star_ptr, pair_ptr, pair_base, star_stride, tet_base,
    tet_stride, out,
):  # pragma: no cover  # fmt: skip
    """Add the blocks of d f / d x (module docstring) to the CSR data ``out``: the star pairs'
    blocks at ``pair_base`` (row strides ``star_stride`` of each star member), each tet's 16 at
    ``tet_base``/``tet_stride`` (:meth:`NodalVolume._layout`)."""
    n = v0n.shape[0]
    m_tets = tets.shape[0]
    grads = np.empty((m_tets, 4, 3))
    vn = np.zeros(n)
    g = np.empty((4, 3))
    for t in range(m_tets):
        q = 0.25 * _gradients(x, tets, t, g)
        for a in range(4):
            vn[tets[t, a]] += q
            for d in range(3):
                grads[t, a, d] = g[a, d]
    dpsi = np.empty(n)
    w = np.empty(n)
    for k in range(n):
        dp, d2p = psi_derivatives(vn[k] / v0n[k], barrier)
        dpsi[k] = dp
        w[k] = kappa * d2p / v0n[k]
    # sum_t p_t d^2 V_t: d g_a / d x_b = skew(s) / 6 with s = x_c - x_d for (a, b, c, d) an even
    # permutation of the tet's nodes (zero for a = b)
    for t in range(m_tets):
        h = -0.25 * kappa * (dpsi[tets[t, 0]] + dpsi[tets[t, 1]] + dpsi[tets[t, 2]] + dpsi[tets[t, 3]]) / 6.0
        for a in range(4):
            for b in range(4):
                if a == b:
                    continue
                c = _OTHER[a, b, 0]
                d = _OTHER[a, b, 1]
                sx = x[tets[t, c], 0] - x[tets[t, d], 0]
                sy = x[tets[t, c], 1] - x[tets[t, d], 1]
                sz = x[tets[t, c], 2] - x[tets[t, d], 2]
                i0 = tet_base[t, 4 * a + b]
                st = tet_stride[t, 4 * a + b]
                # skew(s) = [[0, -sz, sy], [sz, 0, -sx], [-sy, sx, 0]]
                out[i0 + 1] += h * -sz
                out[i0 + 2] += h * sy
                out[i0 + st] += h * sz
                out[i0 + st + 2] += h * -sx
                out[i0 + 2 * st] += h * -sy
                out[i0 + 2 * st + 1] += h * sx
    # sum_n w_n g_n g_n^T over each node's star: g_n in the star's slots, then its outer product
    gn = np.zeros((64, 3))
    for k in range(n):
        m = star_ptr[k + 1] - star_ptr[k]
        if m > gn.shape[0]:
            gn = np.zeros((m, 3))
        for i in range(m):
            gn[i, 0] = 0.0
            gn[i, 1] = 0.0
            gn[i, 2] = 0.0
        for q in range(ntp[k], ntp[k + 1]):
            t = nts[q]
            for a in range(4):
                sl = slot[4 * q + a]
                for d in range(3):
                    gn[sl, d] += 0.25 * grads[t, a, d]
        wk = -w[k]
        p = pair_ptr[k]
        for i in range(m):
            st = star_stride[star_ptr[k] + i]
            for j in range(m):
                i0 = pair_base[p]
                p += 1
                for r in range(3):
                    c0 = wk * gn[i, r]
                    for s2 in range(3):
                        out[i0 + r * st + s2] += c0 * gn[j, s2]
    return out


@jit
def _difference_product(x, tets, v0t, v0n, kappa, barrier, v, out):  # pragma: no cover - compiled
    """Add (J_tet - J) v to ``out`` (N, 3) without assembling either matrix: J the nodal term's
    d f / d x (module docstring), J_tet the per-tet term's at the same positions (rest tet
    volumes ``v0t``; :mod:`softgrasp.physics.volume`). On node a of tet t both are
    ``-c g_a + h sum_b s_ab x v_b`` (s_ab x v_b = 6 (d g_a / d x_b) v_b): the per-tet term's with
    ``c = (kappa psi''(J_t) / V0_t) g_t . v``, ``h = -kappa psi'(J_t) / 6``; the nodal term's with
    the means over the tet's nodes of ``(kappa psi''(J_n) / V0_n) g_n . v`` and of
    ``-kappa psi'(J_n) / 6``."""
    n = v0n.shape[0]
    m_tets = tets.shape[0]
    grads = np.empty((m_tets, 4, 3))
    vt = np.empty(m_tets)
    dvt = np.empty(m_tets)
    vn = np.zeros(n)
    dvn = np.zeros(n)  # g_n . v
    g = np.empty((4, 3))
    for t in range(m_tets):
        vt[t] = _gradients(x, tets, t, g)
        dv = 0.0
        for a in range(4):
            k = tets[t, a]
            for d in range(3):
                grads[t, a, d] = g[a, d]
                dv += g[a, d] * v[k, d]
        dvt[t] = dv
        for a in range(4):
            vn[tets[t, a]] += 0.25 * vt[t]
            dvn[tets[t, a]] += 0.25 * dv
    dpsi = np.empty(n)
    for k in range(n):
        dp, d2p = psi_derivatives(vn[k] / v0n[k], barrier)
        dpsi[k] = dp
        dvn[k] *= kappa * d2p / v0n[k]  # now w_n g_n . v
    for t in range(m_tets):
        n0, n1, n2, n3 = tets[t, 0], tets[t, 1], tets[t, 2], tets[t, 3]
        dpt, d2pt = psi_derivatives(vt[t] / v0t[t], barrier)
        c = kappa * d2pt / v0t[t] * dvt[t] - 0.25 * (dvn[n0] + dvn[n1] + dvn[n2] + dvn[n3])
        h = -kappa * (dpt - 0.25 * (dpsi[n0] + dpsi[n1] + dpsi[n2] + dpsi[n3])) / 6.0
        for a in range(4):
            ka = tets[t, a]
            for d in range(3):
                out[ka, d] -= c * grads[t, a, d]
            for b in range(4):
                if a == b:
                    continue
                kc = tets[t, _OTHER[a, b, 0]]
                kd = tets[t, _OTHER[a, b, 1]]
                kb = tets[t, b]
                sx = x[kc, 0] - x[kd, 0]
                sy = x[kc, 1] - x[kd, 1]
                sz = x[kc, 2] - x[kd, 2]
                out[ka, 0] += h * (sy * v[kb, 2] - sz * v[kb, 1])
                out[ka, 1] += h * (sz * v[kb, 0] - sx * v[kb, 2])
                out[ka, 2] += h * (sx * v[kb, 1] - sy * v[kb, 0])
    return out


class NodalVolume:
    """The node-averaged volume term of one mesh (module docstring).

    Parameters
    ----------
    tets: (M, 4) node indices.  rest_volume: (M,) rest volumes [m^3].  n_nodes: N.
    kappa: the volume modulus [Pa].  barrier: psi with the inversion barrier (kappa >= 0).
    """

    def __init__(self, tets: IntArray, rest_volume: Array, n_nodes: int, kappa: float, barrier: bool) -> None:
        self.tets = i64(tets)
        self.n_nodes = int(n_nodes)
        self.kappa = float(kappa)
        self.barrier = bool(barrier)
        self.rest_volume = f64(rest_volume)
        self.rest_node_volume = np.bincount(
            self.tets.ravel(), weights=np.repeat(f64(rest_volume) / 4.0, 4), minlength=self.n_nodes
        )
        self._ntp, self._nts = _node_tets(self.tets, self.n_nodes)
        self._layouts: dict[tuple[int, int, int], tuple] = {}

    def node_volumes(self, x: Array) -> Array:
        """V_n [m^3], (N,)."""
        return _node_volumes(f64(x), self.tets, self.n_nodes)

    def forces(self, x: Array, out: Array) -> float:
        """Add the term's forces [N] to ``out`` (N, 3); returns its energy [J]."""
        return float(_forces(f64(x), self.tets, self.rest_node_volume, self.kappa, self.barrier, out))

    def _layout(self, indptr: IntArray, indices: IntArray) -> tuple:
        """Where the Jacobian's blocks go in the CSR pattern (``indptr``, ``indices``), worked out
        once per pattern: each node's star (its members sorted), the star slot of each node of
        each of its tets, the CSR position of every star pair's block and of every tet's 16."""
        key = (id(indptr), id(indices), len(indices))
        if key in self._layouts:
            return self._layouts[key]
        n, tets = self.n_nodes, self.tets
        star = _stars(tets, n)
        star_ptr, members = star.indptr.astype(np.int64), star.indices.astype(np.int64)
        # the star slot of node tets[nts[q], a] in the star of the node whose tet list holds q
        owner = np.repeat(np.arange(n, dtype=np.int64), np.diff(self._ntp))
        node = tets[self._nts].reshape(-1)
        star_keys = np.repeat(np.arange(n, dtype=np.int64), np.diff(star_ptr)) * n + members
        slot = np.searchsorted(star_keys, np.repeat(owner, 4) * n + node) - np.repeat(star_ptr[owner], 4)
        m = np.diff(star_ptr)
        pair_ptr = np.zeros(n + 1, dtype=np.int64)
        np.cumsum(m * m, out=pair_ptr[1:])
        of = np.repeat(np.arange(n, dtype=np.int64), m * m)
        local = np.arange(pair_ptr[-1], dtype=np.int64) - pair_ptr[of]
        rows = members[star_ptr[of] + local // m[of]]
        cols = members[star_ptr[of] + local % m[of]]
        indptr, indices = i64(indptr), i64(indices)
        pair_base, _ = _block_positions(indptr, indices, rows, cols)
        _, star_stride = _block_positions(indptr, indices, members, members)
        tr = np.repeat(tets, 4, axis=1)
        tc = np.tile(tets, (1, 4))
        tet_base, tet_stride = _block_positions(indptr, indices, tr.ravel(), tc.ravel())
        layout = (
            slot, star_ptr, pair_ptr, pair_base, star_stride,
            tet_base.reshape(-1, 16), tet_stride.reshape(-1, 16),
        )  # fmt: skip
        self._layouts = {key: layout}  # one pattern per body
        return layout

    def add_jacobian(self, x: Array, indptr: IntArray, indices: IntArray, data: Array) -> None:
        """Add d f / d x to the CSR ``data`` of a (3N, 3N) pattern (``indptr``, ``indices``, the
        body's: the same arrays every call) that holds the 3x3 blocks of every pair of
        :func:`star_pairs`."""
        _jacobian(
            f64(x), self.tets, self.rest_node_volume, self.kappa, self.barrier, self._ntp, self._nts,
            *self._layout(indptr, indices), data,
        )  # fmt: skip

    def add_difference(self, x: Array, v: Array, out: Array) -> None:
        """Add (J_tet - J) v [N] to ``out`` (N, 3) for a displacement ``v`` (N, 3) [m]: what turns
        a product with the per-tet term's d f / d x into one with this term's, neither assembled
        (:func:`_difference_product`)."""
        _difference_product(
            f64(x), self.tets, self.rest_volume, self.rest_node_volume, self.kappa, self.barrier, f64(v), out
        )
