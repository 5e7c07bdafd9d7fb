"""Compiled sparse kernels on several threads for the multigrid path's Newton solves (systems
beyond PARDISO's size), which apply the stiffness, the multigrid transfer operators, the
residuals and the smoothing sweeps thousands of times a plan: SciPy's products and pyamg's
sweeps run on one core.

Products
--------
Each row's sum is taken by one thread, in an order that does not depend on the thread count:
the products are the same to the bit on one thread or two. They differ from SciPy's by the
rounding of a reordered sum (the loop over a row is vectorised). Indices are read unsigned
(Numba adds a negative-index wrap-around to every signed array access: the one-thread product
was then twice as slow as SciPy's, unsigned the same). Measured on the 83 247-unknown Newton
matrix of the 27 749-node sphere (3.49 M non-zeros): SciPy 2.0 ms, one thread 2.0 ms, two
threads 1.05-1.12 ms.
"""

from __future__ import annotations

import math
from typing import Any

import numba
import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

__all__ = [
    "BLOCK",
    "BlockGaussSeidel",
    "BsrProduct",
    "CsrProduct",
    "HybridBlockGaussSeidel",
    "HybridGaussSeidel",
    "MIN_BLOCK_FILL",
    "NodeBlockProduct",
    "SWEEP_PARTS",
    "block_layout",
    "diagonal",
    "fine_smoother",
    "node_blocks",
    "product",
    "unique_pairs",
]

# The parallel kernels' loop iterations each write their own outputs; none sums across
# iterations (a prange reduction): Numba keeps one partial sum per thread, and TBB, its threading
# layer here, hands chunks to threads dynamically, so such a sum would change from run to run.
_pjit = numba.njit(cache=True, parallel=True, fastmath={"reassoc", "contract"}, error_model="numpy")
# The block kernels' sums run in a fixed order (each row's six accumulators), multiply-adds fused.
_bpjit = numba.njit(cache=True, parallel=True, fastmath={"contract"}, error_model="numpy")
_bjit = numba.njit(cache=True, fastmath={"contract"}, error_model="numpy")


@_pjit
def _csr_matvec(indptr, indices, data, x, out):  # pragma: no cover - compiled
    """out = A x for A in CSR arrays (``indptr`` and ``indices`` unsigned)."""
    for i in numba.prange(out.shape[0]):
        s = 0.0
        for k in range(indptr[i], indptr[i + 1]):
            s += data[k] * x[indices[k]]
        out[i] = s


@numba.njit(cache=True, parallel=True, error_model="numpy")
def _csr_diagonal(indptr, indices, data, out):  # pragma: no cover - compiled
    """out[i] = the sum of row i's entries in column i (CSR arrays, ``indptr`` and ``indices``
    unsigned, the indices in any order)."""
    for i in numba.prange(out.shape[0]):
        s = 0.0
        col = np.uint64(i)
        for k in range(indptr[i], indptr[i + 1]):
            if indices[k] == col:
                s += data[k]
        out[i] = s


@numba.njit(cache=True, parallel=True, error_model="numpy")
def _bsr33_diagonal(indptr, indices, data, out):  # pragma: no cover - compiled
    """out = the diagonal of a matrix of 3 x 3 blocks (BSR arrays, one block a column at most)."""
    for i in numba.prange(indptr.shape[0] - 1):
        out[3 * i] = out[3 * i + 1] = out[3 * i + 2] = 0.0
        row = np.uint64(i)
        for k in range(indptr[i], indptr[i + 1]):
            if indices[k] == row:
                out[3 * i] = data[k, 0, 0]
                out[3 * i + 1] = data[k, 1, 1]
                out[3 * i + 2] = data[k, 2, 2]


def diagonal(A: sp.csr_matrix | sp.csr_array) -> NDArray[np.float64]:
    """The main diagonal of a square CSR matrix, as SciPy's ``A.diagonal()`` (duplicates summed),
    on Numba's threads: 0.6 against 4.9 ms for the 83 247-unknown Newton matrix of the 27 749-node
    sphere."""
    if A.format != "csr" or A.shape[0] != A.shape[1]:
        return np.asarray(A.diagonal(), dtype=np.float64)
    out = np.empty(A.shape[0])
    _csr_diagonal(
        _unsigned(A.indptr), _unsigned(A.indices), np.ascontiguousarray(A.data, dtype=np.float64), out
    )
    return out


def _unsigned(a: NDArray[np.integer]) -> NDArray[np.unsignedinteger]:
    """``a`` (non-negative) read as unsigned integers of its width: a view, no copy."""
    return a.view(np.uint32 if a.dtype.itemsize == 4 else np.uint64)


class CsrProduct:
    """Products ``A @ x`` of one sparse matrix with vectors, on ``threads`` threads (at most
    Numba's; the attribute may be changed between products: the products are the same to the
    bit). A CSR matrix's float64 arrays are read, not copied (it must not change while this is
    used); other formats are converted once."""

    def __init__(self, A: sp.spmatrix | sp.sparray, threads: int = 1) -> None:
        A = A.tocsr()
        self.A = A
        self.shape: tuple[int, int] = A.shape
        self.threads = threads
        self._indptr = _unsigned(A.indptr)
        self._indices = _unsigned(A.indices)
        self._data = np.ascontiguousarray(A.data, dtype=np.float64)

    def __matmul__(self, x: NDArray[np.float64]) -> NDArray[np.float64]:
        return _apply(self, _csr_matvec, x)

    matvec = __matmul__


