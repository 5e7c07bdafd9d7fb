"""Weighted damped least-squares (WDLS) inverse kinematics of the hand's fingers.

One WDLS step is :func:`wdls`, ``dq = W^-1 J^T (J W^-1 J^T + lambda^2 I)^-1 dx`` (Nakamura and
Hanafusa; Chiaverini's WDLS), compiled with Numba; every caller uses it: :func:`wdls_step` (checked
arguments), the limit-clamped step :func:`limited_step` of :func:`solve_ik`, :func:`track` and
:func:`follow_line`, and the floating-palm placement (:mod:`softgrasp.hand.placement_solve`).

The kernels are compiled as :mod:`softgrasp.hand.kinematics`'s (:data:`~softgrasp.hand.kinematics.jit`).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from softgrasp.errors import ConfigError, InfeasibleGrasp
from softgrasp.hand.kinematics import FingerChain, HandModel, _kinematics, jit

__all__ = [
    "LINE_TOLERANCE",
    "LIMIT_EPS",
    "wdls",
    "limited_step",
    "wdls_step",
    "solve_ik",
    "track",
    "follow_line",
]

#: Largest distance [m] :func:`follow_line` lets the fingertip stray from its commanded line point.
LINE_TOLERANCE = 5e-4

#: Largest Cartesian correction [m] one IK iteration aims at (longer errors are shortened).
MAX_CARTESIAN_STEP = 0.01

#: A joint closer than this [rad or m] to a limit counts as being at the limit.
LIMIT_EPS = 1e-12

#: Step halvings of the IK line search before an iteration counts as "no progress".
MAX_HALVINGS = 30

#: An IK attempt stops when its error fell by less than this fraction over the last
#: :data:`STALL_WINDOW` iterations (slow creep towards the closest point of an unreachable target).
STALL_FRACTION = 1e-3
STALL_WINDOW = 10

#: Extra random starting configurations tried by :func:`solve_ik` after ``q0`` and mid-range.
IK_RESTARTS = 6


# ---------------------------------------------------------------------- WDLS


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


# ---------------------------------------------------------------------- inverse kinematics


def _descend(
    chain: FingerChain,
    target: NDArray[np.float64],
    q: NDArray[np.float64],
    w: NDArray[np.float64],
    damping: float,
    tol: float,
    max_iter: int,
) -> tuple[NDArray[np.float64], float]:
    """Clamped WDLS iterations from ``q`` (inside the limits, joint weights ``w``); returns the last
    ``q`` and its error."""
    lower, upper = chain.lower, chain.upper
    winv = 1.0 / w
    tip, J = _kinematics(chain, q, True)
    e = target - tip
    err = float(np.linalg.norm(e))
    history = [err]
    for _ in range(max_iter):
        if err <= tol:
            break
        if len(history) > STALL_WINDOW and history[-1 - STALL_WINDOW] - err < STALL_FRACTION * err:
            break  # stalled
        dx = e if err <= MAX_CARTESIAN_STEP else e * (MAX_CARTESIAN_STEP / err)
        assert J is not None
        dq = limited_step(J, dx, q, lower, upper, winv, damping, LIMIT_EPS)[0]
        if not np.any(dq):
            break
        alpha = 1.0
        for _ in range(MAX_HALVINGS):
            q_try = np.clip(q + alpha * dq, lower, upper)
            tip_try = _kinematics(chain, q_try, False)[0]
            err_try = float(np.linalg.norm(target - tip_try))
            if err_try < err:
                break
            alpha *= 0.5
        else:
            break  # no progress: a local minimum of the distance within the limits
        q = q_try
        tip, J = _kinematics(chain, q, True)
        e = target - tip
        err = float(np.linalg.norm(e))
        history.append(err)
    return q, err


def _point(v: ArrayLike, what: str) -> NDArray[np.float64]:
    p = np.asarray(v, dtype=np.float64)
    if p.shape != (3,) or not np.all(np.isfinite(p)):
        raise ConfigError(f"{what} must be 3 finite coordinates [m]; got shape {p.shape}")
    return p


def _mm(p: NDArray[np.float64]) -> str:
    """``(x, y, z)`` in mm with one decimal, for messages."""
    return "(" + ", ".join(f"{1e3 * v:.1f}" for v in p) + ")"


def _ik_options(
    model: HandModel, finger: str, q0: ArrayLike, damping: float, weights: ArrayLike | None
) -> tuple[FingerChain, NDArray[np.float64], NDArray[np.float64], float]:
    chain, q = model._q(finger, q0)
    lam = float(damping)
    if not (math.isfinite(lam) and lam >= 0.0):
        raise ConfigError(f"damping = {damping} is invalid: it must be finite and >= 0")
    return chain, np.clip(q, chain.lower, chain.upper), _weights(weights, chain.dof), lam


def solve_ik(
    model: HandModel,
    finger: str,
    target: ArrayLike,
    q0: ArrayLike,
    *,
    damping: float = 1e-3,
    weights: ArrayLike | None = None,
    tol: float = 1e-5,
    max_iter: int = 200,
) -> NDArray[np.float64]:
    """Independent joint vector placing the ``finger``'s fingertip centre at ``target`` [m].

    Iterates WDLS steps (:func:`limited_step`, joint weights ``weights``, default 1) on the
    fingertip error, each aimed at most :data:`MAX_CARTESIAN_STEP` along the error and shortened
    by halving until the error decreases. Joint limits: ``q0`` is first clipped into the limits;
    at every iteration a joint sitting at a limit whose step would push it further out is removed
    from the step (infinite weight) and the step recomputed with the other joints; the trial
    ``q`` is clipped into the limits, so the result never leaves them. Iterations stop at an error
    ``<= tol`` [m], after ``max_iter`` iterations, when no shortened step decreases the error, or
    when the error fell by less than :data:`STALL_FRACTION` over :data:`STALL_WINDOW` iterations.
    If ``q0`` fails, the mid-range configuration and :data:`IK_RESTARTS` fixed pseudo-random ones
    are tried. :class:`InfeasibleGrasp` names the finger and the closest distance reached.
    """
    chain, q, w, lam = _ik_options(model, finger, q0, damping, weights)
    p = _point(target, "target")
    if not (math.isfinite(tol) and tol > 0.0):
        raise ConfigError(f"tol = {tol} m is invalid: it must be finite and > 0")
    if int(max_iter) != max_iter or max_iter < 1:
        raise ConfigError(f"max_iter = {max_iter} must be an integer >= 1")
    rng = np.random.default_rng(0)
    seeds = [q, 0.5 * (chain.lower + chain.upper)]
    seeds += list(rng.uniform(chain.lower, chain.upper, size=(IK_RESTARTS, chain.dof)))
    best = math.inf
    for seed in seeds:
        q_end, err = _descend(chain, p, seed, w, lam, tol, int(max_iter))
        if err <= tol:
            return q_end
        best = min(best, err)
    raise InfeasibleGrasp(
        f"the {finger} fingertip cannot reach target {_mm(p)} mm: closest {1e3 * best:.3f} mm away"
    )


def track(
    model: HandModel,
    finger: str,
    target: ArrayLike,
    q: ArrayLike,
    *,
    iterations: int = 10,
    damping: float = 1e-3,
) -> NDArray[np.float64]:
    """Joint vector moving the fingertip from its posture ``q`` towards ``target`` (palm frame):
    up to ``iterations`` limit-clamped WDLS iterations, no restarts, so successive calls give a
    continuous motion (a Cartesian controller's inner loop). Never leaves the joint limits."""
    chain, q0, w, lam = _ik_options(model, finger, q, damping, None)
    return _descend(chain, _point(target, "target"), q0, w, lam, 1e-7, int(iterations))[0]


def follow_line(
    model: HandModel,
    finger: str,
    q0: ArrayLike,
    start: ArrayLike,
    end: ArrayLike,
    steps: int,
    *,
    damping: float = 1e-3,
    weights: ArrayLike | None = None,
) -> NDArray[np.float64]:
    """Joint trajectory ``(steps + 1, dof)`` moving the fingertip straight from ``start`` to ``end``.

    Row 0 is ``q0`` (clipped into the limits) if its fingertip is within 1e-6 m of ``start``,
    otherwise :func:`solve_ik` from ``q0`` to ``start``. Row ``k`` tracks the line point
    ``start + k / steps (end - start)`` by limit-clamped WDLS iterations (as :func:`solve_ik`,
    without restarts, so the trajectory is continuous) from row ``k - 1``. If the fingertip ends
    a row more than :data:`LINE_TOLERANCE` (0.5 mm) from its commanded point (so possibly off
    the line), :class:`InfeasibleGrasp` names the finger and the step.
    """
    chain, q, w, lam = _ik_options(model, finger, q0, damping, weights)
    a = _point(start, "start")
    b = _point(end, "end")
    if isinstance(steps, bool) or int(steps) != steps or steps < 1:
        raise ConfigError(f"steps = {steps} must be an integer >= 1")
    steps = int(steps)
    if np.linalg.norm(_kinematics(chain, q, False)[0] - a) > 1e-6:
        q = solve_ik(model, finger, a, q, damping=lam, weights=w, tol=1e-7)
    out = np.empty((steps + 1, chain.dof))
    out[0] = q
    for k in range(1, steps + 1):
        point = a + (k / steps) * (b - a)
        q, err = _descend(chain, point, q, w, lam, 1e-7, 50)
        if err > LINE_TOLERANCE:
            raise InfeasibleGrasp(
                f"the {finger} fingertip cannot follow the line from "
                f"{_mm(a)} to {_mm(b)} mm: "
                f"{1e3 * err:.2f} mm off at step {k}/{steps}"
            )
        out[k] = q
    return out
