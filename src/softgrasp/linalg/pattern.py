"""Sparsity patterns of a body's Newton matrix by node blocks: the distinct node pairs of its
couplings and the CSR layout of their 3 x 3 blocks, compiled (linear time, no sort of all pairs).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from softgrasp import jitcache

__all__ = ["block_layout", "unique_pairs"]


@jitcache.jit(error_model="numpy")
def _unique_pairs(rows, cols, n):  # pragma: no cover - compiled
    """:func:`unique_pairs` by a counting sort on the rows and, within a row, a mark per column
    and an insertion sort of its few columns."""
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
        for q in range(1, m):  # insertion sort: a row has tens of columns (np.sort compiles for seconds)
            c = seen[q]
            j = q - 1
            while j >= 0 and seen[j] > c:
                seen[j + 1] = seen[j]
                j -= 1
            seen[j + 1] = c
        for q in range(m):
            slot[seen[q]] = nu + q
            urow[nu + q] = r
            ucol[nu + q] = seen[q]
        for p in range(start[r], start[r + 1]):
            k = order[p]
            inv[k] = slot[cols[k]]
        nu += m
    return urow[:nu].copy(), ucol[:nu].copy(), inv


@jitcache.jit(error_model="numpy")
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
    temporaries."""
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
