"""Compiled sparse kernels on several threads for the multigrid path's Newton solves (systems
beyond PARDISO's size), which apply the stiffness, the multigrid transfer operators, the
residuals and the smoothing sweeps thousands of times a plan: SciPy's products and pyamg's
sweeps run on one core.

Products
--------
Each row's sum is taken by one thread, in an order that does not depend on the thread count:
the products are the same to the bit on one thread or two. They differ from SciPy's by the
rounding of a reordered sum (the loop over a row is vectorised). Indices are read unsigned
(Numba adds a negative-index wrap-around to every signed array access, which would make the
one-thread product slower than SciPy's).

The smoothing sweeps built on these products are :mod:`softgrasp.linalg.smoothers`'s.
"""

from __future__ import annotations

from typing import Any

import numba
import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from softgrasp import jitcache
from softgrasp.linalg.pattern import block_layout, unique_pairs

__all__ = [
    "BLOCK",
    "BsrProduct",
    "CsrProduct",
    "MIN_BLOCK_FILL",
    "NodeBlockProduct",
    "block_layout",
    "diagonal",
    "node_blocks",
    "product",
    "unique_pairs",
]

# The parallel kernels' loop iterations each write their own outputs; none sums across
# iterations (a prange reduction): Numba keeps one partial sum per thread, and TBB, its threading
# layer here, hands chunks to threads dynamically, so such a sum would change from run to run.
_pjit = jitcache.jit(parallel=True, fastmath={"reassoc", "contract"}, error_model="numpy")
# The block kernels' sums run in a fixed order (each row's six accumulators), multiply-adds fused.
_bpjit = jitcache.jit(parallel=True, fastmath={"contract"}, error_model="numpy")
_bjit = jitcache.jit(fastmath={"contract"}, error_model="numpy")


@_pjit
def _csr_matvec(indptr, indices, data, x, out):  # pragma: no cover - compiled
    """out = A x for A in CSR arrays (``indptr`` and ``indices`` unsigned)."""
    for i in numba.prange(out.shape[0]):
        s = 0.0
        for k in range(indptr[i], indptr[i + 1]):
            s += data[k] * x[indices[k]]
        out[i] = s


@jitcache.jit(parallel=True, error_model="numpy")
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


@jitcache.jit(parallel=True, error_model="numpy")
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
    on Numba's threads."""
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


# Node blocks of the finest level
# -------------------------------
# A body's Newton matrix couples nodes by 3 x 3 blocks. Read as blocks (one index for nine values,
# three accumulators a row), its products and sweeps move a third less memory and take about half
# the instructions.
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