def _apply(op: Any, kernel: Any, x: NDArray[np.float64]) -> NDArray[np.float64]:
    """``op``'s product with ``x`` by the compiled ``kernel`` on its arrays and threads."""
    if np.shape(x) != (op.shape[1],):
        raise ValueError(f"a {op.shape} matrix times a vector of shape {np.shape(x)}")
    out = np.empty(op.shape[0])
    with _Threads(op.threads):
        kernel(op._indptr, op._indices, op._data, np.ascontiguousarray(x, dtype=np.float64), out)
    return out


def _sweep_rhs(shape: tuple[int, int], x: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    """``b`` for a sweep updating ``x`` in place on a ``shape`` matrix: checked, contiguous float64,
    copied where it shares ``x``'s memory."""
    if x.shape != (shape[0],) or np.shape(b) != x.shape:
        raise ValueError(f"a sweep on {shape} needs x and b of length {shape[0]}")
    if x.dtype != np.float64 or not x.flags.c_contiguous:
        raise ValueError("a sweep updates x in place: it must be a contiguous float64 array")
    b = np.ascontiguousarray(b, dtype=np.float64)
    return b.copy() if np.shares_memory(b, x) else b


class _Threads:
    """Numba's thread count set to ``n`` (at most Numba's pool) for the ``with`` block."""

    def __init__(self, n: int) -> None:
        self.n = max(1, min(int(n), numba.config.NUMBA_NUM_THREADS))

    def __enter__(self) -> None:
        self.previous = numba.get_num_threads()
        if self.previous != self.n:
            numba.set_num_threads(self.n)

    def __exit__(self, *exc: object) -> None:
        if self.previous != self.n:
            numba.set_num_threads(self.previous)


# Smoothing sweeps
# ----------------
#: Row blocks of a hybrid Gauss-Seidel sweep, whatever the thread count: a sweep's result does
#: not depend on how many threads run it.
SWEEP_PARTS = 2
#: A matrix with more of its entries coupling the row blocks is swept as one block (Gauss-Seidel
#: itself, on one thread): its unknowns are not numbered for locality, and the l1 term would
#: weaken the sweeps (the BCC ``box(0.05, 14)`` as meshed, 21 885 unknowns, 64 % of its entries
#: across the split: 22 -> 32 iterations to 1e-8; renumbered for locality, 3.6 %: 18 -> 20).
MAX_CROSS_FRACTION = 0.1


@_pjit
def _l1_inverse_diagonal(indptr, indices, data, parts, out, cross):  # pragma: no cover - compiled
    """out[i] = 1 / (a_ii + sum of |a_ij| over the columns j outside row i's block), 0 where
    that is not positive (the row is then left alone); cross[p]: the entries of block p's rows
    outside the block."""
    n = out.shape[0]
    for p in numba.prange(parts):
        lo = np.uint64(p * n // parts)
        hi = np.uint64((p + 1) * n // parts)
        count = 0
        for i in range(lo, hi):
            d = 0.0
            off = 0.0
            for k in range(np.uint64(indptr[i]), np.uint64(indptr[i + np.uint64(1)])):
                j = np.uint64(indices[k])
                if j == i:
                    d += data[k]
                elif j < lo or j >= hi:
                    off += abs(data[k])
                    count += 1
            out[i] = 1.0 / (d + off) if d + off > 0.0 else 0.0
        cross[p] = count


@numba.njit(cache=True, parallel=True, error_model="numpy")
def _hybrid_sweep(indptr, indices, data, dinv, x, b, x_old, parts, forward):  # pragma: no cover
    """One hybrid Gauss-Seidel sweep on ``x`` (in place): row blocks side by side, Gauss-Seidel
    within a block (forward or backward), the other blocks' unknowns as ``x_old`` holds them."""
    n = x.shape[0]
    one = np.uint64(1)
    for p in numba.prange(parts):
        lo = np.uint64(p * n // parts)
        hi = np.uint64((p + 1) * n // parts)
        i = lo if forward else hi - one
        for _ in range(hi - lo):
            s = b[i]
            k0 = np.uint64(indptr[i])
            nk = np.uint64(indptr[i + one]) - k0
            for kk in range(nk):
                k = k0 + kk if forward else k0 + nk - one - kk  # one direction: prefetched
                j = np.uint64(indices[k])
                if j >= lo and j < hi:
                    s -= data[k] * x[j]
                else:
                    s -= data[k] * x_old[j]
            x[i] += s * dinv[i]
            if forward:
                i += one
            else:
                i -= one


def _l1_parts(op: Any, kernel: Any, parts: int | None, entries: int) -> int:
    """Fill ``op.inverse_diagonal`` by ``kernel`` (the l1 inverse diagonal, rows or node blocks) for
    ``parts`` parts, or for None :data:`SWEEP_PARTS`, or 1 where more than
    :data:`MAX_CROSS_FRACTION` of the ``entries`` (as the kernel counts them) would couple them;
    returns the parts used."""
    n = SWEEP_PARTS if parts is None else max(1, int(parts))
    cross = np.zeros(n, dtype=np.int64)
    with _Threads(op.threads):
        kernel(op._indptr, op._indices, op._data, n, op.inverse_diagonal, cross)
        if parts is None and cross.sum() > MAX_CROSS_FRACTION * max(entries, 1):
            n = 1
            kernel(op._indptr, op._indices, op._data, n, op.inverse_diagonal, cross[:1])
    return n


def _hybrid(op: Any, kernel: Any, x: NDArray[np.float64], b: NDArray[np.float64], forward: bool) -> None:
    """One hybrid sweep of ``op`` (its l1 inverse diagonal and parts) on ``x`` by ``kernel``."""
    with _Threads(op.threads):
        kernel(
            op._indptr,
            op._indices,
            op._data,
            op.inverse_diagonal,
            x,
            b,
            x.copy() if op.parts > 1 else x,  # one part reads no other part's values
            op.parts,
            forward,
        )


class HybridGaussSeidel(CsrProduct):
    """l1 hybrid Gauss-Seidel sweeps on a CSR matrix A (and, as a :class:`CsrProduct`, its
    products) (Baker, Falgout, Kolev and Yang, "Multigrid
    smoothers for ultraparallel computing", SIAM J. Sci. Comput. 33, 2011): the rows split in
    :data:`SWEEP_PARTS` blocks swept side by side, each block's own unknowns updated as
    Gauss-Seidel does, the others' taken as they were before the sweep, and each row's diagonal
    increased by the absolute values of its couplings to other blocks. Without that increase the
    sweep need not converge (the iteration's M + M^T - A is the diagonal minus the couplings
    between blocks; measured on the 27 749-node sphere's Newton matrix: 122 iterations to 1e-4
    instead of 20); with it M + M^T - A is positive definite for symmetric positive definite A.
    A forward sweep followed by a backward one is symmetric, as a conjugate-gradient
    preconditioner must be.

    A matrix whose unknowns are not numbered for locality (more than :data:`MAX_CROSS_FRACTION` of
    its entries across the split) is swept as one block: Gauss-Seidel, on one thread.

    83 247 unknowns (3.49 M non-zeros, the sphere's mesh numbered for locality: 2.9 % of the
    entries across the split), one sweep: pyamg's Gauss-Seidel 2.7 ms; this one 2.5 ms on one
    thread, 1.3-1.8 ms on two; the multigrid-preconditioned solves took 0-1 more iterations than
    with Gauss-Seidel (21 against 20, 10 against 9 to 1e-4)."""

    def __init__(self, A: sp.spmatrix | sp.sparray, threads: int = 1, parts: int | None = None) -> None:
        """``parts``: the row blocks; None: :data:`SWEEP_PARTS`, or 1 where more than
        :data:`MAX_CROSS_FRACTION` of the entries would couple them."""
        super().__init__(A, threads)
        self.inverse_diagonal = np.empty(self.A.shape[0])
        self.parts = _l1_parts(self, _l1_inverse_diagonal, parts, self.A.nnz)

    def sweep(self, x: NDArray[np.float64], b: NDArray[np.float64], forward: bool) -> None:
        """One sweep on ``x`` (float64, contiguous; updated in place) for ``A x = b``."""
        _hybrid(self, _hybrid_sweep, x, _sweep_rhs(self.shape, x, b), forward)

    def diagonal(self) -> NDArray[np.float64]:
        """The matrix's diagonal (:func:`diagonal`)."""
        return diagonal(self.A)


# Block kernels
# -------------
# The coarse levels of the smoothed-aggregation hierarchy (rigid-body modes: six unknowns an
# aggregate) are BSR matrices of 6 x 6 blocks, and its transfers from and to the finest level
# 1 x 6 and 6 x 1 blocks. Written for those block shapes (the six accumulators of a block row in
# registers, the loops over a block unrolled by the compiler), their products and sweeps take
# half to a third of the time of the same arithmetic with the block size read at run time
# (pyamg's block Gauss-Seidel) or on the matrix as CSR.
#: The block size of the block kernels (the rigid-body modes of a 3D body).
BLOCK = 6


@_bjit
def _store6(out, o, s0, s1, s2, s3, s4, s5):  # pragma: no cover - compiled
    """out[o:o + 6] = s0..s5 (``o`` unsigned)."""
    out[o] = s0
    out[o + np.uint64(1)] = s1
    out[o + np.uint64(2)] = s2
    out[o + np.uint64(3)] = s3
    out[o + np.uint64(4)] = s4
    out[o + np.uint64(5)] = s5


@_bpjit
def _bsr66_matvec(indptr, indices, data, x, out):  # pragma: no cover - compiled
    """out = A x for A in BSR arrays of 6 x 6 blocks (``indptr`` and ``indices`` unsigned)."""
    six = np.uint64(6)
    for ii in numba.prange(indptr.shape[0] - 1):
        i = np.uint64(ii)
        s0 = s1 = s2 = s3 = s4 = s5 = 0.0
        for k in range(np.uint64(indptr[i]), np.uint64(indptr[i + np.uint64(1)])):
            q = six * np.uint64(indices[k])
            for c in range(6):
                xc = x[q + np.uint64(c)]
                s0 += data[k, 0, c] * xc
                s1 += data[k, 1, c] * xc
                s2 += data[k, 2, c] * xc
                s3 += data[k, 3, c] * xc
                s4 += data[k, 4, c] * xc
                s5 += data[k, 5, c] * xc
        _store6(out, six * i, s0, s1, s2, s3, s4, s5)


@_bpjit
def _bsr61_matvec(indptr, indices, data, x, out):  # pragma: no cover - compiled
    """out = A x for A in BSR arrays of 6 x 1 blocks (a restriction to six unknowns a node)."""
    six = np.uint64(6)
    for ii in numba.prange(indptr.shape[0] - 1):
        i = np.uint64(ii)
        s0 = s1 = s2 = s3 = s4 = s5 = 0.0
        for k in range(np.uint64(indptr[i]), np.uint64(indptr[i + np.uint64(1)])):
            xc = x[np.uint64(indices[k])]
            s0 += data[k, 0, 0] * xc
            s1 += data[k, 1, 0] * xc
            s2 += data[k, 2, 0] * xc
            s3 += data[k, 3, 0] * xc
            s4 += data[k, 4, 0] * xc
            s5 += data[k, 5, 0] * xc
        _store6(out, six * i, s0, s1, s2, s3, s4, s5)


@_bpjit
def _bsr16_matvec(indptr, indices, data, x, out):  # pragma: no cover - compiled
    """out = A x for A in BSR arrays of 1 x 6 blocks (a prolongation from six unknowns a node)."""
    six = np.uint64(6)
    for ii in numba.prange(indptr.shape[0] - 1):
        i = np.uint64(ii)
        s = 0.0
        for k in range(np.uint64(indptr[i]), np.uint64(indptr[i + np.uint64(1)])):
            q = six * np.uint64(indices[k])
            for c in range(6):
                s += data[k, 0, c] * x[q + np.uint64(c)]
        out[i] = s


_BSR_KERNELS = {(6, 6): _bsr66_matvec, (6, 1): _bsr61_matvec, (1, 6): _bsr16_matvec}


class BsrProduct:
    """Products ``A @ x`` of a BSR matrix of 6 x 6, 6 x 1 or 1 x 6 blocks (:func:`product` picks
    it for those) with vectors, on ``threads`` threads: each block row's sums by one thread in a
    fixed order, the same to the bit on any thread count (and to the rounding of a reordered sum
    of SciPy's). The matrix's arrays are read, not copied where they are already contiguous
    float64."""

    def __init__(self, A: sp.bsr_matrix | sp.bsr_array, threads: int = 1) -> None:
        if not sp.issparse(A) or A.format != "bsr" or tuple(A.blocksize) not in _BSR_KERNELS:
            raise ValueError(f"a block product needs a BSR matrix of blocks {sorted(_BSR_KERNELS)}")
        self.A = A
        self.shape: tuple[int, int] = A.shape
        self.threads = threads
        self._kernel = _BSR_KERNELS[tuple(A.blocksize)]
        self._indptr = _unsigned(A.indptr)
        self._indices = _unsigned(A.indices)
        self._data = np.ascontiguousarray(A.data, dtype=np.float64)

    def __matmul__(self, x: NDArray[np.float64]) -> NDArray[np.float64]:
        return _apply(self, self._kernel, x)

    matvec = __matmul__


def product(A: sp.spmatrix | sp.sparray, threads: int = 1) -> CsrProduct | BsrProduct:
    """The compiled product of ``A``: by blocks for a BSR matrix of the block kernels' shapes
    (:class:`BsrProduct`), else as CSR (:class:`CsrProduct`)."""
    if sp.issparse(A) and A.format == "bsr" and tuple(A.blocksize) in _BSR_KERNELS:
        return BsrProduct(A, threads)
    return CsrProduct(A, threads)


@_bjit
def _block_sweep(indptr, indices, data, dinv, x, b, forward):  # pragma: no cover - compiled
    """One block Gauss-Seidel sweep on ``x`` (in place) for A of 6 x 6 blocks: each block row's
    unknowns x_i = D_i^-1 (b_i - sum of A_ij x_j over the other blocks j), ``dinv`` holding the
    D_i^-1, the rows in order (``forward``) or in reverse."""
    nb = indptr.shape[0] - 1
    six = np.uint64(6)
    for step in range(nb):
        i = np.uint64(step if forward else nb - 1 - step)
        o = six * i
        s0 = b[o]
        s1 = b[o + np.uint64(1)]
        s2 = b[o + np.uint64(2)]
        s3 = b[o + np.uint64(3)]
        s4 = b[o + np.uint64(4)]
        s5 = b[o + np.uint64(5)]
        k0 = np.uint64(indptr[i])
        nk = np.uint64(indptr[i + np.uint64(1)]) - k0
        for kk in range(nk):
            k = k0 + kk if forward else k0 + nk - np.uint64(1) - kk  # one direction: prefetched
            j = np.uint64(indices[k])
            if j == i:
                continue
            q = six * j
            for c in range(6):
                xc = x[q + np.uint64(c)]
                s0 -= data[k, 0, c] * xc
                s1 -= data[k, 1, c] * xc
                s2 -= data[k, 2, c] * xc
                s3 -= data[k, 3, c] * xc
                s4 -= data[k, 4, c] * xc
                s5 -= data[k, 5, c] * xc
        for r in range(6):
            x[o + np.uint64(r)] = (
                dinv[i, r, 0] * s0
                + dinv[i, r, 1] * s1
                + dinv[i, r, 2] * s2
                + dinv[i, r, 3] * s3
                + dinv[i, r, 4] * s4
                + dinv[i, r, 5] * s5
            )


class BlockGaussSeidel(BsrProduct):
    """Block Gauss-Seidel sweeps on a BSR matrix of 6 x 6 blocks (a coarse level of the
    smoothed-aggregation hierarchy), and, as a :class:`BsrProduct`, its products: pyamg's
    ``block_gauss_seidel`` to round-off, the diagonal blocks' inverses the same (pyamg's
    ``get_block_diag``), in half the time (the 27 749-node sphere's second level, 9 270 unknowns
    and 2.51 M non-zeros: 0.84 against 1.8-2.4 ms a sweep). The sweep itself is sequential (one
    thread); the products run on ``threads``."""

    def __init__(self, A: sp.bsr_matrix | sp.bsr_array, threads: int = 1) -> None:
        if not sp.issparse(A) or A.format != "bsr" or tuple(A.blocksize) != (BLOCK, BLOCK):
            raise ValueError(f"block Gauss-Seidel needs a BSR matrix of {BLOCK} x {BLOCK} blocks")
        if not A.has_canonical_format:  # one diagonal block a row, as the sweep reads it
            A = A.copy()
            A.sum_duplicates()
        super().__init__(A, threads)
        from pyamg.util.utils import get_block_diag

        self.inverse_diagonal = np.ascontiguousarray(
            get_block_diag(A, blocksize=BLOCK, inv_flag=True), dtype=np.float64
        )

    def invert_rows(self, rows: NDArray[np.integer]) -> None:
        """Recompute the diagonal blocks' inverses of the block ``rows`` from the matrix's
        current values (after they were changed in place; pseudo-inverses, as pyamg's)."""
        rows = np.unique(np.asarray(rows, dtype=np.intp))
        if rows.size == 0:
            return
        A = self.A
        blocks = np.zeros((rows.size, BLOCK, BLOCK))
        for k, r in enumerate(rows):
            lo, hi = A.indptr[r], A.indptr[r + 1]
            at = np.flatnonzero(A.indices[lo:hi] == r)
            if at.size:
                blocks[k] = A.data[lo + at[0]]
        self.inverse_diagonal[rows] = np.linalg.pinv(blocks)

    def sweep(self, x: NDArray[np.float64], b: NDArray[np.float64], forward: bool) -> None:
        """One sweep on ``x`` (float64, contiguous; updated in place) for ``A x = b``."""
        b = _sweep_rhs(self.shape, x, b)
        _block_sweep(self._indptr, self._indices, self._data, self.inverse_diagonal, x, b, forward)


# Node blocks of the finest level
# -------------------------------
# A body's Newton matrix couples nodes by 3 x 3 blocks. Read as blocks (one index for nine values,
# three accumulators a row), its products and sweeps move a third less memory and take about half
# the instructions (the 27 749-node sphere's Newton matrix, 3.49 M non-zeros, on two threads:
# product 1.65 -> 0.81 ms, sweep 1.78 -> 1.01 ms).
#: The least fraction of the node blocks' entries a matrix must store to be swept by blocks (the
#: zeros stored in its blocks cost memory traffic). A body's Newton matrix assembled in its
#: pattern stores all of them; one that went through SciPy's sums loses its exact zeros (the
#: BCC test cubes' axis-aligned springs: 0.76-0.81 of the entries left).
MIN_BLOCK_FILL = 0.75


@_bjit
def _block_row_merge(indptr, indices, data, i, bindices, bdata, start, write):  # pragma: no cover
    """The 3 x 3 blocks of block row ``i`` of a CSR matrix (rows sorted by column): the union of
    its three rows' column blocks in order, written from ``start`` where ``write``; their
    count."""
    three = np.uint64(3)
    one = np.uint64(1)
    p0 = np.uint64(indptr[three * i])
    e0 = np.uint64(indptr[three * i + one])
    p1 = e0
    e1 = np.uint64(indptr[three * i + np.uint64(2)])
    p2 = e1
    e2 = np.uint64(indptr[three * i + three])
    big = np.uint64(0xFFFFFFFFFFFFFFFF)
    count = np.uint64(0)
    while p0 < e0 or p1 < e1 or p2 < e2:
        m = big
        if p0 < e0:
            m = min(m, np.uint64(indices[p0]) // three)
        if p1 < e1:
            m = min(m, np.uint64(indices[p1]) // three)
        if p2 < e2:
            m = min(m, np.uint64(indices[p2]) // three)
        k = start + count
        if write:
            bindices[k] = m
            for r in range(3):
                for c in range(3):
                    bdata[k, r, c] = 0.0
        while p0 < e0 and np.uint64(indices[p0]) // three == m:
            if write:
                bdata[k, 0, np.uint64(indices[p0]) % three] += data[p0]
            p0 += one
        while p1 < e1 and np.uint64(indices[p1]) // three == m:
            if write:
                bdata[k, 1, np.uint64(indices[p1]) % three] += data[p1]
            p1 += one
        while p2 < e2 and np.uint64(indices[p2]) // three == m:
            if write:
                bdata[k, 2, np.uint64(indices[p2]) % three] += data[p2]
            p2 += one
        count += one
    return count


@_bpjit
def _block_counts(indptr, indices, counts):  # pragma: no cover - compiled
    """The number of 3 x 3 blocks of each block row of a CSR matrix (rows sorted by column)."""
    nodata = np.empty(0)
    noblocks = np.empty((0, 3, 3))
    none = np.empty(0, dtype=np.uint64)
    for ii in numba.prange(counts.shape[0]):
        counts[ii] = _block_row_merge(
            indptr, indices, nodata, np.uint64(ii), none, noblocks, np.uint64(0), False
        )


@_bpjit
def _block_fill(indptr, indices, data, bindptr, bindices, bdata):  # pragma: no cover - compiled
    """The 3 x 3 blocks of a CSR matrix (rows sorted by column) into BSR arrays, ``bindptr``
    given."""
    for ii in numba.prange(bindptr.shape[0] - 1):
        i = np.uint64(ii)
        _block_row_merge(indptr, indices, data, i, bindices, bdata, np.uint64(bindptr[i]), True)


@_bpjit
def _bsr33_matvec(indptr, indices, data, x, out):  # pragma: no cover - compiled
    """out = A x for A in BSR arrays of 3 x 3 blocks (``indptr`` and ``indices`` unsigned)."""
    three = np.uint64(3)
    for ii in numba.prange(indptr.shape[0] - 1):
        i = np.uint64(ii)
        s0 = s1 = s2 = 0.0
        for k in range(np.uint64(indptr[i]), np.uint64(indptr[i + np.uint64(1)])):
            q = three * np.uint64(indices[k])
            x0 = x[q]
            x1 = x[q + np.uint64(1)]
            x2 = x[q + np.uint64(2)]
            s0 += data[k, 0, 0] * x0 + data[k, 0, 1] * x1 + data[k, 0, 2] * x2
            s1 += data[k, 1, 0] * x0 + data[k, 1, 1] * x1 + data[k, 1, 2] * x2
            s2 += data[k, 2, 0] * x0 + data[k, 2, 1] * x1 + data[k, 2, 2] * x2
        o = three * i
        out[o] = s0
        out[o + np.uint64(1)] = s1
        out[o + np.uint64(2)] = s2


@_bpjit
def _l1_block_inverse(indptr, indices, data, parts, out, cross):  # pragma: no cover - compiled
    """out[i] = (D_i + L_i)^-1 for each 3 x 3 block row i: D_i its diagonal block, L_i the
    diagonal of its rows' sums of |a_kl| over the blocks outside block row i's part; zero where
    that is not positive definite (the rows are then left alone, as the row-wise sweep leaves a
    row whose l1 diagonal is not positive). cross[p]: the entries of part p's rows in
    blocks outside the part."""
    nb = out.shape[0]
    for p in numba.prange(parts):
        lo = np.uint64(p * nb // parts)
        hi = np.uint64((p + 1) * nb // parts)
        count = 0
        for i in range(lo, hi):
            d = np.zeros((3, 3))
            for k in range(np.uint64(indptr[i]), np.uint64(indptr[i + np.uint64(1)])):
                j = np.uint64(indices[k])
                if j == i:
                    for r in range(3):
                        for c in range(3):
                            d[r, c] += data[k, r, c]
                elif j < lo or j >= hi:
                    count += 9
                    for r in range(3):
                        d[r, r] += abs(data[k, r, 0]) + abs(data[k, r, 1]) + abs(data[k, r, 2])
            c00 = d[1, 1] * d[2, 2] - d[1, 2] * d[2, 1]
            c01 = d[1, 2] * d[2, 0] - d[1, 0] * d[2, 2]
            c02 = d[1, 0] * d[2, 1] - d[1, 1] * d[2, 0]
            det = d[0, 0] * c00 + d[0, 1] * c01 + d[0, 2] * c02
            # Positive pivots (a positive definite block, as the row-wise sweep needs a positive
            # diagonal), else the node is left alone.
            minor = d[0, 0] * d[1, 1] - d[0, 1] * d[1, 0]
            spd = d[0, 0] > 0.0 and minor > 0.0 and det > 1e-14 * d[0, 0] * d[1, 1] * d[2, 2]
            if not spd or not math.isfinite(det):
                for r in range(3):
                    for c in range(3):
                        out[i, r, c] = 0.0
                continue
            inv = 1.0 / det
            out[i, 0, 0] = c00 * inv
            out[i, 1, 0] = c01 * inv
            out[i, 2, 0] = c02 * inv
            out[i, 0, 1] = (d[0, 2] * d[2, 1] - d[0, 1] * d[2, 2]) * inv
            out[i, 1, 1] = (d[0, 0] * d[2, 2] - d[0, 2] * d[2, 0]) * inv
            out[i, 2, 1] = (d[0, 1] * d[2, 0] - d[0, 0] * d[2, 1]) * inv
            out[i, 0, 2] = (d[0, 1] * d[1, 2] - d[0, 2] * d[1, 1]) * inv
            out[i, 1, 2] = (d[0, 2] * d[1, 0] - d[0, 0] * d[1, 2]) * inv
            out[i, 2, 2] = (d[0, 0] * d[1, 1] - d[0, 1] * d[1, 0]) * inv
        cross[p] = count


@_bpjit
def _hybrid_block_sweep(indptr, indices, data, dinv, x, b, x_old, parts, forward):  # pragma: no cover
    """One hybrid block Gauss-Seidel sweep on ``x`` (in place), 3 x 3 blocks: block rows split in
    ``parts`` side by side, each block row's unknowns x_i += dinv_i (b_i - sum_j A_ij x_j) in
    order within a part (forward or backward), the other parts' unknowns as ``x_old`` holds
    them."""
    nb = indptr.shape[0] - 1
    one = np.uint64(1)
    three = np.uint64(3)
    for p in numba.prange(parts):
        lo = np.uint64(p * nb // parts)
        hi = np.uint64((p + 1) * nb // parts)
        i = lo if forward else hi - one
        for _ in range(hi - lo):
            o = three * i
            s0 = b[o]
            s1 = b[o + one]
            s2 = b[o + np.uint64(2)]
            k0 = np.uint64(indptr[i])
            nk = np.uint64(indptr[i + one]) - k0
            for kk in range(nk):
                # Backward sweeps read the row's blocks backward too: memory read in one
                # direction throughout is what the hardware prefetches (forward order in a
                # backward sweep took 4x as long).
                k = k0 + kk if forward else k0 + nk - one - kk
                j = np.uint64(indices[k])
                q = three * j
                if j >= lo and j < hi:
                    x0 = x[q]
                    x1 = x[q + one]
                    x2 = x[q + np.uint64(2)]
                else:
                    x0 = x_old[q]
                    x1 = x_old[q + one]
                    x2 = x_old[q + np.uint64(2)]
                s0 -= data[k, 0, 0] * x0 + data[k, 0, 1] * x1 + data[k, 0, 2] * x2
                s1 -= data[k, 1, 0] * x0 + data[k, 1, 1] * x1 + data[k, 1, 2] * x2
                s2 -= data[k, 2, 0] * x0 + data[k, 2, 1] * x1 + data[k, 2, 2] * x2
            x[o] += dinv[i, 0, 0] * s0 + dinv[i, 0, 1] * s1 + dinv[i, 0, 2] * s2
            x[o + one] += dinv[i, 1, 0] * s0 + dinv[i, 1, 1] * s1 + dinv[i, 1, 2] * s2
            x[o + np.uint64(2)] += dinv[i, 2, 0] * s0 + dinv[i, 2, 1] * s1 + dinv[i, 2, 2] * s2
            if forward:
                i += one
            else:
                i -= one


class NodeBlockProduct:
    """Products ``A @ x`` of a square CSR matrix read by its 3 x 3 node blocks (``blocks``:
    :func:`node_blocks`'s of ``A``), on ``threads`` threads (the same to the bit on any number)."""

    def __init__(self, A: sp.spmatrix | sp.sparray, blocks: tuple, threads: int = 1) -> None:
        self.A = A
        self.shape: tuple[int, int] = A.shape
        self.threads = threads
        self._indptr, self._indices, self._data = blocks

    def __matmul__(self, x: NDArray[np.float64]) -> NDArray[np.float64]:
        return _apply(self, _bsr33_matvec, x)

    matvec = __matmul__


class HybridBlockGaussSeidel(NodeBlockProduct):
    """l1 hybrid Gauss-Seidel sweeps by 3 x 3 node blocks on a body's Newton matrix (CSR of full
    3 x 3 blocks, :func:`node_blocks`), and its products: :class:`HybridGaussSeidel` with each
    node's three unknowns updated together (x_i += (D_i + L_i)^-1 (b_i - (A x)_i), D_i the node's
    diagonal block, L_i the l1 diagonal of its couplings to the other part's nodes), the block
    Gauss-Seidel smoothing of elasticity's multigrid. The same to the bit on one thread or two."""

    def __init__(
        self, A: sp.spmatrix | sp.sparray, blocks: tuple, threads: int = 1, parts: int | None = None
    ) -> None:
        """``blocks``: :func:`node_blocks`'s of ``A``; ``parts`` as :class:`HybridGaussSeidel`'s."""
        super().__init__(A, blocks, threads)
        self.inverse_diagonal = np.empty((self._indptr.shape[0] - 1, 3, 3))
        # Entries counted nine a block, as the block kernel counts its couplings.
        self.parts = _l1_parts(self, _l1_block_inverse, parts, 9 * self._indices.shape[0])

    def sweep(self, x: NDArray[np.float64], b: NDArray[np.float64], forward: bool) -> None:
        """One sweep on ``x`` (float64, contiguous; updated in place) for ``A x = b``."""
        _hybrid(self, _hybrid_block_sweep, x, _sweep_rhs(self.shape, x, b), forward)

    def diagonal(self) -> NDArray[np.float64]:
        """The matrix's diagonal, from its node blocks (a tenth of the indices to scan that the
        rows have: 0.3 against 3 ms on the 27 749-node sphere's Newton matrix)."""
        out = np.empty(self.shape[0])
        _bsr33_diagonal(self._indptr, self._indices, self._data, out)
        return out


def node_blocks(A: sp.spmatrix | sp.sparray, min_fill: float = 0.0) -> tuple | None:
    """The 3 x 3 node blocks of a square CSR matrix ``A`` (of 3 n unknowns) as BSR arrays
    ``(indptr, indices, data)``: unsigned indices, data (blocks, 3, 3), a block wherever one of its
    nine entries is stored (the others zero), each block row's blocks in column order (SciPy's
    ``tobsr`` of sorted indices); None where ``A`` is not such a matrix or stores less than
    ``min_fill`` of its blocks' entries."""
    if not sp.issparse(A) or A.format != "csr" or A.shape[0] != A.shape[1] or A.shape[0] % 3:
        return None
    if not A.has_canonical_format:
        A = A.copy()
        A.sum_duplicates()  # sorts the indices too
    indptr, indices = _unsigned(A.indptr), _unsigned(A.indices)
    counts = np.empty(A.shape[0] // 3, dtype=np.uint64)
    _block_counts(indptr, indices, counts)
    bindptr = np.zeros(counts.shape[0] + 1, dtype=np.uint64)
    np.cumsum(counts, out=bindptr[1:])
    if A.nnz < min_fill * 9 * int(bindptr[-1]):
        return None
    bindices = np.empty(int(bindptr[-1]), dtype=indices.dtype)
    bdata = np.empty((bindices.shape[0], 3, 3))
    _block_fill(indptr, indices, np.ascontiguousarray(A.data, dtype=np.float64), bindptr, bindices, bdata)
    return bindptr, bindices, bdata


def fine_smoother(
    A: sp.spmatrix | sp.sparray, threads: int = 1
) -> HybridBlockGaussSeidel | HybridGaussSeidel:
    """The finest level's sweeps and products of a Newton matrix ``A``: by node blocks
    (:class:`HybridBlockGaussSeidel`) where its stored entries fill at least :data:`MIN_BLOCK_FILL`
    of its blocks, else by rows."""
    A = A.tocsr()
    blocks = node_blocks(A, MIN_BLOCK_FILL)
    if blocks is None:
        return HybridGaussSeidel(A, threads)
    return HybridBlockGaussSeidel(A, blocks, threads)


@numba.njit(cache=True, error_model="numpy")
def _unique_pairs(rows, cols, n):  # pragma: no cover - compiled
    """:func:`unique_pairs` by a counting sort on the rows and, within a row, a mark per column."""
    K = rows.shape[0]
    start = np.zeros(n + 1, dtype=np.int64)
    for k in range(K):
        start[rows[k] + 1] += 1
    widest = 0
    for r in range(n):
        widest = max(widest, start[r + 1])
        start[r + 1] += start[r]
    order = np.empty(K, dtype=np.int64)
    fill = start[:-1].copy()
    for k in range(K):
        order[fill[rows[k]]] = k
        fill[rows[k]] += 1
    mark = np.full(n, -1, dtype=np.int64)
    slot = np.empty(n, dtype=np.int64)
    urow = np.empty(K, dtype=np.int64)
    ucol = np.empty(K, dtype=np.int64)
    inv = np.empty(K, dtype=np.int64)
    seen = np.empty(widest, dtype=np.int64)
    nu = 0
    for r in range(n):
        m = 0
        for p in range(start[r], start[r + 1]):
            c = cols[order[p]]
            if mark[c] != r:
                mark[c] = r
                seen[m] = c
                m += 1
        row = np.sort(seen[:m])
        for q in range(m):
            slot[row[q]] = nu + q
            urow[nu + q] = r
            ucol[nu + q] = row[q]
        for p in range(start[r], start[r + 1]):
            k = order[p]
            inv[k] = slot[cols[k]]
        nu += m
    return urow[:nu].copy(), ucol[:nu].copy(), inv


@numba.njit(cache=True, error_model="numpy")
def _block_layout(
    brow, bcol, inv, n, block_base, block_stride, indptr, indices
):  # pragma: no cover - compiled
    """:func:`block_layout` into the given arrays."""
    U = brow.shape[0]
    start = np.zeros(n + 1, dtype=np.int64)
    for u in range(U):
        start[brow[u] + 1] += 1
    for r in range(n):
        start[r + 1] += start[r]
    base = np.empty(U, dtype=np.int64)
    stride = np.empty(U, dtype=np.int64)
    for u in range(U):
        r = brow[u]
        base[u] = 6 * start[r] + 3 * u
        stride[u] = 3 * (start[r + 1] - start[r])
    for k in range(inv.shape[0]):
        block_base[k] = base[inv[k]]
        block_stride[k] = stride[inv[k]]
    indptr[0] = 0
    for r in range(n):
        count = start[r + 1] - start[r]
        for a in range(3):
            indptr[3 * r + a + 1] = 9 * start[r] + 3 * (a + 1) * count
    for u in range(U):
        c = 3 * bcol[u]
        for a in range(3):
            q = base[u] + a * stride[u]
            for b in range(3):
                indices[q + b] = c + b


def block_layout(
    brow: NDArray[np.int64], bcol: NDArray[np.int64], inv: NDArray[np.int64], n: int, index_dtype: type
) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray, NDArray]:
    """The CSR layout of a (3n, 3n) matrix of 3 x 3 blocks at the distinct node pairs ``(brow,
    bcol)`` (sorted by row, then column: :func:`unique_pairs`), each input block ``k`` being pair
    ``inv[k]``: (data position of each input block's entry (0, 0), its row stride in the data,
    indptr, indices), the index arrays of type ``index_dtype``. Block row r's blocks fill scalar
    rows 3r .. 3r + 2 by column, three entries each: entry (a, b) of distinct block u at
    ``9 start[r] + 3 a count[r] + 3 (u - start[r]) + b``. The arrays
    :class:`softgrasp.physics.forces.BlockPattern` builds with NumPy, to the element, without its
    temporaries (0.4 s a body of 32 543 nodes in a fresh process)."""
    brow = np.ascontiguousarray(brow, dtype=np.int64)
    bcol = np.ascontiguousarray(bcol, dtype=np.int64)
    inv = np.ascontiguousarray(inv, dtype=np.int64)
    U = brow.shape[0]
    if bcol.shape != brow.shape or (U and (brow[0] < 0 or brow[-1] >= n or np.any(np.diff(brow) < 0))):
        raise ValueError("block rows must be sorted and lie in 0 .. n - 1, one column each")
    if U and (bcol.min() < 0 or bcol.max() >= n):
        raise ValueError("block columns must lie in 0 .. n - 1")
    if inv.size and (inv.min() < 0 or inv.max() >= U):
        raise ValueError("every input block must name one of the distinct pairs")
    block_base = np.empty(inv.shape[0], dtype=np.int64)
    block_stride = np.empty(inv.shape[0], dtype=np.int64)
    indptr = np.empty(3 * n + 1, dtype=index_dtype)
    indices = np.empty(9 * U, dtype=index_dtype)
    _block_layout(brow, bcol, inv, int(n), block_base, block_stride, indptr, indices)
    return block_base, block_stride, indptr, indices


def unique_pairs(
    rows: NDArray[np.int64], cols: NDArray[np.int64], n: int
) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]]:
    """The distinct pairs ``(rows[k], cols[k])`` (both in ``0 .. n - 1``) sorted by row, then
    column, and the index of each input pair among them: ``np.unique(rows * n + cols,
    return_inverse=True)`` in linear time (no sort of all the pairs: a body's Jacobian pattern, 3.1 M
    node pairs at 33 969 nodes)."""
    rows = np.ascontiguousarray(rows, dtype=np.int64)
    cols = np.ascontiguousarray(cols, dtype=np.int64)
    if rows.shape != cols.shape or rows.ndim != 1:
        raise ValueError("rows and cols must be equal-length 1-D arrays")
    if rows.size and (min(rows.min(), cols.min()) < 0 or max(rows.max(), cols.max()) >= n):
        raise ValueError(f"node pairs must lie in 0 .. {n - 1}")
    return _unique_pairs(rows, cols, int(n))
