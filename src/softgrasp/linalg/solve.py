"""Linear solves of the Newton systems ``A dx = b`` with optional constraints ``C dx = 0``.

A is the stiffness (minus the force Jacobian): symmetric and, away from buckling, positive definite
on the constraint null space. :func:`solve_newton_system` sends each system one of three ways
(:func:`_route`), chosen by its size, what is installed and :attr:`SolverCache.method`:

* **PARDISO** (MKL's sparse direct solver) up to :data:`PARDISO_MAX_DOF` unknowns, its
  factorisations reused across systems while they still pay (:mod:`softgrasp.linalg.factored`);
* SciPy's sparse LU of the saddle-point system for constrained systems (and small systems without
  MKL);
* Krylov iterations preconditioned by smoothed-aggregation algebraic multigrid (pyamg) with the
  rigid-body modes as near-null space, the standard scalable solver for elasticity, for the
  largest systems and where MKL is missing (:mod:`softgrasp.linalg.multigrid.krylov`).

All of it lives in a :class:`SolverCache` that the callers keep across the solves of one loading.
"""

from __future__ import annotations

import contextlib
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
from softgrasp.linalg.factored import _rigid_motion_free as _rigid_motion_free  # sim.static's
from softgrasp.linalg.factored import pardiso_solve
from softgrasp.linalg.krylov import SINGULAR, STALE_RTOL
from softgrasp.linalg.multigrid.krylov import MULTIGRID_THREADS_MIN_DOF, amg_gmres, pcg
from softgrasp.linalg.threads import choose_threads

__all__ = ["SolverCache", "solve_newton_system", "by_multigrid", "DIRECT_MAX_DOF", "PARDISO_MAX_DOF"]

#: The message for a stiffness that does not hold the body (sim.static's too).
_SINGULAR = SINGULAR

#: Without MKL, systems with at most this many unknowns are solved by sparse LU.
DIRECT_MAX_DOF = 1500
#: Systems with at most this many unknowns are factorised by PARDISO where MKL is installed
#: (beyond, the factor's memory and time grow faster than multigrid's; below, PARDISO's plans take
#: fewer Newton systems and less time).
PARDISO_MAX_DOF = 30_000


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
        same rests to the Newton tolerance, but where the rest is a branch choice (a Newton
        iterate within rounding of the tolerance on an indefinite matrix: a compressed softening
        cube about to buckle) float32 rounding makes that choice noisy; the material tests, whose
        curves the calibration fits difference, use ``"double"``.
    exact_body: whether Newton factorises the body's exact matrix where it would otherwise
        approximate it (a nodal body above
        :data:`~softgrasp.physics.body.NODAL_DIRECT_MAX_NODES` nodes:
        :meth:`~softgrasp.physics.body.Body.newton_jacobian`).
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
    exact_body: bool = False
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
        would keep the removed stiffness and precondition the new systems poorly)."""
        self._try_stale = False
        self._ml = None


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
    thread count (:func:`~softgrasp.linalg.threads.choose_threads`) where the system goes to
    multigrid with at least :data:`MULTIGRID_THREADS_MIN_DOF` unknowns (as its products), one
    otherwise (PARDISO's OpenMP threads may still be spinning on
    the other core)."""
    if n < MULTIGRID_THREADS_MIN_DOF or _uses_pardiso(n, cache):
        return 1
    return choose_threads()


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
        stale_rtol = STALE_RTOL if rtol is None else min(rtol, 1e-2)
        return pardiso_solve(A.tocsr(), b, x_nodes, cache, matvec, stale_rtol)
    cache.stats["amg_solves"] += 1
    if cache.method == "reference":
        return pcg(A.tocsr(), b, x_nodes, cache), np.zeros(0)
    if matvec is not None:
        x = amg_gmres(A.tocsr(), b, x_nodes, cache, matvec, STALE_RTOL if rtol is None else rtol)
        if x is not None:
            return x, np.zeros(0)
    # Conjugate gradients to the Newton iteration's forcing term, as GMRES above.
    x = pcg(A.tocsr(), b, x_nodes, cache, None if rtol is None else max(rtol, cache.rtol))
    return x, np.zeros(0)


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
            raise NotConverged(f"static solve failed: {SINGULAR}") from exc
    if not np.isfinite(sol).all():
        raise NotConverged(f"static solve failed: {SINGULAR}")
    return sol[: A.shape[0]], sol[A.shape[0] :]
