"""Krylov iterations of the Newton systems: conjugate gradients and GMRES.

* :func:`cg`: preconditioned conjugate gradients by SciPy (``scipy.sparse.linalg.cg``), watched
  for what a Newton matrix can do to them: a direction of non-positive curvature (an indefinite
  stiffness: the caller shifts the diagonal) ends them with the progress so far, and a zero or
  non-finite ``r^T M r`` or a non-finite iterate is a breakdown, raised as
  :class:`~softgrasp.errors.NotConverged`;
* :func:`stale_pcg`: conjugate gradients (SciPy's) preconditioned by the factorisation of a
  nearby matrix, started from that factor's solve, which prove a matrix indefinite when they meet
  curvature beyond round-off;
* :func:`gmres`: right-preconditioned GMRES without restart on the exact (non-symmetric) Newton
  product.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any, Protocol

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from numpy.typing import NDArray

from softgrasp.errors import NotConverged

__all__ = ["INDEFINITE_SHIFT", "SINGULAR", "STALE_RTOL", "cg", "gmres", "stale_pcg"]

SINGULAR = (
    "the stiffness matrix is singular, so the body is not held in place (it could slide, spin or "
    "fall freely); add support (table friction, contacts) or constraints"
)
#: Relative residual of the conjugate-gradient iterations preconditioned by an earlier
#: factorisation (the Newton iteration checks the true unbalanced forces; this only has to be
#: well below its contraction).
STALE_RTOL = 1e-8
#: First diagonal shift (relative) of an indefinite Newton matrix; grown tenfold until positive.
INDEFINITE_SHIFT = 1e-6
#: Conjugate gradients preconditioned by an old factor prove the matrix indefinite when they meet
#: a direction p with ``p^T A p`` below minus this multiple of its round-off bound, n eps times the
#: largest absolute row sum times ``|p|^2``.
NEGATIVE_CURVATURE_ROUNDOFF = 10.0


class Factor(Protocol):
    """What :func:`stale_pcg` needs of a factorisation: its solve."""

    def solve(self, b: NDArray[np.float64]) -> NDArray[np.float64]: ...


class _Curvature(Exception):
    """Raised inside SciPy's iteration at a direction ``p`` of non-positive curvature ``pAp``."""

    def __init__(self, p: NDArray[np.float64], pAp: float = 0.0) -> None:
        super().__init__()
        self.p = p
        self.pAp = pAp


def cg(
    A: Any, b: NDArray[np.float64], M: Any, rtol: float, max_it: int
) -> tuple[NDArray[np.float64], int, bool]:
    """Conjugate gradients on ``A x = b`` from zero (``A`` and the preconditioner ``M`` matrices or
    products ``@``) by SciPy, to the relative residual ``rtol`` in at most ``max_it`` iterations.

    Returns (x, the iterations, whether they met a direction ``p`` with ``p^T A p <= 0``: then x is
    the progress so far, or that first direction, both descent directions for a line search).
    Raises NotConverged where they break down: ``r^T M r`` zero for a residual that is not (the
    next step would divide by it), or not finite, or a non-finite iterate. (An indefinite
    preconditioner, ``r^T M r < 0``, is no breakdown: the iterations go on, as the algorithm
    does, until they converge or meet the matrix's negative curvature.)"""
    b = np.asarray(b, dtype=np.float64)
    n = b.shape[0]
    if not float(np.linalg.norm(b)) > 0.0:
        return np.zeros_like(b), 0, False
    seen: dict[str, Any] = {"iterations": 0, "x": None}

    def matvec(p: NDArray[np.float64]) -> NDArray[np.float64]:
        Ap = np.asarray(A @ p, dtype=np.float64)
        if not float(p @ Ap) > 0.0:
            raise _Curvature(p.copy())
        return Ap

    def psolve(r: NDArray[np.float64]) -> NDArray[np.float64]:
        z = np.asarray(M @ r, dtype=np.float64)
        rz = float(r @ z)
        if rz == 0.0 or not math.isfinite(rz):
            # The next step would divide by r^T M r (SciPy's beta, or alpha through p = z).
            raise NotConverged(
                f"conjugate gradients broke down: the preconditioned residual's r^T M r is {rz:.3g}; "
                + SINGULAR
            )
        return z

    def count(xk: NDArray[np.float64]) -> None:
        seen["iterations"] += 1
        seen["x"] = xk  # SciPy's iterate, updated in place

    op = spla.LinearOperator((n, n), matvec=matvec, dtype=np.float64)
    pre = spla.LinearOperator((n, n), matvec=psolve, dtype=np.float64)
    try:
        x, _ = spla.cg(op, b, rtol=rtol, atol=0.0, maxiter=max_it, M=pre, callback=count)
    except _Curvature as bend:
        it = seen["iterations"] + 1
        x, curved = (bend.p if seen["x"] is None else np.array(seen["x"])), True
    else:
        it, curved = seen["iterations"], False
    if not np.isfinite(x).all():
        raise NotConverged(f"conjugate gradients broke down: a non-finite iterate; {SINGULAR}")
    return x, it, curved


