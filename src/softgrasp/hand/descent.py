"""The clamped WDLS descent of the hand's inverse kinematics, compiled with Numba: the fingertips of
one or more fingers driven to their targets by the joints, and by the palm when it floats (the hand
placement, :mod:`softgrasp.hand.placement`) or with the palm fixed (one finger's IK,
:mod:`softgrasp.hand.ik`).

:func:`solve` iterates every starting posture on its own, one after the other. Per posture and
iteration:

* the fingertip errors ``e = targets - tips`` ``(3 C,)`` and their Jacobian ``(3 C, 6 + n)`` with
  respect to the palm translation, a small palm rotation about world axes and the joints;
* the step aims at ``e`` shortened to at most ``max_step`` [m]; the limit-clamped WDLS step
  (:func:`softgrasp.hand.wdls.limited_step`; the palm's six coordinates act as joints without
  limits, or pinned at 0 when the palm is fixed) freezes every joint at a limit whose step points
  out of its range and recomputes, until none is left;
* a line search takes the first of the step times 1, 1/2, 1/4, ... (``max_halvings`` of them) whose
  joints, clipped into their limits, decrease the error norm; the palm moves by the step's
  translation and rotation, and its step coordinates restart at 0;
* the posture stops at a largest fingertip error <= ``reach_tol``, when that error fell by less
  than ``stall_fraction`` of itself over ``stall_window`` iterations, when the step is zero or no
  shortened step decreases the error norm, or after ``max_iter`` iterations.

The kinematics are those of a :class:`~softgrasp.hand.kinematics.ChainStack` (revolute, prismatic and
fixed or padding joints, mimic joints through ``column``, ``gain`` and ``offset``), evaluated as
3 x 4 affine products root to tip. The iteration amplifies round-off as it amplifies any
perturbation: postures that reach their targets are insensitive to it, but postures wandering
short of unreachable targets can end far apart (up to 1 rad) when a starting posture moves by one
ulp, at much the same error.

The kernels are compiled as :mod:`softgrasp.hand.fk`'s (:data:`~softgrasp.hand.fk.jit`).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from softgrasp.errors import ConfigError
from softgrasp.hand.fk import forward, jit, joint_columns
from softgrasp.hand.kinematics import ChainStack
from softgrasp.hand.wdls import limited_step

__all__ = [
    "STOP_REACHED",
    "STOP_STALLED",
    "STOP_NO_STEP",
    "STOP_NO_DECREASE",
    "STOP_MAX_ITER",
    "Solves",
    "rotation",
    "solve",
]

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]

#: Why a posture stopped iterating: its largest fingertip error is <= ``reach_tol``; that error
#: stalled; the clamped step is zero; no shortened step decreased the error norm; ``max_iter``.
STOP_REACHED = 0
STOP_STALLED = 1
STOP_NO_STEP = 2
STOP_NO_DECREASE = 3
STOP_MAX_ITER = 4

@jit
def _jacobian(axis, prismatic, column, gain, length, p, frames, tips, J):  # pragma: no cover
    """Jacobian ``J`` ``(3 C, 6 + n)`` of the fingertips with respect to the palm translation, a small
    palm rotation about world axes and the joints, from the :func:`forward` frames and tips of a
    palm at ``p``: the joints' columns are :func:`~softgrasp.hand.fk.joint_columns`."""
    J[:, :] = 0.0
    for c in range(length.shape[0]):
        r0 = 3 * c
        rx = tips[c, 0] - p[0]
        ry = tips[c, 1] - p[1]
        rz = tips[c, 2] - p[2]
        for i in range(3):
            J[r0 + i, i] = 1.0
        # d tip / d w_k = e_k x r: the columns of -[r]x
        J[r0, 4] = rz
        J[r0, 5] = -ry
        J[r0 + 1, 3] = -rz
        J[r0 + 1, 5] = rx
        J[r0 + 2, 3] = ry
        J[r0 + 2, 4] = -rx
    joint_columns(axis, prismatic, column, gain, length, frames, tips, J, np.int64(6))


@jit
def rotation(wx, wy, wz, out):  # pragma: no cover - compiled
    """Rotation (3, 3) by the vector ``w`` (axis times angle) into ``out`` (the identity below 1e-15
    rad; Rodrigues' formula)."""
    a = math.sqrt(wx * wx + wy * wy + wz * wz)
    if a < 1e-15:
        for i in range(3):
            for j in range(3):
                out[i, j] = 1.0 if i == j else 0.0
        return
    ux = wx / a
    uy = wy / a
    uz = wz / a
    c = math.cos(a)
    s = math.sin(a)
    t = 1.0 - c
    out[0, 0] = c + t * (ux * ux)
    out[1, 1] = c + t * (uy * uy)
    out[2, 2] = c + t * (uz * uz)
    out[0, 1] = -(s * uz) + t * (ux * uy)
    out[1, 0] = s * uz + t * (uy * ux)
    out[0, 2] = s * uy + t * (ux * uz)
    out[2, 0] = -(s * uy) + t * (uz * ux)
    out[1, 2] = -(s * ux) + t * (uy * uz)
    out[2, 1] = s * ux + t * (uz * uy)


