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

import numba
import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

__all__ = ["CsrProduct", "HybridGaussSeidel", "SWEEP_PARTS"]

_pjit = numba.njit(cache=True, parallel=True, fastmath={"reassoc", "contract"}, error_model="numpy")


@_pjit
def _csr_matvec(indptr, indices, data, x, out):  # pragma: no cover - compiled
    """out = A x for A in CSR arrays (``indptr`` and ``indices`` unsigned)."""
    for i in numba.prange(out.shape[0]):
        s = 0.0
        for k in range(indptr[i], indptr[i + 1]):
            s += data[k] * x[indices[k]]
        out[i] = s


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
        if np.shape(x) != (self.shape[1],):
            raise ValueError(f"a {self.shape} matrix times a vector of shape {np.shape(x)}")
        out = np.empty(self.shape[0])
        with _Threads(self.threads):
            _csr_matvec(
                self._indptr, self._indices, self._data, np.ascontiguousarray(x, dtype=np.float64), out
            )
        return out

    matvec = __matmul__


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
            for k in range(np.uint64(indptr[i]), np.uint64(indptr[i + one])):
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
        A = self.A
        self.inverse_diagonal = np.empty(A.shape[0])
        self.parts = SWEEP_PARTS if parts is None else max(1, int(parts))
        cross = np.zeros(self.parts, dtype=np.int64)
        with _Threads(threads):
            _l1_inverse_diagonal(
                self._indptr, self._indices, self._data, self.parts, self.inverse_diagonal, cross
            )
            if parts is None and cross.sum() > MAX_CROSS_FRACTION * max(A.nnz, 1):
                self.parts = 1
                _l1_inverse_diagonal(
                    self._indptr, self._indices, self._data, self.parts, self.inverse_diagonal, cross
                )

    def sweep(self, x: NDArray[np.float64], b: NDArray[np.float64], forward: bool) -> None:
        """One sweep on ``x`` (float64, contiguous; updated in place) for ``A x = b``."""
        if x.shape != (self.A.shape[0],) or np.shape(b) != x.shape:
            raise ValueError(f"a sweep on {self.A.shape} needs x and b of length {self.A.shape[0]}")
        if x.dtype != np.float64 or not x.flags.c_contiguous:
            raise ValueError("a sweep updates x in place: it must be a contiguous float64 array")
        b = np.ascontiguousarray(b, dtype=np.float64)
        if np.shares_memory(b, x):
            b = b.copy()
        with _Threads(self.threads):
            _hybrid_sweep(
                self._indptr,
                self._indices,
                self._data,
                self.inverse_diagonal,
                x,
                b,
                x.copy() if self.parts > 1 else x,  # one block reads no other block's values
                self.parts,
                forward,
            )
