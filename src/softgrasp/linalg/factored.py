"""Newton systems solved with MKL PARDISO's factorisations, reused while they still pay.

The ordering and symbolic factorisation are done once per sparsity pattern (the body's pattern
does not change between Newton iterations, load steps and holding steps). Each system first tries
a few conjugate-gradient iterations preconditioned by the factorisation it already has (a Newton
matrix changes little from one iteration to the next), corrected by the Woodbury formula for the
few nodes that have gained much stiffness since (contacts made, :class:`_Corrected`), and is
refactorised numerically only when they do not converge fast enough: how fast is judged by
operation counts (:data:`SOLVE_SPEED_RATIO`), not timings, so that the solver path, and with
friction the equilibrium, does not depend on the machine's load. An indefinite matrix (a body
about to tip) is solved shifted (Levenberg-Marquardt), a singular one (a body not yet held) by
multigrid-preconditioned CG.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from softgrasp.errors import NotConverged
from softgrasp.linalg import pardiso
from softgrasp.linalg.krylov import (
    INDEFINITE_SHIFT,
    STALE_RTOL,
    gmres,
    stale_pcg,
)
from softgrasp.linalg.multigrid.hierarchy import rigid_modes
from softgrasp.linalg.multigrid.krylov import pcg

if TYPE_CHECKING:
    from softgrasp.linalg.solve import SolverCache

__all__ = ["pardiso_solve"]

#: GMRES iterations allowed with a fresh factorisation on the exact (non-symmetric) Newton matrix.
EXACT_MAX_IT = 20
#: Relative residual to which a single-precision factor's solves of its own matrix are refined
#: (conjugate gradients against the double-precision matrix): as exact as a double factor's
#: direct solve, whatever the Newton iteration's forcing term (the calibration's fits difference
#: simulated forces).
REFINED_RTOL = 1e-11
#: Time of a solve with a factor over the time of its factorisation, per unit of their operation
#: counts' ratio (PARDISO's factorisation flops over 4 flops per factor non-zero): the solve is
#: memory-bound, the factorisation runs at BLAS-3 speed. It sets how many iterations an old
#: factor may take before a refactorisation is cheaper: from operation counts, not timings, so
#: that a plan's solver path, and with friction its equilibrium, does not depend on the machine's
#: load.
SOLVE_SPEED_RATIO = 0.25
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
    B = _unit_rigid_modes(x_nodes)
    return bool((np.linalg.norm(A @ B, axis=0) < 1e-9 * _norm_bound(A)).any())


def _unit_rigid_modes(x_nodes: NDArray[np.float64]) -> NDArray[np.float64]:
    """The six rigid-body modes of the nodes (:func:`rigid_modes`), each of unit length."""
    B = rigid_modes(x_nodes)
    return B / np.linalg.norm(B, axis=0)


def _norm_bound(A: sp.csr_matrix) -> float:
    """The largest absolute row sum of A, which bounds its norm (1 for a zero matrix)."""
    return float(np.abs(A).sum(axis=1).max()) or 1.0


#: A translation is free when the stiffness's product with it is below this fraction of the
#: stiffness's largest row sum (round-off: nothing couples the body to anything that stays put).
FREE_TRANSLATION_RTOL = 1e-12
#: ... and the load pushes the body along it when its share of the load's norm exceeds this.
FREE_LOAD_RTOL = 1e-6


def _load_along_free_translation(
    A: sp.csr_matrix, b: NDArray[np.float64], x_nodes: NDArray[np.float64]
) -> str:
    """The axis ("x", "y", "z") of a translation that meets no stiffness in A while the load b
    pushes the body along it (then ``A x = b`` has no solution: nothing holds the body against
    that load), or "" if there is none."""
    nb = float(np.linalg.norm(b))
    if nb == 0.0:
        return ""
    T = _unit_rigid_modes(x_nodes)[:, :3]  # the three translations
    free = np.linalg.norm(A @ T, axis=0) < FREE_TRANSLATION_RTOL * _norm_bound(A)
    pushed = np.abs(T.T @ b) > FREE_LOAD_RTOL * nb
    hit = np.flatnonzero(free & pushed)
    return "xyz"[int(hit[0])] if len(hit) else ""


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
    x, _ = stale_pcg(A, b, f, EXACT_MAX_IT, tol, keep_last=f.single_precision)
    return f.solve(b) if x is None else x


def pardiso_solve(
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
                x = gmres(matvec, b, pre.solve, cap, rtol)
            else:
                x, indefinite = stale_pcg(A, b, pre, cap, rtol)
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
        x = gmres(matvec, b, f.solve, EXACT_MAX_IT, rtol)
        if x is not None:
            return x
    if f.perturbed_pivots > 0:
        # A singular stiffness (a body not yet held may slide or spin): the factor would blow the
        # free motions up; multigrid-CG finds the solution orthogonal to them (the factor's
        # analysis is kept for the next system). A load along a translation that nothing resists
        # (every contact lost) has no solution at all: said at once, not after the iterations.
        if axis := _load_along_free_translation(A, b, x_nodes):
            cache.stats["free_translations"] = cache.stats.get("free_translations", 0) + 1
            raise NotConverged(
                f"the load pushes the body along {axis} and nothing resists that translation: "
                "the body is not held"
            )
        cache.stats["amg_solves"] += 1
        return pcg(A, b, x_nodes, cache)
    # The factor of A itself: one solve, refined by a few conjugate-gradient steps where rounding
    # in the factor left more than the tolerance (the solves do no iterative refinement).
    return _refined(A, b, f, rtol)


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
