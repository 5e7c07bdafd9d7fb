"""NumPy oracles of the hand's forward kinematics (:func:`softgrasp.hand.kinematics.stack_kinematics`)
and of the placement's floating-palm WDLS (:mod:`softgrasp.hand.descent`).

:func:`stack_kinematics` evaluates the chains of a stack vectorised over configurations and chains:
each joint's 4 x 4 transform from the stack's ``basis`` (:func:`local_transforms`), multiplied
pairwise (:func:`chain_product`, :func:`chain_frames`), the Jacobian's columns scattered to the
joints by :func:`select`.

:func:`solve` iterates all starting postures at once, vectorised with NumPy (every posture still
iterates on its own: they advance in lockstep only to share NumPy calls), with the rules read
from :mod:`softgrasp.hand.placement` at call time (tests patch them). Its limit-clamped step
:func:`limited_steps` is the batched NumPy form of :func:`softgrasp.hand.wdls.limited_step`, its
kinematics those above (pairwise 4 x 4 products, BLAS and LAPACK), so it sums in other orders than
the compiled solve: one iteration of the two agrees to round-off.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from numpy.typing import NDArray

from softgrasp.hand import placement as rules
from softgrasp.hand.kinematics import _LEVI_CIVITA, ChainStack, Kinematics
from softgrasp.hand.wdls import LIMIT_EPS

#: Trial steps of the line search evaluated at once, shared among the postures still searching (a
#: cost trade-off only: each posture takes the first step of 1, 1/2, 1/4, ... that decreases its error).
TRIAL_BUDGET = 24

_EYE3 = np.eye(3)


@lru_cache(maxsize=64)
def select(stack: ChainStack) -> NDArray[np.float64]:
    """``d value / d q`` ``(C, L, n)`` of every joint of ``stack`` (the Jacobian's scatter: a mimic
    joint adds to its driver; zero for a fixed joint)."""
    L, C = stack.column.shape
    out = np.zeros((C, L, stack.n))
    for l in range(L):
        for c in range(C):
            out[c, l, stack.column[l, c]] += stack.gain[l, c]
    return out


def values(stack: ChainStack, q: NDArray[np.float64]) -> NDArray[np.float64]:
    """Every joint's value ``(L, B, C)`` for the stacked joint vectors ``q`` ``(B, n)`` (a fixed
    joint's value is arbitrary when the stack is ``plain``)."""
    value = np.take(q, stack.column, axis=1).transpose(1, 0, 2)
    return value if stack.plain else value * stack.gain[:, None] + stack.offset[:, None]


def local_transforms(
    stack: ChainStack,
    q: NDArray[np.float64],
    rot: NDArray[np.float64] | None = None,
    pos: NDArray[np.float64] | None = None,
) -> NDArray[np.float64]:
    """Each joint's transform (its origin times its motion) for each row of ``q`` ``(B, n)``:
    ``(L, B, C, 4, 4)``, preceded by the palm's pose (``rot`` ``(B, 3, 3)``, ``pos`` ``(B, 3)``, both
    or neither) if given: ``(1 + L, B, C, 4, 4)``. Their product, root to tip, is the chain."""
    B = q.shape[0]
    L, C, K = stack.basis.shape[:3]
    value = values(stack, q)
    coef = np.ones((L, B, C, 1, K))
    np.cos(value, out=coef[..., 0, 0])
    np.sin(value, out=coef[..., 0, 1])
    if stack.has_prismatic:
        coef[..., 0, 3] = value
    root = rot is not None
    E = np.empty((L + root, B, C, 1, 16))
    np.matmul(coef, stack.basis[:, None], out=E[root:])
    E = E.reshape(L + root, B, C, 4, 4)
    if root:
        assert rot is not None and pos is not None
        E[0, :, :, :3, :3] = rot[:, None]
        E[0, :, :, :3, 3] = pos[:, None]
        E[0, :, :, 3] = (0.0, 0.0, 0.0, 1.0)
    return E


