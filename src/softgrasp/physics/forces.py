"""Sparse (3N, 3N) matrices of 3x3 node blocks, and gravity.

The body's Jacobians are ``d f / d x`` (the negative of the stiffness matrix), sparse ``(3N, 3N)``
with 3x3 node blocks ordered ``[x0, y0, z0, x1, ...]``: :func:`assemble_blocks` sums blocks at
node pairs once, :class:`BlockPattern` fixes the structure per topology so that new block values
are summed straight into its CSR data. The force laws themselves are in
:mod:`softgrasp.physics.springs` (springs and dashpots), :mod:`softgrasp.physics.volume` (the volume
term) and :mod:`softgrasp.physics.forces_compiled` (all of them summed in one pass).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

__all__ = ["BlockPattern", "assemble_blocks", "gravity_forces"]


def assemble_blocks(
    n_nodes: int, rows: NDArray[np.int64], cols: NDArray[np.int64], blocks: NDArray[np.float64]
) -> sp.csr_matrix:
    """Sparse (3N, 3N) matrix from 3x3 blocks ``blocks[k]`` at node pair ``(rows[k], cols[k])``.

    Repeated pairs are summed.
    """
    r = (3 * rows[:, None, None] + np.arange(3)[None, :, None]).repeat(3, axis=2)
    c = (3 * cols[:, None, None] + np.arange(3)[None, None, :]).repeat(3, axis=1)
    m = sp.coo_matrix((blocks.ravel(), (r.ravel(), c.ravel())), shape=(3 * n_nodes, 3 * n_nodes))
    return m.tocsr()


class BlockPattern:
    """The CSR structure of a sparse (3N, 3N) matrix of 3x3 blocks at fixed node pairs, built once
    per topology, so that assembling new block values is one ``bincount`` into the CSR data (no
    COO conversion, sorting or duplicate summation per Newton iteration).

    Parameters
    ----------
    n_nodes: N.  rows, cols: (K,) node pair of each block; repeated pairs are summed.
    """

    def __init__(self, n_nodes: int, rows: NDArray[np.int64], cols: NDArray[np.int64]) -> None:
        rows = np.asarray(rows, dtype=np.int64)
        cols = np.asarray(cols, dtype=np.int64)
        if rows.shape != cols.shape or rows.ndim != 1:
            raise ValueError("rows and cols must be equal-length 1-D arrays")
        self.n_nodes = int(n_nodes)
        self.n_blocks_in = len(rows)
        from softgrasp.linalg.sparse import block_layout, unique_pairs

        brow, bcol, inv = unique_pairs(rows, cols, n_nodes)  # sorted by row, then column
        self.nnz = 9 * len(brow)
        # Scalar row 3r + a holds 3 count[r] entries: the blocks of block row r by column, three
        # columns each; entry (a, b) of input block k sits at block_base[k] + a block_stride[k] + b.
        self.block_base, self.block_stride, self.indptr, self.indices = block_layout(
            brow, bcol, inv, n_nodes, self._index_dtype(self.nnz, n_nodes)
        )

    @staticmethod
    def _index_dtype(nnz: int, n_nodes: int) -> type:
        """int32 where it holds the matrix: the index type SciPy would choose. Given int64, each
        :meth:`matrix` would scan and convert a copy (4.8 ms and 16 MB a Newton matrix at 32 543
        nodes); given int32, the matrices share the pattern's arrays (their structure is never
        changed in place: canonical CSR, so SciPy's sum_duplicates / sort_indices leave it
        alone)."""
        return np.int32 if max(nnz, 3 * n_nodes) < np.iinfo(np.int32).max else np.int64

    @property
    def positions(self) -> NDArray[np.int64]:
        """CSR data position of entry (a, b) of input block k at index ``9 k + 3 a + b``, (9K,)
        (``block_base[k] + a block_stride[k] + b``; the compiled kernels use those two (K,) arrays,
        two integers per block instead of nine: 50 MB instead of 230 MB at 28 000 nodes)."""
        a = np.arange(3)[None, :, None]
        b = np.arange(3)[None, None, :]
        return (self.block_base[:, None, None] + a * self.block_stride[:, None, None] + b).ravel()

    def assemble(self, blocks: NDArray[np.float64]) -> sp.csr_matrix:
        """The matrix with ``blocks`` (K, 3, 3) at the pattern's node pairs, summed where repeated."""
        if blocks.shape != (self.n_blocks_in, 3, 3):
            raise ValueError(f"expected blocks of shape ({self.n_blocks_in}, 3, 3), got {blocks.shape}")
        data = np.bincount(self.positions, weights=blocks.ravel(), minlength=self.nnz)
        return self.matrix(np.asarray(data, dtype=np.float64))

    def matrix(self, data: NDArray[np.float64]) -> sp.csr_matrix:
        """The matrix of this pattern with CSR data ``data`` (nnz,) (used without copying)."""
        if data.shape != (self.nnz,):
            raise ValueError(f"expected data of shape ({self.nnz},), got {data.shape}")
        n = 3 * self.n_nodes
        m = sp.csr_matrix((data, self.indices, self.indptr), shape=(n, n), copy=False)
        m.has_sorted_indices = True
        m.has_canonical_format = True
        return m


def gravity_forces(mass: NDArray[np.float64], gravity: NDArray[np.float64]) -> NDArray[np.float64]:
    """Weights ``m_i g`` [N], (N, 3)."""
    return mass[:, None] * np.asarray(gravity, dtype=np.float64)[None, :]
