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
    """
    JW = J * winv  # J W^-1
    A = JW @ J.T
    if damping > 0.0:
        for i in range(A.shape[0]):
            A[i, i] += damping * damping
        y = np.linalg.solve(A, dx)
    else:
        y = np.linalg.pinv(A) @ dx
    return JW.T @ y


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
