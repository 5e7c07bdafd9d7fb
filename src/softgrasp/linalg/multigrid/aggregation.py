"""The smoothed-aggregation hierarchy of a Newton matrix: pyamg's steps, the finest Galerkin product
compiled.

The multigrid path's hierarchy is pyamg's classical smoothed aggregation with the options
:func:`softgrasp.linalg.solve._hierarchy` asks for (symmetric strength with no threshold,
standard aggregation, the candidates improved by four symmetric block Gauss-Seidel sweeps on the
finest level, Jacobi-smoothed prolongators with omega 4/3, R = P^T, coarsening down to
``max_coarse`` block rows). Here each level is built by the same pyamg functions in the same order
(the same random draws for the spectral radius estimates), except the finest level's Galerkin
product ``P^T A P``: pyamg forms it as ``(R A) P`` through SciPy's products on one thread
(0.48-0.60 s of a 1.2-1.4 s set-up at 27 749 nodes), here
:func:`softgrasp.linalg.multigrid.galerkin.galerkin_product` (0.2 s), the same operator to the rounding of
reordered sums. The finest level's aggregates and prolongator are pyamg's to the bit; the second
level's are not always: SciPy's product leaves each row's blocks in the order it reached them,
this one in column order, and the greedy aggregation depends on that order (on the 7 295-node
foam cube 48 second-level aggregates differ, its operator by 7.6 %; the multigrid converges alike).
Coarser levels are small and keep SciPy's products. The finest candidates' Gauss-Seidel sweeps
are compiled too, with pyamg's arithmetic to the bit (:mod:`softgrasp.linalg.multigrid.candidates`), and the
spectral radius estimate that weights each prolongator's smoothing runs pyamg's Arnoldi process
on softgrasp's compiled products: the same estimate to rounding (so the prolongators are pyamg's
to rounding), 0.19-0.34 -> 0.12 s on the finest level at 32 543 nodes.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

__all__ = ["smoothed_aggregation"]

#: The finest level's candidate improvement: pyamg's default (relaxation on A B = 0).
IMPROVE_CANDIDATES = ("block_gauss_seidel", {"sweep": "symmetric", "iterations": 4})
#: The prolongators' smoothing: pyamg's default damping of the Jacobi step.
OMEGA = 4.0 / 3.0
#: pyamg's estimate of the spectral radius that weights it (``approximate_spectral_radius``'s
#: defaults): the dominant Ritz pair's relative residual that ends it, the Arnoldi steps of a run,
#: the restarts.
RHO_TOL = 0.01
RHO_STEPS = 15
RHO_RESTARTS = 5


def smoothed_aggregation(
    A: sp.csr_matrix,
    B: NDArray[np.float64],
    max_coarse: int,
    coarse_solver: str,
    presmoother: tuple,
    postsmoother: tuple,
    max_levels: int = 10,
) -> Any:
    """pyamg's ``smoothed_aggregation_solver(A, B, symmetry="symmetric", max_coarse=...,
    coarse_solver=..., presmoother=..., postsmoother=...)`` with its other options at their
    defaults, the finest Galerkin product compiled where ``A`` is CSR and its prolongator has
    1 x 6 blocks (six near-null modes). Returns pyamg's ``MultilevelSolver``."""
    from pyamg.aggregation import fit_candidates, standard_aggregation
    from pyamg.multilevel import MultilevelSolver
    from pyamg.relaxation.smoothing import change_smoothers
    from pyamg.relaxation.utils import relaxation_as_linear_operator
    from pyamg.strength import symmetric_strength_of_connection
    from pyamg.util.utils import get_blocksize

    from softgrasp.linalg.multigrid.galerkin import galerkin_product

    A = sp.csr_matrix(A, dtype=np.float64) if A.format not in ("csr", "bsr") else A
    A.symmetry = "symmetric"
    B = np.asarray(B, dtype=np.float64)
    levels = [MultilevelSolver.Level()]
    levels[0].A, levels[0].B = A, B
    while len(levels) < max_levels and int(A.shape[0] / get_blocksize(A)) > max_coarse:
        C = symmetric_strength_of_connection(A)
        aggregates, _ = standard_aggregation(C)
        if len(levels) == 1:
            if (
                A.format == "csr"
                and A.dtype == np.float64
                and B.shape[1] == 6
                and _sweeps_compiled(IMPROVE_CANDIDATES)
            ):
                B = _improved_candidates(A, B)
            else:
                zero = np.zeros((A.shape[0], 1), dtype=A.dtype)
                B = relaxation_as_linear_operator(IMPROVE_CANDIDATES, A, zero) @ B
            levels[-1].B = B
        T, B = fit_candidates(aggregates, B)
        P = _smoothed_prolongator(A, T)
        R = P.T
        levels[-1].P, levels[-1].R = P, R
        if A.format == "csr" and P.format == "bsr" and tuple(P.blocksize) == (1, 6):
            A = galerkin_product(A, P)
        else:
            A = R @ A @ P
        A.symmetry = "symmetric"
        levels.append(MultilevelSolver.Level())
        levels[-1].A, levels[-1].B = A, B
    ml = MultilevelSolver(levels, coarse_solver=coarse_solver)
    change_smoothers(ml, presmoother, postsmoother)
    return ml