def chain_product(E: NDArray[np.float64]) -> NDArray[np.float64]:
    """The product ``E[0] @ E[1] @ ... `` of transforms ``(K, ..., 4, 4)`` (pairwise, log2 K rounds)."""
    while len(E) > 1:
        half = len(E) // 2
        P = E[0 : 2 * half : 2] @ E[1 : 2 * half : 2]
        E = np.concatenate([P, E[-1:]]) if len(E) % 2 else P
    return E[0]


def chain_frames(E: NDArray[np.float64]) -> NDArray[np.float64]:
    """The prefix products ``E[0] @ ... @ E[k]`` of transforms ``(K, ..., 4, 4)`` (a new array;
    Hillis-Steele scan, log2 K rounds)."""
    P = E.copy()
    d = 1
    while d < len(P):
        P[d:] = P[:-d] @ P[d:]
        d *= 2
    return P


def frame_kinematics(
    stack: ChainStack,
    frames: NDArray[np.float64],
    q: NDArray[np.float64],
    *,
    jacobian: bool = False,
    origins: bool = False,
) -> Kinematics:
    """:class:`Kinematics` from the frames ``(L, B, C, 4, 4)`` after each joint (the prefix products
    of :func:`local_transforms` without the palm's) for the joint vectors ``q`` ``(B, n)``.

    A revolute joint's Jacobian column is ``a x (p_tip - p_joint)``, a prismatic one's ``a`` (``a``
    the joint axis in the output frame); a mimic joint adds its column times its multiplier to
    its driver's.
    """
    L, B, C = frames.shape[:3]
    tips = frames[-1, :, :, :3, 3]
    if not (jacobian or origins):
        return Kinematics(tips, None, None)
    o = frames[..., :3, 3]  # a revolute or fixed joint does not move its own origin
    a = None
    if stack.has_prismatic or jacobian:
        a = (frames[..., :3, :3] @ stack.axis[:, None])[..., 0]  # joint axes, (L, B, C, 3)
        if stack.has_prismatic:
            o = o - np.where(stack.prismatic[:, None], values(stack, q), 0.0)[..., None] * a
    J = None
    if jacobian:
        assert a is not None
        neg_cross = (a @ _LEVI_CIVITA).reshape(L, B, C, 3, 3)  # -[a]x
        col = (neg_cross @ (o - tips)[..., None])[..., 0]  # a x (tip - o), (L, B, C, 3)
        if stack.has_prismatic:
            col = np.where(stack.prismatic[:, None, :, None], a, col)
        J = col.transpose(1, 2, 3, 0) @ select(stack)  # fixed joints have zero rows in select
    return Kinematics(tips, J, o.transpose(1, 2, 0, 3) if origins else None)


def stack_kinematics(
    stack: ChainStack,
    q: NDArray[np.float64],
    rot: NDArray[np.float64] | None = None,
    pos: NDArray[np.float64] | None = None,
    *,
    jacobian: bool = False,
    origins: bool = False,
) -> Kinematics:
    """Fingertips (and optionally the Jacobian and joint origins) of every chain of ``stack`` for each
    row of ``q`` ``(B, n)`` (validated by the caller), in the frame where the palm has rotation
    ``rot`` ``(B, 3, 3)`` and origin ``pos`` ``(B, 3)`` (both or neither; default: the palm frame).
    See :func:`local_transforms` and :func:`frame_kinematics` (the NumPy form of
    :func:`softgrasp.hand.kinematics.stack_kinematics`)."""
    E = local_transforms(stack, q, rot, pos)
    if not (jacobian or origins):
        return Kinematics(chain_product(E)[..., :3, 3], None, None)
    frames = chain_frames(E)
    return frame_kinematics(stack, frames[rot is not None :], q, jacobian=jacobian, origins=origins)


def rotations(w: NDArray[np.float64]) -> NDArray[np.float64]:
    """:func:`_rotation` of each row of ``w`` ``(B, 3)``: ``(B, 3, 3)``."""
    a = np.sqrt(np.einsum("ij,ij->i", w, w))
    small = a < 1e-15
    u = w / np.where(small, 1.0, a)[:, None]
    c, s = np.cos(a)[:, None, None], np.sin(a)[:, None, None]
    skew = (u @ _LEVI_CIVITA).reshape(-1, 3, 3)  # -[u]x
    R = c * _EYE3 - s * skew + (1.0 - c) * (u[:, :, None] * u[:, None, :])
    R[small] = _EYE3
    return R


