"""The candidates' relaxation of the smoothed-aggregation set-up, compiled: pyamg's arithmetic to
the bit.

The finest level of a multigrid hierarchy (:mod:`softgrasp.linalg.multigrid.aggregation`) improves its six
rigid-body candidates by four symmetric Gauss-Seidel sweeps on ``A x = 0``. pyamg runs them one
candidate at a time: 48 passes over the matrix, each row's sum one chain of adds, each add
waiting on the last (0.19-0.25 s of a 1.1-1.3 s set-up at 32 543 nodes, 97 629 unknowns and
4.1 M non-zeros). Here each pass over a row updates all six candidates, six independent chains
(0.08 s). Compiled without ``fastmath``: every candidate's sums run in pyamg's order with separate
multiplies and adds, so the candidates are pyamg's to the bit (``tests/test_aggregation.py``).
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["gauss_seidel_columns"]

_jit = numba.njit(cache=True, error_model="numpy")


@_jit
def _sweep6(indptr, indices, data, X, start, stop, step):  # pragma: no cover - compiled
    """One Gauss-Seidel sweep on ``A X = 0`` over rows ``start, start + step, ...`` (``stop``
    excluded), the six columns of X in each row: pyamg's ``gauss_seidel`` row update
    ``x_i = (b_i - sum_{j != i} a_ij x_j) / a_ii`` (b = 0), skipped where ``a_ii`` is zero; the six
    sums in registers (an array of sums went through memory: no faster than pyamg's one column
    at a time)."""
    for i in range(start, stop, step):
        diag = 0.0
        r0 = r1 = r2 = r3 = r4 = r5 = 0.0
        for jj in range(indptr[i], indptr[i + 1]):
            j = indices[jj]
            a = data[jj]
            if j == i:
                diag = a
            else:
                r0 += a * X[j, 0]
                r1 += a * X[j, 1]
                r2 += a * X[j, 2]
                r3 += a * X[j, 3]
                r4 += a * X[j, 4]
                r5 += a * X[j, 5]
        if diag != 0.0:
            X[i, 0] = (0.0 - r0) / diag
            X[i, 1] = (0.0 - r1) / diag
            X[i, 2] = (0.0 - r2) / diag
            X[i, 3] = (0.0 - r3) / diag
            X[i, 4] = (0.0 - r4) / diag
            X[i, 5] = (0.0 - r5) / diag


@_jit
def _gauss_seidel_columns(indptr, indices, data, X, iterations):  # pragma: no cover - compiled
    n = indptr.shape[0] - 1
    for _ in range(iterations):
        _sweep6(indptr, indices, data, X, 0, n, 1)
        _sweep6(indptr, indices, data, X, n - 1, -1, -1)


def gauss_seidel_columns(indptr, indices, data, X: np.ndarray, iterations: int) -> None:
    """``iterations`` symmetric Gauss-Seidel sweeps (forward, then backward) on ``A X = 0`` for
    the six columns of ``X`` (n, 6, C order, float64) in place, ``A`` by its CSR arrays (rows may
    hold their columns in any order): each column as pyamg's ``gauss_seidel(A, x, 0, iterations,
    sweep="symmetric")`` leaves it, to the bit."""
    if X.ndim != 2 or X.shape[1] != 6 or X.dtype != np.float64 or not X.flags.c_contiguous:
        raise ValueError("the sweeps take six float64 columns in C order")
    if X.shape[0] != len(indptr) - 1 or len(indices) != len(data) or np.asarray(data).dtype != np.float64:
        raise ValueError("X's rows, the matrix's rows and its float64 entries must match")
    _gauss_seidel_columns(indptr, indices, data, X, iterations)