def _improved_candidates(A: sp.csr_matrix, B: NDArray[np.float64]) -> NDArray[np.float64]:
    """The candidates ``B`` (n, 6) after :data:`IMPROVE_CANDIDATES`' symmetric Gauss-Seidel sweeps
    on ``A x = 0``: pyamg's ``relaxation_as_linear_operator(IMPROVE_CANDIDATES, A, 0) @ B`` (for a
    CSR ``A`` its block sweep is the scalar one), to the bit, all six in each pass over a row."""
    from softgrasp.linalg.multigrid.candidates import gauss_seidel_columns

    X = np.array(B, dtype=np.float64, order="C")
    gauss_seidel_columns(A.indptr, A.indices, A.data, X, int(IMPROVE_CANDIDATES[1]["iterations"]))
    return X


def _sweeps_compiled(method: tuple) -> bool:
    """Whether :func:`_improved_candidates` is ``method``: pyamg's (block) Gauss-Seidel with
    symmetric sweeps (for a CSR matrix its block sweep is the scalar one)."""
    name, options = method
    return (
        name in ("gauss_seidel", "block_gauss_seidel")
        and set(options) <= {"sweep", "iterations"}
        and (options.get("sweep") == "symmetric")
    )


def _smoothed_prolongator(A: Any, T: Any) -> Any:
    """pyamg's ``jacobi_prolongation_smoother(A, T, C, B, omega=OMEGA)`` with its defaults (the
    point diagonal D, one step, no filtering): ``P = T - (omega / rho) D^-1 A T``, ``rho`` the
    spectral radius of ``D^-1 A`` as pyamg estimates it (:func:`_spectral_radius`)."""
    from pyamg.util.utils import get_diagonal, scale_rows

    D_inv = np.asarray(get_diagonal(A, inv=True), dtype=np.float64)
    rho = _spectral_radius(A, D_inv)
    D_inv_S = scale_rows(A, D_inv, copy=True)
    D_inv_S = (OMEGA / rho) * D_inv_S
    return T - (D_inv_S @ T)


def _spectral_radius(A: Any, D_inv: NDArray[np.float64]) -> float:
    """pyamg's ``approximate_spectral_radius(D^-1 A)`` (``D_inv`` the inverted diagonal): the
    same random start from NumPy's global generator (the same draws consumed), Arnoldi by modified
    Gram-Schmidt over :data:`RHO_STEPS` steps, restarted from the dominant Ritz vector until its
    residual is below :data:`RHO_TOL` of the Ritz value, at most :data:`RHO_RESTARTS` times (in
    complex arithmetic where that vector is complex, as pyamg's). The products ``A v`` are
    softgrasp's compiled ones (by node blocks on the finest level, by 6 x 6 blocks below, on
    Numba's threads) instead of SciPy's one-thread rows, and the basis is kept in one array: the
    same estimate to rounding, in a third of the time. (Where ``D^-1 A`` is far from normal,
    diagonal contrasts of 1e8, pyamg's estimate itself moves by ~1e-2 with rounding.)"""
    import numba
    from scipy.linalg import eig

    from softgrasp.linalg.sparse import NodeBlockProduct, node_blocks, product

    threads = numba.get_num_threads()
    blocks = node_blocks(A) if A.format == "csr" else None
    op = NodeBlockProduct(A, blocks, threads) if blocks is not None else product(A, threads)

    def apply(v: NDArray) -> NDArray:  # D^-1 A v, for a complex v by its two parts
        if np.iscomplexobj(v):
            return D_inv * (op @ np.ascontiguousarray(v.real)) + 1j * (
                D_inv * (op @ np.ascontiguousarray(v.imag))
            )
        return D_inv * (op @ v)

    n = A.shape[0]
    steps = min(n, RHO_STEPS)
    v0: NDArray = np.random.rand(n, 1).ravel()
    for _ in range(RHO_RESTARTS + 1):
        if np.iscomplexobj(v0) and not v0.imag.any():
            v0 = v0.real  # a real Ritz vector: the complex arithmetic's real part, exactly
        V = np.empty((steps + 1, n), dtype=v0.dtype)
        V[0] = v0 / np.sqrt(np.vdot(v0, v0).real)
        H = np.zeros((steps + 1, steps), dtype=v0.dtype)
        k, broke = 0, False
        for j in range(steps):
            w = apply(V[j])
            for i in range(j + 1):
                H[i, j] = np.vdot(V[i], w)
                w -= H[i, j] * V[i]
            H[j + 1, j] = np.sqrt(np.vdot(w, w).real)
            k = j + 1
            if abs(H[j + 1, j]) < 1e6 * np.finfo(np.float64).eps:  # an invariant subspace: exact
                broke = True
                break
            np.divide(w, H[j + 1, j], out=V[k])
        ev, evect = eig(H[:k, :k], left=False, right=True)
        m = int(np.abs(ev).argmax())
        error = H[k, k - 1] * evect[-1, m]
        v0 = V[:k].T @ evect[:, m]
        if np.abs(error) / np.abs(ev[m]) < RHO_TOL or broke:
            break
    return float(np.abs(ev[m]))
