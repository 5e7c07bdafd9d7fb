"""Linear solves of the Newton systems ``A dx = b`` with optional constraints ``C dx = 0``.

A is the stiffness (minus the force Jacobian): symmetric and, away from buckling, positive definite
on the constraint null space. Small systems are solved directly (sparse LU of the saddle-point
system). Large ones use conjugate gradients preconditioned by smoothed-aggregation algebraic
multigrid (pyamg) with the rigid-body modes as near-null space — the standard scalable solver for
elasticity — with the constraints enforced by projection. The multigrid hierarchy is kept in a
:class:`SolverCache` and reused while it still preconditions well.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from numpy.typing import NDArray

from softgrasp.errors import NotConverged

__all__ = ["SolverCache", "solve_newton_system", "DIRECT_MAX_DOF"]

#: Systems with at most this many unknowns are solved by sparse LU.
DIRECT_MAX_DOF = 1500

_SINGULAR = (
    "the stiffness matrix is singular, so the body is not held in place (it could slide, spin or "
    "fall freely); add support (table friction, contacts) or constraints"
)


@dataclass
class SolverCache:
    """Reusable state of the iterative solver across Newton iterations and load steps.

    Attributes
    ----------
    method: ``"auto"`` (direct up to :data:`DIRECT_MAX_DOF` unknowns), ``"direct"`` or ``"amg"``.
    rtol: relative tolerance of the iterative solve.
    """

    method: str = "auto"
    rtol: float = 1e-10
    _ml: object | None = field(default=None, repr=False)
    _iterations: list[int] = field(default_factory=list, repr=False)

    @property
    def iterations(self) -> list[int]:
        """CG iterations of each iterative solve so far."""
        return self._iterations


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


def _pcg(
    A: sp.csr_matrix,
    b: NDArray[np.float64],
    C: sp.csr_matrix | None,
    x_nodes: NDArray[np.float64],
    cache: SolverCache,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    import pyamg

    if C is not None:
        Cd = C.toarray()
        G = np.linalg.inv(Cd @ Cd.T)

        def proj(v: NDArray[np.float64]) -> NDArray[np.float64]:
            return v - Cd.T @ (G @ (Cd @ v))
    else:

        def proj(v: NDArray[np.float64]) -> NDArray[np.float64]:
            return v

    for _attempt in range(2):
        if cache._ml is None:
            cache._ml = pyamg.smoothed_aggregation_solver(
                A, B=_rigid_modes(x_nodes), symmetry="symmetric", max_coarse=300, coarse_solver="splu"
            )
        M = cache._ml.aspreconditioner(cycle="V")  # type: ignore[attr-defined]
        x = np.zeros_like(b)
        r = proj(b).copy()  # never modify the caller's vector
        bnorm = float(np.linalg.norm(r))
        if bnorm == 0:
            return x, np.zeros(0 if C is None else C.shape[0])
        z = proj(M @ r)
        p = z.copy()
        rz = float(r @ z)
        max_it = 400
        it = 0
        for it in range(1, max_it + 1):
            Ap = A @ p
            pAp = float(p @ Ap)
            if pAp <= 0:
                # Negative curvature (buckling): return the progress so far, or the direction itself,
                # both descent directions for the Newton line search.
                if it == 1:
                    x = p.copy()
                break
            alpha = rz / pAp
            x += alpha * p
            r -= alpha * proj(Ap)
            if float(np.linalg.norm(r)) <= cache.rtol * bnorm:
                break
            z = proj(M @ r)
            rz_new = float(r @ z)
            p = z + (rz_new / rz) * p
            rz = rz_new
        cache._iterations.append(it)
        if it < max_it:
            if it > 60:
                cache._ml = None  # the hierarchy has gone stale: rebuild next time
            break
        cache._ml = None  # rebuild once with the current matrix, then give up
    else:
        raise NotConverged(f"linear solve did not converge in {max_it} CG iterations: {_SINGULAR}")
    lam = np.zeros(0)
    if C is not None:
        lam = G @ (Cd @ (b - A @ x))  # C^T lam takes the part of b that A dx cannot balance
    return x, lam


def solve_newton_system(
    A: sp.csr_matrix,
    b: NDArray[np.float64],
    C: sp.csr_matrix | None,
    x_nodes: NDArray[np.float64],
    cache: SolverCache | None = None,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Solve ``A dx + C^T lam = b, C dx = 0``.

    Parameters
    ----------
    A: (n, n) sparse symmetric stiffness.  b: (n,) right-hand side (the unbalanced forces).
    C: optional (k, n) constraint rows.  x_nodes: (n/3, 3) node positions (rigid modes for AMG).
    cache: reusable solver state; a fresh one if None.

    Returns
    -------
    (dx (n,), lam (k,))
    """
    cache = cache or SolverCache()
    # Constraints are only used where the stiffness leaves rigid motions free; multigrid cannot
    # precondition such a singular matrix, so those systems go to the direct saddle-point solve.
    direct = (
        cache.method == "direct" or C is not None or (cache.method == "auto" and A.shape[0] <= DIRECT_MAX_DOF)
    )
    if direct:
        return _direct(A, b, C)
    return _pcg(A.tocsr(), b, C, x_nodes, cache)
