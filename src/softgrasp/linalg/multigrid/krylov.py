"""Krylov solves of the large Newton systems preconditioned by the multigrid V-cycle.

The V-cycle (:class:`~softgrasp.linalg.multigrid.cycle.Multigrid`) is kept in the caller's
:class:`~softgrasp.linalg.solve.SolverCache` while it preconditions well and rebuilt when it no
longer does. :func:`pcg` runs conjugate gradients (SciPy's, :func:`softgrasp.linalg.krylov.cg`) on
the symmetric stiffness, shifting an indefinite one's diagonal until it is positive
(Levenberg-Marquardt); :func:`amg_gmres` runs GMRES on the exact, non-symmetric Newton product.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from softgrasp.errors import NotConverged
from softgrasp.linalg.krylov import INDEFINITE_SHIFT, SINGULAR, cg, gmres
from softgrasp.linalg.multigrid.cycle import Multigrid
from softgrasp.linalg.threads import choose_threads

if TYPE_CHECKING:
    from softgrasp.linalg.solve import SolverCache

__all__ = ["amg_gmres", "multigrid", "pcg"]

#: GMRES iterations allowed with a multigrid preconditioner on the exact Newton matrix.
AMG_GMRES_MAX_IT = 80
#: Conjugate-gradient iterations allowed with a multigrid preconditioner.
PCG_MAX_IT = 400
#: Iterations beyond which a hierarchy counts as stale: the next system builds a new one.
STALE_HIERARCHY_IT = 60
#: Systems with fewer unknowns run the multigrid products and sweeps on one thread: a second
#: gains nothing there and would compete with PARDISO's spinning threads where a singular system
#: falls back to multigrid.
MULTIGRID_THREADS_MIN_DOF = 20_000


def multigrid(A: sp.csr_matrix, x_nodes: NDArray[np.float64], cache: SolverCache) -> Multigrid:
    """The multigrid preconditioner kept in ``cache`` (built there when there is none or it was
    dropped), its finest level made ``A``, its products on :func:`choose_threads` threads (one
    below :data:`MULTIGRID_THREADS_MIN_DOF` unknowns)."""
    A = A.tocsr()
    ml = cache._ml
    if not (isinstance(ml, Multigrid) and ml.fits(A)):
        ml = cache._ml = Multigrid(A, x_nodes)
        cache.stats["multigrid_setups"] += 1
    ml.stats = cache.stats
    ml.use(A, choose_threads() if A.shape[0] >= MULTIGRID_THREADS_MIN_DOF else 1)
    return ml


def pcg(
    A: sp.csr_matrix,
    b: NDArray[np.float64],
    x_nodes: NDArray[np.float64],
    cache: SolverCache,
    rtol: float | None = None,
) -> NDArray[np.float64]:
    """Multigrid-preconditioned CG (the hierarchy kept in ``cache`` while it stays effective) to
    the relative residual ``rtol`` (default ``cache.rtol``).

    Where the stiffness is indefinite (a body on the table about to tip, a compressed region
    buckling) CG meets negative curvature: the diagonal is then shifted until it does not
    (Levenberg-Marquardt, as the PARDISO path does), a descent direction close to Newton's. Where
    they do not converge, or break down (:func:`~softgrasp.linalg.krylov.cg`), the hierarchy is
    built anew on this matrix and they run once more; then NotConverged is raised."""
    rtol = cache.rtol if rtol is None else rtol
    failure = ""
    for _attempt in range(2):
        M = multigrid(A, x_nodes, cache)
        try:
            x, last, curved = cg(M.fine, b, M, rtol, PCG_MAX_IT)
            it = last
            tau = INDEFINITE_SHIFT
            while curved and tau <= 1.0:
                shifted = (A + sp.diags(tau * np.abs(A.diagonal()))).tocsr()
                xs, its, curved_s = cg(M.product(shifted), b, M, rtol, PCG_MAX_IT)
                it += its
                if not curved_s:
                    x, last, curved = xs, its, False
                    cache.stats["shifted"] = cache.stats.get("shifted", 0) + 1
                tau *= 10.0
        except NotConverged as exc:
            failure = str(exc)
            cache._ml = None  # rebuild once with the current matrix, then give up
            continue
        cache._iterations.append(it)
        if curved or last < PCG_MAX_IT:
            if last > STALE_HIERARCHY_IT:
                cache._ml = None  # the hierarchy has gone stale: rebuild next time
            return x
        failure = f"linear solve did not converge in {PCG_MAX_IT} CG iterations: {SINGULAR}"
        cache._ml = None  # rebuild once with the current matrix, then give up
    raise NotConverged(failure)


def _fast_exact(
    fine: Any, correction: Callable[..., NDArray[np.float64]], v: NDArray[np.float64]
) -> NDArray[np.float64]:
    """The exact Newton product with its matrix part on the multigrid's product of the same
    matrix (compiled, on the threads it was given, where the compiled kernels are in use)."""
    return correction(v, np.asarray(fine @ v))


def amg_gmres(
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
        M = multigrid(A, x_nodes, cache)
        product = matvec
        if getattr(matvec, "matrix", None) is A:  # the exact product A v + correction(v)
            product = functools.partial(_fast_exact, M.fine, matvec.correction)  # type: ignore[attr-defined]
        x = gmres(product, b, M.matvec, AMG_GMRES_MAX_IT, max(rtol, 1e-10))
        if x is not None:
            return x
        cache._ml = None
    return None