# ---------------------------------------------------------------------------------- WDLS
@jit
def _norm(e):  # pragma: no cover - compiled
    """Euclidean norm of ``e``."""
    s = 0.0
    for i in range(e.shape[0]):
        s += e[i] * e[i]
    return math.sqrt(s)


@jit
def _largest(e):  # pragma: no cover - compiled
    """Largest fingertip distance of the stacked fingertip errors ``e`` ``(3 C,)``."""
    worst = 0.0
    for c in range(e.shape[0] // 3):
        d = math.sqrt(e[3 * c] * e[3 * c] + e[3 * c + 1] * e[3 * c + 1] + e[3 * c + 2] * e[3 * c + 2])
        if d > worst or d != d:  # NaN wins, as in NumPy's max
            worst = d
    return worst


@jit
def _solve(
    basis,
    axis,
    prismatic,
    column,
    gain,
    offset,
    length,
    goal,
    lower,
    upper,
    winv,
    R0,
    p0,
    q0,
    reach_tol,
    max_iter,
    max_step,
    damping,
    stall_fraction,
    stall_window,
    max_halvings,
    limit_eps,
    R_out,
    p_out,
    q_out,
    err_out,
    iterations,
    stop,
    clamps,
):  # pragma: no cover - compiled
    """The floating-palm WDLS of every starting posture ``s`` (``R0[s]``, ``p0[s]``, ``q0[s]``), one
    after the other; writes the last palm rotation, origin, joints and largest fingertip error to
    ``R_out``, ``p_out``, ``q_out``, ``err_out``, the iterations taken, the rule that stopped them
    (``STOP_*``) and the number of limit-clamped step recomputations to ``iterations``, ``stop`` and
    ``clamps``."""
    S, n = q0.shape
    C = length.shape[0]
    L = basis.shape[0]
    N = 6 + n
    m = 3 * C
    T = np.empty((3, 4))
    M = np.empty((3, 4))
    frames = np.empty((C, L, 3, 4))
    tips = np.empty((C, 3))
    J = np.empty((m, N))
    e = np.empty(m)
    e_try = np.empty(m)
    dx = np.empty(m)
    dq = np.empty(N)
    x = np.empty(N)
    x_try = np.empty(N)
    R = np.empty((3, 3))
    R_try = np.empty((3, 3))
    p = np.empty(3)
    p_try = np.empty(3)
    turn = np.empty((3, 3))
    history = np.empty(max_iter + 1)  # history[i]: the largest error after i iterations
    for s in range(S):
        # Element by element (array-to-array slice assignments would bring in Numba's shape check
        # and its exception message, ~4 s of the kernel's compilation).
        for i in range(3):
            p[i] = p0[s, i]
            for j in range(3):
                R[i, j] = R0[s, i, j]
        for k in range(6):
            x[k] = 0.0  # palm step coordinates, 0 at the current pose
        for k in range(n):
            x[6 + k] = q0[s, k]
        forward(basis, column, gain, offset, length, R, p, x[6:], T, M, frames, tips)
        for i in range(m):
            e[i] = goal[i] - tips[i // 3, i % 3]
        err = _largest(e)
        _jacobian(axis, prismatic, column, gain, length, p, frames, tips, J)
        history[0] = err
        clamps[s] = 0
        why = STOP_MAX_ITER
        done = 0
        for it in range(max_iter):
            if not err > reach_tol:
                why = STOP_REACHED
                break
            if it >= stall_window:
                if not history[max(it - stall_window - 1, 0)] - err >= stall_fraction * err:
                    why = STOP_STALLED  # short of the targets: a limit or the workspace's edge
                    break
            norm = _norm(e)
            scale = min(1.0, max_step / norm)  # at most max_step long
            for i in range(m):
                dx[i] = e[i] * scale
            dq, rounds = limited_step(J, dx, x, lower, upper, winv, damping, limit_eps)
            clamps[s] += rounds
            done = it + 1
            any_step = False
            for k in range(N):
                any_step = any_step or dq[k] != 0.0
            if not any_step:
                why = STOP_NO_STEP
                break
            moved = False
            alpha = 1.0
            for _ in range(max_halvings):
                for k in range(N):
                    v = x[k] + dq[k] * alpha  # the palm part is the step itself
                    x_try[k] = min(max(v, lower[k]), upper[k])
                for i in range(3):
                    p_try[i] = p[i] + dq[i] * alpha
                rotation(dq[3] * alpha, dq[4] * alpha, dq[5] * alpha, turn)
                for i in range(3):
                    for j in range(3):
                        R_try[i, j] = turn[i, 0] * R[0, j] + turn[i, 1] * R[1, j] + turn[i, 2] * R[2, j]
                forward(basis, column, gain, offset, length, R_try, p_try, x_try[6:], T, M, frames, tips)
                for i in range(m):
                    e_try[i] = goal[i] - tips[i // 3, i % 3]
                if _norm(e_try) < norm:
                    moved = True
                    break
                alpha *= 0.5
            if not moved:
                why = STOP_NO_DECREASE
                break
            for i in range(3):
                p[i] = p_try[i]
                for j in range(3):
                    R[i, j] = R_try[i, j]
            for k in range(6):
                x[k] = 0.0
            for k in range(6, N):
                x[k] = x_try[k]
            for i in range(m):
                e[i] = e_try[i]
            _jacobian(axis, prismatic, column, gain, length, p, frames, tips, J)  # frames of the step taken
            err = _largest(e)
            history[it + 1] = err
        for i in range(3):
            p_out[s, i] = p[i]
            for j in range(3):
                R_out[s, i, j] = R[i, j]
        for k in range(n):
            q_out[s, k] = x[6 + k]
        err_out[s] = err
        iterations[s] = done
        stop[s] = why


# ---------------------------------------------------------------------------------- Python side
class Solves(NamedTuple):
    """What :func:`solve` returns for ``S`` starting postures of a stack with ``n`` joints.

    R: last palm rotation of each, ``(S, 3, 3)``.  p: last palm origin, ``(S, 3)`` [m].
    q: last joints, ``(S, n)`` [rad or m].  error: largest fingertip distance to its target,
    ``(S,)`` [m].  iterations: WDLS steps computed, ``(S,)`` (a last step that was not taken
    included).  stop: the rule that stopped each, one of the ``STOP_*`` codes, ``(S,)``.
    clamps: limit-clamped step recomputations (a joint at a limit frozen), ``(S,)``.
    """

    R: Array
    p: Array
    q: Array
    error: Array
    iterations: IntArray
    stop: IntArray
    clamps: IntArray


def solve(
    stack: ChainStack,
    targets: Array,
    R: Array,
    p: Array,
    q: Array,
    *,
    winv: Array | None = None,
    palm_fixed: bool = False,
    reach_tol: float,
    max_iter: int,
    max_step: float,
    damping: float,
    stall_fraction: float,
    stall_window: int,
    max_halvings: int,
    limit_eps: float,
) -> Solves:
    """Clamped WDLS towards the targets ``(C, 3)`` [m] from each of ``S`` starting postures (palm
    rotations ``R`` ``(S, 3, 3)``, origins ``p`` ``(S, 3)`` [m], joints ``q`` ``(S, n)``, inside their
    limits); see :class:`Solves`. The palm floats unless ``palm_fixed``.

    ``winv`` ``(n,)`` are the inverse joint weights (default 1; the palm's are 1). The rules are
    those of the module docstring: ``reach_tol`` [m], ``max_iter``, ``max_step`` [m], ``damping``
    [m] (>= 0; 0: the undamped, pseudo-inverse step), ``stall_fraction`` over ``stall_window``
    iterations, ``max_halvings`` and the limit tolerance ``limit_eps`` [rad or m].
    """
    R0 = np.ascontiguousarray(R, dtype=np.float64)
    p0 = np.ascontiguousarray(p, dtype=np.float64)
    q0 = np.ascontiguousarray(q, dtype=np.float64)
    S, n = q0.shape
    if R0.shape != (S, 3, 3) or p0.shape != (S, 3) or n != stack.n:
        raise ConfigError(
            f"solve needs R (S, 3, 3), p (S, 3) and q (S, {stack.n}); got {R0.shape}, {p0.shape}, {q0.shape}"
        )
    goal = np.ascontiguousarray(targets, dtype=np.float64).ravel()
    if goal.shape != (3 * len(stack.chains),):
        raise ConfigError(f"solve needs targets ({len(stack.chains)}, 3); got {np.shape(targets)}")
    palm = np.zeros(6) if palm_fixed else np.full(6, np.inf)
    lower = np.concatenate([-palm] + [c.lower for c in stack.chains])
    upper = np.concatenate([palm] + [c.upper for c in stack.chains])
    weights = np.ones(6 + n)
    if winv is not None:
        weights[6:] = winv
    out = Solves(
        np.empty((S, 3, 3)),
        np.empty((S, 3)),
        np.empty((S, n)),
        np.empty(S),
        np.empty(S, dtype=np.int64),
        np.empty(S, dtype=np.int64),
        np.empty(S, dtype=np.int64),
    )
    _solve(
        stack.basis,
        stack.axis,
        stack.prismatic,
        stack.column,
        stack.gain,
        stack.offset,
        stack.lengths,
        goal,
        lower,
        upper,
        weights,
        R0,
        p0,
        q0,
        float(reach_tol),
        int(max_iter),
        float(max_step),
        float(damping),
        float(stall_fraction),
        int(stall_window),
        int(max_halvings),
        float(limit_eps),
        *out,
    )
    return out
