"""Linear solves of the Newton systems ``A dx = b`` with optional constraints ``C dx = 0``.

A is the stiffness (minus the force Jacobian): symmetric and, away from buckling, positive definite
on the constraint null space. Three solvers, chosen by size and what is installed:

* **PARDISO** (MKL's sparse direct solver, :mod:`softgrasp.linalg.pardiso`) up to
  :data:`PARDISO_MAX_DOF` unknowns: the ordering and symbolic factorisation are done once per
  sparsity pattern (the body's pattern does not change between Newton iterations, load steps and
  holding steps); each system first tries a few conjugate-gradient iterations preconditioned by the
  factorisation it already has (a Newton matrix changes little from one iteration to the next),
  corrected by the Woodbury formula for the few nodes that have gained much stiffness since
  (contacts made), and refactorises numerically only when they do not converge fast enough;
* sparse LU of the saddle-point system for constrained systems (and small systems without MKL);
* conjugate gradients preconditioned by smoothed-aggregation algebraic multigrid (pyamg) with the
  rigid-body modes as near-null space — the standard scalable solver for elasticity — for the
  largest systems, for singular ones (a body not yet held) and where MKL is missing. The
  multigrid hierarchy is reused while it still preconditions well.

All of it lives in a :class:`SolverCache` that the callers keep across the solves of one loading.
"""

from __future__ import annotations

import contextlib
import functools
import math
import os
import threading
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from numpy.typing import NDArray

from softgrasp.errors import NotConverged
from softgrasp.linalg import pardiso
from softgrasp.linalg.multigrid.coarse import UpdatedLevel, changed_nodes, galerkin_change

__all__ = ["SolverCache", "solve_newton_system", "by_multigrid", "DIRECT_MAX_DOF", "PARDISO_MAX_DOF"]

#: Without MKL, systems with at most this many unknowns are solved by sparse LU.
DIRECT_MAX_DOF = 1500
#: Systems with at most this many unknowns are factorised by PARDISO where MKL is installed
#: (beyond, the factor's memory and time grow faster than multigrid's). Default plans measured
#: alternately on the V-cycle by blocks (`softgrasp.linalg.sparse`): 7 576 nodes (22 728
#: unknowns) 4.6-5.2 s on PARDISO, 4.6-4.8 s on multigrid (the same 41 systems); 11 874 nodes
#: 15.6-16.0 s and 520 MB against 12.5-12.7 s and 445 MB; 15 662 nodes 12.5-13.5 s and 624 MB
#: against 8.5-9.3 s and 519 MB. Below, PARDISO: 4 498 nodes 3.0 against 8.0 s (the multigrid
#: path's settle took 41 Newton systems instead of 18).
PARDISO_MAX_DOF = 30_000
#: Relative residual of the conjugate-gradient iterations preconditioned by an earlier
#: factorisation (the Newton iteration checks the true unbalanced forces; this only has to be
#: well below its contraction).
STALE_RTOL = 1e-8
#: GMRES iterations allowed with a fresh factorisation on the exact (non-symmetric) Newton matrix.
EXACT_MAX_IT = 20
#: Relative residual to which a single-precision factor's solves of its own matrix are refined
#: (conjugate gradients against the double-precision matrix): a double factor's direct solve
#: leaves ~1e-13-1e-12 at 2 196 nodes, and what is solved "directly" must stay as exact whatever
#: the Newton iteration's forcing term (the calibration's fits difference simulated forces).
REFINED_RTOL = 1e-11
#: First diagonal shift (relative) of an indefinite Newton matrix; grown tenfold until positive.
INDEFINITE_SHIFT = 1e-6
#: GMRES iterations allowed with a multigrid preconditioner on the exact Newton matrix.
AMG_GMRES_MAX_IT = 80
#: Time of a solve with a factor over the time of its factorisation, per unit of their operation
#: counts' ratio (PARDISO's factorisation flops over 4 flops per factor non-zero): the solve is
#: memory-bound, the factorisation runs at BLAS-3 speed (measured 0.13-0.28 from 388 to 7 576
#: nodes on this machine). It sets how many iterations an old factor may take before a
#: refactorisation is cheaper: from operation counts, not timings, so that a plan's solver path,
#: and with friction its equilibrium, does not depend on the machine's load.
SOLVE_SPEED_RATIO = 0.25

_SINGULAR = (
    "the stiffness matrix is singular, so the body is not held in place (it could slide, spin or "
    "fall freely); add support (table friction, contacts) or constraints"
)


