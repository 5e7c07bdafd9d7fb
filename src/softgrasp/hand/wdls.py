"""The weighted damped least-squares (WDLS) step of the hand's inverse kinematics.

:func:`wdls` is ``dq = W^-1 J^T (J W^-1 J^T + lambda^2 I)^-1 dx`` (Nakamura and Hanafusa;
Chiaverini's WDLS), compiled with Numba; every caller uses it: :func:`wdls_step` (checked
arguments) and the limit-clamped step :func:`limited_step` of every IK iteration
(:mod:`softgrasp.hand.descent`: the fingers' IK and the floating-palm placement).

The kernels are compiled as :mod:`softgrasp.hand.fk`'s (:data:`~softgrasp.hand.fk.jit`).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from softgrasp.errors import ConfigError
from softgrasp.hand.fk import jit

__all__ = ["LIMIT_EPS", "wdls", "limited_step", "wdls_step"]

#: A joint closer than this [rad or m] to a limit counts as being at the limit.
LIMIT_EPS = 1e-12


@jit
def wdls(J, dx, winv, damping):  # pragma: no cover - compiled
    """The WDLS step ``dq = W^-1 J^T (J W^-1 J^T + damping^2 I)^-1 dx`` ``(n,)``.

    ``J`` ``(m, n)``, ``dx`` ``(m,)``, ``winv`` the diagonal of ``W^-1`` ``(n,)`` (``>= 0``: a joint
    with ``winv = 0`` does not move and adds nothing to ``J W^-1 J^T``), ``damping >= 0``. With
    ``damping = 0`` the Moore-Penrose inverse of ``J W^-1 J^T`` is used (rank-deficient ``J``).
    Arguments are not checked (:func:`wdls_step` checks them).

    The m x m system (m = 3 per finger) is solved here by Cholesky's method (SPD with damping > 0)
    or, without damping, by the eigen-decomposition of the PSD matrix (:func:`_pinv_solve`):
    written out because Numba's LAPACK bindings for ``np.linalg.solve`` and ``pinv`` took a third
    of a first run's compile time (``benchmarks/bench_cli.py``, first run).
    """
    m, n = J.shape
    A = np.zeros((m, m))
    for i in range(m):
        for j in range(i + 1):
            s = 0.0
            for k in range(n):
                s += J[i, k] * winv[k] * J[j, k]
            A[i, j] = s
            A[j, i] = s
    if damping > 0.0:
        for i in range(m):
            A[i, i] += damping * damping
        y = _cholesky_solve(A, dx)
    else:
        y = _pinv_solve(A, dx)
    dq = np.zeros(n)
    for k in range(n):
        s = 0.0
        for i in range(m):
            s += J[i, k] * y[i]
        dq[k] = winv[k] * s
    return dq


@jit
def _cholesky_solve(A, b):  # pragma: no cover - compiled
    """``A^-1 b`` for a symmetric positive definite ``A`` (m, m) (overwritten by its factor)."""
    m = A.shape[0]
    for j in range(m):
        d = A[j, j]
        for k in range(j):
            d -= A[j, k] * A[j, k]
        d = math.sqrt(d)
        A[j, j] = d
        for i in range(j + 1, m):
            s = A[i, j]
            for k in range(j):
                s -= A[i, k] * A[j, k]
            A[i, j] = s / d
    y = b.copy()
    for i in range(m):  # L z = b
        s = y[i]
        for k in range(i):
            s -= A[i, k] * y[k]
        y[i] = s / A[i, i]
    for i in range(m - 1, -1, -1):  # L^T y = z
        s = y[i]
        for k in range(i + 1, m):
            s -= A[k, i] * y[k]
        y[i] = s / A[i, i]
    return y


@jit
def _pinv_solve(A, b):  # pragma: no cover - compiled
    """``pinv(A) b`` for a symmetric positive semi-definite ``A`` (m, m) (overwritten): cyclic
    Jacobi rotations diagonalise it, ``A = V diag(w) V^T``, and eigenvalues at most 1e-15 of the
    largest (NumPy's ``pinv`` cut-off) count as zero."""
    m = A.shape[0]
    V = np.eye(m)
    scale = 0.0
    for p in range(m):
        for q in range(m):
            scale += A[p, q] * A[p, q]
    for _ in range(100):
        off = 0.0
        for p in range(m):
            for q in range(p + 1, m):
                off += A[p, q] * A[p, q]
        if off <= 1e-34 * scale:  # off-diagonal below 1e-17 of the matrix's norm
            break
        for p in range(m):
            for q in range(p + 1, m):
                if A[p, q] == 0.0:
                    continue
                theta = 0.5 * (A[q, q] - A[p, p]) / A[p, q]
                t = (1.0 if theta >= 0.0 else -1.0) / (abs(theta) + math.sqrt(theta * theta + 1.0))
                c = 1.0 / math.sqrt(t * t + 1.0)
                s = t * c
                for k in range(m):  # A <- A R (columns p, q)
                    akp, akq = A[k, p], A[k, q]
                    A[k, p] = c * akp - s * akq
                    A[k, q] = s * akp + c * akq
                for k in range(m):  # A <- R^T A (rows p, q)
                    apk, aqk = A[p, k], A[q, k]
                    A[p, k] = c * apk - s * aqk
                    A[q, k] = s * apk + c * aqk
                for k in range(m):
                    vkp, vkq = V[k, p], V[k, q]
                    V[k, p] = c * vkp - s * vkq
                    V[k, q] = s * vkp + c * vkq
    top = 0.0
    for i in range(m):
        top = max(top, abs(A[i, i]))
    y = np.zeros(m)
    for i in range(m):
        w = A[i, i]
        if abs(w) <= 1e-15 * top:
            continue
        s = 0.0
        for k in range(m):
            s += V[k, i] * b[k]
        s /= w
        for k in range(m):
            y[k] += s * V[k, i]
    return y


@jit
def limited_step(J, dx, q, lower, upper, winv, damping, limit_eps):  # pragma: no cover - compiled
    """WDLS step in which joints at a limit that the step would push further out are frozen.

    The :func:`wdls` step is computed with all joints (``q`` ``(n,)`` inside ``lower``/``upper``,
    inverse weights ``winv``); every joint within ``limit_eps`` of a limit whose step points out of
    its range gets the inverse weight 0 (the same as dropping its column: its step is exactly 0) and
    the step is recomputed, until no such joint is left. A joint with ``lower == upper`` never
    moves. Returns the step ``dq`` ``(n,)`` and the number of recomputations.
    """
    n = q.shape[0]
    w = np.empty(n)
    outward = np.empty(n)  # the sign of a step out of the range, or 0
    for k in range(n):
        at_lower = q[k] <= lower[k] + limit_eps
        at_upper = q[k] >= upper[k] - limit_eps
        w[k] = 0.0 if (at_lower and at_upper) else winv[k]
        outward[k] = (1.0 if at_upper else 0.0) - (1.0 if at_lower else 0.0)
    rounds = 0
    while True:
        dq = wdls(J, dx, w, damping)
        blocked = False
        for k in range(n):
            if w[k] != 0.0 and dq[k] * outward[k] > 0.0:
                w[k] = 0.0
                blocked = True
        if not blocked:
            return dq, rounds
        rounds += 1


def _weights(W: ArrayLike | None, n: int) -> NDArray[np.float64]:
    if W is None:
        return np.ones(n)
    w = np.asarray(W, dtype=np.float64)
    if w.shape == (n, n):
        if np.any(w - np.diag(np.diag(w))):
            raise ConfigError("the weight matrix W must be diagonal")
        w = np.diag(w).copy()
    if w.shape != (n,):
        raise ConfigError(f"the weights W must have shape ({n},) or ({n}, {n}); got {w.shape}")
    if not (np.all(np.isfinite(w)) and np.all(w > 0.0)):
        raise ConfigError("the weights W must be finite and > 0")
    return w


def wdls_step(
    J: ArrayLike, dx: ArrayLike, W: ArrayLike | None = None, damping: float = 1e-3
) -> NDArray[np.float64]:
    """Weighted damped least-squares step ``dq = W^-1 J^T (J W^-1 J^T + lambda^2 I)^-1 dx``.

    Minimises ``|J dq - dx|^2 + lambda^2 dq^T W dq`` (:func:`wdls` with checked arguments).
    ``J`` is ``(m, n)``, ``dx`` ``(m,)``, ``W`` a positive diagonal joint weight given as its
    diagonal ``(n,)`` or as an ``(n, n)`` diagonal matrix (default identity; a heavier joint moves
    less) and ``damping`` is ``lambda >= 0`` [units of J]. With ``damping = 0`` this is the weighted
    pseudo-inverse ``W^-1 J^T (J W^-1 J^T)^-1 dx``; for a rank-deficient ``J`` the Moore-Penrose
    inverse of ``J W^-1 J^T`` is then used.
    """
    Jm = np.asarray(J, dtype=np.float64)
    if Jm.ndim != 2 or Jm.shape[0] == 0 or Jm.shape[1] == 0 or not np.all(np.isfinite(Jm)):
        raise ConfigError(f"J must be a finite, non-empty (m, n) matrix; got shape {Jm.shape}")
    m, n = Jm.shape
    d = np.asarray(dx, dtype=np.float64)
    if d.shape != (m,) or not np.all(np.isfinite(d)):
        raise ConfigError(f"dx must be {m} finite values; got shape {d.shape}")
    lam = float(damping)
    if not (math.isfinite(lam) and lam >= 0.0):
        raise ConfigError(f"damping = {damping} is invalid: it must be finite and >= 0")
    winv = 1.0 / _weights(W, n)
    return wdls(np.ascontiguousarray(Jm), np.ascontiguousarray(d), winv, lam)