def jacobian(
    stack: ChainStack, E: NDArray[np.float64], p: NDArray[np.float64], q: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Jacobian ``(B, 3 C, 6 + n)`` of the world fingertips with respect to the palm translation, a
    small palm rotation about world axes and the joints, from the :func:`local_transforms` ``E``
    (palm pose first) of hands with palm origins ``p`` ``(B, 3)`` and joints ``q`` ``(B, n)``."""
    k = frame_kinematics(stack, chain_frames(E)[1:], q, jacobian=True)
    assert k.jacobian is not None
    B, C = k.tips.shape[:2]
    J = np.empty((B, C, 3, 6 + stack.n))
    J[:, :, :, 0:3] = _EYE3
    J[:, :, :, 3:6] = ((k.tips - p[:, None, :]) @ _LEVI_CIVITA).reshape(B, C, 3, 3)  # -[r]x
    J[:, :, :, 6:] = k.jacobian
    return J.reshape(B, 3 * C, 6 + stack.n)


def norms(e: NDArray[np.float64]) -> NDArray[np.float64]:
    """Euclidean norm of each row of ``e`` ``(B, m)``."""
    return np.sqrt(np.einsum("ij,ij->i", e, e))


def errors(e: NDArray[np.float64]) -> NDArray[np.float64]:
    """Largest fingertip distance per row of the stacked fingertip errors ``e`` ``(B, 3 C)``."""
    d = e.reshape(len(e), e.shape[1] // 3, 3)
    return np.sqrt(np.einsum("ijk,ijk->ij", d, d).max(axis=1))


def solve(
    stack: ChainStack,
    targets: NDArray[np.float64],
    R: NDArray[np.float64],
    p: NDArray[np.float64],
    q: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """:func:`softgrasp.hand.placement._solve` in NumPy, all postures at once.

    Every posture iterates on its own (they advance in lockstep only to share NumPy calls): a
    limit-clamped WDLS step (:func:`limited_steps`) on the stacked fingertip errors, shortened by
    halving until the error norm decreases; it stops at an error <= REACH_TOL, when stalled, when no
    step moves it or no halving decreases the error, or after MAX_ITER iterations.
    """
    alpha = 0.5 ** np.arange(rules.MAX_HALVINGS)
    S, n = q.shape
    lower = np.concatenate([np.full(6, -np.inf)] + [c.lower for c in stack.chains])
    upper = np.concatenate([np.full(6, np.inf)] + [c.upper for c in stack.chains])
    winv = np.ones(6 + n)
    goal = targets.ravel()
    out = [R.copy(), p.copy(), np.empty((S, 6 + n)), np.empty(S)]
    x = np.concatenate([np.zeros((S, 6)), q], axis=1)  # palm step coordinates (0 at the current pose), q
    E = local_transforms(stack, q, R, p)
    e = goal - chain_product(E)[..., :3, 3].reshape(S, -1)
    err = errors(e)
    J = jacobian(stack, E, p, q)
    history = np.empty((S, rules.MAX_ITER + 1))  # history[s, i]: the error after i iterations
    history[:, 0] = err
    ids = np.arange(S)  # the postures still iterating (all at iteration i), rows of the state
    state = [R.copy(), p.copy(), x, err, e, J, history, ids]

    def retire(keep: NDArray[np.bool_]) -> None:
        """Write the postures not kept to ``out`` and drop them from the state."""
        done = state[7][~keep]
        for k in range(4):
            out[k][done] = state[k][~keep]
        state[:] = [a[keep] for a in state]

    for i in range(rules.MAX_ITER):
        R, p, x, err, e, J, history, ids = state
        go = err > rules.REACH_TOL
        if i >= rules.STALL_WINDOW:
            # stalled short of the targets: a limit or the workspace's edge
            go &= history[:, max(i - rules.STALL_WINDOW - 1, 0)] - err >= rules.STALL_FRACTION * err
        if not go.all():
            retire(go)
            R, p, x, err, e, J, history, ids = state
            if not ids.size:
                break
        norm = norms(e)
        dx = e * np.minimum(1.0, rules.MAX_STEP / norm)[:, None]  # at most MAX_STEP long
        dq = limited_steps(J, dx, x, lower, upper, winv, rules.DAMPING)
        # Line search: the first of 1, 1/2, 1/4, ... that decreases the error norm, several
        # halvings of every posture still searching at a time (about TRIAL_BUDGET trials at once).
        moved = np.zeros(len(ids), dtype=bool)
        todo = np.flatnonzero(dq.any(axis=1))
        k0 = 0
        E_moved = None
        while todo.size and k0 < rules.MAX_HALVINGS:
            K = min(rules.MAX_HALVINGS - k0, max(1, TRIAL_BUDGET // len(todo)))
            src = todo.repeat(K)
            step = (dq[todo][:, None, :] * alpha[k0 : k0 + K, None]).reshape(-1, 6 + n)
            k0 += K
            x_try = np.clip(x[src] + step, lower, upper)  # the palm part is the step itself
            p_try = p[src] + step[:, 0:3]
            E = local_transforms(stack, x_try[:, 6:], rotations(step[:, 3:6]) @ R[src], p_try)
            e_try = goal - chain_product(E)[..., :3, 3].reshape(len(src), -1)
            better = (norms(e_try) < norm[src]).reshape(-1, K)
            hit = better.any(axis=1)
            pick = np.flatnonzero(hit) * K + better.argmax(axis=1)[hit]
            dst = todo[hit]
            if E_moved is None:
                E_moved = np.empty((len(E), len(ids)) + E.shape[2:])
            E_moved[:, dst] = E[:, pick]
            p[dst], x[dst], e[dst] = p_try[pick], x_try[pick], e_try[pick]
            moved[dst] = True
            todo = todo[~hit]
        if E_moved is not None:
            x[:, :6] = 0.0
            R[moved] = E_moved[0, moved, 0, :3, :3]
            J[moved] = jacobian(stack, E_moved[:, moved], p[moved], x[moved, 6:])
            err[moved] = errors(e[moved])
        history[:, i + 1] = err
        if not moved.all():
            retire(moved)  # no step, or no shorter step decreased the error: stuck
            if not state[7].size:
                break
    retire(np.zeros(len(state[7]), dtype=bool))
    return out[0], out[1], out[2][:, 6:], out[3]


def limited_steps(
    J: NDArray[np.float64],
    dx: NDArray[np.float64],
    q: NDArray[np.float64],
    lower: NDArray[np.float64],
    upper: NDArray[np.float64],
    winv: NDArray[np.float64],
    damping: float,
) -> NDArray[np.float64]:
    """:func:`softgrasp.hand.wdls.limited_step` for a batch: ``J`` ``(B, m, n)``, ``dx`` ``(B, m)``,
    ``q`` ``(B, n)``; ``lower``, ``upper`` and the inverse joint weights ``winv`` ``(n,)``. Returns
    ``dq`` ``(B, n)``.

    A frozen joint gets the inverse weight 0 (the same as dropping its column: its step is exactly
    0 and it adds nothing to ``J W^-1 J^T``).
    """
    at_lower = q <= lower + LIMIT_EPS
    at_upper = q >= upper - LIMIT_EPS
    free = ~(at_lower & at_upper)  # a joint with lower == upper never moves
    outward = at_upper.astype(np.float64) - at_lower  # the sign of a step out of the range, or 0
    JT = J.transpose(0, 2, 1)
    damp = damping * damping * np.eye(J.shape[1])
    while True:  # every row again (a row's result does not depend on the others)
        JW = J * (winv * free)[:, None, :]  # J W^-1 with the frozen columns zeroed
        A = JW @ JT
        if damping > 0.0:
            y = np.linalg.solve(A + damp, dx[..., None])
        else:
            y = np.linalg.pinv(A) @ dx[..., None]
        dq = (JW.transpose(0, 2, 1) @ y)[..., 0]
        blocked = free & (dq * outward > 0.0)
        if not blocked.any():
            return dq
        free &= ~blocked