@dataclass
class SolverCache:
    """Reusable state of the iterative solver across Newton iterations and load steps.

    Attributes
    ----------
    method: ``"auto"`` (PARDISO up to :data:`PARDISO_MAX_DOF` unknowns where MKL is installed,
        else sparse LU up to :data:`DIRECT_MAX_DOF`; multigrid beyond), ``"pardiso"``,
        ``"direct"``, ``"amg"`` or ``"reference"`` (sparse LU up to :data:`DIRECT_MAX_DOF`, multigrid
        beyond, never the exact Newton product).
    rtol: relative tolerance of the multigrid-preconditioned solves (the tightest asked: a Newton
        step asks only its forcing term, when that is looser).
    precision: of PARDISO's Cholesky factors: ``"mixed"`` (single-precision factors, every solve
        refined against the double-precision matrix by conjugate gradients or GMRES to the
        tolerance asked, as solves with an older factor always were; the verdicts positive
        definite / indefinite / singular the double factor's: see
        :class:`~softgrasp.linalg.pardiso.PardisoFactor`) or ``"double"``. The two reach the
        same rests to the Newton tolerance, but where the rest is a branch choice (a Newton iterate within rounding of
        the tolerance on an indefinite matrix: a compressed softening cube about to buckle) float32
        rounding makes that choice noisy; the material tests, whose curves the calibration fits
        difference, use ``"double"``.
    stats: counts of what the solves did: Newton ``systems`` solved, PARDISO ``analyses``,
        ``factorisations`` and solves with an older factor (``stale_solves``), multigrid solves
        (``amg_solves``), hierarchy set-ups and V-cycles (``multigrid_setups``,
        ``multigrid_cycles``), and the shifts of indefinite matrices where there were any.
    """

    method: str = "auto"
    rtol: float = 1e-10
    precision: str = "mixed"
    _ml: object | None = field(default=None, repr=False)
    _iterations: list[int] = field(default_factory=list, repr=False)
    _factor: pardiso.PardisoFactor | None = field(default=None, repr=False)
    _try_stale: bool = field(default=True, repr=False)
    # Solves with the factor in use beyond what its first system needed, summed over the systems
    # solved on it since (the price of its ageing), and that first system's solves (-1: unknown).
    _excess: int = field(default=0, repr=False)
    _fresh: int = field(default=-1, repr=False)
    _correction: Any = field(default=None, repr=False)
    stats: dict[str, int] = field(
        default_factory=lambda: {
            "systems": 0,
            "analyses": 0,
            "factorisations": 0,
            "stale_solves": 0,
            "amg_solves": 0,
            "multigrid_setups": 0,
            "multigrid_cycles": 0,
        },
        repr=False,
    )

    @property
    def iterations(self) -> list[int]:
        """CG iterations of each iterative solve so far."""
        return self._iterations

    def scene_changed(self) -> None:
        """Say that the next systems come from another scene (an interaction taken away or put
        in): the next one refactorises at once instead of first trying the last factorisation as
        a preconditioner, which a removed table's or finger's stiffness makes a poor one (the
        pattern's analysis is kept), and the multigrid hierarchy is built anew (its coarse levels
        would keep the removed stiffness: the 27 749-node hold check's solves took 27-49 V-cycles
        on the hierarchy built with the table, where the closing's took 16-33)."""
        self._try_stale = False
        self._ml = None


def _rigid_modes(x: NDArray[np.float64]) -> NDArray[np.float64]:
    n = x.shape[0]
    B = np.zeros((3 * n, 6))
    for k in range(3):
        B[k::3, k] = 1.0
    r = x - x.mean(axis=0)
    for k, (i, j) in enumerate(((0, 1), (1, 2), (2, 0))):
        B[i::3, 3 + k] = -r[:, j]
        B[j::3, 3 + k] = r[:, i]
    return B


#: The multigrid V-cycle's smoothing on every level pyamg sweeps: one forward (block) Gauss-Seidel
#: sweep before the coarse correction, one backward after (a symmetric preconditioner, as
#: conjugate gradients need; the finest level's sweeps are softgrasp's own where the compiled
#: kernels are in use, :class:`~softgrasp.linalg.sparse.HybridGaussSeidel`). A symmetric sweep
#: on each side (pyamg's default) cost half as much again a cycle for about one iteration fewer
#: (83 247 unknowns: 23-25 against 33-38 ms a cycle, 9 against 8 iterations to 1e-4).
_PRESMOOTHER = ("block_gauss_seidel", {"sweep": "forward"})
_POSTSMOOTHER = ("block_gauss_seidel", {"sweep": "backward"})
#: The coarsest level's most block rows (factorised by sparse LU).
MAX_COARSE = 300
#: Seed of the random start from which pyamg estimates a spectral radius while it builds a
#: hierarchy (NumPy's global generator, seeded and put back: a hierarchy should not be built
#: while another Python thread draws from it; softgrasp's own threads build theirs one at a time,
#: :data:`_GLOBAL_RNG`).
AMG_SEED = 20_240_901
#: Held while a hierarchy is built from NumPy's seeded global generator: two threads planning at
#: once (a script's thread pool) would otherwise draw from each other's seeded sequence, and each
#: plan's numbers would depend on how the threads interleaved.
_GLOBAL_RNG = threading.Lock()


def _fresh_rng_lock() -> None:
    """A forked child gets a lock of its own: one held by another thread at the fork would never
    be released there."""
    global _GLOBAL_RNG
    _GLOBAL_RNG = threading.Lock()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_fresh_rng_lock)
#: Systems with fewer unknowns run the multigrid products and sweeps on one thread: a second
#: gains nothing there (the 2 196-node plan on the multigrid path, 6 588 unknowns: 2.85 s on one
#: thread and on two) and would compete with PARDISO's spinning threads where a singular system
#: falls back to multigrid.
MULTIGRID_THREADS_MIN_DOF = 20_000


def _hierarchy(A: sp.csr_matrix, x_nodes: NDArray[np.float64]) -> Any:
    """pyamg's smoothed-aggregation hierarchy of ``A``, the rigid-body modes of the nodes
    ``x_nodes`` as near-null space. pyamg estimates the spectral radius that smooths the
    prolongator from a random start (NumPy's global generator): seeded with :data:`AMG_SEED`, so
    that the same matrix gives the same hierarchy and a plan the same numbers run after run; the
    caller's generator state is put back."""
    import pyamg

    with _GLOBAL_RNG:
        state = np.random.get_state()
        np.random.seed(AMG_SEED)
        try:
            if _compiled():
                from softgrasp.linalg.multigrid.aggregation import smoothed_aggregation

                # The same hierarchy, its finest Galerkin product, candidate sweeps and spectral
                # radius estimates on compiled kernels (sim.aggregation).
                return smoothed_aggregation(
                    A, _rigid_modes(x_nodes), MAX_COARSE, "splu", _PRESMOOTHER, _POSTSMOOTHER
                )
            return pyamg.smoothed_aggregation_solver(
                A,
                B=_rigid_modes(x_nodes),
                symmetry="symmetric",
                max_coarse=MAX_COARSE,
                coarse_solver="splu",
                presmoother=_PRESMOOTHER,
                postsmoother=_POSTSMOOTHER,
            )
        finally:
            np.random.set_state(state)


