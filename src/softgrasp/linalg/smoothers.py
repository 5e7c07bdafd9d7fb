"""Smoothing sweeps of the multigrid V-cycle, compiled: hybrid Gauss-Seidel on the finest level (by
rows or by 3 x 3 node blocks, on several threads, the same to the bit on any number), block
Gauss-Seidel on the coarse levels' 6 x 6 blocks. Each class is also its matrix's product
(:mod:`softgrasp.linalg.sparse`).
"""

from __future__ import annotations

import math
from typing import Any

import numba
import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from softgrasp import jitcache
from softgrasp.linalg.sparse import (
    BLOCK,
    MIN_BLOCK_FILL,
    BsrProduct,
    CsrProduct,
    NodeBlockProduct,
    _bsr33_diagonal,
    _Threads,
    diagonal,
    node_blocks,
)

__all__ = [
    "SWEEP_PARTS",
    "BlockGaussSeidel",
    "HybridBlockGaussSeidel",
    "HybridGaussSeidel",
    "fine_smoother",
]

# The parallel kernels' loop iterations each write their own outputs; none sums across
# iterations (a prange reduction): Numba keeps one partial sum per thread, and TBB, its threading
# layer here, hands chunks to threads dynamically, so such a sum would change from run to run.
_pjit = jitcache.jit(parallel=True, fastmath={"reassoc", "contract"}, error_model="numpy")
# The block kernels' sums run in a fixed order (each row's six accumulators), multiply-adds fused.
_bpjit = jitcache.jit(parallel=True, fastmath={"contract"}, error_model="numpy")
_bjit = jitcache.jit(fastmath={"contract"}, error_model="numpy")


def _sweep_rhs(shape: tuple[int, int], x: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    """``b`` for a sweep updating ``x`` in place on a ``shape`` matrix: checked, contiguous float64,
    copied where it shares ``x``'s memory."""
    if x.shape != (shape[0],) or np.shape(b) != x.shape:
        raise ValueError(f"a sweep on {shape} needs x and b of length {shape[0]}")
    if x.dtype != np.float64 or not x.flags.c_contiguous:
        raise ValueError("a sweep updates x in place: it must be a contiguous float64 array")
    b = np.ascontiguousarray(b, dtype=np.float64)
    return b.copy() if np.shares_memory(b, x) else b


# Smoothing sweeps
# ----------------
#: Row blocks of a hybrid Gauss-Seidel sweep, whatever the thread count: a sweep's result does
#: not depend on how many threads run it.
SWEEP_PARTS = 2
#: A matrix with more of its entries coupling the row blocks is swept as one block (Gauss-Seidel
#: itself, on one thread): its unknowns are not numbered for locality, and the l1 term would
#: weaken the sweeps (a mesh as generated, before it is renumbered for locality, can have most
#: of its entries across the split).
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


@jitcache.jit(parallel=True, error_model="numpy")
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
    between blocks, which need not be positive); with it M + M^T - A is positive definite for
    symmetric positive definite A.
    A forward sweep followed by a backward one is symmetric, as a conjugate-gradient
    preconditioner must be.

    A matrix whose unknowns are not numbered for locality (more than :data:`MAX_CROSS_FRACTION` of
    its entries across the split) is swept as one block: Gauss-Seidel, on one thread.

    On a mesh numbered for locality (a few percent of the entries across the split) the
    multigrid-preconditioned solves take about as many iterations as with Gauss-Seidel, and the
    sweep runs on as many threads as there are parts."""

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
    ``get_block_diag``), by kernels written for 6 x 6 blocks. The sweep itself is sequential (one
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
        rows have)."""
        out = np.empty(self.shape[0])
        _bsr33_diagonal(self._indptr, self._indices, self._data, out)
        return out


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
