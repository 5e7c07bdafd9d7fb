"""The multigrid V-cycle that preconditions the large Newton systems, applied by softgrasp.

pyamg builds the smoothed-aggregation hierarchy (:mod:`softgrasp.linalg.multigrid.hierarchy`);
:class:`Multigrid` keeps it across the Newton systems of one loading, makes each new matrix its
finest level, and applies one V-cycle from zero: compiled products and sweeps
(:mod:`softgrasp.linalg.sparse`, :mod:`softgrasp.linalg.smoothers`) where the compiled kernels
are in use, SciPy's and pyamg's otherwise.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from softgrasp import backend
from softgrasp.linalg.multigrid.coarse import UpdatedLevel, changed_nodes, galerkin_change
from softgrasp.linalg.multigrid.hierarchy import hierarchy

__all__ = ["Multigrid", "ScipyProduct"]


class Multigrid:
    """The smoothed-aggregation V-cycle preconditioner kept in a solver cache across the
    Newton systems of one loading (pyamg builds the hierarchy; this applies it).

    The hierarchy is built on the first matrix; :meth:`use` makes each new one its finest level
    (the smoothing sweeps, which take the matrix as they run, and the fine residual see it), the
    coarse levels staying those of the matrix it was built on, brought up to date with the
    contacts made since (:mod:`softgrasp.linalg.multigrid.coarse`).

    A cycle is applied here rather than by pyamg's driver, which takes the residual's norm before
    and after each cycle (two products with the finest matrix, a fifth of a cycle's time), with
    the residuals and the transfers between levels on the compiled products
    (:func:`softgrasp.linalg.sparse.product`: by blocks where the hierarchy has them, on the
    threads :meth:`use` is given): the same cycle to the rounding of the products' sums."""

    def __init__(self, A: sp.csr_matrix, x_nodes: NDArray[np.float64]) -> None:
        self.ml: Any = hierarchy(A, x_nodes)
        levels = self.ml.levels
        self._A = [_product(level.A) for level in levels[:-1]]
        self._R = [_product(level.R) for level in levels[:-1]]
        self._P = [_product(level.P) for level in levels[:-1]]
        # What the coarse levels' update for later matrices starts from (multigrid.coarse): the build
        # matrix and its diagonal, the first prolongator by rows, the deeper ones, the coarse
        # operators as built.
        self._A0: sp.csr_matrix | None = A
        self._diagonal0: NDArray[np.float64] | None = None
        self._P0 = levels[0].P if len(levels) > 1 else None
        self._Pc = [level.P for level in levels[1:-1]]
        self._Rc = [level.R for level in levels[1:-1]]
        for level in levels[:-1]:
            # The products above hold the transfers; pyamg's own cycle is not used.
            level.R = level.P = None
        # Each level's sweeps where softgrasp's compiled kernels make them (None: pyamg's): the
        # finest level's l1 hybrid Gauss-Seidel, set by use(); the coarse levels' block
        # Gauss-Seidel (6 x 6 blocks, pyamg's to round-off), made here.
        self._sweeps: list[Any] = [None] * (len(levels) - 1)
        if _compiled():
            from softgrasp.linalg.smoothers import BLOCK, BlockGaussSeidel

            for lvl in range(1, len(levels) - 1):
                Ak = levels[lvl].A
                if sp.issparse(Ak) and Ak.format == "bsr" and tuple(Ak.blocksize) == (BLOCK, BLOCK):
                    self._sweeps[lvl] = self._A[lvl] = BlockGaussSeidel(Ak)
        # The coarse levels kept up to date with the contacts (multigrid.coarse) where the compiled
        # sweeps run them: the finest level's unknowns left out of the coarse space (stiffened
        # nodes), and each coarse level's operator as built plus its change.
        self._pinned: NDArray[np.intp] | None = None
        self._levels: list[UpdatedLevel] = []
        self._built_coarse = self.ml.coarse_solver
        if self._P0 is not None and all(s is not None for s in self._sweeps[1:]):
            self._diagonal0 = _diagonal(A)
            self._levels = [
                UpdatedLevel(levels[lvl].A, self._sweeps[lvl] if lvl < len(levels) - 1 else None)
                for lvl in range(1, len(levels))
            ]
        else:
            self._A0 = None  # no update: the build matrix is not needed
        self.stats: dict[str, int] | None = None  # where the cycles are counted (a cache's stats)

    def fits(self, A: sp.csr_matrix) -> bool:
        return bool(self.ml.levels[0].A.shape == A.shape)

    def use(self, A: sp.csr_matrix, threads: int) -> None:
        """Make ``A`` (CSR) the finest level's matrix, the products and sweeps run on ``threads``
        threads."""
        self.ml.levels[0].A = A
        compiled = backend.compiled
        self._fine = None  # the last matrix's copy by blocks goes before the next one is made
        if self._A:
            self._A[0] = self._sweeps[0] = None

        if compiled():
            from softgrasp.linalg.smoothers import fine_smoother

            # The finest level's sweeps, and its products.
            self._fine = fine_smoother(A, threads)
        else:
            self._fine = ScipyProduct(A)
        if len(self.ml.levels) == 1:
            # A matrix no larger than the coarsest level's limit is its own coarsest level: its
            # factorisation (made at the first solve) must be the new matrix's.
            from pyamg.multilevel import coarse_grid_solver

            self.ml.coarse_solver = coarse_grid_solver("splu")
            return
        self._A[0] = self._fine
        self._sweeps[0] = self._fine if compiled() else None
        if self._levels:
            # Where NumPy's kernels run the cycle it is pyamg's own: the levels as built.
            self._update_coarse(A if compiled() else None)
        for op in (*self._A, *self._R, *self._P):
            op.threads = threads

    def _update_coarse(self, A: sp.csr_matrix | None) -> None:
        """The coarse levels for ``A``: the hierarchy's as built, with the nodes the contacts
        stiffened since left out of the coarse space and the operators' Galerkin change for the
        nodes they changed (:mod:`softgrasp.linalg.multigrid.coarse`); as built for None."""
        assert self._P0 is not None and self._A0 is not None and self._diagonal0 is not None
        levels = self.ml.levels
        none = np.zeros(0, dtype=np.intp)
        stiffened, changed = (
            (none, none) if A is None else changed_nodes(_diagonal(A, self._fine), self._diagonal0)
        )
        if stiffened.size == 0 and changed.size == 0:
            self._pinned = None
            for level in self._levels:
                level.reset()
        else:
            self._pinned = (3 * stiffened[:, None] + np.arange(3)).ravel() if stiffened.size else None
            change = galerkin_change(self._P0, self._A0, A, stiffened, changed)
            for lvl, level in enumerate(self._levels, start=1):
                level.update(change)
                if lvl < len(levels) - 1:
                    change = sp.csr_matrix(self._Rc[lvl - 1] @ (change @ self._Pc[lvl - 1]))
        for lvl, level in enumerate(self._levels, start=1):
            levels[lvl].A = level.matrix
            if lvl < len(levels) - 1:
                self._sweeps[lvl] = self._A[lvl] = level.sweeps
        if not self._levels[-1].changed:
            self.ml.coarse_solver = self._built_coarse
        else:
            from pyamg.multilevel import coarse_grid_solver

            self.ml.coarse_solver = coarse_grid_solver("splu")

    @property
    def fine(self) -> Any:
        """The finest level's matrix, as a product (``fine @ x``)."""
        return self._fine

    def product(self, A: sp.csr_matrix) -> Any:
        """``A`` as a product on the threads of this one's."""
        op = _product(A)
        op.threads = self._fine.threads
        return op

    def _cycle(self, lvl: int, b: NDArray[np.float64]) -> NDArray[np.float64]:
        if len(self.ml.levels) == 1:
            return np.asarray(self.ml.coarse_solver(self.ml.levels[0].A, b), dtype=np.float64)
        level = self.ml.levels[lvl]
        x = np.zeros_like(b)
        sweeps = self._sweeps[lvl]
        if sweeps is not None:
            sweeps.sweep(x, b, forward=True)
        else:
            level.presmoother(level.A, x, b)
        r = b - self._A[lvl] @ x
        pinned = self._pinned if lvl == 0 else None
        if pinned is not None:
            r[pinned] = 0.0
        coarse_b = self._R[lvl] @ r
        if lvl == len(self.ml.levels) - 2:
            coarse_x = self.ml.coarse_solver(self.ml.levels[-1].A, coarse_b)
        else:
            coarse_x = self._cycle(lvl + 1, coarse_b)
        correction = self._P[lvl] @ coarse_x
        if pinned is not None:
            correction[pinned] = 0.0
        x += correction
        if sweeps is not None:
            sweeps.sweep(x, b, forward=False)
        else:
            level.postsmoother(level.A, x, b)
        return x

    def matvec(self, r: NDArray[np.float64]) -> NDArray[np.float64]:
        """One V-cycle from zero on ``r``."""
        if self.stats is not None:
            self.stats["multigrid_cycles"] += 1
        return self._cycle(0, np.asarray(r, dtype=np.float64))

    __matmul__ = matvec


class ScipyProduct:
    """SciPy's product, where the compiled kernels are not in use (the same interface as
    :class:`~softgrasp.linalg.sparse.CsrProduct`)."""

    def __init__(self, A: Any) -> None:
        self.A = A.tocsr()
        self.shape = self.A.shape
        self.threads = 1

    def __matmul__(self, x: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.asarray(self.A @ x)


def _compiled() -> bool:
    return bool(backend.compiled())


def _diagonal(A: sp.csr_matrix, fine: Any = None) -> NDArray[np.float64]:
    """``A``'s diagonal: from ``fine`` (its finest-level sweeps, which read it by node blocks)
    or by the compiled kernel where the compiled kernels are in use, by SciPy otherwise."""
    if _compiled():
        if fine is not None:
            return np.asarray(fine.diagonal())
        from softgrasp.linalg.sparse import diagonal

        return diagonal(A)
    return np.asarray(A.diagonal(), dtype=np.float64)


def _product(A: Any) -> Any:
    """``A`` as a product: softgrasp's compiled one (by blocks where it has 6 x 6, 6 x 1 or 1 x 6
    blocks, :func:`softgrasp.linalg.sparse.product`) where the compiled kernels are in use,
    SciPy's otherwise."""
    if _compiled():
        from softgrasp.linalg.sparse import product

        return product(A)
    return ScipyProduct(A)