class _Multigrid:
    """The smoothed-aggregation V-cycle preconditioner kept in a :class:`SolverCache` across the
    Newton systems of one loading (pyamg builds the hierarchy; this applies it).

    The hierarchy is built on the first matrix; :meth:`use` makes each new one its finest level
    (the smoothing sweeps, which take the matrix as they run, and the fine residual see it), the
    coarse levels staying those of the matrix it was built on. Measured on the settle of the
    27 749-node sphere (eleven Newton matrices against a hierarchy built on the first): 16-26
    iterations to 1e-4 where the whole hierarchy kept from the first matrix took 25-105, and a
    fresh one 7-11.

    A cycle is applied here rather than by pyamg's driver, which takes the residual's norm before
    and after each cycle (two products with the finest matrix, a fifth of a cycle's time), with
    the residuals and the transfers between levels on the compiled products
    (:func:`softgrasp.linalg.sparse.product`: by blocks where the hierarchy has them; both cores
    where they are idle and the system has at least :data:`MULTIGRID_THREADS_MIN_DOF` unknowns):
    the same
    cycle to the rounding of the products' sums. 83 247 unknowns: 23 ms a cycle through pyamg's
    driver, 18 ms here on one thread."""

    def __init__(self, A: sp.csr_matrix, x_nodes: NDArray[np.float64]) -> None:
        self.ml: Any = _hierarchy(A, x_nodes)
        levels = self.ml.levels
        self._A = [_product(level.A) for level in levels[:-1]]
        self._R = [_product(level.R) for level in levels[:-1]]
        self._P = [_product(level.P) for level in levels[:-1]]
        # What the coarse levels' update for later matrices starts from (sim.coarse): the build
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
            from softgrasp.linalg.sparse import BLOCK, BlockGaussSeidel

            for lvl in range(1, len(levels) - 1):
                Ak = levels[lvl].A
                if sp.issparse(Ak) and Ak.format == "bsr" and tuple(Ak.blocksize) == (BLOCK, BLOCK):
                    self._sweeps[lvl] = self._A[lvl] = BlockGaussSeidel(Ak)
        # The coarse levels kept up to date with the contacts (sim.coarse) where the compiled
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
        from softgrasp.backend import compiled

        self._fine = None  # the last matrix's copy by blocks goes before the next one is made
        if self._A:
            self._A[0] = self._sweeps[0] = None

        if compiled():
            from softgrasp.linalg.sparse import fine_smoother

            # The finest level's sweeps, and its products.
            self._fine = fine_smoother(A, threads)
        else:
            self._fine = _ScipyProduct(A)
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