def stale_pcg(
    A: sp.csr_matrix,
    b: NDArray[np.float64],
    f: Factor,
    max_it: int,
    rtol: float = STALE_RTOL,
    keep_last: bool = False,
) -> tuple[NDArray[np.float64] | None, bool]:
    """Conjugate gradients on ``A x = b`` preconditioned by the factorisation ``f`` of a nearby
    matrix, started from ``f``'s solve of ``b`` (SciPy's iteration). Returns (x, or None when they
    do not reach ``rtol`` in ``max_it`` iterations or meet a direction p with ``p^T A p <= 0`` or a
    residual with ``r^T f^-1 r <= 0`` (with ``keep_last``: the last iterate then); whether they met
    a direction p of negative curvature beyond round-off,
    ``p^T A p < -NEGATIVE_CURVATURE_ROUNDOFF n eps max_i sum_j |A_ij| |p|^2``: a proof that A is
    indefinite)."""
    b = np.asarray(b, dtype=np.float64)
    bnorm = float(np.linalg.norm(b))
    if bnorm == 0:
        return np.zeros_like(b), False
    n = b.shape[0]
    x0 = f.solve(b)
    # SciPy's first product is the starting residual's (none from a zero start).
    seen: dict[str, Any] = {"x": x0, "rz": math.inf, "start": bool(x0.any())}

    def matvec(p: NDArray[np.float64]) -> NDArray[np.float64]:
        Ap = np.asarray(A @ p, dtype=np.float64)
        if seen["start"]:
            seen["start"] = False
            return Ap
        pAp = float(p @ Ap)
        if not pAp > 0 or not seen["rz"] > 0:
            raise _Curvature(p.copy(), pAp)
        return Ap

    def psolve(r: NDArray[np.float64]) -> NDArray[np.float64]:
        z = f.solve(r)
        seen["rz"] = float(r @ z)
        return z

    def track(xk: NDArray[np.float64]) -> None:
        seen["x"] = xk  # SciPy's iterate, updated in place

    op = spla.LinearOperator((n, n), matvec=matvec, dtype=np.float64)
    pre = spla.LinearOperator((n, n), matvec=psolve, dtype=np.float64)
    try:
        x, info = spla.cg(op, b, x0=x0.copy(), rtol=rtol, atol=0.0, maxiter=max_it, M=pre, callback=track)
    except _Curvature as bend:
        # Round-off in p^T A p is at most ~n eps |p|^T |A| |p| <= n eps max_i sum_j |A_ij| |p|^2.
        row_sum = float(abs(A).sum(axis=1).max())
        bound = NEGATIVE_CURVATURE_ROUNDOFF * n * np.finfo(float).eps * row_sum * float(bend.p @ bend.p)
        return (np.array(seen["x"]) if keep_last else None), bend.pAp < -bound
    if info > 0 and float(np.linalg.norm(b - A @ x)) > rtol * bnorm:
        return (x if keep_last else None), False  # (SciPy tests the last iterate only at the next)
    return x, False


def gmres(
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