class _ScipyProduct:
    """SciPy's product, where the compiled kernels are not in use (the same interface as
    :class:`~softgrasp.linalg.sparse.CsrProduct`)."""

    def __init__(self, A: Any) -> None:
        self.A = A.tocsr()
        self.shape = self.A.shape
        self.threads = 1

    def __matmul__(self, x: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.asarray(self.A @ x)


def _compiled() -> bool:
    from softgrasp.backend import compiled

    return bool(compiled())


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
    return _ScipyProduct(A)


def _multigrid(A: sp.csr_matrix, x_nodes: NDArray[np.float64], cache: SolverCache) -> _Multigrid:
    """The multigrid preconditioner kept in ``cache`` (built there when there is none or it was
    dropped), its finest level made ``A``, its products on the cores idle now (one thread below
    :data:`MULTIGRID_THREADS_MIN_DOF` unknowns)."""
    A = A.tocsr()
    ml = cache._ml
    if not (isinstance(ml, _Multigrid) and ml.fits(A)):
        ml = cache._ml = _Multigrid(A, x_nodes)
        cache.stats["multigrid_setups"] += 1
    ml.stats = cache.stats
    ml.use(A, pardiso.choose_threads() if A.shape[0] >= MULTIGRID_THREADS_MIN_DOF else 1)
    return ml


def _direct(A: sp.csr_matrix, b: NDArray[np.float64], C: sp.csr_matrix | None):
    with warnings.catch_warnings():
        warnings.simplefilter("error", spla.MatrixRankWarning)
        try:
            if C is None:
                return spla.spsolve(A.tocsc(), b, permc_spec="MMD_AT_PLUS_A"), np.zeros(0)
            k = C.shape[0]
            K = sp.bmat([[A, C.T], [C, None]], format="csc")
            sol = spla.spsolve(K, np.concatenate([b, np.zeros(k)]), permc_spec="MMD_AT_PLUS_A")
        except (spla.MatrixRankWarning, RuntimeError) as exc:
            raise NotConverged(f"static solve failed: {_SINGULAR}") from exc
    if not np.isfinite(sol).all():
        raise NotConverged(f"static solve failed: {_SINGULAR}")
    return sol[: A.shape[0]], sol[A.shape[0] :]


def _cg(
    A: Any,
    b: NDArray[np.float64],
    M: Any,
    proj: Callable[[NDArray[np.float64]], NDArray[np.float64]],
    rtol: float,
    max_it: int,
) -> tuple[NDArray[np.float64], int, bool]:
    """Preconditioned conjugate gradients on ``A x = b`` (``A`` a matrix or a product) in the range
    of ``proj``. Returns (x, the iterations, whether they met negative curvature: then x is the
    progress so far, or the first direction, both descent directions)."""
    x = np.zeros_like(b)
    r = proj(b).copy()  # never modify the caller's vector
    bnorm = float(np.linalg.norm(r))
    if bnorm == 0:
        return x, 0, False
    z = proj(M @ r)
    p = z.copy()
    rz = float(r @ z)
    it = 0
    for it in range(1, max_it + 1):
        Ap = A @ p
        pAp = float(p @ Ap)
        if pAp <= 0:
            return (p.copy() if it == 1 else x), it, True
        alpha = rz / pAp
        x += alpha * p
        r -= alpha * proj(Ap)
        if float(np.linalg.norm(r)) <= rtol * bnorm:
            break
        z = proj(M @ r)
        rz_new = float(r @ z)
        p = z + (rz_new / rz) * p
        rz = rz_new
    return x, it, False


def _pcg(
    A: sp.csr_matrix,
    b: NDArray[np.float64],
    C: sp.csr_matrix | None,
    x_nodes: NDArray[np.float64],
    cache: SolverCache,
    rtol: float | None = None,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Multigrid-preconditioned CG (the hierarchy kept in ``cache`` while it stays effective) to
    the relative residual ``rtol`` (default ``cache.rtol``).
    Where the stiffness is indefinite (a body on the table about to tip, a compressed region
    buckling) CG meets negative curvature: the diagonal is then shifted until it does not
    (Levenberg-Marquardt, as the PARDISO path does), a descent direction close to Newton's."""
    rtol = cache.rtol if rtol is None else rtol
    if C is not None:
        Cd = C.toarray()
        G = np.linalg.inv(Cd @ Cd.T)

        def proj(v: NDArray[np.float64]) -> NDArray[np.float64]:
            return v - Cd.T @ (G @ (Cd @ v))
    else:

        def proj(v: NDArray[np.float64]) -> NDArray[np.float64]:
            return v

    max_it = 400
    for _attempt in range(2):
        M = _multigrid(A, x_nodes, cache)
        x, last, curved = _cg(M.fine, b, M, proj, rtol, max_it)
        it = last
        tau = INDEFINITE_SHIFT
        while curved and tau <= 1.0:
            shifted = (A + sp.diags(tau * np.abs(A.diagonal()))).tocsr()
            xs, its, curved_s = _cg(M.product(shifted), b, M, proj, rtol, max_it)
            it += its
            if not curved_s:
                x, last, curved = xs, its, False
                cache.stats["shifted"] = cache.stats.get("shifted", 0) + 1
            tau *= 10.0
        cache._iterations.append(it)
        if curved or last < max_it:
            if last > 60:
                cache._ml = None  # the hierarchy has gone stale: rebuild next time
            break
        cache._ml = None  # rebuild once with the current matrix, then give up
    else:
        raise NotConverged(f"linear solve did not converge in {max_it} CG iterations: {_SINGULAR}")
    lam = np.zeros(0)
    if C is not None:
        lam = G @ (Cd @ (b - A @ x))  # C^T lam takes the part of b that A dx cannot balance
    return x, lam


def _stale_pcg(
    A: sp.csr_matrix,
    b: NDArray[np.float64],
    f: pardiso.PardisoFactor | _Corrected,
    max_it: int,
    rtol: float = STALE_RTOL,
    keep_last: bool = False,
) -> tuple[NDArray[np.float64] | None, bool]:
    """Conjugate gradients on ``A x = b`` preconditioned by the factorisation ``f`` of a nearby
    matrix. Returns (x, or None when they do not reach ``rtol`` in ``max_it`` iterations or meet
    negative curvature (with ``keep_last``: the last iterate then); whether they met a
    direction p of negative curvature beyond round-off,
    ``p^T A p < -NEGATIVE_CURVATURE_ROUNDOFF n eps max_i sum_j |A_ij| |p|^2``: a proof that A is
    indefinite)."""
    bnorm = float(np.linalg.norm(b))
    if bnorm == 0:
        return np.zeros_like(b), False
    x = f.solve(b)
    r = b - A @ x
    if float(np.linalg.norm(r)) <= rtol * bnorm:
        return x, False
    z = f.solve(r)
    p = z.copy()
    rz = float(r @ z)
    for _ in range(max_it):
        Ap = A @ p
        pAp = float(p @ Ap)
        if not pAp > 0 or not rz > 0:
            # Round-off in p^T A p is at most ~n eps |p|^T |A| |p| <= n eps max_i sum_j |A_ij| |p|^2.
            row_sum = float(abs(A).sum(axis=1).max())
            bound = NEGATIVE_CURVATURE_ROUNDOFF * A.shape[0] * np.finfo(float).eps * row_sum * float(p @ p)
            return (x if keep_last else None), pAp < -bound
        alpha = rz / pAp
        x += alpha * p
        r -= alpha * Ap
        if float(np.linalg.norm(r)) <= rtol * bnorm:
            return x, False
        z = f.solve(r)
        rz_new = float(r @ z)
        p = z + (rz_new / rz) * p
        rz = rz_new
    return (x if keep_last else None), False


def _gmres(
    matvec: Callable[[NDArray[np.float64]], NDArray[np.float64]],
    b: NDArray[np.float64],
    precondition: Callable[[NDArray[np.float64]], NDArray[np.float64]],
    max_it: int,
    rtol: float,
) -> NDArray[np.float64] | None:
    """Right-preconditioned GMRES (no restart) on ``matvec(x) = b``: the true residual is what it
    minimises and what it tests against ``rtol``. None when ``max_it`` iterations do not reach it.
    The Krylov basis is orthogonalised by classical Gram-Schmidt applied twice (as stable as the
    modified one; two matrix-vector products with the basis per iteration instead of a pair of
    vector operations per basis vector: about two thirds of the memory traffic and no Python loop
    over the basis, which BLAS reads)."""
    bnorm = float(np.linalg.norm(b))
    if bnorm == 0:
        return np.zeros_like(b)
    V = np.empty((max_it + 1, b.shape[0]))  # rows touched only as they are used
    V[0] = b / bnorm
    Z: list[NDArray[np.float64]] = []
    R = np.zeros((max_it + 1, max_it))  # the Hessenberg matrix, turned upper triangular
    g = np.zeros(max_it + 1)  # the rotated right-hand side bnorm e1
    g[0] = bnorm
    cs = np.zeros(max_it)
    sn = np.zeros(max_it)
    for k in range(max_it):
        z = precondition(V[k])
        Z.append(z)
        w = np.array(matvec(z), dtype=np.float64)
        h = R[:, k]
        basis = V[: k + 1]
        for _ in range(2):  # classical Gram-Schmidt, twice
            c = basis @ w
            w -= basis.T @ c
            h[: k + 1] += c
        h[k + 1] = float(np.linalg.norm(w))
        breakdown = h[k + 1] <= 1e-14 * bnorm
        # The earlier Givens rotations, then one that zeroes h[k + 1]: the least-squares residual
        # min |H y - bnorm e1| is then |g[k + 1]| (Saad and Schultz).
        for i in range(k):
            h[i], h[i + 1] = cs[i] * h[i] + sn[i] * h[i + 1], cs[i] * h[i + 1] - sn[i] * h[i]
        r = math.hypot(h[k], h[k + 1])
        cs[k], sn[k] = (1.0, 0.0) if r == 0.0 else (h[k] / r, h[k + 1] / r)
        vk = h[k + 1]
        h[k], h[k + 1] = r, 0.0
        g[k], g[k + 1] = cs[k] * g[k], -sn[k] * g[k]
        if abs(g[k + 1]) <= rtol * bnorm or breakdown:
            # The least-squares solution of the triangular system (minimum norm where it is
            # singular: an exact Newton matrix losing its supports), as of the Hessenberg one.
            y = np.linalg.lstsq(R[: k + 1, : k + 1], g[: k + 1], rcond=None)[0]
            x = y[0] * Z[0]
            for yi, zi in zip(y[1:], Z[1:], strict=True):
                x += yi * zi
            return x
        V[k + 1] = w / vk
    return None


def _fast_exact(
    fine: Any, correction: Callable[..., NDArray[np.float64]], v: NDArray[np.float64]
) -> NDArray[np.float64]:
    """The exact Newton product with its matrix part on the multigrid's product of the same
    matrix (compiled, on the threads it was given, where the compiled kernels are in use)."""
    return correction(v, np.asarray(fine @ v))


def _amg_gmres(
    A: sp.csr_matrix,
    b: NDArray[np.float64],
    x_nodes: NDArray[np.float64],
    cache: SolverCache,
    matvec: Callable[[NDArray[np.float64]], NDArray[np.float64]],
    rtol: float,
) -> NDArray[np.float64] | None:
    """GMRES on the exact Newton product preconditioned by a multigrid V-cycle of its symmetric
    approximation A (the hierarchy kept in the cache and rebuilt once when it no longer
    converges); None if it does not converge."""
    for _attempt in range(2):
        M = _multigrid(A, x_nodes, cache)
        product = matvec
        if getattr(matvec, "matrix", None) is A:  # the exact product A v + correction(v)
            product = functools.partial(_fast_exact, M.fine, matvec.correction)  # type: ignore[attr-defined]
        x = _gmres(product, b, M.matvec, AMG_GMRES_MAX_IT, max(rtol, 1e-10))
        if x is not None:
            return x
        cache._ml = None
    return None


class _Corrected:
    """The factorisation of an earlier Newton matrix A0, corrected for the nodes where the current
    matrix A has gained stiffness since (contacts made: a table node touching down adds a penalty
    stiffness ~50 times its own). With E selecting those nodes' unknowns and C the difference of
    A and A0 on them (Woodbury),

        (A0 + E C E^T)^-1 r = y - Z C (I + G C)^-1 y_S,   y = A0^-1 r,  Z = A0^-1 E,  G = E^T Z,

    which is A^-1 r where A differs from A0 only there. Each changed node costs three solves with
    the factor, once per factorisation (the columns of Z are kept in the cache); each application
    one solve and a product with Z. Where stiffness was taken away (a contact lost, the table
    removed) A0 + E C E^T may be nearly singular: the factor is used as it is, and a
    refactorisation follows when it no longer converges.

    Parameters
    ----------
    f: the factorisation of A0.  U: the upper triangle of A in the factor's pattern
    (:meth:`~softgrasp.linalg.pardiso.PardisoFactor.same_pattern`).  cache: where the columns are kept.
    """

    def __init__(self, f: pardiso.PardisoFactor, U: sp.csr_matrix, cache: SolverCache) -> None:
        self._f = f
        self._Z: NDArray[np.float64] | None = None
        self.applications = 0  # solves with it so far
        n = f.n
        base = f.values
        diag = U.indptr[:-1]  # the diagonal leads each row of the sorted upper triangle
        # A contact adds to the diagonal blocks of its nodes: their change flags the nodes.
        ratio = (np.abs(U.data[diag] - base[diag]) / np.maximum(np.abs(base[diag]), 1e-300)).reshape(-1, 3)
        ratio = ratio.max(axis=1)
        nodes = np.flatnonzero(ratio > CORRECT_RTOL)
        if not len(nodes):
            return
        if len(nodes) > CORRECT_MAX_NODES:
            nodes = np.sort(nodes[np.argsort(-ratio[nodes], kind="stable")[:CORRECT_MAX_NODES]])
        S = (3 * nodes[:, None] + np.arange(3)).ravel()
        # C: the difference on S x S, both triangles (from the rows of S in the upper triangle).
        where = np.full(n, -1)
        where[S] = np.arange(len(S))
        seg = np.concatenate([np.arange(U.indptr[r], U.indptr[r + 1]) for r in S])
        rows = np.repeat(where[S], np.diff(U.indptr)[S])
        cols = where[U.indices[seg]]
        keep = cols >= 0
        d = U.data[seg[keep]] - base[seg[keep]]
        C = np.zeros((len(S), len(S)))
        C[rows[keep], cols[keep]] = d
        C[cols[keep], rows[keep]] = d
        ev = np.linalg.eigvalsh(C)
        if ev[0] < -1e-9 * max(abs(ev[-1]), 1e-300):
            return  # stiffness taken away
        count = cache.stats["factorisations"]
        columns: dict[int, NDArray[np.float64]] = {}
        if cache._correction is not None and cache._correction[0] is f and cache._correction[1] == count:
            columns = cache._correction[2]
            if len(columns) > 6 * CORRECT_MAX_NODES:  # two full sets of columns: keep the current ones
                columns = {j: v for j, v in columns.items() if where[j] >= 0}
        new = [int(j) for j in S if int(j) not in columns]
        e = np.zeros(n)
        for j in new:  # one right-hand side a solve: the factor was analysed for one
            e[j] = 1.0
            columns[j] = f.solve(e)
            e[j] = 0.0
        if new:
            cache.stats["correction_columns"] = cache.stats.get("correction_columns", 0) + len(new)
        cache._correction = (f, count, columns)
        Z = np.column_stack([columns[int(j)] for j in S])
        self._S = S
        self._W = C @ np.linalg.inv(np.eye(len(S)) + Z[S, :] @ C)
        self._Z = Z

    @property
    def nodes(self) -> int:
        """How many nodes it corrects for (0: the factor as it is)."""
        return 0 if self._Z is None else len(self._S) // 3

    def solve(self, r: NDArray[np.float64]) -> NDArray[np.float64]:
        """``(A0 + E C E^T)^-1 r``."""
        self.applications += 1
        y = self._f.solve(r)
        if self._Z is None:
            return y
        return y - self._Z @ (self._W @ y[self._S])


#: Conjugate gradients preconditioned by an old factor prove the matrix indefinite when they meet
#: a direction p with ``p^T A p`` below minus this multiple of its round-off bound, n eps times the
#: largest absolute row sum times ``|p|^2`` (at 2 196 nodes the bound is 1.5e-11 of that row sum
#: times ``|p|^2``; a tipping body's lean gave -5.4e-10 of it).
NEGATIVE_CURVATURE_ROUNDOFF = 10.0
#: A solve with an old factor that took more than this fraction of its iteration cap (the cap is
#: half a refactorisation's cost in solves) has the next system refactorise first.
STALE_REFRESH = 0.5
#: A node counts as changed since the factorisation when one of its diagonal entries differs by more
#: than this fraction of its factorised value (a new table contact: ~50 times).
CORRECT_RTOL = 0.5
#: At most this many changed nodes (the largest changes) are corrected for.
CORRECT_MAX_NODES = 24


def _rigid_motion_free(A: sp.csr_matrix, x_nodes: NDArray[np.float64]) -> bool:
    """Whether a rigid translation or rotation of the nodes ``x_nodes`` meets (almost) no stiffness
    in A: nothing holds the body in place (its stiffness is singular)."""
    B = _rigid_modes(x_nodes)
    B /= np.linalg.norm(B, axis=0)
    scale = float(np.abs(A).sum(axis=1).max()) or 1.0  # the largest row sum bounds |A|
    return bool((np.linalg.norm(A @ B, axis=0) < 1e-9 * scale).any())


def _shifted_solve(
    f: pardiso.PardisoFactor,
    A: sp.csr_matrix,
    U: sp.csr_matrix,
    b: NDArray[np.float64],
    cache: SolverCache,
    rtol: float = STALE_RTOL,
) -> NDArray[np.float64]:
    """``(A + tau D)^-1 b`` for an indefinite stiffness A (upper triangle ``U`` in the factor's
    pattern; a body on the table about to tip, a compressed region buckling), D its diagonal's
    magnitudes and tau the first of ``INDEFINITE_SHIFT``, ten times that, ... up to 1 that makes
    it positive definite: the exact Newton step would run towards a saddle, the shifted one
    (Levenberg-Marquardt) is a descent direction for the line search, as conjugate gradients give
    by stopping at negative curvature. Each shift is factorised by Cholesky (which says whether it
    is positive definite); if even tau = 1 is not, its LDL^T is used. A single-precision factor's
    solve is refined by conjugate gradients on the shifted matrix (``A`` both triangles) as
    :func:`_refined` does."""
    diag = U.indptr[:-1]  # the diagonal leads each row of the sorted upper triangle
    scale = np.abs(U.data[diag])
    tau = INDEFINITE_SHIFT
    before = f.factorisations
    while True:
        shifted = U.copy()
        shifted.data[diag] += tau * scale
        if f.refactor_positive(shifted):
            break
        if tau * 10.0 > 1.0:
            f.refactor(shifted, ldlt=True)
            break
        tau *= 10.0
    cache.stats["factorisations"] += f.factorisations - before
    cache._try_stale = True
    cache._excess, cache._fresh = 0, -1  # a shifted matrix's solves say little of the next ones'
    cache.stats["shifted"] = cache.stats.get("shifted", 0) + 1
    # Counted apart from multigrid's shifts: the factorisation's inertia, or conjugate gradients'
    # curvature beyond round-off, proves the matrix indefinite, which multigrid-preconditioned
    # conjugate gradients meeting negative curvature (round-off on a nearly neutral mode) do not.
    cache.stats["indefinite_factor"] = cache.stats.get("indefinite_factor", 0) + 1
    if f.single_precision:
        return _refined((A + sp.diags(tau * scale)).tocsr(), b, f, rtol)
    return f.solve(b)


def _refined(
    A: sp.csr_matrix, b: NDArray[np.float64], f: pardiso.PardisoFactor, rtol: float
) -> NDArray[np.float64]:
    """``A^-1 b`` by the fresh factorisation ``f`` of A itself: a double factor's solve, refined by
    conjugate gradients only where rounding left more than ``rtol``; a single-precision factor's
    solve refined to :data:`REFINED_RTOL` (its last iterate where round-off stops it short)."""
    tol = min(rtol, REFINED_RTOL) if f.single_precision else rtol
    x, _ = _stale_pcg(A, b, f, EXACT_MAX_IT, tol, keep_last=f.single_precision)
    return f.solve(b) if x is None else x


def _pardiso(
    A: sp.csr_matrix,
    b: NDArray[np.float64],
    x_nodes: NDArray[np.float64],
    cache: SolverCache,
    matvec: Callable[[NDArray[np.float64]], NDArray[np.float64]] | None = None,
    rtol: float = STALE_RTOL,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """PARDISO with the analysis reused per pattern and the factorisation reused as a
    preconditioner while it converges in fewer iterations than a refactorisation costs. With
    ``matvec`` (the product with the exact, non-symmetric Newton matrix, of which A is the
    symmetric approximation), GMRES preconditioned by the factorisation of A solves the exact
    system; where it does not converge the approximate step A^-1 b is returned."""
    f = cache._factor
    U = f.same_pattern(A) if f is not None and f.n == A.shape[0] else None
    if U is not None:
        assert f is not None
        before = f.factorisations
        x = None
        indefinite = False  # whether the old factor's conjugate gradients proved A indefinite
        if cache._try_stale and f.ready:
            # As many iterations with the old factor as half a refactorisation costs in solves.
            cap = int(np.clip(0.5 * SOLVE_SPEED_RATIO * f.solves_per_factorisation, 4, 40))
            # The old factor, corrected for the nodes that gained stiffness since.
            solves = f.solves
            pre = _Corrected(f, U, cache)
            if matvec is not None:
                x = _gmres(matvec, b, pre.solve, cap, rtol)
            else:
                x, indefinite = _stale_pcg(A, b, pre, cap, rtol)
            if cache._fresh >= 0:
                cache._excess += max(f.solves - solves - cache._fresh, 0)
            # After a failed attempt, or one that converged at more than a quarter of a
            # refactorisation's cost (the factor only ages), or once the solves the factor's age
            # has cost since it was made add up to a refactorisation's time, the next system
            # refactorises first.
            cache._try_stale = (
                x is not None
                and pre.applications <= STALE_REFRESH * cap
                and cache._excess <= SOLVE_SPEED_RATIO * f.solves_per_factorisation
            )
        if x is not None:
            cache.stats["stale_solves"] += 1
            return x, np.zeros(0)
        if indefinite and not _rigid_motion_free(A, x_nodes):
            # Conjugate gradients proved A indefinite (a body on the table about to tip): the
            # shifted matrix is factorised at once, not A itself first.
            return _shifted_solve(f, A, U, b, cache, rtol), np.zeros(0)
        factored = f.refactor(U, stop_if_indefinite=True)
        if not factored:
            # Cholesky met a non-positive pivot. A body that is held (no rigid motion free, no
            # unknown without stiffness) is tipping or buckling: the shifted matrix next, without
            # the LDL^T that would count the negative pivots. A singular stiffness (a free body, a
            # node that nothing holds) gets that LDL^T, as before (where it perturbed pivots,
            # multigrid solves below).
            if U.data[U.indptr[:-1]].all() and not _rigid_motion_free(A, x_nodes):
                cache.stats["factorisations"] += f.factorisations - before
                return _shifted_solve(f, A, U, b, cache, rtol), np.zeros(0)
            f.refactor(U, ldlt=True)
        cache.stats["factorisations"] += f.factorisations - before
    else:
        # A new pattern (contacts couple nodes that no edge joins, or others than before): analyse
        # the union with the previous pattern, so that both kinds of system reuse it.
        P = A if f is None or f.n != A.shape[0] else pardiso.PardisoFactor.union(A, f.matrix())
        cache._factor = f = pardiso.PardisoFactor(P, single=cache.precision == "mixed")
        cache.stats["analyses"] += 1
        cache.stats["factorisations"] += f.factorisations
    cache._try_stale = True
    if f.negative_pivots > 0 and f.perturbed_pivots == 0:
        return _shifted_solve(f, A, f.matrix(), b, cache, rtol), np.zeros(0)
    solves = f.solves
    cache._excess, cache._fresh = 0, -1  # until this factor's own system is solved
    x = _fresh_solve(A, b, x_nodes, cache, f, matvec, rtol)
    cache._fresh = f.solves - solves
    return x, np.zeros(0)


def _fresh_solve(
    A: sp.csr_matrix,
    b: NDArray[np.float64],
    x_nodes: NDArray[np.float64],
    cache: SolverCache,
    f: pardiso.PardisoFactor,
    matvec: Callable[[NDArray[np.float64]], NDArray[np.float64]] | None,
    rtol: float,
) -> NDArray[np.float64]:
    """``A x = b`` with ``f`` the factorisation of A itself (just made): GMRES on the exact
    product ``matvec`` where given, else the factor's solve refined (:func:`_refined`); a singular
    stiffness by multigrid-preconditioned CG."""
    if matvec is not None and f.perturbed_pivots == 0:
        x = _gmres(matvec, b, f.solve, EXACT_MAX_IT, rtol)
        if x is not None:
            return x
    if f.perturbed_pivots > 0:
        # A singular stiffness (a body not yet held may slide or spin): the factor would blow the
        # free motions up; multigrid-CG finds the solution orthogonal to them (the factor's
        # analysis is kept for the next system).
        cache.stats["amg_solves"] += 1
        return _pcg(A, b, None, x_nodes, cache)[0]
    # The factor of A itself: one solve, refined by a few conjugate-gradient steps where rounding
    # in the factor left more than the tolerance (the solves do no iterative refinement).
    return _refined(A, b, f, rtol)


def _uses_pardiso(n: int, cache: SolverCache) -> bool:
    """Whether an unconstrained system of ``n`` unknowns goes to PARDISO."""
    return cache.method == "pardiso" or (
        cache.method == "auto" and n <= PARDISO_MAX_DOF and pardiso.available()
    )


def _check_method(cache: SolverCache) -> None:
    if cache.method not in ("auto", "pardiso", "direct", "amg", "reference"):
        raise ValueError(f"unknown linear solver {cache.method!r}")


def _route(n: int, C: sp.csr_matrix | None, cache: SolverCache) -> str:
    """Where a Newton system of ``n`` unknowns (``C`` its constraints, or None) goes first:
    ``"direct"`` (SciPy's sparse LU or the saddle-point solve), ``"pardiso"`` or ``"multigrid"``
    (multigrid-preconditioned Krylov iterations). Constraints are only used where the stiffness
    leaves rigid motions free; multigrid cannot precondition such a singular matrix, so those
    systems go to the direct saddle-point solve."""
    _check_method(cache)
    if C is not None or cache.method == "direct":
        return "direct"
    if cache.method == "reference":
        # softgrasp's first solver, kept as the reference of the benchmarks and tests: the
        # symmetrised Newton matrix, sparse LU up to DIRECT_MAX_DOF unknowns, multigrid-CG beyond.
        return "direct" if n <= DIRECT_MAX_DOF else "multigrid"
    if _uses_pardiso(n, cache):
        return "pardiso"
    return "direct" if cache.method == "auto" and n <= DIRECT_MAX_DOF else "multigrid"


def by_multigrid(n: int, cache: SolverCache) -> bool:
    """Whether an unconstrained Newton system of ``n`` unknowns that ``cache`` solves goes first to
    the multigrid-preconditioned Krylov iterations (not PARDISO's or SciPy's direct factors; a
    singular system PARDISO hands on to multigrid does not count)."""
    return _route(n, None, cache) == "multigrid"


def assembly_threads(n: int, cache: SolverCache) -> int:
    """Threads for assembling a Newton matrix of ``n`` unknowns that ``cache`` will solve: the
    idle cores where the system goes to multigrid with at least :data:`MULTIGRID_THREADS_MIN_DOF`
    unknowns (as its products), one otherwise (PARDISO's OpenMP threads may still be spinning on
    the other core)."""
    if n < MULTIGRID_THREADS_MIN_DOF or _uses_pardiso(n, cache):
        return 1
    return pardiso.choose_threads()


def solve_newton_system(
    A: sp.csr_matrix,
    b: NDArray[np.float64],
    C: sp.csr_matrix | None,
    x_nodes: NDArray[np.float64],
    cache: SolverCache | None = None,
    *,
    matvec: Callable[[NDArray[np.float64]], NDArray[np.float64]] | None = None,
    rtol: float | None = None,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Solve ``A dx + C^T lam = b, C dx = 0``.

    Parameters
    ----------
    A: (n, n) sparse symmetric stiffness.  b: (n,) right-hand side (the unbalanced forces).
    C: optional (k, n) constraint rows.  x_nodes: (n/3, 3) node positions (rigid modes for AMG).
    cache: reusable solver state; a fresh one if None.
    matvec: the product with the exact Newton matrix where A is only its symmetric
        approximation (without constraints: GMRES on the exact system, preconditioned by the
        factorisation of A or a multigrid V-cycle of it). Where it has ``matrix`` (A itself) and
        ``correction(v, out)`` (adding to ``out = A v`` the rest of the exact product), the
        multigrid path applies A with its own product.
    rtol: relative residual the iterative parts must reach (an inexact Newton iteration's forcing
        term); default :data:`STALE_RTOL`. Direct solves are exact regardless.

    Returns
    -------
    (dx (n,), lam (k,))
    """
    cache = cache if cache is not None else SolverCache()
    route = _route(A.shape[0], C, cache)
    if cache.precision not in ("mixed", "double"):
        raise ValueError(f"unknown factor precision {cache.precision!r} (use 'mixed' or 'double')")
    cache.stats["systems"] += 1
    with pardiso.blas_one_thread() if route == "pardiso" else contextlib.nullcontext():
        return _solve_newton_system(A, b, C, x_nodes, cache, matvec, rtol, route)


def _solve_newton_system(
    A: sp.csr_matrix,
    b: NDArray[np.float64],
    C: sp.csr_matrix | None,
    x_nodes: NDArray[np.float64],
    cache: SolverCache,
    matvec: Callable[[NDArray[np.float64]], NDArray[np.float64]] | None,
    rtol: float | None,
    route: str,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    if route == "direct":
        return _direct(A, b, C)
    if route == "pardiso":
        return _pardiso(A.tocsr(), b, x_nodes, cache, matvec, STALE_RTOL if rtol is None else min(rtol, 1e-2))
    cache.stats["amg_solves"] += 1
    if cache.method == "reference":
        return _pcg(A.tocsr(), b, C, x_nodes, cache)
    if matvec is not None:
        x = _amg_gmres(A.tocsr(), b, x_nodes, cache, matvec, STALE_RTOL if rtol is None else rtol)
        if x is not None:
            return x, np.zeros(0)
    # Conjugate gradients to the Newton iteration's forcing term, as GMRES above (the body's
    # settle at 27 749 nodes: 745 -> 581 V-cycles, 36 -> 30 s).
    return _pcg(A.tocsr(), b, C, x_nodes, cache, None if rtol is None else max(rtol, cache.rtol))
